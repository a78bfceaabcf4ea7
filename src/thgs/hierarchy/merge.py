"""Progressive merging of level-0 superpoints into three nested levels (design §4.6).

Pass k (k = 1, 2, 3) merges the units of level k − 1 (pass 1 merges the superpoints) guided by the
labels of SAM level s, m, l lifted onto the Gaussians:

- **Evidence per view.** For unit u and view v, ``h_u^v`` is the histogram of mask labels over
  u's Gaussians labelled in v and ``s_u^v`` = (labelled Gaussians of u in v) / |u|. Ours counts
  each labelled Gaussian with weight ``(max_x w(x))^p`` (``visibility_power`` p = 2) in both, so
  a Gaussian seen faintly (at an occluder's edge, grazing, mostly hidden) adds little; the
  reference counts every label once (p = 0).
- **Affinity** of two units within two hops: ``A(u, u') = Σ_v s_u s_u' cos(h_u, h_u') /
  Σ_v s_u s_u'`` (views where either has no label add nothing; 0 without any common view). The
  formula is symmetric, so the reference's symmetrization by max changes nothing.
- **Region growing.** Units are visited in id order; an unassigned unit seeds a region, which
  grows breadth-first: a 1-hop neighbour j of a member joins when the weighted mean of A(j, r)
  over members r within two hops of j reaches the pass's threshold, each member weighted by its
  Gaussian count times ``one_hop_weight`` (2) if it is a 1-hop neighbour of j, else times
  ``two_hop_weight``. The reference meant a 3 : 1 decay but its code counts 1-hop members twice
  and 2-hop members once, which is 2 : 1 (``two_hop_weight`` 1); ours counts only the members
  that touch j (``two_hop_weight`` 0).
- **Rounds.** Ours repeats each pass on its own regions (the regions become the units, their
  histograms pooled) until a round merges nothing or ``rounds`` (10) is reached: growing is
  greedy and order-dependent, and two touching regions whose pooled evidence passes the
  threshold stay apart after one round. The reference runs one round.
- **Incoherent regions (ours).** After the last pass's rounds, a region whose two sides (cut
  along its weakest link) agree, pooled, less than the threshold is cut, again and again
  (:mod:`thgs.hierarchy.coherence`); the reference keeps what growing made.
- **Small regions.** After the last pass, a level-3 region of at most ``max_absorbed_units``
  level-2 units and fewer than ``min_region_gaussians`` Gaussians joins the touching region (not
  itself small) of highest level-3 affinity. One with no such neighbour stays its own region:
  the reference lumps all of those into one junk region that can win queries.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from itertools import chain
from typing import Literal

import numba
import numpy as np
import torch

from thgs.errors import InputError
from thgs.graph.knn import MAX_NEIGHBOURS
from thgs.hierarchy.adjacency import UnitGraph, coarsened_graph, gaussian_neighbors, unit_graph
from thgs.hierarchy.affinity import MaskEvidence, Source, mask_evidence, pair_affinity
from thgs.hierarchy.coherence import split_incoherent
from thgs.hierarchy.levels import RegionLevels, renumber_by_units
from thgs.lift import ViewLift
from thgs.scene.gaussians import Gaussians

__all__ = ["MergeConfig", "MergeResult", "merge_levels", "renumber_by_units"]

log = logging.getLogger(__name__)

MergeMode = Literal["progressive", "independent", "instance"]


MIN_SUPPORT = 1e-4
"""Default :attr:`MergeConfig.min_support`."""


@dataclass(frozen=True)
class MergeConfig:
    """How superpoints merge into levels 1–3. Defaults: the reference's LERF numbers with our
    fixes (``min_max_weight``, ``visibility_power``, ``two_hop_weight``, ``rounds``,
    ``min_support``); :meth:`as_reference` gives the authors' behaviour.

    Attributes:
        thresholds: affinity a unit needs to join a region, per pass (s, m, l): (0.9, 0.7, 0.7).
            Affinities are cosine-like, in [0, 1] for non-negative histograms.
        neighbors: k of the 3-D Gaussian KNN (itself included) that defines touching units (8;
            at most 1,000).
        one_hop_weight: weight of region members that touch the candidate, relative to members
            two hops away (2.0, the reference's effective 2 : 1).
        min_region_gaussians: after the last pass, a region with fewer Gaussians than this (and at
            most ``max_absorbed_units`` level-2 units) is absorbed (``thres_merge``: LERF 20,
            3DOVS 100). 0 disables absorption.
        max_absorbed_units: see ``min_region_gaussians`` (2).
        seg_enhance: 3DOVS option: pass 1 also uses the m-level labels of every
            ``enhance_stride``-th view.
        enhance_stride: 3.
        mode: ``"progressive"`` (the method): pass k merges level k − 1; ``"independent"``
            (ablation "no progressive merging"): every level merges the superpoints directly, so
            levels need not nest; ``"instance"`` (ablation "instance level only"): one pass with
            l labels and threshold ``thresholds[2]``, copied to levels 1–3.
        min_max_weight: a Gaussian's label in a view counts only if its ``max_x w(x)`` there
            reaches this (ours 0.05; the reference 0). Gaussians seen only through an occluder
            carry the occluder's mask; without the threshold they pollute the histograms.
        visibility_power: p: a counted label weighs ``(max_x w(x))^p`` in the unit's histogram
            and labelled share of that view (ours 2; the reference 0: every label weighs 1).
        two_hop_weight: weight of region members two hops from the candidate, against
            ``one_hop_weight`` for touching members (ours 0: touching members only; the
            reference 1).
        rounds: each pass is repeated on its own regions until a round merges nothing, at most
            this many times in all (ours 10; the reference 1).
        min_support: a pair of units whose affinity rests on less evidence than this (its
            support ``Σ_v s_a s_b``, :func:`thgs.hierarchy.pair_affinity`) has none, and does
            not merge (ours 1e-4, :data:`MIN_SUPPORT`; the reference 0). Without it a unit
            glimpsed in a view or two with vanishing weight takes affinity 1 with whatever mask
            covered it there.
        split_incoherent: after the last pass, cut each object along its weakest link between
            sub-parts while the two sides, pooled, agree less than the pass's threshold
            (:func:`thgs.hierarchy.split_incoherent`), cutting any part the cut crosses (ours
            True, the reference False). Growing compares a unit only with the members it
            touches, so one unit that the masks confuse can carry two objects into one region;
            and a part that took in a piece of another object carries it into the object.
    """

    thresholds: tuple[float, float, float] = (0.9, 0.7, 0.7)
    neighbors: int = 8
    one_hop_weight: float = 2.0
    min_region_gaussians: int = 20
    max_absorbed_units: int = 2
    seg_enhance: bool = False
    enhance_stride: int = 3
    mode: MergeMode = "progressive"
    min_max_weight: float = 0.05
    visibility_power: float = 2.0
    two_hop_weight: float = 0.0
    rounds: int = 10
    min_support: float = MIN_SUPPORT
    split_incoherent: bool = True

    def __post_init__(self) -> None:
        if len(self.thresholds) != 3 or not all(np.isfinite(t) for t in self.thresholds):
            raise InputError("MergeConfig", "thresholds must be three finite numbers")
        if not 2 <= self.neighbors <= MAX_NEIGHBOURS:
            raise InputError(
                "MergeConfig.neighbors",
                f"must be from 2 to {MAX_NEIGHBOURS:,}, got {self.neighbors:,}",
            )
        if self.enhance_stride < 1 or self.max_absorbed_units < 0:
            raise InputError("MergeConfig", "need enhance_stride ≥ 1, max_absorbed_units ≥ 0")
        if self.one_hop_weight <= 0 or self.min_region_gaussians < 0:
            raise InputError("MergeConfig", "one_hop_weight must be > 0, min_region_gaussians ≥ 0")
        if not (self.two_hop_weight >= 0 and self.visibility_power >= 0 and self.rounds >= 1):
            raise InputError(
                "MergeConfig", "need two_hop_weight ≥ 0, visibility_power ≥ 0 and rounds ≥ 1"
            )
        if not (np.isfinite(self.min_support) and self.min_support >= 0):
            raise InputError("MergeConfig", f"min_support must be ≥ 0, got {self.min_support}")
        if self.mode not in ("progressive", "independent", "instance"):
            raise InputError(
                "MergeConfig",
                f"mode must be progressive, independent or instance, got {self.mode!r}",
            )

    @classmethod
    def lerf(cls) -> MergeConfig:
        """The reference's LERF-OVS numbers: thresholds 0.9 / 0.7 / 0.7, small regions < 20 (our
        fixes on; see :meth:`as_reference`)."""
        return cls()

    @classmethod
    def three_dovs(cls) -> MergeConfig:
        """The reference's 3DOVS setting: small regions < 100, ``seg_enhance`` on."""
        return cls(min_region_gaussians=100, seg_enhance=True)

    def as_reference(self) -> MergeConfig:
        """The same numbers with the authors' behaviour where ours differs: every label votes
        with weight 1 (no visibility threshold or weighting), 2-hop members count 1 : 2, one
        round per pass, any support counts, no split of incoherent regions."""
        return replace(
            self,
            min_max_weight=0.0,
            visibility_power=0.0,
            two_hop_weight=1.0,
            rounds=1,
            min_support=0.0,
            split_incoherent=False,
        )


