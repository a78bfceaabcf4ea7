"""Mask evidence per unit and the affinity of unit pairs (design §4.6), on the lifts' device.

A *source* is one view's labels at one SAM level: the Gaussians that carry a label there, their
mask ids and optionally a weight per label. For unit u and source s the evidence is the weighted
histogram ``h_u^s`` of mask ids over u's labelled Gaussians and the labelled share ``s_u^s =
Σ h_u^s / |u|``. The affinity of two units is

    A(a, b) = Σ_s s_a^s s_b^s cos(h_a^s, h_b^s) / Σ_s s_a^s s_b^s    (0 without common evidence)

which is the ratio of two dot products: of the rows ``X_u[(s, m)] = s_u^s · h_u^s[m] / |h_u^s|``
and of the rows ``Y_u[s] = s_u^s``. :class:`MaskEvidence` keeps the histograms of every source in
one sparse table, so that pooling units into regions (a merging round) is one segment sum and the
affinity of P pairs is one sorted join, however many views there are.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

__all__ = ["MaskEvidence", "Source", "affinity_and_support", "mask_evidence", "pair_affinity"]

Source = tuple[Tensor, ...]
"""One view's labels at one level: ([n] Gaussian indices, [n] mask ids, −1 = none) and optionally
[n] non-negative weights of the labels (1 when absent), int64 / float64 tensors on one device."""

_DENSE_MAX = 1 << 24
"""Largest units × masks table a source's histogram is summed in; larger ones are sorted."""

_JOIN_CHUNK = 1 << 23
"""Entries looked up at once when pairs are joined (bounds the join's memory)."""


@dataclass(frozen=True, eq=False)
class MaskEvidence:
    """Per (unit, source, mask) the summed label weight, and the units' sizes.

    Attributes:
        units: [E] int64 unit of each entry; entries sorted by (unit, column), each pair once.
        columns: [E] int64 ``source · masks + mask``.
        weights: [E] float64 positive summed weights ``h_u^s[m]``.
        sizes: [U] float64 Gaussians per unit.
        masks: the column stride (largest mask id + 1 over all sources).
        sources: how many sources.
    """

    units: Tensor
    columns: Tensor
    weights: Tensor
    sizes: Tensor
    masks: int
    sources: int

    @property
    def count(self) -> int:
        return len(self.sizes)

    def pooled(self, groups: Tensor, count: int) -> MaskEvidence:
        """The evidence of ``count`` regions made of these units: ``groups`` [U] int64 region of
        each unit; histograms and sizes add up."""
        groups = groups.to(self.units.device)
        sizes = torch.zeros(count, dtype=torch.float64, device=self.sizes.device)
        sizes.index_add_(0, groups, self.sizes)
        units, columns, weights = _summed(
            groups[self.units], self.columns, self.weights, self.masks * self.sources
        )
        return MaskEvidence(units, columns, weights, sizes, self.masks, self.sources)

    def of_units(self, units: Tensor) -> MaskEvidence:
        """The evidence of ``units`` [M] int64 (distinct ids) alone, renumbered 0 … M − 1 in
        that order; reads only their entries."""
        units = units.to(self.units.device)
        bounds = torch.searchsorted(self.units, torch.stack([units, units + 1]))
        lengths = bounds[1] - bounds[0]
        offsets = torch.cumsum(lengths, 0) - lengths
        entries = torch.arange(int(lengths.sum()), device=units.device)
        entries += torch.repeat_interleave(bounds[0] - offsets, lengths)
        rows = torch.repeat_interleave(torch.arange(len(units), device=units.device), lengths)
        return MaskEvidence(
            rows,
            self.columns[entries],
            self.weights[entries],
            self.sizes[units],
            self.masks,
            self.sources,
        )


def _summed(rows: Tensor, columns: Tensor, weights: Tensor, width: int) -> tuple[Tensor, ...]:
    """Duplicate (row, column) entries summed, sorted by (row, column)."""
    keys, inverse = torch.unique(rows * width + columns, return_inverse=True)
    sums = torch.zeros(len(keys), dtype=weights.dtype, device=weights.device)
    sums.index_add_(0, inverse, weights)
    return keys // width, keys % width, sums


def _source_histogram(
    units: Tensor, count: int, source: Source
) -> tuple[Tensor, Tensor, Tensor] | None:
    """(unit, mask, weight) of one source, summed per (unit, mask), or None if it has no label."""
    gaussians, labels = source[0], source[1]
    labelled = labels >= 0
    if len(source) > 2:
        labelled &= source[2] > 0
    if not bool(labelled.any()):
        return None
    unit = units[gaussians[labelled]]
    mask = labels[labelled]
    weight = (
        source[2][labelled].double()
        if len(source) > 2
        else torch.ones(len(unit), dtype=torch.float64, device=unit.device)
    )
    low = int(mask.min())
    width = int(mask.max()) - low + 1
    if count * width <= _DENSE_MAX:
        table = torch.bincount(unit * width + (mask - low), weights=weight, minlength=count * width)
        keys = torch.nonzero(table)[:, 0]
        return keys // width, keys % width + low, table[keys]
    rows, columns, sums = _summed(unit, mask - low, weight, width)
    return rows, columns + low, sums


