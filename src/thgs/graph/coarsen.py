"""Heavy-edge matching of a graph's vertices into atoms before cut pursuit
(``PartitionConfig.coarsen_levels``, as in multilevel graph partitioners).

Each pass joins pairs of neighbours across their heaviest edge when joining them raises cut
pursuit's data term by little (:data:`ATOM_TOLERANCE`); the solver then works on the atoms,
weighted by their sizes, which keeps the energy of every partition that keeps atoms whole.
"""

from __future__ import annotations

import logging

import numba
import numpy as np

from thgs.graph.energy import both_directions

__all__ = ["ATOM_TOLERANCE", "coarsen"]

log = logging.getLogger(__name__)

ATOM_TOLERANCE = 0.5
"""Two vertices are matched only when joining them raises the data term by at most this share
of the price of cutting their edge (:func:`_matching`)."""


@numba.njit(cache=True)
def _matching(first_edge, neighbour, cost, features, weight, tolerance):  # pragma: no cover
    """[n] atom id per vertex after one pass of heavy-edge matching.

    Each vertex not yet matched, in index order, is matched to the unmatched neighbour across
    its heaviest edge (the first found on a tie) among those whose join raises the data term,
    ``w_u w_v / (w_u + w_v) · ‖f_u − f_v‖²``, by at most ``tolerance`` times the edge's
    ``cost``; a vertex without such a neighbour stays alone. Atoms are numbered in order of
    their smallest vertex. Edges in forward-star form over both directions."""
    n, dim = features.shape
    mate = np.full(n, -1, np.int64)
    for v in range(n):
        if mate[v] >= 0:
            continue
        chosen = -1
        heaviest = 0.0
        for e in range(first_edge[v], first_edge[v + 1]):
            u = neighbour[e]
            if u == v or mate[u] >= 0 or cost[e] <= heaviest:
                continue
            distance = 0.0
            for d in range(dim):
                step = features[v, d] - features[u, d]
                distance += step * step
            if weight[v] * weight[u] / (weight[v] + weight[u]) * distance <= tolerance * cost[e]:
                chosen, heaviest = u, cost[e]
        if chosen < 0:
            mate[v] = v
        else:
            mate[v], mate[chosen] = chosen, v
    atom = np.empty(n, np.int64)
    count = 0
    for v in range(n):
        if mate[v] >= v:
            atom[v] = count
            atom[mate[v]] = count
            count += 1
    return atom


def coarsen(
    features: np.ndarray,
    sources: np.ndarray,
    targets: np.ndarray,
    weights: np.ndarray,
    joinable: np.ndarray,
    regularization: float,
    levels: int,
) -> tuple[np.ndarray, tuple]:
    """The solver's task on atoms: ``(atom [m], (features [a, 9], sources [E'], targets [E'],
    weights [E'], vertex_weights [a]))`` after ``levels`` passes of :func:`_matching` on one
    piece's graph (``features`` [m, 9], edges ``sources[e] < targets[e]`` with ``weights`` [E]
    before R = ``regularization``; only edges with ``joinable`` [E] may join).

    An atom's feature is the mean of its Gaussians' and its weight their count; the edges
    between two atoms are one edge of their summed weight. Cut pursuit's energy of any partition
    that keeps every atom whole is the same on the atoms as on the Gaussians, up to a constant
    (the atoms' own scatter), so the solver sees the same problem, smaller; single-Gaussian
    moves afterwards (:func:`thgs.graph.energy.polish`) can still part what a match joined."""
    atom = np.arange(len(features))
    vertex_weights = np.ones(len(features))
    features = features.astype(np.float64)
    for _ in range(levels):
        first_edge, neighbour, cost = both_directions(
            len(features), sources, targets, np.where(joinable, regularization * weights, 0)
        )
        matched = _matching(first_edge, neighbour, cost, features, vertex_weights, ATOM_TOLERANCE)
        count = int(matched.max()) + 1
        if count == len(features):
            break
        sums = np.stack(
            [np.bincount(matched, vertex_weights * column, count) for column in features.T], 1
        )
        vertex_weights = np.bincount(matched, vertex_weights, count)
        features = sums / vertex_weights[:, None]
        a, b = matched[sources], matched[targets]
        apart = a != b
        keys, inverse = np.unique(
            np.minimum(a, b)[apart] * count + np.maximum(a, b)[apart], return_inverse=True
        )
        weights = np.bincount(inverse, weights[apart])
        joinable = np.bincount(inverse, (~joinable[apart]).astype(np.float64)) == 0
        sources, targets = keys // count, keys % count
        atom = matched[atom]
    log.debug("coarsened %d Gaussians into %d atoms", len(atom), len(features))
    return atom, (features.astype(np.float32), sources, targets, weights, vertex_weights)
