"""numba backend: the CPU rasterizer, float64, compiled loops.

Per view:

1. **Projection**: one compiled pass over the Gaussians with the formulas of
   :func:`thgs.render.projection.project_torch` (tested against it). The kernels hold the
   Gaussians in Z-order of their centres (:func:`thgs._spatial.spatial_order`, computed once
   per Gaussians), so a tile's Gaussians lie near each other in memory; what they return is in
   the Gaussians' own order, the same bytes as in any other order.
2. **Binning**: the Gaussians that can contribute, sorted by depth (stable, so ties go by their
   own index), are counted into the tiles their α ≥ alpha_min box overlaps; every tile's list is
   then in depth order without sorting pairs (a counting sort, O(pairs)).
3. **Per tile**: the tile's Gaussians are gathered into contiguous arrays (box, α centre,
   parameters, opacity), and for each pixel row the Gaussians whose box spans that row are listed;
   a pixel walks its row's list front to back: skip α < alpha_min, stop before the Gaussian that
   would bring the transmittance to ≤ transmittance_min. Work and memory are bounded by
   (tile, Gaussian) pairs, never by (pixel, Gaussian) pairs.

``render`` deals the tiles round-robin to threads (each pixel is written by one tile).
``splat_back`` and ``label_weights`` run one view serially, summing per tile before adding into
the per-Gaussian results, so they are deterministic and independent of the thread count;
:mod:`thgs.lift` runs several views at once instead, one per thread (the kernels release the
GIL).
"""

from __future__ import annotations

import math
import threading
import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from thgs._spatial import spatial_order
from thgs.render.config import RasterConfig
from thgs.render.outputs import LabelWeights, RenderOutput, SplatBackOutput
from thgs.render.projection import Projection
from thgs.scene import Cameras, Gaussians

__all__ = ["NumbaBackend"]

_KIND = {"3dgs": 0, "2dgs": 1}

_REACH_MARGIN = 1e-9
"""σ beyond a Gaussian's reach by this much gives α < alpha_min whatever the rounding."""

_LOCAL_SLOTS_MAX = 1 << 22
"""Largest per-tile (Gaussian, level, label) accumulator of ``label_weights``; a tile with more
(very many distinct labels under many Gaussians) adds each pixel's weights directly instead."""


@numba.njit(nogil=True, cache=True)
def _bounds(center, half, size):
    """Inclusive pixel index range whose centres lie within ``center ± half``, widened by one."""
    low = math.ceil(center - half - 0.5) - 1.0
    high = math.floor(center + half - 0.5) + 1.0
    if math.isnan(low) or low == -math.inf:
        low = 0.0
    elif low == math.inf:
        low = float(size)
    if math.isnan(high) or high == -math.inf:
        high = -1.0
    elif high == math.inf:
        high = float(size - 1)
    return int(min(max(low, 0.0), float(size))), int(min(max(high, -1.0), float(size - 1)))


@numba.njit(nogil=True, cache=True)
def _prepare_kernel(quats, log_scales, logits):  # pragma: no cover - compiled
    """What the projection needs of each Gaussian whatever the view: its rotation (row-major,
    the quaternion normalized), its scales and its opacity, activated."""
    n = quats.shape[0]
    rotations = np.empty((n, 9))
    scales = np.empty(log_scales.shape)
    opacities = np.empty(n)
    for i in range(n):
        qw, qx, qy, qz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        norm = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
        rotations[i, 0] = 1 - 2 * (qy * qy + qz * qz)
        rotations[i, 1] = 2 * (qx * qy - qw * qz)
        rotations[i, 2] = 2 * (qx * qz + qw * qy)
        rotations[i, 3] = 2 * (qx * qy + qw * qz)
        rotations[i, 4] = 1 - 2 * (qx * qx + qz * qz)
        rotations[i, 5] = 2 * (qy * qz - qw * qx)
        rotations[i, 6] = 2 * (qx * qz - qw * qy)
        rotations[i, 7] = 2 * (qy * qz + qw * qx)
        rotations[i, 8] = 1 - 2 * (qx * qx + qy * qy)
        for k in range(log_scales.shape[1]):
            scales[i, k] = math.exp(log_scales[i, k])
        opacities[i] = 1.0 / (1.0 + math.exp(-logits[i]))
    return rotations, scales, opacities


