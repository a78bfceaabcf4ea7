"""Level-0 superpoints by ℓ0 cut pursuit on the KNN graph (design §4.5).

The partition solves, over one 9-D value ``x_v`` per Gaussian,

    min_x  Σ_v ‖x_v − y_v‖²  +  R · Σ_(u,v) w_uv · [x_u ≠ x_v]

with ``y_v = [√W · (μ_v − mean μ), rgb_v, n_v]`` (centre, DC colour, surface normal) and edge
weights ``w_uv = 1 / (1 + d'_uv / mean d')`` from the (reweighted) squared KNN distances, using
pycut-pursuit's ``cp_d0_dist``. The connected pieces of constant ``x`` are the superpoints.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from thgs.errors import InputError, ThgsError
from thgs.graph.knn import KnnGraph, nearest_neighbors
from thgs.scene.gaussians import Gaussians

__all__ = ["PartitionConfig", "partition"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class PartitionConfig:
    """Cut-pursuit parameters. Defaults are the reference's LERF numbers with our
    ``weight_scale`` and ``split_alternatives``.

    Attributes:
        regularization: R, the price of cutting an edge of weight 1, in units of the squared
            feature distance (0.1; 3DOVS 0.3). Larger R gives fewer, larger superpoints.
        spatial_weight: W, the weight of the centred position (scene units) against colour
            ([0, 1]) and normal (unit vector) in the squared feature distance (0.1; 3DOVS 0.2).
            Positions enter the features scaled by √W, so W is in 1 / scene units².
        min_comp_weight: smallest superpoint, in Gaussians (10); smaller components are merged
            into an adjacent one. Only adjacent components can merge, so a piece of the graph
            that is disconnected from the rest and smaller than this stays as it is.
        cp_dif_tol: cut pursuit stops when the relative change of the iterate falls below this
            (1e-2).
        cp_it_max: at most this many cut-pursuit iterations (cut, reduce, merge) (15).
        split_damp_ratio: edge weights in the split step start at this fraction of their value
            and grow linearly to it (0.7; 1 = no damping).
        flip_normals_up: flip each normal to world z ≥ 0 before use, as the reference does on
            LERF. Off by default: whether z is "up" depends on the scene's frame.
        max_num_threads: OpenMP threads of the solver; 0 = all. Results are deterministic for a
            fixed thread count (the parallel split may cut differently with another count).
        weight_scale: the d̄ of the edge weights ``w = 1 / (1 + d' / d̄)``: ``"graph"`` (ours,
            default) the mean of the graph's own squared distances (before any votes), so a vote
            changes only the weight of the edge it lands on; ``"reweighted"`` (the reference) the
            mean of the distances being partitioned, so strong negative votes inflate d̄ and
            raise the weight of every other edge, coarsening the whole partition (on
            ``synth-small`` at R = 1: sub-part purity 0.895 instead of 0.958, docs/partition.md).
            Identical when the distances are not reweighted.
        split_alternatives: K, the number of candidate values each component's split step
            tries (the solver's ``K``; ours 6, the reference the solver's default 2). With 2 the
            split of a large component follows its widest spread, which on a table top is
            position: a flat object of another colour lying on it stays in the table's
            superpoint (synth-small seed 0: 27 % of a stack of books). More alternatives cost
            split time and give purer superpoints; the solver's objective is not lower for it
            (docs/partition.md).
        polish: after cut pursuit, move single Gaussians to a neighbouring superpoint while that
            lowers cut pursuit's own energy (ours True; the reference keeps the solver's
            output). The solver merges a component smaller than ``min_comp_weight`` into an
            adjacent one, which can be the wrong one: five Gaussians of a table's underside,
            joined to a chair's superpoint through floaters (docs/partition.md).
    """

    regularization: float = 0.1
    spatial_weight: float = 0.1
    min_comp_weight: float = 10.0
    cp_dif_tol: float = 1e-2
    cp_it_max: int = 15
    split_damp_ratio: float = 0.7
    flip_normals_up: bool = False
    max_num_threads: int = 0
    weight_scale: Literal["graph", "reweighted"] = "graph"
    split_alternatives: int = 6
    polish: bool = True

    def __post_init__(self) -> None:
        if not (self.regularization >= 0 and self.spatial_weight >= 0):
            raise InputError("PartitionConfig", "regularization and spatial_weight must be ≥ 0")
        if not (self.min_comp_weight >= 0 and self.cp_dif_tol >= 0):
            raise InputError("PartitionConfig", "min_comp_weight and cp_dif_tol must be ≥ 0")
        if self.cp_it_max < 1 or self.max_num_threads < 0:
            raise InputError("PartitionConfig", "need cp_it_max ≥ 1 and max_num_threads ≥ 0")
        if self.split_alternatives < 2:
            raise InputError(
                "PartitionConfig",
                f"split_alternatives must be at least 2, got {self.split_alternatives}",
            )
        if not 0 < self.split_damp_ratio <= 1:
            raise InputError(
                "PartitionConfig",
                f"split_damp_ratio must be in (0, 1], got {self.split_damp_ratio}",
            )
        if self.weight_scale not in ("graph", "reweighted"):
            raise InputError(
                "PartitionConfig",
                f"weight_scale must be 'graph' or 'reweighted', got {self.weight_scale!r}",
            )

    @classmethod
    def lerf(cls) -> PartitionConfig:
        """The reference's LERF-OVS setting: R = 0.1, W = 0.1, normals flipped to z ≥ 0."""
        return cls(regularization=0.1, spatial_weight=0.1, flip_normals_up=True)

    @classmethod
    def three_dovs(cls) -> PartitionConfig:
        """The reference's 3DOVS setting: R = 0.3, W = 0.2."""
        return cls(regularization=0.3, spatial_weight=0.2)


