"""What the evaluation protocols ask of a scene segmentation: text → Gaussians, per level.

The protocols score selections, relevancies and per-Gaussian classes. They read them from a
:class:`Segmenter`, which needs only each level's region ids, features and seen flags, not the
nesting of a :class:`thgs.field.SemanticField`. That lets the "no progressive merging" ablation
(levels built independently from the superpoints, which need not nest) be scored by exactly the
same code as a field.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from thgs.errors import InputError
from thgs.field import SemanticField
from thgs.query import (
    CANONICAL_PHRASES,
    QueryConfig,
    default_threshold,
    relevancy,
    select,
    small_region_size,
)
from thgs.text import TextEncoder, check_space

__all__ = ["Regions", "Segmenter"]


@dataclass(frozen=True, eq=False)
class Regions:
    """Regions of N Gaussians at levels 1–3 and their features; levels need not nest.

    Attributes:
        labels: [N, 4] integer region id per Gaussian at levels 0–3 (column k is level k; ids
            0 … R_k − 1, every Gaussian in one region).
        features: level k = 1..3 at index k − 1: [R_k, D] unit features (zero rows unseen).
        seen: level k at index k − 1: [R_k] bool, whether any view saw the region.
        space: the features' embedding space.
        min_region_gaussians: regions with fewer Gaussians are never selected (the field's
            small-region size; 0 selects every region).
    """

    labels: np.ndarray
    features: tuple[np.ndarray, np.ndarray, np.ndarray]
    seen: tuple[np.ndarray, np.ndarray, np.ndarray]
    space: str
    min_region_gaussians: int = 0

    @classmethod
    def from_field(cls, field: SemanticField) -> Regions:
        """A field's regions, with its small-region size (``config["merge"]``)."""
        return cls(field.labels, field.features, field.seen, field.space, small_region_size(field))

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def check(self, source: str = "Regions") -> Regions:
        """Verify shapes and id ranges; raise :class:`InputError` naming ``source``."""
        labels = np.asarray(self.labels)
        if labels.ndim != 2 or labels.shape[1] != 4:
            raise InputError(source, f"labels must be [N, 4], got {list(labels.shape)}")
        dims = set()
        for k in (1, 2, 3):
            features, seen = self.features[k - 1], self.seen[k - 1]
            if features.ndim != 2 or seen.shape != (features.shape[0],):
                raise InputError(
                    source,
                    f"level {k}: features {list(features.shape)} and seen {list(seen.shape)} "
                    "must be [R, D] and [R]",
                )
            if len(labels) and (labels[:, k].min() < 0 or labels[:, k].max() >= len(features)):
                raise InputError(source, f"level {k}: region ids outside 0..{len(features) - 1}")
            dims.add(features.shape[1])
        if len(dims) != 1:
            raise InputError(source, f"levels have different feature dimensions {sorted(dims)}")
        return self


class Segmenter:
    """Text queries of :class:`Regions` with one encoder, for the protocols.

    Args:
        regions: the regions and features (``Regions.from_field(field)`` for a field).
        encoder: a text encoder in ``regions.space``.
        config: how relevancies become a selection (:class:`thgs.query.QueryConfig`; the
            default is the paper's reference selection).
        source: what to name in errors.

    Raises:
        SpaceMismatchError: the encoder's space is not the regions'.
    """

    def __init__(
        self,
        regions: Regions,
        encoder: TextEncoder,
        config: QueryConfig = QueryConfig(),
        *,
        source: str = "segmentation",
    ):
        check_space(regions.space, encoder, source)
        self.regions = regions.check(source)
        self.encoder = encoder
        self.config = config.check()
        self._canonical = encoder.encode(list(CANONICAL_PHRASES)).astype(np.float64)
        self._threshold = default_threshold(regions.space)
        smallest = (
            regions.min_region_gaussians if config.min_gaussians is None else config.min_gaussians
        )
        self._allowed = {
            k: np.bincount(regions.labels[:, k], minlength=len(regions.features[k - 1])) >= smallest
            for k in (1, 2, 3)
        }

    def _embed(self, texts: Sequence[str]) -> np.ndarray:
        if isinstance(texts, str) or not all(isinstance(t, str) and t.strip() for t in texts):
            raise InputError("texts", "pass a list of non-empty texts")
        return self.encoder.encode(list(texts)).astype(np.float64)

    def region_relevancy(self, texts: Sequence[str], level: int) -> np.ndarray:
        """[Q, R_level] relevancy of every region of ``level`` (1..3) for every text."""
        if level not in (1, 2, 3):
            raise InputError("level", f"must be 1, 2 or 3, got {level}")
        return relevancy(
            self.regions.features[level - 1],
            self._embed(texts),
            self._canonical,
            self.config.temperature,
            self.regions.seen[level - 1],
        )

    def relevancy(self, texts: Sequence[str], level: int) -> np.ndarray:
        """[N, Q] float64: each Gaussian carries its level-``level`` region's relevancy."""
        return self.region_relevancy(texts, level).T[self.regions.labels[:, level]]

    def select(self, texts: Sequence[str]) -> np.ndarray:
        """[N, Q] bool: the Gaussians each text selects under ``config``."""
        levels = self.config.searched_levels
        scores = {k: self.region_relevancy(texts, k) for k in levels}
        selected = np.zeros((len(self.regions), len(texts)), dtype=bool)
        for q in range(len(texts)):
            chosen = select(
                {k: s[q] for k, s in scores.items()}, self.config, self._allowed, self._threshold
            )
            for level, region, _ in chosen:
                selected[:, q] |= self.regions.labels[:, level] == region
        return selected

    def classify(self, texts: Sequence[str], level: int) -> np.ndarray:
        """[N] int: per Gaussian, the index of the text whose embedding is closest (cosine) to
        its level-``level`` region's feature; −1 for Gaussians of unseen regions."""
        if level not in (1, 2, 3):
            raise InputError("level", f"must be 1, 2 or 3, got {level}")
        cosine = self.regions.features[level - 1].astype(np.float64) @ self._embed(texts).T
        best = cosine.argmax(axis=1)
        best[~self.regions.seen[level - 1]] = -1
        return best[self.regions.labels[:, level]]
