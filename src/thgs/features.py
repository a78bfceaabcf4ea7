"""Semantic features per region (design §4.7): one unit vector per region of a hierarchy level.

A region at level k ∈ {1, 2, 3} takes its feature from SAM level k's masks (1 ↔ ``s``, 2 ↔ ``m``,
3 ↔ ``l``: the same index is the guidance level and the :class:`~thgs.lift.ViewLift` label
column). Two training-free, one-pass modes, both the reference's:

- ``"shares"`` (its mode 2, LERF preset): per view v and region r, the share ``s_t`` of each mask
  t among r's Gaussians that carry a label in v; shares below ``min_share`` are dropped (no
  renormalisation); ``f_r += normalize(Σ_t s_t · F_v[t]) · p_r^v`` with ``p_r^v`` the share of r's
  Gaussians visible in v (``max w > visible_weight``). **Ours weighs every Gaussian by how well
  the view sees it**, as the merging does (:class:`thgs.hierarchy.MergeConfig`): a Gaussian
  counts only where its ``max w`` reaches ``min_max_weight`` (0.05) and then weighs
  ``(max w)^p`` (``visibility_power`` p = 2) in the shares and in ``p_r^v``. A Gaussian seen only
  through an occluder carries the occluder's mask (a table's legs under its top); counted like a
  well-seen one it pulls its region's feature towards the occluder's name. The reference counts
  every labelled Gaussian once (:meth:`FeatureConfig.as_reference`).
- ``"centres"`` (its mode 1, 3DOVS preset): per view, every Gaussian with ``max w >
  centre_weight`` takes the mask under its projected centre, weighted by its ``max w``; if at
  least ``min_visible`` of r's Gaussians are used in v, ``f_r += normalize(Σ w · F_v[mask]) ·
  portion`` with ``portion`` that share.

Finally every ``f_r`` is L2-normalized; regions no view contributed to keep a zero row. The work
is vectorized per view (bincounts and one sparse product), so memory per view is O(n_seen +
masks·D + R·D) and time is linear in the number of seen Gaussians.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
import scipy.sparse

from thgs.errors import InputError
from thgs.guidance import LEVELS, ViewGuidance
from thgs.lift import ViewLift
from thgs.scene import Cameras, Gaussians

__all__ = ["FeatureConfig", "centre_masks", "region_features"]

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
        centre_weight: mode centres: a Gaussian is used in a view if its max blending weight
            exceeds this.
        min_visible: mode centres: a view contributes to a region only if at least this share
            (in [0, 1]) of the region's Gaussians are used in it.
    """

    mode: Literal["shares", "centres"] = "shares"
    min_share: float = 0.3
    visible_weight: float = 1e-4
    min_max_weight: float = 0.05
    visibility_power: float = 2.0
    centre_weight: float = 0.01
    min_visible: float = 0.1

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
        if not self.visibility_power >= 0:
            raise InputError(
                "FeatureConfig", f"visibility_power must be ≥ 0, got {self.visibility_power}"
            )

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
        """The same numbers with the authors' mode 2: every labelled Gaussian counts once,
        however faintly the view sees it (mode centres has nothing of ours to switch off)."""
        return replace(self, min_max_weight=0.0, visibility_power=0.0)