@numba.njit(cache=True)
def _slot(neighbors, i, j):
    """The column of j in row i of ``neighbors``, −1 if absent."""
    for a in range(neighbors.shape[1]):
        if neighbors[i, a] == j:
            return a
    return -1


@numba.njit(cache=True)
def _undirected(neighbors, weights):
    """Forward-star undirected graph of directed edges ``i → neighbors[i, a]`` (−1 = none).

    Each edge is stored once, from its smaller end; its weight is the mean of the two directions'
    weights where both exist. Returns ``first_edge`` [N + 1], ``targets`` [E] int32, weights [E].
    """
    n, k = neighbors.shape
    first = np.zeros(n + 1, dtype=np.int64)
    for i in range(n):
        for a in range(k):
            j = neighbors[i, a]
            if j > i:
                first[i + 1] += 1
            elif j >= 0 and _slot(neighbors, j, i) < 0:
                first[j + 1] += 1
    first = np.cumsum(first)
    fill = first[:-1].copy()
    targets = np.empty(first[n], dtype=np.int32)
    merged = np.empty(first[n], dtype=np.float64)
    for i in range(n):
        for a in range(k):
            j = neighbors[i, a]
            if j < 0:
                continue
            back = _slot(neighbors, j, i)
            if j > i:
                targets[fill[i]] = j
                merged[fill[i]] = (
                    weights[i, a] if back < 0 else 0.5 * (weights[i, a] + weights[j, back])
                )
                fill[i] += 1
            elif back < 0:
                targets[fill[j]] = i
                merged[fill[j]] = weights[i, a]
                fill[j] += 1
    return first, targets, merged


