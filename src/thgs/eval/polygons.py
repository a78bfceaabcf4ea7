"""Polygon rasterization with the project's pixel convention."""

from __future__ import annotations

import numpy as np

__all__ = ["rasterize_polygon"]


def rasterize_polygon(vertices: np.ndarray, height: int, width: int) -> np.ndarray:
    """[height, width] bool: pixels whose centre (u + 0.5, v + 0.5) lies inside the polygon.

    Args:
        vertices: [K, 2] (x, y) pixel coordinates of a closed polygon (the last vertex joins the
            first), any orientation, self-intersections by the even-odd rule.

    A pixel centre exactly on a left or top edge counts as inside, on a right or bottom edge as
    outside, so polygons that tile the plane never share a pixel and an axis-aligned rectangle
    with integer corners covers exactly its area in pixels.
    """
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 2)
    mask = np.zeros((height, width), dtype=bool)
    if len(vertices) < 3:
        return mask
    x0, y0 = vertices[:, 0], vertices[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    centres_x = np.arange(width) + 0.5
    for v in range(height):
        y = v + 0.5
        crossing = (y0 <= y) != (y1 <= y)  # half-open in y: each crossing counted once
        if not crossing.any():
            continue
        t = (y - y0[crossing]) / (y1[crossing] - y0[crossing])
        xs = np.sort(x0[crossing] + t * (x1[crossing] - x0[crossing]))
        inside = (np.searchsorted(xs, centres_x, side="right") % 2) == 1
        mask[v] = inside
    return mask
