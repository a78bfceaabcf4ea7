"""Open-vocabulary queries of a semantic field (design §4.8): relevancy and region selection.

The relevancy of a region with unit feature φ for a query embedding q, against the canonical
phrases c_i ("object", "things", "stuff", "texture"), is LERF's

    rel(φ, q) = min_i exp(t φ·q) / (exp(t φ·q) + exp(t φ·c_i)),   t = 10,

which equals ``min_i σ(t (φ·q − φ·c_i))`` and is computed in that stable form. It lies in
(0, 1); 0.5 means "no more like the query than like a generic phrase". Regions that no view saw
have no feature and score 0, so they are never selected.

Four ways to turn relevancies into a selection (:class:`QueryConfig`):

- ``auto`` (the default) — decided from the query's own scores and the hierarchy, with no
  per-scene setting (:func:`select_auto`, docs/query.md). Cosines are read on features centred
  on the scene's mean feature, which removes what every region shares (CLIP's image embeddings
  share one direction) and makes them comparable across embedding spaces. Abstain when the
  best region is no closer to the query than ordinary names get to this scene (its cosine
  ``min_score`` standard deviations above the null of :data:`thgs.confidence.NULL_PHRASES`;
  the selection says why). Otherwise descend the hierarchy from every object: a region at
  least as close as ``best − extent · (best − median)`` is taken whole unless a region inside
  it is closer by more than ``descend`` of that spread — then the query is about a part of it,
  and the descent goes on into the children that come near the best one. One part, an object
  split over several regions, a table's four legs, two mugs: the regions named like the query,
  at the level where they are so named, and not the object around a part that only looks
  like it.
- ``paper`` — the paper's evaluation: the 3 most relevant regions of level 2 and the 3 of
  level 3 are pooled, the 3 best of those six are kept, no threshold. Something is always
  selected, even for a query about nothing in the scene.
- ``level`` — the ``top`` most relevant regions of one level: "the best object", "the best part".
- ``threshold`` — every region of one level whose relevancy reaches a threshold, so a query about
  nothing in the scene selects nothing, and an object split into several regions is selected
  whole. The default threshold depends on the embedding space (:func:`default_threshold`).

The selected Gaussians are the union of the chosen regions' members. :class:`FieldQuery` is the
one query engine: it runs batches of queries on a field or on any :class:`Regions` (levels that
need not nest), with text embeddings and results cached per text, for the CLI, the viewer and
every evaluation protocol.
"""

from __future__ import annotations

import copy
import logging
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.special import expit

from thgs._config_json import config_from_json
from thgs.choices import SelectionMode
from thgs.confidence import NULL_PHRASES, NullModel, presence_confidence, region_confidence
from thgs.errors import InputError
from thgs.field import SemanticField
from thgs.hierarchy import MergeConfig
from thgs.hierarchy.levels import RegionLevels
from thgs.text import MINILM_SPACE, TextEncoder, check_space

__all__ = [
    "CANONICAL_PHRASES",
    "AutoChoice",
    "FieldQuery",
    "QueryConfig",
    "Regions",
    "Selection",
    "abstain_reason",
    "default_threshold",
    "relevancy",
    "select",
    "select_auto",
    "select_paper",
    "small_region_size",
    "unselectable_reason",
]

logger = logging.getLogger(__name__)

CANONICAL_PHRASES = ("object", "things", "stuff", "texture")
"""LERF's canonical negatives, encoded in the field's space and passed as ``canonical``."""


_THRESHOLDS = {MINILM_SPACE: 0.8}
_CACHED_RESULTS = 256


def default_threshold(space: str) -> float:
    """The ``threshold`` mode's default relevancy for features in ``space``.

    0.8 for all-MiniLM-L6-v2, measured on the synthetic scenes: regions named after the query
    score ≥ 0.99, phrases naming nothing in the scene ("a giraffe", "the ocean") at most 0.66.
    0.5 elsewhere: LERF's indifference point, the least a region must score to be more like the
    query than like every canonical phrase. CLIP relevancies are compressed towards 0.5, so
    calibrate ``QueryConfig.threshold`` on a scene you know.
    """
    return _THRESHOLDS.get(space, 0.5)


def relevancy(
    features: np.ndarray,
    queries: np.ndarray,
    canonical: np.ndarray,
    temperature: float = 10.0,
    seen: np.ndarray | None = None,
) -> np.ndarray:
    """Relevancy of every region for every query.

    Args:
        features: [R, D] region features (unit rows; zero rows for unseen regions).
        queries: [Q, D] unit query embeddings (or [D] for one query).
        canonical: [C, D] unit embeddings of the canonical phrases, C ≥ 1.
        temperature: t of the softmax (10).
        seen: [R] bool; regions marked False score 0 (default: non-zero rows are seen).

    Returns:
        [Q, R] float64 relevancies in [0, 1) ([R] for a single [D] query).

    Raises:
        InputError: mismatched dimensions or no canonical phrase.
    """
    features = np.asarray(features, dtype=np.float64)
    single = np.ndim(queries) == 1
    queries = np.atleast_2d(np.asarray(queries, dtype=np.float64))
    canonical = np.atleast_2d(np.asarray(canonical, dtype=np.float64))
    if features.ndim != 2 or queries.shape[1] != features.shape[1]:
        raise InputError(
            "relevancy",
            f"queries [Q, {queries.shape[1]}] and features {list(features.shape)} must share D",
        )
    if canonical.shape[0] < 1 or canonical.shape[1] != features.shape[1]:
        raise InputError("relevancy", f"canonical must be [C ≥ 1, D], got {list(canonical.shape)}")
    if seen is None:
        seen = (features != 0).any(axis=1)
    query_scores = queries @ features.T  # [Q, R]
    canonical_scores = canonical @ features.T  # [C, R]
    margin = query_scores[:, None, :] - canonical_scores[None, :, :]  # [Q, C, R]
    scores = expit(temperature * margin.min(axis=1))
    scores[:, ~np.asarray(seen, dtype=bool)] = 0.0
    return scores[0] if single else scores


