"""gsplat backend: gsplat's fused CUDA kernels, float32 (``pip install 'thgs[gpu]'``).

Per call, gsplat projects and bins the Gaussians once (``fully_fused_projection`` for 3DGS,
``fully_fused_projection_2dgs`` for 2DGS, then ``isect_tiles`` and ``isect_offset_encode``), and
every output comes from that one binning:

- **Fused**: ``render``'s image, alpha and depth are ``rasterize_to_pixels`` /
  ``rasterize_to_pixels_2dgs`` of the features plus two channels, the centres' camera depth z and
  ones (``alpha = Σ w``, ``depth = Σ w z / Σ w``: our centre depth, for 2DGS too, rather than
  gsplat's depth modes), in chunks of at most :data:`_CHANNEL_CHUNK` channels zero-padded to a
  count the kernels are compiled for. ``splat_back``'s feature sums are the vector–Jacobian
  product of the same kernels (gsplat's fused backward pass): ``Σ_x w_k(x) F(x)`` is exactly the
  gradient of ``Σ_x ⟨render(f)(x), F(x)⟩`` with respect to f.
- **Exact per pair**: ``max_id``, the per-Gaussian weight sums, maxima and pixel counts, and
  ``label_weights`` come from the (Gaussian, pixel) pairs listed by
  ``rasterize_to_indices_in_range`` (``_2dgs`` for surfels), each pair's weight ``w = α·T``
  recomputed in torch from gsplat's projection as gsplat's pure-torch ``accumulate`` does. Each
  call lists whole tiles (a block of tiles at a time, the others given empty ranges), starting
  from T = 1, so the kernel applies the same α test and stop rule in the same float32 arithmetic
  as the fused forward pass: the pairs are exactly those ``render`` composites, and the weights
  differ from the kernel's only by rounding (``exp`` against ``__expf``).
- ``project`` is the shared projection, :func:`thgs.render.projection.project_torch`;
  ``splat_back``'s depths and centres are its first step alone
  (:func:`~thgs.render.projection.project_centers`), in float32 on the device.

**Memory of the pair listing.** A block of tiles is as large as half the device's free memory
allows (:func:`_pair_budget`) at :data:`_BYTES_PER_PAIR` bytes per pair, counting for each tile
an upper bound on its pairs (:func:`_tile_pair_bounds`): per intersection the tile's pixels inside
the Gaussian's box (3DGS, whose box holds every α ≥ 1/255) or all of the tile's pixels (2DGS,
whose box does not), and per pixel at most :data:`_MAX_PAIRS_PER_PIXEL` pairs. On a large GPU a
1M-Gaussian view is listed in one or a few calls instead of one per 2^16 intersections.

gsplat's kernels fix some constants that :class:`thgs.render.RasterConfig` makes parameters:

- α is capped at 0.999 (``RasterConfig.alpha_max`` defaults to 0.99, the 2DGS/3DGS CUDA value);
- contributions with α < 1/255 are skipped, and a pixel stops before the Gaussian that would
  bring its transmittance to T ≤ 1e-4 (the defaults of ``alpha_min`` and ``transmittance_min``);
- the 2DGS low-pass is ``2·|x − c|²`` (``filter_inv_square`` 2, the default), centred on the
  centre of the projected 1σ ellipse as in :mod:`thgs.render.projection`;
- its own 16-pixel tiles (``RasterConfig.tile_size`` is ignored), each Gaussian binned into the
  tiles of a box around its α centre. 3DGS: ``ceil(min(3.33, √(2 ln(255·o))) · √Σ2D_ii)``
  pixels, which holds every α ≥ 1/255 (the 3σ radius of the original 3DGS CUDA code is what
  drops contributions up to α ≈ 0.011, docs/rendering.md). 2DGS: ``ceil(3.33 ×`` the half
  extents of the projected 1σ ellipse``)``, at least one pixel, which can cut off part of the
  α ≥ 1/255 region: the perspective image of the surfel is larger on its far side, and the
  low-pass disc (radius up to 2.35 px) sticks out of the box of a surfel thinner than a pixel.
  Lost contributions are mostly below α ≈ 0.015, up to ≈ 0.1 for such thin surfels at a tile
  border;
- ``near``, ``far`` and ``eps2d`` are passed through (gsplat's 3DGS projection keeps a centre at
  exactly ``near``, the other backends cull it).

A config asking for other values (the default ``alpha_max`` 0.99 among them) is logged once per
process at INFO, not refused: results then differ from the numba and torch backends by the
different cap (and minimum, stop rule or filter) as well as by the binning above.
"""

