"""torch backend: vectorized PyTorch on any device (CPU, CUDA, MPS), the on-device reference.

Per view, on the Gaussians' device, in the compute dtype:

1. **Projection**: :func:`thgs.render.projection.project_torch`.
2. **Binning**: every Gaussian with a non-empty α ≥ alpha_min box is paired with each tile
   (``config.tile_size``) its box overlaps (``repeat_interleave``); one int64 key sort by
   (tile, depth rank) puts each tile's Gaussians in compositing order. The rank comes from a
   stable sort of the depths, so ties go by index.
3. **Steps**: tiles, ordered by how many Gaussians they hold, are processed a chunk at a time.
   Each step takes the next B (:data:`_BATCH`) Gaussians of every tile of the chunk and
   evaluates α on [tiles, tile pixels, B] (the terms that depend on a pixel's row or column
   only are computed on [tiles, tile_size, B] and broadcast). Each pixel's transmittance is
   carried from step to step; within a step it is one ``cumprod`` over
   ``[T, 1 − α₀, 1 − α₁, …]``, with the factor 1 for the skipped α < alpha_min, which on the CPU
   multiplies in the order of a per-pixel loop and rounds the same. The transmittance never
   increases, so the stop rule (stop before the Gaussian that would bring it to
   ≤ transmittance_min) reads: composite where the transmittance after the Gaussian is
   > transmittance_min. The weight is ``w = α · T`` before it. Tiles whose lists are exhausted
   or whose pixels have all stopped leave the chunk.
4. Each step's weights [tiles, pixels, B] feed the operation: ``render`` adds ``w @ features``
   (batched matmul) into the image and keeps each pixel's largest weight; ``splat_back`` adds
   ``wᵀ @ pixel_map`` and the weights into per-Gaussian sums (``index_add_``);
   ``label_weights`` sums the weights per (tile, label) and Gaussian, and one sort over the
   (Gaussian, level, label) keys merges the steps at the end.

Memory: a step holds at most about :data:`_STEP_TENSORS` tensors of [tiles, pixels, B]
elements; the number of tiles per step is chosen so that they fit in :data:`_STEP_BYTES` on
accelerators (256 MiB: fewer, larger kernels) and :data:`_CPU_STEP_BYTES` on the CPU (16 MiB:
tensors that stay in cache are several times faster there than larger steps). The rest is
O(pairs) for binning and O(N·C + H·W·C) for inputs and outputs (O(pairs · labels per tile) for
``label_weights``), so a 1M-Gaussian 986×728 view fits on a GPU as on the CPU. On the CPU in
float64 the results equal the brute-force reference to rounding (~1e-12); float32 and the
parallel ``cumprod`` of accelerators round differently.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import NamedTuple

import torch
from torch import Tensor

from thgs.render.config import RasterConfig
from thgs.render.outputs import LabelWeights, RenderOutput, SplatBackOutput
from thgs.render.projection import Projection, project_torch
from thgs.scene import Cameras, Gaussians

__all__ = ["TorchBackend"]

_BATCH = 64
"""Gaussians per tile in one step: larger steps mean fewer kernel launches but more α evaluated
past the point where a tile's pixels have all stopped."""

_STEP_BYTES = 256 * 2**20
"""Working memory of one step on an accelerator (bytes): the number of tiles per step is chosen
so that :data:`_STEP_TENSORS` tensors of [tiles, tile pixels, B] elements in the compute dtype
fit (at least one tile per step)."""

_CPU_STEP_BYTES = 16 * 2**20
"""The same on the CPU."""

_STEP_TENSORS = 12
"""How many [tiles, tile pixels, B] tensors a step holds at most at once, with a margin (σ and
the temporaries of the 2DGS intersection, α, the transmittance chain, the consumers' products;
about 8 measured)."""


class _Padded(NamedTuple):
    """Per-Gaussian projection arrays with one extra row N, a Gaussian that covers no pixel,
    for the padding of tiles that hold fewer than B Gaussians."""

    centres: Tensor  # [N + 1, 2] α centres
    params: Tensor  # [N + 1, 9] conic (3DGS) or homography (2DGS)
    opacities: Tensor  # [N + 1]
    bounds: Tensor  # [N + 1, 4] int64 (x0, x1, y0, y1), the last one empty
    cutoffs: Tensor  # [N + 1] σ beyond which α < alpha_min / e: max(ln(o / alpha_min), 0) + 1


