"""Virtual cameras that see every Gaussian of a splat well, for a scene without its photos.

Placement runs in two steps, both on the Gaussians alone:

1. **Base views.** The model's own cameras when it has them (``cameras.json`` beside the PLY:
   the training views, which saw the scene), scaled down to at most ``max_width`` pixels wide;
   else an *orbit*: rings of cameras at several elevations around the scene's centre (the
   median centre of the opaque Gaussians), looking at it from where the sphere holding
   ``core_percentiles`` % of the opaque Gaussians fills the narrower side of the image (by
   default half of them: where the objects are; the floor and far background around them are
   left to the close-ups). Several scales can be given, each with its own number of views.
   "Up" is the model cameras' mean up direction when there are some; else the axis along which
   the opaque Gaussians spread least (a floor, a table top), pointing away from the denser of its
   two extremes (things stand on a floor or a table, which is the densest layer; their tops are
   sparse); or as given.
2. **Close-ups.** Every base view is rendered at ``coverage_scale`` of its size; a Gaussian is
   *seen* in a view when it is the largest-weight Gaussian of at least one pixel. Opaque
   Gaussians seen in fewer than ``min_views`` views (under a table, between objects, the small
   ones a wide view leaves to a few pixels) are clustered (k-means on their centres); for each
   cluster, from the largest, cameras around it at ``close_directions`` azimuths and two
   elevations (15° and 50°) are rendered at ``candidate_scale`` — only the Gaussians near enough
   to stand between such a camera and the cluster, which is exact for the cluster's visibility
   and keeps the cost of a candidate independent of the scene's size — and the one that newly
   sees the most of the still-uncovered Gaussians is kept, while it sees at least ``min_gain`` of
   them. At most ``close_views`` are added.

Coordinates: world frame of the PLY, its units; cameras use OpenCV axes (x right, y down,
z forward), as :class:`thgs.scene.Cameras` does everywhere.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
import torch

from thgs.errors import InputError
from thgs.render import RasterConfig, render
from thgs.scene import Cameras, Gaussians
from thgs.scene.cameras import viewmat_from_pose

__all__ = [
    "Placement",
    "PlacementConfig",
    "SceneFrame",
    "close_up_cameras",
    "look_at",
    "orbit_cameras",
    "place_cameras",
    "scene_frame",
    "visibility_counts",
]

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class PlacementConfig:
    """Where virtual cameras go and what they see.

    Attributes:
        width, height: image size of orbit and close-up views, pixels.
        fov_deg: horizontal field of view of orbit and close-up views, degrees.
        orbit_views: number of orbit views at each scale, spread over the rings (more on the
            lower, longer rings: in proportion to the cosine of the elevation).
        elevations_deg: the rings' elevations above the scene's horizontal plane, degrees.
        core_percentiles: per orbit scale, the percentage of the opaque Gaussians that the
            sphere it frames holds (the rest is background); one per ``orbit_views``.
        distance_margin: the core sphere's radius is this fraction of the half image height.
        up: the scene's up direction (world frame); None: estimated from the Gaussians.
        max_width: the model's own cameras are scaled down to at most this width, pixels.
        min_opacity: Gaussians at least this opaque must be seen; fainter ones need not.
        min_views: a Gaussian is covered once seen in this many views.
        close_views: at most this many close-ups are added.
        close_directions: azimuths tried around each close-up's target (each at two
            elevations).
        coverage_scale: visibility is measured on renders at this fraction of the view size.
        candidate_scale: close-up candidates are compared on renders at this fraction.
        min_gain: a close-up is kept only when it newly sees this many uncovered Gaussians.
        seed: seeds the k-means of uncovered Gaussians.
    """

    width: int = 512
    height: int = 384
    fov_deg: float = 60.0
    orbit_views: tuple[int, ...] = (30,)
    elevations_deg: tuple[float, ...] = (20.0, 45.0, 70.0)
    core_percentiles: tuple[float, ...] = (50.0,)
    distance_margin: float = 1.0
    up: tuple[float, float, float] | None = None
    max_width: int = 640
    min_opacity: float = 0.5
    min_views: int = 2
    close_views: int = 12
    close_directions: int = 8
    coverage_scale: float = 0.5
    candidate_scale: float = 0.25
    min_gain: int = 20
    seed: int = 0

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> PlacementConfig:
        """Raise :class:`InputError` naming the setting that is out of range; returns self
        (run when the config is made)."""
        checks = {
            "width": self.width >= 16,
            "height": self.height >= 16,
            "fov_deg": 1.0 <= self.fov_deg <= 150.0,
            "orbit_views": len(self.orbit_views) >= 1
            and all(count >= 0 for count in self.orbit_views)
            and sum(self.orbit_views) >= 1,
            "elevations_deg": len(self.elevations_deg) >= 1
            and all(-89.0 <= e <= 89.0 for e in self.elevations_deg),
            "core_percentiles": len(self.core_percentiles) == len(self.orbit_views)
            and all(1.0 <= value <= 100.0 for value in self.core_percentiles),
            "distance_margin": self.distance_margin > 0.0,
            "up": self.up is None
            or (len(self.up) == 3 and np.isfinite(self.up).all() and np.linalg.norm(self.up) > 0),
            "max_width": self.max_width >= 16,
            "min_opacity": 0.0 <= self.min_opacity <= 1.0,
            "min_views": self.min_views >= 1,
            "close_views": self.close_views >= 0,
            "close_directions": self.close_directions >= 1,
            "coverage_scale": 0.0 < self.coverage_scale <= 1.0,
            "candidate_scale": 0.0 < self.candidate_scale <= 1.0,
            "min_gain": self.min_gain >= 1,
        }
        for name, ok in checks.items():
            if not ok:
                raise InputError(f"PlacementConfig.{name}", f"out of range: {getattr(self, name)}")
        return self


@dataclass(frozen=True)
class SceneFrame:
    """Where the scene is: ``centre`` [3] and ``up`` [3] (unit) in the world frame, ``radii``
    of the core spheres in scene units (one per ``core_percentiles``)."""

    centre: np.ndarray
    up: np.ndarray
    radii: tuple[float, ...]

    @property
    def radius(self) -> float:
        """The largest core radius."""
        return max(self.radii)


@dataclass(frozen=True)
class Placement:
    """Placed cameras and what they see.

    Attributes:
        cameras: every view: the base views first, then the close-ups.
        base_views: how many of them are base views (the model's cameras or the orbit).
        from_model: whether the base views are the model's own cameras.
        seen: [N] int64, in how many views each Gaussian is seen (at ``coverage_scale``).
        covered: fraction of the opaque Gaussians seen in at least ``min_views`` views.
    """

    cameras: Cameras
    base_views: int
    from_model: bool
    seen: np.ndarray
    covered: float


def _opaque(gaussians: Gaussians, min_opacity: float) -> np.ndarray:
    return gaussians.activated_opacities().detach().cpu().numpy() >= min_opacity


def _estimated_up(points: np.ndarray) -> np.ndarray:
    offsets = points - points.mean(axis=0)
    _, vectors = np.linalg.eigh(offsets.T @ offsets)
    up = vectors[:, 0]
    heights = offsets @ up
    low, high = np.percentile(heights, [0.5, 99.5])
    band = 0.03 * (high - low)
    if (heights <= low + band).sum() < (heights >= high - band).sum():
        up = -up
    return up


def _cameras_up(cameras: Cameras) -> np.ndarray | None:
    """The cameras' mean up direction (their −y axis in the world), None when they cancel."""
    ups = -cameras.camtoworlds().numpy()[:, :3, 1]
    mean = ups.mean(axis=0)
    norm = float(np.linalg.norm(mean))
    return mean / norm if norm > 0.1 else None


def scene_frame(
    gaussians: Gaussians,
    config: PlacementConfig = PlacementConfig(),
    *,
    cameras: Cameras | None = None,
    source: str = "scene",
) -> SceneFrame:
    """The scene's centre, up direction and core radii (see the module docstring); ``cameras``,
    the model's own, give the up direction when ``config.up`` does not.

    Raises:
        InputError: naming ``source``, when no Gaussian is at least ``min_opacity`` opaque with a
            finite centre, or the opaque ones do not span a volume (all at one point).
    """
    means = gaussians.means.detach().cpu().numpy().astype(np.float64)
    keep = _opaque(gaussians, config.min_opacity) & np.isfinite(means).all(axis=1)
    if not keep.any():
        raise InputError(
            source,
            f"no usable Gaussians: none is at least {config.min_opacity:g} opaque with a finite "
            "centre",
        )
    points = means[keep]
    centre = np.median(points, axis=0)
    distances = np.linalg.norm(points - centre, axis=1)
    radii = tuple(float(np.percentile(distances, p)) for p in config.core_percentiles)
    extent = float(np.abs(points - centre).max()) if len(points) else 0.0
    if len(points) < 4 or not min(radii) > 1e-9 * max(1.0, float(np.abs(centre).max())):
        raise InputError(
            source,
            f"too small or degenerate to place cameras around: {len(points)} opaque Gaussians "
            f"within {extent:.3g} scene units of one point",
        )
    up = None if cameras is None else _cameras_up(cameras)
    if config.up is not None:
        up = np.asarray(config.up, dtype=np.float64)
        up = up / np.linalg.norm(up)
    elif up is None:
        up = _estimated_up(points)
    return SceneFrame(centre, up, radii)


def look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> np.ndarray:
    """[4, 4] world→camera transform (OpenCV axes) of a camera at ``eye`` looking at ``target``
    with ``up`` pointing up in the image (any up not parallel to the view direction)."""
    forward = target - eye
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, up)
    if np.linalg.norm(right) < 1e-9:  # looking straight along up: any right will do
        right = np.cross(forward, np.eye(3)[int(np.argmin(np.abs(forward)))])
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    return viewmat_from_pose(np.stack([right, down, forward], axis=1), eye)