from __future__ import annotations

import bisect
import functools
import importlib.util
import logging
import math
import os
import shutil
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from thgs.render.config import RasterConfig
from thgs.render.outputs import LabelWeights, RenderOutput, SplatBackOutput
from thgs.render.projection import Projection, project_centers, project_torch
from thgs.scene import Cameras, Gaussians

__all__ = ["GsplatBackend"]

logger = logging.getLogger(__name__)

_TILE_SIZE = 16
"""gsplat's tile edge in pixels (the only one its kernels are tested with)."""

_FIXED = {"alpha_max": 0.999, "alpha_min": 1.0 / 255.0, "transmittance_min": 1e-4}
"""RasterConfig fields gsplat's kernels hard-code, and their values there."""

_FILTER_INV_SQUARE = 2.0
"""gsplat's 2DGS low-pass factor (``FILTER_INV_SQUARE_2DGS``)."""

_CHANNEL_CHUNK = 32
"""Channels rasterized per kernel call (gsplat's ``rasterization`` uses 32 as well)."""

_CHANNEL_COUNTS = (1, 2, 3, 4, 8, 16, 32)
"""Channel counts up to :data:`_CHANNEL_CHUNK` that both rasterizers are compiled for; a chunk
is zero-padded to the next one (gsplat pads the 2DGS colours with uninitialised memory)."""

_MAX_PAIRS_PER_PIXEL = (
    math.floor(math.log(_FIXED["transmittance_min"]) / math.log1p(-_FIXED["alpha_min"])) + 1
)
"""Pairs of one pixel at most (2345): every composited Gaussian has α ≥ 1/255, and a pixel stops
before the Gaussian that would bring its transmittance to ≤ 1e-4 (one more for rounding)."""

_BYTES_PER_PAIR = 400
"""Device memory one listed pair takes at most with the temporaries: its ids and weight (the
kernel's output and ``_pair_weights``, about 300 bytes for surfels) and ``label_weights``' keys of
four levels."""

_FREE_SHARE = 0.5
"""Share of the device's free memory that one block of the pair listing may take."""

_NO_KERNELS = (
    "gsplat's CUDA kernels are not built and no CUDA toolkit (nvcc) was found to compile them: "
    "install a prebuilt gsplat wheel for your torch and CUDA versions from "
    "https://docs.gsplat.studio/whl (e.g. pip install gsplat --index-url "
    "https://docs.gsplat.studio/whl/pt24cu124), or install the CUDA toolkit and set CUDA_HOME"
)


@functools.cache
def _kernels_problem() -> str | None:
    """Why gsplat's CUDA extension cannot load, found without importing it (which compiles it
    when no prebuilt one exists); None when it can."""
    if not torch.cuda.is_available():
        return "torch sees no CUDA device (torch.cuda.is_available() is False)"
    if importlib.util.find_spec("gsplat") is None:
        return "gsplat is not installed: pip install 'thgs[gpu]'"
    loaded = sys.modules.get("gsplat.cuda._backend")
    if loaded is not None:
        return None if loaded._C is not None else _NO_KERNELS
    if importlib.util.find_spec("gsplat.csrc") is not None:
        return None  # a prebuilt wheel
    from torch.utils.cpp_extension import CUDA_HOME

    nvcc = CUDA_HOME is not None and os.path.isfile(os.path.join(CUDA_HOME, "bin", "nvcc"))
    if nvcc or shutil.which("nvcc") is not None:
        logger.info(
            "gsplat has no prebuilt kernels: it compiles them with the CUDA toolkit on first use "
            "(minutes, once; cached afterwards)"
        )
        return None
    return _NO_KERNELS


