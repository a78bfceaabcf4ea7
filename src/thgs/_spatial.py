"""A cache-friendly order of points: along a Z-order (Morton) curve through their bounding box.

Work that visits points by where they are (a tile's Gaussians, a KD-tree query's neighbours)
reads far less memory when points near in space are near in the arrays. The order is a pure
function of the coordinates, so every use of it is deterministic.
"""

from __future__ import annotations

import numpy as np

__all__ = ["spatial_order"]

_BITS = 21
"""Bits per axis: 3 × 21 fit one uint64 code."""


def _spread(values: np.ndarray) -> np.ndarray:
    """The 21 low bits of each uint64 spread to every third bit (bit i → bit 3i)."""
    v = values & np.uint64(0x1FFFFF)
    for shift, mask in (
        (32, 0x1F00000000FFFF),
        (16, 0x1F0000FF0000FF),
        (8, 0x100F00F00F00F00F),
        (4, 0x10C30C30C30C30C3),
        (2, 0x1249249249249249),
    ):
        v = (v | (v << np.uint64(shift))) & np.uint64(mask)
    return v


def spatial_order(points: np.ndarray) -> np.ndarray:
    """[N] int64 indices of ``points`` [N, 3] in Z-order over their bounding box, each axis
    quantized to 2²¹ steps; ties (points in one cell) keep their index order. A point with a
    non-finite coordinate counts as the lower corner of the finite points' box."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [N, 3], got {points.shape}")
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    finite = np.isfinite(points).all(axis=1)
    kept = points[finite]
    low = kept.min(axis=0) if len(kept) else np.zeros(3)
    high = kept.max(axis=0) if len(kept) else np.zeros(3)
    steps = float((1 << _BITS) - 1)
    extent = np.where(high > low, high - low, 1.0)
    cells = np.where(finite[:, None], (points - low) * (steps / extent), 0.0)
    cells = np.clip(cells, 0.0, steps).astype(np.uint64)
    codes = _spread(cells[:, 0]) | _spread(cells[:, 1]) << np.uint64(1)
    codes |= _spread(cells[:, 2]) << np.uint64(2)
    return np.argsort(codes, kind="stable").astype(np.int64)
