""":class:`FieldQuery`, the one query engine: batches of queries on a field or on any
:class:`thgs.query.Regions`, text embeddings and results cached per text, selections with their
confidences, for the CLI, the viewer and every evaluation protocol.
"""

from __future__ import annotations

import copy
import logging
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from thgs.confidence import NULL_PHRASES, NullModel, presence_confidence, region_confidence
from thgs.errors import InputError
from thgs.field import SemanticField
from thgs.query.config import QueryConfig
from thgs.query.regions import Regions
from thgs.query.relevancy import CANONICAL_PHRASES, default_threshold, relevancy
from thgs.query.rules import Selection, abstain_reason, select, select_auto, unselectable_reason
from thgs.text import TextEncoder, check_space

__all__ = [
    "FieldQuery",
]

logger = logging.getLogger(__name__)


_CACHED_RESULTS = 256


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
            given = config.min_relevancy if config.mode == "auto" else config.threshold
            cut = given if given is not None else self.threshold
            if config.mode == "auto":
                read = (
                    cosines if config.centred else {k: self.similarity(todo, k) for k in (1, 2, 3)}
                )
                judge = None
                if config.min_relevancy is None:
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
                        min_part_score=config.min_part_score,
                        part_lead=config.part_lead,
                    )
                    regions = choice.regions
                    if not regions and choice.needed_score is not None:
                        reason = abstain_reason(
                            text, choice.best_score, choice.needed_score, score=True
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


def _checked_texts(texts: Sequence[str]) -> list[str]:
    if isinstance(texts, str):
        raise InputError("queries", "pass a list of texts, not one string")
    texts = list(texts)
    for text in texts:
        if not isinstance(text, str) or not text.strip():
            raise InputError("queries", f"every query must be a non-empty text, got {text!r}")
    return texts
