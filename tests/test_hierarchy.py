"""Progressive merging: adjacency and affinity vs brute force, growing by hand, nesting."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from conftest import random_gaussians
from thgs.errors import InputError
from thgs.hierarchy import (
    MergeConfig,
    coarsened_graph,
    gaussian_neighbors,
    mask_evidence,
    merge_levels,
    pair_affinity,
    split_incoherent,
    unit_graph,
)
from thgs.hierarchy import affinity as affinity_module
from thgs.hierarchy.affinity import affinity_and_support
from thgs.hierarchy.coherence import _weakest_cut
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


def test_coarsened_graph_equals_the_graph_of_the_regions():
    rng = np.random.default_rng(3)
    units = rng.integers(0, 30, 400)
    units[:30] = np.arange(30)
    neighbors = rng.integers(0, 400, (400, 5))
    groups = rng.integers(0, 9, 30)
    groups[:9] = np.arange(9)
    coarse = coarsened_graph(unit_graph(units, neighbors), groups, 9)
    direct = unit_graph(groups[units], neighbors, 9)
    np.testing.assert_array_equal(coarse.pairs, direct.pairs)
    np.testing.assert_array_equal(coarse.hops, direct.hops)
    assert (coarse.one_hop != direct.one_hop).nnz == 0


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


def _tensor(array) -> torch.Tensor:
    return torch.as_tensor(np.asarray(array))


def _tensors(sources):
    return [tuple(_tensor(part) for part in source) for source in sources]


def _affinity(units, count, pairs, sources) -> np.ndarray:
    return pair_affinity(mask_evidence(_tensor(units), count, _tensors(sources)), pairs)


def _brute_affinity(units, count, a, b, sources):
    sizes = np.bincount(units, minlength=count)
    numerator = denominator = 0.0
    for source in sources:
        gaussians, labels = source[:2]
        weights = source[2] if len(source) > 2 else np.ones(len(labels))
        hist = {}
        for g, label, weight in zip(gaussians, labels, weights):
            if label >= 0 and weight > 0:
                hist.setdefault(units[g], {}).setdefault(label, 0)
                hist[units[g]][label] += weight
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
@pytest.mark.parametrize("weighted", [False, True])
def test_pair_affinity_matches_brute_force(seed, weighted):
    rng = np.random.default_rng(seed)
    units = rng.integers(0, 10, 200)
    units[:10] = np.arange(10)
    sources = []
    for _ in range(5):
        seen = np.sort(rng.choice(200, 120, replace=False))
        labels = rng.integers(-1, 6, seen.size)
        weights = rng.uniform(0, 1, seen.size) * (rng.uniform(size=seen.size) > 0.1)
        sources.append((seen, labels, weights) if weighted else (seen, labels))
    sources.append((np.zeros(0, np.int64), np.zeros(0, np.int64)))  # a view without labels
    pairs = np.array([(a, b) for a in range(10) for b in range(a + 1, 10)])
    got = _affinity(units, 10, pairs, sources)
    expected = [_brute_affinity(units, 10, a, b, sources) for a, b in pairs]
    np.testing.assert_allclose(got, expected, atol=1e-12)
    # pooled into regions, the evidence gives the regions' affinities
    groups = np.array([0, 0, 1, 2, 2, 2, 3, 1, 4, 4])
    pooled = mask_evidence(_tensor(units), 10, _tensors(sources)).pooled(_tensor(groups), 5)
    region_pairs = np.array([(a, b) for a in range(5) for b in range(a + 1, 5)])
    expected = [_brute_affinity(groups[units], 5, a, b, sources) for a, b in region_pairs]
    np.testing.assert_allclose(pair_affinity(pooled, region_pairs), expected, atol=1e-12)


def test_pair_affinity_in_small_chunks_and_sorted_histograms(monkeypatch):
    """The join in chunks of one entry and histograms summed by sorting give the same values."""
    rng = np.random.default_rng(4)
    units = rng.integers(0, 8, 100)
    units[:8] = np.arange(8)
    sources = [(np.arange(100), rng.integers(-1, 4, 100), rng.uniform(0, 1, 100))] * 3
    pairs = np.array([(a, b) for a in range(8) for b in range(a + 1, 8)])
    expected = _affinity(units, 8, pairs, sources)
    monkeypatch.setattr(affinity_module, "_JOIN_CHUNK", 1)
    monkeypatch.setattr(affinity_module, "_DENSE_MAX", 0)
    np.testing.assert_allclose(_affinity(units, 8, pairs, sources), expected, atol=1e-14)


def test_affinity_hand_case():
    # unit 0 = Gaussians 0, 1; unit 1 = 2, 3. View A: all four in mask 7 → cos 1, shares 1, 1.
    # View B: Gaussian 0 in mask 7, 2 in mask 8 → cos 0, shares ½, ½. A = (1 + 0) / (1 + ¼)
    units = np.array([0, 0, 1, 1])
    view_a = (np.arange(4), np.array([7, 7, 7, 7]))
    view_b = (np.array([0, 2]), np.array([7, 8]))
    got = _affinity(units, 2, np.array([[0, 1]]), [view_a, view_b])
    np.testing.assert_allclose(got, [1 / 1.25])
    # weighted labels: in view B Gaussian 0 now weighs 0.2 and 2 weighs 0.1 (faint): shares
    # 0.1 and 0.05, so B counts 0.005 against A's 1: A = 1 / 1.005
    view_b = (np.array([0, 2]), np.array([7, 8]), np.array([0.2, 0.1]))
    view_a = (*view_a, np.ones(4))
    got = _affinity(units, 2, np.array([[0, 1]]), [view_a, view_b])
    np.testing.assert_allclose(got, [1 / 1.005])


def test_evidence_of_some_units_pools_like_all_of_them():
    # the affinity of two groups of units is the same from the evidence of those units alone
    rng = np.random.default_rng(4)
    units = rng.integers(0, 12, 300)
    sources = [
        (np.arange(300), rng.integers(-1, 5, 300), rng.uniform(0.1, 1.0, 300)) for _ in range(6)
    ]
    evidence = mask_evidence(_tensor(units), 12, _tensors(sources))
    members = np.array([7, 2, 9, 4, 11])
    side = np.array([0, 1, 0, 1, 1])
    groups = np.full(12, 2)
    groups[members] = side
    everything = evidence.pooled(_tensor(groups), 3)
    alone = evidence.of_units(_tensor(members)).pooled(_tensor(side), 2)
    np.testing.assert_allclose(alone.sizes.numpy(), everything.sizes.numpy()[:2])
    for got, want in zip(
        affinity_and_support(alone, np.array([[0, 1]])),
        affinity_and_support(everything, np.array([[0, 1]])),
        strict=True,
    ):
        np.testing.assert_allclose(got, want)


def test_affinity_without_support_is_none():
    # one view: Gaussian 0 (unit 0) weighs 0.5 and Gaussian 2 (unit 1) 0.01, both in mask 7:
    # shares 0.25 and 0.005, support 0.00125, cos 1. A ratio of such sums is 1 whatever it rests
    # on; below min_support it is no evidence at all
    units = np.array([0, 0, 1, 1])
    view = (np.array([0, 2]), np.array([7, 7]), np.array([0.5, 0.01]))
    evidence = mask_evidence(_tensor(units), 2, _tensors([view]))
    pair = np.array([[0, 1]])
    np.testing.assert_allclose(pair_affinity(evidence, pair), [1.0])
    np.testing.assert_allclose(pair_affinity(evidence, pair, min_support=0.00124), [1.0])
    np.testing.assert_allclose(pair_affinity(evidence, pair, min_support=0.00126), [0.0])


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

    def grow(threshold, two_hop=1.0):
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
            two_hop,
        )

    np.testing.assert_array_equal(grow(0.79), [0, 0, 0, 1])
    np.testing.assert_array_equal(grow(0.81), [0, 0, 1, 2])  # 2 seeds a region 3 cannot join
    np.testing.assert_array_equal(grow(0.15), [0, 0, 0, 0])
    np.testing.assert_array_equal(grow(0.96), [0, 1, 2, 3])
    # touching members only (ours): unit 2 sees A(1, 2) = 0.95 alone and joins at 0.81
    np.testing.assert_array_equal(grow(0.81, two_hop=0.0), [0, 0, 0, 1])


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


def _views(truth, count=4, offset=100, max_weight=0.5):
    n = len(truth)
    labels = np.stack([truth[:, 0], truth[:, 0], truth[:, 1] + offset, truth[:, 2] + 2 * offset])
    return [
        ViewLift(
            gaussians=np.arange(n, dtype=np.int32),
            labels=labels.T.astype(np.int16),
            depths=np.full(n, 2.0, np.float32),
            max_weights=np.full(n, max_weight, np.float32),
        )
        for _ in range(count)
    ]


def test_clean_labels_recover_the_hierarchy_and_levels_nest():
    gaussians, superpoints, truth = _blocks_scene()
    merged = merge_levels(gaussians, superpoints, _views(truth), MergeConfig()).levels
    assert merged.counts == (16, 8, 4, 2)
    for k in (1, 2, 3):
        np.testing.assert_array_equal(merged.labels[:, k], truth[:, k - 1])
        parent = merged.parents[k - 1]
        np.testing.assert_array_equal(merged.labels[:, k], parent[merged.labels[:, k - 1]])
    instance = merge_levels(
        gaussians, superpoints, _views(truth), MergeConfig(mode="instance")
    ).levels
    for k in (1, 2, 3):
        np.testing.assert_array_equal(instance.labels[:, k], truth[:, 2])
    independent = merge_levels(
        gaussians, superpoints, _views(truth), MergeConfig(mode="independent")
    ).levels
    assert independent.parents is None and not independent.nested
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
    ours = merge_levels(gaussians, superpoints, views, MergeConfig()).levels
    assert ours.counts == (16, 8, 4, 2)
    # the reference counts them: across objects A = 12 / 16 = 0.75 ≥ 0.7, one object remains
    reference = merge_levels(gaussians, superpoints, views, MergeConfig().as_reference()).levels
    assert reference.counts[3] == 1


def test_faint_labels_weigh_less():
    # four views see the blocks well (max w 0.9) with clean labels; eight see them faintly
    # (max w 0.1, above the 0.05 threshold) with every superpoint in a mask of its own. With
    # every label weighing 1, two superpoints of a sub-part agree in 4 of 12 views (A = 1/3)
    # and nothing merges; weighted by (max w)², a faint view counts 1/6561 of a clear one.
    gaussians, superpoints, truth = _blocks_scene()
    split = np.repeat(superpoints[:, None], 3, axis=1) + 1000
    views = [*_views(truth, max_weight=0.9), *_views(split, count=8, max_weight=0.1)]
    ours = merge_levels(gaussians, superpoints, views, MergeConfig()).levels
    for k in (1, 2, 3):
        np.testing.assert_array_equal(ours.labels[:, k], truth[:, k - 1])
    unweighted = merge_levels(
        gaussians, superpoints, views, MergeConfig(visibility_power=0.0)
    ).levels
    assert unweighted.counts[1] == 16


def test_a_unit_glimpsed_once_does_not_join_another_object():
    # superpoint 8 (object 1's first) is hidden in the four clear views; one more view glimpses
    # it and superpoint 7 (object 0's last) faintly (max w 0.06, just above min_max_weight),
    # both under one mask: affinity 1 on support 0.06⁴ = 1.3e-5
    gaussians, superpoints, truth = _blocks_scene()
    views = _views(truth)
    for view in views:
        view.max_weights[superpoints == 8] = 0.0
    glimpsed = np.flatnonzero((superpoints == 7) | (superpoints == 8))
    views.append(
        ViewLift(
            glimpsed.astype(np.int32),
            np.full((glimpsed.size, 4), 555, np.int16),
            np.full(glimpsed.size, 2.0, np.float32),
            np.full(glimpsed.size, 0.06, np.float32),
        )
    )
    ours = merge_levels(gaussians, superpoints, views, MergeConfig()).levels
    others = superpoints != 8
    for k in (1, 2, 3):  # 8 stays a region of its own; the others are the truth's regions
        assert set(ours.labels[superpoints == 8, k]).isdisjoint(ours.labels[others, k])
        pairs = np.unique(np.stack([ours.labels[others, k], truth[others, k - 1]], 1), axis=0)
        assert len(pairs) == len(np.unique(pairs[:, 0])) == len(np.unique(pairs[:, 1]))
    unsupported = merge_levels(gaussians, superpoints, views, MergeConfig(min_support=0.0))
    joined = unsupported.levels.labels
    assert joined[superpoints == 8, 1][0] == joined[superpoints == 7, 1][0]  # across objects


def test_rounds_merge_regions_whose_pooled_evidence_agrees():
    # 16 superpoints in a line. Three views put all of them in one mask; a fourth sees only
    # superpoints 0 and 1, in different masks. A(0, 1) = 3 / 4 < 0.9, so 0 cannot join 1 and
    # one round leaves {0} and {1 … 15}. In the second round {1 … 15} is the unit: the fourth
    # view sees 1/15 of it, A = 3 / (3 + 1/15) = 0.98, and the two regions merge.
    gaussians, superpoints, _ = _blocks_scene()
    n = len(superpoints)
    one = np.zeros((n, 3), dtype=np.int64)
    views = _views(one, count=3)
    seen = np.flatnonzero(superpoints < 2).astype(np.int32)
    labels = np.repeat((superpoints[seen] + 7)[:, None], 4, axis=1).astype(np.int16)
    views.append(
        ViewLift(seen, labels, np.full(seen.size, 2.0, np.float32), np.full(seen.size, 0.5))
    )
    ours = merge_levels(gaussians, superpoints, views, MergeConfig()).levels
    assert ours.counts[1] == 1
    single = merge_levels(gaussians, superpoints, views, MergeConfig(rounds=1)).levels
    assert single.counts[1] == 2
    np.testing.assert_array_equal(single.labels[:, 1], (superpoints > 0).astype(np.int32))


def test_a_confused_part_does_not_join_two_objects():
    # the second part of object 0 (superpoints 4–7) lies against object 1; the object masks
    # cover its far half (6, 7) with object 1's mask in every view. Its histogram is then
    # (1/2, 1/2): A = 0.71 ≥ 0.7 with both neighbouring parts, and growing joins everything
    # through it. The check cuts the object between its sub-parts where the object masks
    # disagree: 0–5 ((1, 0)) against 6–15 ((0, 1)), A = 0, and the part 4–7 with it; the
    # object masks, not the part masks, decide what an object is.
    gaussians, superpoints, truth = _blocks_scene()
    views = _views(truth)
    for view in views:
        view.labels[(superpoints == 6) | (superpoints == 7), 3] = 201  # object 1's mask
    grown = merge_levels(gaussians, superpoints, views, MergeConfig(split_incoherent=False))
    assert grown.levels.counts == (16, 8, 4, 1)
    ours = merge_levels(gaussians, superpoints, views, MergeConfig()).levels
    assert ours.counts == (16, 8, 5, 2)
    np.testing.assert_array_equal(ours.labels[:, 3], (superpoints >= 6).astype(np.int32))
    expected_parts = np.select([superpoints < 4, superpoints < 6, superpoints < 8], [0, 1, 2], 3)
    expected_parts[superpoints >= 12] = 4
    np.testing.assert_array_equal(ours.labels[:, 2], expected_parts)
    np.testing.assert_array_equal(ours.labels[:, 1], truth[:, 0])


def test_a_part_that_took_another_objects_part_is_cut_with_the_object():
    # the part masks put object 1's first part (superpoints 8–11) into object 0's last part in
    # every view, so level 2 makes one part of superpoints 4–11. Its object histogram is
    # (1/2, 1/2): A = 0.71 ≥ 0.7 with both other parts, and growing objects on parts joins
    # everything. On parts, no cut of the object finds the truth (4–11 is one unit); on
    # sub-parts the weakest link is between 7 and 8 (object masks 200 | 201, A = 0): the
    # object is cut there, the part 4–11 with it, and every level is the truth again.
    gaussians, superpoints, truth = _blocks_scene()
    views = _views(truth)
    for view in views:
        view.labels[(superpoints >= 8) & (superpoints < 12), 2] = 101  # part 1's mask
    unchecked = merge_levels(gaussians, superpoints, views, MergeConfig(split_incoherent=False))
    assert unchecked.levels.counts == (16, 8, 3, 1)
    ours = merge_levels(gaussians, superpoints, views, MergeConfig()).levels
    assert ours.counts == (16, 8, 4, 2)
    for k in (1, 2, 3):
        np.testing.assert_array_equal(ours.labels[:, k], truth[:, k - 1])


def test_a_split_needs_evidence_that_the_sides_disagree():
    # two touching units of 10 Gaussians in one region. Views seen by both: one puts them in one
    # mask, one in two masks, so A = 1/2: cut at threshold 0.9, kept whole at 0.4. Views that
    # each see one unit only give no support: the region stays whole at any threshold.
    units = np.repeat(np.arange(2), 10)
    neighbors = np.stack([np.arange(20), np.clip(np.arange(20) + 1, 0, 19)], axis=1)
    graph = unit_graph(units, neighbors, 2)
    everyone = _tensor(np.arange(20))
    agree = (everyone, _tensor(np.zeros(20, dtype=np.int64)))
    disagree = (everyone, _tensor(units.astype(np.int64)))
    evidence = mask_evidence(_tensor(units), 2, [agree, disagree])
    together = np.zeros(2, dtype=np.int64)
    np.testing.assert_array_equal(split_incoherent(together, graph, evidence, 0.4), [0, 0])
    np.testing.assert_array_equal(split_incoherent(together, graph, evidence, 0.9), [0, 1])
    apart = [
        (_tensor(np.flatnonzero(units == u)), _tensor(np.full(10, u, np.int64))) for u in (0, 1)
    ]
    unseen_together = mask_evidence(_tensor(units), 2, apart)
    np.testing.assert_array_equal(split_incoherent(together, graph, unseen_together, 0.9), [0, 0])
    # with more support required than the two views give (1 + 1), the cut is not kept
    np.testing.assert_array_equal(split_incoherent(together, graph, evidence, 0.9, 2.5), [0, 0])


def test_weakest_cut_by_hand():
    # a path 0 – 1 – 2 – 3 with a weak middle link: the cut separates {0, 1} from {2, 3}
    weights = np.zeros((4, 4))
    for a, b, w in ((0, 1, 1.0), (1, 2, 0.1), (2, 3, 1.0)):
        weights[a, b] = weights[b, a] = w
    side = _weakest_cut(weights)
    assert side[0] == side[1] != side[2] == side[3]
    # two triangles joined by one edge: the cut is that edge
    weights = np.zeros((6, 6))
    for a, b in itertools.chain(
        itertools.combinations((0, 1, 2), 2), itertools.combinations((3, 4, 5), 2), [(2, 3)]
    ):
        weights[a, b] = weights[b, a] = 1.0
    side = _weakest_cut(weights)
    assert len(set(side[:3])) == len(set(side[3:])) == 1 and side[0] != side[3]


def test_small_regions_join_their_most_similar_neighbour():
    gaussians, superpoints, truth = _blocks_scene()
    truth = truth.copy()
    truth[superpoints == 15, :] = [99, 99, 99]  # the last superpoint is its own object
    merged = merge_levels(gaussians, superpoints, _views(truth), MergeConfig()).levels
    assert merged.counts[3] == 3  # 50 Gaussians ≥ 20: kept
    absorbing = MergeConfig(min_region_gaussians=60)
    merged = merge_levels(gaussians, superpoints, _views(truth), absorbing).levels
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
    for bad in ({"rounds": 0}, {"two_hop_weight": -1.0}, {"visibility_power": -1.0}):
        with pytest.raises(InputError, match="rounds"):
            MergeConfig(**bad)
    for bad_support in (-1e-4, float("nan")):
        with pytest.raises(InputError, match="min_support must be ≥ 0"):
            MergeConfig(min_support=bad_support)


def test_reference_config_keeps_the_authors_merging():
    reference = MergeConfig.lerf().as_reference()
    assert (reference.min_max_weight, reference.visibility_power) == (0.0, 0.0)
    assert (reference.one_hop_weight, reference.two_hop_weight, reference.rounds) == (2.0, 1.0, 1)
    assert reference.min_support == 0.0 and not reference.split_incoherent
    assert reference.thresholds == (0.9, 0.7, 0.7)