def _intrinsics(width: int, height: int, fov_deg: float) -> np.ndarray:
    focal = 0.5 * width / math.tan(math.radians(fov_deg) / 2)
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def _basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors spanning the plane orthogonal to ``up``."""
    helper = np.eye(3)[int(np.argmin(np.abs(up)))]
    first = np.cross(up, helper)
    first /= np.linalg.norm(first)
    return first, np.cross(up, first)


def _direction(up: np.ndarray, azimuth: float, elevation: float) -> np.ndarray:
    first, second = _basis(up)
    horizontal = math.cos(azimuth) * first + math.sin(azimuth) * second
    return math.cos(elevation) * horizontal + math.sin(elevation) * up


def _ring_sizes(total: int, elevations: tuple[float, ...]) -> list[int]:
    weights = np.array([math.cos(math.radians(e)) for e in elevations]) + 1e-6
    shares = weights / weights.sum() * total
    sizes = np.floor(shares).astype(int)
    for index in np.argsort(-(shares - sizes), kind="stable")[: total - int(sizes.sum())]:
        sizes[index] += 1
    return sizes.tolist()


def orbit_cameras(frame: SceneFrame, config: PlacementConfig = PlacementConfig()) -> Cameras:
    """``orbit_views[s]`` cameras at each scale ``s`` on rings at ``elevations_deg`` around
    ``frame``'s centre, looking at it from the distance at which the core sphere of radius
    ``frame.radii[s]`` fills the image's narrower side (named ``orbit_00001`` …)."""
    K = _intrinsics(config.width, config.height, config.fov_deg)
    half_fov = math.atan(0.5 * min(config.width, config.height) / K[0, 0])
    golden = math.pi * (3.0 - math.sqrt(5.0))
    viewmats = []
    for scale, (radius, views) in enumerate(zip(frame.radii, config.orbit_views)):
        distance = radius / (config.distance_margin * math.sin(half_fov))
        sizes = _ring_sizes(views, config.elevations_deg)
        for ring, (elevation, size) in enumerate(zip(config.elevations_deg, sizes)):
            for i in range(size):
                azimuth = 2 * math.pi * i / size + (ring + 0.5 * scale) * golden
                eye = frame.centre + distance * _direction(
                    frame.up, azimuth, math.radians(elevation)
                )
                viewmats.append(look_at(eye, frame.centre, frame.up))
    count = len(viewmats)
    return Cameras.from_lists(
        viewmats,
        [K] * count,
        [config.width] * count,
        [config.height] * count,
        [f"orbit_{i + 1:05d}" for i in range(count)],
    ).check(source="orbit cameras")


