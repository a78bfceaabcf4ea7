"""The brute-force reference every backend is tested against (gsplat's ``_torch_impl`` pattern).

Every pixel against every Gaussian, in float64 on the CPU: α is evaluated densely for all
(pixel, Gaussian) pairs (the 2DGS ray–surfel intersection by solving the homography, not with the
backends' plane cross products), and compositing is a Python loop over the depth-sorted Gaussians
that writes the blending weight of every pair. Memory and time grow with pixels × Gaussians: meant
for scenes of tens of Gaussians and images of a few thousand pixels. It shares only the
projection (:func:`thgs.render.projection.project_torch`, tested against gsplat's pure-torch
projection) with the torch backend.
"""

from __future__ import annotations

import torch
from torch import Tensor

from thgs.render.config import RasterConfig
from thgs.render.outputs import LabelWeights, RenderOutput, SplatBackOutput
from thgs.render.projection import Projection, project_torch
from thgs.scene import Cameras, Gaussians

__all__ = ["ReferenceBackend", "dense_alpha", "dense_weights"]


def _alpha_of_pixels(projection: Projection, config: RasterConfig) -> Tensor:
    """α [P, N] at every pixel centre (P = H·W, row-major) for every Gaussian, capped, before the
    alpha_min test; 0 for invalid Gaussians."""
    height, width = projection.height, projection.width
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    pixels = torch.stack([xs.reshape(-1) + 0.5, ys.reshape(-1) + 0.5], dim=-1).double()
    d = pixels[:, None, :] - projection.alpha_centers[None, :, :]  # [P, N, 2]
    if projection.kind == "3dgs":
        a, b, c = projection.params[:, 0], projection.params[:, 1], projection.params[:, 2]
        sigma = 0.5 * (a * d[..., 0] ** 2 + c * d[..., 1] ** 2) + b * d[..., 0] * d[..., 1]
        alpha = projection.opacities * torch.exp(-sigma)
        alpha = torch.where(sigma < 0, torch.zeros_like(alpha), alpha)
    else:
        homography = projection.params.reshape(-1, 3, 3)
        homogeneous = torch.cat([pixels, torch.ones(len(pixels), 1, dtype=torch.float64)], dim=1)
        valid = projection.valid
        surfel = torch.zeros(len(pixels), len(valid), 3, dtype=torch.float64)
        surfel[:, valid] = torch.linalg.solve(
            homography[valid][None].expand(len(pixels), -1, -1, -1),
            homogeneous[:, None, :].expand(-1, int(valid.sum()), -1),
        )
        w = surfel[..., 2]
        rho3d = torch.where(
            w != 0, (surfel[..., 0] ** 2 + surfel[..., 1] ** 2) / w**2, torch.full_like(w, 1e300)
        )
        rho2d = config.filter_inv_square * (d**2).sum(-1)
        alpha = projection.opacities * torch.exp(-0.5 * torch.minimum(rho3d, rho2d))
    alpha = torch.clamp(alpha, max=config.alpha_max)
    return torch.where(projection.valid[None, :], alpha, torch.zeros_like(alpha))


def dense_alpha(
    gaussians: Gaussians, camera: Cameras, config: RasterConfig = RasterConfig()
) -> tuple[Tensor, Projection]:
    """α [H·W, N] float64 at every pixel centre (row-major) for every Gaussian, capped, before the
    alpha_min test (0 for Gaussians that cannot contribute), and the projection."""
    projection = project_torch(gaussians.to("cpu"), camera, config, torch.float64)
    return _alpha_of_pixels(projection, config), projection


def dense_weights(
    gaussians: Gaussians, camera: Cameras, config: RasterConfig = RasterConfig()
) -> tuple[Tensor, Projection]:
    """Blending weights ``w_k(x)`` [H, W, N] float64 of every pixel and Gaussian, and the
    projection; Gaussians are composited in order of depth, then index."""
    projection = project_torch(gaussians.to("cpu"), camera, config, torch.float64)
    alpha = _alpha_of_pixels(projection, config)
    n_pixels, n = alpha.shape
    order = sorted(range(n), key=lambda g: (float(projection.depths[g]), g))
    transmittance = torch.ones(n_pixels, dtype=torch.float64)
    done = torch.zeros(n_pixels, dtype=torch.bool)
    weights = torch.zeros(n_pixels, n, dtype=torch.float64)
    for g in order:
        if not bool(projection.valid[g]):
            continue
        a = alpha[:, g]
        used = ~done & (a >= config.alpha_min)
        after = transmittance * (1 - a)
        stop = used & (after <= config.transmittance_min)
        done |= stop
        used &= ~stop
        weights[used, g] = a[used] * transmittance[used]
        transmittance = torch.where(used, after, transmittance)
    return weights.reshape(projection.height, projection.width, n), projection


