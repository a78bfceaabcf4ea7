"""Polygon rasterization with the project's pixel convention, and masks back to polygons.

Pixel (u, v) covers [u, u+1) × [v, v+1) and its centre is (u + 0.5, v + 0.5)
(docs/conventions.md). Polygon vertices are (x, y) = (column, row) in those continuous coordinates.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from thgs.errors import InputError

__all__ = ["mask_to_polygons", "rasterize_polygon"]


def rasterize_polygon(vertices: np.ndarray, height: int, width: int) -> np.ndarray:
    """[height, width] bool: pixels whose centre (u + 0.5, v + 0.5) lies inside the polygon.

    Args:
        vertices: [K, 2] (x, y) pixel coordinates of a closed polygon (the last vertex joins the
            first), any orientation, self-intersections by the even-odd rule.

    A pixel centre exactly on a left or top edge counts as inside, on a right or bottom edge as
    outside, so polygons that tile the plane never share a pixel and an axis-aligned rectangle
    with integer corners covers exactly its area in pixels. Fewer than 3 vertices cover nothing.

    Raises:
        InputError: ``vertices`` is not [K, 2] (3-D points, or a flat list of coordinates).
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] != 2:
        raise InputError(
            "rasterize_polygon",
            f"vertices must be [K, 2] (x, y) pixel coordinates, got shape {list(vertices.shape)}",
        )
    mask = np.zeros((height, width), dtype=bool)
    if len(vertices) < 3:
        return mask
    x0, y0 = vertices[:, 0], vertices[:, 1]
    x1, y1 = np.roll(x0, -1), np.roll(y0, -1)
    # only rows whose centre y has min(y) ≤ y < max(y) can cross an edge
    first = max(0, int(np.ceil(y0.min() - 0.5)))
    stop = min(height, max(first, int(np.ceil(y0.max() - 0.5))))
    rows = np.arange(first, stop)[:, None]
    y = rows + 0.5
    crossing = (y0 <= y) != (y1 <= y)  # [R, K], half-open in y: each crossing counted once
    row, edge = np.nonzero(crossing)
    t = (y[row, 0] - y0[edge]) / (y1[edge] - y0[edge])
    xs = x0[edge] + t * (x1[edge] - x0[edge])
    # a centre is inside when an odd number of crossings lie at or left of it: each crossing
    # toggles every column from the first centre at or right of it
    first_column = np.searchsorted(np.arange(width) + 0.5, xs, side="left")
    toggles = np.zeros((rows.shape[0], width + 1), dtype=np.int32)
    np.add.at(toggles, (row, first_column), 1)
    mask[first:stop] = (np.cumsum(toggles[:, :width], axis=1) % 2) == 1
    return mask


# Right turn of a unit step (dx, dy) in image coordinates (x right, y down): east → south → west →
# north → east.
_RIGHT_TURN = {(1, 0): (0, 1), (0, 1): (-1, 0), (-1, 0): (0, -1), (0, -1): (1, 0)}


def _boundary_edges(component: np.ndarray) -> np.ndarray:
    """[E, 4] int64 directed unit edges (x0, y0, x1, y1) between the component and the rest.

    Each pixel contributes its sides that face a pixel outside ``component``, directed clockwise
    on screen (top edge left→right, right edge downwards, ...), so the component is always on the
    right of an edge: outer boundaries run clockwise on screen, hole boundaries anticlockwise.
    """
    padded = np.pad(component, 1)
    inside = padded[1:-1, 1:-1]
    sides = (
        (inside & ~padded[:-2, 1:-1], (0, 0, 1, 0)),  # top: (u, v) → (u+1, v)
        (inside & ~padded[1:-1, 2:], (1, 0, 1, 1)),  # right: (u+1, v) → (u+1, v+1)
        (inside & ~padded[2:, 1:-1], (1, 1, 0, 1)),  # bottom: (u+1, v+1) → (u, v+1)
        (inside & ~padded[1:-1, :-2], (0, 1, 0, 0)),  # left: (u, v+1) → (u, v)
    )
    blocks = []
    for facing, (ax, ay, bx, by) in sides:
        rows, cols = np.nonzero(facing)
        blocks.append(np.stack([cols + ax, rows + ay, cols + bx, rows + by], axis=1))
    return np.concatenate(blocks).astype(np.int64)


