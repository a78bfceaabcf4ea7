"""Level-0 superpoints by ℓ0 cut pursuit on the KNN graph (design §4.5).

The partition solves, over one 9-D value ``x_v`` per Gaussian,

    min_x  Σ_v ‖x_v − y_v‖²  +  R · Σ_(u,v) w_uv · [x_u ≠ x_v]

with ``y_v = [√W · (μ_v − mean μ), rgb_v, n_v]`` (centre, DC colour, surface normal) and edge
weights ``w_uv = 1 / (1 + d'_uv / mean d')`` from the (reweighted) squared KNN distances, using
pycut-pursuit's ``cp_d0_dist``. The connected pieces of constant ``x`` are the superpoints.

The result does not depend on the number of threads or on the machine: the graph is cut into
spatial blocks of at most ``block_size`` Gaussians (recursive halving of each connected piece
at the median of its longest axis: the data decide the blocks, not the threads), every
connected piece of a block is solved by the solver, in parallel worker processes
(:func:`_solved`), and superpoints that meet across a block seam are merged while that lowers
the same energy (:func:`thgs.graph.energy.join_seams`). A piece is solved on one thread (the
solver's parallel split cuts differently with another thread count); with
``threaded_largest``, a piece holding more than half of the vertices to solve, which would
otherwise keep one core busy while the others wait, is solved by the solver's own threads in a
form whose result does not depend on their number (:func:`_solver_arguments`).
Single-Gaussian moves then polish the whole partition (:func:`thgs.graph.energy.polish`).

With ``coarsen_levels``, each piece's graph is first coarsened by heavy-edge matching into atoms
of Gaussians that would rather stay together (:func:`thgs.graph.coarsen.coarsen`) and the
solver works on the atoms, weighted by their sizes: the same energy for every partition keeping
atoms whole.
"""

from __future__ import annotations

import logging
import pickle
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from thgs.errors import InputError, ThgsError
from thgs.graph.coarsen import coarsen
from thgs.graph.energy import join_seams, polish
from thgs.graph.knn import KnnGraph, nearest_neighbors
from thgs.scene.gaussians import Gaussians

__all__ = ["MIN_BLOCK_SIZE", "SOLVER_THREADS", "PartitionConfig", "partition"]

log = logging.getLogger(__name__)

MIN_BLOCK_SIZE = 1000
"""The smallest block the partition accepts: smaller blocks would cut most superpoints."""

MAX_COARSEN_LEVELS = 8
"""The most matching passes before the solver (each about halves the vertices)."""

SOLVER_THREADS = 2
"""The most threads a solve with ``threaded_largest`` runs on: its first split cuts the graph
into as many chunks as the solver has threads beyond two (:func:`_solver_arguments`)."""


