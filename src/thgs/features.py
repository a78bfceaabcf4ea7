"""Semantic features per region (design §4.7): one unit vector per region of a hierarchy level.

A region at level k ∈ {1, 2, 3} takes its feature from SAM level k's masks (1 ↔ ``s``, 2 ↔ ``m``,
3 ↔ ``l``: the same index is the guidance level and the :class:`~thgs.lift.ViewLift` label
column). Two training-free modes, both the reference's:

- ``"shares"`` (its mode 2, LERF preset): per view v and region r, the share ``s_t`` of each mask
  t among r's Gaussians that carry a label in v; shares below ``min_share`` are dropped (no
  renormalisation); ``f_r += normalize(Σ_t s_t · F_v[t]) · p_r^v`` with ``p_r^v`` the share of r's
  Gaussians visible in v (``max w > visible_weight``). **Ours weighs every Gaussian by how well
  the view sees it**, as the merging does (:class:`thgs.hierarchy.MergeConfig`): a Gaussian
  counts only where its ``max w`` reaches ``min_max_weight`` (0.05) and then weighs
  ``(max w)^p`` (``visibility_power`` p = 2) in the shares and in ``p_r^v``. A Gaussian seen only
  through an occluder carries the occluder's mask (a table's legs under its top); counted like a
  well-seen one it pulls its region's feature towards the occluder's name. **Ours also weighs
  each view by how well its masks fit the region**: ``p_r^v`` times ``fit_r^v``
  (``fit_power`` 1), the kept masks' precision (the share of each mask's counted weight in the
  view that lies in r) averaged by their shares: a view whose mask holds the region and much
  else (a table leg's ``m`` mask that also holds the top) says less about the region than one
  whose mask is the region. The reference counts every labelled Gaussian once and every view by
  its visible share alone (:meth:`FeatureConfig.as_reference`).
- ``"centres"`` (its mode 1, 3DOVS preset): per view, every Gaussian with ``max w >
  centre_weight`` takes the mask under its projected centre, weighted by its ``max w``; if at
  least ``min_visible`` of r's Gaussians are used in v, ``f_r += normalize(Σ w · F_v[mask]) ·
  portion`` with ``portion`` that share.

Finally every ``f_r`` is L2-normalized; regions no view contributed to keep a zero row. That is
the reference's weighted mean of the views' unit vectors. **Ours then takes**
``FeatureConfig.median_steps`` (2) **steps towards their weighted median direction**: each step
pools the views again with view v's weight divided by ``‖u_v − m_r‖ + ε`` (``u_v`` its unit
vector for r, ``m_r`` the previous step's feature; iteratively reweighted least squares, whose
fixed point minimises ``Σ_v p_r^v ρ(‖u_v − m_r‖)`` over unit ``m_r`` with
``ρ(d) = d − ε ln(1 + d/ε)``, an L1 distance smoothed below ε). A view that sees a region
mostly through or beside another thing gives it that thing's name; the mean moves towards it
in proportion to its weight, the median much less. The work
runs on the lifted views' device, vectorized per view (indexed sums into a dense [R, masks of the
level] table and one product with the masks' features), so memory per view is O(n_seen + R·masks
+ masks·D + R·D) and time is linear in the number of seen Gaussians (times ``median_steps + 1``:
each step goes over the views again rather than holding every view's [R, D] vectors). Only the
[R, D] result comes back to the CPU.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from thgs.errors import InputError
from thgs.guidance import LEVELS, GuidanceFolder, ViewGuidance
from thgs.lift import ViewLift
from thgs.scene import Cameras, Gaussians

__all__ = ["FeatureConfig", "centre_masks", "level_features", "region_features"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class FeatureConfig:
    """How region features are pooled from the views' mask features.

    Attributes:
        mode: ``"shares"`` — mask shares of each region's labelled Gaussians, weighted by the
            region's visible share (the reference's mode 2, LERF preset); ``"centres"`` — the mask
            under each visible Gaussian's projected centre, weighted by its max blending weight
            (mode 1, 3DOVS preset; needs the Gaussians and cameras).
        min_share: mode shares: a mask holding less than this share (in [0, 1]) of a region's
            labelled Gaussians in a view is dropped; the kept shares are not renormalised.
        visible_weight: mode shares: a Gaussian is visible in a view if its max blending weight
            ``max_x w(x)`` (unitless, in (0, 1]) exceeds this.
        min_max_weight: mode shares: a Gaussian's label and visibility in a view count only if
            its ``max_x w(x)`` there reaches this (ours 0.05; the reference 0).
        visibility_power: mode shares: p: a counted Gaussian weighs ``(max_x w(x))^p`` in the
            mask shares and in the visible share ``p_r^v`` (ours 2; the reference 0: every
            Gaussian weighs 1).
        fit_power: mode shares: q: view v's vector of region r weighs ``p_r^v · (fit_r^v)^q``,
            ``fit_r^v`` in [0, 1] the kept masks' precision in v (each mask's counted weight
            inside r over its counted weight in the view) averaged by their shares (ours 1; the
            reference 0: the visible share alone).
        centre_weight: mode centres: a Gaussian is used in a view if its max blending weight
            exceeds this.
        min_visible: mode centres: a view contributes to a region only if at least this share
            (in [0, 1]) of the region's Gaussians are used in it.
        median_steps: both modes: steps from the weighted mean of the views' unit vectors
            towards their weighted median direction (ours 2; the reference 0: the mean; at
            most 1,000). Each
            step pools the views again, view v's vector ``u_v`` of region r weighing
            ``p_r^v / (‖u_v − m_r‖ + median_softness)`` with ``m_r`` the previous step's unit
            feature: one view that disagrees with the others (a part seen mostly through or
            next to another thing) pulls the result less than in the mean.
        median_softness: ε of those weights (unitless, on distances between unit vectors,
            which lie in [0, 2]): views closer than ε to ``m_r`` weigh about alike.
    """

    mode: Literal["shares", "centres"] = "shares"
    min_share: float = 0.3
    visible_weight: float = 1e-4
    min_max_weight: float = 0.05
    visibility_power: float = 2.0
    fit_power: float = 1.0
    centre_weight: float = 0.01
    min_visible: float = 0.1
    median_steps: int = 2
    median_softness: float = 0.1

    def __post_init__(self) -> None:
        if self.mode not in ("shares", "centres"):
            raise InputError(
                "FeatureConfig", f"mode must be 'shares' or 'centres', got {self.mode!r}"
            )
        for name in ("min_share", "min_visible"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InputError("FeatureConfig", f"{name} must be in [0, 1], got {value}")
        for name in ("visible_weight", "centre_weight", "min_max_weight"):
            value = getattr(self, name)
            if not 0.0 <= value < 1.0:
                raise InputError("FeatureConfig", f"{name} must be in [0, 1), got {value}")
        if isinstance(self.median_steps, bool) or not (
            isinstance(self.median_steps, int) and 0 <= self.median_steps <= 1000
        ):
            raise InputError(
                "FeatureConfig",
                f"median_steps must be an integer from 0 to 1,000, got {self.median_steps!r}",
            )
        if not self.median_softness > 0:
            raise InputError(
                "FeatureConfig", f"median_softness must be > 0, got {self.median_softness}"
            )
        for name in ("visibility_power", "fit_power"):
            value = getattr(self, name)
            if not 0 <= value < math.inf:
                raise InputError("FeatureConfig", f"{name} must be finite and ≥ 0, got {value}")

    @classmethod
    def lerf(cls) -> FeatureConfig:
        """The reference's LERF-OVS setting: mode 2 (shares ≥ 0.3, visible if max w > 1e-4),
        with our visibility weighting (see :meth:`as_reference`)."""
        return cls(mode="shares", min_share=0.3, visible_weight=1e-4)

    @classmethod
    def three_dovs(cls) -> FeatureConfig:
        """The reference's 3DOVS setting: mode 1 (centres, max w > 0.01, ≥ 10 % used)."""
        return cls(mode="centres", centre_weight=0.01, min_visible=0.1)

    def as_reference(self) -> FeatureConfig:
        """The same numbers with the authors' pooling: the weighted mean over views, and in
        mode shares every labelled Gaussian counting once, however faintly the view sees it,
        and every view weighing its visible share, however well its masks fit."""
        return replace(
            self, min_max_weight=0.0, visibility_power=0.0, fit_power=0.0, median_steps=0
        )


