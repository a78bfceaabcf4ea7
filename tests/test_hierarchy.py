"""Progressive merging: adjacency and affinity vs brute force, growing by hand, nesting."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from conftest import random_gaussians
from thgs.errors import InputError
from thgs.hierarchy import MergeConfig, gaussian_neighbors, merge_levels, pair_affinity, unit_graph
from thgs.hierarchy.merge import _grow
from thgs.lift import ViewLift


def test_gaussian_neighbors_include_self_and_match_brute_force():
    gaussians = random_gaussians(60, seed=1)
    neighbors = gaussian_neighbors(gaussians, 8)
    means = gaussians.means.numpy().astype(np.float64)
    squared = ((means[:, None] - means[None]) ** 2).sum(-1)
    expected = np.argsort(squared, axis=1, kind="stable")[:, :8]
    np.testing.assert_array_equal(np.sort(neighbors, axis=1), np.sort(expected, axis=1))
    assert (neighbors == np.arange(60)[:, None]).any(axis=1).all()
    few = gaussian_neighbors(random_gaussians(3, seed=2), 8)
    assert few.shape == (3, 8) and set(few[0]) == {0, 1, 2}


def test_unit_graph_matches_brute_force():
    rng = np.random.default_rng(0)
    units = rng.integers(0, 12, 80)
    units[:12] = np.arange(12)
    neighbors = rng.integers(0, 80, (80, 4))
    graph = unit_graph(units, neighbors)
    touching = set()
    for i, j in itertools.product(range(80), range(4)):
        a, b = units[i], units[neighbors[i, j]]
        if a != b:
            touching.add((min(a, b), max(a, b)))
    adjacent = {a: set() for a in range(12)}
    for a, b in touching:
        adjacent[a].add(b)
        adjacent[b].add(a)
    two = {
        (min(a, c), max(a, c))
        for a in range(12)
        for b in adjacent[a]
        for c in adjacent[b]
        if c != a and (min(a, c), max(a, c)) not in touching
    }
    pairs = {tuple(p): h for p, h in zip(graph.pairs.tolist(), graph.hops.tolist())}
    assert pairs == {**{p: 1 for p in touching}, **{p: 2 for p in two}}
    one = graph.one_hop.toarray()
    assert (one == one.T).all() and not one.diagonal().any()


@pytest.mark.parametrize("links", [127, 128, 150, 256, 300])
def test_units_joined_by_many_gaussian_pairs_touch(links):
    # regression: counting the Gaussian pairs between two units in int8 wrapped at 128, and
    # units joined by 128–255 (mod 256) pairs were taken for 2-hop or unrelated units
    units = np.repeat([0, 1, 2], links)
    neighbors = np.stack([np.arange(3 * links), np.arange(3 * links)], axis=1)
    neighbors[:links, 1] += links  # every Gaussian of unit 0 has one of unit 1 as neighbour
    neighbors[links : links + 1, 1] = 2 * links  # one pair joins units 1 and 2
    graph = unit_graph(units, neighbors)
    assert graph.pairs.tolist() == [[0, 1], [0, 2], [1, 2]]
    assert graph.hops.tolist() == [1, 2, 1]


def _brute_affinity(units, count, a, b, sources):
    sizes = np.bincount(units, minlength=count)
    numerator = denominator = 0.0
    for gaussians, labels in sources:
        hist = {}
        for g, label in zip(gaussians, labels):
            if label >= 0:
                hist.setdefault(units[g], {}).setdefault(label, 0)
                hist[units[g]][label] += 1
        if a not in hist or b not in hist:
            continue
        share_a = sum(hist[a].values()) / sizes[a]
        share_b = sum(hist[b].values()) / sizes[b]
        dot = sum(v * hist[b].get(k, 0) for k, v in hist[a].items())
        norm = np.sqrt(sum(v * v for v in hist[a].values()) * sum(v * v for v in hist[b].values()))
        numerator += share_a * share_b * dot / norm
        denominator += share_a * share_b
    return numerator / denominator if denominator else 0.0


@pytest.mark.parametrize("seed", range(3))
def test_pair_affinity_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    units = rng.integers(0, 10, 200)
    units[:10] = np.arange(10)
    sources = []
    for _ in range(5):
        seen = np.sort(rng.choice(200, 120, replace=False))
        sources.append((seen, rng.integers(-1, 6, seen.size)))
    sources.append((np.zeros(0, np.int64), np.zeros(0, np.int64)))  # a view without labels
    pairs = np.array([(a, b) for a in range(10) for b in range(a + 1, 10)])
    got = pair_affinity(units, 10, pairs, sources)
    expected = [_brute_affinity(units, 10, a, b, sources) for a, b in pairs]
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_affinity_hand_case():
    # unit 0 = Gaussians 0, 1; unit 1 = 2, 3. View A: all four in mask 7 → cos 1, shares 1, 1.
    # View B: Gaussian 0 in mask 7, 2 in mask 8 → cos 0, shares ½, ½. A = (1 + 0) / (1 + ¼)
    units = np.array([0, 0, 1, 1])
    view_a = (np.arange(4), np.array([7, 7, 7, 7]))
    view_b = (np.array([0, 2]), np.array([7, 8]))
    got = pair_affinity(units, 2, np.array([[0, 1]]), [view_a, view_b])
    np.testing.assert_allclose(got, [1 / 1.25])


def test_growing_hand_case():
    # a chain 0 – 1 – 2 – 3 of equal units; A(0,1) = 0.95, A(1,2) = 0.95, A(0,2) = 0.5 (2 hops),
    # A(2,3) = 0.2, A(1,3) = 0.2. Unit 2 joins {0, 1} if (2·0.95 + 1·0.5) / 3 = 0.8 ≥ threshold;
    # unit 3 then joins if (2·0.2 + 1·0.2) / 3 = 0.2 ≥ threshold.
    pairs = [(0, 1, 1, 0.95), (1, 2, 1, 0.95), (0, 2, 2, 0.5), (2, 3, 1, 0.2), (1, 3, 2, 0.2)]
    rows, cols, hops, values = [], [], [], []
    for a, b, h, v in pairs:
        rows += [a, b]
        cols += [b, a]
        hops += [h, h]
        values += [v, v]
    order = np.lexsort((cols, rows))
    indptr2 = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=4))])
    one_rows = [0, 1, 1, 2, 2, 3]
    one_cols = [1, 0, 2, 1, 3, 2]
    indptr1 = np.concatenate([[0], np.cumsum(np.bincount(one_rows, minlength=4))])

    def grow(threshold):
        return _grow(
            indptr1.astype(np.int64),
            np.array(one_cols, dtype=np.int64),
            indptr2.astype(np.int64),
            np.array(cols)[order].astype(np.int64),
            np.array(hops)[order].astype(np.int8),
            np.array(values)[order],
            np.ones(4),
            threshold,
            2.0,
        )

    np.testing.assert_array_equal(grow(0.79), [0, 0, 0, 1])
    np.testing.assert_array_equal(grow(0.81), [0, 0, 1, 2])  # 2 seeds a region 3 cannot join
    np.testing.assert_array_equal(grow(0.15), [0, 0, 0, 0])
    np.testing.assert_array_equal(grow(0.96), [0, 1, 2, 3])


def _blocks_scene():
    """Two objects, each of two parts, each of two sub-parts, each of two superpoints: 16
    superpoints of 50 Gaussians on a line of blocks, with clean labels at every level."""
    n = 800
    x = np.repeat(np.arange(16), 50) + np.tile(np.linspace(0, 0.9, 50), 16)
    means = np.stack([x, np.zeros(n), np.zeros(n)], axis=1)
    gaussians = random_gaussians(n, seed=3)
    gaussians = type(gaussians)(
        means=torch.tensor(means, dtype=torch.float32),
        quats=gaussians.quats,
        scales=gaussians.scales,
        opacities=gaussians.opacities,
        sh=gaussians.sh,
    )
    superpoints = np.repeat(np.arange(16), 50)
    truth = np.stack([superpoints // 2, superpoints // 4, superpoints // 8], axis=1)
    return gaussians, superpoints, truth


def _views(truth, count=4, offset=100):
    n = len(truth)
    labels = np.stack([truth[:, 0], truth[:, 0], truth[:, 1] + offset, truth[:, 2] + 2 * offset])
    return [
        ViewLift(
            gaussians=np.arange(n, dtype=np.int32),
            labels=labels.T.astype(np.int16),
            depths=np.full(n, 2.0, np.float32),
            max_weights=np.full(n, 0.5, np.float32),
        )
        for _ in range(count)
    ]


def test_clean_labels_recover_the_hierarchy_and_levels_nest():
    gaussians, superpoints, truth = _blocks_scene()
    merged = merge_levels(gaussians, superpoints, _views(truth), MergeConfig())
    assert merged.counts == (16, 8, 4, 2)
    for k in (1, 2, 3):
        np.testing.assert_array_equal(merged.labels[:, k], truth[:, k - 1])
        parent = merged.parents[k - 1]
        np.testing.assert_array_equal(merged.labels[:, k], parent[merged.labels[:, k - 1]])
    instance = merge_levels(gaussians, superpoints, _views(truth), MergeConfig(mode="instance"))
    for k in (1, 2, 3):
        np.testing.assert_array_equal(instance.labels[:, k], truth[:, 2])
    independent = merge_levels(
        gaussians, superpoints, _views(truth), MergeConfig(mode="independent")
    )
    assert independent.parents is None
    np.testing.assert_array_equal(independent.labels[:, 2], truth[:, 1])


def test_hidden_labels_do_not_vote():
    # twelve more views see everything through an occluder (max w 0.01), all in one mask
    gaussians, superpoints, truth = _blocks_scene()
    views = _views(truth)
    n = len(truth)
    occluded = ViewLift(
        np.arange(n, dtype=np.int32),
        np.full((n, 4), 999, np.int16),
        np.full(n, 2.0, np.float32),
        np.full(n, 0.01, np.float32),
    )
    views = [*views, *[occluded] * 12]
    ours = merge_levels(gaussians, superpoints, views, MergeConfig())
    assert ours.counts == (16, 8, 4, 2)
    # the reference counts them: across objects A = 12 / 16 = 0.75 ≥ 0.7, one object remains
    reference = merge_levels(gaussians, superpoints, views, MergeConfig(min_max_weight=0.0))
    assert reference.counts[3] == 1


def test_small_regions_join_their_most_similar_neighbour():
    gaussians, superpoints, truth = _blocks_scene()
    truth = truth.copy()
    truth[superpoints == 15, :] = [99, 99, 99]  # the last superpoint is its own object
    merged = merge_levels(gaussians, superpoints, _views(truth), MergeConfig())
    assert merged.counts[3] == 3  # 50 Gaussians ≥ 20: kept
    absorbing = MergeConfig(min_region_gaussians=60)
    merged = merge_levels(gaussians, superpoints, _views(truth), absorbing)
    assert merged.counts[3] == 2  # absorbed into its only touching region
    np.testing.assert_array_equal(merged.labels[superpoints == 15, 3], 1)


def test_bad_input_is_named():
    gaussians, superpoints, truth = _blocks_scene()
    with pytest.raises(InputError, match="superpoints"):
        merge_levels(gaussians, superpoints[:-1], _views(truth))
    with pytest.raises(InputError, match="each used"):
        merge_levels(gaussians, superpoints * 2, _views(truth))
    with pytest.raises(InputError, match="mode"):
        MergeConfig(mode="flat")
