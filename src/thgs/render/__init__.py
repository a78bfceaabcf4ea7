"""Rasterization of Gaussians into views and its adjoint, splat-back (design §4.1).

The functions here check their inputs and dispatch to a backend chosen by
``RasterConfig.backend`` (:mod:`thgs.render.backends`): numba on the CPU, vectorized torch on any
device, gsplat on CUDA. See docs/rendering.md for the formulas, conventions and measurements.
"""

from thgs.render.api import project, render, splat_back, splat_labels
from thgs.render.backends import (
    BACKENDS,
    RasterBackend,
    available_backends,
    compute_dtype,
    get_backend,
    resolve_backend,
)
from thgs.render.config import RasterConfig
from thgs.render.outputs import LabelWeights, RenderOutput, SplatBackOutput
from thgs.render.projection import Projection

__all__ = [
    "BACKENDS",
    "LabelWeights",
    "Projection",
    "RasterBackend",
    "RasterConfig",
    "RenderOutput",
    "SplatBackOutput",
    "available_backends",
    "compute_dtype",
    "get_backend",
    "project",
    "render",
    "resolve_backend",
    "splat_back",
    "splat_labels",
]