def _centre_pixels(means: Tensor, camera: Cameras, indices: Tensor, height: int, width: int):
    """``(rows, columns, inside)``: the pixel under each selected centre and whether it lies in
    front of the camera and inside the image (rows and columns are 0 where it does not)."""
    device = means.device
    viewmat = camera.viewmats[0].to(device=device, dtype=torch.float64)
    K = camera.Ks[0].to(device=device, dtype=torch.float64)
    points = means[indices].double() @ viewmat[:3, :3].T + viewmat[:3, 3]
    image = points @ K.T
    front = points[:, 2] > 0
    z = torch.where(front, image[:, 2], 1.0)
    x, y = image[:, 0] / z, image[:, 1] / z
    inside = front & (x >= 0) & (x < width) & (y >= 0) & (y < height)
    rows = torch.where(inside, torch.floor(y), 0.0).long()
    columns = torch.where(inside, torch.floor(x), 0.0).long()
    return rows, columns, inside


def centre_masks(
    means: Tensor | np.ndarray,
    camera: Cameras,
    segments: Tensor | np.ndarray,
    indices: Tensor | np.ndarray,
) -> Tensor:
    """The mask under the projected centre of some Gaussians in one view.

    A centre at camera-frame position ``c = R·μ + t`` lands on the continuous pixel coordinates
    ``(K·c)[:2] / c_z`` (the formula of :meth:`thgs.scene.Cameras.project`, in float64 and for
    the selected Gaussians only); pixel (u, v) covers ``[u, u+1) × [v, v+1)``, so the mask of a
    centre at (x, y) is ``segments[⌊y⌋, ⌊x⌋]``.

    Args:
        means: [N, 3] float Gaussian centres, world frame, scene units.
        camera: the view's camera (one).
        segments: [H, W] integer mask id per pixel of one level, −1 = none; H, W the camera's.
        indices: [m] integer indices into ``means`` of the Gaussians to look up.

    Returns:
        [m] int64 mask id per Gaussian, on the device of ``means``; −1 where the centre lies
        behind the camera (z ≤ 0), outside the image, or on a pixel without a mask.
    """
    means = torch.as_tensor(means)
    segments = torch.as_tensor(segments, device=means.device)
    indices = torch.as_tensor(indices, device=means.device).long()
    height, width = segments.shape
    rows, columns, inside = _centre_pixels(means, camera, indices, height, width)
    return torch.where(inside, segments[rows, columns].long(), -1)