@dataclass(frozen=True, eq=False)
class MergeResult:
    """What :func:`merge_levels` returns.

    Attributes:
        levels: the regions at levels 0–3 (:class:`RegionLevels`): level 0 the superpoints,
            levels 1–3 the merged regions (sub-part, part, object), each numbered 0 … R_k − 1
            in order of their first unit; nested (``parents`` set) except for the
            ``independent`` ablation.
        seconds: wall time per pass (``"adjacency"``, ``"level 1"`` …, ``"split"``, ``"absorb"``).
    """

    levels: RegionLevels
    seconds: dict[str, float]


def _sources(
    lifted: Sequence[ViewLift], column: int, config: MergeConfig, stride: int = 1
) -> Iterator[Source]:
    """Per view (every ``stride``-th), on the views' device: the Gaussians with ``max w ≥
    min_max_weight``, their labels in ``column`` and their weights ``(max w)^visibility_power``
    (no weights when the power is 0: every label weighs 1). Made one view at a time, as they
    are consumed, so that they never all take memory at once."""
    for view in lifted[::stride]:
        visible = view.max_weights >= config.min_max_weight
        gaussians = view.gaussians[visible].long()
        labels = view.labels[visible, column].long()
        if config.visibility_power == 0:
            yield gaussians, labels
        else:
            yield gaussians, labels, view.max_weights[visible].double() ** config.visibility_power


