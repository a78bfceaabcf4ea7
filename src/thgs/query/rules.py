"""The selection rules, on one query's relevancies or cosines per level: the paper's
(:func:`select_paper`, top 3 of parts and objects), one level's best or those past a threshold
(:func:`select`), and the automatic descent of the hierarchy (:func:`select_auto`), with the
words that say why nothing was chosen.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from thgs.confidence import NullModel
from thgs.errors import InputError
from thgs.field import SemanticField
from thgs.query.config import QueryConfig
from thgs.query.regions import Regions
from thgs.query.relevancy import relevancy

__all__ = [
    "AutoChoice",
    "Selection",
    "abstain_reason",
    "select",
    "select_auto",
    "select_paper",
    "unselectable_reason",
]

logger = logging.getLogger(__name__)


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
        threshold: the threshold mode's relevancy when ``config.threshold`` is None, and the
            auto mode's when ``config.min_relevancy`` is (auto mode here always abstains by
            relevancy: the null is :class:`FieldQuery`'s).
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
    given = config.min_relevancy if config.mode == "auto" else config.threshold
    cut = given if given is not None else threshold
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
        needed_score: the score the best candidate needed (None when the relevancy decided, or
            there is no candidate).
    """

    regions: tuple[tuple[int, int, float], ...]
    best_relevancy: float
    best_score: float | None = None
    needed_score: float | None = None


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
    min_score: float = 1.3,
    min_part_score: float = 1.05,
    part_lead: float = 0.5,
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
            the best candidate's score is below ``min_score`` (else the relevancy rule), or
            below ``min(min_score, min_part_score)`` when the best candidate is a part or
            sub-part that stands out from its parent (a candidate too): its cosine above the
            parent's by at least ``part_lead`` times the null's spread. A query matched that
            specifically is about something there; one matched as much by the region around
            it (a giraffe by a teddy bear and all its pieces) needs more.
        min_score: see ``null``.
        min_part_score: see ``null`` (read only with ``parents``).
        part_lead: see ``null``.
    """
    pairs = [(level, int(region)) for level, ids in candidates.items() for region in ids]
    best_relevancy = max((float(scores[level][region]) for level, region in pairs), default=0.0)
    if not pairs:
        return AutoChoice((), best_relevancy)
    cosines = np.array([similarities[level][region] for level, region in pairs])
    best, median = float(cosines.max()), float(np.median(cosines))
    own = None  # with parents: level → each region's cosine, −inf where it is no candidate
    if parents is not None:
        objects = max(int(parents[1].max(initial=-1)) + 1, len(similarities.get(3, ())))
        sizes = {1: len(parents[0]), 2: len(parents[1]), 3: objects}
        own = {level: np.full(size, -np.inf) for level, size in sizes.items()}
        for (level, region), cosine in zip(pairs, cosines):
            own[level][region] = cosine
    best_score = needed = None
    if null is not None:
        best_score = float(null.score(best))
        needed = min_score
        top = pairs[int(np.argmax(cosines))]  # the first on ties
        if own is not None and _stands_out(own, parents, *top, part_lead * null.std):
            needed = min(min_score, min_part_score)
        if best_score < needed:
            return AutoChoice((), best_relevancy, best_score, needed)
    elif best_relevancy < threshold:
        return AutoChoice((), best_relevancy)
    spread = best - median
    cut = best - extent * spread
    if own is None:
        picked = [(level, region) for (level, region), c in zip(pairs, cosines) if c >= cut]
    else:
        picked = _descend(own, parents, cut, descend * spread, siblings)
    order = sorted((-float(similarities[level][region]), level, region) for level, region in picked)
    regions = tuple((level, region, float(scores[level][region])) for _, level, region in order)
    return AutoChoice(regions, best_relevancy, best_score, needed)


def _stands_out(
    own: dict[int, np.ndarray], parents: Sequence[np.ndarray], level: int, region: int, lead: float
) -> bool:
    """Whether the level-``level`` region ``region`` is a part or sub-part whose parent is a
    candidate (a finite cosine in ``own``) ``lead`` or more below it."""
    if level == 3:
        return False
    above = own[level + 1][int(parents[level - 1][region])]
    return bool(np.isfinite(above)) and float(own[level][region] - above) >= lead


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