@numba.njit(nogil=True, cache=True)
def _project_kernel(
    means, rotations, scales, opacities, viewmat, K, width, height, kind, settings
):  # pragma: no cover - compiled
    """The projection of :func:`thgs.render.projection.project_torch` for one view, with the
    Gaussians' prepared values (:func:`_prepare_kernel`); also each Gaussian's reach, the σ at
    which α falls to alpha_min: ``ln(o / alpha_min)``."""
    near, far, alpha_min, eps2d, filter_inv_square = settings
    n = means.shape[0]
    depths = np.empty(n)
    centers = np.empty((n, 2))
    alpha_centers = np.empty((n, 2))
    params = np.zeros((n, 9))
    reaches = np.empty(n)
    valid = np.zeros(n, dtype=np.bool_)
    bounds = np.empty((n, 4), dtype=np.int64)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    axes = np.empty((3, 3))
    h = np.empty((3, 3))
    for i in range(n):
        m0, m1, m2 = means[i, 0], means[i, 1], means[i, 2]
        x = viewmat[0, 0] * m0 + viewmat[0, 1] * m1 + viewmat[0, 2] * m2 + viewmat[0, 3]
        y = viewmat[1, 0] * m0 + viewmat[1, 1] * m1 + viewmat[1, 2] * m2 + viewmat[1, 3]
        z = viewmat[2, 0] * m0 + viewmat[2, 1] * m1 + viewmat[2, 2] * m2 + viewmat[2, 3]
        depths[i] = z
        opacity = opacities[i]
        in_range = near < z < far
        zs = z if in_range else 1.0
        centers[i, 0] = fx * x / zs + cx
        centers[i, 1] = fy * y / zs + cy
        bounds[i, 0], bounds[i, 1], bounds[i, 2], bounds[i, 3] = 0, -1, 0, -1
        alpha_centers[i, 0], alpha_centers[i, 1] = centers[i, 0], centers[i, 1]
        log_ratio = math.log(opacity / alpha_min) if opacity > 0 else -math.inf
        reaches[i] = log_ratio
        if not in_range or log_ratio < 0:
            continue
        k_squared = max(2.0 * log_ratio, 1e-12)
        for r in range(3):
            for c in range(3):
                axes[r, c] = (
                    viewmat[r, 0] * rotations[i, c]
                    + viewmat[r, 1] * rotations[i, 3 + c]
                    + viewmat[r, 2] * rotations[i, 6 + c]
                )
        if kind == 0:
            s0, s1, s2 = scales[i, 0], scales[i, 1], scales[i, 2]
            lim_x0 = (width - cx) / fx + 0.3 * (0.5 * width / fx)
            lim_x1 = cx / fx + 0.3 * (0.5 * width / fx)
            lim_y0 = (height - cy) / fy + 0.3 * (0.5 * height / fy)
            lim_y1 = cy / fy + 0.3 * (0.5 * height / fy)
            tx = z * min(max(x / z, -lim_x1), lim_x0)
            ty = z * min(max(y / z, -lim_y1), lim_y0)
            j00, j02 = fx / z, -fx * tx / (z * z)
            j11, j12 = fy / z, -fy * ty / (z * z)
            # rows of J·A·S: the projected, scaled axes
            u0 = j00 * axes[0, 0] * s0 + j02 * axes[2, 0] * s0
            u1 = j00 * axes[0, 1] * s1 + j02 * axes[2, 1] * s1
            u2 = j00 * axes[0, 2] * s2 + j02 * axes[2, 2] * s2
            v0 = j11 * axes[1, 0] * s0 + j12 * axes[2, 0] * s0
            v1 = j11 * axes[1, 1] * s1 + j12 * axes[2, 1] * s1
            v2 = j11 * axes[1, 2] * s2 + j12 * axes[2, 2] * s2
            a = u0 * u0 + u1 * u1 + u2 * u2 + eps2d
            b = u0 * v0 + u1 * v1 + u2 * v2
            c = v0 * v0 + v1 * v1 + v2 * v2 + eps2d
            det = a * c - b * b
            if not det > 0:
                continue
            valid[i] = True
            params[i, 0], params[i, 1], params[i, 2] = c / det, -b / det, a / det
            x0, x1 = _bounds(centers[i, 0], math.sqrt(k_squared * a), width)
            y0, y1 = _bounds(centers[i, 1], math.sqrt(k_squared * c), height)
        else:
            s0, s1 = scales[i, 0], scales[i, 1]
            for r in range(3):
                h[r, 0] = (
                    K[r, 0] * axes[0, 0] * s0
                    + K[r, 1] * axes[1, 0] * s0
                    + K[r, 2] * axes[2, 0] * s0
                )
                h[r, 1] = (
                    K[r, 0] * axes[0, 1] * s1
                    + K[r, 1] * axes[1, 1] * s1
                    + K[r, 2] * axes[2, 1] * s1
                )
                h[r, 2] = K[r, 0] * x + K[r, 1] * y + K[r, 2] * z
            d = h[2, 0] ** 2 + h[2, 1] ** 2 - h[2, 2] ** 2
            if d == 0:
                continue
            valid[i] = True
            filter_x = (h[0, 0] * h[2, 0] + h[0, 1] * h[2, 1] - h[0, 2] * h[2, 2]) / d
            filter_y = (h[1, 0] * h[2, 0] + h[1, 1] * h[2, 1] - h[1, 2] * h[2, 2]) / d
            alpha_centers[i, 0], alpha_centers[i, 1] = filter_x, filter_y
            for r in range(3):
                for c in range(3):
                    params[i, 3 * r + c] = h[r, c]
            inv_k2 = 1.0 / k_squared
            dual_00 = h[0, 0] * h[0, 0] + h[0, 1] * h[0, 1] - h[0, 2] * h[0, 2] * inv_k2
            dual_11 = h[1, 0] * h[1, 0] + h[1, 1] * h[1, 1] - h[1, 2] * h[1, 2] * inv_k2
            dual_22 = h[2, 0] * h[2, 0] + h[2, 1] * h[2, 1] - h[2, 2] * h[2, 2] * inv_k2
            dual_02 = h[0, 0] * h[2, 0] + h[0, 1] * h[2, 1] - h[0, 2] * h[2, 2] * inv_k2
            dual_12 = h[1, 0] * h[2, 0] + h[1, 1] * h[2, 1] - h[1, 2] * h[2, 2] * inv_k2
            if dual_22 < 0:
                half_x = math.sqrt(max(dual_02 * dual_02 - dual_00 * dual_22, 0.0)) / abs(dual_22)
                half_y = math.sqrt(max(dual_12 * dual_12 - dual_11 * dual_22, 0.0)) / abs(dual_22)
                ex0, ex1 = _bounds(dual_02 / dual_22, half_x, width)
                ey0, ey1 = _bounds(dual_12 / dual_22, half_y, height)
            else:
                ex0, ex1 = _bounds(-dual_02, math.inf, width)
                ey0, ey1 = _bounds(-dual_12, math.inf, height)
            radius = math.sqrt(k_squared / filter_inv_square)
            fx0, fx1 = _bounds(filter_x, radius, width)
            fy0, fy1 = _bounds(filter_y, radius, height)
            ellipse_empty = ex0 > ex1 or ey0 > ey1
            filter_empty = fx0 > fx1 or fy0 > fy1
            if ellipse_empty:
                x0, x1, y0, y1 = fx0, fx1, fy0, fy1
            elif filter_empty:
                x0, x1, y0, y1 = ex0, ex1, ey0, ey1
            else:
                x0, x1, y0, y1 = min(ex0, fx0), max(ex1, fx1), min(ey0, fy0), max(ey1, fy1)
        bounds[i, 0], bounds[i, 1], bounds[i, 2], bounds[i, 3] = x0, x1, y0, y1
    return depths, centers, alpha_centers, params, opacities, valid, bounds, reaches


