"""SAM-guided reweighting of the KNN edges (design §4.4).

Every view votes on every KNN edge whose two ends carry a mask label in that view: the same mask
says "same segment" (a positive count), different masks say "different segments" (a negative
count), each vote weighted by a decay with the depth of the edge's source Gaussian. After all views
the counts are capped, and :func:`reweight` lengthens edges with negative votes and shortens edges
with positive ones before the partition turns distances into edge weights.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
import torch
from torch import Tensor

from thgs.errors import InputError
from thgs.graph.knn import KnnGraph
from thgs.lift import ViewLift

__all__ = ["ReweightConfig", "ReweightMode", "edge_counts", "reweight"]

log = logging.getLogger(__name__)

ReweightMode = Literal["relative", "absolute", "none"]


@dataclass(frozen=True)
class ReweightConfig:
    """How mask evidence changes the KNN distances. Cap and depth law are the reference's.

    The defaults are ours (relative offsets tuned on the synthetic benchmark, docs/partition.md);
    :meth:`reference` gives the authors' absolute offsets.

    Attributes:
        mode: how the offsets enter the squared 6-D distances d (scene units²):
            ``"relative"`` (ours, default): ``d' = max(0, d + d̄ · (negative_offset · neg −
            positive_offset · pos))`` with ``d̄`` the mean of d over all present edges, so the
            offsets are multiples of the typical edge and the effect does not depend on the
            scene's scale; ``"absolute"`` (the reference): ``d' = max(0, d + negative_offset · neg −
            positive_offset · pos)``, offsets in scene units²; ``"none"`` (ablation): d' = d.
        level: the mask level whose labels vote, as a column of ``ViewLift.labels`` (0 default,
            1 s, 2 m, 3 l); the reference uses s (1).
        depth_decay: weight each vote by ``f(z) = 1 / (1 + max(0, z − depth_start))`` with z the
            source Gaussian's camera-space depth (scene units) in that view; False is the "fixed
            weights" ablation, f = 1.
        depth_start: depth (scene units) up to which votes count fully (5.0).
        cap: after all views, both counts are clamped to [0, cap] (25, in votes).
        negative_offset: distance added per negative vote: multiples of the mean squared edge
            distance d̄ in relative mode (10: one disagreeing vote makes an edge ~11 times the
            typical one), scene units² in absolute mode (reference 0.1).
        positive_offset: distance removed per positive vote, same units as ``negative_offset``
            (relative 2, reference 0.02; the reference's 5 : 1 ratio is kept).
        min_max_weight: a Gaussian votes in a view only if its ``max_x w(x)`` there is at least
            this (0.0: every labelled Gaussian votes, as in the reference, where the lifting's
            confidence threshold already decides what is labelled). Applies to both ends of an
            edge. Raising it keeps Gaussians seen only through an occluder from voting, but on
            the synthetic benchmark 0.05 did not raise purity (docs/partition.md).
    """

    mode: ReweightMode = "relative"
    level: int = 1
    depth_decay: bool = True
    depth_start: float = 5.0
    cap: float = 25.0
    negative_offset: float = 10.0
    positive_offset: float = 2.0
    min_max_weight: float = 0.0

    @classmethod
    def reference(cls) -> ReweightConfig:
        """The authors' reweighting: absolute offsets 0.1 / 0.02 (scene units²), level s."""
        return cls(mode="absolute", negative_offset=0.1, positive_offset=0.02)

    def __post_init__(self) -> None:
        if self.mode not in ("relative", "absolute", "none"):
            raise InputError(
                "ReweightConfig", f"mode must be relative, absolute or none, got {self.mode!r}"
            )
        if self.level not in (0, 1, 2, 3):
            raise InputError("ReweightConfig", f"level must be 0, 1, 2 or 3, got {self.level}")
        if not (self.cap >= 0 and self.negative_offset >= 0 and self.positive_offset >= 0):
            raise InputError("ReweightConfig", "cap and both offsets must be ≥ 0")
        if not (np.isfinite(self.depth_start) and 0 <= self.min_max_weight <= 1):
            raise InputError(
                "ReweightConfig", "depth_start must be finite and min_max_weight in [0, 1]"
            )


@numba.njit(nogil=True, cache=True)
def _count_view(neighbors, gaussians, labels, votes, dense, pos, neg):  # pragma: no cover
    """Add one view's votes on the CPU: ``dense`` is an all −1 [N] scratch array, restored on
    return. The same sums as the torch path of :func:`edge_counts`, in the same order."""
    n = gaussians.shape[0]
    for t in range(n):
        dense[gaussians[t]] = labels[t]
    for t in range(n):
        label = labels[t]
        if label < 0:
            continue
        i = gaussians[t]
        vote = votes[t]
        for k in range(neighbors.shape[1]):
            j = neighbors[i, k]
            if j < 0:
                continue
            other = dense[j]
            if other < 0:
                continue
            if other == label:
                pos[i, k] += vote
            else:
                neg[i, k] += vote
    for t in range(n):
        dense[gaussians[t]] = -1


def _view_votes(view: ViewLift, config: ReweightConfig) -> tuple[Tensor, Tensor, Tensor]:
    """A view's voting Gaussians: [n] indices, [n] int32 labels (−1 = no vote) and [n] float32
    votes ``f(z)``."""
    labels = view.labels[:, config.level].int()
    if config.min_max_weight > 0:
        labels = torch.where(view.max_weights >= config.min_max_weight, labels, -1)
    if config.depth_decay:
        votes = 1.0 / (1.0 + (view.depths.float() - config.depth_start).clamp_min(0))
    else:
        votes = torch.ones(len(view), dtype=torch.float32, device=view.device)
    return view.gaussians.long(), labels, votes


def _count_view_torch(
    neighbors: Tensor,
    view: ViewLift,
    config: ReweightConfig,
    dense: Tensor,
    pos: Tensor,
    neg: Tensor,
) -> None:
    """Add one view's votes with tensor operations on any device (``neighbors`` has −1 replaced
    by N, ``dense`` [N + 1] is all −1 and restored on return)."""
    gaussians, labels, votes = _view_votes(view, config)
    voting = labels >= 0
    sources, own = gaussians[voting], labels[voting]
    dense[gaussians] = labels
    other = dense[neighbors[sources]]
    same = other == own[:, None]
    pos[sources] += votes[voting][:, None] * same
    neg[sources] += votes[voting][:, None] * ((other >= 0) & ~same)
    dense[gaussians] = -1


def edge_counts(
    graph: KnnGraph, views: Sequence[ViewLift], config: ReweightConfig = ReweightConfig()
) -> tuple[np.ndarray, np.ndarray]:
    """Depth-weighted votes of all views on every directed KNN edge.

    For every view and every edge ``i → j = graph.neighbors[i, k]`` whose ends both carry a label
    ≥ 0 at ``config.level`` in that view (and, if set, reach ``config.min_max_weight``): add
    ``f(z_i)`` to ``pos[i, k]`` if the labels are equal, to ``neg[i, k]`` otherwise, with ``z_i``
    the depth of ``i`` in that view. Then clamp both to [0, cap]. The edge ``j → i``, if present,
    collects its own votes, weighted by ``f(z_j)``.

    The votes are counted on the views' device: a compiled loop on the CPU, one gather of the
    voting Gaussians' neighbours per view elsewhere (the same sums in the same order); the counts
    come back to the CPU, where the graph is cut.

    Args:
        graph: the [N, K] KNN graph.
        views: the lifted masks of each view (sparse: only the Gaussians the view sees), all on
            one device.
        config: level, depth law, cap and visibility threshold.

    Returns:
        ``(pos, neg)``, each [N, K] float32 in [0, cap], in votes; zero at missing edges.
        Deterministic: each entry sums its views in the given order.
    """
    started = time.perf_counter()
    n = len(graph)
    graph.check(n, source="edge_counts graph")  # the kernel indexes without bounds checks
    device = views[0].device if views else torch.device("cpu")
    for index, view in enumerate(views):
        view.check(n, source=f"view {index}")
        if view.device != device:
            raise InputError(f"view {index}", f"is on {view.device}, view 0 on {device}")
    if device.type == "cpu":
        neighbors = np.ascontiguousarray(graph.neighbors)
        pos = np.zeros(neighbors.shape, dtype=np.float32)
        neg = np.zeros(neighbors.shape, dtype=np.float32)
        dense = np.full(n, -1, dtype=np.int32)
        for view in views:
            gaussians, labels, votes = _view_votes(view, config)
            _count_view(
                neighbors, gaussians.numpy(), labels.numpy(), votes.numpy(), dense, pos, neg
            )
    else:
        targets = torch.from_numpy(np.ascontiguousarray(graph.neighbors)).to(device).long()
        targets = torch.where(targets >= 0, targets, n)
        pos_t = torch.zeros(targets.shape, dtype=torch.float32, device=device)
        neg_t = torch.zeros(targets.shape, dtype=torch.float32, device=device)
        dense_t = torch.full((n + 1,), -1, dtype=torch.int32, device=device)
        for view in views:
            _count_view_torch(targets, view, config, dense_t, pos_t, neg_t)
        pos, neg = pos_t.cpu().numpy(), neg_t.cpu().numpy()
    np.minimum(pos, config.cap, out=pos)
    np.minimum(neg, config.cap, out=neg)
    log.info(
        "edge votes: %d views, %d edges with positive and %d with negative votes in %.2f s",
        len(views),
        int(np.count_nonzero(pos)),
        int(np.count_nonzero(neg)),
        time.perf_counter() - started,
    )
    return pos, neg


def reweight(
    graph: KnnGraph,
    pos: np.ndarray,
    neg: np.ndarray,
    config: ReweightConfig = ReweightConfig(),
) -> np.ndarray:
    """Edge distances after the votes: [N, K] float32 squared 6-D distances (scene units²).

    ``absolute``: ``d' = max(0, d + a·neg − b·pos)``; ``relative``: ``d' = max(0, d + d̄·(a·neg −
    b·pos))`` with ``d̄`` the mean of ``graph.distances`` over present edges; ``none``: ``d' = d``.
    ``a``, ``b`` are ``config.negative_offset`` and ``config.positive_offset``; ``pos``, ``neg``
    come from :func:`edge_counts`. Missing edges stay ``inf``.
    """
    if pos.shape != graph.neighbors.shape or neg.shape != graph.neighbors.shape:
        raise InputError(
            "reweight",
            f"pos {pos.shape} and neg {neg.shape} must match the graph's {graph.neighbors.shape}",
        )
    if config.mode == "none":
        return graph.distances.copy()
    valid = graph.valid()
    distances = graph.distances.astype(np.float64)
    offsets = config.negative_offset * neg.astype(np.float64)
    offsets -= config.positive_offset * pos.astype(np.float64)
    if config.mode == "relative":
        offsets *= distances[valid].mean() if valid.any() else 0.0
    changed = np.maximum(distances + offsets, 0.0)
    return np.where(valid, changed, np.inf).astype(np.float32)