def _seen_in(gaussians: Gaussians, camera: Cameras, scale: float, raster: RasterConfig):
    """Indices of the Gaussians that are the largest-weight one of some pixel of ``camera``
    rendered at ``scale`` of its size."""
    small = camera.resized(
        [max(1, round(float(camera.widths[0]) * scale))],
        [max(1, round(float(camera.heights[0]) * scale))],
    )
    ones = torch.ones((len(gaussians), 1), dtype=gaussians.means.dtype, device=gaussians.device)
    max_id = render(gaussians, small, ones, config=raster).max_id.detach().cpu().numpy()
    return np.unique(max_id[max_id >= 0])


def visibility_counts(
    gaussians: Gaussians,
    cameras: Cameras,
    *,
    scale: float = 1.0,
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
) -> np.ndarray:
    """[N] int64: in how many of ``cameras`` each Gaussian is the largest-weight Gaussian of at
    least one pixel, rendering each view at ``scale`` of its size."""
    counts = np.zeros(len(gaussians), dtype=np.int64)
    for i in range(len(cameras)):
        counts[_seen_in(gaussians, cameras.select([i]), scale, raster)] += 1
        if progress is not None:
            progress("coverage", i + 1, len(cameras))
    return counts


def _clusters(points: np.ndarray, count: int, seed: int) -> list[np.ndarray]:
    """Indices into ``points`` of up to ``count`` k-means clusters, largest first."""
    from scipy.cluster.vq import kmeans2

    count = min(count, len(points))
    if count <= 1:
        return [np.arange(len(points))]
    _, labels = kmeans2(points, count, minit="++", seed=seed)
    groups = [np.flatnonzero(labels == k) for k in range(count)]
    return sorted((g for g in groups if len(g)), key=len, reverse=True)