@dataclass(frozen=True)
class QueryConfig:
    """How relevancies become a selection (see the module docstring).

    Attributes:
        mode: ``"auto"`` (decided per query), ``"paper"`` (the paper's evaluation),
            ``"level"`` or ``"threshold"``.
        levels: auto and paper modes: the levels searched ((1, 2, 3) for auto; the paper pools
            (2, 3): parts and objects).
        per_level: paper mode: regions taken from each pooled level (3).
        keep: paper mode: regions kept from the pool by relevancy (3).
        extent: auto mode: how far below the best region's cosine, as a share of the best's
            lead over the median region (the query's spread), a region may be and still be
            selected (0.1, chosen on synthetic seeds 0–4; docs/query.md).
        hierarchical: auto mode: judge each region against the regions inside it (descend
            from the objects, :func:`select_auto`); False selects every region past the cut
            wherever it is, as thgs did before (nested fields only; others are always flat).
        descend: auto mode: a region past the cut is taken whole unless a region inside it is
            closer to the query by more than this share of the spread.
        siblings: auto mode: when the descent goes into a region's children, those whose best
            cosine (their own or inside them) rises above the region's by at least this share
            of the best child's rise are followed; the others are left out.
        centred: auto mode: read cosines on features centred on the mean feature of the
            scene's selectable regions (renormalized), not on the raw features.
        min_score: auto mode: the query is abstained from when its best region's score, the
            cosine's distance above the scene's null in units of the null's spread (the best
            cosines of the generic :data:`thgs.confidence.NULL_PHRASES`, read the same way), is
            below this. Used when ``threshold`` is None; a scene without a null falls back to
            the space's relevancy threshold.
        level: level and threshold modes: the level searched (1 sub-parts, 2 parts, 3 objects).
        top: level mode: how many regions (1).
        threshold: threshold mode: the relevancy a region needs (None:
            :func:`default_threshold` of the field's space); auto mode: if given, the relevancy
            the best region needs, or the query is abstained from, instead of ``min_score``.
        min_gaussians: regions with fewer Gaussians are never selected (0: all may be); None:
            the field's small-region size (``config["merge"]["min_region_gaussians"]``, 20 for
            the LERF preset, 0 if the field does not say). Leftover specks that merging could
            not absorb otherwise win queries on a few lucky views (design §4.6: excluded from
            queries).
        temperature: t of :func:`relevancy` (10).
    """

    mode: SelectionMode = "auto"
    levels: tuple[int, ...] | None = None
    per_level: int = 3
    keep: int = 3
    extent: float = 0.1
    hierarchical: bool = True
    descend: float = 0.05
    siblings: float = 0.6
    centred: bool = True
    min_score: float = 1.05
    level: int = 3
    top: int = 1
    threshold: float | None = None
    min_gaussians: int | None = None
    temperature: float = 10.0

    def check(self) -> QueryConfig:
        """Raise :class:`InputError` naming the first invalid setting; return ``self``."""
        if self.mode not in ("auto", "paper", "level", "threshold"):
            raise InputError(
                "QueryConfig.mode",
                f"must be auto, paper, level or threshold, got {self.mode!r}",
            )
        levels = self.searched_levels
        if not levels or any(
            isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k not in (1, 2, 3)
            for k in levels
        ):
            raise InputError("QueryConfig", f"levels must be among 1, 2, 3, got {levels}")
        for name in ("per_level", "keep", "top"):
            if getattr(self, name) < 1:
                raise InputError(f"QueryConfig.{name}", f"must be ≥ 1, got {getattr(self, name)}")
        if self.threshold is not None and not 0.0 <= self.threshold <= 1.0:
            raise InputError("QueryConfig.threshold", f"must be in [0, 1], got {self.threshold}")
        if self.min_gaussians is not None and self.min_gaussians < 0:
            raise InputError("QueryConfig.min_gaussians", f"must be ≥ 0, got {self.min_gaussians}")
        if not self.temperature > 0:
            raise InputError("QueryConfig.temperature", f"must be > 0, got {self.temperature}")
        if not 0.0 <= self.extent < 1.0:
            raise InputError("QueryConfig.extent", f"must be in [0, 1), got {self.extent}")
        if not 0.0 <= self.descend:
            raise InputError("QueryConfig.descend", f"must be ≥ 0, got {self.descend}")
        if not 0.0 <= self.siblings <= 1.0:
            raise InputError("QueryConfig.siblings", f"must be in [0, 1], got {self.siblings}")
        if not np.isfinite(self.min_score):
            raise InputError("QueryConfig.min_score", f"must be a number, got {self.min_score}")
        return self

    @property
    def searched_levels(self) -> tuple[int, ...]:
        """The levels whose relevancies this mode reads."""
        if self.mode in ("level", "threshold"):
            return (self.level,)
        if self.levels is not None:
            return tuple(self.levels)
        return (1, 2, 3) if self.mode == "auto" else (2, 3)