def _check_labels(labels: np.ndarray, regions: int | None) -> tuple[np.ndarray, int]:
    labels = np.asarray(labels)
    if labels.ndim != 1:
        raise InputError("labels", f"must be [N] region ids, got shape {list(labels.shape)}")
    if not np.issubdtype(labels.dtype, np.integer):
        raise InputError("labels", f"must be integer region ids, got dtype {labels.dtype}")
    if len(labels) and int(labels.min()) < 0:
        raise InputError(
            "labels", f"region ids must be ≥ 0 (every Gaussian in a region), got {labels.min()}"
        )
    needed = int(labels.max()) + 1 if len(labels) else 0
    if regions is None:
        regions = needed
    elif isinstance(regions, bool) or not isinstance(regions, (int, np.integer)):
        raise InputError("regions", f"must be an integer count, got {regions!r}")
    elif regions < needed:
        raise InputError("regions", f"{regions} regions but labels use ids up to {needed - 1}")
    return labels.astype(np.int64), int(regions)


def _view_features(guidance: Sequence[ViewGuidance], i: int) -> tuple[str, np.ndarray]:
    """View ``i``'s stem and [n, D] mask features; from a folder read lazily, its feature file
    alone (its masks are not read)."""
    if isinstance(guidance, GuidanceFolder):
        return guidance.cameras.stems[i], guidance.features(i)
    return guidance[i].stem, guidance[i].features