def close_up_cameras(
    gaussians: Gaussians,
    frame: SceneFrame,
    seen: np.ndarray,
    config: PlacementConfig = PlacementConfig(),
    *,
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
) -> tuple[Cameras | None, np.ndarray]:
    """Close-up views of the opaque Gaussians seen in fewer than ``min_views`` views.

    Args:
        gaussians: the scene.
        frame: its :func:`scene_frame`.
        seen: [N] views each Gaussian is seen in so far (:func:`visibility_counts`).
        config: placement settings.
        raster: rasterization settings of the coverage renders.
        progress: called as ``progress("close-ups", done, total)`` per cluster.

    Returns:
        ``(cameras or None, seen)``: the close-ups (named ``close_00001`` …, in the order they
        were chosen) and the updated counts.
    """
    seen = seen.copy()
    opaque = _opaque(gaussians, config.min_opacity)
    uncovered = np.flatnonzero(opaque & (seen < config.min_views))
    if config.close_views == 0 or len(uncovered) < config.min_gain:
        return None, seen
    means = gaussians.means.detach().cpu().numpy().astype(np.float64)
    extents = 3.0 * gaussians.activated_scales().detach().cpu().numpy().max(axis=1)
    K = _intrinsics(config.width, config.height, config.fov_deg)
    tan_half = 0.5 * min(config.width, config.height) / K[0, 0]
    clusters = _clusters(means[uncovered], config.close_views, config.seed)
    directions = [
        _direction(frame.up, 2 * math.pi * i / config.close_directions, elevation)
        for i in range(config.close_directions)
        for elevation in (math.radians(15.0), math.radians(50.0))
    ]
    chosen: list[np.ndarray] = []
    for done, members in enumerate(clusters, start=1):
        targets = uncovered[members]
        targets = targets[seen[targets] < config.min_views]
        if len(targets) >= config.min_gain:
            target = means[targets].mean(axis=0)
            spread = float(np.percentile(np.linalg.norm(means[targets] - target, axis=1), 90))
            distance = max(spread, 0.05 * frame.radius) / tan_half * 1.2
            # every ray from a candidate to the cluster stays within this ball around its centre
            near = np.flatnonzero(
                np.linalg.norm(means - target, axis=1) - extents <= 1.05 * distance + spread
            )
            nearby = gaussians.select(torch.from_numpy(near))
            best, best_gain = None, config.min_gain - 1
            for direction in directions:
                viewmat = look_at(target + distance * direction, target, frame.up)
                camera = Cameras.from_lists(
                    [viewmat], [K], [config.width], [config.height], ["candidate"]
                )
                visible = near[_seen_in(nearby, camera, config.candidate_scale, raster)]
                gain = int(np.isin(targets, visible).sum())
                if gain > best_gain:
                    best, best_gain = viewmat, gain
            if best is not None:
                chosen.append(best)
                camera = Cameras.from_lists(
                    [best], [K], [config.width], [config.height], ["close-up"]
                )
                seen[_seen_in(gaussians, camera, config.coverage_scale, raster)] += 1
        if progress is not None:
            progress("close-ups", done, len(clusters))
    if not chosen:
        return None, seen
    count = len(chosen)
    cameras = Cameras.from_lists(
        chosen,
        [K] * count,
        [config.width] * count,
        [config.height] * count,
        [f"close_{i + 1:05d}" for i in range(count)],
    ).check(source="close-up cameras")
    return cameras, seen


