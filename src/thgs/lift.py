"""Lifting 2D masks onto Gaussians (design §4.2): per view, one label per Gaussian and mask level.

For every view, one rasterization pass weighs each Gaussian's blending weight by the mask under
each pixel, for all four mask levels at once (:func:`thgs.render.splat_labels`: per (Gaussian,
level, mask) the summed weight ``W``). Both methods decide from these sums:

- ``latent`` (the paper): the sum of the splatted codes is ``y = Σ_t W_t · Y_t + W_bg · β ·
  Y_bg`` (``W_bg`` the weight on pixels without a mask), exactly what splatting the code map back
  gives, without materialising a [H, W, 4·D] map;
- ``exact``: the mask with the largest share ``W_t / Σ_x w(x)``.

Each view keeps, for the Gaussians it sees, the mask per level (or none), the camera-space depth
of the centre and the largest blending weight ``max_x w(x)`` (:class:`ViewLift`, 20 bytes per seen
Gaussian and view). For 1M Gaussians × 200 views that is 4 GB × the share of Gaussians a view
sees: about 1.2 GB for LERF-like captures (~30 % per view), 2.7 GB for the synthetic scenes, whose
views show the whole table (68 % measured on ``synth-small``).

Everything stays on the Gaussians' device. On the CPU with the numba backend several views are
lifted at once, one per thread (:func:`lift_views`); each view's result does not depend on that.
"""

from __future__ import annotations

import logging
from collections import deque
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Literal

import numba
import numpy as np
import torch
from torch import Tensor

from thgs._lift_numba import latent_labels_kernel
from thgs.errors import InputError
from thgs.guidance import LEVELS, ViewGuidance
from thgs.render import LabelWeights, RasterConfig, resolve_backend, splat_labels
from thgs.scene import Cameras, Gaussians

