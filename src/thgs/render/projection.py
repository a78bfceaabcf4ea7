"""Per-view projection of Gaussians: what the rasterizer needs to evaluate α at a pixel.

:func:`project_torch` is the projection in PyTorch, on the Gaussians' device in any floating dtype;
it is tested against gsplat's pure-torch projection, and the numba backend's compiled projection is
tested against it. Pixel coordinates are continuous, pixel (u, v) having its centre at
(u + 0.5, v + 0.5) (docs/conventions.md).

α of Gaussian k at pixel centre p, before the cap ``alpha_max``:

- 3DGS: ``o · exp(−σ)``, ``σ = ½ (A dx² + C dy²) + B dx dy`` with ``d = p − centre`` and
  ``(A, B, C)`` the inverse of the EWA-projected covariance plus ``eps2d · I`` (gsplat's
  projection, including its clamp of the Jacobian to 1.3× the field of view).
- 2DGS: ``o · exp(−½ min(ρ3d, ρ2d))``: ``ρ3d = u² + v²`` at the intersection (u, v) of the pixel's
  ray with the surfel plane, in units of the surfel's scales; ``ρ2d = filter_inv_square · |p − c|²``
  around the filter centre c, which is gsplat's: the centre of the projected 1σ ellipse.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from thgs.render.config import RasterConfig
from thgs.scene import Cameras, Gaussians
from thgs.scene.gaussians import quaternions_to_matrices

__all__ = ["Projection", "project_centers", "project_torch"]


@dataclass(frozen=True, eq=False)
class Projection:
    """The Gaussians as seen by one camera, in the backend's compute dtype.

    Attributes:
        kind: "2dgs" or "3dgs".
        width, height: image size in pixels.
        depths: [N] camera-space z of the centres (scene units; ≤ 0 behind the camera).
        centers: [N, 2] projected centres ``K · μ_cam / z`` in pixels (meaningless where z ≤ 0).
        alpha_centers: [N, 2] the point α is centred on: ``centers`` for 3DGS, the 2D filter
            centre for 2DGS.
        params: [N, 9] 3DGS: the conic (A, B, C) in columns 0–2; 2DGS: the homography
            ``H = K · [s₀ r₀, s₁ r₁, μ_cam]`` row-major, mapping surfel coordinates (u, v, 1) to
            homogeneous pixels.
        opacities: [N] activated opacities.
        valid: [N] near < z < far, a non-degenerate projection, and opacity ≥ alpha_min.
        bounds: [N, 4] int64 (x0, x1, y0, y1): inclusive pixel ranges outside which α < alpha_min
            (conservative by one pixel), clipped to the image; empty when x0 > x1 or y0 > y1.
    """

    kind: Literal["2dgs", "3dgs"]
    width: int
    height: int
    depths: Tensor
    centers: Tensor
    alpha_centers: Tensor
    params: Tensor
    opacities: Tensor
    valid: Tensor
    bounds: Tensor


def _pixel_bounds(center: Tensor, half: Tensor, size: int) -> tuple[Tensor, Tensor]:
    """Inclusive pixel index range whose centres lie within ``center ± half``, widened by one."""
    low = torch.ceil(center - half - 0.5) - 1
    high = torch.floor(center + half - 0.5) + 1
    low = torch.nan_to_num(low, nan=0.0, neginf=0.0, posinf=float(size))
    high = torch.nan_to_num(high, nan=-1.0, neginf=-1.0, posinf=float(size - 1))
    return low.clamp(0, size).long(), high.clamp(-1, size - 1).long()


def _union(
    low_a: Tensor, high_a: Tensor, empty_a: Tensor, low_b: Tensor, high_b: Tensor, empty_b: Tensor
) -> tuple[Tensor, Tensor]:
    """The smallest range holding two ranges, either of which may be empty."""
    low = torch.where(empty_a, low_b, torch.where(empty_b, low_a, torch.minimum(low_a, low_b)))
    high = torch.where(empty_a, high_b, torch.where(empty_b, high_a, torch.maximum(high_a, high_b)))
    return low, high


def _camera_means(
    gaussians: Gaussians, camera: Cameras, dtype: torch.dtype
) -> tuple[Tensor, Tensor]:
    """The centres in the camera frame [N, 3] (scene units) and the intrinsics [3, 3], in
    ``dtype`` on the Gaussians' device."""
    device = gaussians.device
    viewmat = camera.viewmats[0].to(device=device, dtype=dtype)
    K = camera.Ks[0].to(device=device, dtype=dtype)
    rotation, translation = viewmat[:3, :3], viewmat[:3, 3]
    return gaussians.means.to(dtype) @ rotation.T + translation, K


