"""CPU backend: tiles, a depth sort per tile, and numba loops over each pixel's Gaussians.

The loops are the rasterization of 3DGS/gsplat written out per pixel: front to back over the
Gaussians of the pixel's tile, skip α < alpha_min, stop before the Gaussian that would bring the
transmittance to ≤ transmittance_min. Work and memory are bounded by (tile, Gaussian) pairs, never
by (pixel, Gaussian) pairs.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from thgs.render.config import RasterConfig
from thgs.render.projection import Projection

_KIND = {"3dgs": 0, "2dgs": 1}


@numba.njit(cache=True)
def _bin_tiles(bounds, tile_size, tiles_x):
    """(tile, Gaussian) pairs for every tile each Gaussian's bounds overlap, Gaussians in order."""
    n = bounds.shape[0]
    counts = np.zeros(n, dtype=np.int64)
    for g in range(n):
        x0, x1, y0, y1 = bounds[g, 0], bounds[g, 1], bounds[g, 2], bounds[g, 3]
        if x0 <= x1 and y0 <= y1:
            counts[g] = (x1 // tile_size - x0 // tile_size + 1) * (
                y1 // tile_size - y0 // tile_size + 1
            )
    tiles = np.empty(counts.sum(), dtype=np.int64)
    gaussians = np.empty(counts.sum(), dtype=np.int64)
    p = 0
    for g in range(n):
        if counts[g] == 0:
            continue
        for ty in range(bounds[g, 2] // tile_size, bounds[g, 3] // tile_size + 1):
            for tx in range(bounds[g, 0] // tile_size, bounds[g, 1] // tile_size + 1):
                tiles[p] = ty * tiles_x + tx
                gaussians[p] = g
                p += 1
    return tiles, gaussians


@numba.njit(inline="always")
def _alpha(g, px, py, kind, centers, params, opacities, filter_inv_square, alpha_max):
    """α of Gaussian g at the pixel centre (px, py), before the alpha_min test."""
    dx = px - centers[g, 0]
    dy = py - centers[g, 1]
    if kind == 0:
        sigma = 0.5 * (params[g, 0] * dx * dx + params[g, 2] * dy * dy) + params[g, 1] * dx * dy
        if sigma < 0.0:
            return 0.0
    else:
        # planes through the pixel's ray, in surfel coordinates; their cross product is (u, v, 1)
        ux = px * params[g, 6] - params[g, 0]
        uy = px * params[g, 7] - params[g, 1]
        uz = px * params[g, 8] - params[g, 2]
        vx = py * params[g, 6] - params[g, 3]
        vy = py * params[g, 7] - params[g, 4]
        vz = py * params[g, 8] - params[g, 5]
        qx = uy * vz - uz * vy
        qy = uz * vx - ux * vz
        qz = ux * vy - uy * vx
        rho = filter_inv_square * (dx * dx + dy * dy)
        if qz != 0.0:
            u = qx / qz
            v = qy / qz
            rho = min(rho, u * u + v * v)
        sigma = 0.5 * rho
    return min(alpha_max, opacities[g] * math.exp(-sigma))


@numba.njit(cache=True)
def _composite_pixel(px, py, first, last, order, view, settings, ids, weights):
    """Composite pixel (px, py) front to back over ``order[first:last]``.

    Writes the composited Gaussians and their weights ``w = α·T`` into ``ids`` and ``weights``
    (in depth order) and returns how many there are.
    """
    kind, centers, params, opacities, bounds = view
    alpha_min, alpha_max, t_min, filter_inv_square = settings
    transmittance = 1.0
    count = 0
    for p in range(first, last):
        g = order[p]
        if px < bounds[g, 0] or px > bounds[g, 1] or py < bounds[g, 2] or py > bounds[g, 3]:
            continue
        a = _alpha(
            g, px + 0.5, py + 0.5, kind, centers, params, opacities, filter_inv_square, alpha_max
        )
        if a < alpha_min:
            continue
        after = transmittance * (1.0 - a)
        if after <= t_min:
            break
        ids[count] = g
        weights[count] = a * transmittance
        count += 1
        transmittance = after
    return count


@numba.njit(parallel=True, cache=True)
def _render_kernel(
    order, tile_start, tiles_x, tile_size, width, height, view, settings, depths, features
):
    channels = features.shape[1]
    image = np.zeros((height, width, channels))
    alpha = np.zeros((height, width))
    depth = np.zeros((height, width))
    max_id = np.full((height, width), -1, dtype=np.int64)
    tiles_y = (height + tile_size - 1) // tile_size
    for tile in numba.prange(tiles_x * tiles_y):
        first, last = tile_start[tile], tile_start[tile + 1]
        ids = np.empty(last - first, dtype=np.int64)
        weights = np.empty(last - first)
        ty, tx = tile // tiles_x, tile % tiles_x
        for py in range(ty * tile_size, min((ty + 1) * tile_size, height)):
            for px in range(tx * tile_size, min((tx + 1) * tile_size, width)):
                count = _composite_pixel(px, py, first, last, order, view, settings, ids, weights)
                best = 0.0
                for i in range(count):
                    g, w = ids[i], weights[i]
                    for c in range(channels):
                        image[py, px, c] += w * features[g, c]
                    alpha[py, px] += w
                    depth[py, px] += w * depths[g]
                    if w > best:
                        best = w
                        max_id[py, px] = g
                if alpha[py, px] > 0.0:
                    depth[py, px] /= alpha[py, px]
    return image, alpha, depth, max_id


@numba.njit(cache=True)
def _splat_back_kernel(
    order, tile_start, tiles_x, tile_size, width, height, view, settings, pixel_map, mask
):
    n = view[1].shape[0]
    channels = pixel_map.shape[2]
    feature_sums = np.zeros((n, channels))
    weight_sums = np.zeros(n)
    max_weights = np.zeros(n)
    pixel_counts = np.zeros(n, dtype=np.int64)
    tiles_y = (height + tile_size - 1) // tile_size
    for tile in range(tiles_x * tiles_y):
        first, last = tile_start[tile], tile_start[tile + 1]
        ids = np.empty(last - first, dtype=np.int64)
        weights = np.empty(last - first)
        ty, tx = tile // tiles_x, tile % tiles_x
        for py in range(ty * tile_size, min((ty + 1) * tile_size, height)):
            for px in range(tx * tile_size, min((tx + 1) * tile_size, width)):
                if not mask[py, px]:
                    continue
                count = _composite_pixel(px, py, first, last, order, view, settings, ids, weights)
                for i in range(count):
                    g, w = ids[i], weights[i]
                    for c in range(channels):
                        feature_sums[g, c] += w * pixel_map[py, px, c]
                    weight_sums[g] += w
                    if w > max_weights[g]:
                        max_weights[g] = w
                    pixel_counts[g] += 1
    return feature_sums, weight_sums, max_weights, pixel_counts


@numba.njit(cache=True)
def _label_weights_kernel(
    order, tile_start, tiles_x, tile_size, width, height, view, settings, labels, label_count
):
    """Per (Gaussian, level, label): the summed weight ``Σ_x w(x)`` over pixels with that label.

    Keys are ``(g · levels + level) · label_count + label``; pixels without a label (−1) add to
    the Gaussian's total weight only.
    """
    n = view[1].shape[0]
    levels = labels.shape[0]
    sums = numba.typed.Dict.empty(key_type=numba.types.int64, value_type=numba.types.float64)
    weight_sums = np.zeros(n)
    max_weights = np.zeros(n)
    tiles_y = (height + tile_size - 1) // tile_size
    for tile in range(tiles_x * tiles_y):
        first, last = tile_start[tile], tile_start[tile + 1]
        ids = np.empty(last - first, dtype=np.int64)
        weights = np.empty(last - first)
        ty, tx = tile // tiles_x, tile % tiles_x
        for py in range(ty * tile_size, min((ty + 1) * tile_size, height)):
            for px in range(tx * tile_size, min((tx + 1) * tile_size, width)):
                count = _composite_pixel(px, py, first, last, order, view, settings, ids, weights)
                for i in range(count):
                    g, w = ids[i], weights[i]
                    weight_sums[g] += w
                    if w > max_weights[g]:
                        max_weights[g] = w
                    for level in range(levels):
                        label = labels[level, py, px]
                        if label >= 0:
                            key = (g * levels + level) * label_count + label
                            sums[key] = sums.get(key, 0.0) + w
    keys = np.empty(len(sums), dtype=np.int64)
    values = np.empty(len(sums))
    for i, (key, value) in enumerate(sums.items()):
        keys[i] = key
        values[i] = value
    return keys, values, weight_sums, max_weights


def _sorted_tiles(projection: Projection, config: RasterConfig):
    """Pairs sorted by tile, then by depth (ties by Gaussian index), and each tile's start."""
    tile_size = config.tile_size
    tiles_x = (projection.width + tile_size - 1) // tile_size
    tiles_y = (projection.height + tile_size - 1) // tile_size
    bounds = np.ascontiguousarray(projection.bounds.cpu().numpy())
    tiles, gaussians = _bin_tiles(bounds, tile_size, tiles_x)
    depths = projection.depths.cpu().numpy()
    order = np.lexsort((gaussians, depths[gaussians], tiles))
    tile_start = np.searchsorted(tiles[order], np.arange(tiles_x * tiles_y + 1))
    return gaussians[order], tile_start.astype(np.int64), tiles_x, bounds


def _view(projection: Projection, bounds: np.ndarray):
    """The projection as the kernels take it: (kind, α centres, params, opacities, bounds)."""
    return (
        _KIND[projection.kind],
        np.ascontiguousarray(projection.alpha_centers.cpu().numpy()),
        np.ascontiguousarray(projection.params.cpu().numpy()),
        np.ascontiguousarray(projection.opacities.cpu().numpy()),
        bounds,
    )


def _kernel_inputs(projection: Projection, config: RasterConfig) -> tuple:
    """The arguments both kernels start with: sorted pairs, tiles, image size, view, settings."""
    order, tile_start, tiles_x, bounds = _sorted_tiles(projection, config)
    settings = (
        config.alpha_min,
        config.alpha_max,
        config.transmittance_min,
        config.filter_inv_square,
    )
    return (
        order,
        tile_start,
        tiles_x,
        config.tile_size,
        projection.width,
        projection.height,
        _view(projection, bounds),
        settings,
    )


def render_cpu(projection: Projection, features: np.ndarray, config: RasterConfig):
    """Forward pass; returns NumPy float64 image [H,W,C], alpha, depth [H,W], int64 max_id [H,W]."""
    return _render_kernel(
        *_kernel_inputs(projection, config),
        np.ascontiguousarray(projection.depths.cpu().numpy()),
        np.ascontiguousarray(features, dtype=np.float64),
    )


def splat_back_cpu(
    projection: Projection, pixel_map: np.ndarray, mask: np.ndarray, config: RasterConfig
):
    """Adjoint pass; returns NumPy feature sums [N,C], weight sums, max weights [N], counts [N]."""
    return _splat_back_kernel(
        *_kernel_inputs(projection, config),
        np.ascontiguousarray(pixel_map, dtype=np.float64),
        np.ascontiguousarray(mask, dtype=np.bool_),
    )


def label_weights_cpu(projection: Projection, labels: np.ndarray, config: RasterConfig):
    """Per-(Gaussian, level, label) weight sums; returns (keys, values, weight sums, max weights).

    ``labels`` is [L, H, W] int (−1 = none); keys encode ``(g · L + level) · count + label`` with
    ``count = labels.max() + 1``.
    """
    label_count = max(int(labels.max()) + 1, 1)
    return _label_weights_kernel(
        *_kernel_inputs(projection, config),
        np.ascontiguousarray(labels, dtype=np.int64),
        label_count,
    )