@dataclass(frozen=True, eq=False)
class Selection:
    """The regions one query selected and their Gaussians.

    Attributes:
        text: the query ("" when the query was an embedding).
        regions: ``(level, region, relevancy)`` triples, most relevant first (auto mode: the
            closest by cosine first); empty when nothing was relevant enough (auto and threshold
            modes).
        gaussians: [N] bool, True for the members of any selected region.
        reason: why nothing was selected (auto mode abstaining; or, in every mode, no
            selectable region has a feature: :func:`unselectable_reason`), else None.
        confidence: the calibrated probability that the scene holds what the text names
            (:func:`thgs.confidence.presence_confidence`, whatever the mode); None when it
            cannot be computed (:meth:`FieldQuery.null_model` is None) or was not
            (:func:`select_paper`).
        region_confidence: per selected region, in the order of ``regions``, the calibrated
            probability that it belongs to what was asked
            (:func:`thgs.confidence.region_confidence`); None when not computed.
    """

    text: str
    regions: tuple[tuple[int, int, float], ...]
    gaussians: np.ndarray
    reason: str | None = None
    confidence: float | None = None
    region_confidence: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.region_confidence is not None and len(self.region_confidence) != len(self.regions):
            raise ValueError("Selection: one region confidence per region")

    @property
    def empty(self) -> bool:
        """Whether nothing was selected."""
        return not self.regions

    def to_json(self, field: SemanticField | Regions) -> dict[str, Any]:
        """JSON-ready summary: the text, the presence confidence, the regions (with their
        confidence and their sizes in ``field``, the one queried) and the Gaussian count
        (confidences only where computed)."""
        confidences = self.region_confidence or (None,) * len(self.regions)
        regions = []
        for (level, region, score), confidence in zip(self.regions, confidences):
            entry: dict[str, Any] = {"level": level, "region": region, "relevancy": score}
            if confidence is not None:
                entry["confidence"] = confidence
            entry["gaussians"] = int(field.sizes(level)[region])
            regions.append(entry)
        return {
            "text": self.text,
            **({"confidence": self.confidence} if self.confidence is not None else {}),
            "regions": regions,
            "gaussians": int(self.gaussians.sum()),
            **({"reason": self.reason} if self.reason is not None else {}),
        }


def _ranked(scores: np.ndarray, candidates: np.ndarray) -> np.ndarray:
    """Candidate region ids by decreasing score, lower id first on ties."""
    return candidates[np.lexsort((candidates, -scores[candidates]))]


def select(
    scores: dict[int, np.ndarray],
    config: QueryConfig,
    allowed: dict[int, np.ndarray] | None = None,
    threshold: float = 0.5,
    similarities: dict[int, np.ndarray] | None = None,
    parents: Sequence[np.ndarray] | None = None,
) -> tuple[tuple[int, int, float], ...]:
    """Choose regions of one query from its relevancies.

    Args:
        scores: level → [R_level] relevancies, for every level in ``config.searched_levels``.
        config: the selection mode and its settings.
        allowed: level → [R_level] bool, the regions that may be chosen (default: all).
        threshold: threshold and auto modes' relevancy, used when ``config.threshold`` is None
            (auto mode here always abstains by relevancy: the null is :class:`FieldQuery`'s).
        similarities: auto mode: level → [R_level] cosine of each region's feature with the
            query (required there).
        parents: auto mode: the nesting of levels 1–3 (:func:`select_auto`); None: flat.

    Returns:
        ``(level, region, relevancy)``, most relevant first (auto: closest first); ties go to
        the lower level, then the lower region id. Empty when auto mode abstains (see
        :func:`abstain_reason`) or nothing reaches the threshold.
    """
    config.check()
    candidates = {}
    for level in config.searched_levels:
        ok = np.ones(scores[level].shape, bool) if allowed is None else allowed[level]
        candidates[level] = np.flatnonzero(ok & (scores[level] > 0))
    cut = config.threshold if config.threshold is not None else threshold
    if config.mode == "auto":
        if similarities is None:
            raise InputError("select", "auto mode needs the regions' cosine similarities")
        return select_auto(
            scores,
            similarities,
            candidates,
            config.extent,
            cut,
            parents=parents if config.hierarchical else None,
            descend=config.descend,
            siblings=config.siblings,
        ).regions
    if config.mode == "paper":
        pool = []
        for level in config.searched_levels:
            for region in _ranked(scores[level], candidates[level])[: config.per_level]:
                pool.append((-float(scores[level][region]), level, int(region)))
        chosen = sorted(pool)[: config.keep]
        return tuple((level, region, -score) for score, level, region in chosen)
    level = config.level
    ranked = _ranked(scores[level], candidates[level])
    if config.mode == "level":
        ranked = ranked[: config.top]
    else:
        ranked = ranked[scores[level][ranked] >= cut]
    return tuple((level, int(region), float(scores[level][region])) for region in ranked)


@dataclass(frozen=True)
class AutoChoice:
    """What :func:`select_auto` decided for one query.

    Attributes:
        regions: ``(level, region, relevancy)``, closest by cosine first; empty when abstaining.
        best_relevancy: the highest relevancy among the candidates (0 when there are none).
        best_score: the best candidate's score against the scene's null (None when the
            relevancy decided, or there is no candidate).
    """

    regions: tuple[tuple[int, int, float], ...]
    best_relevancy: float
    best_score: float | None = None