def centre_masks(
    means: np.ndarray, camera: Cameras, segments: np.ndarray, indices: np.ndarray
) -> np.ndarray:
    """The mask under the projected centre of some Gaussians in one view.

    A centre at camera-frame position ``c = R·μ + t`` lands on the continuous pixel coordinates
    ``(K·c)[:2] / c_z`` (the formula of :meth:`thgs.scene.Cameras.project`, in NumPy and for the
    selected Gaussians only); pixel (u, v) covers ``[u, u+1) × [v, v+1)``, so the mask of a
    centre at (x, y) is ``segments[⌊y⌋, ⌊x⌋]``.

    Args:
        means: [N, 3] float Gaussian centres, world frame, scene units.
        camera: the view's camera (one).
        segments: [H, W] integer mask id per pixel of one level, −1 = none; H, W the camera's.
        indices: [m] integer indices into ``means`` of the Gaussians to look up.

    Returns:
        [m] int64 mask id per Gaussian; −1 where the centre lies behind the camera (z ≤ 0),
        outside the image, or on a pixel without a mask.
    """
    viewmat = camera.viewmats[0].detach().cpu().numpy().astype(np.float64)
    K = camera.Ks[0].detach().cpu().numpy().astype(np.float64)
    points = means[indices].astype(np.float64) @ viewmat[:3, :3].T + viewmat[:3, 3]
    image = points @ K.T
    front = points[:, 2] > 0
    z = np.where(front, image[:, 2], 1.0)
    x, y = image[:, 0] / z, image[:, 1] / z
    height, width = segments.shape
    inside = front & (x >= 0) & (x < width) & (y >= 0) & (y < height)
    out = np.full(len(indices), -1, dtype=np.int64)
    rows = np.floor(y[inside]).astype(np.int64)
    columns = np.floor(x[inside]).astype(np.int64)
    out[inside] = segments[rows, columns]
    return out


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
    for i, (view, masks) in enumerate(zip(lifted, guidance)):
        view.check(count, source=f"lifted view {i}")
        if not np.issubdtype(view.labels.dtype, np.integer):
            raise InputError(
                f"lifted view {i}", f"labels must be integers, not {view.labels.dtype}"
            )
        if masks.features.ndim != 2 or masks.segments.ndim != 3 or masks.segments.shape[0] != 4:
            raise InputError(
                f"guidance {masks.stem}", "segments must be [4, H, W] and features [n, D]"
            )
        dims.add(int(masks.features.shape[1]))
        column = view.labels[:, level]
        if len(column) and (int(column.min()) < -1 or int(column.max()) >= len(masks.features)):
            raise InputError(
                f"lifted view {i}",
                f"level-{LEVELS[level]} mask ids range over [{column.min()}, {column.max()}] but "
                f"guidance {masks.stem} has {len(masks.features)} feature rows",
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
    return gaussians.means.detach().cpu().numpy().astype(np.float64), cameras


def _pooled(
    regions: np.ndarray, masks: np.ndarray, weights: np.ndarray, shape: tuple[int, int]
) -> scipy.sparse.csr_matrix:
    """[R, M] sparse sum of ``weights`` per (region, mask) pair."""
    return scipy.sparse.csr_matrix((weights, (regions, masks)), shape=shape)


def _accumulate(
    out: np.ndarray, pooled: scipy.sparse.csr_matrix, features: np.ndarray, scale: np.ndarray
) -> None:
    """``out[r] += normalize(pooled[r] @ features) · scale[r]`` for rows with a non-zero sum."""
    rows = np.flatnonzero(np.diff(pooled.indptr) > 0)
    rows = rows[scale[rows] > 0]
    if len(rows) == 0:
        return
    sums = np.asarray(pooled[rows] @ features)
    norms = np.linalg.norm(sums, axis=1)
    nonzero = norms > 0
    rows, sums, norms = rows[nonzero], sums[nonzero], norms[nonzero]
    out[rows] += sums * (scale[rows] / norms)[:, None]


def _shares_view(
    out: np.ndarray,
    labels: np.ndarray,
    sizes: np.ndarray,
    view: ViewLift,
    features: np.ndarray,
    level: int,
    config: FeatureConfig,
) -> None:
    count = len(sizes)
    regions = labels[view.gaussians]
    counted = view.max_weights >= config.min_max_weight
    weights = view.max_weights.astype(np.float64) ** config.visibility_power
    visible = counted & (view.max_weights > config.visible_weight)
    share_visible = np.divide(
        np.bincount(regions[visible], weights=weights[visible], minlength=count),
        sizes,
        out=np.zeros(count),
        where=sizes > 0,
    )
    masks = view.labels[:, level].astype(np.int64)
    labelled = counted & (masks >= 0)
    if not labelled.any():
        return
    shares = _pooled(regions[labelled], masks[labelled], weights[labelled], (count, len(features)))
    labelled_per_region = np.asarray(shares.sum(axis=1)).ravel()
    shares.data = shares.data / np.repeat(labelled_per_region, np.diff(shares.indptr))
    shares.data[shares.data < config.min_share] = 0.0
    shares.eliminate_zeros()
    _accumulate(out, shares, features, share_visible)


def _centres_view(
    out: np.ndarray,
    labels: np.ndarray,
    sizes: np.ndarray,
    view: ViewLift,
    features: np.ndarray,
    means: np.ndarray,
    camera: Cameras,
    segments: np.ndarray,
    config: FeatureConfig,
) -> None:
    count = len(sizes)
    used = view.max_weights > config.centre_weight
    gaussians = view.gaussians[used].astype(np.int64)
    weights = view.max_weights[used].astype(np.float64)
    regions = labels[gaussians]
    portion = np.divide(
        np.bincount(regions, minlength=count).astype(np.float64),
        sizes,
        out=np.zeros(count),
        where=sizes > 0,
    )
    eligible = (portion >= config.min_visible) & (portion > 0)
    keep = eligible[regions]
    gaussians, weights, regions = gaussians[keep], weights[keep], regions[keep]
    if len(gaussians) == 0:
        return
    masks = centre_masks(means, camera, segments, gaussians)
    hit = masks >= 0
    if not hit.any():
        return
    pooled = _pooled(regions[hit], masks[hit], weights[hit], (count, len(features)))
    _accumulate(out, pooled, features, portion)


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
    start = time.perf_counter()
    if isinstance(level, bool) or level not in (1, 2, 3):
        raise InputError("level", f"must be 1, 2 or 3 (SAM levels s, m, l), got {level!r}")
    labels, count = _check_labels(labels, regions)
    dim = _check_views(lifted, guidance, len(labels), level)
    if config.mode == "centres":
        means, cameras = _check_geometry(gaussians, cameras, guidance, level, len(labels))
    sizes = np.bincount(labels, minlength=count).astype(np.float64)
    out = np.zeros((count, dim), dtype=np.float64)
    for i, (view, masks) in enumerate(zip(lifted, guidance)):
        if len(view) == 0 or len(masks.features) == 0:
            continue
        features = masks.features.astype(np.float64)
        if config.mode == "shares":
            _shares_view(out, labels, sizes, view, features, level, config)
        else:
            camera = cameras.select([i])
            segments = masks.segments[level]
            _centres_view(out, labels, sizes, view, features, means, camera, segments, config)
    norms = np.linalg.norm(out, axis=1)
    seen = norms > 0
    out[seen] /= norms[seen, None]
    logger.info(
        "region features (%s) at level %d: %d of %d regions seen in %d views (%.2f s)",
        config.mode,
        level,
        int(seen.sum()),
        count,
        len(lifted),
        time.perf_counter() - start,
    )
    return out.astype(np.float32), seen