@numba.njit(nogil=True, cache=True)
def _depth_order(depths, candidates):  # pragma: no cover - compiled
    """``candidates`` sorted by depth, stably (ties keep their order): an LSD radix sort on the
    bits of the depths, which order like the numbers for the positive depths of valid Gaussians."""
    n = candidates.shape[0]
    keys = depths[candidates].view(np.uint64)
    order = candidates.copy()
    other_keys = np.empty(n, dtype=np.uint64)
    other_order = np.empty(n, dtype=np.int64)
    counts = np.empty(1 << 16, dtype=np.int64)
    digit = np.uint64(0xFFFF)
    for shift in range(0, 64, 16):
        by = np.uint64(shift)
        counts[:] = 0
        for i in range(n):
            counts[(keys[i] >> by) & digit] += 1
        if n == 0 or counts[(keys[0] >> by) & digit] == n:
            continue
        total = 0
        for b in range(1 << 16):
            c = counts[b]
            counts[b] = total
            total += c
        for i in range(n):
            k = (keys[i] >> by) & digit
            at = counts[k]
            other_keys[at] = keys[i]
            other_order[at] = order[i]
            counts[k] = at + 1
        keys, other_keys = other_keys, keys
        order, other_order = other_order, order
    return order


@numba.njit(nogil=True, cache=True)
def _bin_tiles(depths, bounds, inverse, tile_size, tiles_x, tiles_y):  # pragma: no cover - compiled
    """Per tile, the Gaussians whose box overlaps it, in order of depth, ties by their own index
    (Gaussian i of the caller is the kernels' ``inverse[i]``).

    Returns ``(pairs, start)``: tile t's Gaussians are ``pairs[start[t]:start[t + 1]]``.
    """
    n = depths.shape[0]
    count = 0
    for g in range(n):
        if bounds[g, 0] <= bounds[g, 1] and bounds[g, 2] <= bounds[g, 3]:
            count += 1
    candidates = np.empty(count, dtype=np.int64)
    count = 0
    for i in range(n):
        g = inverse[i]
        if bounds[g, 0] <= bounds[g, 1] and bounds[g, 2] <= bounds[g, 3]:
            candidates[count] = g
            count += 1
    order = _depth_order(depths, candidates)
    tiles = tiles_x * tiles_y
    # tile ranges in depth order, gathered once, so the passes below read them in sequence
    ranges = np.empty((count, 4), dtype=np.int32)
    for i in range(count):
        g = order[i]
        ranges[i, 0] = bounds[g, 0] // tile_size
        ranges[i, 1] = bounds[g, 1] // tile_size
        ranges[i, 2] = bounds[g, 2] // tile_size
        ranges[i, 3] = bounds[g, 3] // tile_size
    start = np.zeros(tiles + 1, dtype=np.int64)
    for i in range(count):
        for ty in range(ranges[i, 2], ranges[i, 3] + 1):
            for tx in range(ranges[i, 0], ranges[i, 1] + 1):
                start[ty * tiles_x + tx + 1] += 1
    for t in range(tiles):
        start[t + 1] += start[t]
    fill = start[:-1].copy()
    pairs = np.empty(start[tiles], dtype=np.int64)
    for i in range(count):
        g = order[i]
        for ty in range(ranges[i, 2], ranges[i, 3] + 1):
            for tx in range(ranges[i, 0], ranges[i, 1] + 1):
                t = ty * tiles_x + tx
                pairs[fill[t]] = g
                fill[t] += 1
    return pairs, start


@numba.njit(nogil=True, cache=True)
def _gather(pairs, first, last, view, local):  # pragma: no cover - compiled
    """Copy the tile's Gaussians (``pairs[first:last]``) into the contiguous ``local`` arrays."""
    alpha_centers, params, opacities, bounds, reaches = view
    ids, boxes, centres, parameters, opacity, reach = local
    for j in range(last - first):
        g = pairs[first + j]
        ids[j] = g
        for k in range(4):
            boxes[j, k] = bounds[g, k]
        centres[j, 0] = alpha_centers[g, 0]
        centres[j, 1] = alpha_centers[g, 1]
        for k in range(9):
            parameters[j, k] = params[g, k]
        opacity[j] = opacities[g]
        reach[j] = reaches[g]


@numba.njit(nogil=True, cache=True)
def _local_arrays(m):
    return (
        np.empty(m, dtype=np.int64),
        np.empty((m, 4), dtype=np.int64),
        np.empty((m, 2)),
        np.empty((m, 9)),
        np.empty(m),
        np.empty(m),
    )


