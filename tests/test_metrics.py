"""Segmentation scores against hand-computed cases and brute force."""

from __future__ import annotations

import numpy as np
import pytest

from thgs.errors import InputError
from thgs.eval import purity


def _brute_force_purity(labels: np.ndarray, truth: np.ndarray) -> float:
    """Per Gaussian: is its node the most common one (smallest on ties) in its region?"""
    scored = [i for i in range(len(truth)) if truth[i] >= 0]
    if not scored:
        return 1.0
    pure = 0
    for i in scored:
        if labels[i] < 0:
            continue
        nodes = [int(truth[j]) for j in scored if labels[j] == labels[i]]
        majority = max(sorted(set(nodes)), key=nodes.count)
        pure += int(truth[i] == majority)
    return pure / len(scored)


def test_purity_hand_case():
    # region 0: nodes (0, 0, 1) → 2 pure; region 1: (2, 2) → 2; a floater (truth −1) is left
    # out; a Gaussian in no region counts as impure: 4 / 6
    labels = np.array([0, 0, 0, 1, 1, 1, -1])
    truth = np.array([0, 0, 1, 2, 2, -1, 2])
    assert purity(labels, truth) == pytest.approx(4 / 6)
    assert purity(np.arange(7), truth) == 1.0  # one region per Gaussian is trivially pure
    assert purity(labels, np.full(7, -1)) == 1.0


@pytest.mark.parametrize("seed", range(5))
def test_purity_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    labels = rng.integers(-1, 8, size=200)
    truth = rng.integers(-1, 5, size=200)
    assert purity(labels, truth) == pytest.approx(_brute_force_purity(labels, truth))


def test_purity_rejects_bad_shapes():
    with pytest.raises(InputError, match="must be"):
        purity(np.zeros(3, int), np.zeros(4, int))
    with pytest.raises(InputError, match="≥ −1"):
        purity(np.array([0, -2]), np.array([0, 0]))
