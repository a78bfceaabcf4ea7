"""The method's stages composed over a whole scene, with per-stage timings (design §2).

:func:`partition_scene` runs the first half of the method: lift every view's masks onto the
Gaussians, build the KNN graph, reweight it with the mask votes and cut it into level-0
superpoints. :func:`build_field` runs all of it: lift → graph → reweight → partition → merge →
features, and returns the :class:`thgs.field.SemanticField`. Each stage keeps its own config;
:class:`SuperpointConfig` and :class:`FieldConfig` only group them; they, their presets and the
reading of settings live in :mod:`thgs.field_config` (re-exported here).
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Protocol

import numpy as np
import torch

from thgs.build_ray import ray_lift_views
from thgs.errors import InputError
from thgs.features import FeatureConfig, level_features
from thgs.field import SemanticField, scene_fingerprint
from thgs.field_config import (
    PRESETS,
    FieldConfig,
    SuperpointConfig,
    chosen_field_config,
    lifted_raster,
    read_field_config,
    recorded_config,
)
from thgs.graph import (
    edge_counts,
    knn_graph,
    partition,
    reweight,
)
from thgs.guidance import ViewGuidance, check_masks
from thgs.hierarchy import (
    RegionLevels,
    gaussian_neighbors,
    group_repeated_parts,
    merge_levels,
)
from thgs.lift import LiftConfig, ViewLift, iter_lift_views, views_at_once
from thgs.lift_cache import lift_cache_path, lift_key, read_cached_lift, write_lift
from thgs.lift_store import DEFAULT_LIFT_MEMORY, LiftStore, lift_bytes
from thgs.memory import check_build_memory
from thgs.provenance import Provenance, installed_version
from thgs.scene import Cameras, Gaussians

__all__ = [
    "PRESETS",
    "BuiltLevels",
    "FieldConfig",
    "LiftedScene",
    "MergedLevels",
    "PartitionReport",
    "PosedScene",
    "SuperpointConfig",
    "build_field",
    "build_levels",
    "chosen_field_config",
    "describe_levels",
    "lift_scene",
    "lifted_raster",
    "merge_lifted",
    "partition_lifted",
    "partition_scene",
    "read_field_config",
    "recorded_config",
]

logger = logging.getLogger(__name__)

Progress = Callable[[str, int, int], None]
"""``progress(stage, done, total)``: called as a stage advances. ``"lift"`` reports every view;
in :func:`build_field` every other stage reports ``(stage, 0, 1)`` when it starts and
``(stage, 1, 1)`` when it ends."""


class PosedScene(Protocol):
    """Gaussians and the cameras of their views: :class:`thgs.Scene` or a synthetic scene."""

    @property
    def gaussians(self) -> Gaussians: ...

    @property
    def cameras(self) -> Cameras | None: ...


@dataclass(frozen=True)
class PartitionReport:
    """What :func:`partition_scene` did.

    Attributes:
        gaussians: N.
        views: number of views lifted.
        views_without_masks: views whose guidance has no mask at all.
        superpoints: S0, the number of level-0 superpoints.
        edges: present directed KNN edges.
        voted_edges: directed edges with at least one vote (positive or negative).
        labelled_share: share of (Gaussian, view) pairs seen by a view that carry a label at
            the voting level, in [0, 1].
        seconds: wall time per stage: ``lift``, ``knn``, ``votes``, ``reweight``, ``partition``.
    """

    gaussians: int
    views: int
    views_without_masks: int
    superpoints: int
    edges: int
    voted_edges: int
    labelled_share: float
    seconds: dict[str, float]

    def lines(self) -> list[str]:
        """A human-readable summary, one fact per line."""
        timings = ", ".join(f"{stage} {value:.2f} s" for stage, value in self.seconds.items())
        return [
            f"{self.gaussians:,} Gaussians, {self.views} views "
            f"({self.views_without_masks} without masks)",
            f"{self.edges:,} KNN edges, {self.voted_edges:,} with mask votes; "
            f"{self.labelled_share:.1%} of seen Gaussians labelled",
            f"{self.superpoints:,} superpoints "
            f"({self.gaussians / max(self.superpoints, 1):.1f} Gaussians each)",
            f"time: {timings} (total {sum(self.seconds.values()):.2f} s)",
        ]


def partition_lifted(
    gaussians: Gaussians,
    lifted: Sequence[ViewLift],
    config: SuperpointConfig = SuperpointConfig(),
    *,
    ray: bool = False,
) -> tuple[np.ndarray, PartitionReport]:
    """Level-0 superpoints from masks already lifted (:func:`thgs.lift.lift_views`).

    Args:
        gaussians: the N Gaussians (world frame, scene units).
        lifted: one :class:`thgs.lift.ViewLift` per view.
        config: graph, reweighting and partition settings (``config.lift`` is not used).
        ray: solve the partition's blocks as Ray tasks (:func:`thgs.graph.partition`).

    Returns:
        ``(labels, report)``: [N] int32 superpoint ids 0 … S−1 (see :func:`thgs.graph.partition`)
        and a :class:`PartitionReport` without lifting time or mask-less views.

    Raises:
        InputError: no Gaussians, or a lift that does not index these Gaussians.
    """
    n = len(gaussians)
    if n == 0:
        raise InputError("scene", "has no Gaussians to partition")
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    graph = knn_graph(gaussians, config.graph)
    seconds["knn"] = time.perf_counter() - started
    started = time.perf_counter()
    pos, neg = edge_counts(graph, lifted, config.reweight)
    seconds["votes"] = time.perf_counter() - started
    started = time.perf_counter()
    distances = reweight(graph, pos, neg, config.reweight)
    seconds["reweight"] = time.perf_counter() - started
    started = time.perf_counter()
    labels = partition(gaussians, graph, distances, config.partition, ray=ray)
    seconds["partition"] = time.perf_counter() - started
    seen = sum(len(view) for view in lifted)
    labelled = sum(int((view.labels[:, config.reweight.level] >= 0).sum()) for view in lifted)
    report = PartitionReport(
        gaussians=n,
        views=len(lifted),
        views_without_masks=0,
        superpoints=int(labels.max()) + 1,
        edges=int(graph.valid().sum()),
        voted_edges=int(((pos > 0) | (neg > 0)).sum()),
        labelled_share=labelled / seen if seen else 0.0,
        seconds=seconds,
    )
    return labels, report


def _checked_inputs(
    scene: PosedScene, guidance: Sequence[ViewGuidance]
) -> tuple[Gaussians, Cameras]:
    gaussians, cameras = scene.gaussians, scene.cameras
    if len(gaussians) == 0:
        raise InputError("scene", "has no Gaussians to partition")
    if cameras is None:
        raise InputError(
            "scene", "has no cameras to lift masks with: give the training data with --source"
        )
    if len(guidance) != len(cameras):
        raise InputError(
            "guidance", f"{len(guidance)} views of guidance for {len(cameras)} cameras"
        )
    for view in guidance:
        view.check(source=f"guidance of view {view.stem}")
    return gaussians, cameras


@dataclass(frozen=True, eq=False)
class LiftedScene:
    """A scene's views lifted onto its Gaussians once, to build several fields from.

    Attributes:
        gaussians: the N Gaussians; cameras: the M cameras, in guidance order.
        lifted: one :class:`thgs.lift.ViewLift` per view: a list, or a
            :class:`thgs.lift_store.LiftStore` reading them back from a temporary file when
            they outgrew the memory budget of :func:`lift_scene`.
        config: the lifting settings used.
        views_without_masks: views whose guidance has no mask.
        seconds: wall time of the lifting.
    """

    gaussians: Gaussians
    cameras: Cameras
    lifted: Sequence[ViewLift]
    config: LiftConfig
    views_without_masks: int
    seconds: float


def _check_features(guidance: Sequence[ViewGuidance]) -> None:
    if not guidance or guidance[0].features.ndim != 2 or guidance[0].features.shape[1] < 1:
        raise InputError("guidance", "has no mask features (need [masks, D] with D ≥ 1)")


def _held(
    views: Iterable[ViewLift], memory: int | None, device: torch.device
) -> Sequence[ViewLift]:
    """``views`` kept in a list, moved into a :class:`LiftStore` once they exceed ``memory``
    bytes (None: never)."""
    held: list[ViewLift] | LiftStore = []
    total = 0
    for view in views:
        if isinstance(held, list) and memory is not None:
            total += lift_bytes(view)
            if total > memory:
                store = LiftStore(device)
                for kept in held:
                    store.append(kept)
                held = store
                logger.info(
                    "lift: over %.2f GB after %d views, kept in a temporary file",
                    memory / 1e9,
                    len(store),
                )
        held.append(view)
    return held


def lift_scene(
    scene: PosedScene,
    guidance: Sequence[ViewGuidance],
    config: LiftConfig = LiftConfig(),
    progress: Progress | None = None,
    *,
    cache: str | os.PathLike[str] | None = None,
    memory: int | None = DEFAULT_LIFT_MEMORY,
    ray: bool = False,
) -> LiftedScene:
    """Every view's masks lifted onto the Gaussians, after checking the inputs (the first stage
    of :func:`partition_scene` and :func:`build_field`).

    Args:
        cache: a folder keeping lifts (:mod:`thgs.lift_cache`): a lift of the same Gaussians,
            cameras, guidance and settings is read from it instead of computed (the same
            tensors), and a computed one is written to it. None: no cache.
        memory: bytes of lifted views held in memory; past that the views go to a temporary
            file (:class:`thgs.lift_store.LiftStore`) and are read back when used. The same
            views either way. None: always in memory.
        ray: lift the views as Ray tasks (:func:`thgs.build_ray.ray_lift_views`: the same
            views), on the Ray this process is connected to (:func:`thgs.cluster.connect_ray`).

    Raises:
        InputError: the inputs :func:`partition_scene` refuses, or ``memory`` is negative.
        ThgsError: the device has less memory left than the build needs at least
            (:func:`thgs.memory.check_build_memory`), before any work.
    """
    if memory is not None and (isinstance(memory, bool) or memory < 0):
        raise InputError("memory", f"must be a number of bytes ≥ 0 or None, got {memory!r}")
    if cache is not None and Path(cache).exists() and not Path(cache).is_dir():
        raise InputError(cache, "is a file; the lift cache is a folder (lift_cache, --lift-cache)")
    gaussians, cameras = _checked_inputs(scene, guidance)
    device = gaussians.device
    check_build_memory(
        len(gaussians),
        len(cameras),
        int(cameras.widths.max()),
        int(cameras.heights.max()),
        memory,
        0 if ray else views_at_once(gaussians, config),
        device,
    )
    empty = [view.stem for view in guidance if not (view.segments >= 0).any()]
    if len(empty) == len(guidance):
        logger.warning("no view has any mask: superpoints come from geometry and colour alone")
    elif empty:
        logger.warning(
            "%d of %d views have no masks (first: %s)", len(empty), len(guidance), empty[0]
        )
    started = time.perf_counter()
    key = lifted = None
    if cache is not None:
        key = lift_key(gaussians, cameras, guidance, config)
        lifted = read_cached_lift(
            lift_cache_path(cache, key),
            key,
            len(guidance),
            collect=lambda views: _held(
                (
                    view.to(device).check(len(gaussians), source=f"cached lift of {g.stem}")
                    for view, g in zip(views, guidance)
                ),
                memory,
                device,
            ),
        )
    if lifted is not None:
        if progress is not None:
            progress("lift", len(lifted), len(lifted))
    else:
        lift = ray_lift_views if ray else iter_lift_views
        views = lift(
            gaussians,
            cameras,
            guidance,
            config,
            progress=None
            if progress is None
            else lambda done, total: progress("lift", done, total),
        )
        lifted = _held(views, memory, device)
        if cache is not None and key is not None:
            write_lift(lift_cache_path(cache, key), key, lifted)
    seconds = time.perf_counter() - started
    logger.info("lift: %d views in %.2f s", len(lifted), seconds)
    return LiftedScene(gaussians, cameras, lifted, config, len(empty), seconds)


def partition_scene(
    scene: PosedScene,
    guidance: Sequence[ViewGuidance],
    config: SuperpointConfig = SuperpointConfig(),
    progress: Progress | None = None,
) -> tuple[np.ndarray, PartitionReport]:
    """Level-0 superpoints of a scene from its views' masks: lift → KNN → reweight → partition.

    Args:
        scene: N Gaussians and M cameras (:func:`thgs.load_scene` with a source, or a
            :class:`thgs.synthetic.SyntheticScene`).
        guidance: M views of masks, in camera order and matched by stem
            (:func:`thgs.guidance.load_guidance`), each at its camera's resolution.
        config: one config per stage; :meth:`SuperpointConfig.lerf` and
            :meth:`SuperpointConfig.three_dovs` give the reference's numbers.
        progress: optional ``progress(stage, done, total)`` callback.

    Returns:
        ``(labels, report)``: [N] int32 superpoint ids 0 … S−1, each superpoint connected in the
        KNN graph, the same for the same inputs, config and thread count; and a
        :class:`PartitionReport` with counts and per-stage times.

    Raises:
        InputError: no Gaussians or no cameras; guidance that does not match the cameras (count,
            stems, resolution) or is malformed (mask ids outside its feature table). Views
            without masks are allowed (logged): they carry no votes.
    """
    lifted = lift_scene(scene, guidance, config.lift, progress)
    labels, report = partition_lifted(lifted.gaussians, lifted.lifted, config)
    report = replace(
        report,
        views_without_masks=lifted.views_without_masks,
        seconds={"lift": lifted.seconds, **report.seconds},
    )
    for line in report.lines():
        logger.info("%s", line)
    return labels, report


@dataclass(frozen=True, eq=False)
class BuiltLevels:
    """Regions at levels 0–3 and their features, before they become a field.

    Attributes:
        levels: the regions (:class:`thgs.hierarchy.RegionLevels`); not nested (``parents``
            None) for merge mode ``independent``.
        features: level k at index k − 1: [R_k, D] float32 unit rows (zero rows unseen).
        seen: level k at index k − 1: [R_k] bool.
        timings: wall time per stage (lifting excluded).
    """

    levels: RegionLevels
    features: tuple[np.ndarray, np.ndarray, np.ndarray]
    seen: tuple[np.ndarray, np.ndarray, np.ndarray]
    timings: dict[str, float]


def _features(
    labels: np.ndarray,
    levels: Sequence[int],
    lifted: LiftedScene,
    guidance: Sequence[ViewGuidance],
    config: FeatureConfig,
    within: np.ndarray | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Features and seen flags of the regions of [N, 4] labels at ``levels``, in one pass."""
    return level_features(
        labels[:, list(levels)],
        levels,
        lifted.lifted,
        guidance,
        config,
        gaussians=lifted.gaussians,
        cameras=lifted.cameras,
        within=within,
    )


