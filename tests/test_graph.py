"""The KNN graph and the SAM-guided edge reweighting, against brute force and hand cases."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
import torch

from thgs import Gaussians
from thgs.errors import InputError
from thgs.graph import (
    GraphConfig,
    KnnGraph,
    ReweightConfig,
    edge_counts,
    knn_graph,
    reweight,
    search_points,
)
from thgs.graph import knn as knn_module
from thgs.lift import ViewLift
from thgs.scene.gaussians import SH_C0


def gaussians_at(means, rgb) -> Gaussians:
    """2DGS surfels at ``means`` [N, 3] with DC colour ``rgb`` [N, 3] in [0, 1]."""
    means = np.asarray(means, dtype=np.float64).reshape(-1, 3)
    rgb = np.asarray(rgb, dtype=np.float64).reshape(-1, 3)
    n = means.shape[0]
    return Gaussians(
        means=torch.tensor(means, dtype=torch.float32),
        quats=torch.tensor(np.tile([1.0, 0.0, 0.0, 0.0], (n, 1)), dtype=torch.float32),
        scales=torch.full((n, 2), -4.0),
        opacities=torch.zeros(n),
        sh=torch.tensor((rgb - 0.5) / SH_C0, dtype=torch.float32)[:, None, :],
    ).check()


def brute_force_knn(points: np.ndarray, k: int, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """O(N²) reference: per row the k nearest other points closer than radius, nearest first."""
    points = points.astype(np.float64)
    squared = ((points[:, None, :] - points[None, :, :]) ** 2).sum(-1)
    np.fill_diagonal(squared, np.inf)
    order = np.argsort(squared, axis=1, kind="stable")[:, :k]
    nearest = np.take_along_axis(squared, order, axis=1)
    inside = nearest < radius**2
    return np.where(inside, order, -1), np.where(inside, nearest, np.inf)


# --- KNN graph ------------------------------------------------------------------------------


@pytest.mark.parametrize(("k", "radius"), [(10, 2.0), (10, 0.35), (4, np.inf)])
def test_knn_matches_brute_force_on_random_points(k, radius):
    rng = np.random.default_rng(0)
    gaussians = gaussians_at(rng.uniform(0, 2, (400, 3)), rng.uniform(0, 1, (400, 3)))
    config = GraphConfig(k=k, radius=radius)
    graph = knn_graph(gaussians, config)
    expected_neighbors, expected_squared = brute_force_knn(
        search_points(gaussians, config), k, radius
    )
    assert graph.neighbors.dtype == np.int32 and graph.distances.dtype == np.float32
    np.testing.assert_array_equal(graph.neighbors, expected_neighbors)
    np.testing.assert_allclose(graph.distances, expected_squared, rtol=1e-5)
    if radius == 0.35:  # the radius drops neighbours of some Gaussians, not of all
        missing = (graph.neighbors < 0).sum(axis=1)
        assert 0 < (missing > 0).mean() < 1
    graph.check(400)


def test_knn_hand_case_with_colour_and_radius():
    # on a line at x = 0, 1, 3, 7; Gaussian 1 is 1 unit redder: 0.3² added to its squared distances
    rgb = [[0.2, 0.5, 0.5], [1.0, 0.5, 0.5], [0.2, 0.5, 0.5], [0.2, 0.5, 0.5]]
    means = [[0, 0, 0], [1, 0, 0], [3, 0, 0], [7, 0, 0]]
    colour = (0.3 * 0.8) ** 2
    graph = knn_graph(gaussians_at(means, rgb), GraphConfig(k=2, radius=2.5))
    np.testing.assert_array_equal(graph.neighbors, [[1, -1], [0, 2], [1, -1], [-1, -1]])
    expected = [[1 + colour, np.inf], [1 + colour, 4 + colour], [4 + colour, np.inf], [np.inf] * 2]
    np.testing.assert_allclose(graph.distances, expected, rtol=1e-6)
    # colour weight 0: positions only
    graph = knn_graph(gaussians_at(means, rgb), GraphConfig(k=2, radius=2.5, color_weight=0.0))
    np.testing.assert_allclose(graph.distances[1], [1, 4], rtol=1e-6)


def test_knn_with_fewer_gaussians_than_k_gives_every_other_gaussian():
    means = [[0, 0, 0], [1, 0, 0], [0, 1.5, 0]]
    graph = knn_graph(gaussians_at(means, np.full((3, 3), 0.5)), GraphConfig(k=10))
    assert graph.neighbors.shape == (3, 10)
    np.testing.assert_array_equal(graph.neighbors[:, :2], [[1, 2], [0, 2], [0, 1]])
    np.testing.assert_allclose(graph.distances[:, :2], [[1, 2.25], [1, 3.25], [2.25, 3.25]])
    assert (graph.neighbors[:, 2:] == -1).all() and np.isinf(graph.distances[:, 2:]).all()
    one = gaussians_at([[0, 0, 0]], [[0.5] * 3])
    np.testing.assert_array_equal(knn_graph(one, GraphConfig(k=3)).neighbors, [[-1, -1, -1]])
    empty = knn_graph(one.select(np.arange(0)), GraphConfig(k=3))
    assert empty.neighbors.shape == (0, 3) and empty.distances.shape == (0, 3)


def test_knn_excludes_self_among_coincident_gaussians():
    means = np.zeros((6, 3))
    graph = knn_graph(gaussians_at(means, np.full((6, 3), 0.5)), GraphConfig(k=3))
    assert (graph.neighbors >= 0).all()
    assert not (graph.neighbors == np.arange(6)[:, None]).any()
    assert all(len(set(row)) == 3 for row in graph.neighbors.tolist())
    np.testing.assert_array_equal(graph.distances, 0.0)


def test_scipy_fallback_gives_the_same_graph(monkeypatch):
    rng = np.random.default_rng(3)
    gaussians = gaussians_at(rng.uniform(0, 2, (300, 3)), rng.uniform(0, 1, (300, 3)))
    config = GraphConfig(k=6, radius=0.4)
    expected = knn_graph(gaussians, config)
    monkeypatch.setattr(knn_module, "_PyKDTree", None)
    fallback = knn_graph(gaussians, config)
    np.testing.assert_array_equal(fallback.neighbors, expected.neighbors)
    np.testing.assert_allclose(fallback.distances, expected.distances, rtol=1e-5)


def test_graph_config_and_check_reject_bad_values():
    for bad in ({"k": 0}, {"radius": 0.0}, {"color_weight": -1.0}):
        with pytest.raises(InputError):
            GraphConfig(**bad)
    neighbors = np.array([[1], [1]], dtype=np.int32)  # Gaussian 1 is its own neighbour
    with pytest.raises(InputError, match="own neighbour"):
        KnnGraph(neighbors, np.ones((2, 1), dtype=np.float32)).check(2)
    with pytest.raises(InputError, match=r"\[3, K\]"):
        KnnGraph(neighbors, np.ones((2, 1), dtype=np.float32)).check(3)


# --- edge votes -----------------------------------------------------------------------------

# Four Gaussians, K = 2: 0 → 1, 2; 1 → 0; 2 → 0, 3; 3 → 2 (squared distances below).
HAND_GRAPH = KnnGraph(
    neighbors=np.array([[1, 2], [0, -1], [0, 3], [2, -1]], dtype=np.int32),
    distances=np.array([[1, 4], [1, np.inf], [4, 2], [2, np.inf]], dtype=np.float32),
)


def view(gaussians, level1, depths, *, max_weights=None) -> ViewLift:
    """A lift whose level-1 (s) labels are ``level1``; the other levels hold decoys."""
    n = len(gaussians)
    labels = np.full((n, 4), 9, dtype=np.int16)  # int16 as lifts store them; 9 at other levels
    labels[:, 1] = level1
    weights = np.ones(n) if max_weights is None else max_weights
    return ViewLift(
        np.asarray(gaussians, dtype=np.int32),
        labels,
        np.asarray(depths, dtype=np.float32),
        np.asarray(weights, dtype=np.float32),
    )


# A: 0, 1 share a mask, 2 (depth 7: f = 1/3) another. B: 0 (depth 6: f = 1/2), 2, 3 one mask.
# C: 0 unlabelled, 1, 2 one mask, 3 another.
VIEW_A = view([0, 1, 2], [5, 5, 7], [1.0, 1.0, 7.0])
VIEW_B = view([0, 2, 3], [2, 2, 2], [6.0, 2.0, 2.0])
VIEW_C = view([0, 1, 2, 3], [-1, 3, 3, 4], [1.0, 1.0, 1.0, 1.0])


def test_edge_counts_hand_case():
    pos, neg = edge_counts(HAND_GRAPH, [VIEW_A, VIEW_B, VIEW_C], ReweightConfig())
    # A: pos 0→1, 1→0; neg 0→2, 2→0 (×1/3). B: pos 0→2 (×1/2), 2→0, 2→3, 3→2. C: neg 2→3, 3→2.
    np.testing.assert_allclose(pos, [[1, 0.5], [1, 0], [1, 1], [1, 0]], rtol=1e-6)
    np.testing.assert_allclose(neg, [[0, 1], [0, 0], [1 / 3, 1], [1, 0]], rtol=1e-6)
    assert pos.dtype == neg.dtype == np.float32


def test_edge_counts_without_depth_decay_count_every_vote_as_one():
    pos, neg = edge_counts(HAND_GRAPH, [VIEW_A, VIEW_B, VIEW_C], ReweightConfig(depth_decay=False))
    np.testing.assert_array_equal(pos, [[1, 1], [1, 0], [1, 1], [1, 0]])
    np.testing.assert_array_equal(neg, [[0, 1], [0, 0], [1, 1], [1, 0]])


def test_edge_counts_depth_start_and_cap():
    # depth_start 6.5: only Gaussian 2 in A (depth 7) decays, to 1 / 1.5
    pos, neg = edge_counts(HAND_GRAPH, [VIEW_A, VIEW_B], ReweightConfig(depth_start=6.5))
    assert pos[0, 1] == 1.0
    assert neg[2, 0] == pytest.approx(1 / 1.5)
    pos, neg = edge_counts(HAND_GRAPH, [VIEW_A] * 3, ReweightConfig(cap=2.5))
    np.testing.assert_allclose(pos, [[2.5, 0], [2.5, 0], [0, 0], [0, 0]])
    np.testing.assert_allclose(neg, [[0, 2.5], [0, 0], [1, 0], [0, 0]], rtol=1e-6)


def test_edge_counts_level_and_visibility_threshold():
    # level 0 holds label 9 for every Gaussian: every edge between two seen Gaussians agrees
    pos, neg = edge_counts(HAND_GRAPH, [VIEW_A], ReweightConfig(level=0, depth_decay=False))
    np.testing.assert_array_equal(pos, [[1, 1], [1, 0], [1, 0], [0, 0]])
    assert not neg.any()
    # Gaussian 1 barely visible in A: it neither votes nor is voted on
    faint = view([0, 1, 2], [5, 5, 7], [1.0, 1.0, 7.0], max_weights=[1.0, 0.01, 1.0])
    pos, neg = edge_counts(HAND_GRAPH, [faint], ReweightConfig(min_max_weight=0.05))
    assert not pos.any()
    np.testing.assert_allclose(neg, [[0, 1], [0, 0], [1 / 3, 0], [0, 0]], rtol=1e-6)


@pytest.mark.parametrize("seed", range(3))
def test_compiled_edge_counts_equal_the_tensor_path(seed):
    """The CPU's compiled loop and the gathers every other device runs: the same float32 sums."""
    module = importlib.import_module("thgs.graph.reweight")  # the package exports reweight()

    rng = np.random.default_rng(seed)
    n, k = 300, 6
    neighbors = rng.integers(-1, n, size=(n, k)).astype(np.int32)
    neighbors[neighbors == np.arange(n)[:, None]] = -1
    graph = KnnGraph(neighbors, np.where(neighbors >= 0, 1.0, np.inf).astype(np.float32))
    views = []
    for _ in range(5):
        seen = np.sort(rng.choice(n, 200, replace=False))
        views.append(
            view(
                seen,
                rng.integers(-1, 4, seen.size),
                rng.uniform(1, 9, seen.size),
                max_weights=rng.uniform(0, 1, seen.size),
            )
        )
    config = ReweightConfig(min_max_weight=0.2, cap=3.0)
    pos, neg = edge_counts(graph, views, config)
    targets = torch.from_numpy(neighbors).long()
    targets = torch.where(targets >= 0, targets, n)
    expected = torch.zeros(n, k), torch.zeros(n, k)
    dense = torch.full((n + 1,), -1, dtype=torch.int32)
    for lifted in views:
        module._count_view_torch(targets, lifted, config, dense, *expected)
    np.testing.assert_array_equal(pos, expected[0].clamp(max=3.0).numpy())
    np.testing.assert_array_equal(neg, expected[1].clamp(max=3.0).numpy())
    assert pos.any() and neg.any()