def _concat(first: Cameras, second: Cameras) -> Cameras:
    return Cameras(
        torch.cat([first.viewmats, second.viewmats]),
        torch.cat([first.Ks, second.Ks]),
        torch.cat([first.widths, second.widths]),
        torch.cat([first.heights, second.heights]),
        first.names + second.names,
    )


def _model_base(cameras: Cameras, max_width: int) -> Cameras:
    """The model's cameras as pinholes at most ``max_width`` wide (renders need no lens)."""
    plain = replace(cameras, distortion=None)
    widest = int(plain.widths.max())
    if widest <= max_width:
        return plain
    scale = max_width / widest
    return plain.resized(
        [max(1, math.floor(float(w) * scale)) for w in plain.widths],
        [max(1, math.floor(float(h) * scale)) for h in plain.heights],
    )


def place_cameras(
    gaussians: Gaussians,
    config: PlacementConfig = PlacementConfig(),
    *,
    model_cameras: Cameras | None = None,
    raster: RasterConfig = RasterConfig(),
    source: str = "scene",
    progress: Progress | None = None,
) -> Placement:
    """Virtual cameras for ``gaussians``: the base views (``model_cameras`` when given, else an
    orbit) and close-ups of what they leave unseen (see the module docstring).

    Raises:
        InputError: naming ``source``, for a scene without usable Gaussians or too degenerate
            to place cameras around (:func:`scene_frame`), or a setting out of range.
    """
    frame = scene_frame(gaussians, config, cameras=model_cameras, source=source)
    if model_cameras is not None:
        base = _model_base(model_cameras, config.max_width)
    else:
        base = orbit_cameras(frame, config)
    seen = visibility_counts(
        gaussians, base, scale=config.coverage_scale, raster=raster, progress=progress
    )
    close, seen = close_up_cameras(gaussians, frame, seen, config, raster=raster, progress=progress)
    cameras = base if close is None else _concat(base, close)
    opaque = _opaque(gaussians, config.min_opacity)
    covered = float((seen[opaque] >= config.min_views).mean())
    logger.info(
        "placed %d views (%d %s, %d close-ups): %.1f %% of the opaque Gaussians seen in ≥ %d",
        len(cameras),
        len(base),
        "model cameras" if model_cameras is not None else "orbit",
        len(cameras) - len(base),
        100 * covered,
        config.min_views,
    )
    return Placement(cameras, len(base), model_cameras is not None, seen, covered)