def _regrouped_part_features(
    before: np.ndarray,
    after: np.ndarray,
    features: tuple[np.ndarray, np.ndarray],
    lifted: LiftedScene,
    guidance: Sequence[ViewGuidance],
    config: FeatureConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Level-2 features after repeated parts were grouped: a region made of one former region
    keeps its feature; a joined one is computed again over its own Gaussians only.

    Args:
        before, after: [N] level-2 regions before and after grouping.
        features: ``(features, seen)`` of the regions before.
    """
    pairs = np.unique(np.stack([after, before], axis=1), axis=0)
    count = int(after.max()) + 1
    pieces = np.bincount(pairs[:, 0], minlength=count)
    out_features = np.zeros((count, features[0].shape[1]), dtype=features[0].dtype)
    out_seen = np.zeros(count, dtype=bool)
    single = pieces[pairs[:, 0]] == 1
    out_features[pairs[single, 0]] = features[0][pairs[single, 1]]
    out_seen[pairs[single, 0]] = features[1][pairs[single, 1]]
    joined = pieces > 1
    if joined.any():
        labels = np.zeros((len(after), 4), dtype=np.int64)
        labels[:, 2] = after
        again, seen = _features(labels, (2,), lifted, guidance, config, within=joined[after])[0]
        out_features[joined], out_seen[joined] = again[joined], seen[joined]
    return out_features, out_seen


@dataclass(frozen=True, eq=False)
class MergedLevels:
    """Regions at levels 0–3 before their features (:func:`merge_lifted`): everything of a
    build that depends on the masks alone, so fields whose guidance differs only in its
    features share it (:func:`describe_levels`).

    Attributes:
        levels: the regions (:class:`thgs.hierarchy.RegionLevels`) before repeated parts are
            grouped (grouping reads the part features).
        neighbors: [N, k] each Gaussian's nearest Gaussians (the merging's adjacency), shared
            with the grouping of repeated parts.
        timings: wall time per stage (lifting excluded).
    """

    levels: RegionLevels
    neighbors: np.ndarray
    timings: dict[str, float]


def _check_lifted(lifted: LiftedScene, config: FieldConfig) -> None:
    if lifted.config != config.superpoints.lift:
        raise InputError(
            "lifted",
            "was lifted with other settings than config.superpoints.lift; lift again "
            "(thgs.pipeline.lift_scene) with the config's",
        )


def merge_lifted(
    lifted: LiftedScene,
    config: FieldConfig = FieldConfig(),
    *,
    progress: Progress | None = None,
    ray: bool = False,
) -> MergedLevels:
    """Graph → reweight → partition → merge on views lifted by :func:`lift_scene` (the first
    half of :func:`build_levels`); with ``ray`` the partition's blocks are solved as Ray tasks.

    Raises:
        InputError: ``lifted`` was made with other lifting settings than ``config``'s.
    """
    _check_lifted(lifted, config)

    def stage(name: str, done: int) -> None:
        if progress is not None:
            progress(name, done, 1)

    gaussians = lifted.gaussians
    stage("partition", 0)
    superpoints, report = partition_lifted(gaussians, lifted.lifted, config.superpoints, ray=ray)
    stage("partition", 1)
    for name in ("knn", "votes", "reweight", "partition"):
        logger.info("%s: %.2f s", name, report.seconds[name])
    stage("merge", 0)
    started = time.perf_counter()
    neighbors = gaussian_neighbors(gaussians, config.merge.neighbors)
    adjacency_seconds = time.perf_counter() - started
    merge = merge_levels(gaussians, superpoints, lifted.lifted, config.merge, neighbors=neighbors)
    merge_seconds = {**merge.seconds}
    merge_seconds["adjacency"] = adjacency_seconds  # the shared neighbours, computed here
    stage("merge", 1)
    for name, seconds in merge_seconds.items():
        logger.info("merge %s: %.2f s", name, seconds)
    return MergedLevels(merge.levels, neighbors, {**report.seconds, **merge_seconds})


def describe_levels(
    merged: MergedLevels,
    lifted: LiftedScene,
    guidance: Sequence[ViewGuidance],
    config: FieldConfig = FieldConfig(),
    *,
    progress: Progress | None = None,
) -> BuiltLevels:
    """Region features, then repeated parts grouped (the second half of :func:`build_levels`):
    ``merged`` must come from :func:`merge_lifted` on ``lifted`` with ``config``, and
    ``guidance`` may differ from the guidance lifted in its features only (the masks are what
    was lifted).

    Raises:
        InputError: ``lifted`` was made with other lifting settings than ``config``'s, the
            guidance has no feature dimension, or another number of views than was lifted.
    """
    _check_lifted(lifted, config)
    _check_features(guidance)
    if len(guidance) != len(lifted.lifted):
        raise InputError("guidance", f"has {len(guidance)} views, {len(lifted.lifted)} lifted")
    if progress is not None:
        progress("features", 0, 1)
    started = time.perf_counter()
    levels = merged.levels
    features = _features(levels.labels, (1, 2, 3), lifted, guidance, config.features)
    feature_seconds = time.perf_counter() - started
    timings = dict(merged.timings)
    if config.repeats.enabled and config.merge.mode == "progressive":
        started = time.perf_counter()
        before = levels.labels[:, 2]
        shared = merged.neighbors if config.repeats.neighbors == config.merge.neighbors else None
        levels = group_repeated_parts(
            lifted.gaussians,
            levels,
            features[1][0],
            config.repeats,
            neighbors=shared,
            object_features=features[2][0],
        )
        timings["repeats"] = time.perf_counter() - started
        logger.info("merge repeats: %.2f s", timings["repeats"])
        started = time.perf_counter()
        features[1] = _regrouped_part_features(
            before, levels.labels[:, 2], features[1], lifted, guidance, config.features
        )
        feature_seconds += time.perf_counter() - started
    if progress is not None:
        progress("features", 1, 1)
    logger.info("features: %.2f s", feature_seconds)
    features_of, seen_of = zip(*features)
    return BuiltLevels(
        levels=levels,
        features=features_of,
        seen=seen_of,
        timings={**timings, "features": feature_seconds},
    )


def build_levels(
    lifted: LiftedScene,
    guidance: Sequence[ViewGuidance],
    config: FieldConfig = FieldConfig(),
    *,
    progress: Progress | None = None,
    ray: bool = False,
) -> BuiltLevels:
    """Graph → reweight → partition → merge → features on views lifted by :func:`lift_scene`
    (:func:`merge_lifted`, then :func:`describe_levels`); ``ray`` as :func:`merge_lifted`.

    Every merge mode is allowed here, ``independent`` included (its levels need not nest).

    Raises:
        InputError: ``lifted`` was made with other lifting settings than ``config``'s, or the
            guidance has no feature dimension.
    """
    _check_features(guidance)  # before the partition, not after it
    merged = merge_lifted(lifted, config, progress=progress, ray=ray)
    return describe_levels(merged, lifted, guidance, config, progress=progress)


def build_field(
    scene: PosedScene,
    guidance: Sequence[ViewGuidance],
    config: FieldConfig = FieldConfig(),
    *,
    space: str,
    progress: Progress | None = None,
    lift_cache: str | os.PathLike[str] | None = None,
    lift_memory: int | None = DEFAULT_LIFT_MEMORY,
    ray: bool = False,
) -> SemanticField:
    """The semantic field of a scene: lift → graph → reweight → partition → merge → features.

    Every view is lifted once (:func:`lift_scene`); merging and features reuse the lift
    (:func:`build_levels`). Each stage is logged with its wall time, and the times are stored
    in :attr:`SemanticField.timings` (``lift``, ``knn``, ``votes``, ``reweight``,
    ``partition``, ``adjacency``, ``level 1`` … ``level 3``, ``split`` when objects are checked
    for incoherent halves, ``absorb`` when small regions are absorbed, ``repeats`` when
    repeated parts are grouped, ``features``).

    Args:
        scene: N Gaussians and M cameras (:func:`thgs.load_scene` with cameras, or a
            :class:`thgs.synthetic.SyntheticScene`).
        guidance: M views of masks and mask features, in camera order, at the cameras'
            resolution (:func:`thgs.guidance.load_guidance`); all views share one D.
        config: the stages' configs; :meth:`FieldConfig.lerf` (the default's numbers) and
            :meth:`FieldConfig.three_dovs` are the reference's presets.
        space: the embedding space of the guidance's features (e.g. what
            :func:`thgs.guidance.read_embedding_space` returns); recorded so that queries are
            encoded in the same space.
        progress: optional ``progress(stage, done, total)`` callback (:data:`Progress`).
        lift_cache: a folder to keep and reuse the lift in (:func:`lift_scene`'s ``cache``):
            builds that differ only after the lift (merging, features, partition settings) lift
            once.
        lift_memory: bytes of lifted views held in memory (:func:`lift_scene`'s ``memory``,
            default 1 GiB); a larger lift is kept in a temporary file and read back view by
            view. The field is the same.
        ray: lift the views and solve the partition's blocks as Ray tasks, on the Ray this
            process is connected to (:func:`thgs.cluster.connect_ray`; :mod:`thgs.build_ray`).
            The field is the same.

    Returns:
        a checked :class:`thgs.field.SemanticField` with nested levels 0–3 (region counts never
        increase), unit features where seen, the scene fingerprint and ``config.to_json()``.
        Same inputs and config → the same field (timings aside).

    Raises:
        InputError: the inputs :func:`partition_scene` refuses, no feature dimension in the
            guidance, no mask in any view (:func:`thgs.guidance.check_masks`: no region could
            get a feature), an empty ``space``, or ``config.merge.mode == "independent"``.
    """
    if config.merge.mode == "independent":
        raise InputError(
            "FieldConfig.merge",
            "mode 'independent' makes levels that need not nest, and a field must nest; "
            "run thgs.pipeline.build_levels for that ablation",
        )
    if not isinstance(space, str) or not space.strip():
        raise InputError("space", "name the embedding space of the guidance features")
    _check_features(guidance)
    check_masks(guidance, "guidance")
    lifted = lift_scene(
        scene,
        guidance,
        config.superpoints.lift,
        progress,
        cache=lift_cache,
        memory=lift_memory,
        ray=ray,
    )
    built = build_levels(lifted, guidance, config, progress=progress, ray=ray)
    timings = {"lift": lifted.seconds, **built.timings}
    result = SemanticField(
        levels=built.levels,
        features=built.features,
        seen=built.seen,
        space=space,
        fingerprint=scene_fingerprint(lifted.gaussians),
        config=config.to_json(),
        timings=timings,
        provenance=Provenance(thgs_version=installed_version()),
    ).check("build_field")
    logger.info(
        "semantic field: %s regions at levels 0–3 in %.2f s",
        " → ".join(f"{count:,}" for count in result.region_counts),
        sum(timings.values()),
    )
    return result
