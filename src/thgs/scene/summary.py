"""Numbers that describe a scene at a glance (what ``thgs info`` prints)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from thgs.scene.loader import Scene

__all__ = ["CameraSummary", "SceneSummary", "summarize"]


@dataclass(frozen=True)
class CameraSummary:
    """The cameras of a scene: count, image sizes and focal lengths (pixels)."""

    count: int
    width_range: tuple[int, int]
    height_range: tuple[int, int]
    focal_range: tuple[float, float]
    source: str


@dataclass(frozen=True)
class SceneSummary:
    """A scene at a glance. Lengths are in scene units, opacities in [0, 1].

    Attributes:
        count: number of Gaussians.
        kind: "2dgs" or "3dgs".
        sh_degree: 0–3.
        has_normals: whether the PLY stored nx, ny, nz.
        extra_properties: names of non-standard PLY properties carried along.
        bbox_min, bbox_max: axis-aligned bounds of the centres (world frame).
        bbox_1_99: the 1st and 99th percentiles of the centres per axis (floaters excluded).
        opacity_quantiles: opacity at quantiles 0, 0.25, 0.5, 0.75, 1.
        opacity_mean: mean opacity.
        low_opacity_share: share of Gaussians with opacity < 0.1.
        scale_median: median of the largest activated scale per Gaussian.
        cameras: camera summary, or None.
    """

    count: int
    kind: str
    sh_degree: int
    has_normals: bool
    extra_properties: tuple[str, ...]
    bbox_min: tuple[float, float, float]
    bbox_max: tuple[float, float, float]
    bbox_1_99: tuple[tuple[float, float, float], tuple[float, float, float]]
    opacity_quantiles: tuple[float, ...]
    opacity_mean: float
    low_opacity_share: float
    scale_median: float
    cameras: CameraSummary | None


def _triple(values: np.ndarray) -> tuple[float, float, float]:
    return (float(values[0]), float(values[1]), float(values[2]))


def summarize(scene: Scene) -> SceneSummary:
    """Summary statistics of ``scene`` (float64; quantiles interpolate linearly, as NumPy's)."""
    gaussians = scene.gaussians
    means = gaussians.means.detach().cpu().double().numpy()
    opacities = gaussians.activated_opacities().detach().cpu().double().numpy()
    largest_scales = gaussians.activated_scales().detach().cpu().double().numpy().max(axis=-1)
    cameras = None
    if scene.cameras is not None:
        Ks = scene.cameras.Ks.numpy()
        focals = np.concatenate([Ks[:, 0, 0], Ks[:, 1, 1]])
        cameras = CameraSummary(
            count=len(scene.cameras),
            width_range=(int(scene.cameras.widths.min()), int(scene.cameras.widths.max())),
            height_range=(int(scene.cameras.heights.min()), int(scene.cameras.heights.max())),
            focal_range=(float(focals.min()), float(focals.max())),
            source=str(scene.cameras_path),
        )
    return SceneSummary(
        count=len(gaussians),
        kind=gaussians.kind,
        sh_degree=gaussians.sh_degree,
        has_normals=gaussians.normals is not None,
        extra_properties=tuple(gaussians.extras),
        bbox_min=_triple(means.min(axis=0)),
        bbox_max=_triple(means.max(axis=0)),
        bbox_1_99=(
            _triple(np.quantile(means, 0.01, axis=0)),
            _triple(np.quantile(means, 0.99, axis=0)),
        ),
        opacity_quantiles=tuple(
            float(q) for q in np.quantile(opacities, [0.0, 0.25, 0.5, 0.75, 1.0])
        ),
        opacity_mean=float(opacities.mean()),
        low_opacity_share=float((opacities < 0.1).mean()),
        scale_median=float(np.median(largest_scales)),
        cameras=cameras,
    )
