"""Rasterization of Gaussians into views and its adjoint, splat-back (design §4.1).

See docs/rendering.md for the formulas and conventions.
"""

from thgs.render.api import (
    LabelWeights,
    RenderOutput,
    SplatBackOutput,
    render,
    splat_back,
    splat_labels,
)
from thgs.render.config import RasterConfig
from thgs.render.projection import Projection, project

__all__ = [
    "LabelWeights",
    "Projection",
    "RasterConfig",
    "RenderOutput",
    "SplatBackOutput",
    "project",
    "render",
    "splat_back",
    "splat_labels",
]
