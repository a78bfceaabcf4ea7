"""Public rasterization API: project, render, splat back and weigh labels, through a backend.

Each function checks its inputs (one camera, tensors of the right shape on the Gaussians' device,
finite values), resolves ``config.backend`` for the Gaussians' device
(:func:`thgs.render.backends.resolve_backend`) and returns torch tensors on that device.
"""

from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import torch
from torch import Tensor

from thgs.errors import InputError
from thgs.render.backends import resolve_backend
from thgs.render.config import RasterConfig
from thgs.render.outputs import LabelWeights, RenderOutput, SplatBackOutput
from thgs.render.projection import Projection
from thgs.scene import Cameras, Gaussians

__all__ = ["project", "render", "splat_back", "splat_labels"]


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


@contextmanager
def _device_memory(device: torch.device, gaussians: Gaussians, height: int, width: int):
    """An out-of-memory error of the device as an :class:`InputError` that says what ran out."""
    try:
        yield
    except torch.OutOfMemoryError as error:
        raise InputError(
            str(device),
            f"out of memory rasterizing {len(gaussians):,} Gaussians at {width}×{height} "
            f"({str(error).splitlines()[0]}); free memory on the device, or render on another "
            "one (--device cpu)",
        ) from error
    except RuntimeError as error:  # MPS reports running out of memory as a RuntimeError
        if "out of memory" not in str(error):
            raise
        raise InputError(
            str(device),
            f"out of memory rasterizing {len(gaussians):,} Gaussians at {width}×{height}; free "
            "memory on the device, or render on another one (--device cpu)",
        ) from error


def project(
    gaussians: Gaussians, camera: Cameras, config: RasterConfig = RasterConfig()
) -> Projection:
    """Project ``gaussians`` into one camera (``cameras.select([i])``) with the configured
    backend, in its compute dtype.

    Returns:
        a :class:`thgs.render.Projection` on the Gaussians' device; Gaussians that cannot
        contribute are marked invalid with empty bounds.
    """
    height, width = _one_camera(camera)
    gaussians.check()
    backend, dtype = resolve_backend(config, gaussians.device)
    with _device_memory(gaussians.device, gaussians, height, width):
        return backend.project(gaussians, camera, config, dtype)


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
        config: rasterization settings and backend.

    Returns:
        a :class:`RenderOutput` on the Gaussians' device, values in the features' dtype.

    Raises:
        InputError: a camera count other than one, an invalid camera, features of the wrong shape,
            device or with non-finite values, a backend that cannot run on the device, the
            device running out of memory.
    """
    height, width = _one_camera(camera)
    gaussians.check()
    if features.ndim != 2 or features.shape[0] != len(gaussians):
        raise InputError(
            "features", f"must be [N, C] with N = {len(gaussians)}, got {list(features.shape)}"
        )
    if not features.is_floating_point():
        raise InputError("features", f"must be floating point, got {features.dtype}")
    _check_values("features", features, gaussians.device)
    backend, dtype = resolve_backend(config, gaussians.device)
    with _device_memory(gaussians.device, gaussians, height, width):
        return backend.render(gaussians, camera, features.detach(), config, dtype)


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
        config: rasterization settings and backend.

    Returns:
        a :class:`SplatBackOutput` on the Gaussians' device, sums in the pixel map's dtype.

    Raises:
        InputError: a camera count other than one, an invalid camera, a pixel map or mask of the
            wrong shape, dtype or device, non-finite values, a backend that cannot run here.
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
    if mask is not None:
        if tuple(mask.shape) != (height, width) or mask.dtype != torch.bool:
            raise InputError(
                "mask",
                f"must be a bool [{height}, {width}] tensor, got {mask.dtype} {list(mask.shape)}",
            )
        _check_values("mask", mask, gaussians.device)
    backend, dtype = resolve_backend(config, gaussians.device)
    with _device_memory(gaussians.device, gaussians, height, width):
        return backend.splat_back(gaussians, camera, pixel_map.detach(), mask, config, dtype)


def splat_labels(
    gaussians: Gaussians,
    camera: Cameras,
    label_maps: Tensor | np.ndarray,
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
        label_maps: [L, H, W] integer labels ≥ −1 (−1 = no label) for L levels; a tensor on the
            Gaussians' device, or a NumPy array (moved there).
        config: rasterization settings and backend.

    Returns:
        a :class:`LabelWeights` on the Gaussians' device.

    Raises:
        InputError: a camera count other than one, maps of the wrong shape, type or device, a
            backend that cannot run here.
    """
    height, width = _one_camera(camera)
    gaussians.check()
    if isinstance(label_maps, np.ndarray):
        if not np.issubdtype(label_maps.dtype, np.integer):
            raise InputError("label_maps", f"must be integers ≥ −1, got {label_maps.dtype}")
        label_maps = torch.from_numpy(label_maps.astype(np.int64)).to(gaussians.device)
    if label_maps.ndim != 3 or tuple(label_maps.shape[1:]) != (height, width):
        raise InputError(
            "label_maps",
            f"must be [L, {height}, {width}] for this camera, got {list(label_maps.shape)}",
        )
    if label_maps.is_floating_point() or label_maps.dtype == torch.bool:
        raise InputError("label_maps", f"must be integers ≥ −1, got {label_maps.dtype}")
    _check_values("label_maps", label_maps, gaussians.device)
    label_maps = label_maps.long()
    if label_maps.numel() and int(label_maps.min()) < -1:
        raise InputError("label_maps", f"must be integers ≥ −1, got {int(label_maps.min())}")
    backend, dtype = resolve_backend(config, gaussians.device)
    with _device_memory(gaussians.device, gaussians, height, width):
        return backend.label_weights(gaussians, camera, label_maps, config, dtype)
