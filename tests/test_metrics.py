"""Segmentation scores against hand-computed cases and brute force."""

from __future__ import annotations

import numpy as np
import pytest

from thgs.errors import InputError
from thgs.eval import best_iou, matched_miou, purity


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


def _brute_force_best_iou(labels: np.ndarray, truth: np.ndarray) -> list[float]:
    """Per node, every region's IoU by set arithmetic, the best kept."""
    scored = {i for i in range(len(truth)) if truth[i] >= 0}
    out = []
    for node in range(int(truth.max()) + 1):
        members = {i for i in scored if truth[i] == node}
        if not members:
            out.append(float("nan"))
            continue
        best = 0.0
        for region in {int(labels[i]) for i in scored if labels[i] >= 0}:
            region_members = {i for i in scored if labels[i] == region}
            best = max(best, len(members & region_members) / len(members | region_members))
        out.append(best)
    return out


def test_best_iou_hand_case():
    # node 0 = {0, 1, 2, 3} split into halves by regions 0 and 1: 0.5; node 1 = {4, 5} and node
    # 2 = {6, 7} merged into region 2: 0.5 each; node 3 = {8}, its Gaussian in no region: 0;
    # a floater (truth −1) in region 2 changes nothing
    labels = np.array([0, 0, 1, 1, 2, 2, 2, 2, -1, 2])
    truth = np.array([0, 0, 0, 0, 1, 1, 2, 2, 3, -1])
    np.testing.assert_allclose(best_iou(labels, truth), [0.5, 0.5, 0.5, 0.0])
    assert matched_miou(labels, truth) == pytest.approx(1.5 / 4)
    assert matched_miou(truth, truth) == 1.0
    np.testing.assert_array_equal(np.isnan(best_iou(np.zeros(2, int), np.array([1, 1]))), [1, 0])


@pytest.mark.parametrize("seed", range(5))
def test_best_iou_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    labels = rng.integers(-1, 8, size=150)
    truth = rng.integers(-1, 6, size=150)
    np.testing.assert_allclose(best_iou(labels, truth), _brute_force_best_iou(labels, truth))


def test_best_iou_rejects_bad_shapes():
    with pytest.raises(InputError, match="must be"):
        best_iou(np.zeros(3, int), np.zeros(4, int))
    with pytest.raises(InputError, match="≥ −1"):
        matched_miou(np.array([0, -2]), np.array([0, 0]))