def _check_views(
    lifted: Sequence[ViewLift], guidance: Sequence[ViewGuidance], count: int, level: int
) -> int:
    """Validate the views' shapes and return the feature dimension D."""
    if len(lifted) != len(guidance):
        raise InputError(
            "lifted", f"{len(lifted)} lifted views for {len(guidance)} views of guidance"
        )
    if not guidance:
        raise InputError("guidance", "no views: the feature dimension is unknown")
    dims = set()
    for i, view in enumerate(lifted):
        view.check(count, source=f"lifted view {i}")
        if view.device != lifted[0].device:
            raise InputError(
                f"lifted view {i}", f"is on {view.device}, view 0 on {lifted[0].device}"
            )
        stem, features = _view_features(guidance, i)
        if not isinstance(guidance, GuidanceFolder):  # a folder's views were checked when found
            segments = guidance[i].segments
            if features.ndim != 2 or segments.ndim != 3 or segments.shape[0] != 4:
                raise InputError(
                    f"guidance {stem}", "segments must be [4, H, W] and features [n, D]"
                )
        dims.add(int(features.shape[1]))
        column = view.labels[:, level]
        if len(column):
            low, high = int(column.min()), int(column.max())
            if low < -1 or high >= len(features):
                raise InputError(
                    f"lifted view {i}",
                    f"level-{LEVELS[level]} mask ids range over [{low}, {high}] but "
                    f"guidance {stem} has {len(features)} feature rows",
                )
    if len(dims) != 1:
        raise InputError("guidance", f"views disagree on the feature dimension: {sorted(dims)}")
    return dims.pop()


def _check_geometry(
    gaussians: Gaussians | None,
    cameras: Cameras | None,
    guidance: Sequence[ViewGuidance],
    level: int,
    count: int,
) -> tuple[np.ndarray, Cameras]:
    if gaussians is None or cameras is None:
        raise InputError(
            "FeatureConfig", "mode 'centres' projects Gaussian centres: pass gaussians and cameras"
        )
    if len(gaussians) != count:
        raise InputError("gaussians", f"{len(gaussians)} Gaussians but {count} labels")
    if len(cameras) != len(guidance):
        raise InputError("cameras", f"{len(cameras)} cameras for {len(guidance)} views")
    if [view.stem for view in guidance] != list(cameras.stems):
        raise InputError("guidance", "must hold one view per camera, in camera order (by stem)")
    for i, view in enumerate(guidance):
        height, width = int(cameras.heights[i]), int(cameras.widths[i])
        if (view.height, view.width) != (height, width):
            raise InputError(
                f"guidance {view.stem}",
                f"masks are {view.width}×{view.height} but the camera is {width}×{height}",
            )
        segments = view.segments[level]
        if segments.size and (
            int(segments.min()) < -1 or int(segments.max()) >= len(view.features)
        ):
            raise InputError(
                f"guidance {view.stem}",
                f"level-{LEVELS[level]} mask ids range over [{segments.min()}, {segments.max()}] "
                f"but there are {len(view.features)} feature rows",
            )
    return gaussians.means.detach(), cameras


def _accumulate(level: _Level, pooled: Tensor, features: Tensor, scale: Tensor) -> None:
    """``out[r] += u_r · scale[r]`` with ``u_r = normalize(pooled[r] @ features)``, for rows with
    a non-zero sum; with a ``centre`` (a median step), ``scale[r] / (‖u_r − centre[r]‖ + ε)``.

    ``pooled`` is [R, M] (region × the masks ``features`` [M, D] describe)."""
    rows = torch.nonzero((pooled != 0).any(dim=1) & (scale > 0))[:, 0]
    if len(rows) == 0:
        return
    sums = pooled[rows] @ features
    norms = torch.linalg.vector_norm(sums, dim=1)
    nonzero = norms > 0
    rows, sums, norms = rows[nonzero], sums[nonzero], norms[nonzero]
    units = sums / norms[:, None]
    weights = scale[rows]
    if level.centre is not None:
        distances = torch.linalg.vector_norm(units - level.centre[rows], dim=1)
        weights = weights / (distances + level.softness)
    level.out[rows] += units * weights[:, None]