@numba.njit(cache=True)
def _grow(
    indptr1, indices1, indptr2, indices2, hops2, affinity2, sizes, threshold, one_hop, two_hop
):
    """Breadth-first region growing over units in id order; returns [U] region ids."""
    count = sizes.shape[0]
    region = np.full(count, -1, dtype=np.int64)
    queue = np.empty(count, dtype=np.int64)
    regions = 0
    for seed in range(count):
        if region[seed] >= 0:
            continue
        region[seed] = regions
        head = 0
        tail = 1
        queue[0] = seed
        while head < tail:
            x = queue[head]
            head += 1
            for e in range(indptr1[x], indptr1[x + 1]):
                j = indices1[e]
                if region[j] >= 0:
                    continue
                numerator = 0.0
                denominator = 0.0
                for f in range(indptr2[j], indptr2[j + 1]):
                    r = indices2[f]
                    if region[r] != regions:
                        continue
                    weight = sizes[r] * (one_hop if hops2[f] == 1 else two_hop)
                    numerator += weight * affinity2[f]
                    denominator += weight
                if denominator > 0 and numerator >= threshold * denominator:
                    region[j] = regions
                    queue[tail] = j
                    tail += 1
        regions += 1
    return region


def _both_directions(graph: UnitGraph, values: np.ndarray):
    """CSR (indptr, indices, hops, values) of the within-two-hops pairs, both directions."""
    rows = np.concatenate([graph.pairs[:, 0], graph.pairs[:, 1]])
    cols = np.concatenate([graph.pairs[:, 1], graph.pairs[:, 0]])
    order = np.lexsort((cols, rows))
    indptr = np.zeros(graph.units + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=graph.units), out=indptr[1:])
    hops = np.concatenate([graph.hops, graph.hops])[order]
    both = np.concatenate([values, values])[order]
    return indptr, cols[order], hops, both


def _grow_round(graph: UnitGraph, evidence: MaskEvidence, threshold: float, config: MergeConfig):
    """[U] region id of every unit of ``graph`` after one round of region growing."""
    if config.two_hop_weight == 0:  # 2-hop members do not count: no affinity needed for them
        touching = graph.hops == 1
        graph = UnitGraph(graph.one_hop, graph.pairs[touching], graph.hops[touching])
    affinity = pair_affinity(evidence, graph.pairs, config.min_support)
    indptr2, indices2, hops2, affinity2 = _both_directions(graph, affinity)
    sizes = evidence.sizes.cpu().numpy()
    one = graph.one_hop
    return _grow(
        one.indptr.astype(np.int64),
        one.indices.astype(np.int64),
        indptr2,
        indices2,
        hops2,
        affinity2,
        sizes,
        float(threshold),
        float(config.one_hop_weight),
        float(config.two_hop_weight),
    )