def _pinhole(means: Tensor, K: Tensor, in_range: Tensor) -> tuple[Tensor, Tensor]:
    """Projected centres [N, 2] in pixels of camera-frame points ``means`` [N, 3], and the
    depth they were divided by [N] (1 where ``in_range`` [N] is False)."""
    z = torch.where(in_range, means[:, 2], torch.ones_like(means[:, 2]))
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    return torch.stack([fx * means[:, 0] / z + cx, fy * means[:, 1] / z + cy], dim=-1), z


def project_centers(
    gaussians: Gaussians,
    camera: Cameras,
    config: RasterConfig = RasterConfig(),
    dtype: torch.dtype = torch.float64,
) -> tuple[Tensor, Tensor]:
    """The depths and projected centres of :func:`project_torch`, without the covariances.

    Returns:
        ``(depths, centers)``: [N] camera-space z of the centres (scene units) and [N, 2] their
        pixel coordinates, exactly :attr:`Projection.depths` and :attr:`Projection.centers`.
    """
    means, K = _camera_means(gaussians, camera, dtype)
    depths = means[:, 2]
    centers, _ = _pinhole(means, K, (depths > config.near) & (depths < config.far))
    return depths, centers


def project_torch(
    gaussians: Gaussians,
    camera: Cameras,
    config: RasterConfig = RasterConfig(),
    dtype: torch.dtype = torch.float64,
) -> Projection:
    """Project ``gaussians`` into the single camera ``camera`` (a :class:`Cameras` of length 1),
    computing in ``dtype`` on the Gaussians' device.

    Returns:
        a :class:`Projection`; Gaussians that cannot contribute are marked invalid with empty
        bounds.
    """
    device = gaussians.device
    width, height = int(camera.widths[0]), int(camera.heights[0])
    means, K = _camera_means(gaussians, camera, dtype)
    depths = means[:, 2]
    opacities = torch.sigmoid(gaussians.opacities.to(dtype))
    in_range = (depths > config.near) & (depths < config.far)
    centers, z = _pinhole(means, K, in_range)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    rotation = camera.viewmats[0, :3, :3].to(device=device, dtype=dtype)
    axes = rotation @ quaternions_to_matrices(gaussians.quats.to(dtype))  # local axes, camera frame
    scales = torch.exp(gaussians.scales.to(dtype))
    log_ratio = torch.log(opacities / config.alpha_min)
    visible = log_ratio >= 0
    k_squared = (2 * log_ratio).clamp_min(1e-12)  # α ≥ alpha_min ⟺ Mahalanobis² ≤ k²

    if gaussians.kind == "3dgs":
        scaled = axes * scales[:, None, :]
        cov = scaled @ scaled.transpose(1, 2)
        lim_x = (width - cx) / fx + 0.3 * (0.5 * width / fx), cx / fx + 0.3 * (0.5 * width / fx)
        lim_y = (height - cy) / fy + 0.3 * (0.5 * height / fy), cy / fy + 0.3 * (0.5 * height / fy)
        tx = z * torch.clamp(means[:, 0] / z, min=-lim_x[1], max=lim_x[0])
        ty = z * torch.clamp(means[:, 1] / z, min=-lim_y[1], max=lim_y[0])
        zeros = torch.zeros_like(z)
        jacobian = torch.stack(
            [fx / z, zeros, -fx * tx / z**2, zeros, fy / z, -fy * ty / z**2], dim=-1
        ).reshape(-1, 2, 3)
        cov2d = jacobian @ cov @ jacobian.transpose(1, 2)
        a = cov2d[:, 0, 0] + config.eps2d
        b = cov2d[:, 0, 1]
        c = cov2d[:, 1, 1] + config.eps2d
        det = a * c - b * b
        valid = in_range & visible & (det > 0)
        det = torch.where(valid, det, torch.ones_like(det))
        params = torch.zeros(len(gaussians), 9, dtype=dtype, device=device)
        params[:, 0], params[:, 1], params[:, 2] = c / det, -b / det, a / det
        alpha_centers = centers
        half_x, half_y = torch.sqrt(k_squared * a), torch.sqrt(k_squared * c)
        x0, x1 = _pixel_bounds(centers[:, 0], half_x, width)
        y0, y1 = _pixel_bounds(centers[:, 1], half_y, height)
    else:
        columns = torch.stack(
            [axes[:, :, 0] * scales[:, 0:1], axes[:, :, 1] * scales[:, 1:2], means], dim=-1
        )
        homography = K @ columns  # [N, 3, 3]
        h = homography
        d = h[:, 2, 0] ** 2 + h[:, 2, 1] ** 2 - h[:, 2, 2] ** 2
        valid = in_range & visible & (d != 0)
        d = torch.where(valid, d, torch.ones_like(d))
        filter_x = (h[:, 0, 0] * h[:, 2, 0] + h[:, 0, 1] * h[:, 2, 1] - h[:, 0, 2] * h[:, 2, 2]) / d
        filter_y = (h[:, 1, 0] * h[:, 2, 0] + h[:, 1, 1] * h[:, 2, 1] - h[:, 1, 2] * h[:, 2, 2]) / d
        alpha_centers = torch.stack([filter_x, filter_y], dim=-1)
        params = homography.reshape(-1, 9)
        # Bounding box of the image of the ellipse u² + v² ≤ k² from the dual conic
        # C* = H diag(1, 1, −1/k²) Hᵀ; bounded (entirely in front of the camera) iff C*₂₂ < 0.
        inv_k2 = 1 / k_squared

        def dual(i: int, j: int) -> Tensor:
            return (
                h[:, i, 0] * h[:, j, 0] + h[:, i, 1] * h[:, j, 1] - h[:, i, 2] * h[:, j, 2] * inv_k2
            )

        dual_22, dual_02, dual_12 = dual(2, 2), dual(0, 2), dual(1, 2)
        bounded = dual_22 < 0
        safe = torch.where(bounded, dual_22, -torch.ones_like(d))
        ellipse_x, ellipse_y = dual_02 / safe, dual_12 / safe
        half_x = torch.sqrt((dual_02**2 - dual(0, 0) * safe).clamp_min(0)) / safe.abs()
        half_y = torch.sqrt((dual_12**2 - dual(1, 1) * safe).clamp_min(0)) / safe.abs()
        infinite = torch.full_like(half_x, math.inf)
        half_x = torch.where(bounded, half_x, infinite)
        half_y = torch.where(bounded, half_y, infinite)
        ex0, ex1 = _pixel_bounds(ellipse_x, half_x, width)
        ey0, ey1 = _pixel_bounds(ellipse_y, half_y, height)
        radius = torch.sqrt(k_squared / config.filter_inv_square)
        fx0, fx1 = _pixel_bounds(filter_x, radius, width)
        fy0, fy1 = _pixel_bounds(filter_y, radius, height)
        ellipse_empty = (ex0 > ex1) | (ey0 > ey1)
        filter_empty = (fx0 > fx1) | (fy0 > fy1)
        x0, x1 = _union(ex0, ex1, ellipse_empty, fx0, fx1, filter_empty)
        y0, y1 = _union(ey0, ey1, ellipse_empty, fy0, fy1, filter_empty)

    bounds = torch.stack([x0, x1, y0, y1], dim=-1)
    bounds[~valid] = torch.tensor([0, -1, 0, -1], device=device)
    return Projection(
        kind=gaussians.kind,
        width=width,
        height=height,
        depths=depths,
        centers=centers,
        alpha_centers=alpha_centers,
        params=params,
        opacities=opacities,
        valid=valid,
        bounds=bounds,
    )
