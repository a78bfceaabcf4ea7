"""The K-nearest-neighbour graph over Gaussians in position–colour space (design §4.3).

Every Gaussian is a point ``[x, y, z, c·r, c·g, c·b]`` in a 6-D search space: its centre (world
frame, scene units) and its view-independent DC colour (``Gaussians.dc_colors()``, in [0, 1])
scaled by ``c = GraphConfig.color_weight``. Each Gaussian is linked to its K nearest other
Gaussians in that space that lie within ``GraphConfig.radius``.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from thgs._spatial import spatial_order
from thgs.errors import InputError
from thgs.scene.gaussians import Gaussians

try:
    from pykdtree.kdtree import KDTree as _PyKDTree
except ImportError:  # pykdtree is a dependency; scipy serves where it cannot be installed
    _PyKDTree = None

__all__ = ["GraphConfig", "KnnGraph", "knn_graph", "nearest_neighbors", "search_points"]

log = logging.getLogger(__name__)


MAX_NEIGHBOURS = 1000
"""The most neighbours per Gaussian a graph may have (the reference uses 10)."""


@dataclass(frozen=True)
class GraphConfig:
    """How the KNN graph is built. Defaults are the reference's.

    Attributes:
        k: neighbours per Gaussian, itself excluded (10; at most 1,000: the graph holds N × k
            edges). With fewer than ``k + 1`` Gaussians every Gaussian gets all the others, and
            the remaining slots are marked missing.
        color_weight: factor on the RGB colour (in [0, 1]) in the search space (0.3); 0 searches
            by position only. Unit: scene units per unit of colour.
        radius: neighbours at a **Euclidean** 6-D distance of ``radius`` or more are dropped (2.0,
            scene units), i.e. an edge is kept when its squared distance is below ``radius²`` = 4.
            The reference passes 2 as the search radius of a radius-bounded KNN and keeps squared
            distances, as FRNN, pykdtree's ``distance_upper_bound`` and scipy's do: the bound is on
            the distance, not on the squared distance. ``inf`` keeps every neighbour.
    """

    k: int = 10
    color_weight: float = 0.3
    radius: float = 2.0

    def __post_init__(self) -> None:
        if not 1 <= self.k <= MAX_NEIGHBOURS:
            raise InputError(
                "GraphConfig.k", f"must be from 1 to {MAX_NEIGHBOURS:,} neighbours, got {self.k:,}"
            )
        if not self.color_weight >= 0:
            raise InputError("GraphConfig", f"color_weight must be ≥ 0, got {self.color_weight}")
        if not self.radius > 0:
            raise InputError("GraphConfig", f"radius must be > 0, got {self.radius}")


@dataclass(frozen=True, eq=False)
class KnnGraph:
    """Directed KNN edges ``i → neighbors[i, k]``, nearest first.

    Attributes:
        neighbors: [N, K] int32 neighbour indices, ascending distance along each row; −1 = missing
            (fewer than K Gaussians within the radius, or fewer than K + 1 Gaussians). Missing
            slots are always at the end of a row. A Gaussian is never its own neighbour.
        distances: [N, K] float32 **squared** Euclidean distances in the 6-D search space (scene
            units²); ``inf`` where the neighbour is missing.
    """

    neighbors: np.ndarray
    distances: np.ndarray

    def __len__(self) -> int:
        return int(self.neighbors.shape[0])

    @property
    def k(self) -> int:
        """Neighbour slots per Gaussian (K)."""
        return int(self.neighbors.shape[1])

    def valid(self) -> np.ndarray:
        """[N, K] bool: True where the slot holds a neighbour."""
        return self.neighbors >= 0

    def check(self, count: int, source: str = "KnnGraph") -> KnnGraph:
        """Raise :class:`InputError` unless the graph is [count, K] with consistent slots.

        Checks dtypes (int32 neighbours, float32 distances), shapes, indices in ``[−1, count)``,
        no self edges, and distances finite and ≥ 0 exactly where a neighbour is present.
        """
        neighbors, distances = self.neighbors, self.distances
        if neighbors.ndim != 2 or neighbors.shape[0] != count:
            raise InputError(source, f"neighbors must be [{count}, K], got {neighbors.shape}")
        if distances.shape != neighbors.shape:
            raise InputError(
                source, f"distances {distances.shape} and neighbors {neighbors.shape} differ"
            )
        if neighbors.dtype != np.int32 or distances.dtype != np.float32:
            raise InputError(
                source,
                f"neighbors must be int32 and distances float32, got {neighbors.dtype} and "
                f"{distances.dtype}",
            )
        if neighbors.size and (neighbors.min() < -1 or neighbors.max() >= count):
            raise InputError(source, f"neighbour indices outside [-1, {count})")
        if (neighbors == np.arange(count, dtype=np.int32)[:, None]).any():
            raise InputError(source, "a Gaussian is its own neighbour")
        valid = neighbors >= 0
        if not (np.isfinite(distances[valid]).all() and (distances[valid] >= 0).all()):
            raise InputError(source, "distances of present edges must be finite and ≥ 0")
        if not np.isinf(distances[~valid]).all():
            raise InputError(source, "distances of missing edges must be inf")
        return self


def search_points(gaussians: Gaussians, config: GraphConfig = GraphConfig()) -> np.ndarray:
    """[N, 6] float32 points of the search space: ``[means, color_weight · dc_colors()]``.

    Positions are world-frame scene units; colours are the view-independent DC colours in [0, 1].
    """
    means = gaussians.means.detach().cpu().numpy()
    colors = gaussians.dc_colors().detach().cpu().numpy()
    return np.concatenate([means, config.color_weight * colors], axis=1).astype(np.float32)


def nearest_neighbors(
    points: np.ndarray, k: int, radius: float, queries: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The k nearest ``points`` closer than ``radius`` to each query, by a KD-tree (pykdtree,
    else scipy).

    Args:
        points: [N, D] points (any units; distances are Euclidean in them).
        k: neighbours per query.
        radius: the largest distance searched (``np.inf`` for none), in the points' units.
        queries: [M, D] query points; default the points themselves, each then among its own
            neighbours.

    Returns:
        squared distances [M, k] and int64 indices [M, k], nearest first; missing entries have
        index N and distance inf.
    """
    queries = points if queries is None else queries
    m = queries.shape[0]
    bound = None if np.isinf(radius) else radius
    # queried in Z-order of their first three coordinates (near queries walk the same branches
    # of the tree, so memory is read once); each query's answer does not depend on the order
    order = spatial_order(queries[:, :3]) if queries.shape[1] >= 3 else np.arange(m)
    ordered = queries[order]
    if _PyKDTree is not None:
        squared, index = _PyKDTree(points).query(
            ordered, k=k, distance_upper_bound=bound, sqr_dists=True
        )
    else:
        distance, index = cKDTree(points).query(
            ordered, k=k, distance_upper_bound=np.inf if bound is None else bound, workers=-1
        )
        squared = np.square(distance)
    squared_out = np.empty((m, k), dtype=squared.dtype)
    index_out = np.empty((m, k), dtype=np.int64)
    squared_out[order] = squared.reshape(m, k)
    index_out[order] = index.reshape(m, k)
    return squared_out, index_out