def _padded(projection: Projection, config: RasterConfig) -> _Padded:
    def pad(values: Tensor) -> Tensor:
        return torch.cat([values, torch.zeros_like(values[:1])])

    empty = torch.tensor([[0, -1, 0, -1]], dtype=torch.int64, device=projection.bounds.device)
    opacities = pad(projection.opacities)
    return _Padded(
        centres=pad(projection.alpha_centers),
        params=pad(projection.params),
        opacities=opacities,
        bounds=torch.cat([projection.bounds, empty]),
        cutoffs=torch.log(opacities / config.alpha_min).clamp_min(0) + 1,
    )


def _bin(projection: Projection, tile_size: int, tiles_x: int, tiles: int) -> tuple[Tensor, Tensor]:
    """Each tile's Gaussians in compositing order (depth, then index).

    Returns:
        ``(pairs, start)``: tile t (row-major) holds ``pairs[start[t]:start[t + 1]]``; pairs [M]
        int64 Gaussian indices, start [tiles + 1] int64.
    """
    bounds = projection.bounds
    device = bounds.device
    n = len(bounds)
    x0, x1, y0, y1 = bounds.unbind(-1)
    present = torch.nonzero((x0 <= x1) & (y0 <= y1)).squeeze(1)
    tx0, ty0 = x0[present] // tile_size, y0[present] // tile_size
    nx = x1[present] // tile_size - tx0 + 1
    ny = y1[present] // tile_size - ty0 + 1
    counts = nx * ny
    total = int(counts.sum())
    owner = torch.repeat_interleave(
        torch.arange(len(present), device=device), counts, output_size=total
    )
    local = torch.arange(total, device=device) - (torch.cumsum(counts, 0) - counts)[owner]
    tile = (ty0[owner] + local // nx[owner]) * tiles_x + tx0[owner] + local % nx[owner]
    rank = torch.empty(n, dtype=torch.int64, device=device)
    rank[torch.argsort(projection.depths, stable=True)] = torch.arange(n, device=device)
    gaussian = present[owner]
    keys, order = torch.sort(tile * n + rank[gaussian])
    start = torch.zeros(tiles + 1, dtype=torch.int64, device=device)
    start[1:] = torch.cumsum(torch.bincount(keys // max(n, 1), minlength=tiles), 0)
    return gaussian[order], start


def _alpha(
    view: _Padded,
    ids: Tensor,
    columns: Tensor,
    rows: Tensor,
    kind: str,
    config: RasterConfig,
) -> Tensor:
    """α of Gaussians ``ids`` [t, B] at the centres of the pixels of ``rows`` [t, th] ×
    ``columns`` [t, tw] (int64 pixel indices) of each of t tiles.

    Returns:
        α [t, th, tw, B], capped at alpha_max; 0 where it is not composited at all (below
        alpha_min, or the pixel outside the Gaussian's box).
    """
    dtype = view.params.dtype
    px = columns.to(dtype)[:, :, None] + 0.5  # [t, tw, 1]
    py = rows.to(dtype)[:, :, None] + 0.5  # [t, th, 1]
    centres = view.centres[ids]  # [t, B, 2]
    dx = px - centres[:, None, :, 0]  # [t, tw, B]
    dy = py - centres[:, None, :, 1]  # [t, th, B]
    boxes = view.bounds[ids][:, None]  # [t, 1, B, 4]
    col, row = columns[:, :, None], rows[:, :, None]
    outside_x = (col < boxes[..., 0]) | (col > boxes[..., 1])  # [t, tw, B]
    outside_y = (row < boxes[..., 2]) | (row > boxes[..., 3])  # [t, th, B]
    # σ = ∞ outside the box, through a penalty on the row and column terms
    penalty_x = torch.zeros_like(dx).masked_fill_(outside_x, torch.inf)
    penalty_y = torch.zeros_like(dy).masked_fill_(outside_y, torch.inf)
    params = view.params[ids][:, None]  # [t, 1, B, 9]
    cutoffs = view.cutoffs[ids][:, None, None, :]  # [t, 1, 1, B]
    if kind == "3dgs":
        a, b, c = params[..., 0], params[..., 1], params[..., 2]
        sigma = (a * dx**2 + penalty_x)[:, None] + (c * dy**2 + penalty_y)[:, :, None]
        sigma.mul_(0.5).add_((b * dx)[:, None] * dy[:, :, None])
        sigma.masked_fill_(sigma < 0, torch.inf)  # rounding: skipped, as in gsplat
        sigma = torch.minimum(sigma, cutoffs).neg_()
    else:
        # planes through the pixel's ray, in surfel coordinates; their cross product is
        # (u, v, 1)·q_z. Zeroing the planes outside the box makes q = 0 there, so ρ3d = ∞ or NaN
        ux, uy, uz = (px * params[..., 6 + k] - params[..., k] for k in range(3))  # [t, tw, B]
        vx, vy, vz = (py * params[..., 6 + k] - params[..., 3 + k] for k in range(3))  # [t, th, B]
        ux, uy = (u.masked_fill_(outside_x, 0.0)[:, None] for u in (ux, uy))
        vx, vy = (v.masked_fill_(outside_y, 0.0)[:, :, None] for v in (vx, vy))
        uz, vz = uz[:, None], vz[:, :, None]
        qz = ux * vy - uy * vx
        rho3d = ((uy * vz - uz * vy) / qz).square_()
        rho3d += ((uz * vx - ux * vz) / qz).square_()
        del qz
        rho2d = (dx * dx + penalty_x)[:, None] + (dy * dy + penalty_y)[:, :, None]
        rho2d.mul_(config.filter_inv_square).clamp_(max=2 * cutoffs)
        # where q_z = 0, ρ3d is ∞ or NaN and ρ2d holds (the numba backend's test q_z ≠ 0)
        sigma = torch.where(rho3d < rho2d, rho3d, rho2d).mul_(-0.5)
    # beyond the cutoff α < alpha_min either way; capping σ there keeps exp off ∞ and off the
    # slow subnormal results
    alpha = torch.exp(sigma).mul_(view.opacities[ids][:, None, None, :])
    alpha.clamp_(max=config.alpha_max)
    return alpha.masked_fill_(alpha < config.alpha_min, 0.0)


def _step(
    view: _Padded,
    ids: Tensor,
    columns: Tensor,
    rows: Tensor,
    transmittance: Tensor,
    kind: str,
    config: RasterConfig,
) -> tuple[Tensor, Tensor]:
    """Composite the next B Gaussians ``ids`` [t, B] of t tiles over their pixels (``rows``
    [t, th] × ``columns`` [t, tw]) with transmittance ``transmittance`` [t, th, tw].

    Returns:
        the weights [t, th·tw, B] and the transmittance after them [t, th, tw] (≤
        transmittance_min where a pixel has stopped).
    """
    alpha = _alpha(view, ids, columns, rows, kind, config)
    # chain[..., k] = T before Gaussian k: [T, T(1 − α₀), T(1 − α₀)(1 − α₁), …], multiplied in
    # this order; a skipped Gaussian (α = 0) has the factor 1
    chain = torch.cat([transmittance[..., None], 1 - alpha], dim=-1).cumprod_(-1)
    weights = alpha.mul_(chain[..., :-1]).mul_(chain[..., 1:] > config.transmittance_min)
    return weights.reshape(len(ids), -1, ids.shape[1]), chain[..., -1]


def _steps(projection: Projection, config: RasterConfig) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """The blending weights of the view, a step at a time.

    Yields:
        ``(pixels, ids, weights)``: pixels [t, P] int64 row-major pixel index of each tile pixel
        (H·W for those past the image's edge), ids [t, B] int64 Gaussian index (N for padding)
        and weights [t, P, B] ``w = α·T`` (0 where not composited) of t tiles of P = tile_size²
        pixels. Every (pixel, Gaussian) pair with a positive weight occurs in exactly one step,
        and a pixel's steps come in compositing order.
    """
    width, height = projection.width, projection.height
    tile_size = config.tile_size
    tiles_x = -(-width // tile_size)
    tiles = tiles_x * -(-height // tile_size)
    pairs, start = _bin(projection, tile_size, tiles_x, tiles)
    if len(pairs) == 0:
        return
    device, dtype = pairs.device, projection.params.dtype
    view = _padded(projection, config)
    n = len(projection.depths)
    counts = start[1:] - start[:-1]
    order = torch.argsort(counts, descending=True, stable=True)
    ordered_counts = counts[order].tolist()
    order = order[: sum(count > 0 for count in ordered_counts)]
    budget = _CPU_STEP_BYTES if device.type == "cpu" else _STEP_BYTES
    elements = max(1, budget // (_STEP_TENSORS * dtype.itemsize))
    offsets = torch.arange(tile_size, device=device)
    first = 0
    while first < len(order):
        batch = min(_BATCH, ordered_counts[first])
        chunk = order[first : first + max(1, elements // (tile_size * tile_size * batch))]
        first += len(chunk)
        columns = (chunk % tiles_x)[:, None] * tile_size + offsets  # [t, tw]
        rows = (chunk // tiles_x)[:, None] * tile_size + offsets  # [t, th]
        inside = (rows < height)[:, :, None] & (columns < width)[:, None, :]  # [t, th, tw]
        pixels = torch.where(inside, rows[:, :, None] * width + columns[:, None, :], width * height)
        pixels = pixels.reshape(len(chunk), -1)
        transmittance = inside.to(dtype)
        position, last = start[chunk], start[chunk + 1]
        slots = torch.arange(batch, device=device)
        while True:
            index = position[:, None] + slots  # [t, B]
            ids = torch.where(index < last[:, None], pairs[index.clamp(max=len(pairs) - 1)], n)
            weights, transmittance = _step(
                view, ids, columns, rows, transmittance, projection.kind, config
            )
            yield pixels, ids, weights
            position = position + batch
            running = (transmittance > config.transmittance_min).flatten(1).any(1)
            active = (position < last) & running
            if not bool(active.all()):
                keep = torch.nonzero(active).squeeze(1)
                if len(keep) == 0:
                    break
                columns, rows, pixels = columns[keep], rows[keep], pixels[keep]
                transmittance, position, last = transmittance[keep], position[keep], last[keep]


class TorchBackend:
    """Vectorized PyTorch on any device: float64 on the CPU, float32 on accelerators by default."""

    name = "torch"

    def unusable(self, device: torch.device, dtype: torch.dtype) -> str | None:
        if dtype not in (torch.float32, torch.float64):
            return f"it computes in float32 or float64, not {dtype}"
        if dtype == torch.float64 and torch.device(device).type == "mps":
            return "MPS has no float64 (use precision 'float32' or 'auto')"
        return None

    def project(
        self, gaussians: Gaussians, camera: Cameras, config: RasterConfig, dtype: torch.dtype
    ) -> Projection:
        return project_torch(gaussians, camera, config, dtype)

    def render(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        features: Tensor,
        config: RasterConfig,
        dtype: torch.dtype,
    ) -> RenderOutput:
        projection = project_torch(gaussians, camera, config, dtype)
        height, width = projection.height, projection.width
        pixel_count, channels = height * width, features.shape[1]
        device = gaussians.device
        # per Gaussian [features, 1, depth], so that one matmul gives image, alpha and Σ w z;
        # row N (zeros) is the padding
        values = torch.cat(
            [
                features.to(dtype),
                torch.ones_like(projection.depths)[:, None],
                projection.depths[:, None],
            ],
            dim=1,
        )
        values = torch.cat([values, values.new_zeros(1, channels + 2)])
        # one extra pixel, pixel_count, collects the tile pixels past the image's edge
        sums = torch.zeros(pixel_count + 1, channels + 2, dtype=dtype, device=device)
        best = torch.zeros(pixel_count + 1, dtype=dtype, device=device)
        max_id = torch.full((pixel_count + 1,), -1, dtype=torch.int64, device=device)
        for pixels, ids, weights in _steps(projection, config):
            flat = pixels.reshape(-1)
            sums.index_add_(0, flat, torch.bmm(weights, values[ids]).reshape(-1, channels + 2))
            # the first maximum is the nearest; a later step wins only with a larger weight
            step_best, step_arg = weights.max(-1)
            step_best, step_id = step_best.reshape(-1), ids.gather(1, step_arg).reshape(-1)
            current = best[flat]
            max_id[flat] = torch.where(step_best > current, step_id, max_id[flat])
            best[flat] = torch.maximum(step_best, current)
        image, alpha, depth = sums[:-1].split([channels, 1, 1], dim=1)
        alpha, depth = alpha[:, 0], depth[:, 0]
        depth = torch.where(alpha > 0, depth / torch.where(alpha > 0, alpha, 1), 0)
        out_dtype = features.dtype
        return RenderOutput(
            image=image.reshape(height, width, channels).to(out_dtype),
            alpha=alpha.reshape(height, width).to(out_dtype),
            depth=depth.reshape(height, width).to(out_dtype),
            max_id=max_id[:-1].reshape(height, width),
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
        projection = project_torch(gaussians, camera, config, dtype)
        n, channels = len(gaussians), pixel_map.shape[2]
        device = gaussians.device
        # per pixel [F, 1], so that one matmul gives the feature and weight sums; the extra
        # pixel H·W (past the image's edge) is outside the mask
        values = pixel_map.to(dtype).reshape(-1, channels)
        values = torch.cat([values, torch.ones_like(values[:, :1])], dim=1)
        values = torch.cat([values, values.new_zeros(1, channels + 1)])
        keep = torch.ones(len(values) - 1, dtype=dtype, device=device)
        if mask is not None:
            keep = mask.reshape(-1).to(dtype)
        keep = torch.cat([keep, keep.new_zeros(1)])
        # row N collects the padding
        sums = torch.zeros(n + 1, channels + 1, dtype=dtype, device=device)
        max_weights = torch.zeros(n + 1, dtype=dtype, device=device)
        pixel_counts = torch.zeros(n + 1, dtype=torch.int32, device=device)  # MPS adds no int64
        for pixels, ids, weights in _steps(projection, config):
            weights = weights * keep[pixels][..., None]
            flat_ids = ids.reshape(-1)
            step_sums = torch.bmm(weights.transpose(1, 2), values[pixels])  # [t, B, C + 1]
            sums.index_add_(0, flat_ids, step_sums.reshape(-1, channels + 1))
            max_weights.scatter_reduce_(0, flat_ids, weights.amax(1).reshape(-1), "amax")
            pixel_counts.index_add_(
                0, flat_ids, (weights > 0).sum(1, dtype=torch.int32).reshape(-1)
            )
        out_dtype = pixel_map.dtype
        return SplatBackOutput(
            feature_sums=sums[:-1, :channels].to(out_dtype),
            weight_sums=sums[:-1, channels].to(out_dtype),
            max_weights=max_weights[:-1].to(out_dtype),
            pixel_counts=pixel_counts[:-1].long(),
            depths=projection.depths.to(out_dtype),
            centers=projection.centers.to(out_dtype),
        )

    def label_weights(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        label_maps: Tensor,
        config: RasterConfig,
        dtype: torch.dtype,
    ) -> LabelWeights:
        projection = project_torch(gaussians, camera, config, dtype)
        n, levels = len(gaussians), label_maps.shape[0]
        height, width = projection.height, projection.width
        device = gaussians.device
        # labels numbered 0 … U − 1 in increasing order; U stands for "no label" (−1, and the
        # pixel H·W past the image's edge), so a key (Gaussian·L + level)·(U + 1) + label sorts
        # rows by Gaussian, level and label
        values, compact = torch.unique(label_maps, return_inverse=True)
        unlabelled = len(values)
        compact = torch.where(label_maps < 0, unlabelled, compact).reshape(levels, height * width)
        compact = torch.cat([compact, compact.new_full((levels, 1), unlabelled)], dim=1)
        weight_sums = torch.zeros(n + 1, dtype=dtype, device=device)
        max_weights = torch.zeros(n + 1, dtype=dtype, device=device)
        keys, sums = [], []
        for pixels, ids, weights in _steps(projection, config):
            flat_ids = ids.reshape(-1)
            weight_sums.index_add_(0, flat_ids, weights.sum(1).reshape(-1))
            max_weights.scatter_reduce_(0, flat_ids, weights.amax(1).reshape(-1), "amax")
            tiles, batch = ids.shape
            tile = torch.arange(tiles, device=device)[:, None]
            for level in range(levels):
                # cells (tile, label) of this step, then the weight of each cell and Gaussian
                cells, cell = torch.unique(
                    tile * (unlabelled + 1) + compact[level][pixels], return_inverse=True
                )
                index = (cell[..., None] * batch + torch.arange(batch, device=device)).reshape(-1)
                totals = torch.zeros(len(cells) * batch, dtype=dtype, device=device)
                totals.index_add_(0, index, weights.reshape(-1))
                found = torch.nonzero(totals > 0).squeeze(1)
                cell_of, slot = found // batch, found % batch
                label = cells[cell_of] % (unlabelled + 1)
                gaussian = ids[cells[cell_of] // (unlabelled + 1), slot]
                labelled = label < unlabelled
                keys.append(((gaussian * levels + level) * (unlabelled + 1) + label)[labelled])
                sums.append(totals[found][labelled])
        if keys:
            merged, row = torch.unique(torch.cat(keys), return_inverse=True)
            weights = torch.zeros(len(merged), dtype=dtype, device=device)
            weights.index_add_(0, row, torch.cat(sums))
        else:
            merged = torch.zeros(0, dtype=torch.int64, device=device)
            weights = torch.zeros(0, dtype=dtype, device=device)
        level_of = merged // (unlabelled + 1)
        return LabelWeights(
            gaussians=level_of // max(levels, 1),
            levels=level_of % max(levels, 1),
            labels=values[merged % (unlabelled + 1)],
            weights=weights,
            weight_sums=weight_sums[:-1],
            max_weights=max_weights[:-1],
            depths=projection.depths,
        )
