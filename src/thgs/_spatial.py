"""A cache-friendly order of points: along a Z-order (Morton) curve through their bounding box.

Work that visits points by where they are (a tile's Gaussians, a KD-tree query's neighbours, a
pick's cells) reads far less memory when points near in space are near in the arrays. The order
is a pure function of the coordinates, so every use of it is deterministic.
"""

from __future__ import annotations

import numpy as np

__all__ = ["spatial_order"]

_BITS = 21
"""Quantization per axis of the Morton code (3 × 21 bits fit in 64)."""


def _spread_bits(values: np.ndarray) -> np.ndarray:
    """[N] uint64 < 2²¹ with bit i moved to bit 3i."""
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
    """[N] int64 indices of ``points`` [N, 3] in Z-order, quantized in 2²¹ steps on the cube
    around the finite points' bounding box (one step for all axes, so that cells are about as
    long as wide); ties (points in one cell) keep their index order. A point with a non-finite
    coordinate counts as the box's lower corner."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [N, 3], got {points.shape}")
    finite = np.isfinite(points).all(axis=1)
    kept = points[finite]
    if len(kept) == 0:
        return np.arange(len(points), dtype=np.int64)
    low = kept.min(axis=0)
    span = max(float((kept.max(axis=0) - low).max()), np.finfo(np.float64).tiny)
    steps = np.where(finite[:, None], (points - low) / span * (2**_BITS - 1), 0.0)
    quantized = np.clip(steps, 0, 2**_BITS - 1).astype(np.uint64)
    codes = np.zeros(len(points), dtype=np.uint64)
    for axis in range(3):
        codes |= _spread_bits(quantized[:, axis]) << np.uint64(axis)
    return np.argsort(codes, kind="stable").astype(np.int64)