def test_edge_counts_reject_views_of_another_scene():
    with pytest.raises(InputError, match="view 1"):
        edge_counts(HAND_GRAPH, [VIEW_A, view([0, 7], [1, 1], [1.0, 1.0])])


# --- reweighting ----------------------------------------------------------------------------

POS = np.array([[1, 0.5], [1, 0], [1, 1], [1, 0]], dtype=np.float32)
NEG = np.array([[0, 1], [0, 0], [1 / 3, 1], [1, 0]], dtype=np.float32)


def test_reweight_absolute_is_the_reference_formula():
    out = reweight(HAND_GRAPH, POS, NEG, ReweightConfig.reference())
    # d + 0.1·neg − 0.02·pos
    expected = [
        [1 - 0.02, 4 + 0.1 - 0.01],
        [1 - 0.02, np.inf],
        [4 + 0.1 / 3 - 0.02, 2 + 0.1 - 0.02],
        [2 + 0.1 - 0.02, np.inf],
    ]
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    assert out.dtype == np.float32


def test_reweight_relative_scales_the_offsets_by_the_mean_distance():
    out = reweight(HAND_GRAPH, POS, NEG, ReweightConfig(mode="relative"))
    mean = (1 + 4 + 1 + 4 + 2 + 2) / 6
    # defaults: d + mean · (10·neg − 2·pos), clamped at 0
    expected = [
        [0, 4 + 9 * mean],
        [0, np.inf],
        [4 + (10 / 3 - 2) * mean, 2 + 8 * mean],
        [2 + 8 * mean, np.inf],
    ]
    np.testing.assert_allclose(out, expected, rtol=1e-6)
    assert ReweightConfig().mode == "relative"