def _pooled(
    regions: Tensor, masks: Tensor, weights: Tensor, take: Tensor, count: int
) -> tuple[Tensor, int] | None:
    """[R, M] sums of ``weights`` per (region, mask) over the entries where ``take`` is True, M
    spanning the masks that occur there from the smallest (returned); None when none is taken."""
    if not bool(take.any()):
        return None
    chosen = masks[take]
    low, high = int(chosen.min()), int(chosen.max())
    width = high - low + 1
    keys = regions * width + (masks - low).clamp(0, width - 1)
    table = torch.zeros(count * width, dtype=weights.dtype, device=weights.device)
    table.index_add_(0, keys, torch.where(take, weights, 0.0))
    return table.reshape(count, width), low


def _normalized(rows: Tensor) -> Tensor:
    """``rows`` [R, D] scaled to unit length; zero rows stay zero."""
    norms = torch.linalg.vector_norm(rows, dim=1, keepdim=True)
    return torch.where(norms > 0, rows / torch.where(norms > 0, norms, 1.0), 0.0)


def _fraction(values: Tensor, sizes: Tensor) -> Tensor:
    return torch.where(sizes > 0, values / torch.where(sizes > 0, sizes, 1.0), 0.0)


@dataclass(frozen=True, eq=False)
class _Level:
    """One hierarchy level's accumulation: its regions and running feature sums, and in a
    median step the previous step's [R, D] unit features ``centre`` with ε ``softness``."""

    level: int
    region_of: Tensor
    sizes: Tensor
    out: Tensor
    centre: Tensor | None = None
    softness: float = 0.0


def _shares_view(
    levels: list[_Level],
    gaussians: Tensor,
    max_weights: Tensor,
    labels: Tensor,
    features: Tensor,
    config: FeatureConfig,
    keep: Tensor | None,
) -> None:
    """One view's unit vectors in mode shares; ``keep`` [n] (None: all) the view's Gaussians
    that count, while every one of them counts in its mask's weight (the fit's precision)."""
    counted = max_weights >= config.min_max_weight
    weights = max_weights.double() ** config.visibility_power
    # level → [masks] each mask's counted weight over the whole view; without ``keep`` these are
    # the column sums of the level's table below
    whole_view = {}
    if keep is not None:
        if config.fit_power > 0:
            for level in levels:
                masks = labels[:, level.level].long()
                use = counted & (masks >= 0)
                whole_view[level.level] = torch.bincount(masks[use], weights[use])
        gaussians, labels, max_weights = gaussians[keep], labels[keep], max_weights[keep]
        counted, weights = counted[keep], weights[keep]
    visible_weights = torch.where(counted & (max_weights > config.visible_weight), weights, 0.0)
    for level in levels:
        count = len(level.sizes)
        regions = level.region_of[gaussians]
        seen = torch.zeros(count, dtype=torch.float64, device=weights.device)
        seen.index_add_(0, regions, visible_weights)
        masks = labels[:, level.level].long()
        pooled = _pooled(regions, masks, weights, counted & (masks >= 0), count)
        if pooled is None:
            continue
        table, low = pooled
        shares = _fraction(table, table.sum(dim=1, keepdim=True))
        shares = torch.where(shares < config.min_share, 0.0, shares)
        scale = _fraction(seen, level.sizes)
        if config.fit_power > 0:
            totals = whole_view.get(level.level)
            totals = table.sum(dim=0) if totals is None else totals[low : low + table.shape[1]]
            scale = scale * _fit(table, shares, totals) ** config.fit_power
        _accumulate(level, shares, features[low : low + shares.shape[1]], scale)