@numba.njit(nogil=True, cache=True)
def _row_lists(m, y0, rows_in_tile, boxes, rows, row_counts):  # pragma: no cover - compiled
    """``rows[r, :row_counts[r]]``: the tile's Gaussians (in depth order) whose box spans pixel
    row ``y0 + r``."""
    for r in range(rows_in_tile):
        row_counts[r] = 0
    for j in range(m):
        low = max(boxes[j, 2] - y0, 0)
        high = min(boxes[j, 3] - y0, rows_in_tile - 1)
        for r in range(low, high + 1):
            rows[r, row_counts[r]] = j
            row_counts[r] += 1


@numba.njit(nogil=True, cache=True)
def _surfel_span(ax, ay, az, bx, by, bz, center_x, filter_inv_square, filter_row, two_limit):
    """``(low, high)``: the x of a row where a 2DGS Gaussian's ρ can be ≤ ``two_limit`` (2σ at
    its reach); empty when low > high, unbounded when a side is infinite.

    ρ is the smaller of the screen filter ``f·(dx² + dy²)`` (``filter_row`` = f·dy²) and the ray
    term ``(q_x² + q_y²) / q_z²`` with ``q(x) = x·a − b``. The filter's set is an interval around
    ``center_x``; the ray term's is ``A·x² + B·x + C ≤ 0``, an interval when A > 0 (else its
    complement or everything: no bound). The hull of the two is returned: a superset of the
    pixels whose σ is within reach, so skipping the others changes nothing.
    """  # pragma: no cover - compiled
    quad_a = ax * ax + ay * ay - two_limit * az * az
    if not quad_a > 0.0:
        return -math.inf, math.inf
    quad_b = -2.0 * (ax * bx + ay * by - two_limit * az * bz)
    quad_c = bx * bx + by * by - two_limit * bz * bz
    disc = quad_b * quad_b - 4.0 * quad_a * quad_c
    low, high = math.inf, -math.inf
    if disc >= 0.0:
        root = math.sqrt(disc)
        low, high = (-quad_b - root) / (2.0 * quad_a), (-quad_b + root) / (2.0 * quad_a)
    room = two_limit - filter_row
    if room >= 0.0:
        if not filter_inv_square > 0.0:
            return -math.inf, math.inf
        half = math.sqrt(room / filter_inv_square)
        low, high = min(low, center_x - half), max(high, center_x + half)
    if math.isnan(low) or math.isnan(high):
        return -math.inf, math.inf
    return low, high


@numba.njit(nogil=True, cache=True)
def _composite_row(
    py, x_low, x_high, row, count, kind, local, settings, transmittance, done, out
):  # pragma: no cover - compiled
    """Composite the pixels ``x_low … x_high − 1`` of row ``py`` over the local Gaussians
    ``row[:count]`` (in depth order), one Gaussian at a time across the row.

    Each pixel sees its Gaussians front to back, skips α < alpha_min and stops before the one
    that would bring its transmittance to ≤ transmittance_min; the row ends early once every
    pixel has stopped. Writes the composited (pixel x, local Gaussian, weight ``w = α·T``)
    triples into ``out`` = (xs, ids, weights), ordered by depth then x, and returns how many.

    α is :func:`_alpha`'s, computed with what is constant along the row taken out of the pixel
    loop: 3DGS ``σ = (½a·dx + b·dy)·dx + ½c·dy²``, where the row's pixels with σ within the
    Gaussian's reach form an interval (a quadratic in dx), so only those are visited; 2DGS the
    ray–plane cross product, linear in x along the row: ``q(x) = x·(P × v) − P₀ × v``.
    """
    alpha_min, alpha_max, t_min, filter_inv_square = settings
    _, boxes, centres, p, opacity, reach = local
    xs, ids, weights = out
    width = x_high - x_low
    for c in range(width):
        transmittance[c] = 1.0
        done[c] = False
    running = width
    composited = 0
    cy = py + 0.5
    for q in range(count):
        j = row[q]
        first = max(boxes[j, 0], x_low)
        end = min(boxes[j, 1] + 1, x_high)
        dy = cy - centres[j, 1]
        limit = reach[j] + _REACH_MARGIN
        if kind == 0:
            half_a = 0.5 * p[j, 0]
            cross = p[j, 1] * dy
            constant = 0.5 * p[j, 2] * dy * dy
            # the row's dx with σ ≤ limit + margin: ½a·dx² + cross·dx + constant − that ≤ 0;
            # pixels outside have σ above the limit by more than rounding, α < alpha_min
            disc = cross * cross - 4.0 * half_a * (constant - limit - _REACH_MARGIN)
            if half_a > 0.0 and disc < 0.0:
                continue
            if half_a > 0.0 and math.isfinite(disc):
                root = math.sqrt(disc)
                low = centres[j, 0] + (-cross - root) / (2.0 * half_a) - 0.5
                high = centres[j, 0] + (-cross + root) / (2.0 * half_a) - 0.5
                if math.isfinite(low) and math.isfinite(high):
                    if low > first:
                        first = min(math.ceil(low), end)
                    if high < end - 1:
                        end = max(math.floor(high) + 1, first)
        else:
            vx = cy * p[j, 6] - p[j, 3]
            vy = cy * p[j, 7] - p[j, 4]
            vz = cy * p[j, 8] - p[j, 5]
            ax = p[j, 7] * vz - p[j, 8] * vy
            ay = p[j, 8] * vx - p[j, 6] * vz
            az = p[j, 6] * vy - p[j, 7] * vx
            bx = p[j, 1] * vz - p[j, 2] * vy
            by = p[j, 2] * vx - p[j, 0] * vz
            bz = p[j, 0] * vy - p[j, 1] * vx
            filter_row = filter_inv_square * dy * dy
            reach_rho = 2.0 * (limit + _REACH_MARGIN)
            low, high = _surfel_span(
                ax, ay, az, bx, by, bz, centres[j, 0], filter_inv_square, filter_row, reach_rho
            )
            if low > high:
                continue
            if math.isfinite(low) and math.isfinite(high):
                # x = px + ½ within [low, high], one pixel more on each side against rounding
                first = max(first, min(math.ceil(low - 0.5) - 1, end))
                end = min(end, max(math.floor(high - 0.5) + 2, first))
        for px in range(first, end):
            c = px - x_low
            if done[c]:
                continue
            x = px + 0.5
            dx = x - centres[j, 0]
            if kind == 0:
                sigma = (half_a * dx + cross) * dx + constant
                if sigma < 0.0:
                    continue
            else:
                qx = x * ax - bx
                qy = x * ay - by
                qz = x * az - bz
                rho = filter_inv_square * dx * dx + filter_row
                if qz != 0.0:
                    rho = min(rho, (qx * qx + qy * qy) / (qz * qz))
                sigma = 0.5 * rho
            if sigma > limit:
                continue
            a = min(alpha_max, opacity[j] * math.exp(-sigma))
            if a < alpha_min:
                continue
            after = transmittance[c] * (1.0 - a)
            if after <= t_min:
                done[c] = True
                running -= 1
                continue
            xs[composited] = px
            ids[composited] = j
            weights[composited] = a * transmittance[c]
            composited += 1
            transmittance[c] = after
        if running == 0:
            break
    return composited