@functools.cache
def _log_unhonoured(settings: str) -> None:
    """Log, once per distinct ``settings``, that gsplat cannot follow them."""
    logger.info(
        "gsplat cannot honour RasterConfig %s: its kernels fix them, so its results differ from "
        "the numba and torch backends' by the different constants (and by its tile culling, "
        "docs/rendering.md)",
        settings,
    )


def _check_config(config: RasterConfig, kind: str) -> None:
    """Log (once per combination) the settings gsplat's kernels cannot follow."""
    fixed = dict(_FIXED)
    if kind == "2dgs":
        fixed["filter_inv_square"] = _FILTER_INV_SQUARE
    unhonoured = [
        f"{name}={getattr(config, name):g} (gsplat: {value:g})"
        for name, value in fixed.items()
        if not math.isclose(getattr(config, name), value, rel_tol=1e-6)
    ]
    if unhonoured:
        _log_unhonoured(", ".join(unhonoured))


@dataclass(frozen=True, eq=False)
class _View:
    """One camera's Gaussians as gsplat's kernels take them (a batch of one image, unpacked),
    float32 on the Gaussians' CUDA device.

    Attributes:
        kind: "2dgs" or "3dgs".
        width, height: image size in pixels.
        means2d: [1, N, 2] the point α is centred on, in pixels: the projected centre (3DGS) or
            the 2D filter centre (2DGS).
        params: [1, N, 3] conics (3DGS) or [1, N, 3, 3] ray transforms, the homographies
            ``K · [s₀ r₀, s₁ r₁, μ_cam]`` row-major (2DGS).
        normals: [1, N, 3] camera-frame surfel normals (2DGS, for the kernel's normal map); None
            for 3DGS.
        opacities: [1, N] activated opacities.
        depths: [N] camera-space z of every centre (scene units).
        radii: [1, N, 2] int32 half extents in pixels of the box each Gaussian was binned by
            (0 for Gaussians not drawn).
        offsets: [1, tiles_y, tiles_x] int32 first intersection of each tile (row-major).
        flatten_ids: [I] int32 Gaussian of each intersection, by tile, then depth, then index.
    """

    kind: Literal["2dgs", "3dgs"]
    width: int
    height: int
    means2d: Tensor
    params: Tensor
    normals: Tensor | None
    opacities: Tensor
    depths: Tensor
    radii: Tensor
    offsets: Tensor
    flatten_ids: Tensor


