"""Rasterization settings shared by every backend."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from thgs.errors import InputError

__all__ = ["BackendName", "Precision", "RasterConfig"]

BackendName = Literal["auto", "numba", "torch", "gsplat"]
Precision = Literal["auto", "float64", "float32"]


@dataclass(frozen=True)
class RasterConfig:
    """How Gaussians are composited into a view (and splatted back), and by which backend.

    Defaults follow the 2DGS/3DGS CUDA code where it and gsplat differ in a parameter (near plane
    0.2, α cap 0.99); the formulas follow gsplat (see docs/rendering.md).

    Attributes:
        near: Gaussians whose centre is at camera depth ≤ ``near`` (scene units) are culled.
        far: … and those at depth ≥ ``far``.
        alpha_max: α is capped here (0.99 in 2DGS/3DGS; gsplat uses 0.999).
        alpha_min: contributions with α below this are skipped (1/255).
        transmittance_min: a pixel stops when the transmittance after a Gaussian would be ≤ this;
            that Gaussian is not composited (as in 3DGS and gsplat).
        eps2d: 3DGS low-pass, added to the projected 2D covariance (pixels²).
        filter_inv_square: 2DGS low-pass, ``ρ2d = filter_inv_square · |x − c|²`` in pixels (2.0:
            a 2D Gaussian of standard deviation 1/√2 px around the filter centre).
        tile_size: tile edge in pixels for binning Gaussians (numba and torch backends; gsplat
            uses its own 16); from 1 to 256.
        backend: who rasterizes (:mod:`thgs.render.backends`): ``"numba"`` (CPU, float64),
            ``"torch"`` (vectorized PyTorch on any device), ``"gsplat"`` (fused CUDA kernels;
            its α cap, α minimum, stop rule and 2DGS filter are fixed at 0.999, 1/255, 1e-4
            and 2), or ``"auto"``: gsplat on CUDA when it is installed, torch on other
            accelerators, numba on the CPU. How a result is computed, not what: it is not
            recorded in a field's config.
        precision: floating point of the computation: ``"float64"``, ``"float32"`` or
            ``"auto"`` (float64 on the CPU, float32 on accelerators; MPS has no float64). Not
            recorded in a field's config either.
    """

    near: float = 0.2
    far: float = 1e10
    alpha_max: float = 0.99
    alpha_min: float = 1.0 / 255.0
    transmittance_min: float = 1e-4
    eps2d: float = 0.3
    filter_inv_square: float = 2.0
    tile_size: int = 16
    backend: BackendName = "auto"
    precision: Precision = "auto"

    def __post_init__(self) -> None:
        if not 0 < self.near < self.far:
            raise InputError("RasterConfig", f"need 0 < near < far, got {self.near}, {self.far}")
        if not 0 < self.alpha_min < self.alpha_max <= 1:
            raise InputError(
                "RasterConfig",
                f"need 0 < alpha_min < alpha_max <= 1, got {self.alpha_min}, {self.alpha_max}",
            )
        if not 0 <= self.transmittance_min < 1:
            raise InputError(
                "RasterConfig", f"transmittance_min {self.transmittance_min} not in [0, 1)"
            )
        if self.eps2d < 0 or self.filter_inv_square <= 0 or not 1 <= self.tile_size <= 256:
            raise InputError(
                "RasterConfig", "need eps2d ≥ 0, filter_inv_square > 0, tile_size from 1 to 256"
            )
        if self.backend not in ("auto", "numba", "torch", "gsplat"):
            raise InputError(
                "RasterConfig",
                f"backend must be auto, numba, torch or gsplat, got {self.backend!r}",
            )
        if self.precision not in ("auto", "float64", "float32"):
            raise InputError(
                "RasterConfig",
                f"precision must be auto, float64 or float32, got {self.precision!r}",
            )