@numba.njit(nogil=True, cache=True)
def _tile_setup(pairs, first, last, view, tile, tiles_x, tile_size, width, height):
    """The tile's pixel rows ``y0 …`` and columns ``x0 … x1 − 1``, its local arrays, row lists,
    and buffers for one row's compositing."""
    y0, x0 = (tile // tiles_x) * tile_size, (tile % tiles_x) * tile_size
    rows_in_tile = min(tile_size, height - y0)
    x1 = min(x0 + tile_size, width)
    m = last - first
    local = _local_arrays(m)
    _gather(pairs, first, last, view, local)
    rows = np.empty((rows_in_tile, m), dtype=np.int64)
    row_counts = np.empty(rows_in_tile, dtype=np.int64)
    _row_lists(m, y0, rows_in_tile, local[1], rows, row_counts)
    out = (
        np.empty(tile_size * m, dtype=np.int64),
        np.empty(tile_size * m, dtype=np.int64),
        np.empty(tile_size * m),
    )
    transmittance, done = np.empty(tile_size), np.empty(tile_size, dtype=np.bool_)
    return y0, x0, x1, rows_in_tile, local, rows, row_counts, out, transmittance, done


@numba.njit(nogil=True, cache=True)
def _render_tiles(
    pairs,
    start,
    tiles_x,
    tile_size,
    width,
    height,
    kind,
    view,
    settings,
    depths,
    features,
    first_tile,
    step,
    outputs,
):  # pragma: no cover - compiled
    """Render the tiles ``first_tile, first_tile + step, …`` into ``outputs`` = (image [H, W, C],
    alpha [H, W], depth [H, W], max_id [H, W], best weight [H, W]), which start zeroed (max_id
    −1); every pixel belongs to one tile, so calls on disjoint tile sets can run at once."""
    image, alpha, depth, max_id, best = outputs
    channels = features.shape[1]
    tiles_y = (height + tile_size - 1) // tile_size
    for tile in range(first_tile, tiles_x * tiles_y, step):
        first, last = start[tile], start[tile + 1]
        if last == first:
            continue
        y0, x0, x1, rows_in_tile, local, rows, row_counts, out, transmittance, done = _tile_setup(
            pairs, first, last, view, tile, tiles_x, tile_size, width, height
        )
        ids = local[0]
        for r in range(rows_in_tile):
            py = y0 + r
            count = _composite_row(
                py, x0, x1, rows[r], row_counts[r], kind, local, settings, transmittance, done, out
            )
            for i in range(count):
                px, g, w = out[0][i], ids[out[1][i]], out[2][i]
                for c in range(channels):
                    image[py, px, c] += w * features[g, c]
                alpha[py, px] += w
                depth[py, px] += w * depths[g]
                if w > best[py, px]:
                    best[py, px] = w
                    max_id[py, px] = g
            for px in range(x0, x1):
                if alpha[py, px] > 0.0:
                    depth[py, px] /= alpha[py, px]


def _render_arrays(inputs: tuple, depths: np.ndarray, features: np.ndarray) -> tuple:
    """(image [H, W, C], alpha, depth, max_id [H, W]) of :func:`_render_tiles` over every tile,
    the tiles dealt round-robin to ``numba.get_num_threads()`` threads (the kernel releases the
    GIL; each pixel is written by one thread, so the result does not depend on their number)."""
    _, start, _, _, width, height, *_ = inputs
    outputs = (
        np.zeros((height, width, features.shape[1])),
        np.zeros((height, width)),
        np.zeros((height, width)),
        np.full((height, width), -1, dtype=np.int64),
        np.zeros((height, width)),
    )
    tiles = max(len(start) - 1, 1)
    threads = max(1, min(numba.get_num_threads(), tiles))

    def run(first_tile: int) -> None:
        _render_tiles(*inputs, depths, features, first_tile, threads, outputs)

    if threads == 1:
        run(0)
    else:
        with ThreadPoolExecutor(max_workers=threads, thread_name_prefix="thgs-render") as pool:
            list(pool.map(run, range(threads)))
    return outputs[:4]


@numba.njit(nogil=True, cache=True)
def _splat_back_kernel(
    pairs, start, tiles_x, tile_size, width, height, kind, view, settings, pixel_map, mask
):  # pragma: no cover - compiled
    n = view[0].shape[0]
    channels = pixel_map.shape[2]
    feature_sums = np.zeros((n, channels))
    weight_sums = np.zeros(n)
    max_weights = np.zeros(n)
    pixel_counts = np.zeros(n, dtype=np.int64)
    tiles_y = (height + tile_size - 1) // tile_size
    for tile in range(tiles_x * tiles_y):
        first, last = start[tile], start[tile + 1]
        m = last - first
        if m == 0:
            continue
        y0, x0, x1, rows_in_tile, local, rows, row_counts, out, transmittance, done = _tile_setup(
            pairs, first, last, view, tile, tiles_x, tile_size, width, height
        )
        sums = np.zeros((m, channels))
        weights = np.zeros(m)
        largest = np.zeros(m)
        counts = np.zeros(m, dtype=np.int64)
        for r in range(rows_in_tile):
            py = y0 + r
            count = _composite_row(
                py, x0, x1, rows[r], row_counts[r], kind, local, settings, transmittance, done, out
            )
            for i in range(count):
                px, j, w = out[0][i], out[1][i], out[2][i]
                if not mask[py, px]:
                    continue
                for c in range(channels):
                    sums[j, c] += w * pixel_map[py, px, c]
                weights[j] += w
                largest[j] = max(largest[j], w)
                counts[j] += 1
        for j in range(m):
            if counts[j] == 0:
                continue
            g = local[0][j]
            for c in range(channels):
                feature_sums[g, c] += sums[j, c]
            weight_sums[g] += weights[j]
            max_weights[g] = max(max_weights[g], largest[j])
            pixel_counts[g] += counts[j]
    return feature_sums, weight_sums, max_weights, pixel_counts


@numba.njit(nogil=True, cache=True)
def _add_tuple_weight(
    g, slot, weight, slot_labels, firsts, heads, node_label, node_weight, node_next, used
):  # pragma: no cover - compiled
    """Add ``weight`` to Gaussian g's label at every level of the label tuple ``slot``.

    Each (Gaussian, level)'s first label and its weight are held inline, side by side, in
    ``firsts[2·k]`` and ``firsts[2·k + 1]`` with k = g·levels + level (a Gaussian's levels share a
    cache line: one random access, and most (Gaussian, level) have one label in a view); further
    labels go to linked lists of nodes starting at ``heads[k]``; ``used[0]`` counts the nodes, and
    the caller keeps room for one more per level.
    """
    levels = slot_labels.shape[1]
    for level in range(levels):
        label = slot_labels[slot, level]
        if label < 0:
            continue
        k = g * levels + level
        if firsts[2 * k] == label:
            firsts[2 * k + 1] += weight
            continue
        if firsts[2 * k] < 0:
            firsts[2 * k] = label
            firsts[2 * k + 1] = weight
            continue
        node = heads[k]
        while node >= 0 and node_label[node] != label:
            node = node_next[node]
        if node >= 0:
            node_weight[node] += weight
            continue
        count = used[0]
        node_label[count] = label
        node_weight[count] = weight
        node_next[count] = heads[k]
        heads[k] = count
        used[0] = count + 1


@numba.njit(cache=True)
def _grown(node_label, node_weight, node_next):  # pragma: no cover - compiled
    """The node arrays copied into ones twice as long (plus some)."""
    used = node_label.shape[0]
    size = 2 * used + 1024
    labels = np.empty(size, dtype=np.int64)
    weights = np.empty(size)
    links = np.empty(size, dtype=np.int64)
    # element by element: a slice assignment compiles numba's shape-mismatch error path,
    # seconds of a first run's compilation
    for i in range(used):
        labels[i] = node_label[i]
        weights[i] = node_weight[i]
        links[i] = node_next[i]
    return labels, weights, links


@numba.njit(nogil=True, cache=True)
def _label_weights_kernel(
    pairs,
    start,
    tiles_x,
    tile_size,
    width,
    height,
    kind,
    view,
    settings,
    labels,
    cells_max,
    inverse,
):  # pragma: no cover - compiled
    """Per (Gaussian, level, label): ``Σ_x w(x)`` over the pixels with that label.

    Per tile, each distinct tuple of labels over the levels gets a slot, and every composited
    weight is added to its (local Gaussian, slot) cell; at the end of the tile every cell's weight
    is added, for each level, to a linked list of (label, weight) nodes per (Gaussian, level).
    Returns the rows sorted by the caller's Gaussian index (Gaussian i is the kernels'
    ``inverse[i]``), and the per-Gaussian weight sums and maxima in the kernels' order. A tile
    whose cells would exceed ``cells_max`` adds each pixel's weights to the lists directly.
    """
    n = view[0].shape[0]
    levels = labels.shape[0]
    weight_sums = np.zeros(n)
    max_weights = np.zeros(n)
    firsts = np.empty(2 * n * levels)  # (label, weight) of each (Gaussian, level), side by side
    firsts[0::2] = -1.0
    heads = np.full(n * levels, -1, dtype=np.int64)
    node_label = np.empty(1024, dtype=np.int64)
    node_weight = np.empty(1024)
    node_next = np.empty(1024, dtype=np.int64)
    used = np.zeros(1, dtype=np.int64)
    area = tile_size * tile_size
    slot_labels = np.empty((area, levels), dtype=np.int64)
    pixel_slot = np.empty(area, dtype=np.int64)
    tiles_y = (height + tile_size - 1) // tile_size
    for tile in range(tiles_x * tiles_y):
        first, last = start[tile], start[tile + 1]
        m = last - first
        if m == 0:
            continue
        y0, x0, x1, rows_in_tile, local, rows, row_counts, out, transmittance, done = _tile_setup(
            pairs, first, last, view, tile, tiles_x, tile_size, width, height
        )
        slots = 0
        for r in range(rows_in_tile):
            for c in range(x1 - x0):
                slot = -1
                for s in range(slots):
                    same = True
                    for level in range(levels):
                        if slot_labels[s, level] != labels[level, y0 + r, x0 + c]:
                            same = False
                            break
                    if same:
                        slot = s
                        break
                if slot < 0:
                    slot = slots
                    for level in range(levels):
                        slot_labels[slot, level] = labels[level, y0 + r, x0 + c]
                    slots += 1
                pixel_slot[r * tile_size + c] = slot
        direct = m * slots > cells_max
        cells = np.zeros(1 if direct else m * slots)
        weights = np.zeros(m)
        largest = np.zeros(m)
        for r in range(rows_in_tile):
            py = y0 + r
            count = _composite_row(
                py, x0, x1, rows[r], row_counts[r], kind, local, settings, transmittance, done, out
            )
            for i in range(count):
                px, j, w = out[0][i], out[1][i], out[2][i]
                weights[j] += w
                largest[j] = max(largest[j], w)
                slot = pixel_slot[r * tile_size + px - x0]
                if not direct:
                    cells[j * slots + slot] += w
                    continue
                if used[0] + levels > node_label.shape[0]:
                    node_label, node_weight, node_next = _grown(node_label, node_weight, node_next)
                _add_tuple_weight(
                    local[0][j],
                    slot,
                    w,
                    slot_labels,
                    firsts,
                    heads,
                    node_label,
                    node_weight,
                    node_next,
                    used,
                )
        for j in range(m):
            if weights[j] == 0.0:
                continue
            g = local[0][j]
            weight_sums[g] += weights[j]
            max_weights[g] = max(max_weights[g], largest[j])
            if direct:
                continue
            for s in range(slots):
                w = cells[j * slots + s]
                if w == 0.0:
                    continue
                if used[0] + levels > node_label.shape[0]:
                    node_label, node_weight, node_next = _grown(node_label, node_weight, node_next)
                _add_tuple_weight(
                    g, s, w, slot_labels, firsts, heads, node_label, node_weight, node_next, used
                )
    total = used[0]
    for slot in range(n * levels):
        total += firsts[2 * slot] >= 0
    out_gaussians = np.empty(total, dtype=np.int64)
    out_levels = np.empty(total, dtype=np.int64)
    out_labels = np.empty(total, dtype=np.int64)
    out_weights = np.empty(total)
    row = 0
    for index in range(n):
        g = inverse[index]
        if max_weights[g] == 0.0:
            continue
        for level in range(levels):
            slot = g * levels + level
            if firsts[2 * slot] < 0:
                continue
            begin = row
            out_labels[row] = int(firsts[2 * slot])
            out_weights[row] = firsts[2 * slot + 1]
            row += 1
            node = heads[slot]
            while node >= 0:
                # insertion by label: the lists hold a few labels each
                at = row
                while at > begin and out_labels[at - 1] > node_label[node]:
                    out_labels[at] = out_labels[at - 1]
                    out_weights[at] = out_weights[at - 1]
                    at -= 1
                out_labels[at] = node_label[node]
                out_weights[at] = node_weight[node]
                row += 1
                node = node_next[node]
            for k in range(begin, row):
                out_gaussians[k] = index
                out_levels[k] = level
    return out_gaussians, out_levels, out_labels, out_weights, weight_sums, max_weights


@dataclass(frozen=True, eq=False)
class _Prepared:
    """What every view's projection needs of the Gaussians, in the kernels' order.

    Attributes:
        order: [N] int64, the Gaussian at each position of the kernels' arrays (Z-order of the
            centres).
        inverse: [N] int64, the position of each Gaussian: ``order[inverse[i]] == i``.
        arrays: (means [N, 3], rotations [N, 9], scales [N, 2|3], opacities [N]) in float64,
            in the kernels' order.
    """

    order: np.ndarray
    inverse: np.ndarray
    arrays: tuple[np.ndarray, ...]


_PREPARED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
"""Gaussians → (their state key, their :class:`_Prepared`)."""
_PREPARED_LOCK = threading.Lock()


def _prepared(gaussians: Gaussians) -> _Prepared:
    """The Gaussians' :class:`_Prepared`, computed once per Gaussians and reused by every view
    until a tensor is modified in place."""
    key = gaussians.state_key()
    with _PREPARED_LOCK:
        cached = _PREPARED.get(gaussians)
    if cached is not None and cached[0] == key:
        return cached[1]

    means = gaussians.means.detach().cpu().double().numpy()
    order = spatial_order(means)
    inverse = np.empty_like(order)
    inverse[order] = np.arange(len(order))

    def array(tensor: Tensor) -> np.ndarray:
        return tensor.detach().cpu().double().numpy()[order]  # a C-contiguous copy

    arrays = (
        means[order],
        *_prepare_kernel(
            array(gaussians.quats), array(gaussians.scales), array(gaussians.opacities)
        ),
    )
    prepared = _Prepared(order, inverse, arrays)
    with _PREPARED_LOCK:
        _PREPARED[gaussians] = (key, prepared)
    return prepared


def _project_arrays(prepared: _Prepared, camera: Cameras, kind: int, config: RasterConfig) -> tuple:
    """:func:`_project_kernel`'s arrays, in the kernels' order."""
    settings = (config.near, config.far, config.alpha_min, config.eps2d, config.filter_inv_square)
    return _project_kernel(
        *prepared.arrays,
        np.ascontiguousarray(camera.viewmats[0].double().numpy()),
        np.ascontiguousarray(camera.Ks[0].double().numpy()),
        int(camera.widths[0]),
        int(camera.heights[0]),
        kind,
        settings,
    )


def _projection(gaussians: Gaussians, camera: Cameras, config: RasterConfig) -> Projection:
    prepared = _prepared(gaussians)
    arrays = _project_arrays(prepared, camera, _KIND[gaussians.kind], config)
    depths, centers, alpha_centers, params, opacities, valid, bounds, _ = (
        torch.from_numpy(array[prepared.inverse]) for array in arrays
    )
    return Projection(
        kind=gaussians.kind,
        width=int(camera.widths[0]),
        height=int(camera.heights[0]),
        depths=depths,
        centers=centers,
        alpha_centers=alpha_centers,
        params=params,
        opacities=opacities,
        valid=valid,
        bounds=bounds,
    )


def _kernel_inputs(gaussians: Gaussians, camera: Cameras, config: RasterConfig) -> tuple:
    """The Gaussians' :class:`_Prepared`, the projection arrays (in the kernels' order) and the
    arguments every compositing kernel starts with."""
    prepared = _prepared(gaussians)
    kind = _KIND[gaussians.kind]
    arrays = _project_arrays(prepared, camera, kind, config)
    depths, _, alpha_centers, params, opacities, _, bounds, reaches = arrays
    width, height = int(camera.widths[0]), int(camera.heights[0])
    tile_size = config.tile_size
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    pairs, start = _bin_tiles(depths, bounds, prepared.inverse, tile_size, tiles_x, tiles_y)
    settings = (
        config.alpha_min,
        config.alpha_max,
        config.transmittance_min,
        config.filter_inv_square,
    )
    view = (alpha_centers, params, opacities, bounds, reaches)
    inputs = (pairs, start, tiles_x, tile_size, width, height, kind, view, settings)
    return prepared, arrays, inputs


class NumbaBackend:
    """Compiled CPU loops in float64 (the CPU default)."""

    name = "numba"

    def unusable(self, device: torch.device, dtype: torch.dtype) -> str | None:
        if device.type != "cpu":
            return "it runs on the CPU only (use backend 'torch' or 'gsplat', or device cpu)"
        if dtype != torch.float64:
            return "it computes in float64 only (use precision 'float64' or 'auto')"
        return None

    def project(
        self, gaussians: Gaussians, camera: Cameras, config: RasterConfig, dtype: torch.dtype
    ) -> Projection:
        return _projection(gaussians, camera, config)

    def render(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        features: Tensor,
        config: RasterConfig,
        dtype: torch.dtype,
    ) -> RenderOutput:
        prepared, arrays, inputs = _kernel_inputs(gaussians, camera, config)
        values = features.cpu().double().numpy()[prepared.order]
        image, alpha, depth, max_id = _render_arrays(inputs, arrays[0], values)
        out_dtype = features.dtype
        return RenderOutput(
            image=torch.from_numpy(image).to(out_dtype),
            alpha=torch.from_numpy(alpha).to(out_dtype),
            depth=torch.from_numpy(depth).to(out_dtype),
            max_id=torch.from_numpy(np.where(max_id >= 0, prepared.order[max_id], -1)),
        )

    def splat_back(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        pixel_map: Tensor,
        mask: Tensor | None,
        config: RasterConfig,
        dtype: torch.dtype,
    ) -> SplatBackOutput:
        prepared, arrays, inputs = _kernel_inputs(gaussians, camera, config)
        height, width = pixel_map.shape[:2]
        values = np.ascontiguousarray(pixel_map.cpu().double().numpy())
        keep = np.ones((height, width), dtype=np.bool_) if mask is None else mask.numpy()
        sums = _splat_back_kernel(*inputs, values, np.ascontiguousarray(keep))
        feature_sums, weight_sums, max_weights, counts, depths, centers = (
            torch.from_numpy(array[prepared.inverse]) for array in (*sums, *arrays[:2])
        )
        out_dtype = pixel_map.dtype
        return SplatBackOutput(
            feature_sums=feature_sums.to(out_dtype),
            weight_sums=weight_sums.to(out_dtype),
            max_weights=max_weights.to(out_dtype),
            pixel_counts=counts,
            depths=depths.to(out_dtype),
            centers=centers.to(out_dtype),
        )

    def label_weights(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        label_maps: Tensor,
        config: RasterConfig,
        dtype: torch.dtype,
    ) -> LabelWeights:
        prepared, arrays, inputs = _kernel_inputs(gaussians, camera, config)
        maps = np.ascontiguousarray(label_maps.numpy().astype(np.int64, copy=False))
        g, levels, labels, weights, weight_sums, max_weights = _label_weights_kernel(
            *inputs, maps, _LOCAL_SLOTS_MAX, prepared.inverse
        )
        inverse = prepared.inverse
        return LabelWeights(
            gaussians=torch.from_numpy(g),
            levels=torch.from_numpy(levels),
            labels=torch.from_numpy(labels),
            weights=torch.from_numpy(weights),
            weight_sums=torch.from_numpy(weight_sums[inverse]),
            max_weights=torch.from_numpy(max_weights[inverse]),
            depths=torch.from_numpy(arrays[0][inverse]),
        )
