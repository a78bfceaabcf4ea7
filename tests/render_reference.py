"""Brute-force rasterizer for tests: every pixel, every Gaussian, sorted by depth.

Independent of the CPU backend except for the projection (tested on its own against gsplat's
pure-torch projection and by hand): α is evaluated densely for all (pixel, Gaussian) pairs, the
2DGS ray–surfel intersection by solving the homography instead of the backend's cross products,
and compositing is a Python loop over the depth-sorted Gaussians.
"""

from __future__ import annotations

import torch

from thgs.render import RasterConfig, project


def dense_alpha(gaussians, camera, config: RasterConfig):
    """α [P, N] at every pixel centre (P = H·W, row-major) for every Gaussian, before alpha_min."""
    projection = project(gaussians, camera, config)
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
    return torch.where(projection.valid[None, :], alpha, torch.zeros_like(alpha)), projection


def brute_force(gaussians, camera, config: RasterConfig, features=None, pixel_map=None, mask=None):
    """Forward outputs and splat-back sums, as plain float64 tensors in a dict."""
    alpha, projection = dense_alpha(gaussians, camera, config)
    n_pixels, n = alpha.shape
    height, width = projection.height, projection.width
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
    out = {"weights": weights.reshape(height, width, n)}
    acc = weights.sum(1)
    out["alpha"] = acc.reshape(height, width)
    depth = (weights * projection.depths[None, :]).sum(1)
    out["depth"] = torch.where(acc > 0, depth / acc.clamp_min(1e-300), 0.0).reshape(height, width)
    # the largest weight, the nearest Gaussian on ties
    order_t = torch.tensor(order)
    rank = torch.empty(n, dtype=torch.long)
    rank[order_t] = torch.arange(n)
    best = weights.max(1).values
    ranked = torch.where((weights == best[:, None]) & (weights > 0), rank[None, :], n)
    nearest = order_t[ranked.min(1).values.clamp(max=n - 1)]
    out["max_id"] = torch.where(best > 0, nearest, -1).reshape(height, width)
    if features is not None:
        out["image"] = (weights @ features.double()).reshape(height, width, -1)
    if pixel_map is not None:
        flat = pixel_map.double().reshape(n_pixels, -1)
        keep = torch.ones(n_pixels, dtype=torch.bool) if mask is None else mask.reshape(-1)
        kept = weights * keep[:, None]
        out["feature_sums"] = kept.T @ flat
        out["weight_sums"] = kept.sum(0)
        out["max_weights"] = kept.max(0).values
        out["pixel_counts"] = (kept > 0).sum(0)
    out["projection"] = projection
    return out
