"""Taking results elsewhere: PLY subsets, region-coloured scenes, labels, masks and JSON.

Every writer is atomic (a temporary file in the target folder, then a rename), so a failed or
interrupted export never leaves a half-written file behind.

- :func:`write_selection_ply` — the selected Gaussians in the input's own PLY layout (same
  properties, normals and extra properties included), so any splat viewer that opened the scene
  opens the selection.
- :func:`write_region_ply` — the whole scene with every Gaussian's colour replaced by its
  region's colour at one level (DC term set, higher SH bands zeroed, so the colour does not
  change with the view).
- :func:`write_labels` — per-Gaussian region ids: ``.npy`` (int32 [N] or [N, L]) or ``.json``.
- :func:`write_selection` — one selection as a set: its PLY, its Gaussians' region ids and
  indices, and a JSON description (what the viewer's export button writes).
- :func:`write_mask_png` — a 2D mask as an 8-bit PNG (255 = selected); :func:`write_map_png`
  values in [0, 1] (a relevancy map, an RGB picture) as an 8-bit PNG.
- :func:`write_json` — any JSON value, UTF-8, indented.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import re
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from thgs._atomic import atomic_output
from thgs.errors import InputError
from thgs.field import SemanticField
from thgs.hierarchy.levels import LEVEL_NAMES
from thgs.scene import SH_C0, Gaussians, write_ply

__all__ = [
    "region_colors",
    "slug",
    "write_json",
    "write_labels",
    "write_map_png",
    "write_mask_png",
    "write_region_ply",
    "write_selection",
    "write_selection_ply",
]


def _checked_selection(selected: np.ndarray, n: int) -> np.ndarray:
    selected = np.asarray(selected)
    if selected.shape != (n,) or selected.dtype != np.bool_:
        raise InputError(
            "selected",
            f"must be an [N] bool mask with N = {n}, got {selected.dtype} {list(selected.shape)}",
        )
    return selected


def write_selection_ply(
    path: str | os.PathLike[str], gaussians: Gaussians, selected: np.ndarray
) -> int:
    """Write the selected Gaussians, in their original order and layout, as a PLY.

    Args:
        path: the PLY to write.
        gaussians: the scene's N Gaussians (as read by :func:`thgs.scene.read_ply`).
        selected: [N] bool.

    Returns:
        the number of Gaussians written.

    Raises:
        InputError: a mask of the wrong shape or an empty selection (a PLY without vertices
            opens in no viewer).
    """
    selected = _checked_selection(selected, len(gaussians))
    if not selected.any():
        raise InputError(Path(path), "nothing is selected, so there is nothing to write")
    write_ply(path, gaussians.select(np.flatnonzero(selected)))
    return int(selected.sum())


def region_colors(labels: np.ndarray, seed: int = 0) -> np.ndarray:
    """[N, 3] float64 RGB in [0.15, 1]: one random colour per region id, drawn from ``seed``.

    The same labels and seed always give the same colours; a region's colour depends only on its
    id, not on the other regions.
    """
    labels = np.asarray(labels)
    if labels.ndim != 1 or (labels.size and labels.min() < 0):
        raise InputError("labels", "must be [N] non-negative region ids")
    count = int(labels.max()) + 1 if labels.size else 0
    palette = np.random.default_rng(seed).uniform(0.15, 1.0, size=(count, 3))
    return palette[labels]


def write_region_ply(
    path: str | os.PathLike[str],
    gaussians: Gaussians,
    field: SemanticField,
    level: int,
    *,
    seed: int = 0,
) -> None:
    """Write the whole scene coloured by region at ``level`` (0..3) as a PLY.

    Geometry, opacity and extra properties are unchanged; the colour of Gaussian i becomes
    :func:`region_colors` of its region (SH degree kept, higher bands zero).

    Raises:
        InputError: a field of another size or an invalid level.
    """
    if len(field) != len(gaussians):
        raise InputError(
            Path(path), f"the field has {len(field)} Gaussians, the scene {len(gaussians)}"
        )
    if level not in (0, 1, 2, 3):
        raise InputError("level", f"must be in 0..3, got {level}")
    colors = torch.from_numpy(region_colors(field.labels[:, level], seed))
    sh = torch.zeros_like(gaussians.sh)
    sh[:, 0] = ((colors - 0.5) / SH_C0).to(device=sh.device, dtype=sh.dtype)
    write_ply(path, replace(gaussians, sh=sh))


def write_labels(
    path: str | os.PathLike[str], field: SemanticField, levels: tuple[int, ...] = (0, 1, 2, 3)
) -> None:
    """Write per-Gaussian region ids at ``levels``.

    ``.npy``: int32 [N] for one level, [N, L] for several (columns in ``levels`` order).
    ``.json``: ``{"levels": {"object": [...], ...}, "gaussians": N, "space": ...}``, one list of
    N ids per level, keyed by the level's name (:data:`thgs.hierarchy.LEVEL_NAMES`).

    Raises:
        InputError: another extension or an invalid level.
    """
    path = Path(path)
    if not levels or any(k not in (0, 1, 2, 3) for k in levels):
        raise InputError("levels", f"must be among 0..3, got {levels}")
    labels = field.labels[:, list(levels)]
    if path.suffix == ".npy":
        _write_npy(path, labels[:, 0] if len(levels) == 1 else labels)
    elif path.suffix == ".json":
        write_json(
            path,
            {
                "gaussians": len(field),
                "space": field.space,
                "levels": {LEVEL_NAMES[k]: labels[:, j].tolist() for j, k in enumerate(levels)},
            },
            indent=None,
        )
    else:
        raise InputError(path, "labels are written as .npy or .json")


def _write_npy(path: Path, array: np.ndarray) -> None:
    """Write ``array`` as a C-ordered ``.npy``, atomically."""
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array))
    with atomic_output(path) as handle:
        handle.write(buffer.getvalue())


def write_mask_png(path: str | os.PathLike[str], mask: np.ndarray) -> None:
    """Write an [H, W] bool mask as an 8-bit grayscale PNG (0 / 255)."""
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != np.bool_:
        raise InputError(Path(path), f"a mask must be [H, W] bool, got {mask.dtype} {mask.shape}")
    write_map_png(path, mask.astype(np.float64))


def write_map_png(path: str | os.PathLike[str], values: np.ndarray) -> None:
    """Write values in [0, 1] as an 8-bit PNG (round(255 · v), clipped): [H, W] grayscale (a
    relevancy map) or [H, W, 3] RGB (a picture)."""
    from PIL import Image

    values = np.asarray(values, dtype=np.float64)
    if values.ndim not in (2, 3) or values.shape[2:] not in ((), (3,)):
        raise InputError(Path(path), f"an image must be [H, W] or [H, W, 3], got {values.shape}")
    if not np.isfinite(values).all():
        raise InputError(Path(path), "an image must have finite values")
    pixels = np.floor(np.clip(values, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    with atomic_output(path) as handle:
        Image.fromarray(pixels).save(handle, format="PNG")


def slug(text: str) -> str:
    """A file-name-safe form of a query: lower case, runs of other characters as ``-``; at most
    80 characters (a longer one keeps its first 71 and the first 8 hex digits of the text's
    SHA-256, so a 10,000-character query still names a file)."""
    name = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "query"
    if len(name) <= 80:
        return name
    return f"{name[:71].rstrip('-')}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"


def write_json(path: str | os.PathLike[str], value: Any, *, indent: int | None = 2) -> None:
    """Write ``value`` as UTF-8 JSON (NaN and infinity refused)."""
    try:
        text = json.dumps(value, indent=indent, ensure_ascii=False, allow_nan=False)
    except (TypeError, ValueError) as error:
        raise InputError(Path(path), f"cannot be written as JSON: {error}") from error
    with atomic_output(path, "w") as handle:
        handle.write(text + "\n")


def write_selection(
    folder: str | os.PathLike[str],
    name: str,
    gaussians: Gaussians,
    field: SemanticField,
    selected: np.ndarray,
    description: dict[str, Any] | None = None,
) -> list[Path]:
    """Write one selection to ``folder`` as four files named after ``name``.

    - ``<name>.ply``: the selected Gaussians in the input's PLY layout, as
      :func:`write_selection_ply` writes them;
    - ``<name>-labels.npy``: int32 [M, 4], the region ids of those Gaussians at levels 0..3, row
      i for the PLY's vertex i;
    - ``<name>-indices.npy``: int64 [M], their indices in the scene;
    - ``<name>.json``: ``description`` plus the Gaussian count, the levels' names and the files,
      written last.

    Each file is written atomically; if one fails, the ones this call already wrote are removed,
    so the folder holds either the whole set or none of it.

    Returns:
        the four paths, in the order above.

    Raises:
        InputError: a field of another size, an empty or malformed selection, or a folder that
            cannot be created or written (the message names it and the system's reason).
    """
    folder = Path(folder)
    if len(field) != len(gaussians):
        raise InputError(
            folder, f"the field has {len(field)} Gaussians, the scene {len(gaussians)}"
        )
    selected = _checked_selection(selected, len(gaussians))
    if not selected.any():
        raise InputError(folder, "nothing is selected, so there is nothing to write")
    index = np.flatnonzero(selected)
    paths = [
        folder / f"{name}.ply",
        folder / f"{name}-labels.npy",
        folder / f"{name}-indices.npy",
        folder / f"{name}.json",
    ]
    summary = {
        **(description or {}),
        "gaussians": int(index.size),
        "levels": list(LEVEL_NAMES),
        "files": [path.name for path in paths[:3]],
    }
    written: list[Path] = []
    try:
        write_ply(paths[0], gaussians.select(index))
        written.append(paths[0])
        for path, array in zip(paths[1:3], (field.labels[index].astype(np.int32), index)):
            _write_npy(path, array)
            written.append(path)
        write_json(paths[3], summary)
    except BaseException as error:
        for path in written:
            path.unlink(missing_ok=True)
        if isinstance(error, OSError):
            reason = error.strerror or str(error)
            raise InputError(folder, f"cannot write the selection there: {reason}") from error
        raise
    return paths