def _trace_loops(edges: np.ndarray) -> list[np.ndarray]:
    """Link directed unit edges into closed loops of corner vertices.

    Returns:
        one [K, 2] int64 array of (x, y) corners per loop, collinear vertices removed. Loops come
        in order of their first vertex, which is the loop's top-most then left-most point (a
        corner): the outer boundary first, then the holes in raster order.

    Where two pixels of the component touch only diagonally, a vertex has two outgoing edges; the
    trace takes the right turn (towards the component), so it goes round the pixel it came along
    and diagonal neighbours stay apart (4-connectivity, as ``scipy.ndimage.label`` uses).
    """
    outgoing: dict[tuple[int, int], list[int]] = {}
    for index, (x0, y0, _, _) in enumerate(edges.tolist()):
        outgoing.setdefault((x0, y0), []).append(index)
    used = np.zeros(len(edges), dtype=bool)
    loops = []
    for start in np.lexsort((edges[:, 0], edges[:, 1])).tolist():
        if used[start]:
            continue
        vertices: list[tuple[int, int]] = []
        steps: list[tuple[int, int]] = []
        edge = start
        while True:
            used[edge] = True
            x0, y0, x1, y1 = edges[edge].tolist()
            vertices.append((x0, y0))
            steps.append((x1 - x0, y1 - y0))
            candidates = [e for e in outgoing[(x1, y1)] if not used[e]]
            if not candidates:  # back at the start: its only outgoing edge is used
                break
            edge = candidates[0]
            if len(candidates) == 2:
                turn = list(_RIGHT_TURN[steps[-1]])
                edge = next(
                    (e for e in candidates if (edges[e, 2:] - edges[e, :2]).tolist() == turn),
                    candidates[0],
                )
        corners = [v for i, v in enumerate(vertices) if steps[i] != steps[i - 1]]
        loops.append(np.array(corners, dtype=np.int64))
    return loops


def _join_loops(loops: list[np.ndarray]) -> np.ndarray:
    """One vertex sequence for an outer loop and its holes, joined by two-way bridges.

    Hole i is joined to loop i − 1: from the vertex p of loop i − 1 nearest (L1, first on ties) to
    the hole's first vertex q, the path goes p → (q.x, p.y) → q, round the hole, and back the same
    way. The bridge is axis-aligned with integer vertices, so under :func:`rasterize_polygon`'s
    even-odd, pixel-centre rule its horizontal part crosses no scanline and its vertical part
    crosses each scanline twice at exactly the same x: it changes no pixel and no area.
    """
    path = loops[-1].tolist()
    for host_array in reversed(loops[:-1]):
        host = host_array.tolist()
        q = path[0]
        distances = np.abs(host_array - np.asarray(q)).sum(axis=1)
        j = int(np.argmin(distances))
        p = host[j]
        bridge = [] if p[0] == q[0] or p[1] == q[1] else [[q[0], p[1]]]
        path = host[: j + 1] + bridge + path + [q] + bridge + host[j:]
    joined = np.asarray(path, dtype=np.float64)
    keep = np.any(joined != np.roll(joined, 1, axis=0), axis=1)  # drop zero-length edges
    return joined[keep]


def mask_to_polygons(mask: np.ndarray) -> list[np.ndarray]:
    """One polygon per 4-connected component of ``mask``, exact under :func:`rasterize_polygon`.

    Args:
        mask: [H, W] bool.

    Returns:
        one [K, 2] float64 array of (x, y) pixel-corner coordinates (whole numbers) per component,
        in ``scipy.ndimage.label`` order (the component's first pixel in raster order). For each
        component, ``rasterize_polygon(polygon, H, W)`` is exactly that component, holes included,
        and the polygon's shoelace area is ±its pixel count (clockwise on screen, positive with
        ``½ Σ x_i·y_{i+1} − x_{i+1}·y_i`` in image coordinates). An empty mask gives ``[]``.

    The polygon follows the pixel edges between the component and the rest (no smoothing), with
    collinear vertices removed, starting at the component's top-left corner. A component with
    holes is still one polygon: LERF-style label files (ISAT's layout, as in LangSplat's release)
    hold a single ``segmentation`` polygon per object, so each hole's boundary is joined to the
    previous boundary by a zero-width bridge, traversed once there and once back. The coincident
    opposite segments cancel under the even-odd rule, so the fill is exact; tools that fill with
    the non-zero rule also fill holes correctly since hole boundaries run the opposite way. Such a
    polygon touches itself along the bridges, so it is not a *simple* polygon, and a filler that
    also paints the outline (OpenCV's ``fillPoly``, as LangSplat's evaluation uses) draws the
    bridges as one-pixel lines.

    Raises:
        InputError: ``mask`` is not a 2-D bool array.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2 or mask.dtype != np.bool_:
        raise InputError(
            "mask_to_polygons", f"expected an [H, W] bool mask, got {mask.dtype} {list(mask.shape)}"
        )
    if not mask.any():
        return []
    labels, _ = ndimage.label(mask)
    polygons = []
    for index, window in enumerate(ndimage.find_objects(labels)):
        if window is None:
            continue
        component = labels[window] == index + 1
        loops = _trace_loops(_boundary_edges(component))
        polygon = _join_loops(loops)
        polygon += np.array([window[1].start, window[0].start], dtype=np.float64)
        polygons.append(polygon)
    return polygons