def _edge_weights(
    graph: KnnGraph, distances: np.ndarray, means: np.ndarray, scale_from: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The undirected weighted graph in forward-star form: ``(first_edge, targets, weights)``.

    Directed KNN edges get ``w = 1 / (1 + d' / d̄)`` with ``d'`` = ``distances`` and ``d̄`` the
    mean of ``scale_from`` [N, K] over present edges (w = 1 when that mean is 0). The two
    directions of an edge are averaged, an edge present in one direction keeps its weight, self
    loops are dropped. A Gaussian without any edge is joined to its nearest
    other Gaussian by 3-D distance (KD-tree over the centres ``means`` [N, 3]), weighted by the
    same formula applied to the squared 3-D distance: the geometric part of their 6-D distance,
    since the colour weight of the search space is not known here. Each edge is stored once, from
    its smaller end: ``first_edge`` [N + 1] int64, ``targets`` [E] int32, ``weights`` [E] float64
    in (0, 1].
    """
    n = len(graph)
    valid = graph.valid() & (graph.neighbors != np.arange(n)[:, None])
    neighbors = np.where(valid, graph.neighbors, -1).astype(np.int32)
    squared = np.where(valid, distances, np.inf).astype(np.float64)
    scale = scale_from[valid].astype(np.float64).mean() if valid.any() else 0.0
    degree = valid.sum(axis=1) + np.bincount(neighbors[valid], minlength=n)
    isolated = np.flatnonzero(degree == 0)
    if isolated.size and n > 1:
        log.info("joining %d isolated Gaussians to their nearest neighbour", isolated.size)
        near_squared, near = nearest_neighbors(means, 2, np.inf, queries=means[isolated])
        first_is_self = near[:, 0] == isolated
        neighbors[isolated, 0] = np.where(first_is_self, near[:, 1], near[:, 0])
        squared[isolated, 0] = np.where(first_is_self, near_squared[:, 1], near_squared[:, 0])
    weights = 1.0 / (1.0 + squared / scale) if scale > 0 else np.where(neighbors >= 0, 1.0, 0.0)
    return _undirected(neighbors, weights)


def _features(gaussians: Gaussians, config: PartitionConfig) -> np.ndarray:
    """[N, 9] float32 ``[√W · (μ − mean μ), rgb, normal]`` per Gaussian."""
    means = gaussians.means.detach().cpu().double().numpy()
    colors = gaussians.dc_colors().detach().cpu().double().numpy()
    normals = gaussians.surface_normals().detach().cpu().double().numpy()
    if config.flip_normals_up:
        normals = np.where(normals[:, 2:3] < 0, -normals, normals)
    position = np.sqrt(config.spatial_weight) * (means - means.mean(axis=0))
    return np.concatenate([position, colors, normals], axis=1).astype(np.float32)


def _cut_pursuit(
    features: np.ndarray,
    sources: np.ndarray,
    targets: np.ndarray,
    weights: np.ndarray,
    config: PartitionConfig,
) -> np.ndarray:
    """[m] component ids from ``cp_d0_dist`` on one connected graph of m vertices.

    ``features`` is [m, 9]; edges ``sources[e] < targets[e]`` are local indices sorted by source.
    """
    try:
        from pycut_pursuit.cp_d0_dist import cp_d0_dist
    except ImportError as error:
        raise ThgsError(
            f"the partition needs pycut-pursuit built against the installed NumPy {np.__version__}"
            f" ({error}); its wheels need NumPy 1 up to Python 3.12 and NumPy 2 from 3.13, and "
            "`pip install thgs` installs that pair (README, Installing)"
        ) from error
    m = features.shape[0]
    first_edge = np.zeros(m + 1, dtype=np.int32)
    np.cumsum(np.bincount(sources, minlength=m), out=first_edge[1:])
    components, _ = cp_d0_dist(
        features.shape[1],
        features.T,  # the transpose of a C-contiguous [m, 9] array is F-contiguous, as required
        first_edge,
        targets.astype(np.int32),
        edge_weights=(config.regularization * weights).astype(np.float32),
        min_comp_weight=config.min_comp_weight,
        cp_dif_tol=config.cp_dif_tol,
        cp_it_max=config.cp_it_max,
        split_damp_ratio=config.split_damp_ratio,
        K=config.split_alternatives,
        verbose=False,
        max_num_threads=config.max_num_threads,
    )
    return components.astype(np.int64)


def _polished(
    labels: np.ndarray,
    features: np.ndarray,
    sources: np.ndarray,
    targets: np.ndarray,
    weights: np.ndarray,
    config: PartitionConfig,
) -> np.ndarray:
    """[N] component ids after passes of single-vertex moves on cut pursuit's energy
    ``Σ_i ‖x_i − c(i)‖² + R · Σ_(i,j) w_ij [i, j apart]`` (c: each component's mean feature).

    In each pass every vertex takes, among its own component and its neighbours', the one of
    lowest energy for it alone (:func:`_best_components`), the means held fixed; a pass is kept
    only if the whole energy, recomputed, went down. At most ``config.cp_it_max`` passes. The
    components are then made connected again (:func:`_connected`), keeping
    ``config.min_comp_weight``.
    """
    _, labels = np.unique(labels, return_inverse=True)  # 0 … C − 1 from here on
    count = int(labels.max()) + 1
    n = len(labels)
    cost = config.regularization * weights.astype(np.float64)
    first_edge, neighbour, edge_cost = _both_directions(n, sources, targets, cost)
    features = features.astype(np.float64)
    means = _means(labels, features, count)
    energy = _energy(labels, features, means, sources, targets, cost)
    for _ in range(config.cp_it_max):
        moved = _best_components(first_edge, neighbour, edge_cost, labels, features, means)
        if (moved == labels).all():
            break
        moved_means = _means(moved, features, count)
        moved_energy = _energy(moved, features, moved_means, sources, targets, cost)
        if moved_energy >= energy:
            break
        labels, means, energy = moved, moved_means, moved_energy
    return _connected(labels, sources, targets, cost, config.min_comp_weight)


@numba.njit(cache=True)
def _both_directions(n, sources, targets, cost):  # pragma: no cover
    """Forward star ``(first_edge [n + 1], neighbour [2E], cost [2E])`` of the undirected edges
    ``sources[e] – targets[e]``, each stored from both ends."""
    first_edge = np.zeros(n + 1, dtype=np.int64)
    for e in range(sources.size):
        first_edge[sources[e] + 1] += 1
        first_edge[targets[e] + 1] += 1
    for v in range(n):
        first_edge[v + 1] += first_edge[v]
    fill = first_edge[:-1].copy()
    neighbour = np.empty(2 * sources.size, dtype=np.int64)
    both_cost = np.empty(2 * sources.size, dtype=np.float64)
    for e in range(sources.size):
        a, b = sources[e], targets[e]
        neighbour[fill[a]] = b
        both_cost[fill[a]] = cost[e]
        fill[a] += 1
        neighbour[fill[b]] = a
        both_cost[fill[b]] = cost[e]
        fill[b] += 1
    return first_edge, neighbour, both_cost


@numba.njit(cache=True)
def _best_components(first_edge, neighbour, cost, dense, features, means):  # pragma: no cover
    """[N] for each vertex, among its own component and its neighbours' (``dense`` ids), the one
    of lowest ``‖x − mean‖² + weight of its edges into other components``; its own on a tie,
    else the lowest id. Edges in forward-star form over both directions."""
    n, dim = features.shape
    best = dense.copy()
    slots = np.max(first_edge[1:] - first_edge[:-1]) + 1 if n else 1  # own + one per edge
    options = np.empty(slots, dtype=np.int64)
    joined = np.empty(slots, dtype=np.float64)
    for v in range(n):
        own = dense[v]
        count = 1
        options[0] = own
        joined[0] = 0.0
        total = 0.0
        apart = False
        for e in range(first_edge[v], first_edge[v + 1]):
            other = dense[neighbour[e]]
            total += cost[e]
            slot = -1
            for q in range(count):
                if options[q] == other:
                    slot = q
                    break
            if slot < 0:
                apart = True
                slot = count
                options[count] = other
                joined[count] = 0.0
                count += 1
            joined[slot] += cost[e]
        if not apart:
            continue
        chosen, lowest = own, np.inf
        for q in range(count):
            distance = 0.0
            for d in range(dim):
                step = features[v, d] - means[options[q], d]
                distance += step * step
            energy = distance + total - joined[q]
            if energy < lowest or (
                energy == lowest and (options[q] == own or (chosen != own and options[q] < chosen))
            ):
                chosen, lowest = options[q], energy
        best[v] = chosen
    return best


def _connected(
    labels: np.ndarray, sources: np.ndarray, targets: np.ndarray, cost: np.ndarray, min_size: float
) -> np.ndarray:
    """[N] ids of the connected pieces of each component (edges ``sources[e] – targets[e]`` of
    weight ``cost[e]``); a piece smaller than ``min_size`` joins the adjacent piece it shares the
    most edge weight with (repeatedly, so that joined small pieces grow), as the solver merges
    its small components."""
    same = labels[sources] == labels[targets]
    _, piece = np.unique(
        _union_roots(len(labels), sources[same], targets[same]), return_inverse=True
    )
    across = np.flatnonzero(~same)
    start = np.r_[sources[across], targets[across]]
    end = np.r_[targets[across], sources[across]]
    weight = np.r_[cost[across], cost[across]]
    while True:
        count = int(piece.max()) + 1
        sizes = np.bincount(piece, minlength=count)
        small = (piece[start] != piece[end]) & (sizes[piece[start]] < min_size)
        if not small.any():
            return piece.astype(np.int64)
        pairs = piece[start[small]] * count + piece[end[small]]
        keys, inverse = np.unique(pairs, return_inverse=True)
        shared = np.bincount(inverse, weights=weight[small])
        source, target = keys // count, keys % count
        order = np.lexsort((target, -shared, source))  # per small piece: most shared weight
        first = order[np.r_[True, np.diff(source[order]) != 0]]
        _, root = np.unique(_union_roots(count, source[first], target[first]), return_inverse=True)
        piece = root[piece]


@numba.njit(cache=True)
def _union_roots(n, sources, targets):  # pragma: no cover
    """[n] a root vertex per connected piece of the edges ``sources[e] – targets[e]``
    (union–find with path halving)."""
    parent = np.arange(n)
    for e in range(sources.size):
        a, b = sources[e], targets[e]
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        while parent[b] != b:
            parent[b] = parent[parent[b]]
            b = parent[b]
        if a != b:
            parent[max(a, b)] = min(a, b)
    for v in range(n):
        root = v
        while parent[root] != root:
            root = parent[root]
        parent[v] = root
    return parent


@numba.njit(cache=True)
def _means(labels, features, count):  # pragma: no cover
    """[count, D] mean feature of each component (0 for an empty one)."""
    sums = np.zeros((count, features.shape[1]))
    sizes = np.zeros(count)
    for v in range(features.shape[0]):
        sizes[labels[v]] += 1.0
        for d in range(features.shape[1]):
            sums[labels[v], d] += features[v, d]
    for c in range(count):
        if sizes[c] > 0:
            sums[c] /= sizes[c]
    return sums


@numba.njit(cache=True)
def _energy(labels, features, means, sources, targets, cost):  # pragma: no cover
    """Cut pursuit's energy of ``labels`` with components' mean features ``means``, over the
    undirected edges ``sources[e] – targets[e]`` of weight ``cost[e]`` (R included)."""
    total = 0.0
    for v in range(features.shape[0]):
        for d in range(features.shape[1]):
            step = features[v, d] - means[labels[v], d]
            total += step * step
    for e in range(sources.size):
        if labels[sources[e]] != labels[targets[e]]:
            total += cost[e]
    return total


def _relabel(components: np.ndarray) -> np.ndarray:
    """[N] int32 ids 0 … S−1 numbered by each component's smallest Gaussian index."""
    _, first, inverse = np.unique(components, return_index=True, return_inverse=True)
    rank = np.empty(first.size, dtype=np.int32)
    rank[np.argsort(first)] = np.arange(first.size, dtype=np.int32)
    return rank[inverse]


def partition(
    gaussians: Gaussians,
    graph: KnnGraph,
    distances: np.ndarray,
    config: PartitionConfig = PartitionConfig(),
) -> np.ndarray:
    """Level-0 superpoints of N Gaussians.

    The solver is run once per connected component of the graph: ``cp_d0_dist`` only separates
    vertices across edges it cuts, so pieces of a disconnected graph would otherwise share one
    value. A component smaller than ``max(2, 2 · min_comp_weight)`` Gaussians cannot hold two
    superpoints and is one superpoint without a solver call. With ``config.polish`` single
    Gaussians then move to a neighbouring superpoint while that lowers the same energy
    (:func:`_polished`).

    Args:
        gaussians: the N Gaussians; centres (world frame, scene units), DC colours and surface
            normals (``Gaussians.surface_normals()``) make the features.
        graph: their [N, K] KNN graph (:func:`thgs.graph.knn_graph`).
        distances: [N, K] squared edge distances to partition with, aligned with
            ``graph.neighbors``: ``graph.distances`` or the output of :func:`thgs.graph.reweight`
            (finite and ≥ 0 at present edges).
        config: cut-pursuit parameters.

    Returns:
        [N] int32 superpoint ids 0 … S−1, numbered in order of each superpoint's smallest
        Gaussian index. Every superpoint is connected in the graph (plus the joins of isolated
        Gaussians); the same inputs and thread count give the same ids.
    """
    started = time.perf_counter()
    n = len(gaussians)
    graph.check(n, source="partition graph")
    if distances.shape != graph.neighbors.shape:
        raise InputError(
            "partition",
            f"distances {distances.shape} must match the graph's {graph.neighbors.shape}",
        )
    present = distances[graph.valid()]
    if not (np.isfinite(present).all() and (present >= 0).all()):
        raise InputError("partition", "distances of present edges must be finite and ≥ 0")
    if n == 0:
        return np.zeros(0, dtype=np.int32)
    means = gaussians.means.detach().cpu().numpy().astype(np.float32)
    scale_from = graph.distances if config.weight_scale == "graph" else distances
    first_edge, targets, weights = _edge_weights(graph, distances, means, scale_from)
    sources = np.repeat(np.arange(n), np.diff(first_edge))
    adjacency = coo_matrix((np.ones(sources.size, dtype=np.int8), (sources, targets)), (n, n))
    count, piece = connected_components(adjacency, directed=False)
    sizes = np.bincount(piece, minlength=count)
    members = np.argsort(piece, kind="stable")  # Gaussians grouped by piece, ascending inside
    starts = np.concatenate([[0], np.cumsum(sizes)])
    local = np.empty(n, dtype=np.int64)
    local[members] = np.arange(n) - starts[piece[members]]
    edge_order = np.argsort(piece[sources], kind="stable")  # by piece, then (u, v)
    edge_starts = np.concatenate([[0], np.cumsum(np.bincount(piece[sources], minlength=count))])
    sources, targets, weights = sources[edge_order], targets[edge_order], weights[edge_order]
    features = _features(gaussians, config)
    components = piece.astype(np.int64) * n  # one id per piece; pieces solved below refine it
    solved = np.flatnonzero(sizes >= max(2.0, 2.0 * config.min_comp_weight))
    for p in solved:
        vertices = members[starts[p] : starts[p + 1]]
        edges = slice(edge_starts[p], edge_starts[p + 1])
        components[vertices] += _cut_pursuit(
            features[vertices], local[sources[edges]], local[targets[edges]], weights[edges], config
        )
    if config.polish:
        components = _polished(components, features, sources, targets, weights, config)
    labels = _relabel(components)
    log.info(
        "partition: %d Gaussians, %d edges, %d connected pieces (%d solved) → %d superpoints "
        "in %.2f s",
        n,
        sources.size,
        count,
        solved.size,
        int(labels.max()) + 1,
        time.perf_counter() - started,
    )
    return labels