__all__ = [
    "LiftConfig",
    "ViewLift",
    "iter_lift_views",
    "lift_view",
    "lift_views",
    "views_at_once",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class LiftConfig:
    """How masks are lifted onto Gaussians.

    Attributes:
        method: ``"latent"`` — the paper's latent label encoding: each mask gets a seeded random
            unit code of ``code_dim`` dimensions, pixels without a mask a background code scaled
            by ``background_scale``; the codes are splatted back, each Gaussian's sum is
            normalized and takes the mask of the most similar code if the cosine exceeds
            ``cosine_threshold`` (the background code wins → no label). ``"exact"`` — the
            blending weight of each Gaussian is summed per mask, and it takes the mask holding
            the largest share of its total weight (pixels without a mask count in the total) if
            that share exceeds ``share_threshold``. No projection noise, no limit on masks.
        code_dim: D of the latent codes (reference 20; from 2 to 1,024).
        cosine_threshold: τ of the latent method (reference 0.85; 0.5 for reweighting on 3DOVS).
        background_scale: length of the background code in the splatted map (reference
            ``zero_scale`` 0.2 on LERF): smaller lets a Gaussian that sees some background keep
            its mask.
        share_threshold: τ of the exact method, a share of the Gaussian's weight in (0, 1).
        seed: latent codes of view i are drawn from ``[seed, i]`` (the reference does not seed).
        raster: rasterization settings of the splat-back (and the backend that runs it).
    """

    method: Literal["latent", "exact"] = "latent"
    code_dim: int = 20
    cosine_threshold: float = 0.85
    background_scale: float = 0.2
    share_threshold: float = 0.5
    seed: int = 0
    raster: RasterConfig = field(default_factory=RasterConfig)

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> LiftConfig:
        if self.method not in ("latent", "exact"):
            raise InputError(
                "LiftConfig.method", f"must be 'latent' or 'exact', got {self.method!r}"
            )
        if not 2 <= self.code_dim <= 1024:
            raise InputError(
                "LiftConfig.code_dim", f"must be from 2 to 1,024, got {self.code_dim:,}"
            )
        if not 0.0 <= self.share_threshold < 1.0:
            raise InputError("LiftConfig.share_threshold", "must be in [0, 1)")
        return self


def _tensor(value: Tensor | np.ndarray) -> Tensor:
    return value if isinstance(value, Tensor) else torch.from_numpy(np.ascontiguousarray(value))


@dataclass(frozen=True, eq=False)
class ViewLift:
    """The lifted masks of one view, for the Gaussians the view sees (torch tensors on one
    device; NumPy arrays given to the constructor become tensors on the CPU).

    Attributes:
        gaussians: [n] int32 indices of the Gaussians with ``max_weights > 0``, ascending.
        labels: [n, 4] int16 mask id per level (``thgs.guidance.LEVELS`` order: default, s, m, l;
            int32 if the view has more than 32767 masks),
            the view's global mask id as in its guidance (the row of the mask's feature), −1 = no
            confident label (background, ambiguous, or below the threshold).
        depths: [n] float32 camera-space z of each Gaussian's centre (scene units).
        max_weights: [n] float32 ``max_x w(x)`` over the view's pixels, in (0, 1].
    """

    gaussians: Tensor
    labels: Tensor
    depths: Tensor
    max_weights: Tensor

    def __post_init__(self) -> None:
        for name in ("gaussians", "labels", "depths", "max_weights"):
            object.__setattr__(self, name, _tensor(getattr(self, name)))

    def __len__(self) -> int:
        return int(self.gaussians.shape[0])

    @property
    def device(self) -> torch.device:
        return self.gaussians.device

    def dense_labels(self, level: int, count: int) -> Tensor:
        """[count] int32 labels of every Gaussian at ``level`` (−1 where unseen or unlabelled)."""
        out = torch.full((count,), -1, dtype=torch.int32, device=self.device)
        out[self.gaussians.long()] = self.labels[:, level].int()
        return out

    def compact(self) -> ViewLift:
        """The same lift with labels stored as int16 when every id fits."""
        fits = len(self.labels) == 0 or int(self.labels.max()) < torch.iinfo(torch.int16).max
        labels = self.labels.to(torch.int16 if fits else torch.int32)
        return ViewLift(self.gaussians, labels, self.depths, self.max_weights)

    def to(self, device: torch.device | str) -> ViewLift:
        """A copy on ``device``."""
        return ViewLift(
            self.gaussians.to(device),
            self.labels.to(device),
            self.depths.to(device),
            self.max_weights.to(device),
        )

    def check(self, count: int, source: str = "ViewLift") -> ViewLift:
        """Raise :class:`InputError` unless shapes, dtypes and devices agree and indices lie in
        ``[0, count)``."""
        n = len(self)
        if self.gaussians.ndim != 1 or self.gaussians.is_floating_point():
            raise InputError(source, "gaussians must be [n] integer indices")
        if tuple(self.labels.shape) != (n, 4) or tuple(self.depths.shape) != (n,):
            raise InputError(source, "labels must be [n, 4] and depths [n] for n Gaussians")
        if tuple(self.max_weights.shape) != (n,):
            raise InputError(source, "max_weights must be [n]")
        if self.labels.is_floating_point():
            raise InputError(source, f"labels must be integers, not {self.labels.dtype}")
        devices = {t.device for t in (self.gaussians, self.labels, self.depths, self.max_weights)}
        if len(devices) != 1:
            raise InputError(source, f"tensors on several devices: {sorted(map(str, devices))}")
        if n and (int(self.gaussians.min()) < 0 or int(self.gaussians.max()) >= count):
            raise InputError(source, f"Gaussian indices outside [0, {count})")
        if n > 1 and not bool((self.gaussians[1:] > self.gaussians[:-1]).all()):
            raise InputError(source, "Gaussian indices must be strictly ascending")
        return self


def latent_codes(
    features: int, view_index: int, config: LiftConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The seeded codes of one view: [features, D] unit mask codes and [4, D] unit background
    codes (one per level), float64, drawn from ``[config.seed, view_index]``."""
    rng = np.random.default_rng([config.seed, view_index])
    codes = rng.normal(size=(features, config.code_dim))
    codes /= np.linalg.norm(codes, axis=1, keepdims=True)
    background = rng.normal(size=(len(LEVELS), config.code_dim))
    background /= np.linalg.norm(background, axis=1, keepdims=True)
    return codes, background


def _present(segments: Tensor, count: int) -> Tensor:
    """[4, count] bool: which mask ids occur at each level of ``segments`` [4, H, W]."""
    return torch.stack(
        [
            torch.bincount(segments[level].reshape(-1) + 1, minlength=count + 1)[1:] > 0
            for level in range(segments.shape[0])
        ]
    )


@dataclass(frozen=True, eq=False)
class _Weighed:
    """One view's per-mask weights, indexed by the rows of the Gaussians the view sees.

    Attributes:
        seen: [n] int64 ascending indices of the Gaussians with ``max_x w(x) > 0``.
        rows: [P] int64 row in ``seen`` of every (Gaussian, level, mask) weight.
        totals: [n] ``Σ_x w(x)`` of the seen Gaussians.
        weights: the :class:`thgs.render.LabelWeights` they come from.
    """

    seen: Tensor
    rows: Tensor
    totals: Tensor
    weights: LabelWeights


def _weighed(weights: LabelWeights) -> _Weighed:
    visible = weights.max_weights > 0
    seen = torch.nonzero(visible)[:, 0]
    row_of = torch.cumsum(visible, 0) - 1  # the row of every seen Gaussian
    rows = row_of[weights.gaussians]  # every weighted Gaussian is seen
    return _Weighed(seen, rows, weights.weight_sums[seen], weights)


def _latent_labels(
    weighed: _Weighed, present: Tensor, view_index: int, count: int, config: LiftConfig
) -> Tensor:
    """[n, 4] labels of the latent method: per level ``y = Σ_t W_t·Y_t + β·W_bg·Y_bg``,
    normalized, against every code of the level's masks and the background code.

    On the CPU the compiled kernel of :mod:`thgs._lift_numba` gives the same labels faster (it
    skips the masks that provably cannot win)."""
    weights = weighed.weights
    device, dtype = weights.weights.device, weights.weights.dtype
    codes_np, background_np = latent_codes(count, view_index, config)
    n = len(weighed.seen)
    if device.type == "cpu" and dtype == torch.float64:
        return torch.from_numpy(
            latent_labels_kernel(
                n,
                weighed.rows.numpy(),
                weights.levels.numpy(),
                weights.labels.numpy(),
                weights.weights.numpy(),
                weighed.totals.numpy(),
                codes_np,
                background_np,
                present.numpy(),
                config.background_scale,
                config.cosine_threshold,
            )
        )
    return _latent_labels_torch(weighed, present, codes_np, background_np, config)


def _latent_labels_torch(
    weighed: _Weighed,
    present: Tensor,
    codes_np: np.ndarray,
    background_np: np.ndarray,
    config: LiftConfig,
) -> Tensor:
    """The latent decision in torch on any device (every code compared with every sum)."""
    weights = weighed.weights
    device, dtype = weights.weights.device, weights.weights.dtype
    codes = torch.from_numpy(codes_np).to(device=device, dtype=dtype)
    background = torch.from_numpy(background_np).to(device=device, dtype=dtype)
    n = len(weighed.seen)
    labels = torch.full((n, len(LEVELS)), -1, dtype=torch.int64, device=device)
    for level in range(len(LEVELS)):
        ids = torch.nonzero(present[level])[:, 0]
        if n == 0 or len(ids) == 0:
            continue
        at = weights.levels == level
        row, label, weight = weighed.rows[at], weights.labels[at], weights.weights[at]
        sums = torch.zeros(n, config.code_dim, dtype=dtype, device=device)
        sums.index_add_(0, row, weight[:, None] * codes[label])
        labelled = torch.zeros(n, dtype=dtype, device=device)
        labelled.index_add_(0, row, weight)
        unlabelled = weighed.totals - labelled
        sums += (config.background_scale * unlabelled)[:, None] * background[level]
        norms = torch.linalg.vector_norm(sums, dim=1, keepdim=True)
        vectors = sums / torch.where(norms > 0, norms, torch.ones_like(norms))
        candidates = torch.cat([codes[ids], background[level][None]])
        best_cosine, best = (vectors @ candidates.T).max(dim=1)
        confident = (best < len(ids)) & (best_cosine > config.cosine_threshold)
        labels[confident, level] = ids[best[confident]]
    return labels


def _exact_labels(weighed: _Weighed, config: LiftConfig) -> Tensor:
    """[n, 4] labels of the exact method: per (Gaussian, level) the mask of largest weight (the
    largest id on ties), kept if its share of the Gaussian's weight exceeds the threshold."""
    weights = weighed.weights
    device, levels, n = weights.weights.device, len(LEVELS), len(weighed.seen)
    labels = torch.full((n * levels,), -1, dtype=torch.int64, device=device)
    if len(weights.weights):
        group = weighed.rows * levels + weights.levels
        best = torch.zeros(n * levels, dtype=weights.weights.dtype, device=device)
        best.scatter_reduce_(0, group, weights.weights, reduce="amax", include_self=False)
        winner = weights.weights == best[group]
        chosen = torch.full((n * levels,), -1, dtype=torch.int64, device=device)
        chosen.scatter_reduce_(0, group[winner], weights.labels[winner], reduce="amax")
        share = best / weighed.totals.repeat_interleave(levels)
        keep = (chosen >= 0) & (share > config.share_threshold)
        labels[keep] = chosen[keep]
    return labels.reshape(n, levels)


def _decide(
    weights: LabelWeights,
    guidance: ViewGuidance,
    segments: Tensor,
    view_index: int,
    config: LiftConfig,
) -> ViewLift:
    """A view's :class:`ViewLift` from its per-mask weights."""
    weighed = _weighed(weights)
    if config.method == "latent":
        count = len(guidance.features)
        labels = _latent_labels(weighed, _present(segments, count), view_index, count, config)
    else:
        labels = _exact_labels(weighed, config)
    return ViewLift(
        gaussians=weighed.seen.to(torch.int32),
        labels=labels,
        depths=weights.depths[weighed.seen].to(torch.float32),
        max_weights=weights.max_weights[weighed.seen].to(torch.float32),
    ).compact()


def _segments(gaussians: Gaussians, camera: Cameras, guidance: ViewGuidance) -> Tensor:
    """The view's [4, H, W] int64 masks on the Gaussians' device, checked against the camera."""
    height, width = int(camera.heights[0]), int(camera.widths[0])
    if (guidance.height, guidance.width) != (height, width):
        raise InputError(
            f"guidance {guidance.stem}",
            f"masks are {guidance.width}×{guidance.height} but the camera is {width}×{height}; "
            "resample the masks with --resize (load_guidance(resize=True))",
        )
    return torch.from_numpy(guidance.segments.astype(np.int64)).to(gaussians.device)


def lift_view(
    gaussians: Gaussians,
    camera: Cameras,
    guidance: ViewGuidance,
    view_index: int = 0,
    config: LiftConfig = LiftConfig(),
) -> ViewLift:
    """Lift one view's masks (all four levels) onto the Gaussians in one rasterization pass.

    Args:
        gaussians: N Gaussians, world frame.
        camera: the view's camera (one); its size must equal the guidance's.
        guidance: the view's masks and features (:func:`thgs.guidance.load_guidance`).
        view_index: the view's position (seeds the latent codes).
        config: method, thresholds and rasterization (backend included).

    Returns:
        a :class:`ViewLift` for the Gaussians contributing to some pixel, on the Gaussians'
        device.

    Raises:
        InputError: the guidance's resolution differs from the camera's (resample it explicitly
            with ``load_guidance(..., resize=True)``), or the backend cannot run on the device.
    """
    config.check()
    segments = _segments(gaussians, camera, guidance)
    weights = splat_labels(gaussians, camera, segments, config=config.raster)
    lifted = _decide(weights, guidance, segments, view_index, config)
    return lifted.check(len(gaussians), source=f"lift of {guidance.stem}")


def views_at_once(gaussians: Gaussians, config: LiftConfig) -> int:
    """Views lifted at once: one per numba thread for the numba backend (its kernels run a view
    serially and release the GIL); one on accelerators, which are parallel within a view."""
    backend, _ = resolve_backend(config.raster, gaussians.device)
    return numba.get_num_threads() if backend.name == "numba" else 1


def _weights_in_order(
    gaussians: Gaussians,
    cameras: Cameras,
    segments: Callable[[int], Tensor],
    count: int,
    config: LiftConfig,
) -> Iterator[tuple[int, Tensor, LabelWeights]]:
    """Each view's masks and per-mask weights, in view order; with several workers the next
    views are computed while one is decided (at most ``workers`` ahead, to bound memory)."""
    workers = views_at_once(gaussians, config)

    def weigh(index: int) -> tuple[int, Tensor, LabelWeights]:
        maps = segments(index)
        camera = cameras.select([index])
        return index, maps, splat_labels(gaussians, camera, maps, config=config.raster)

    if workers == 1:
        for index in range(count):
            yield weigh(index)
        return
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="thgs-lift") as pool:
        pending: deque = deque()
        for index in range(count):
            pending.append(pool.submit(weigh, index))
            if len(pending) > workers:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()


def iter_lift_views(
    gaussians: Gaussians,
    cameras: Cameras,
    guidance: Sequence[ViewGuidance],
    config: LiftConfig = LiftConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> Iterator[ViewLift]:
    """:func:`lift_views` one view at a time, in camera order (the same views): a caller that
    does not keep them all holds only the views being computed.

    Raises:
        InputError: as :func:`lift_views`, before the first view is computed.
    """
    config.check()
    if [view.stem for view in guidance] != list(cameras.stems):
        raise InputError("guidance", "must hold one view per camera, in camera order (by stem)")
    for i, view in enumerate(guidance):
        _segments(gaussians, cameras.select([i]), view)  # check every size before any work
    return _lifted(gaussians, cameras, guidance, config, progress)


def _lifted(
    gaussians: Gaussians,
    cameras: Cameras,
    guidance: Sequence[ViewGuidance],
    config: LiftConfig,
    progress: Callable[[int, int], None] | None,
) -> Iterator[ViewLift]:
    views = _weights_in_order(
        gaussians,
        cameras,
        lambda i: _segments(gaussians, cameras.select([i]), guidance[i]),
        len(guidance),
        config,
    )
    for index, segments, weights in views:
        view = _decide(weights, guidance[index], segments, index, config)
        yield view.check(len(gaussians), source=f"lift of {guidance[index].stem}")
        if progress is not None:
            progress(index + 1, len(guidance))


def lift_views(
    gaussians: Gaussians,
    cameras: Cameras,
    guidance: Sequence[ViewGuidance],
    config: LiftConfig = LiftConfig(),
    progress: Callable[[int, int], None] | None = None,
) -> list[ViewLift]:
    """:func:`lift_view` for every camera (view i with ``guidance[i]``), the same results.

    With the numba backend, views are rasterized in parallel, one per numba thread
    (``NUMBA_NUM_THREADS``), each holding its view's per-mask weights until it is decided.

    Raises:
        InputError: the guidance does not match the cameras one to one by stem, a view's
            resolution differs, or the backend cannot run on the device.
    """
    lifted = list(iter_lift_views(gaussians, cameras, guidance, config, progress))
    labelled = sum(int((view.labels[:, 1] >= 0).sum()) for view in lifted)
    logger.info("lifted %d views (%s): %d level-s labels", len(lifted), config.method, labelled)
    return lifted
