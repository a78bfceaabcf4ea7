"""The ``thgs`` command line: a thin layer over the library, and the only code that prints."""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
from pathlib import Path
from typing import Annotated

import tyro
from rich.console import Console
from rich.logging import RichHandler
from rich.table import Table

from thgs.errors import ThgsError
from thgs.scene import SceneSummary, load_scene, summarize

__all__ = ["entrypoint", "info"]

_stdout = Console()
_stderr = Console(stderr=True)


def _setup_logging(verbose: bool) -> None:
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(message)s",
        handlers=[RichHandler(console=_stderr, show_path=False, show_time=False)],
        force=True,
    )


def _span(low: float, high: float, digits: int = 3) -> str:
    return f"{low:.{digits}g}" if low == high else f"{low:.{digits}g}–{high:.{digits}g}"


def _render_summary(path: Path, found: tuple[str, ...], summary: SceneSummary) -> Table:
    table = Table(title=f"thgs info {path}", show_header=False, title_justify="left")
    table.add_column(style="bold")
    table.add_column()
    details = [f"{summary.kind.upper()}", f"SH degree {summary.sh_degree}"]
    if summary.has_normals:
        details.append("normals stored")
    if summary.extra_properties:
        details.append(f"extra properties {', '.join(summary.extra_properties)}")
    table.add_row("Gaussians", f"{summary.count:,} ({', '.join(details)})")

    def box(low: tuple[float, ...], high: tuple[float, ...]) -> str:
        return "  ".join(f"{axis} [{lo:.3f}, {hi:.3f}]" for axis, lo, hi in zip("xyz", low, high))

    table.add_row("bounding box", box(summary.bbox_min, summary.bbox_max))
    table.add_row("1–99th pct box", box(*summary.bbox_1_99))
    q = summary.opacity_quantiles
    table.add_row(
        "opacity",
        f"mean {summary.opacity_mean:.3f}, median {q[2]:.3f}, quartiles {q[1]:.3f}–{q[3]:.3f}, "
        f"range {q[0]:.3f}–{q[4]:.3f}; {100 * summary.low_opacity_share:.1f} % below 0.1",
    )
    table.add_row("largest scale", f"median {summary.scale_median:.4g} scene units")
    cameras = summary.cameras
    if cameras is None:
        table.add_row(
            "cameras", "none (pass --source with COLMAP, transforms.json or cameras.json)"
        )
    else:
        table.add_row(
            "cameras",
            f"{cameras.count} from {cameras.source}, {_span(*cameras.width_range, 6)}×"
            f"{_span(*cameras.height_range, 6)} px, focal {_span(*cameras.focal_range, 5)} px",
        )
    for line in found:
        table.add_row("found", line)
    return table


def info(
    path: Path,
    /,
    *,
    source: Path | None = None,
    iteration: int | None = None,
    images: str | None = None,
    scale: float = 1.0,
    undo_applied_transform: bool = False,
    json_output: Annotated[bool, tyro.conf.arg(name="json")] = False,
    verbose: bool = False,
) -> None:
    """Describe a Gaussian scene: count, kind, SH degree, bounding box, opacities, cameras.

    Args:
        path: a trained 3DGS/2DGS model folder (point_cloud/iteration_*/point_cloud.ply,
            cameras.json) or a .ply file.
        source: cameras from here instead of the model's cameras.json: a training data folder
            (COLMAP sparse/0 + images/, transforms.json) or a camera file.
        iteration: which iteration_* of a model folder (default: the newest).
        images: image folder name inside the source, e.g. images_4 (default: images, if present).
        scale: image size / camera-file size, e.g. 0.25 for images_4. Never guessed.
        undo_applied_transform: map nerfstudio transforms.json poses back to the COLMAP frame.
        json_output: print the summary as JSON instead of a table.
        verbose: log what is read.
    """
    _setup_logging(verbose)
    scene = load_scene(
        path,
        source=source,
        iteration=iteration,
        images=images,
        scale=scale,
        undo_applied_transform=undo_applied_transform,
    )
    summary = summarize(scene)
    if json_output:
        document = {"path": str(path), "found": list(scene.found), **dataclasses.asdict(summary)}
        _stdout.print_json(json.dumps(document))
    else:
        _stdout.print(_render_summary(path, scene.found, summary))


def entrypoint(argv: list[str] | None = None) -> None:
    """Run the CLI; bad input ends with one line on stderr and exit status 2."""
    try:
        tyro.extras.subcommand_cli_from_dict(
            {"info": info},
            prog="thgs",
            description="thgs: open-vocabulary, hierarchical understanding of Gaussian scenes.",
            args=argv,
        )
    except ThgsError as exc:
        _stderr.print(f"[bold red]error:[/] {exc}", highlight=False)
        sys.exit(2)
