"""Scores of a segmentation of the Gaussians against ground truth."""

from __future__ import annotations

import numpy as np

from thgs.errors import InputError

__all__ = ["best_iou", "matched_miou", "purity"]


def _checked(name: str, labels: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``labels`` and ``truth`` as arrays, after checking they are [N] ids ≥ −1."""
    labels = np.asarray(labels)
    truth = np.asarray(truth)
    if labels.shape != truth.shape or labels.ndim != 1:
        raise InputError(name, f"labels {labels.shape} and truth {truth.shape} must be [N]")
    if (labels.size and labels.min() < -1) or (truth.size and truth.min() < -1):
        raise InputError(name, "ids must be ≥ −1")
    return labels, truth


def purity(labels: np.ndarray, truth: np.ndarray) -> float:
    """The share of Gaussians whose region's majority ground-truth node is their own.

    Each region (a value ≥ 0 of ``labels``) is assigned the ground-truth node that most of its
    Gaussians with ground truth belong to; a Gaussian counts as pure
    when that node is its own. Gaussians without ground truth (``truth`` −1, e.g. floaters) are
    left out entirely; Gaussians in no region (``labels`` −1) count as impure. 1.0 means no
    region straddles two nodes; it says nothing about over-segmentation (one region per
    Gaussian is pure), so report the region count beside it.

    Args:
        labels: [N] integer region id per Gaussian, −1 = none.
        truth: [N] integer ground-truth node per Gaussian at one level, −1 = none.

    Returns:
        purity in [0, 1]; 1.0 if no Gaussian has ground truth.

    Raises:
        InputError: shapes differ or ids below −1.
    """
    labels, truth = _checked("purity", labels, truth)
    keep = truth >= 0
    if not keep.any():
        return 1.0
    regions, truth = labels[keep].astype(np.int64), truth[keep].astype(np.int64)
    inside = regions >= 0
    nodes = int(truth.max()) + 1
    pairs, counts = np.unique(regions[inside] * nodes + truth[inside], return_counts=True)
    majority = np.zeros(int(regions.max()) + 1 if inside.any() else 0, dtype=np.int64)
    np.maximum.at(majority, pairs // nodes, counts)
    return float(majority.sum() / keep.sum())


def best_iou(labels: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """For every ground-truth node, the IoU of the region that overlaps it best.

    Regions are matched to ground truth one node at a time (a region may be the best match of
    several nodes): node t scores ``max_r |r ∩ t| / |r ∪ t|`` over regions r. Gaussians without
    ground truth (``truth`` −1, e.g. floaters) are left out of every region and node; Gaussians
    in no region (``labels`` −1) count in their node only. Splitting a node into halves scores
    0.5; merging two equal nodes scores 0.5 for each.

    Args:
        labels: [N] integer region id per Gaussian, −1 = none.
        truth: [N] integer ground-truth node per Gaussian at one level, −1 = none.

    Returns:
        [T] float64 with T = ``truth.max() + 1``; nodes without Gaussians score NaN.

    Raises:
        InputError: shapes differ or ids below −1.
    """
    labels, truth = _checked("best_iou", labels, truth)
    nodes = int(truth.max()) + 1 if truth.size else 0
    keep = truth >= 0
    regions, truth = labels[keep].astype(np.int64), truth[keep].astype(np.int64)
    node_sizes = np.bincount(truth, minlength=nodes).astype(np.float64)
    inside = regions >= 0
    best = np.zeros(nodes)
    if inside.any():
        region_sizes = np.bincount(regions[inside]).astype(np.float64)
        pairs, overlap = np.unique(regions[inside] * nodes + truth[inside], return_counts=True)
        region, node = pairs // nodes, pairs % nodes
        iou = overlap / (node_sizes[node] + region_sizes[region] - overlap)
        np.maximum.at(best, node, iou)
    best[node_sizes == 0] = np.nan
    return best


def matched_miou(labels: np.ndarray, truth: np.ndarray) -> float:
    """The mean over ground-truth nodes of :func:`best_iou` (nodes without Gaussians skipped).

    The per-level agreement of a hierarchy with ground truth: level k's regions against the
    level-k nodes. 1.0 only when every node is exactly one region.
    """
    scores = best_iou(labels, truth)
    scores = scores[~np.isnan(scores)]
    return float(scores.mean()) if scores.size else 1.0
