"""Rendering backends behind one seam (docs/rendering.md).

A backend turns Gaussians and one camera into the outputs of :mod:`thgs.render.outputs`:
``project``, ``render``, ``splat_back`` and ``label_weights``, each with the same meaning and, up
to rounding, the same values whichever backend computed them. :mod:`thgs.render.api` checks the
inputs and dispatches; backends trust what they are given.

- ``numba``: CPU, float64; tiles, a depth sort and compiled per-pixel loops.
- ``torch``: any torch device, float64 on the CPU and float32 on accelerators; vectorized
  PyTorch, memory bounded by processing tiles in chunks.
- ``gsplat``: CUDA, float32; gsplat's fused kernels (``pip install thgs[gpu]``).

The brute-force reference every backend is tested against is :class:`thgs.render._reference.
ReferenceBackend` (every pixel against every Gaussian; tiny scenes only).
"""

from __future__ import annotations

import importlib.util
import logging
from typing import Protocol

import torch
from torch import Tensor

from thgs.errors import InputError
from thgs.render.config import RasterConfig
from thgs.render.outputs import LabelWeights, RenderOutput, SplatBackOutput
from thgs.render.projection import Projection
from thgs.scene import Cameras, Gaussians

__all__ = [
    "BACKENDS",
    "RasterBackend",
    "available_backends",
    "compute_dtype",
    "get_backend",
    "resolve_backend",
]

logger = logging.getLogger(__name__)

BACKENDS = ("numba", "torch", "gsplat")
"""Every backend name ``RasterConfig.backend`` accepts besides ``"auto"``."""


class RasterBackend(Protocol):
    """What a rendering backend implements. Inputs are checked by :mod:`thgs.render.api`: one
    camera, tensors on the Gaussians' device with the right shapes and finite values; ``dtype``
    is the compute dtype (:func:`compute_dtype`). Outputs are on the Gaussians' device."""

    name: str

    def unusable(self, device: torch.device, dtype: torch.dtype) -> str | None:
        """Why this backend cannot compute on ``device`` in ``dtype``; None when it can."""
        ...

    def project(
        self, gaussians: Gaussians, camera: Cameras, config: RasterConfig, dtype: torch.dtype
    ) -> Projection:
        """The Gaussians as the camera sees them, in ``dtype``."""
        ...

    def render(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        features: Tensor,
        config: RasterConfig,
        dtype: torch.dtype,
    ) -> RenderOutput:
        """``features`` [N, C] composited front to back into the camera's [H, W] image."""
        ...

    def splat_back(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        pixel_map: Tensor,
        mask: Tensor | None,
        config: RasterConfig,
        dtype: torch.dtype,
    ) -> SplatBackOutput:
        """``pixel_map`` [H, W, C] summed back onto the Gaussians (pixels where ``mask`` [H, W]
        is True, or all)."""
        ...

    def label_weights(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        label_maps: Tensor,
        config: RasterConfig,
        dtype: torch.dtype,
    ) -> LabelWeights:
        """Each Gaussian's blending weight per label of ``label_maps`` [L, H, W] int64 (≥ −1)."""
        ...


def compute_dtype(config: RasterConfig, device: torch.device) -> torch.dtype:
    """The floating dtype rasterization computes in on ``device``.

    Raises:
        InputError: float64 asked for on MPS, which has no float64.
    """
    if config.precision == "float32":
        return torch.float32
    if config.precision == "float64":
        if device.type == "mps":
            raise InputError(
                "RasterConfig.precision", "MPS has no float64: use precision 'float32' or 'auto'"
            )
        return torch.float64
    return torch.float64 if device.type == "cpu" else torch.float32


def _installed(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


def available_backends() -> tuple[str, ...]:
    """The backends whose libraries are installed (whether the device suits them is checked when
    one is chosen)."""
    return tuple(name for name in BACKENDS if name != "gsplat" or _installed("gsplat"))


def get_backend(name: str) -> RasterBackend:
    """The backend called ``name`` (one of :data:`BACKENDS`).

    Raises:
        InputError: an unknown name, or gsplat when it is not installed.
    """
    if name == "numba":
        from thgs.render._numba import NumbaBackend

        return NumbaBackend()
    if name == "torch":
        from thgs.render._torch import TorchBackend

        return TorchBackend()
    if name == "gsplat":
        if not _installed("gsplat"):
            raise InputError(
                "RasterConfig.backend",
                "gsplat is not installed: pip install 'thgs[gpu]' (it needs a CUDA GPU)",
            )
        from thgs.render._gsplat import GsplatBackend

        return GsplatBackend()
    raise InputError(
        "RasterConfig.backend", f"unknown backend {name!r}; choose auto or one of {BACKENDS}"
    )


def _auto_name(device: torch.device) -> str:
    if device.type == "cpu":
        return "numba"
    if device.type == "cuda" and _installed("gsplat"):
        return "gsplat"
    return "torch"


def resolve_backend(
    config: RasterConfig, device: torch.device
) -> tuple[RasterBackend, torch.dtype]:
    """The backend and compute dtype that rasterize on ``device`` under ``config``.

    ``"auto"`` takes gsplat on CUDA when it is installed, torch on other accelerators (and on
    CUDA without gsplat, which is logged), numba on the CPU.

    Raises:
        InputError: a backend that is not installed or cannot run on ``device`` (numba off the
            CPU, gsplat without CUDA), or a precision the device or backend lacks.
    """
    device = torch.device(device)
    dtype = compute_dtype(config, device)
    name = config.backend
    if name == "auto":
        name = _auto_name(device)
        if device.type == "cuda" and name == "torch":
            logger.info("gsplat is not installed: rendering on %s with the torch backend", device)
    backend = get_backend(name)
    reason = backend.unusable(device, dtype)
    if reason is not None:
        raise InputError("RasterConfig.backend", f"{name} cannot render on {device}: {reason}")
    return backend, dtype