def mask_evidence(units: Tensor, count: int, sources: Iterable[Source]) -> MaskEvidence:
    """The evidence of ``count`` units from the sources' labels.

    Args:
        units: [N] int64 unit id of every Gaussian, 0 … count − 1, on the sources' device.
        count: U.
        sources: the views' labels at one level (:data:`Source`), read once, one at a time
            (each source's histogram is all that is kept of it).
    """
    device = units.device
    sizes = torch.bincount(units, minlength=count).double()
    parts = [_source_histogram(units, count, source) for source in sources]
    source_count = len(parts)
    masks = 1 + max((int(part[1].max()) for part in parts if part is not None), default=0)
    found = [(index, part) for index, part in enumerate(parts) if part is not None]
    if not found:
        empty = torch.zeros(0, dtype=torch.int64, device=device)
        return MaskEvidence(empty, empty, empty.double(), sizes, masks, source_count)
    rows = torch.cat([part[0] for _, part in found])
    columns = torch.cat([index * masks + part[1] for index, part in found])
    weights = torch.cat([part[2] for _, part in found])
    width = masks * source_count
    order = torch.argsort(rows * width + columns)
    return MaskEvidence(rows[order], columns[order], weights[order], sizes, masks, source_count)


def _pair_dots(units: Tensor, columns: Tensor, values: Tensor, count: int, pairs: Tensor) -> Tensor:
    """[P] ``Σ_c M[a, c] · M[b, c]`` of a sparse matrix M given as entries sorted by (unit,
    column), for every pair (a, b): a's entries looked up among b's."""
    out = torch.zeros(len(pairs), dtype=values.dtype, device=values.device)
    if len(units) == 0 or len(pairs) == 0:
        return out
    width = int(columns.max()) + 1
    keys = units * width + columns
    starts = torch.searchsorted(units, torch.arange(count + 1, device=units.device))
    lengths = starts[pairs[:, 0] + 1] - starts[pairs[:, 0]]
    chunk_ends = torch.cumsum(lengths, 0)
    first = 0
    while first < len(pairs):
        base = int(chunk_ends[first - 1]) if first else 0
        last = int(torch.searchsorted(chunk_ends, base + _JOIN_CHUNK, right=True))
        last = max(last, first + 1)
        chunk = torch.arange(first, last, device=units.device)
        size = lengths[chunk]
        pair = torch.repeat_interleave(chunk, size)
        offsets = torch.cumsum(size, 0) - size
        within = torch.arange(len(pair), device=units.device) - torch.repeat_interleave(
            offsets, size
        )
        entry = starts[pairs[pair, 0]] + within
        target = pairs[pair, 1] * width + columns[entry]
        at = torch.searchsorted(keys, target).clamp(max=len(keys) - 1)
        hit = keys[at] == target
        out.index_add_(0, pair[hit], values[entry[hit]] * values[at[hit]])
        first = last
    return out


def pair_affinity(
    evidence: MaskEvidence, pairs: Tensor | np.ndarray, min_support: float = 0.0
) -> np.ndarray:
    """``A(a, b) = Σ_s s_a s_b cos(h_a, h_b) / Σ_s s_a s_b`` for every pair, 0 without evidence.

    Args:
        evidence: the units' :class:`MaskEvidence`.
        pairs: [P, 2] int unit pairs.
        min_support: the pair's *support* ``Σ_s s_a s_b`` (in views where both units are
            wholly labelled) must exceed this, or the pair counts as without evidence (0): a
            ratio of two vanishing sums says nothing, yet can be 1.

    Returns:
        [P] float64 affinities in [0, 1] (on the CPU: they drive the region growing there).
    """
    affinity, support = affinity_and_support(evidence, pairs)
    return np.where(support > min_support, affinity, 0.0)


def affinity_and_support(
    evidence: MaskEvidence, pairs: Tensor | np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """[P] float64 affinities (as :func:`pair_affinity` with ``min_support`` 0) and [P] float64
    supports ``Σ_s s_a s_b`` of the pairs, on the CPU."""
    device = evidence.units.device
    pairs = torch.as_tensor(np.asarray(pairs), dtype=torch.int64, device=device).reshape(-1, 2)
    if len(evidence.units) == 0:
        return np.zeros(len(pairs)), np.zeros(len(pairs))
    # per (unit, source): the histogram's sum and norm
    source = evidence.columns // evidence.masks
    groups, group = torch.unique_consecutive(
        evidence.units * evidence.sources + source, return_inverse=True
    )
    totals = torch.zeros(len(groups), dtype=torch.float64, device=device)
    totals.index_add_(0, group, evidence.weights)
    squares = torch.zeros(len(groups), dtype=torch.float64, device=device)
    squares.index_add_(0, group, evidence.weights**2)
    group_unit = groups // evidence.sources
    share = totals / evidence.sizes[group_unit].clamp_min(1.0)
    normalized = evidence.weights * (share / torch.sqrt(squares))[group]
    count = evidence.count
    numerator = _pair_dots(evidence.units, evidence.columns, normalized, count, pairs)
    denominator = _pair_dots(group_unit, groups % evidence.sources, share, count, pairs)
    supported = denominator > 0
    affinity = torch.where(supported, numerator / torch.where(supported, denominator, 1.0), 0.0)
    return affinity.cpu().numpy(), denominator.cpu().numpy()