class ReferenceBackend:
    """The brute-force backend (CPU, float64; outputs moved to the Gaussians' device)."""

    name = "reference"

    def unusable(self, device: torch.device, dtype: torch.dtype) -> str | None:
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
        dtype: torch.dtype = torch.float64,
    ) -> RenderOutput:
        weights, projection = dense_weights(gaussians, camera, config)
        height, width, n = weights.shape
        flat = weights.reshape(-1, n)
        accumulated = flat.sum(1)
        depth = (flat * projection.depths[None, :]).sum(1)
        depth = torch.where(accumulated > 0, depth / accumulated.clamp_min(1e-300), 0.0)
        # the largest weight, the nearest Gaussian (in compositing order) on ties
        order = sorted(range(n), key=lambda g: (float(projection.depths[g]), g))
        order_t = torch.tensor(order, dtype=torch.int64)
        rank = torch.empty(n, dtype=torch.int64)
        rank[order_t] = torch.arange(n)
        best = flat.max(1).values if n else torch.zeros(len(flat), dtype=torch.float64)
        ranked = torch.where((flat == best[:, None]) & (flat > 0), rank[None, :], n)
        nearest = order_t[ranked.min(1).values.clamp(max=n - 1)] if n else best.long()
        max_id = torch.where(best > 0, nearest, -1)
        device, out_dtype = gaussians.device, features.dtype
        image = flat @ features.detach().cpu().double()
        return RenderOutput(
            image=image.reshape(height, width, -1).to(device=device, dtype=out_dtype),
            alpha=accumulated.reshape(height, width).to(device=device, dtype=out_dtype),
            depth=depth.reshape(height, width).to(device=device, dtype=out_dtype),
            max_id=max_id.reshape(height, width).to(device),
        )

    def splat_back(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        pixel_map: Tensor,
        mask: Tensor | None,
        config: RasterConfig,
        dtype: torch.dtype = torch.float64,
    ) -> SplatBackOutput:
        weights, projection = dense_weights(gaussians, camera, config)
        n = weights.shape[2]
        flat = weights.reshape(-1, n)
        keep = torch.ones(len(flat), dtype=torch.bool) if mask is None else mask.cpu().reshape(-1)
        kept = flat * keep[:, None]
        values = pixel_map.detach().cpu().double().reshape(len(flat), -1)
        device, out_dtype = gaussians.device, pixel_map.dtype
        return SplatBackOutput(
            feature_sums=(kept.T @ values).to(device=device, dtype=out_dtype),
            weight_sums=kept.sum(0).to(device=device, dtype=out_dtype),
            max_weights=kept.max(0).values.to(device=device, dtype=out_dtype),
            pixel_counts=(kept > 0).sum(0).to(device),
            depths=projection.depths.to(device=device, dtype=out_dtype),
            centers=projection.centers.to(device=device, dtype=out_dtype),
        )

    def label_weights(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        label_maps: Tensor,
        config: RasterConfig,
        dtype: torch.dtype = torch.float64,
    ) -> LabelWeights:
        weights, projection = dense_weights(gaussians, camera, config)
        maps = label_maps.cpu()
        rows: list[tuple[int, int, int, float]] = []
        for level in range(maps.shape[0]):
            for label in torch.unique(maps[level]).tolist():
                if label < 0:
                    continue
                sums = weights[maps[level] == label].sum(0)
                rows += [
                    (g, level, label, float(sums[g]))
                    for g in torch.nonzero(sums > 0)[:, 0].tolist()
                ]
        rows.sort()
        device = gaussians.device
        columns = list(zip(*rows)) if rows else [(), (), (), ()]
        return LabelWeights(
            gaussians=torch.tensor(columns[0], dtype=torch.int64, device=device),
            levels=torch.tensor(columns[1], dtype=torch.int64, device=device),
            labels=torch.tensor(columns[2], dtype=torch.int64, device=device),
            weights=torch.tensor(columns[3], dtype=torch.float64, device=device),
            weight_sums=weights.sum((0, 1)).to(device),
            max_weights=weights.amax((0, 1)).to(device),
            depths=projection.depths.to(device),
        )
