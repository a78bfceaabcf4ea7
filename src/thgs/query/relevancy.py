"""LERF's relevancy of a region's feature for a query, against the canonical phrases, and the
``threshold`` mode's default per embedding space (the formula: :mod:`thgs.query`).
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.special import expit

from thgs.errors import InputError
from thgs.text import MINILM_SPACE

__all__ = [
    "CANONICAL_PHRASES",
    "default_threshold",
    "relevancy",
]

logger = logging.getLogger(__name__)


CANONICAL_PHRASES = ("object", "things", "stuff", "texture")
"""LERF's canonical negatives, encoded in the field's space and passed as ``canonical``."""


_THRESHOLDS = {MINILM_SPACE: 0.8}


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