@torch.no_grad()
def _view(gaussians: Gaussians, camera: Cameras, config: RasterConfig) -> _View:
    """gsplat's projection and binning of ``gaussians`` for the single camera ``camera``."""
    import gsplat

    _check_config(config, gaussians.kind)
    device = gaussians.device
    width, height = int(camera.widths[0]), int(camera.heights[0])
    viewmats = camera.viewmats.to(device=device, dtype=torch.float32)  # [1, 4, 4]
    Ks = camera.Ks.to(device=device, dtype=torch.float32)  # [1, 3, 3]
    means = gaussians.means.float().contiguous()
    quats = gaussians.quats.float().contiguous()
    scales = gaussians.activated_scales().float()
    opacities = gaussians.activated_opacities().float().contiguous()
    near, far = config.near, config.far
    normals = None
    if gaussians.kind == "3dgs":
        radii, means2d, sort_depths, params, _ = gsplat.fully_fused_projection(
            means,
            None,
            quats,
            scales.contiguous(),
            viewmats,
            Ks,
            width,
            height,
            eps2d=config.eps2d,
            near_plane=near,
            far_plane=far,
            opacities=opacities,
        )
    else:
        # gsplat takes three scales and uses the first two
        scales = torch.cat([scales, torch.zeros_like(scales[:, :1])], dim=1)
        radii, means2d, sort_depths, params, normals = gsplat.fully_fused_projection_2dgs(
            means,
            quats,
            scales,
            viewmats,
            Ks,
            width,
            height,
            eps2d=config.eps2d,
            near_plane=near,
            far_plane=far,
        )
    tiles_x, tiles_y = -(-width // _TILE_SIZE), -(-height // _TILE_SIZE)
    _, isect_ids, flatten_ids = gsplat.isect_tiles(
        means2d, radii, sort_depths, _TILE_SIZE, tiles_x, tiles_y
    )
    offsets = gsplat.isect_offset_encode(isect_ids, 1, tiles_x, tiles_y)
    rotation, translation = viewmats[0, :3, :3], viewmats[0, :3, 3]
    return _View(
        kind=gaussians.kind,
        width=width,
        height=height,
        means2d=means2d,
        params=params,
        normals=normals,
        opacities=opacities[None],
        depths=(means @ rotation.T + translation)[:, 2],
        radii=radii,
        offsets=offsets.reshape(1, tiles_y, tiles_x),
        flatten_ids=flatten_ids,
    )


def _channel_slices(channels: int) -> Iterator[slice]:
    """Ranges of at most :data:`_CHANNEL_CHUNK` of ``channels`` channels."""
    for first in range(0, channels, _CHANNEL_CHUNK):
        yield slice(first, min(first + _CHANNEL_CHUNK, channels))


def _rasterize(view: _View, colors: Tensor) -> Tensor:
    """``colors`` [N, D] float32 (D ≤ :data:`_CHANNEL_CHUNK`) composited front to back by
    gsplat's fused kernel: [H, W, D], differentiable with respect to ``colors``."""
    import gsplat

    channels = colors.shape[1]
    padded = next(count for count in _CHANNEL_COUNTS if count >= channels)
    colors = torch.nn.functional.pad(colors, (0, padded - channels))[None]  # [1, N, padded]
    arguments = (view.width, view.height, _TILE_SIZE, view.offsets, view.flatten_ids)
    if view.kind == "3dgs":
        image, _ = gsplat.rasterize_to_pixels(
            view.means2d, view.params, colors, view.opacities, *arguments
        )
    else:
        densify = torch.zeros_like(view.means2d)  # gsplat's densification gradient, unused
        image, *_ = gsplat.rasterize_to_pixels_2dgs(
            view.means2d, view.params, colors, view.opacities, view.normals, densify, *arguments
        )
    return image[0, ..., :channels]


def _pair_weights(view: _View, gaussian_ids: Tensor, pixel_ids: Tensor) -> Tensor:
    """Blending weights ``w = α·T`` [M] float32 of the (Gaussian, pixel) pairs ``gaussian_ids``,
    ``pixel_ids`` [M] int64 (row-major pixel index), with α as gsplat's kernels evaluate it.

    The pairs must list each pixel's composited Gaussians completely, consecutively and in
    compositing order (as ``rasterize_to_indices_in_range`` writes them for whole tiles): T of a
    pair is the product of ``1 − α`` over the pairs before it in its pixel's run.
    """
    px = (pixel_ids % view.width).float() + 0.5
    py = torch.div(pixel_ids, view.width, rounding_mode="floor").float() + 0.5
    centres = view.means2d[0, gaussian_ids]  # [M, 2]
    dx, dy = centres[:, 0] - px, centres[:, 1] - py
    if view.kind == "3dgs":
        a, b, c = view.params[0, gaussian_ids].unbind(-1)
        sigma = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    else:
        # the pixel's ray meets the surfel plane at (u, v) = cross.xy / cross.z
        rows = view.params[0, gaussian_ids]  # [M, 3, 3]
        cross = torch.linalg.cross(
            px[:, None] * rows[:, 2] - rows[:, 0], py[:, None] * rows[:, 2] - rows[:, 1], dim=-1
        )
        rho3d = (cross[:, 0] / cross[:, 2]) ** 2 + (cross[:, 1] / cross[:, 2]) ** 2
        rho2d = _FILTER_INV_SQUARE * (dx * dx + dy * dy)
        sigma = 0.5 * torch.minimum(rho3d, rho2d)
    alpha = (view.opacities[0, gaussian_ids] * torch.exp(-sigma)).clamp(max=_FIXED["alpha_max"])
    # log T before each pair: an exclusive cumulative sum of log(1 − α) restarted at each pixel,
    # in float64 so that subtracting the running sum at a pixel's first pair loses nothing
    logs = torch.log1p(-alpha.double())
    before = torch.cumsum(logs, 0) - logs
    _, counts = torch.unique_consecutive(pixel_ids, return_counts=True)
    firsts = torch.cumsum(counts, 0) - counts
    before -= torch.repeat_interleave(before[firsts], counts, output_size=len(before))
    return alpha * torch.exp(before).float()


def _tile_pair_bounds(view: _View) -> Tensor:
    """An upper bound on the (Gaussian, pixel) pairs of each tile: [tiles] int64, row-major.

    Each of a tile's intersections counts the tile's pixels inside the Gaussian's box widened by
    a pixel (3DGS: gsplat's box holds every α ≥ 1/255) or all the tile's pixels (2DGS, whose box
    can cut off part of α ≥ 1/255); a tile holds at most :data:`_MAX_PAIRS_PER_PIXEL` pairs per
    pixel.
    """
    device = view.flatten_ids.device
    tiles_y, tiles_x = view.offsets.shape[1:]
    starts = view.offsets.flatten().long()
    ends = torch.cat([starts[1:], torch.tensor([len(view.flatten_ids)], device=device)])
    tile = torch.arange(tiles_y * tiles_x, device=device)
    x0 = (tile % tiles_x) * _TILE_SIZE
    y0 = torch.div(tile, tiles_x, rounding_mode="floor") * _TILE_SIZE
    tile_columns = (view.width - x0).clamp(max=_TILE_SIZE)
    tile_rows = (view.height - y0).clamp(max=_TILE_SIZE)
    if view.kind == "2dgs":
        sums = (ends - starts) * tile_columns * tile_rows
    else:
        tile_of = torch.repeat_interleave(tile, ends - starts, output_size=len(view.flatten_ids))
        ids = view.flatten_ids.long()
        centres = view.means2d[0, ids]
        radii = view.radii[0, ids].to(centres.dtype)
        # pixel (c, r) has its centre at (c + 0.5, r + 0.5)
        low = torch.floor(centres - radii - 0.5).long()
        high = torch.ceil(centres + radii - 0.5).long()
        corner = torch.stack([x0[tile_of], y0[tile_of]], dim=1)
        size = torch.stack([tile_columns[tile_of], tile_rows[tile_of]], dim=1)
        inside = torch.minimum(high, corner + size - 1) - torch.maximum(low, corner) + 1
        # the intersections come tile by tile: a tile's sum is a difference of running sums
        running = torch.cumsum(inside.clamp(min=0).prod(dim=1), 0)
        running = torch.cat([running.new_zeros(1), running])
        sums = running[ends] - running[starts]
    return torch.minimum(sums, tile_columns * tile_rows * _MAX_PAIRS_PER_PIXEL)


def _pair_budget(free_bytes: int) -> int:
    """Pairs one block of tiles may list, given the device's free memory in bytes (≥ 1)."""
    return max(1, int(free_bytes * _FREE_SHARE) // _BYTES_PER_PAIR)


def _free_bytes(device: torch.device) -> int:
    """The CUDA device's free memory in bytes, counting what torch's allocator holds unused."""
    free, _ = torch.cuda.mem_get_info(device)
    return free + torch.cuda.memory_reserved(device) - torch.cuda.memory_allocated(device)


def _tile_blocks(bounds: list[int], budget: int) -> list[tuple[int, int]]:
    """Consecutive tile ranges ``[first, last)`` covering every tile once, each as long as the
    sum of its tiles' ``bounds`` stays within ``budget`` (a tile over it alone)."""
    cumulative = [0]
    for bound in bounds:
        cumulative.append(cumulative[-1] + bound)
    blocks, first = [], 0
    while first < len(bounds):
        last = max(first + 1, bisect.bisect_right(cumulative, cumulative[first] + budget) - 1)
        blocks.append((first, last))
        first = last
    return blocks


def _pairs(view: _View) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """The (Gaussian, pixel) pairs gsplat composites, a block of whole tiles at a time (blocks
    sized by the device's free memory, :func:`_tile_blocks`).

    Yields:
        ``(gaussian_ids, pixel_ids, weights)``, each [M]: int64 Gaussian index, int64 row-major
        pixel index and float32 ``w = α·T`` (> 0). Every composited pair occurs once; all the
        pairs of a pixel occur in one block, consecutively, in compositing order.
    """
    import gsplat

    enumerate_pairs = (
        gsplat.rasterize_to_indices_in_range
        if view.kind == "3dgs"
        else gsplat.rasterize_to_indices_in_range_2dgs
    )
    # tile t holds intersections starts[t]:starts[t + 1] (one host copy of the tile offsets)
    starts = [*view.offsets.flatten().tolist(), len(view.flatten_ids)]
    device = view.depths.device
    budget = _pair_budget(_free_bytes(device))
    ones = torch.ones(1, view.height, view.width, device=device)
    batch = _TILE_SIZE * _TILE_SIZE  # Gaussians per tile per kernel batch
    for first, last in _tile_blocks(_tile_pair_bounds(view).tolist(), budget):
        begin, end = starts[first], starts[last]
        if end > begin:
            # tiles outside [first, last) get empty ranges: offsets clamped to [begin, end] and
            # the intersections cut at end
            gaussian_ids, pixel_ids, _ = enumerate_pairs(
                0,
                -(-(end - begin) // batch),
                ones,
                view.means2d,
                view.params,
                view.opacities,
                view.width,
                view.height,
                _TILE_SIZE,
                view.offsets.clamp(begin, end),
                view.flatten_ids[:end],
            )
            yield gaussian_ids, pixel_ids, _pair_weights(view, gaussian_ids, pixel_ids)


def _add_weight_stats(
    gaussian_ids: Tensor, weights: Tensor, sums: Tensor, maxima: Tensor, counts: Tensor | None
) -> None:
    """Add the pairs' weights into per-Gaussian ``sums`` [N], ``maxima`` [N] and, when given,
    pixel ``counts`` [N] int64."""
    sums.index_add_(0, gaussian_ids, weights)
    maxima.scatter_reduce_(0, gaussian_ids, weights, "amax")
    if counts is not None:
        counts += torch.bincount(gaussian_ids, minlength=len(counts))


class GsplatBackend:
    """gsplat's fused CUDA kernels, float32 (the CUDA default when gsplat is installed)."""

    name = "gsplat"

    def unusable(self, device: torch.device, dtype: torch.dtype) -> str | None:
        device = torch.device(device)
        if device.type != "cuda":
            return (
                f"gsplat needs a CUDA device, not {device.type} (use backend 'torch', or "
                "'numba' on the CPU)"
            )
        if dtype != torch.float32:
            return f"gsplat computes in float32 only, not {dtype} (use precision 'float32')"
        return _kernels_problem()

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
        view = _view(gaussians, camera, config)
        height, width, channels = view.height, view.width, features.shape[1]
        depths = view.depths[:, None]
        values = torch.cat([features.float(), depths, torch.ones_like(depths)], dim=1)
        with torch.no_grad():
            image = torch.cat(
                [_rasterize(view, values[:, part]) for part in _channel_slices(channels + 2)],
                dim=-1,
            )  # [H, W, C + 2]
        alpha = image[..., channels + 1]
        depth = torch.where(alpha > 0, image[..., channels] / torch.where(alpha > 0, alpha, 1), 0)
        # per pixel, the first of its pairs (compositing order) with its largest weight
        best = torch.zeros(height * width, device=features.device)
        max_id = torch.full((height * width,), -1, dtype=torch.int64, device=features.device)
        for gaussian_ids, pixel_ids, weights in _pairs(view):
            best.scatter_reduce_(0, pixel_ids, weights, "amax")
            top = weights == best[pixel_ids]
            pixels, ids = pixel_ids[top], gaussian_ids[top]
            first = torch.ones(len(pixels), dtype=torch.bool, device=pixels.device)
            first[1:] = pixels[1:] != pixels[:-1]
            max_id[pixels[first]] = ids[first]
        out_dtype = features.dtype
        return RenderOutput(
            image=image[..., :channels].to(out_dtype),
            alpha=alpha.to(out_dtype),
            depth=depth.to(out_dtype),
            max_id=max_id.reshape(height, width),
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
        view = _view(gaussians, camera, config)
        n, channels = len(gaussians), pixel_map.shape[2]
        device = gaussians.device
        targets = pixel_map.float()
        if mask is not None:
            targets = targets * mask[..., None]
        sums = []
        for part in _channel_slices(channels):
            # Σ_x w_k(x) F(x) is the gradient of Σ_x ⟨render(f)(x), F(x)⟩ with respect to f
            colors = torch.zeros(n, part.stop - part.start, device=device, requires_grad=True)
            with torch.enable_grad():
                image = _rasterize(view, colors)
                (gradient,) = torch.autograd.grad(image, colors, grad_outputs=targets[..., part])
            sums.append(gradient)
        feature_sums = torch.cat(sums, dim=1) if sums else targets.new_zeros(n, 0)
        weight_sums = torch.zeros(n, device=device)
        max_weights = torch.zeros(n, device=device)
        pixel_counts = torch.zeros(n, dtype=torch.int64, device=device)
        keep = None if mask is None else mask.reshape(-1)
        for gaussian_ids, pixel_ids, weights in _pairs(view):
            if keep is not None:
                inside = keep[pixel_ids]
                gaussian_ids, weights = gaussian_ids[inside], weights[inside]
            _add_weight_stats(gaussian_ids, weights, weight_sums, max_weights, pixel_counts)
        depths, centers = project_centers(gaussians, camera, config, dtype)
        out_dtype = pixel_map.dtype
        return SplatBackOutput(
            feature_sums=feature_sums.to(out_dtype),
            weight_sums=weight_sums.to(out_dtype),
            max_weights=max_weights.to(out_dtype),
            pixel_counts=pixel_counts,
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
        view = _view(gaussians, camera, config)
        n, levels = len(gaussians), label_maps.shape[0]
        device = gaussians.device
        # labels numbered 0 … U − 1 in increasing order, U for "no label" (−1), so a key
        # (Gaussian·L + level)·(U + 1) + label sorts rows by Gaussian, level and label
        values, compact = torch.unique(label_maps, return_inverse=True)
        unlabelled = len(values)
        compact = torch.where(label_maps < 0, unlabelled, compact)
        compact = compact.reshape(levels, view.height * view.width)
        level_index = torch.arange(levels, device=device)[:, None]
        weight_sums = torch.zeros(n, device=device)
        max_weights = torch.zeros(n, device=device)
        keys, sums = [], []
        for gaussian_ids, pixel_ids, weights in _pairs(view):
            _add_weight_stats(gaussian_ids, weights, weight_sums, max_weights, None)
            labels = compact[:, pixel_ids]  # [L, M]
            labelled = labels < unlabelled
            key = (gaussian_ids * levels + level_index) * (unlabelled + 1) + labels
            block_keys, row = torch.unique(key[labelled], return_inverse=True)
            totals = torch.zeros(len(block_keys), device=device)
            totals.index_add_(0, row, weights.expand(levels, -1)[labelled])
            keys.append(block_keys)
            sums.append(totals)
        merged = torch.cat(keys) if keys else torch.zeros(0, dtype=torch.int64, device=device)
        merged, row = torch.unique(merged, return_inverse=True)
        label_sums = torch.zeros(len(merged), device=device)
        if sums:
            label_sums.index_add_(0, row, torch.cat(sums))
        level_of = merged // (unlabelled + 1)
        return LabelWeights(
            gaussians=level_of // max(levels, 1),
            levels=level_of % max(levels, 1),
            labels=values[merged % (unlabelled + 1)],
            weights=label_sums,
            weight_sums=weight_sums,
            max_weights=max_weights,
            depths=view.depths,
        )
