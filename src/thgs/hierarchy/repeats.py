"""Repeated parts: one level-2 region for the alike pieces of an object that do not touch.

A table's four legs, a chair's legs, a teddy bear's two ears are one part each, but they touch
only through another part (the top, the seat, the head), and no SAM mask shows them together:
a point on one leg gives that leg. The paper's merging joins touching regions only, so it ends
with one part per leg. Ours (not in the paper) groups them after the last merging pass, using
the level-2 features (the ``m`` masks' features, :mod:`thgs.features`):

two level-2 regions a and b of one object (level-3 region) join when

- they do not touch (touching ones had their chance in the merging),
- they look alike: ``cos(f_a, f_b) ≥ similarity`` (0.8), and
- they are more alike than either is to some region c of the same object that both touch:
  ``cos(f_a, f_b) − max(cos(f_a, f_c), cos(f_b, f_c)) ≥ margin`` (0.1).

The last condition is what makes it a repeated part: the legs are alike and unlike the top they
hang from, while the books of a stack are as alike as the book between them (and stay apart).
Joined pairs are grouped transitively (connected components). Levels 0, 1 and 3 do not change,
so the levels still nest.

The cosines are those of the features as they are (``compare="raw"``, the default) or of their
residuals (``"residual"``, :func:`residual_part_features`): each part's feature centred on the
mean of the scene's seen parts, with its object's direction taken out. Features like CLIP's
share much between every crop (one common direction) and between the parts of one object (a
leg looks like its table): with the raw features every pair of parts is then alike and no
difference reaches the margin, so nothing is grouped; the residuals keep what tells one part
of an object from another.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from thgs.errors import InputError
from thgs.graph.knn import MAX_NEIGHBOURS
from thgs.hierarchy.adjacency import gaussian_neighbors, unit_graph
from thgs.hierarchy.levels import RegionLevels
from thgs.hierarchy.merge import renumber_by_units
from thgs.scene.gaussians import Gaussians

__all__ = ["RepeatConfig", "group_repeated_parts", "repeated_part_pairs", "residual_part_features"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class RepeatConfig:
    """When alike, non-touching parts of one object become one part (ours; not in the paper).

    Attributes:
        enabled: group them (ours True; the reference False: one part per connected piece).
        similarity: the least feature cosine of two pieces, in (0, 1] (0.8).
        margin: how much more alike the two pieces must be than either is to a part both touch,
            in [0, 2) (0.1).
        neighbors: k of the 3-D Gaussian KNN (itself included) that defines touching regions
            (8, as the merging).
        compare: the cosines of the level-2 features as they are (``"raw"``) or of their
            residuals within their object (``"residual"``, :func:`residual_part_features`;
            measured with ``similarity`` 0.3 and ``margin`` 0.2, docs/build.md).
    """

    enabled: bool = True
    similarity: float = 0.8
    margin: float = 0.1
    neighbors: int = 8
    compare: Literal["raw", "residual"] = "raw"

    def __post_init__(self) -> None:
        if self.compare not in ("raw", "residual"):
            raise InputError(
                "RepeatConfig.compare", f"must be 'raw' or 'residual', got {self.compare!r}"
            )
        if not 0.0 < self.similarity <= 1.0:
            raise InputError("RepeatConfig", f"similarity must be in (0, 1], got {self.similarity}")
        if not 0.0 <= self.margin < 2.0:
            raise InputError("RepeatConfig", f"margin must be in [0, 2), got {self.margin}")
        if not 2 <= self.neighbors <= MAX_NEIGHBOURS:
            raise InputError(
                "RepeatConfig.neighbors",
                f"must be from 2 to {MAX_NEIGHBOURS:,}, got {self.neighbors:,}",
            )


def _pairs_within_rows(indptr: np.ndarray, indices: np.ndarray):
    """All (row, i, j) with i < j two column indices of one CSR row: [T] arrays each."""
    degree = np.diff(indptr)
    row_of = np.repeat(np.arange(degree.size), degree)
    entry = np.arange(indices.size)
    later = indptr[row_of + 1] - entry - 1  # entries after this one in its row
    first = np.repeat(entry, later)
    offset = np.arange(first.size) - np.repeat(np.cumsum(later) - later, later)
    second = first + 1 + offset
    return row_of[first], indices[first], indices[second]


def repeated_part_pairs(
    touching: np.ndarray, objects: np.ndarray, features: np.ndarray, config: RepeatConfig
) -> np.ndarray:
    """The pairs of parts that :func:`group_repeated_parts` joins.

    Args:
        touching: [E, 2] int pairs of level-2 regions that touch (either order, any repeats).
        objects: [R] int level-3 region of every level-2 region.
        features: [R, D] float level-2 features, unit rows or zero rows (never seen: such a
            region joins nothing).
        config: thresholds.

    Returns:
        [P, 2] int64 pairs (a < b), sorted.
    """
    count = len(objects)
    touching = np.asarray(touching, dtype=np.int64).reshape(-1, 2)
    a, b = touching[:, 0], touching[:, 1]
    keep = (a != b) & (objects[a] == objects[b])
    a, b = a[keep], b[keep]
    adjacency = coo_matrix(
        (np.ones(2 * a.size), (np.concatenate([a, b]), np.concatenate([b, a]))),
        shape=(count, count),
    ).tocsr()
    adjacency.sum_duplicates()
    adjacency.sort_indices()
    via, first, second = _pairs_within_rows(adjacency.indptr, adjacency.indices)
    if via.size == 0:
        return np.zeros((0, 2), dtype=np.int64)
    features = np.asarray(features, dtype=np.float64)
    alike = np.einsum("td,td->t", features[first], features[second])
    to_via = np.maximum(
        np.einsum("td,td->t", features[first], features[via]),
        np.einsum("td,td->t", features[second], features[via]),
    )
    apart = np.asarray(adjacency[first, second]).ravel() == 0
    joined = apart & (alike >= config.similarity) & (alike - to_via >= config.margin)
    pairs = np.unique(np.stack([first[joined], second[joined]], axis=1), axis=0)
    return pairs.reshape(-1, 2).astype(np.int64)


def _unit_rows(vectors: np.ndarray, shortest: float = 0.0) -> np.ndarray:
    """The rows made unit; rows not longer than ``shortest`` become zero rows."""
    norms = np.linalg.norm(vectors, axis=1, keepdims=True)
    return np.divide(vectors, norms, out=np.zeros_like(vectors), where=norms > shortest)


def residual_part_features(
    part_features: np.ndarray, object_features: np.ndarray, objects: np.ndarray
) -> np.ndarray:
    """What tells the parts of one object apart: each seen part's feature minus the mean of the
    seen parts' features, with its object's direction (the object's feature minus that mean,
    unit) projected out, unit again.

    Args:
        part_features: [R_2, D] level-2 features, unit rows or zero rows (never seen).
        object_features: [R_3, D] level-3 features, unit rows or zero rows (never seen: nothing
            is projected out of its parts).
        objects: [R_2] int level-3 region of every level-2 region.

    Returns:
        [R_2, D] float64 unit rows; zero rows for parts never seen and for parts with nothing
        left (their feature is the object's), which join nothing.
    """
    parts = np.asarray(part_features, dtype=np.float64)
    seen = np.abs(parts).sum(axis=1) > 0
    if not seen.any():
        return np.zeros_like(parts)
    mean = parts[seen].mean(axis=0)
    centred = _unit_rows(parts - mean)
    whole = np.asarray(object_features, dtype=np.float64)
    whole_seen = np.abs(whole).sum(axis=1) > 0
    direction = np.where(whole_seen[:, None], _unit_rows(whole - mean), 0.0)[objects]
    residual = centred - np.einsum("rd,rd->r", centred, direction)[:, None] * direction
    # what is left of a part lying along its object's direction is rounding: nothing
    return np.where(seen[:, None], _unit_rows(residual, shortest=1e-9), 0.0)


def group_repeated_parts(
    gaussians: Gaussians,
    levels: RegionLevels,
    part_features: np.ndarray,
    config: RepeatConfig = RepeatConfig(),
    *,
    neighbors: np.ndarray | None = None,
    object_features: np.ndarray | None = None,
) -> RegionLevels:
    """The levels with the repeated parts of every object grouped at level 2.

    Args:
        gaussians: the N Gaussians (their centres define which regions touch).
        levels: nested levels 0–3 of the N Gaussians (:func:`merge_levels`' ``levels``).
        part_features: [R_2, D] float features of its level-2 regions (unit or zero rows,
            :func:`thgs.features.region_features` at level 2).
        config: thresholds; ``enabled`` False returns ``levels`` unchanged.
        neighbors: the [N, config.neighbors] output of
            :func:`thgs.hierarchy.gaussian_neighbors`, when the caller has it.
        object_features: [R_3, D] features of the level-3 regions (unit or zero rows), needed
            by ``config.compare`` ``"residual"``.

    Returns:
        nested :class:`RegionLevels`: levels 0, 1, 3 as given; level 2 with joined regions,
        numbered in order of their smallest level-1 region.

    Raises:
        InputError: levels that do not nest or are not of these Gaussians, features not
            [R_2, D], or object features missing or not [R_3, D] where ``compare`` needs them.
    """
    labels = levels.labels
    n = len(gaussians)
    if levels.parents is None or labels.shape != (n, 4):
        raise InputError("levels", f"must be nested levels of the {n} Gaussians")
    parts = labels[:, 2].astype(np.int64)
    count = levels.counts[2]
    part_features = np.asarray(part_features)
    if part_features.ndim != 2 or len(part_features) != count:
        raise InputError("part_features", f"must be [R_2, D] with R_2 = {count} level-2 regions")
    if not config.enabled:
        return levels
    if config.compare == "residual":
        shape = (levels.counts[3], part_features.shape[1])
        if object_features is None or np.shape(object_features) != shape:
            raise InputError(
                "object_features",
                f"must be [R_3, D] = {list(shape)} level-3 features for compare='residual'",
            )
        part_features = residual_part_features(part_features, object_features, levels.parents[2])
    if neighbors is None:
        neighbors = gaussian_neighbors(gaussians, config.neighbors)
    elif neighbors.shape != (n, config.neighbors):
        raise InputError("neighbors", f"must be [N, k] = [{n}, {config.neighbors}]")
    graph = unit_graph(parts, neighbors, count)
    touching = graph.pairs[graph.hops == 1]
    pairs = repeated_part_pairs(touching, levels.parents[2], part_features, config)
    joined = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(count, count))
    groups, group = connected_components(joined, directed=False)
    out = labels.copy()
    out[:, 2] = renumber_by_units(group[parts], labels[:, 1])
    log.info("repeated parts: %d level-2 regions grouped into %d", count, groups)
    return RegionLevels.from_labels(out)