def _merge_pass(
    units: np.ndarray,
    neighbors: np.ndarray,
    sources: Iterable[Source],
    threshold: float,
    config: MergeConfig,
    device: torch.device,
    split: bool = False,
) -> np.ndarray:
    """[N] int32 region of every Gaussian after one pass over ``units`` [N] (0 … U − 1):
    ``config.rounds`` rounds of growing at most, each on the previous round's regions (their
    adjacency and evidence pooled from the units'), stopping when a round merges nothing; with
    ``split``, incoherent regions are then cut (:func:`split_incoherent`); numbered in order of
    their smallest unit."""
    count = int(units.max()) + 1
    graph = unit_graph(units, neighbors, count)
    evidence = mask_evidence(torch.from_numpy(units).to(device), count, sources)
    units_graph, units_evidence = graph, evidence
    region_of_unit = np.arange(count)
    for _ in range(config.rounds):
        grown = _grow_round(graph, evidence, threshold, config)  # per current region
        regions = int(grown.max()) + 1
        merged = regions < graph.units
        renumbered = renumber_by_units(grown[region_of_unit], np.arange(count)).astype(np.int64)
        new_of_current = np.zeros(graph.units, dtype=np.int64)
        new_of_current[region_of_unit] = renumbered
        region_of_unit = renumbered
        if not merged:
            break
        graph = coarsened_graph(graph, new_of_current, regions)
        evidence = evidence.pooled(torch.from_numpy(new_of_current), regions)
    if split:
        region_of_unit = split_incoherent(
            region_of_unit, units_graph, units_evidence, threshold, config.min_support
        )
    return region_of_unit[units].astype(np.int32)


def _split_objects(
    levels: list[np.ndarray],
    neighbors: np.ndarray,
    lifted: Sequence[ViewLift],
    config: MergeConfig,
    device: torch.device,
) -> tuple[np.ndarray, np.ndarray]:
    """Parts and objects ([N] int32 each) after every object was checked for a split between
    its sub-parts (:func:`split_incoherent` on level-1 units with the objects' evidence); a part
    that a cut crosses is cut with it."""
    units = levels[1].astype(np.int64)
    count = int(units.max()) + 1
    graph = unit_graph(units, neighbors, count)
    evidence = mask_evidence(torch.from_numpy(units).to(device), count, _sources(lifted, 3, config))
    object_of_unit = np.zeros(count, dtype=np.int64)
    object_of_unit[units] = levels[3]
    split = split_incoherent(
        object_of_unit, graph, evidence, config.thresholds[2], config.min_support
    )
    objects = split[units]
    _, parts = np.unique(np.stack([levels[2], objects], axis=1), axis=0, return_inverse=True)
    return renumber_by_units(parts.reshape(-1), units), objects.astype(np.int32)


def _absorb(
    regions: np.ndarray,
    units: np.ndarray,
    neighbors: np.ndarray,
    sources: Iterable[Source],
    config: MergeConfig,
    device: torch.device,
) -> np.ndarray:
    """[N] level-3 regions after small regions joined their most similar touching neighbour.

    ``regions`` [N] are the level-3 ids, ``units`` [N] the units of the last pass.
    """
    count = int(regions.max()) + 1
    sizes = np.bincount(regions, minlength=count)
    pairs_of_units = np.unique(np.stack([regions, units], axis=1), axis=0)
    unit_counts = np.bincount(pairs_of_units[:, 0], minlength=count)
    small = (sizes < config.min_region_gaussians) & (unit_counts <= config.max_absorbed_units)
    if not small.any():
        return regions
    graph = unit_graph(regions, neighbors, count)
    touching = graph.pairs[graph.hops == 1]
    evidence = mask_evidence(torch.from_numpy(regions).to(device), count, sources)
    affinity = pair_affinity(evidence, touching)
    a = np.concatenate([touching[:, 0], touching[:, 1]])
    b = np.concatenate([touching[:, 1], touching[:, 0]])
    score = np.concatenate([affinity, affinity])
    candidate = small[a] & ~small[b]
    a, b, score = a[candidate], b[candidate], score[candidate]
    order = np.lexsort((b, -score, a))  # per small region: best affinity, then lowest id
    a, b = a[order], b[order]
    first = np.ones(a.size, dtype=bool)
    first[1:] = a[1:] != a[:-1]
    target = np.arange(count)
    target[a[first]] = b[first]
    log.info(
        "absorbed %d of %d small regions (%d stay on their own)",
        int(first.sum()),
        int(small.sum()),
        int(small.sum() - first.sum()),
    )
    return target[regions]


