"""Splitting merged regions whose halves disagree (ours, not in the paper).

Region growing admits a unit on its affinity with the members it touches, so one unit that the
masks confuse can carry two objects into one region: a chair leg whose foot the floor's masks
cover agrees with the floor (A ≈ 0.8) and with the seat, and floor, leg and chair become one
object although the floor and the chair, as wholes, agree in few views. :func:`split_incoherent`
checks every region after a pass: it cuts the region in two along its weakest link and keeps
the cut when the two sides, their evidence pooled, fall below the pass's threshold — the test a
merging round applies to two regions. Each side is checked again in turn.

The weakest link is the normalized spectral cut (Shi and Malik) of the region's units, joined
where they touch and weighted by their affinity: the Fiedler vector of the normalized Laplacian
orders the units, and of the cuts along that order the one of lowest conductance (cut weight
over the smaller side's volume) is taken.

After merging, objects are checked on sub-part units (:func:`thgs.hierarchy.merge_levels`): a
part that took in a piece of another object is cut with the object.
"""

from __future__ import annotations

import logging

import numpy as np
import torch
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from thgs.hierarchy.adjacency import UnitGraph
from thgs.hierarchy.affinity import MaskEvidence, affinity_and_support, pair_affinity
from thgs.hierarchy.levels import renumber_by_units

__all__ = ["split_incoherent"]

log = logging.getLogger(__name__)

MAX_SPLIT_UNITS = 2000
"""Largest region (in units) that :func:`split_incoherent` checks: its cut solves a dense
eigenproblem of that size."""

_FLOOR = 1e-3
"""Weight of a touching pair without affinity, so that every unit stays joined to the others."""


def split_incoherent(
    regions: np.ndarray,
    graph: UnitGraph,
    evidence: MaskEvidence,
    threshold: float,
    min_support: float = 0.0,
) -> np.ndarray:
    """Regions cut where their two sides disagree.

    Args:
        regions: [U] int region id (0 … R − 1) of each unit.
        graph: the units' adjacency (only touching pairs are used).
        evidence: the units' mask evidence, from which the sides' evidence is pooled.
        threshold: a cut is kept when the sides' affinity is below this (the pass's threshold).
        min_support: a cut whose sides' support is not above this is not kept (no evidence
            either way).

    Returns:
        [U] int64 region ids 0 … R' − 1 (R' ≥ R), numbered in order of each region's smallest
        unit; every new region lies inside one old region and is connected.
    """
    regions = np.asarray(regions, dtype=np.int64)
    touching = graph.pairs[graph.hops == 1]
    affinity = pair_affinity(evidence, touching, min_support)
    count = graph.units
    weights = coo_matrix(
        (np.maximum(affinity, _FLOOR), (touching[:, 0], touching[:, 1])), shape=(count, count)
    ).tocsr()
    weights = (weights + weights.T).tocsr()
    order = np.argsort(regions, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(regions[order]) != 0])
    pending = [members for members in np.split(order, starts[1:]) if members.size > 1]
    result = regions.copy()
    fresh = int(regions.max()) + 1
    splits = 0
    while pending:
        members = pending.pop()
        if members.size > MAX_SPLIT_UNITS:
            log.info("a region of %d units is not checked for a split", members.size)
            continue
        local = weights[members][:, members]
        if (local.getnnz(axis=1) == 0).any():  # not connected: growing never makes one
            continue
        side = _weakest_cut(local.toarray())
        if not _disagree(evidence, members, side, threshold, min_support):
            continue
        splits += 1
        for half in (np.flatnonzero(side), np.flatnonzero(~side)):
            pieces, piece = connected_components(local[half][:, half], directed=False)
            for p in range(pieces):
                part = members[half[piece == p]]
                result[part] = fresh
                fresh += 1
                if part.size > 1:
                    pending.append(part)
    if splits:
        log.info("split %d incoherent regions", splits)
    _, dense = np.unique(result, return_inverse=True)
    return renumber_by_units(dense, np.arange(count)).astype(np.int64)


def _weakest_cut(weights: np.ndarray) -> np.ndarray:
    """[M] bool: one side of the lowest-conductance cut along the Fiedler vector of the
    normalized Laplacian of the symmetric [M, M] ``weights`` (every degree > 0, M ≥ 2)."""
    degree = weights.sum(axis=1)
    scale = 1.0 / np.sqrt(degree)
    laplacian = np.eye(len(degree)) - scale[:, None] * weights * scale[None, :]
    _, vectors = np.linalg.eigh(laplacian)
    rank = np.argsort(vectors[:, 1] * scale, kind="stable")
    ordered = weights[rank][:, rank]
    volume = np.cumsum(degree[rank])[:-1]
    inner = np.cumsum(np.tril(ordered, -1).sum(axis=1))[:-1]  # weight inside each prefix
    cut = volume - 2.0 * inner
    conductance = cut / np.minimum(volume, degree.sum() - volume)
    side = np.zeros(len(degree), dtype=bool)
    side[rank[: int(np.argmin(conductance)) + 1]] = True
    return side


def _disagree(
    evidence: MaskEvidence,
    members: np.ndarray,
    side: np.ndarray,
    threshold: float,
    min_support: float,
) -> bool:
    """Whether the two sides of ``members`` (``side`` True / False), pooled, have an affinity
    below ``threshold`` on support above ``min_support``."""
    groups = torch.from_numpy(np.where(side, 0, 1))
    pooled = evidence.of_units(torch.from_numpy(members)).pooled(groups, 2)
    affinity, support = affinity_and_support(pooled, np.array([[0, 1]]))
    return bool(support[0] > min_support and affinity[0] < threshold)