def _fit(table: Tensor, shares: Tensor, totals: Tensor) -> Tensor:
    """[R] how well the kept masks fit each region in one view: each mask's precision (its
    weight inside the region, ``table`` [R, M], over its weight in the view, ``totals`` [M])
    averaged by the region's kept ``shares`` [R, M]; 0 for a region that keeps none."""
    precision = _fraction(table, totals[None, :])
    return _fraction((shares * precision).sum(dim=1), shares.sum(dim=1))


def _centres_view(
    levels: list[_Level],
    gaussians: Tensor,
    max_weights: Tensor,
    features: Tensor,
    means: Tensor,
    camera: Cameras,
    segments: Tensor,
    config: FeatureConfig,
) -> None:
    used = max_weights > config.centre_weight
    gaussians = gaussians[used]
    weights = max_weights[used].double()
    for level in levels:
        count = len(level.sizes)
        regions = level.region_of[gaussians]
        portion = _fraction(torch.bincount(regions, minlength=count).double(), level.sizes)
        eligible = ((portion >= config.min_visible) & (portion > 0))[regions]
        masks = torch.as_tensor(
            centre_masks(means, camera, segments[level.level], gaussians), device=weights.device
        )
        pooled = _pooled(regions, masks, weights, eligible & (masks >= 0), count)
        if pooled is None:
            continue
        table, low = pooled
        _accumulate(level, table, features[low : low + table.shape[1]], portion)


def _pool_views(
    levels: list[_Level],
    lifted: Sequence[ViewLift],
    guidance: Sequence[ViewGuidance],
    config: FeatureConfig,
    inside: Tensor | None,
    means: Tensor | None,
    cameras: Cameras | None,
) -> None:
    """One pass over the views, adding each view's unit vectors into ``levels``' sums."""
    device = lifted[0].device
    for i, view in enumerate(lifted):
        if len(view) == 0:
            continue
        masks = guidance[i] if config.mode == "centres" else None
        view_features = _view_features(guidance, i)[1] if masks is None else masks.features
        if len(view_features) == 0:
            continue
        seen, max_weights, view_labels = view.gaussians.long(), view.max_weights, view.labels
        keep = None if inside is None else inside[seen]
        features = torch.from_numpy(view_features).to(device=device, dtype=torch.float64)
        if masks is None:
            _shares_view(levels, seen, max_weights, view_labels, features, config, keep)
        else:
            if keep is not None:
                seen, max_weights = seen[keep], max_weights[keep]
            segments = torch.from_numpy(masks.segments).to(device)
            camera = cameras.select([i])
            _centres_view(levels, seen, max_weights, features, means, camera, segments, config)