def merge_levels(
    gaussians: Gaussians,
    superpoints: np.ndarray,
    lifted: Sequence[ViewLift],
    config: MergeConfig = MergeConfig(),
    *,
    neighbors: np.ndarray | None = None,
) -> MergeResult:
    """Levels 1–3 of the hierarchy from level-0 superpoints and the lifted s/m/l labels.

    Args:
        gaussians: the N Gaussians (their centres define which units touch).
        superpoints: [N] int level-0 ids 0 … S−1 (:func:`thgs.pipeline.partition_scene`).
        lifted: one :class:`thgs.lift.ViewLift` per view (columns 1, 2, 3: s, m, l).
        config: thresholds, adjacency, absorption, ablation mode.
        neighbors: the [N, config.neighbors] output of :func:`gaussian_neighbors` for these
            Gaussians, when the caller has it (computed otherwise).

    Returns:
        :class:`MergeResult`; in ``progressive`` and ``instance`` modes the levels nest (every
        level-k region lies inside one level-(k + 1) region) and counts never increase from
        level to level.

    Raises:
        InputError: superpoints of the wrong shape or not numbered 0 … S−1, a lift that does
            not index these Gaussians.
    """
    n = len(gaussians)
    superpoints = np.asarray(superpoints)
    if superpoints.shape != (n,) or not np.issubdtype(superpoints.dtype, np.integer):
        raise InputError("superpoints", f"must be [N] = [{n}] integers")
    if n == 0:
        raise InputError("superpoints", "no Gaussians to merge")
    if superpoints.min() < 0 or np.unique(superpoints).size != int(superpoints.max()) + 1:
        raise InputError("superpoints", "ids must be 0 … S−1, each used")
    device = lifted[0].device if lifted else torch.device("cpu")
    for index, view in enumerate(lifted):
        view.check(n, source=f"lifted view {index}")
        if view.device != device:
            raise InputError(f"lifted view {index}", f"is on {view.device}, view 0 on {device}")
    seconds: dict[str, float] = {}
    started = time.perf_counter()
    if neighbors is None:
        neighbors = gaussian_neighbors(gaussians, config.neighbors)
    elif neighbors.shape != (n, config.neighbors):
        raise InputError("neighbors", f"must be [N, k] = [{n}, {config.neighbors}]")
    seconds["adjacency"] = time.perf_counter() - started
    base = superpoints.astype(np.int64)
    levels = [base.astype(np.int32)]
    if config.mode == "instance":
        started = time.perf_counter()
        regions = _merge_pass(
            base,
            neighbors,
            _sources(lifted, 3, config),
            config.thresholds[2],
            config,
            device,
            split=config.split_incoherent,
        )
        seconds["level 3"] = time.perf_counter() - started
        levels += [regions, regions, regions]
    else:
        for k in (1, 2, 3):
            started = time.perf_counter()
            sources = _sources(lifted, k, config)
            if k == 1 and config.seg_enhance:
                sources = chain(sources, _sources(lifted, 2, config, config.enhance_stride))
            units = base if config.mode == "independent" else levels[-1].astype(np.int64)
            split = k == 3 and config.split_incoherent and config.mode == "independent"
            threshold = config.thresholds[k - 1]
            levels.append(
                _merge_pass(units, neighbors, sources, threshold, config, device, split=split)
            )
            seconds[f"level {k}"] = time.perf_counter() - started
        if config.split_incoherent and config.mode == "progressive":
            started = time.perf_counter()
            levels[2], levels[3] = _split_objects(levels, neighbors, lifted, config, device)
            seconds["split"] = time.perf_counter() - started
    if config.min_region_gaussians > 0 and config.mode != "independent":
        started = time.perf_counter()
        last_units = base if config.mode == "instance" else levels[2].astype(np.int64)
        absorbed = _absorb(
            levels[3].astype(np.int64),
            last_units,
            neighbors,
            _sources(lifted, 3, config),
            config,
            device,
        )
        regions = renumber_by_units(absorbed, last_units)
        levels[3] = regions
        if config.mode == "instance":
            levels[1] = levels[2] = regions
        seconds["absorb"] = time.perf_counter() - started
    labels = np.stack(levels, axis=1).astype(np.int32)
    merged = RegionLevels.from_labels(labels, nested=config.mode != "independent")
    log.info("merged levels: %s regions", " → ".join(f"{c:,}" for c in merged.counts))
    return MergeResult(levels=merged, seconds=seconds)