@dataclass(frozen=True)
class PartitionConfig:
    """Cut-pursuit parameters. Defaults are the reference's LERF numbers with our
    ``weight_scale`` and ``split_alternatives``.

    Attributes:
        regularization: R, the price of cutting an edge of weight 1, in units of the squared
            feature distance (0.1; 3DOVS 0.3; at most 100). Larger R gives fewer, larger
            superpoints; from about 100 every connected piece is one superpoint, and the
            solver's time grows with R (synth-small: 18.7 s at R = 1,000).
        spatial_weight: W, the weight of the centred position (scene units) against colour
            ([0, 1]) and normal (unit vector) in the squared feature distance (0.1; 3DOVS 0.2).
            Positions enter the features scaled by √W, so W is in 1 / scene units².
        min_comp_weight: smallest superpoint, in Gaussians (10); smaller components are merged
            into an adjacent one. Only adjacent components can merge, so a piece of the graph
            that is disconnected from the rest and smaller than this stays as it is.
        cp_dif_tol: cut pursuit stops when the relative change of the iterate falls below this
            (1e-2).
        cp_it_max: at most this many cut-pursuit iterations (cut, reduce, merge) (15; at most
            1,000: the solver's objective can oscillate without meeting ``cp_dif_tol``).
        split_damp_ratio: edge weights in the split step start at this fraction of their value
            and grow linearly to it (0.7; 1 = no damping).
        flip_normals_up: flip each normal to world z ≥ 0 before use, as the reference does on
            LERF. Off by default: whether z is "up" depends on the scene's frame.
        block_size: the most Gaussians of one block (50 000): connected pieces of the graph
            larger than this are halved at the median of their longest axis until every block
            fits, each block is solved on its own (in parallel) and superpoints are merged
            across the seams (module docstring). 0 solves every connected piece whole. The
            result depends on this, never on the number of threads or processes.
        weight_scale: the d̄ of the edge weights ``w = 1 / (1 + d' / d̄)``: ``"graph"`` (ours,
            default) the mean of the graph's own squared distances (before any votes), so a vote
            changes only the weight of the edge it lands on; ``"reweighted"`` (the reference) the
            mean of the distances being partitioned, so strong negative votes inflate d̄ and
            raise the weight of every other edge, coarsening the whole partition (on
            ``synth-small`` at R = 1: sub-part purity 0.895 instead of 0.958, docs/partition.md).
            Identical when the distances are not reweighted.
        split_alternatives: K, the number of candidate values each component's split step
            tries (the solver's ``K``, 2 to 64; ours 6, the reference the solver's default 2).
            With 2 the split of a large component follows its widest spread, which on a table top is
            position: a flat object of another colour lying on it stays in the table's
            superpoint (synth-small seed 0: 27 % of a stack of books). More alternatives cost
            split time and give purer superpoints; the solver's objective is not lower for it
            (docs/partition.md).
        polish: after cut pursuit, move single Gaussians to a neighbouring superpoint while that
            lowers cut pursuit's own energy (ours True; the reference keeps the solver's
            output). The solver merges a component smaller than ``min_comp_weight`` into an
            adjacent one, which can be the wrong one: five Gaussians of a table's underside,
            joined to a chair's superpoint through floaters (docs/partition.md).
        threaded_largest: solve a piece that holds more than half of the vertices to solve (a
            scene of one block, such as synth-small) on up to :data:`SOLVER_THREADS` of the
            solver's own threads, in a form whose result does not depend on their number (ours
            True; False solves every piece on one thread, as the reference's settings do).
            Another path to another local minimum, its first split cut into two chunks by
            breadth-first search: on two cores synth-small's builds took 3.7–5.0 s instead of
            4.7–6.3 s, and its regions scored 0.002 lower on each level over ten seeds
            (docs/partition.md). Scenes of several blocks of similar size are unchanged.
        coarsen_levels: passes of heavy-edge matching before the solver (0, the default: the
            solver sees every Gaussian; at most 8). Each pass joins pairs of neighbours whose
            edge the votes made no lighter and whose join raises the data term by at most half
            the price of cutting their edge; the solver then works on these atoms, weighted by
            their Gaussians, and the polish moves single Gaussians again. Faster, a little
            coarser: with 2 passes synth-small's partition ran about 3.5× faster,
            synth-medium's and synth-large's 2–2.5×; on synth-small and synth-medium sub-parts
            lost 0.006 mIoU on average and objects 0.014, on synth-large every level gained
            (docs/partition.md).
    """

    regularization: float = 0.1
    spatial_weight: float = 0.1
    min_comp_weight: float = 10.0
    cp_dif_tol: float = 1e-2
    cp_it_max: int = 15
    split_damp_ratio: float = 0.7
    flip_normals_up: bool = False
    block_size: int = 50_000
    weight_scale: Literal["graph", "reweighted"] = "graph"
    split_alternatives: int = 6
    polish: bool = True
    threaded_largest: bool = True
    coarsen_levels: int = 0

    def __post_init__(self) -> None:
        if not (0 <= self.regularization <= 100 and self.spatial_weight >= 0):
            raise InputError(
                "PartitionConfig",
                "regularization must be from 0 to 100 and spatial_weight ≥ 0, got "
                f"{self.regularization:g} and {self.spatial_weight:g}",
            )
        if not (self.min_comp_weight >= 0 and self.cp_dif_tol >= 0):
            raise InputError("PartitionConfig", "min_comp_weight and cp_dif_tol must be ≥ 0")
        if not 1 <= self.cp_it_max <= 1000:
            raise InputError(
                "PartitionConfig", f"cp_it_max must be from 1 to 1,000, got {self.cp_it_max:,}"
            )
        if self.block_size != 0 and not MIN_BLOCK_SIZE <= self.block_size:
            raise InputError(
                "PartitionConfig.block_size",
                f"must be 0 (no blocks) or at least {MIN_BLOCK_SIZE} Gaussians, "
                f"got {self.block_size}",
            )
        if not 2 <= self.split_alternatives <= 64:
            raise InputError(
                "PartitionConfig",
                f"split_alternatives must be from 2 to 64, got {self.split_alternatives:,}",
            )
        if not 0 < self.split_damp_ratio <= 1:
            raise InputError(
                "PartitionConfig",
                f"split_damp_ratio must be in (0, 1], got {self.split_damp_ratio}",
            )
        if not 0 <= self.coarsen_levels <= MAX_COARSEN_LEVELS:
            raise InputError(
                "PartitionConfig",
                f"coarsen_levels must be from 0 to {MAX_COARSEN_LEVELS}, got "
                f"{self.coarsen_levels:,}",
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


def _solver() -> Callable:
    """pycut-pursuit's ``cp_d0_dist``, or a :class:`ThgsError` saying how to install it."""
    try:
        from pycut_pursuit.cp_d0_dist import cp_d0_dist
    except ImportError as error:
        raise ThgsError(
            f"the partition needs pycut-pursuit built against the installed NumPy {np.__version__}"
            f" ({error}); its wheels need NumPy 1 up to Python 3.12 and NumPy 2 from 3.13, and "
            "`pip install thgs` installs that pair (README, Installing)"
        ) from error
    return cp_d0_dist


def _solver_arguments(
    features: np.ndarray,
    sources: np.ndarray,
    targets: np.ndarray,
    weights: np.ndarray,
    vertex_weights: np.ndarray | None,
    config: PartitionConfig,
    threads: int | None = None,
) -> tuple[tuple, dict]:
    """``(args, kwargs)`` of ``cp_d0_dist`` on one connected graph of m vertices: on one thread
    (``threads`` None), or on up to ``threads`` with the same result for any number ≥ 1.

    ``features`` is [m, 9]; edges ``sources[e] < targets[e]`` are local indices sorted by source;
    ``vertex_weights`` [m] the Gaussians each vertex stands for (None: one each). The solver's
    output holds the graph's m vertices first (:func:`_solved` drops any others).

    What the solver's result depends on in its threads t (pycut-pursuit 0.1.3–0.1.4, read in
    its source and checked): it orders its components by size before each split when t > 1 or
    its ``max_split_size`` S is below its vertex count V, and it cuts a component larger than
    ``min(S, (V − 1) // t + 1)`` into chunks when its balancing is on or a component exceeds S.
    With threads, the graph gets one isolated vertex more (V = m + 1), its value beyond every
    vertex's in every coordinate (with the value of one of them, the solver often left two
    touching blobs whole, docs/partition.md), S = m and the balancing off: the components are
    always ordered, and only the first split, whose one component holds all V vertices (the
    solver starts from one component, joined or not), is cut into chunks by breadth-first
    search: into ⌈V / min(m, m // t + 1)⌉ chunks, two for t = 1 and t = 2 alike but t for
    larger t. So the solver is given at most :data:`SOLVER_THREADS` threads: on one and on two
    it gave the same ids in every test (an empirical fact about its other parallel loops, not
    one read in its source). The order and the two chunks are another path to another local
    minimum than one thread's (docs/partition.md).
    """
    m = features.shape[0]
    shared = threads is not None
    first_edge = np.zeros(m + 1 + shared, dtype=np.int32)
    np.cumsum(np.bincount(sources, minlength=m), out=first_edge[1 : m + 1])
    if shared:
        first_edge[m + 1] = first_edge[m]
        low, high = features.min(axis=0), features.max(axis=0)
        features = np.concatenate([features, (2 * high - low + 1)[None, :]])  # beyond them all
        if vertex_weights is not None:
            vertex_weights = np.append(vertex_weights, 1.0)
    args = (
        features.shape[1],
        features.T,  # the transpose of a C-contiguous [V, 9] array is F-contiguous, as required
        first_edge,
        targets.astype(np.int32),
    )
    kwargs = {
        "edge_weights": (config.regularization * weights).astype(np.float32),
        "min_comp_weight": config.min_comp_weight,
        "cp_dif_tol": config.cp_dif_tol,
        "cp_it_max": config.cp_it_max,
        "split_damp_ratio": config.split_damp_ratio,
        "K": config.split_alternatives,
        "verbose": False,
        "max_num_threads": min(threads, SOLVER_THREADS) if shared else 1,
    }
    if shared:
        kwargs |= {"max_split_size": m, "balance_parallel_split": False}
    if vertex_weights is not None:
        kwargs["vert_weights"] = vertex_weights.astype(np.float32)
    return args, kwargs


def _relabel(components: np.ndarray) -> np.ndarray:
    """[N] int32 ids 0 … S−1 numbered by each component's smallest Gaussian index."""
    _, first, inverse = np.unique(components, return_index=True, return_inverse=True)
    rank = np.empty(first.size, dtype=np.int32)
    rank[np.argsort(first)] = np.arange(first.size, dtype=np.int32)
    return rank[inverse]


def _blocks(means: np.ndarray, piece: np.ndarray, sizes: np.ndarray, block_size: int) -> np.ndarray:
    """[N] block id of each vertex: its connected piece's id, or for a piece of more than
    ``block_size`` vertices, one of the halves it is cut into, again and again, at the median
    of the members' longest axis (centres ``means`` [N, 3]; stable sort, so ties go by index)
    until every half fits. ``block_size`` 0: the pieces themselves."""
    block = piece.astype(np.int64)
    if block_size == 0:
        return block
    fresh = len(sizes)
    for p in np.flatnonzero(sizes > block_size):
        stack = [np.flatnonzero(piece == p)]
        while stack:
            members = stack.pop()
            if len(members) <= block_size:
                block[members] = fresh
                fresh += 1
                continue
            points = means[members]
            axis = int(np.argmax(points.max(axis=0) - points.min(axis=0)))
            order = members[np.argsort(points[:, axis], kind="stable")]
            half = len(order) // 2
            stack += [order[half:], order[:half]]
    return block


_WORKER = """
import pickle, sys
from pycut_pursuit.cp_d0_dist import cp_d0_dist
calls = pickle.load(sys.stdin.buffer)
pickle.dump([cp_d0_dist(*args, **kwargs)[0] for args, kwargs in calls], sys.stdout.buffer, 5)
"""
"""A solver process: reads a pickled list of ``cp_d0_dist`` calls, writes their components.
It imports the solver alone (neither thgs nor the caller's main module)."""


_SHARED_FROM = 2000
"""Vertices to solve besides the largest piece below which worker processes (about 0.25 s to
start each) are not started: the pieces are solved here."""


def _shares(sizes: list[int], workers: int) -> list[list[int]]:
    """Task indices per worker: the largest task first to the least loaded (ties: lower index)."""
    shares: list[list[int]] = [[] for _ in range(min(workers, len(sizes)))]
    loads = [0] * len(shares)
    for i in sorted(range(len(sizes)), key=lambda i: (-sizes[i], i)):
        lightest = loads.index(min(loads))
        shares[lightest].append(i)
        loads[lightest] += sizes[i]
    return shares


def _solved(
    tasks: list[tuple], config: PartitionConfig, workers: int, ray: bool = False
) -> list[np.ndarray]:
    """[m] component ids of every ``(features, sources, targets, weights, vertex_weights)`` task
    (:func:`_solver_arguments`), in order.

    With ``ray``, or ``workers`` > 1, and at least :data:`_SHARED_FROM` vertices besides the
    largest task, the tasks are shared out (:func:`_shares`) to Ray tasks, one per CPU of the
    cluster (:func:`thgs.build_ray.ray_solve`), or to ``workers`` fresh Python processes
    (:data:`_WORKER`); else they are solved here one by one. Every task is solved on one
    thread, except with ``config.threaded_largest`` one holding more than half of all the
    vertices, solved in the solver's form that gives the same result on one thread or on
    :data:`SOLVER_THREADS`: here on up to ``workers`` threads, in a worker process on the share
    of them its share of the vertices rounds to, in a Ray task (one CPU) on one. So where a
    task runs does not change its result. Fresh processes, not a fork of this one (a fork of a
    process whose OpenMP runtimes, the KD-tree's or torch's, have started threads hangs in the
    solver) nor multiprocessing's spawn (which runs the caller's main module again in every
    worker).

    Raises:
        ThgsError: a solver process failed (its error output is in the message), or Ray is
            asked for and not initialised.
    """
    solver = _solver()
    sizes = [len(task[0]) for task in tasks]
    total = sum(sizes)
    dominant = [config.threaded_largest and 2 * size > total for size in sizes]

    def arguments(i: int, threads: int) -> tuple[tuple, dict]:
        return _solver_arguments(*tasks[i], config, threads if dominant[i] else None)

    small = sum(sorted(sizes)[:-1]) < _SHARED_FROM
    found: list[np.ndarray] = [np.zeros(0)] * len(tasks)
    if ray and not small:
        from thgs.build_ray import ray_solve, ray_workers

        shares = _shares(sizes, ray_workers())
        solved = ray_solve([[arguments(i, 1) for i in share] for share in shares])
        for share, components in zip(shares, solved):
            for i, ids in zip(share, components):
                found[i] = ids[: sizes[i]].astype(np.int64)
        return found
    if workers < 2 or small or not sys.executable:
        calls = [arguments(i, workers) for i in range(len(tasks))]
        return [
            solver(*args, **kwargs)[0][:size].astype(np.int64)
            for (args, kwargs), size in zip(calls, sizes)
        ]
    shares = _shares(sizes, workers)
    processes = []
    try:
        for share in shares:
            load = sum(sizes[i] for i in share)
            threads = max(1, round(workers * load / total))  # its share of the threads
            calls = [arguments(i, threads) for i in share]
            errors = tempfile.TemporaryFile()
            process = subprocess.Popen(
                [sys.executable, "-c", _WORKER],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                stderr=errors,
            )
            processes.append((process, errors))
            try:
                with process.stdin:  # type: ignore[union-attr]
                    pickle.dump(calls, process.stdin, 5)
            except BrokenPipeError:
                pass  # it died before reading: its exit code and error output say why
        for share, (process, errors) in zip(shares, processes):
            output = process.stdout.read()  # type: ignore[union-attr]
            if process.wait() != 0:
                errors.seek(0)
                message = errors.read().decode(errors="replace").strip()[-2000:]
                raise ThgsError(
                    f"a cut-pursuit solver process ({sys.executable}) failed with exit code "
                    f"{process.returncode}: {message}"
                )
            for i, components in zip(share, pickle.loads(output)):
                found[i] = components[: sizes[i]].astype(np.int64)
    finally:
        for process, errors in processes:
            if process.poll() is None:
                process.kill()
                process.wait()
            process.stdout.close()  # type: ignore[union-attr]
            errors.close()
    return found


def partition(
    gaussians: Gaussians,
    graph: KnnGraph,
    distances: np.ndarray,
    config: PartitionConfig = PartitionConfig(),
    *,
    workers: int | None = None,
    ray: bool = False,
) -> np.ndarray:
    """Level-0 superpoints of N Gaussians.

    The graph is cut into blocks (module docstring, ``config.block_size``) and the solver run
    once per connected piece of each block: ``cp_d0_dist`` only separates vertices across
    edges it cuts, so pieces of a disconnected graph would otherwise share one value. A piece
    smaller than ``max(2, 2 · min_comp_weight)`` Gaussians cannot hold two superpoints and is
    one superpoint without a solver call. Superpoints meeting across a block seam are then
    merged while that lowers the energy (:func:`thgs.graph.energy.join_seams`), and with
    ``config.polish`` single Gaussians move to a neighbouring superpoint while that lowers it
    (:func:`thgs.graph.energy.polish`).

    Args:
        gaussians: the N Gaussians; centres (world frame, scene units), DC colours and surface
            normals (``Gaussians.surface_normals()``) make the features.
        graph: their [N, K] KNN graph (:func:`thgs.graph.knn_graph`).
        distances: [N, K] squared edge distances to partition with, aligned with
            ``graph.neighbors``: ``graph.distances`` or the output of :func:`thgs.graph.reweight`
            (finite and ≥ 0 at present edges).
        config: cut-pursuit parameters.
        workers: processes solving pieces at once (None: numba's thread count, the CPU
            threads thgs uses, ``NUMBA_NUM_THREADS``). The result is the same for any number.
        ray: solve the blocks as Ray tasks instead, one share per CPU of the Ray this process
            is connected to (:func:`thgs.build_ray.ray_solve`); the same result.

    Returns:
        [N] int32 superpoint ids 0 … S−1, numbered in order of each superpoint's smallest
        Gaussian index. Every superpoint is connected in the graph (plus the joins of isolated
        Gaussians); the same inputs give the same ids, whatever ``workers`` or the machine.

    Raises:
        InputError: inconsistent inputs, or ``workers`` < 1.
    """
    started = time.perf_counter()
    workers = numba.get_num_threads() if workers is None else workers
    if isinstance(workers, bool) or not isinstance(workers, (int, np.integer)) or workers < 1:
        raise InputError("partition", f"workers must be a whole number ≥ 1, got {workers!r}")
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
    # an edge the votes made no lighter: only such edges may join two Gaussians into an atom
    joinable = (
        weights >= _edge_weights(graph, graph.distances, means, scale_from)[2]
        if config.coarsen_levels
        else np.ones(weights.size, dtype=bool)
    )
    sources = np.repeat(np.arange(n), np.diff(first_edge))
    piece, sizes = _pieces(n, sources, targets)
    block = _blocks(means, piece, sizes, config.block_size)
    seam = block[sources] != block[targets]
    if seam.any():  # the pieces of the blocks, without the edges across their seams
        piece, sizes = _pieces(n, sources[~seam], targets[~seam])
    count = len(sizes)
    members = np.argsort(piece, kind="stable")  # Gaussians grouped by piece, ascending inside
    starts = np.concatenate([[0], np.cumsum(sizes)])
    local = np.empty(n, dtype=np.int64)
    local[members] = np.arange(n) - starts[piece[members]]
    inner_sources, inner_targets, inner_weights = sources[~seam], targets[~seam], weights[~seam]
    inner_joinable = joinable[~seam]
    inner_piece = piece[inner_sources]
    edge_order = np.argsort(inner_piece, kind="stable")  # by piece, then (u, v)
    edge_starts = np.concatenate([[0], np.cumsum(np.bincount(inner_piece, minlength=count))])
    inner_sources, inner_targets = inner_sources[edge_order], inner_targets[edge_order]
    inner_weights = inner_weights[edge_order]
    inner_joinable = inner_joinable[edge_order]
    features = _features(gaussians, config)
    components = piece.astype(np.int64) * n  # one id per piece; pieces solved below refine it
    solved = np.flatnonzero(sizes >= max(2.0, 2.0 * config.min_comp_weight))
    tasks, atoms = [], []
    for p in solved:
        vertices = members[starts[p] : starts[p + 1]]
        edges = slice(edge_starts[p], edge_starts[p + 1])
        task = (
            features[vertices],
            local[inner_sources[edges]],
            local[inner_targets[edges]],
            inner_weights[edges],
        )
        atom, task = (
            coarsen(*task, inner_joinable[edges], config.regularization, config.coarsen_levels)
            if config.coarsen_levels
            else (None, (*task, None))
        )
        tasks.append(task)
        atoms.append(atom)
    for p, atom, found in zip(solved, atoms, _solved(tasks, config, workers, ray)):
        components[members[starts[p] : starts[p + 1]]] += found if atom is None else found[atom]
    cost = config.regularization * weights.astype(np.float64)
    if seam.any():
        components = join_seams(
            components, features.astype(np.float64), sources, targets, cost, seam
        )
    if config.polish:
        components = polish(
            components, features, sources, targets, cost, config.cp_it_max, config.min_comp_weight
        )
    labels = _relabel(components)
    log.info(
        "partition: %d Gaussians, %d edges, %d blocks, %d pieces (%d solved, %d workers) → %d "
        "superpoints in %.2f s",
        n,
        sources.size,
        len(np.unique(block)),
        count,
        solved.size,
        workers,
        int(labels.max()) + 1,
        time.perf_counter() - started,
    )
    return labels


def _pieces(n: int, sources: np.ndarray, targets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(piece [N], sizes [P])``: the connected pieces of the undirected edges
    ``sources[e] – targets[e]`` over n vertices."""
    adjacency = coo_matrix((np.ones(sources.size, dtype=np.int8), (sources, targets)), (n, n))
    _, piece = connected_components(adjacency, directed=False)
    return piece, np.bincount(piece)
