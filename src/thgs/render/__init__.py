"""Rasterization of Gaussians into views and its adjoint, splat-back (design §4.1).

See docs/rendering.md for the formulas and conventions.
"""

from thgs.render.api import RenderOutput, SplatBackOutput, render, splat_back
from thgs.render.config import RasterConfig
from thgs.render.projection import Projection, project

__all__ = [
    "Projection",
    "RasterConfig",
    "RenderOutput",
    "SplatBackOutput",
    "project",
    "render",
    "splat_back",
]