def _children(upward: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The child regions of every region one level up, as ``(order, bounds)``: region r's
    children are ``order[bounds[r] : bounds[r + 1]]``; ``upward`` [R] maps each child to its
    region."""
    order = np.argsort(upward, kind="stable")
    return order, np.searchsorted(upward[order], np.arange(int(upward.max(initial=-1)) + 2))


def _descend(
    own: dict[int, np.ndarray],
    parents: Sequence[np.ndarray],
    cut: float,
    margin: float,
    siblings: float,
) -> list[tuple[int, int]]:
    """The hierarchical choice of :func:`select_auto` (module docstring); ``own`` holds each
    region's cosine, −inf where it may not be chosen."""
    inside = {1: np.full(len(own[1]), -np.inf)}  # best cosine strictly inside each region
    for level, upward in ((2, parents[0]), (3, parents[1])):
        below = np.maximum(own[level - 1], inside[level - 1])
        inside[level] = np.full(len(own[level]), -np.inf)
        np.maximum.at(inside[level], upward, below)
    children = {2: _children(parents[0]), 3: _children(parents[1])}
    chosen: list[tuple[int, int]] = []
    stack = [(3, int(region)) for region in range(len(own[3]))][::-1]
    while stack:
        level, region = stack.pop()
        value, best_inside = own[level][region], inside[level][region]
        rise = best_inside - value if np.isfinite(value) and np.isfinite(best_inside) else 0.0
        if value >= cut and not rise > margin:
            chosen.append((level, region))
            continue
        if level == 1:
            continue
        order, bounds = children[level]
        kids = order[bounds[region] : bounds[region + 1]] if region + 1 < len(bounds) else order[:0]
        if rise > margin:  # the query is about something inside it
            best = np.maximum(own[level - 1][kids], inside[level - 1][kids])
            kids = kids[best - value >= siblings * rise]
        stack.extend((level - 1, int(kid)) for kid in kids[::-1])
    return chosen


def select_auto(
    scores: dict[int, np.ndarray],
    similarities: dict[int, np.ndarray],
    candidates: dict[int, np.ndarray],
    extent: float = 0.1,
    threshold: float = 0.5,
    *,
    parents: Sequence[np.ndarray] | None = None,
    descend: float = 0.05,
    siblings: float = 0.6,
    null: NullModel | None = None,
    min_score: float = 1.05,
) -> AutoChoice:
    """The automatic selection of one query (module docstring, docs/query.md).

    With ``best`` the highest cosine among the candidates and ``median`` their median, the cut
    is ``best − extent · (best − median)``. Without ``parents`` every candidate past the cut is
    chosen. With them, the descent starts at every level-3 region: a candidate past the cut is
    chosen whole unless a candidate inside it has a cosine higher than its own by more than
    ``descend · (best − median)``; otherwise (or when it is no candidate, or short of the cut)
    the descent goes on into its children, and where something inside it rose that far, only
    into the children whose best cosine (their own or inside them) rises above its own by at
    least ``siblings`` times that rise.

    Args:
        scores: level → [R_level] relevancies (reported with each chosen region).
        similarities: level → [R_level] cosines of the regions' features with the query (the
            centred ones where the caller centres).
        candidates: level → [C_level] ids of the regions that may be chosen (seen, not small).
        extent: share of the best's lead over the median a region may fall short by.
        threshold: the relevancy the best candidate needs when ``null`` is None.
        parents: the nesting, for levels 1–3: ``parents[0]`` [R_1] the level-2 region of each
            level-1 region, ``parents[1]`` [R_2] the level-3 region of each level-2 region
            (:attr:`thgs.hierarchy.RegionLevels.parents` [1:]); None: the flat rule.
        descend: share of the spread a region inside a candidate must rise above it by for the
            candidate not to be taken whole.
        siblings: share of the best child's rise a child must reach to be descended into.
        null: the scene's null of the same cosines; with it, the query is abstained from when
            the best candidate's score is below ``min_score`` (else the relevancy rule).
        min_score: see ``null``.
    """
    pairs = [(level, int(region)) for level, ids in candidates.items() for region in ids]
    best_relevancy = max((float(scores[level][region]) for level, region in pairs), default=0.0)
    if not pairs:
        return AutoChoice((), best_relevancy)
    cosines = np.array([similarities[level][region] for level, region in pairs])
    best, median = float(cosines.max()), float(np.median(cosines))
    best_score = None
    if null is not None:
        best_score = float(null.score(best))
        if best_score < min_score:
            return AutoChoice((), best_relevancy, best_score)
    elif best_relevancy < threshold:
        return AutoChoice((), best_relevancy)
    spread = best - median
    cut = best - extent * spread
    if parents is None:
        picked = [(level, region) for (level, region), c in zip(pairs, cosines) if c >= cut]
    else:
        objects = max(int(parents[1].max(initial=-1)) + 1, len(similarities.get(3, ())))
        sizes = {1: len(parents[0]), 2: len(parents[1]), 3: objects}
        own = {level: np.full(size, -np.inf) for level, size in sizes.items()}
        for (level, region), cosine in zip(pairs, cosines):
            own[level][region] = cosine
        picked = _descend(own, parents, cut, descend * spread, siblings)
    order = sorted((-float(similarities[level][region]), level, region) for level, region in picked)
    regions = tuple((level, region, float(scores[level][region])) for _, level, region in order)
    return AutoChoice(regions, best_relevancy, best_score)


def abstain_reason(text: str, best: float, threshold: float, *, score: bool = False) -> str:
    """Why auto mode selected nothing for ``text``: its best region's relevancy (``score``
    False) or score against the scene's null (``score`` True), ``best``, is below
    ``threshold``."""
    if score:
        return (
            f"nothing relevant to {text!r}: the best region is {best:.2f} standard deviations "
            f"above what ordinary names reach in this scene, below the {threshold:.2f} needed"
        )
    return (
        f"nothing relevant to {text!r}: the best region scores {best:.3f}, below the "
        f"{threshold:.3f} a region needs (relevancy against 'object', 'things', 'stuff', "
        "'texture')"
    )


def unselectable_reason(seen: dict[int, np.ndarray], allowed: dict[int, np.ndarray]) -> str | None:
    """Why no query can select anything, or None when some region can be selected.

    Args:
        seen: level → [R_level] bool, the regions with a feature (any view saw them).
        allowed: level → [R_level] bool, the regions large enough to be selected.

    Returns:
        None if some region is both; else the reason: no region of the searched levels has a
        feature (the guidance had no masks where the field is), or every one that has is too
        small.
    """
    levels = ", ".join(str(k) for k in seen)
    if not any(bool(flags.any()) for flags in seen.values()):
        return (
            f"no region of level(s) {levels} has a feature: no view's masks covered them, so "
            "no text can match; rebuild the field from guidance with masks (thgs preprocess, "
            "thgs build)"
        )
    if not any(bool((seen[k] & allowed[k]).any()) for k in seen):
        return (
            f"every region of level(s) {levels} with a feature is smaller than the smallest "
            "selectable region; lower --min-gaussians"
        )
    return None


@dataclass(frozen=True, eq=False)
class Regions:
    """What queries read of a segmentation: regions of N Gaussians at levels 1–3 with their
    features; the levels need not nest (the "no progressive merging" ablation's do not).

    Attributes:
        levels: the regions (:class:`thgs.hierarchy.RegionLevels`, nested or not).
        features: level k = 1..3 at index k − 1: [R_k, D] unit features (zero rows unseen).
        seen: level k at index k − 1: [R_k] bool, whether any view saw the region.
        space: the features' embedding space.
        min_region_gaussians: regions with fewer Gaussians are never selected (the field's
            small-region size; 0 selects every region).
    """

    levels: RegionLevels
    features: tuple[np.ndarray, np.ndarray, np.ndarray]
    seen: tuple[np.ndarray, np.ndarray, np.ndarray]
    space: str
    min_region_gaussians: int = 0

    @classmethod
    def from_field(cls, field: SemanticField) -> Regions:
        """A field's regions, with its small-region size (:func:`small_region_size`)."""
        return cls(field.levels, field.features, field.seen, field.space, small_region_size(field))

    def __len__(self) -> int:
        return len(self.levels)

    @property
    def labels(self) -> np.ndarray:
        """[N, 4] int32: ``labels[i, k]`` is the level-k region of Gaussian i."""
        return self.levels.labels

    @property
    def dim(self) -> int:
        """D, the length of a feature vector."""
        return int(self.features[0].shape[1])

    def sizes(self, level: int) -> np.ndarray:
        """[R_level] int64: the number of Gaussians in each region of ``level`` (1..3)."""
        return self.levels.sizes(self.checked_level(level))

    def checked_level(self, level: int) -> int:
        """``level`` as an int after checking that it is 1, 2 or 3 (the levels with features).

        Raises:
            InputError: anything else.
        """
        return self.levels.checked_level(level, range(1, 4))

    def checked_region(self, level: int, region: int) -> int:
        """``region`` as an int after checking that it is a region id of ``level`` (1..3).

        Raises:
            InputError: not an integer, or not in 0..R_level − 1.
        """
        return self.levels.checked_region(self.checked_level(level), region)

    def check(self, source: str = "Regions") -> Regions:
        """Verify the levels (:meth:`RegionLevels.check`) and that every level 1–3 has one
        [R_k, D] feature row and one seen flag per region, with one D; raise
        :class:`InputError` naming ``source``."""
        if not isinstance(self.levels, RegionLevels):
            raise InputError(source, f"levels must be RegionLevels, got {type(self.levels)}")
        self.levels.check(source)
        dims = set()
        for k in (1, 2, 3):
            features, seen = self.features[k - 1], self.seen[k - 1]
            count = self.levels.counts[k]
            if features.ndim != 2 or features.shape[0] != count or seen.shape != (count,):
                raise InputError(
                    source,
                    f"level {k}: features {list(features.shape)} and seen {list(seen.shape)} "
                    f"must be [R, D] and [R] with R = {count} regions",
                )
            dims.add(features.shape[1])
        if len(dims) != 1:
            raise InputError(source, f"levels have different feature dimensions {sorted(dims)}")
        return self


class _Members:
    """Every region's Gaussians at one level, grouped once so a union costs its size."""

    def __init__(self, labels: np.ndarray, count: int):
        self.order = np.argsort(labels, kind="stable")
        self.bounds = np.concatenate([[0], np.cumsum(np.bincount(labels, minlength=count))])

    def mark(self, mask: np.ndarray, region: int) -> None:
        mask[self.order[self.bounds[region] : self.bounds[region + 1]]] = True


class FieldQuery:
    """The query engine: text queries of one segmentation with one text encoder, used by the
    CLI, the viewer and every evaluation protocol.

    Text embeddings and selections are cached per text (and per config), so asking again, or
    asking the same text with another mode, does not run the text model again.

    Args:
        regions: a semantic field, or any :class:`Regions` (levels that need not nest).
        encoder: a text encoder in the regions' space.
        config: the default selection settings.
        source: what to name in errors (e.g. the field's path).

    Raises:
        SpaceMismatchError: the encoder's space or dimension is not the regions'.
    """

    def __init__(
        self,
        regions: SemanticField | Regions,
        encoder: TextEncoder,
        config: QueryConfig = QueryConfig(),
        *,
        source: str = "semantic field",
    ):
        if isinstance(regions, SemanticField):
            regions = Regions.from_field(regions)
        check_space(regions.space, encoder, source)
        self.regions = regions.check(source)
        check_space(regions.space, encoder, source, dim=self.regions.dim)
        self.encoder = encoder
        self.config = config.check()
        self.threshold = default_threshold(regions.space)
        self.min_gaussians = regions.min_region_gaussians
        self._canonical = encoder.encode(list(CANONICAL_PHRASES)).astype(np.float64)
        self._embeddings: dict[str, np.ndarray] = {}
        self._sizes = {k: regions.sizes(k) for k in (1, 2, 3)}
        self._members = {k: _Members(regions.labels[:, k], len(self._sizes[k])) for k in (1, 2, 3)}
        self._results: OrderedDict[tuple[str, QueryConfig], Selection] = OrderedDict()
        self._nulls: dict[tuple[int, bool], NullModel | None] = {}
        self._centred: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def embed(self, texts: Sequence[str]) -> np.ndarray:
        """[Q, D] float64 unit embeddings of ``texts`` (encoded once per distinct text)."""
        texts = _checked_texts(texts)
        new = [text for text in dict.fromkeys(texts) if text not in self._embeddings]
        if new:
            for text, vector in zip(new, self.encoder.encode(new)):
                self._embeddings[text] = vector.astype(np.float64)
        if not texts:
            return np.zeros((0, self.regions.dim))
        return np.stack([self._embeddings[text] for text in texts])

    def relevancy(self, texts: Sequence[str], level: int, temperature: float = 10.0) -> np.ndarray:
        """[Q, R_level] relevancy of every level-``level`` region (1..3) for every text."""
        level = self.regions.checked_level(level)
        return relevancy(
            self.regions.features[level - 1],
            self.embed(texts),
            self._canonical,
            temperature,
            self.regions.seen[level - 1],
        )

    def similarity(self, texts: Sequence[str], level: int) -> np.ndarray:
        """[Q, R_level] cosine of every level-``level`` region's feature with every text (0 for
        unseen regions, whose feature is zero)."""
        level = self.regions.checked_level(level)
        features = self.regions.features[level - 1].astype(np.float64)
        return self.embed(texts) @ features.T

    def centred_similarity(
        self, texts: Sequence[str], level: int, min_gaussians: int | None = None
    ) -> np.ndarray:
        """[Q, R_level] cosine of every level-``level`` region's centred feature with every
        text: each feature minus the mean feature of the selectable regions of levels 1–3 (seen,
        at least ``min_gaussians`` Gaussians; None: the field's small-region size), made unit
        again (0 for unseen regions). What every region shares (CLIP's image embeddings share
        one direction that its text embeddings lack) no longer decides the cosines."""
        level = self.regions.checked_level(level)
        smallest = self.min_gaussians if min_gaussians is None else min_gaussians
        return self.embed(texts) @ self._centred_features(smallest)[level - 1].T

    def _centred_features(self, smallest: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if smallest not in self._centred:
            features = [f.astype(np.float64) for f in self.regions.features]
            selectable = [
                features[k - 1][self.regions.seen[k - 1] & (self._sizes[k] >= smallest)]
                for k in (1, 2, 3)
            ]
            pooled = np.concatenate(selectable)
            centre = pooled.mean(axis=0) if len(pooled) else np.zeros(self.regions.dim)
            centred = []
            for k in (1, 2, 3):
                moved = features[k - 1] - centre
                norms = np.linalg.norm(moved, axis=1, keepdims=True)
                unit = np.divide(moved, norms, out=np.zeros_like(moved), where=norms > 0)
                centred.append(np.where(self.regions.seen[k - 1][:, None], unit, 0.0))
            self._centred[smallest] = tuple(centred)  # type: ignore[assignment]
        return self._centred[smallest]

    def gaussian_relevancy(self, text: str, level: int, temperature: float = 10.0) -> np.ndarray:
        """[N] float64: each Gaussian carries its level-``level`` region's relevancy for
        ``text`` (what a relevancy map renders)."""
        scores = self.relevancy([text], level, temperature)[0]
        return scores[self.regions.labels[:, level]]

    def gaussian_relevancies(self, texts: Sequence[str], level: int) -> np.ndarray:
        """[N, Q] float64: each Gaussian carries its level-``level`` region's relevancy for each
        text, at the config's temperature (what the LangSplat protocol renders)."""
        scores = self.relevancy(texts, level, self.config.temperature)
        return scores.T[self.regions.labels[:, level]]

    def gaussians_of(self, regions: Sequence[tuple[int, int]]) -> np.ndarray:
        """[N] bool: the members of the ``(level, region)`` pairs (levels 1..3)."""
        mask = np.zeros(len(self.regions), dtype=bool)
        for level, region in regions:
            level = self.regions.checked_level(level)
            self._members[level].mark(mask, self.regions.checked_region(level, region))
        return mask

    def select(self, texts: Sequence[str], config: QueryConfig | None = None) -> list[Selection]:
        """One :class:`Selection` per text, in order (repeated texts share one result).

        Raises:
            InputError: an empty text or an invalid config.
        """
        texts = _checked_texts(texts)
        config = (config or self.config).check()
        todo = [text for text in dict.fromkeys(texts) if (text, config) not in self._results]
        if todo:
            smallest = self.min_gaussians if config.min_gaussians is None else config.min_gaussians
            allowed = {k: self._sizes[k] >= smallest for k in config.searched_levels}
            scores = {
                k: self.relevancy(todo, k, config.temperature) for k in config.searched_levels
            }
            cosines = {k: self.centred_similarity(todo, k, smallest) for k in (1, 2, 3)}
            null = self.null_model(smallest)
            presence = self._presence(cosines, smallest, null)
            cut = config.threshold if config.threshold is not None else self.threshold
            if config.mode == "auto":
                read = (
                    cosines if config.centred else {k: self.similarity(todo, k) for k in (1, 2, 3)}
                )
                judge = None
                if config.threshold is None:
                    judge = self.null_model(smallest, centred=config.centred)
                parents = None
                if config.hierarchical and self.regions.levels.nested:
                    parents = self.regions.levels.parents[1:]  # type: ignore[index]
            unselectable = unselectable_reason(
                {k: self.regions.seen[k - 1] for k in config.searched_levels}, allowed
            )
            for q, text in enumerate(todo):
                reason = None
                if unselectable is not None:
                    regions, reason = (), unselectable
                elif config.mode == "auto":
                    choice = select_auto(
                        {k: s[q] for k, s in scores.items()},
                        {k: c[q] for k, c in read.items()},
                        {k: np.flatnonzero(allowed[k] & (s[q] > 0)) for k, s in scores.items()},
                        config.extent,
                        cut,
                        parents=parents,
                        descend=config.descend,
                        siblings=config.siblings,
                        null=judge,
                        min_score=config.min_score,
                    )
                    regions = choice.regions
                    if not regions and choice.best_score is not None:
                        reason = abstain_reason(
                            text, choice.best_score, config.min_score, score=True
                        )
                    elif not regions:
                        reason = abstain_reason(text, choice.best_relevancy, cut)
                else:
                    regions = select(
                        {k: s[q] for k, s in scores.items()}, config, allowed, self.threshold
                    )
                selection = Selection(
                    text,
                    regions,
                    self.gaussians_of([(k, r) for k, r, _ in regions]),
                    reason,
                    None if null is None else float(presence[q]),
                    None
                    if null is None
                    else tuple(  # selected regions are seen
                        float(region_confidence(null.score(cosines[k][q, r])))
                        for k, r, _ in regions
                    ),
                )
                self._remember((text, config), selection)
                logger.debug(
                    "query %r (%s): %d regions, %d Gaussians",
                    text,
                    config.mode,
                    len(regions),
                    selection.gaussians.sum(),
                )
        return [self._results[(text, config)] for text in texts]

    def null_model(
        self, min_gaussians: int | None = None, *, centred: bool = True
    ) -> NullModel | None:
        """The scene's null (:class:`thgs.confidence.NullModel`): how well the generic
        :data:`thgs.confidence.NULL_PHRASES` match the regions of levels 1–3 that are seen and
        have at least ``min_gaussians`` Gaussians (None: the field's small-region size), by
        their centred cosines (:meth:`centred_similarity`; what confidences and the automatic
        selection read) or, with ``centred`` False, their raw ones. None when no region
        qualifies or every phrase matches equally well (no spread to measure against)."""
        smallest = self.min_gaussians if min_gaussians is None else min_gaussians
        if (smallest, centred) not in self._nulls:
            similarity = (
                (lambda k: self.centred_similarity(NULL_PHRASES, k, smallest))
                if centred
                else (lambda k: self.similarity(NULL_PHRASES, k))
            )
            cosines = self._selectable_cosines({k: similarity(k) for k in (1, 2, 3)}, smallest)
            degenerate = cosines.size == 0 or not cosines.max(axis=1).std() > 1e-9
            self._nulls[(smallest, centred)] = (
                None if degenerate else NullModel.from_similarities(cosines)
            )
        return self._nulls[(smallest, centred)]

    def confidence(
        self, texts: Sequence[str], level: int, min_gaussians: int | None = None
    ) -> np.ndarray:
        """[Q, R_level] the calibrated probability that each level-``level`` region belongs to
        what each text names (:func:`thgs.confidence.region_confidence`; 0 for unseen regions;
        NaN when the scene has no null, see :meth:`null_model`), from the centred cosines."""
        level = self.regions.checked_level(level)
        null = self.null_model(min_gaussians)
        cosines = self.centred_similarity(texts, level, min_gaussians)
        return self._region_confidence(cosines, level, null)

    def presence(self, texts: Sequence[str], min_gaussians: int | None = None) -> np.ndarray:
        """[Q] the calibrated probability that the scene holds what each text names
        (:func:`thgs.confidence.presence_confidence` of its best selectable region; NaN when
        the scene has no null)."""
        smallest = self.min_gaussians if min_gaussians is None else min_gaussians
        cosines = {k: self.centred_similarity(texts, k, smallest) for k in (1, 2, 3)}
        return self._presence(cosines, smallest, self.null_model(smallest))

    def _selectable_cosines(self, cosines: dict[int, np.ndarray], smallest: int) -> np.ndarray:
        """[Q, C] the columns of ``cosines`` (level → [Q, R_level]) that belong to seen regions
        with at least ``smallest`` Gaussians."""
        columns = [
            cosines[k][:, self.regions.seen[k - 1] & (self._sizes[k] >= smallest)]
            for k in (1, 2, 3)
        ]
        return np.concatenate(columns, axis=1)

    def _region_confidence(
        self, cosines: np.ndarray, level: int, null: NullModel | None
    ) -> np.ndarray:
        """[Q, R_level] region confidences from the texts' cosines with the level's regions."""
        if null is None:
            return np.full(cosines.shape, np.nan)
        return np.where(self.regions.seen[level - 1], region_confidence(null.score(cosines)), 0.0)

    def _presence(
        self, cosines: dict[int, np.ndarray], smallest: int, null: NullModel | None
    ) -> np.ndarray:
        """[Q] presence from the texts' cosines with every level's regions (level → [Q, R])."""
        if null is None:
            return np.full(len(cosines[1]), np.nan)
        best = self._selectable_cosines(cosines, smallest).max(axis=1)
        return presence_confidence(null.score(best))

    def selected(self, texts: Sequence[str]) -> np.ndarray:
        """[N, Q] bool: the Gaussians each text selects under the default config."""
        selections = self.select(texts)
        if not selections:
            return np.zeros((len(self.regions), 0), dtype=bool)
        return np.stack([selection.gaussians for selection in selections], axis=1)

    def classify(self, texts: Sequence[str], level: int) -> np.ndarray:
        """[N] int: per Gaussian, the index of the text whose embedding is closest (cosine) to
        its level-``level`` region's feature; −1 for Gaussians of unseen regions (ScanNet's
        per-point classes)."""
        level = self.regions.checked_level(level)
        cosine = self.regions.features[level - 1].astype(np.float64) @ self.embed(texts).T
        best = cosine.argmax(axis=1)
        best[~self.regions.seen[level - 1]] = -1
        return best[self.regions.labels[:, level]]

    def with_config(self, **changes: Any) -> QueryConfig:
        """This query's default config with ``changes`` applied (checked)."""
        return replace(self.config, **changes).check()

    def using(self, **changes: Any) -> FieldQuery:
        """The same engine (regions, encoder, caches shared) whose default config has
        ``changes`` applied: e.g. ``engine.using(mode="paper")`` scores the paper's rule where a
        protocol takes the engine's default."""
        other = copy.copy(self)
        other.config = self.with_config(**changes)
        return other

    def _remember(self, key: tuple[str, QueryConfig], selection: Selection) -> None:
        self._results[key] = selection
        self._results.move_to_end(key)
        while len(self._results) > _CACHED_RESULTS:
            self._results.popitem(last=False)


def small_region_size(field: SemanticField) -> int:
    """The field's ``thres_merge`` (its recorded :class:`thgs.hierarchy.MergeConfig`'s
    ``min_region_gaussians``): regions below it are unabsorbed leftovers. 0 (every region
    selectable) when the field records no merge settings or ones this thgs cannot read (logged)."""
    if "merge" not in field.config:
        return 0
    try:
        merge = config_from_json(MergeConfig, field.config["merge"], "field config: merge")
    except InputError as error:
        logger.warning("%s; every region may be selected", error)
        return 0
    return merge.min_region_gaussians


def _checked_texts(texts: Sequence[str]) -> list[str]:
    if isinstance(texts, str):
        raise InputError("queries", "pass a list of texts, not one string")
    texts = list(texts)
    for text in texts:
        if not isinstance(text, str) or not text.strip():
            raise InputError("queries", f"every query must be a non-empty text, got {text!r}")
    return texts


def select_paper(
    field: SemanticField,
    query: np.ndarray,
    canonical: np.ndarray,
    *,
    levels: tuple[int, ...] = (2, 3),
    per_level: int = 3,
    keep: int = 3,
    temperature: float = 10.0,
) -> Selection:
    """The paper's evaluation selection for one query embedding.

    Args:
        field: the semantic field.
        query: [D] unit query embedding in ``field.space``.
        canonical: [C, D] canonical phrase embeddings in the same space.
        levels: the levels pooled (2 and 3: parts and objects).
        per_level: regions taken from each level (3).
        keep: regions kept from the pool, by raw relevancy (3); no threshold.
        temperature: of :func:`relevancy`.

    Returns:
        a :class:`Selection` (``text`` empty); ties are broken by lower level, then lower
        region id.
    """
    config = QueryConfig(
        mode="paper", levels=levels, per_level=per_level, keep=keep, temperature=temperature
    ).check()
    scores = {
        level: relevancy(
            field.features[level - 1], query, canonical, temperature, field.seen[level - 1]
        )
        for level in levels
    }
    regions = select(scores, config)
    selected = np.zeros(len(field), dtype=bool)
    for level, region, _ in regions:
        selected |= field.labels[:, level] == region
    return Selection("", regions, selected)