def level_features(
    labels: np.ndarray,
    levels: Sequence[int],
    lifted: Sequence[ViewLift],
    guidance: Sequence[ViewGuidance],
    config: FeatureConfig = FeatureConfig(),
    *,
    gaussians: Gaussians | None = None,
    cameras: Cameras | None = None,
    regions: Sequence[int] | None = None,
    within: np.ndarray | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """:func:`region_features` of several levels in one pass over the views.

    Args:
        labels: [N, K] integer region ids, column i for level ``levels[i]``.
        levels: K levels, each 1, 2 or 3.
        regions: R of each column (default its largest id + 1).
        within: optional [N] bool; only these Gaussians count (a region's Gaussians outside
            are ignored, its size included): the features of regions that lie inside, computed
            with work proportional to the Gaussians inside.
        lifted, guidance, config, gaussians, cameras: as :func:`region_features`.

    Returns:
        one ``(features, seen)`` per level, as :func:`region_features`.
    """
    start = time.perf_counter()
    labels = np.asarray(labels)
    if labels.ndim != 2 or labels.shape[1] != len(levels):
        raise InputError("labels", f"must be [N, {len(levels)}], got {list(labels.shape)}")
    for level in levels:
        if isinstance(level, bool) or level not in (1, 2, 3):
            raise InputError("level", f"must be 1, 2 or 3 (SAM levels s, m, l), got {level!r}")
    counts = [None] * len(levels) if regions is None else list(regions)
    checked = [_check_labels(labels[:, i], counts[i]) for i in range(len(levels))]
    n = len(labels)
    dims = {_check_views(lifted, guidance, n, level) for level in levels}
    dim = dims.pop()
    if config.mode == "centres":
        for level in levels:
            means, cameras = _check_geometry(gaussians, cameras, guidance, level, n)
    if within is not None and np.asarray(within).shape != (n,):
        raise InputError("within", f"must be [N] = [{n}] bool, got {np.asarray(within).shape}")
    device = lifted[0].device
    inside = None if within is None else torch.from_numpy(np.asarray(within, bool)).to(device)
    accumulations = []
    for level, (column, count) in zip(levels, checked):
        region_of = torch.from_numpy(column).to(device)
        kept = region_of if inside is None else region_of[inside]
        sizes = torch.bincount(kept, minlength=count).double()
        out = torch.zeros((count, dim), dtype=torch.float64, device=device)
        accumulations.append(_Level(level, region_of, sizes, out))
    means = means.to(device) if config.mode == "centres" else None
    _pool_views(accumulations, lifted, guidance, config, inside, means, cameras)
    for _ in range(config.median_steps):
        accumulations = [
            replace(
                accumulation,
                out=torch.zeros_like(accumulation.out),
                centre=_normalized(accumulation.out),
                softness=config.median_softness,
            )
            for accumulation in accumulations
        ]
        _pool_views(accumulations, lifted, guidance, config, inside, means, cameras)
    results = []
    for accumulation in accumulations:
        out = _normalized(accumulation.out)
        seen_rows = torch.linalg.vector_norm(out, dim=1) > 0
        results.append((out.float().cpu().numpy(), seen_rows.cpu().numpy()))
        logger.info(
            "region features (%s) at level %d: %d of %d regions seen in %d views",
            config.mode,
            accumulation.level,
            int(seen_rows.sum()),
            len(out),
            len(lifted),
        )
    logger.info("region features of levels %s: %.2f s", list(levels), time.perf_counter() - start)
    return results


def region_features(
    labels: np.ndarray,
    level: int,
    lifted: Sequence[ViewLift],
    guidance: Sequence[ViewGuidance],
    config: FeatureConfig = FeatureConfig(),
    *,
    gaussians: Gaussians | None = None,
    cameras: Cameras | None = None,
    regions: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """One feature vector per region of hierarchy level ``level`` from SAM level ``level``.

    Args:
        labels: [N] integer region id of every Gaussian (0 … R−1; every Gaussian in a region).
        level: 1, 2 or 3: the hierarchy level, which is also the SAM mask level used (s, m, l)
            and the :attr:`ViewLift.labels` column.
        lifted: one :class:`~thgs.lift.ViewLift` per view (:func:`thgs.lift.lift_views`).
        guidance: one :class:`~thgs.guidance.ViewGuidance` per view, in the same order; every
            view's features must have the same D (a view may have no masks: [0, D]).
        config: mode and thresholds (default :class:`FeatureConfig`, mode ``"shares"``).
        gaussians: the N Gaussians (mode ``"centres"`` only: their centres are projected).
        cameras: one camera per view, in guidance order (mode ``"centres"`` only).
        regions: R, when it exceeds ``labels.max() + 1`` (regions without Gaussians); default
            ``labels.max() + 1``.

    Returns:
        ``(features, seen)``: [R, D] float32 unit rows (zero rows for regions no view
        contributed to) and [R] bool, True where the row is a unit vector.

    Raises:
        InputError: labels not [N] non-negative integers, ``level`` not in 1…3, ``lifted`` and
            ``guidance`` of different lengths, a lifted Gaussian index outside [0, N), a mask id
            outside its view's feature rows, views with different D, or mode ``"centres"``
            without ``gaussians`` and ``cameras`` (or with ones that do not match).
    """
    labels = np.asarray(labels)
    if labels.ndim != 1:
        raise InputError("labels", f"must be [N] region ids, got shape {list(labels.shape)}")
    return level_features(
        labels[:, None],
        (level,),
        lifted,
        guidance,
        config,
        gaussians=gaussians,
        cameras=cameras,
        regions=None if regions is None else [regions],
    )[0]
