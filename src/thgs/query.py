"""Open-vocabulary queries of a semantic field (design §4.8): relevancy and the paper's selection.

The relevancy of a region with unit feature φ for a query embedding q, against the canonical
phrases c_i ("object", "things", "stuff", "texture"), is LERF's

    rel(φ, q) = min_i exp(t φ·q) / (exp(t φ·q) + exp(t φ·c_i)),   t = 10,

which equals ``min_i σ(t (φ·q − φ·c_i))`` and is computed in that stable form. It lies in
(0, 1); 0.5 means "no more like the query than like a generic phrase". Regions that no view saw
have no feature and score 0, so they are never selected.

:func:`select_reference` is the selection of the paper's evaluation: the 3 most relevant regions
of level 2 and the 3 of level 3 are pooled, the 3 best of those six are kept (no threshold), and
the selected Gaussians are the union of their members.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import expit

from thgs.errors import InputError
from thgs.field import SemanticField

__all__ = ["CANONICAL_PHRASES", "Selection", "relevancy", "select_reference"]

CANONICAL_PHRASES = ("object", "things", "stuff", "texture")
"""LERF's canonical negatives, encoded in the field's space and passed as ``canonical``."""


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


@dataclass(frozen=True, eq=False)
class Selection:
    """The regions a query selected and their Gaussians.

    Attributes:
        regions: ``(level, region, relevancy)`` triples, most relevant first.
        gaussians: [N] bool, True for the members of any selected region.
    """

    regions: tuple[tuple[int, int, float], ...]
    gaussians: np.ndarray


def select_reference(
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
        a :class:`Selection`; ties are broken by lower level, then lower region id.
    """
    pool = []
    for level in levels:
        if level not in (1, 2, 3):
            raise InputError("select_reference", f"levels must be in 1..3, got {level}")
        scores = relevancy(
            field.features[level - 1], query, canonical, temperature, field.seen[level - 1]
        )
        order = np.lexsort((np.arange(scores.size), -scores))[:per_level]
        pool += [(-float(scores[r]), level, int(r)) for r in order]
    chosen = sorted(pool)[:keep]
    selected = np.zeros(len(field), dtype=bool)
    for _, level, region in chosen:
        selected |= field.labels[:, level] == region
    return Selection(
        regions=tuple((level, region, -score) for score, level, region in chosen),
        gaussians=selected,
    )
