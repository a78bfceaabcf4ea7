"""Synthetic datasets generated once and kept in a cache folder, for the demo, ``thgs bench`` and
the benchmarks: :func:`synthetic_dataset` writes a preset's scene with oracle guidance the first
time it is asked for and reuses it afterwards; :func:`open_synthetic_dataset` loads one.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from pathlib import Path

from thgs.errors import InputError
from thgs.guidance import ViewGuidance, load_guidance, read_embedding_space
from thgs.scene import Scene, load_scene
from thgs.synthetic.dataset import DatasetConfig, is_current_dataset, write_dataset
from thgs.synthetic.oracle import OracleConfig, stand_in_spec
from thgs.synthetic.scene import generate_scene, preset
from thgs.text import TextEncoder

__all__ = ["default_cache", "open_synthetic_dataset", "synthetic_dataset"]

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]


def default_cache() -> Path:
    """``$THGS_CACHE``, else ``$XDG_CACHE_HOME/thgs``, else ``~/.cache/thgs``."""
    if os.environ.get("THGS_CACHE"):
        return Path(os.environ["THGS_CACHE"])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "thgs"


def synthetic_dataset(
    cache: Path,
    name: str,
    seed: int,
    gaussians: int | None,
    views: int | None,
    encoder: TextEncoder,
    progress: Progress | None = None,
    *,
    kind: str = "2dgs",
    severity: float = 0.5,
    stand_in: str = "name-perfect",
) -> tuple[Path, bool]:
    """The synthetic dataset of ``name`` (a preset) and ``seed`` in ``cache``, written there
    with oracle guidance in ``encoder``'s space if it is not yet: ``(folder, generated now)``.

    ``gaussians`` and ``views`` override the preset's size; ``kind`` (2dgs, 3dgs), the oracle's
    mask ``severity`` and its CLIP stand-in (a :func:`thgs.synthetic.stand_in` spec, e.g.
    ``"clip-like"``) choose the scenario. The folder name says every value that is not the
    default.

    Raises:
        InputError: a bad stand-in spec (before anything is written).
    """
    overrides: dict[str, object] = {"seed": seed}
    tag = f"{name}-seed{seed}"
    if gaussians is not None:
        overrides["gaussians"] = gaussians
        tag += f"-{gaussians}g"
    if views is not None:
        overrides["views"] = views
        tag += f"-{views}v"
    if kind != "2dgs":
        overrides["kind"] = kind
        tag += f"-{kind}"
    if severity != 0.5:
        tag += f"-severity{severity:g}"
    oracle = OracleConfig(severity=severity, seed=seed).with_stand_in(stand_in)
    spec = stand_in_spec(oracle)
    if spec != "name-perfect":
        tag += "-" + spec.replace(":", "-").replace(",", "-").replace("=", "")
    folder = cache / tag
    if is_current_dataset(folder):
        logger.info("reusing the cached dataset %s", folder)
        return folder, False
    config = preset(name, **overrides)
    scene = generate_scene(config)
    write_dataset(
        folder,
        scene,
        encoder,
        oracle=oracle,
        config=DatasetConfig(),
        overwrite=folder.exists(),
        progress=None if progress is None else lambda d, t: progress("generate", d, t),
    )
    return folder, True


def open_synthetic_dataset(folder: Path, encoder: TextEncoder) -> tuple[Scene, list[ViewGuidance]]:
    """A synthetic dataset's scene and guidance, checking its features are in ``encoder``'s
    space.

    Raises:
        InputError: the guidance records no embedding space, or another one.
    """
    scene = load_scene(folder)
    features_dir = folder / "language_features"
    recorded = read_embedding_space(features_dir)
    if recorded is None:
        raise InputError(features_dir, "records no embedding space (embedding.json)")
    if recorded[0] != encoder.space:
        raise InputError(
            features_dir, f"features are in {recorded[0]!r}, expected {encoder.space!r}"
        )
    return scene, load_guidance(features_dir, scene.cameras)
