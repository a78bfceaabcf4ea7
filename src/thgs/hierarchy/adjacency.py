"""Which units (superpoints or merged regions) touch: 1-hop and 2-hop adjacency (design §4.6).

Two units are 1-hop neighbours when some Gaussian of one has a Gaussian of the other among its
k nearest Gaussians by centre (3-D, the Gaussian itself included, k = 8 as in the reference);
2-hop neighbours are neighbours of neighbours that are not 1-hop neighbours. Both are kept as
sparse CSR lists, never as dense U × U matrices.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix

from thgs.errors import InputError
from thgs.graph.knn import nearest_neighbors
from thgs.scene.gaussians import Gaussians

__all__ = ["UnitGraph", "coarsened_graph", "gaussian_neighbors", "unit_graph"]


def gaussian_neighbors(gaussians: Gaussians, k: int = 8) -> np.ndarray:
    """[N, k] int64 indices of each Gaussian's k nearest Gaussians by centre, itself included.

    Fewer than k Gaussians: the missing slots repeat the Gaussian itself.
    """
    if k < 1:
        raise InputError("gaussian_neighbors", f"k must be ≥ 1, got {k}")
    n = len(gaussians)
    means = gaussians.means.detach().cpu().numpy().astype(np.float32)
    if n == 0:
        return np.zeros((0, k), dtype=np.int64)
    _, index = nearest_neighbors(means, min(k, n), np.inf)
    if index.shape[1] < k:
        own = np.repeat(np.arange(n)[:, None], k - index.shape[1], axis=1)
        index = np.concatenate([index, own], axis=1)
    return index


@dataclass(frozen=True, eq=False)
class UnitGraph:
    """Adjacency of U units in CSR form.

    Attributes:
        one_hop: [U, U] sparse bool, symmetric, no diagonal: units that touch.
        pairs: [P, 2] int64 unit pairs (a < b) within two hops, sorted: the pairs an affinity is
            needed for.
        hops: [P] int8 1 or 2, the hop distance of each pair.
    """

    one_hop: csr_matrix
    pairs: np.ndarray
    hops: np.ndarray

    @property
    def units(self) -> int:
        return int(self.one_hop.shape[0])


def _graph_from_edges(a: np.ndarray, b: np.ndarray, count: int) -> UnitGraph:
    """The adjacency of ``count`` units from touching unit pairs (a[i], b[i]), a ≠ b."""
    # int64 counts: a narrow dtype would wrap when many Gaussian pairs join two units
    one = coo_matrix((np.ones(a.size, dtype=np.int64), (a, b)), shape=(count, count)).tocsr()
    one = ((one + one.T) > 0).astype(np.int64).tocsr()
    two = (one @ one + one).tocsr()
    two.setdiag(0)
    two.eliminate_zeros()
    upper = coo_matrix(two)
    keep = upper.row < upper.col
    pairs = np.stack([upper.row[keep], upper.col[keep]], axis=1).astype(np.int64)
    order = np.lexsort((pairs[:, 1], pairs[:, 0]))
    pairs = pairs[order]
    adjacent = np.asarray(one[pairs[:, 0], pairs[:, 1]]).ravel() > 0 if len(pairs) else []
    hops = np.where(adjacent, 1, 2).astype(np.int8)
    return UnitGraph(one_hop=one.astype(bool).tocsr(), pairs=pairs, hops=hops)


def unit_graph(units: np.ndarray, neighbors: np.ndarray, count: int | None = None) -> UnitGraph:
    """The 1-hop and 2-hop adjacency of the units of N Gaussians.

    Args:
        units: [N] int unit id per Gaussian, 0 … U−1.
        neighbors: [N, k] Gaussian neighbour indices (:func:`gaussian_neighbors`).
        count: U (default ``units.max() + 1``).
    """
    units = np.asarray(units, dtype=np.int64)
    u = int(units.max()) + 1 if count is None and units.size else int(count or 0)
    a = np.repeat(units, neighbors.shape[1])
    b = units[neighbors.ravel()]
    different = a != b
    return _graph_from_edges(a[different], b[different], u)


def coarsened_graph(graph: UnitGraph, groups: np.ndarray, count: int) -> UnitGraph:
    """The adjacency of ``count`` regions made of the graph's units: two regions touch when
    some of their units touch, which is what :func:`unit_graph` gives for the regions' Gaussians.

    Args:
        graph: the units' adjacency.
        groups: [U] int region of every unit, 0 … count − 1.
    """
    one = graph.one_hop.tocoo()
    groups = np.asarray(groups, dtype=np.int64)
    a, b = groups[one.row], groups[one.col]
    different = a != b
    return _graph_from_edges(a[different], b[different], count)
