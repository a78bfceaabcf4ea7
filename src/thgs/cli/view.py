"""``thgs view``: the browser viewer."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated, Literal

import tyro

from thgs.choices import Device
from thgs.cli._console import setup_logging, stdout
from thgs.errors import settings_as_flags

__all__ = ["view"]


def view(
    field: Annotated[Path, tyro.conf.arg(metavar="FIELD")],
    /,
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    scene: Path | None = None,
    level: Literal[1, 2, 3] = 3,
    mode: Literal["auto", "paper", "level", "threshold"] = "auto",
    threshold: float | None = None,
    text_model: Path | None = None,
    device: Device = "auto",
    token: bool = True,
    export_root: Path = Path("thgs-export"),
    verbose: bool = False,
) -> None:
    """Explore a semantic field in the browser: text queries, click-to-pick, climbing the
    hierarchy, 2D masks, exports.

    Serves a viser app until Ctrl-C. Problems (a field that does not match its scene, a port in
    use, an export folder that cannot be written) are logged here and shown in the viewer; the
    server keeps running.

    Args:
        field: the field file (thgs build).
        host: the address to listen on; the default serves this machine only. 0.0.0.0 serves
            every network interface: anyone who can reach the port can see the scene and write
            exports where this process may write.
        port: the port; the next free one if it is taken.
        scene: the scene the field was built on, if not where the field says.
        level: the level shown first: 1 sub-parts, 2 parts, 3 objects.
        mode: how a query selects, as thgs query --mode: auto (every region named like the
            query, at any level, or nothing), paper (top 3 of parts and objects), level (the
            best region of the level shown) or threshold (every region of the level above
            --threshold).
        threshold: relevancy for the threshold mode (default: the embedding space's).
        text_model: the text model's local folder, instead of the one the field records (or,
            for a field that records none, the Hugging Face cache).
        device: where to render: auto (a CUDA GPU if torch sees one, else MPS, else the CPU),
            cpu, cuda or mps (docs/rendering.md).
        token: require the secret token in the printed URL (as Jupyter does); --no-token
            lets anyone who can reach the port in (requests must still name this server in
            their Host and Origin headers).
        export_root: the folder exports are confined to; the viewer's "Folder" names a folder
            inside it.
        verbose: log what is loaded and every action.
    """
    from thgs.viewer.app import start_viewer, viewer_url
    from thgs.viewer.state import ViewerConfig

    setup_logging(verbose)
    with settings_as_flags("level", "mode", "threshold"):
        config = ViewerConfig(level=level, mode=mode, threshold=threshold).check()
    app = start_viewer(
        field,
        scene=scene,
        host=host,
        port=port,
        text_model=text_model,
        config=config,
        device=device,
        token=token,
        export_root=export_root,
    )
    try:
        count = f"{len(app.state):,} Gaussians" if app.state is not None else "no field open"
        stdout.print(
            f"thgs view: {viewer_url(app, host)} ({count}); Ctrl-C to stop", soft_wrap=True
        )
        while True:
            time.sleep(1.0)
    except KeyboardInterrupt:
        pass
    finally:
        app.stop()
