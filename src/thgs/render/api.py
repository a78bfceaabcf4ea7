"""Public rasterization API: render per-Gaussian features into a view, splat pixel maps back."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from thgs.errors import InputError
from thgs.render._cpu import label_weights_cpu, render_cpu, splat_back_cpu
from thgs.render.config import RasterConfig
from thgs.render.projection import project
from thgs.scene import Cameras, Gaussians

__all__ = [
    "LabelWeights",
    "RenderOutput",
    "SplatBackOutput",
    "render",
    "splat_back",
    "splat_labels",
]


@dataclass(frozen=True, eq=False)
class RenderOutput:
    """One rendered view. With ``w_k(x) = α_k(x) · T_k(x)`` the blending weight of Gaussian k.

    Attributes:
        image: [H, W, C] ``Σ_k w_k(x) · features[k]``, in the features' dtype.
        alpha: [H, W] accumulated opacity ``Σ_k w_k(x)`` in [0, 1].
        depth: [H, W] ``Σ_k w_k z_k / Σ_k w_k`` with z_k the camera-space depth of Gaussian k's
            centre (for 2DGS too, not the ray–surfel intersection); 0 where alpha is 0.
        max_id: [H, W] int64 index of the Gaussian with the largest ``w_k(x)`` (the nearest on
            ties), −1 where no Gaussian contributes.
    """

    image: Tensor
    alpha: Tensor
    depth: Tensor
    max_id: Tensor


@dataclass(frozen=True, eq=False)
class SplatBackOutput:
    """Per-Gaussian sums of a pixel map over the pixels each Gaussian contributes to.

    Only pixels inside the mask are summed; all pixels still composite (occlusion is unchanged).

    Attributes:
        feature_sums: [N, C] ``Σ_x w_k(x) · F(x)``.
        weight_sums: [N] ``Σ_x w_k(x)``.
        max_weights: [N] ``max_x w_k(x)`` (0 where the Gaussian contributes to no pixel).
        pixel_counts: [N] int64 number of pixels with ``w_k(x) > 0``.
        depths: [N] camera-space z of each centre (scene units; ≤ 0 behind the camera).
        centers: [N, 2] projected centres in pixels (pixel (u, v) is centred at (u+0.5, v+0.5));
            meaningless where depth ≤ 0.
    """

    feature_sums: Tensor
    weight_sums: Tensor
    max_weights: Tensor
    pixel_counts: Tensor
    depths: Tensor
    centers: Tensor


@dataclass(frozen=True, eq=False)
class LabelWeights:
    """How much of each Gaussian's blending weight falls on each label of a label map.

    Sparse: one row per (Gaussian, level, label) with a positive weight, sorted by Gaussian, then
    level, then label.

    Attributes:
        gaussians: [P] int64 Gaussian index.
        levels: [P] int64 level (first axis of the label maps).
        labels: [P] int64 label.
        weights: [P] float64 ``Σ_{x: label_level(x) = label} w_g(x)``.
        weight_sums: [N] float64 ``Σ_x w_g(x)`` over all pixels, labelled or not.
        max_weights: [N] float64 ``max_x w_g(x)``.
        depths: [N] float64 camera-space z of each centre (scene units).
    """

    gaussians: np.ndarray
    levels: np.ndarray
    labels: np.ndarray
    weights: np.ndarray
    weight_sums: np.ndarray
    max_weights: np.ndarray
    depths: np.ndarray


def _one_camera(camera: Cameras) -> tuple[int, int]:
    if len(camera) != 1:
        raise InputError(
            "camera", f"expected one camera (use cameras.select([i])), got {len(camera)}"
        )
    camera.check(source="camera")
    return int(camera.heights[0]), int(camera.widths[0])


def _check_values(name: str, tensor: Tensor, device: torch.device) -> None:
    if tensor.device != device:
        raise InputError(name, f"is on {tensor.device} but the Gaussians are on {device}")
    if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
        raise InputError(name, "has NaN or infinite values")


def render(
    gaussians: Gaussians,
    camera: Cameras,
    features: Tensor,
    *,
    config: RasterConfig = RasterConfig(),
) -> RenderOutput:
    """Composite per-Gaussian ``features`` front to back into ``camera``'s view.

    Args:
        gaussians: N Gaussians (2DGS or 3DGS), world frame.
        camera: one camera (``cameras.select([i])``); the image is ``heights[0] × widths[0]``.
        features: [N, C] float values to render (colours, codes, a one-hot selection …), on the
            Gaussians' device.
        config: rasterization settings.

    Returns:
        a :class:`RenderOutput` on the Gaussians' device.

    Raises:
        InputError: a camera count other than one, an invalid camera, features of the wrong shape,
            device or with non-finite values.
    """
    _one_camera(camera)
    gaussians.check()
    if features.ndim != 2 or features.shape[0] != len(gaussians):
        raise InputError(
            "features", f"must be [N, C] with N = {len(gaussians)}, got {list(features.shape)}"
        )
    if not features.is_floating_point():
        raise InputError("features", f"must be floating point, got {features.dtype}")
    _check_values("features", features, gaussians.device)
    projection = project(gaussians, camera, config)
    image, alpha, depth, max_id = render_cpu(
        projection, features.detach().cpu().double().numpy(), config
    )
    device = gaussians.device
    return RenderOutput(
        image=torch.from_numpy(image).to(device=device, dtype=features.dtype),
        alpha=torch.from_numpy(alpha).to(device=device, dtype=features.dtype),
        depth=torch.from_numpy(depth).to(device=device, dtype=features.dtype),
        max_id=torch.from_numpy(max_id).to(device),
    )


def splat_back(
    gaussians: Gaussians,
    camera: Cameras,
    pixel_map: Tensor,
    *,
    mask: Tensor | None = None,
    config: RasterConfig = RasterConfig(),
) -> SplatBackOutput:
    """Splat a pixel map back onto the Gaussians, weighted by their blending weights.

    This is the adjoint of :func:`render`:
    ``<render(f).image, F> = <f, splat_back(F).feature_sums>``.

    Args:
        gaussians: N Gaussians, world frame.
        camera: one camera; ``pixel_map`` must match its size.
        pixel_map: [H, W, C] float values per pixel (row y, column x).
        mask: optional [H, W] bool; pixels outside it add nothing to the sums.
        config: rasterization settings.

    Returns:
        a :class:`SplatBackOutput` on the Gaussians' device, sums in the pixel map's dtype.

    Raises:
        InputError: a camera count other than one, an invalid camera, a pixel map or mask of the
            wrong shape, dtype or device, non-finite values.
    """
    height, width = _one_camera(camera)
    gaussians.check()
    if pixel_map.ndim != 3 or tuple(pixel_map.shape[:2]) != (height, width):
        raise InputError(
            "pixel_map",
            f"must be [H, W, C] = [{height}, {width}, C] for this camera, "
            f"got {list(pixel_map.shape)}",
        )
    if not pixel_map.is_floating_point():
        raise InputError("pixel_map", f"must be floating point, got {pixel_map.dtype}")
    _check_values("pixel_map", pixel_map, gaussians.device)
    if mask is None:
        mask_np = np.ones((height, width), dtype=np.bool_)
    else:
        if tuple(mask.shape) != (height, width) or mask.dtype != torch.bool:
            raise InputError(
                "mask",
                f"must be a bool [{height}, {width}] tensor, got {mask.dtype} {list(mask.shape)}",
            )
        _check_values("mask", mask, gaussians.device)
        mask_np = mask.cpu().numpy()
    projection = project(gaussians, camera, config)
    feature_sums, weight_sums, max_weights, pixel_counts = splat_back_cpu(
        projection, pixel_map.detach().cpu().double().numpy(), mask_np, config
    )
    device, dtype = gaussians.device, pixel_map.dtype
    return SplatBackOutput(
        feature_sums=torch.from_numpy(feature_sums).to(device=device, dtype=dtype),
        weight_sums=torch.from_numpy(weight_sums).to(device=device, dtype=dtype),
        max_weights=torch.from_numpy(max_weights).to(device=device, dtype=dtype),
        pixel_counts=torch.from_numpy(pixel_counts).to(device),
        depths=projection.depths.to(dtype),
        centers=projection.centers.to(dtype),
    )


def splat_labels(
    gaussians: Gaussians,
    camera: Cameras,
    label_maps: np.ndarray,
    *,
    config: RasterConfig = RasterConfig(),
) -> LabelWeights:
    """Accumulate each Gaussian's blending weight per label of integer label maps.

    The exact counterpart of splatting one-hot maps back (``splat_back`` with one channel per
    label) without materialising the channels: only the (Gaussian, level, label) triples that
    occur are stored.

    Args:
        gaussians: N Gaussians, world frame.
        camera: one camera; the maps must match its size.
        label_maps: [L, H, W] integer labels ≥ −1 (−1 = no label) for L levels.
        config: rasterization settings.

    Raises:
        InputError: a camera count other than one, maps of the wrong shape or type.
    """
    height, width = _one_camera(camera)
    gaussians.check()
    label_maps = np.asarray(label_maps)
    if label_maps.ndim != 3 or label_maps.shape[1:] != (height, width):
        raise InputError(
            "label_maps",
            f"must be [L, {height}, {width}] for this camera, got {list(label_maps.shape)}",
        )
    if not np.issubdtype(label_maps.dtype, np.integer) or (
        label_maps.size and label_maps.min() < -1
    ):
        raise InputError("label_maps", "must be integers ≥ −1")
    projection = project(gaussians, camera, config)
    keys, values, weight_sums, max_weights = label_weights_cpu(projection, label_maps, config)
    count = max(int(label_maps.max()) + 1, 1) if label_maps.size else 1
    order = np.argsort(keys, kind="stable")
    keys, values = keys[order], values[order]
    levels = label_maps.shape[0]
    return LabelWeights(
        gaussians=keys // (count * levels),
        levels=(keys // count) % levels,
        labels=keys % count,
        weights=values,
        weight_sums=weight_sums,
        max_weights=max_weights,
        depths=projection.depths.cpu().double().numpy(),
    )