def test_relative_mode_is_scale_free_and_absolute_is_not():
    scaled = KnnGraph(HAND_GRAPH.neighbors, HAND_GRAPH.distances * 1000)
    relative, absolute = ReweightConfig(), ReweightConfig.reference()
    np.testing.assert_allclose(
        reweight(scaled, POS, NEG, relative),
        1000 * reweight(HAND_GRAPH, POS, NEG, relative),
        rtol=1e-6,
    )
    ratio = (
        reweight(scaled, POS, NEG, absolute)[0, 1] / reweight(HAND_GRAPH, POS, NEG, absolute)[0, 1]
    )
    assert ratio == pytest.approx((4000 + 0.09) / 4.09)


def test_reweight_clamps_at_zero_and_none_mode_keeps_distances():
    many = np.full((4, 2), 25.0, dtype=np.float32)
    out = reweight(HAND_GRAPH, many, np.zeros((4, 2), np.float32), ReweightConfig.reference())
    np.testing.assert_allclose(out, [[0.5, 3.5], [0.5, np.inf], [3.5, 1.5], [1.5, np.inf]])
    close = KnnGraph(HAND_GRAPH.neighbors, HAND_GRAPH.distances / 10)  # 0.1 − 0.5 < 0
    out = reweight(close, many, np.zeros((4, 2), np.float32), ReweightConfig.reference())
    assert out[0, 0] == 0.0 and out[1, 0] == 0.0
    out = reweight(HAND_GRAPH, POS, NEG, ReweightConfig(mode="none"))
    np.testing.assert_array_equal(out, HAND_GRAPH.distances)


def test_reweight_rejects_mismatched_counts_and_bad_config():
    with pytest.raises(InputError, match="must match"):
        reweight(HAND_GRAPH, POS[:3], NEG, ReweightConfig())
    for bad in ({"mode": "squared"}, {"level": 4}, {"cap": -1.0}, {"min_max_weight": 2.0}):
        with pytest.raises(InputError):
            ReweightConfig(**bad)