def knn_graph(gaussians: Gaussians, config: GraphConfig = GraphConfig()) -> KnnGraph:
    """The K nearest neighbours of every Gaussian in the 6-D position–colour space.

    Args:
        gaussians: N Gaussians; their centres (world frame, scene units) and DC colours are used.
        config: K, colour weight and radius.

    Returns:
        [N, K] neighbours and squared 6-D distances (see :class:`KnnGraph`). A Gaussian's own
        index is removed even when other Gaussians coincide with it; among equidistant neighbours
        the KD-tree's order decides. With N ≤ K, every row holds at most N − 1 neighbours.
    """
    started = time.perf_counter()
    n, k = len(gaussians), config.k
    neighbors = np.full((n, k), -1, dtype=np.int32)
    distances = np.full((n, k), np.inf, dtype=np.float32)
    queried = min(k + 1, n)
    if queried < 2:
        return KnnGraph(neighbors, distances)
    squared, index = nearest_neighbors(search_points(gaussians, config), queried, config.radius)
    # Drop exactly one entry per row: the point itself, or (when more than k + 1 points coincide
    # and the tree returned others before it) the farthest entry.
    is_self = index == np.arange(n)[:, None]
    drop = is_self.copy()
    drop[~is_self.any(axis=1), -1] = True
    keep = ~drop
    index = index[keep].reshape(n, queried - 1)
    squared = squared[keep].reshape(n, queried - 1)
    present = (index < n) & np.isfinite(squared)
    neighbors[:, : queried - 1] = np.where(present, index, -1)
    distances[:, : queried - 1] = np.where(present, squared, np.inf)
    log.info(
        "KNN graph: %d Gaussians, k=%d, %d edges within radius %g in %.2f s",
        n,
        k,
        int(present.sum()),
        config.radius,
        time.perf_counter() - started,
    )
    return KnnGraph(neighbors, distances)
