"""Cut pursuit's energy on a partition of a graph's vertices, and the moves that lower it.

For components with mean features ``c``, vertices with features ``x_v`` and undirected edges
``sources[e] – targets[e]`` of weight ``cost[e]`` (R included), the energy is

    Σ_v ‖x_v − c(v)‖²  +  Σ_e cost[e] · [the ends of e are apart].

:func:`join_seams` merges components that meet across a block seam while that lowers it,
:func:`polish` moves single vertices while that lowers it, and :func:`connected` splits
components into connected pieces and joins the small ones. All of it is deterministic: ties go
to the lower ids.
"""

from __future__ import annotations

import heapq

import numba
import numpy as np

__all__ = ["both_directions", "connected", "join_seams", "polish"]


@numba.njit(cache=True)
def both_directions(n, sources, targets, cost):  # pragma: no cover
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
            # element by element: an array operation compiles numba's shape-mismatch error
            # path, seconds of a first run's compilation
            for d in range(features.shape[1]):
                sums[c, d] /= sizes[c]
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


def connected(
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


def polish(
    labels: np.ndarray,
    features: np.ndarray,
    sources: np.ndarray,
    targets: np.ndarray,
    cost: np.ndarray,
    passes: int,
    min_size: float,
) -> np.ndarray:
    """[N] component ids after passes of single-vertex moves on cut pursuit's energy
    ``Σ_i ‖x_i − c(i)‖² + R · Σ_(i,j) w_ij [i, j apart]`` (c: each component's mean feature).

    In each pass every vertex takes, among its own component and its neighbours', the one of
    lowest energy for it alone (:func:`_best_components`), the means held fixed; a pass is kept
    only if the whole energy, recomputed, went down. At most ``passes`` passes. The components
    are then made connected again (:func:`connected`, with ``min_size``). Edges
    ``sources[e] – targets[e]`` weigh ``cost[e]`` (R included).
    """
    _, labels = np.unique(labels, return_inverse=True)  # 0 … C − 1 from here on
    count = int(labels.max()) + 1
    n = len(labels)
    cost = np.asarray(cost, dtype=np.float64)
    first_edge, neighbour, edge_cost = both_directions(n, sources, targets, cost)
    features = features.astype(np.float64)
    means = _means(labels, features, count)
    energy = _energy(labels, features, means, sources, targets, cost)
    for _ in range(passes):
        moved = _best_components(first_edge, neighbour, edge_cost, labels, features, means)
        if (moved == labels).all():
            break
        moved_means = _means(moved, features, count)
        moved_energy = _energy(moved, features, moved_means, sources, targets, cost)
        if moved_energy >= energy:
            break
        labels, means, energy = moved, moved_means, moved_energy
    return connected(labels, sources, targets, cost, min_size)


def join_seams(
    labels: np.ndarray,
    features: np.ndarray,
    sources: np.ndarray,
    targets: np.ndarray,
    cost: np.ndarray,
    seam: np.ndarray,
) -> np.ndarray:
    """[N] component ids after merging components that meet across a block seam.

    Merging components a and b changes cut pursuit's energy by
    ``n_a n_b / (n_a + n_b) · ‖c_a − c_b‖² − w_ab`` (c: mean feature, n: size, w_ab: the
    summed ``cost`` of the edges between them): the pair joined by at least one seam edge
    (``seam`` [E] bool) with the most negative change is merged, its edges and means updated,
    until no such pair lowers the energy (ties: the lower ids first; the merged component keeps
    the lower id)."""
    _, labels = np.unique(labels, return_inverse=True)
    count = int(labels.max()) + 1
    sizes = np.bincount(labels, minlength=count).astype(np.float64)
    sums = np.stack(
        [np.bincount(labels, weights=column, minlength=count) for column in features.T], axis=1
    )
    a, b = labels[sources], labels[targets]
    apart = a != b
    low, high = np.minimum(a, b)[apart], np.maximum(a, b)[apart]
    keys, inverse = np.unique(low * count + high, return_inverse=True)
    weight = np.bincount(inverse, weights=cost[apart])
    crossing = np.bincount(inverse, weights=seam[apart].astype(np.float64)) > 0

    def change(x: int, y: int, w: float) -> float:
        step = sums[x] / sizes[x] - sums[y] / sizes[y]
        return float(sizes[x] * sizes[y] / (sizes[x] + sizes[y]) * (step @ step)) - w

    edges: list[dict[int, list]] = [{} for _ in range(count)]
    heap = []
    for x, y, w, c in zip((keys // count).tolist(), (keys % count).tolist(), weight, crossing):
        edges[x][y] = [float(w), bool(c)]
        edges[y][x] = [float(w), bool(c)]
        if c and (gain := change(x, y, float(w))) < 0:
            heap.append((gain, x, y, 0, 0))
    heapq.heapify(heap)
    version = [0] * count
    root = np.arange(count)
    while heap:
        _, x, y, seen_x, seen_y = heapq.heappop(heap)
        if version[x] != seen_x or version[y] != seen_y:
            continue  # one of them changed since: its pairs were pushed again
        sizes[x] += sizes[y]
        sums[x] += sums[y]
        root[y] = x
        del edges[x][y]
        for z, (w, c) in edges[y].items():
            if z == x:
                continue
            del edges[z][y]
            if z in edges[x]:
                edges[x][z][0] += w
                edges[x][z][1] |= c
                edges[z][x][0] += w
                edges[z][x][1] |= c
            else:
                edges[x][z] = [w, c]
                edges[z][x] = [w, c]
        edges[y] = {}
        version[x] += 1
        version[y] += 1
        for z, (w, c) in edges[x].items():
            low_id, high_id = min(x, z), max(x, z)
            if c and (gain := change(low_id, high_id, w)) < 0:
                heapq.heappush(heap, (gain, low_id, high_id, version[low_id], version[high_id]))
    while not (root[root] == root).all():
        root = root[root]
    return root[labels]
