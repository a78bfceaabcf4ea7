"""Relevancy against a hand computation, and the paper's selection on a hand-built field."""

from __future__ import annotations

import math

import numpy as np
import pytest

from thgs.errors import InputError
from thgs.field import SemanticField
from thgs.query import relevancy, select_reference


def _unit(*values: float) -> np.ndarray:
    v = np.array(values, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_relevancy_hand_case():
    features = np.stack([_unit(1, 0, 0), _unit(0, 1, 0), _unit(1, 1, 0), np.zeros(3)])
    query = _unit(1, 0, 0)
    canonical = np.stack([_unit(0, 1, 0), _unit(0, 0, 1)])

    def lerf(phi_q: float, phi_c: float) -> float:
        return math.exp(10 * phi_q) / (math.exp(10 * phi_q) + math.exp(10 * phi_c))

    expected = [
        min(lerf(1, 0), lerf(1, 0)),
        min(lerf(0, 1), lerf(0, 0)),
        min(lerf(math.sqrt(0.5), math.sqrt(0.5)), lerf(math.sqrt(0.5), 0)),
        0.0,  # unseen: no feature, never relevant
    ]
    np.testing.assert_allclose(relevancy(features, query, canonical), expected, rtol=1e-12)
    both = relevancy(features, np.stack([query, _unit(0, 1, 0)]), canonical)
    assert both.shape == (2, 4)
    np.testing.assert_allclose(both[0], expected, rtol=1e-12)
    # large margins either way neither overflow nor warn
    np.testing.assert_array_equal(
        relevancy(features[:2], query, canonical, temperature=1e4), [1.0, 0.0]
    )


def test_relevancy_rejects_mismatched_dimensions():
    with pytest.raises(InputError, match="share D"):
        relevancy(np.zeros((2, 3)), np.zeros(4), np.zeros((1, 3)))
    with pytest.raises(InputError, match="canonical"):
        relevancy(np.zeros((2, 3)), np.zeros(3), np.zeros((0, 3)))


def _field() -> SemanticField:
    """8 Gaussians; objects {0–3} and {4–7}; parts {0, 1}, {2, 3}, {4, 5}, {6, 7}."""
    superpoint = np.arange(8)
    labels = np.stack([superpoint, superpoint // 2, superpoint // 2, superpoint // 4], axis=1)
    labels = labels.astype(np.int32)
    parents = (
        np.array([0, 0, 1, 1, 2, 2, 3, 3], np.int32),
        np.arange(4, dtype=np.int32),
        np.array([0, 0, 1, 1], np.int32),
    )
    parts = np.stack([_unit(1, 0, 0), _unit(1, 0.2, 0), _unit(0, 1, 0.1), np.zeros(3)])
    objects = np.stack([_unit(1, 0.1, 0), _unit(0, 1, 0)])
    features = (parts.astype(np.float32), parts.astype(np.float32), objects.astype(np.float32))
    seen = (np.array([1, 1, 1, 0], bool), np.array([1, 1, 1, 0], bool), np.ones(2, bool))
    return SemanticField(
        labels, parents, features, seen, "test", "sha256:" + "0" * 64, {}, {}
    ).check()


def test_reference_selection_pools_top_regions_of_levels_two_and_three():
    field = _field()
    canonical = np.stack([_unit(0, 0, 1)])
    query = _unit(1, 0, 0)
    scores = {(2, r): s for r, s in enumerate(relevancy(field.features[1], query, canonical))} | {
        (3, r): s for r, s in enumerate(relevancy(field.features[2], query, canonical))
    }
    # level 2 top 3: parts 0, 1, 2 (part 3 unseen); level 3: objects 0, 1; best 3 overall:
    expected = sorted(scores, key=lambda key: (-scores[key], key))[:3]
    selection = select_reference(field, query, canonical)
    assert [(level, region) for level, region, _ in selection.regions] == expected
    assert expected == [(2, 0), (3, 0), (2, 1)]
    np.testing.assert_array_equal(selection.gaussians, [1, 1, 1, 1, 0, 0, 0, 0])
    assert [s for _, _, s in selection.regions] == pytest.approx([scores[k] for k in expected])
    one = select_reference(field, query, canonical, levels=(3,), per_level=1, keep=1)
    assert one.regions[0][:2] == (3, 0)
