"""The one hierarchy type: regions of N Gaussians at levels 0–3, nested through index maps.

Modelled on Superpoint Transformer's nested acyclic graph (NAG): every level is a partition of
the Gaussians, numbered 0 … R_k − 1, and each level's regions point to the region of the next
level that holds them (``parents``, the NAG's ``super_index``). One numbering is used everywhere
in thgs — the merging, the pipeline, the field, the query engine, the evaluation and the
synthetic ground truth:

    level 0  superpoints (the graph partition; the ground truth, which has none, repeats its
             sub-parts here)
    level 1  sub-parts   (SAM's ``s`` masks)
    level 2  parts       (``m``)
    level 3  objects     (``l``)

so ``labels[:, k]`` is level k and ``parents[k − 1]`` maps level k − 1 into level k, whatever
object holds them. Features, where a container has them, are per level 1–3 at index k − 1.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from thgs.errors import InputError

__all__ = ["LEVEL_NAMES", "RegionLevels", "renumber_by_units"]

LEVEL_NAMES = ("superpoint", "subpart", "part", "object")
"""The levels' names, finest first: column k of :attr:`RegionLevels.labels` is level k."""

_NONE = -1


@dataclass(frozen=True, eq=False)
class RegionLevels:
    """The regions of N Gaussians at levels 0–3 (see the module docstring for the numbering).

    Attributes:
        labels: [N, 4] int32; ``labels[i, k]`` is the level-k region of Gaussian i, or −1 where
            the Gaussian is in no region (only ground truth has such Gaussians — its floaters —
            and they are −1 at every level).
        parents: ``parents[k − 1]`` [R_{k−1}] int32 is the level-k region holding each
            level-(k − 1) region, k = 1 … 3, so ``labels[:, k] == parents[k − 1][labels[:, k −
            1]]``; None when the levels need not nest (the merging's ``independent`` ablation).
        counts: (R_0, R_1, R_2, R_3), the number of regions at each level.
    """

    labels: np.ndarray
    parents: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    counts: tuple[int, int, int, int]

    @classmethod
    def from_labels(cls, labels: np.ndarray, *, nested: bool = True) -> RegionLevels:
        """Levels from [N, 4] integer labels (ids 0 … R_k − 1, −1 = in no region), counts taken
        from the largest id; with ``nested`` the parents are derived and checked.

        Raises:
            InputError: labels not [N, 4] integers, or ``nested`` and a level-(k − 1) region
                spread over several level-k regions.
        """
        labels = np.asarray(labels)
        if labels.ndim != 2 or labels.shape[1] != 4 or not np.issubdtype(labels.dtype, np.integer):
            raise InputError("labels", f"must be [N, 4] integers, got {_describe(labels)}")
        labels = labels.astype(np.int32)
        counts = tuple(int(labels[:, k].max(initial=_NONE)) + 1 for k in range(4))
        parents = None
        if nested:
            parents = tuple(
                _parents(labels[:, k - 1], labels[:, k], counts[k - 1]) for k in (1, 2, 3)
            )
        return cls(labels, parents, counts).check("labels")  # type: ignore[arg-type]

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    @property
    def nested(self) -> bool:
        """Whether every level-k region lies inside one level-(k + 1) region."""
        return self.parents is not None

    def sizes(self, level: int) -> np.ndarray:
        """[R_level] int64: the number of Gaussians in each region of ``level`` (0 … 3)."""
        level = self.checked_level(level)
        column = self.labels[:, level]
        return np.bincount(column[column >= 0], minlength=self.counts[level]).astype(np.int64)

    def parent(self, level: int, region: int) -> int:
        """The level + 1 region holding ``region`` of ``level`` (0 … 2); nested levels only."""
        level = self.checked_level(level, range(3))
        region = self.checked_region(level, region)
        return int(self._nested_parents()[level][region])

    def children(self, level: int, region: int) -> np.ndarray:
        """[C] int32, sorted: the level − 1 regions inside ``region`` of ``level`` (1 … 3);
        nested levels only."""
        level = self.checked_level(level, range(1, 4))
        region = self.checked_region(level, region)
        return np.flatnonzero(self._nested_parents()[level - 1] == region).astype(np.int32)

    def members(self, level: int, region: int) -> np.ndarray:
        """[M] int64, sorted: the indices of the Gaussians in ``region`` of ``level`` (0 … 3).

        Scans all N labels; to list every region's members at once, group
        ``np.argsort(labels[:, level], kind="stable")`` instead.
        """
        level = self.checked_level(level)
        region = self.checked_region(level, region)
        return np.flatnonzero(self.labels[:, level] == region).astype(np.int64)

    def checked_level(self, level: int, allowed: range = range(4)) -> int:
        """``level`` as an int after checking that it is an integer in ``allowed``.

        Raises:
            InputError: not an integer, or outside ``allowed`` (e.g. ``range(1, 4)`` for the
                levels with features).
        """
        if isinstance(level, bool) or not isinstance(level, (int, np.integer)):
            raise InputError("RegionLevels", f"level must be an integer, got {level!r}")
        if int(level) not in allowed:
            raise InputError(
                "RegionLevels",
                f"level must be in {allowed.start}..{allowed.stop - 1} here, got {level}",
            )
        return int(level)

    def checked_region(self, level: int, region: int) -> int:
        """``region`` as an int after checking that it is a region id of ``level``.

        Raises:
            InputError: not an integer, or not in 0 … R_level − 1.
        """
        if isinstance(region, bool) or not isinstance(region, (int, np.integer)):
            raise InputError("RegionLevels", f"region must be an integer, got {region!r}")
        count = self.counts[level]
        if not 0 <= int(region) < count:
            raise InputError(
                "RegionLevels", f"level {level} has regions 0..{count - 1}, got region {region}"
            )
        return int(region)

    def select(self, gaussians: np.ndarray) -> tuple[RegionLevels, tuple[np.ndarray, ...]]:
        """The levels of a subset of the Gaussians, still consistent: regions left without a
        Gaussian are dropped, the rest renumbered in their old order, parents remapped.

        Args:
            gaussians: [N] bool mask or [M] int indices of the Gaussians to keep (in that
                order).

        Returns:
            ``(levels, kept)``: the subset's levels and, per level k, ``kept[k]`` [R'_k] int64
            the old id of each new region (index a level's features with it).

        Raises:
            InputError: a mask of the wrong length or indices out of range.
        """
        index = np.asarray(gaussians)
        n = len(self)
        if index.dtype == np.bool_:
            if index.shape != (n,):
                raise InputError(
                    "gaussians", f"a mask must be [N] = [{n}], got {list(index.shape)}"
                )
            index = np.flatnonzero(index)
        elif not np.issubdtype(index.dtype, np.integer) or index.ndim != 1:
            raise InputError("gaussians", "must be an [N] bool mask or [M] integer indices")
        elif index.size and (index.min() < 0 or index.max() >= n):
            raise InputError("gaussians", f"indices must be in 0..{n - 1}")
        labels = self.labels[index]
        kept = []
        new_labels = np.full_like(labels, _NONE)
        for k in range(4):
            column = labels[:, k]
            used = np.unique(column[column >= 0]).astype(np.int64)
            renumber = np.full(self.counts[k], _NONE, dtype=np.int32)
            renumber[used] = np.arange(used.size, dtype=np.int32)
            labelled = column >= 0
            new_labels[labelled, k] = renumber[column[labelled]]
            kept.append((used, renumber))
        parents = None
        if self.parents is not None:
            parents = tuple(kept[k][1][self.parents[k - 1][kept[k - 1][0]]] for k in (1, 2, 3))
        counts = tuple(int(used.size) for used, _ in kept)
        levels = RegionLevels(new_labels, parents, counts)  # type: ignore[arg-type]
        return levels, tuple(used for used, _ in kept)

    def check(
        self,
        source: str = "RegionLevels",
        *,
        unlabelled: bool = False,
        contiguous: bool = True,
    ) -> RegionLevels:
        """Verify every invariant; raise :class:`InputError` naming ``source`` and the problem.

        Invariants: ``labels`` [N, 4] int32 with ids in 0 … R_k − 1 (−1 too with
        ``unlabelled``, at every level of a Gaussian or at none); with ``contiguous`` every
        region holds a Gaussian; ``parents`` None or three [R_{k−1}] int32 arrays of level-k
        ids, nested with the labels. Returns ``self`` to allow chaining.
        """
        labels = self.labels
        if not isinstance(labels, np.ndarray) or labels.dtype != np.int32:
            raise InputError(source, f"labels must have dtype int32, got {_describe(labels)}")
        if labels.ndim != 2 or labels.shape[1] != 4:
            raise InputError(source, f"labels must be [N, 4], got {list(labels.shape)}")
        counts = self.counts
        if len(counts) != 4 or any(isinstance(c, bool) or int(c) < 0 for c in counts):
            raise InputError(source, f"counts must be four region counts, got {counts!r}")
        parents = self.parents
        if parents is not None:
            if not isinstance(parents, tuple) or len(parents) != 3:
                raise InputError(source, "parents must be a tuple of 3 arrays (levels 1..3)")
            for k in (1, 2, 3):
                _check_parent_array(source, k, parents[k - 1], counts)
        lowest = _NONE if unlabelled else 0
        for k in range(4):
            column = labels[:, k]
            outside = (column < lowest) | (column >= counts[k])
            if outside.any():
                bad = int(np.flatnonzero(outside)[0])
                raise InputError(
                    source,
                    f"labels[:, {k}] must be in {lowest}..{counts[k] - 1}, "
                    f"Gaussian {bad} has {int(column[bad])}",
                )
            if contiguous:
                empty = np.flatnonzero(_bincount(column, counts[k]) == 0)
                if empty.size:
                    raise InputError(
                        source,
                        f"level {k} ids are not contiguous: {empty.size} of {counts[k]} regions "
                        f"have no Gaussian (first: region {int(empty[0])})",
                    )
        if unlabelled:
            none = labels < 0
            if not (none == none[:, :1]).all():
                raise InputError(source, "a Gaussian is labelled at some levels but not others")
        if parents is not None:
            for k in (1, 2, 3):
                _check_nesting(source, k, labels, parents[k - 1])
        return self

    def _nested_parents(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if self.parents is None:
            raise InputError("RegionLevels", "these levels do not nest: no parents or children")
        return self.parents


def _parents(lower: np.ndarray, upper: np.ndarray, count: int) -> np.ndarray:
    """[count] int32 level-k region of each level-(k − 1) region; −1 for one without Gaussians.

    Raises:
        InputError: a level-(k − 1) region whose Gaussians lie in several level-k regions.
    """
    labelled = lower >= 0
    parent = np.full(count, _NONE, dtype=np.int32)
    parent[lower[labelled]] = upper[labelled]
    broken = np.flatnonzero(parent[lower[labelled]] != upper[labelled])
    if broken.size:
        region = int(lower[labelled][broken[0]])
        raise InputError("labels", f"are not nested: region {region} lies in several regions")
    return parent


def _bincount(column: np.ndarray, count: int) -> np.ndarray:
    return np.bincount(column[column >= 0], minlength=count)


def _check_parent_array(source: str, k: int, parents: object, counts: Sequence[int]) -> None:
    if not isinstance(parents, np.ndarray) or parents.dtype != np.int32:
        raise InputError(
            source, f"parents[{k - 1}] must have dtype int32, got {_describe(parents)}"
        )
    if parents.ndim != 1:
        raise InputError(source, f"parents[{k - 1}] must have 1 dimension(s), got {parents.ndim}")
    if parents.shape[0] != counts[k - 1]:
        raise InputError(
            source,
            f"parents[{k - 1}] has {parents.shape[0]} entries, level {k - 1} has "
            f"{counts[k - 1]} regions",
        )
    if parents.size and (parents.min() < 0 or parents.max() >= counts[k]):
        bad = int(np.flatnonzero((parents < 0) | (parents >= counts[k]))[0])
        raise InputError(
            source,
            f"parents[{k - 1}] must be level-{k} ids in 0..{counts[k] - 1}, "
            f"region {bad} has {int(parents[bad])}",
        )


def _check_nesting(source: str, k: int, labels: np.ndarray, parents: np.ndarray) -> None:
    lower = labels[:, k - 1]
    labelled = lower >= 0
    broken = np.flatnonzero(labelled & (labels[:, k] != parents[np.maximum(lower, 0)]))
    if broken.size:
        i = int(broken[0])
        raise InputError(
            source,
            f"labels are not nested between levels {k - 1} and {k}: {broken.size} "
            f"Gaussians disagree with parents[{k - 1}] (first: Gaussian {i}, level-"
            f"{k - 1} region {int(labels[i, k - 1])} has parent "
            f"{int(parents[labels[i, k - 1]])}, label says {int(labels[i, k])})",
        )


def _describe(value: object) -> str:
    if isinstance(value, np.ndarray):
        return f"{value.dtype} array of shape {list(value.shape)}"
    return type(value).__name__


def renumber_by_units(regions: np.ndarray, units: np.ndarray) -> np.ndarray:
    """Region ids renumbered 0 … R − 1 in order of their smallest unit id (the growing order).

    Args:
        regions: [N] region id (0 … R − 1, every id used) of each Gaussian.
        units: [N] the unit (superpoint or lower-level region) id of each Gaussian.

    Returns:
        [N] int32 renumbered region ids.
    """
    count = int(regions.max()) + 1
    first_unit = np.full(count, np.iinfo(np.int64).max)
    np.minimum.at(first_unit, regions, units)
    rank = np.empty(count, dtype=np.int64)
    rank[np.argsort(first_unit, kind="stable")] = np.arange(count)
    return rank[regions].astype(np.int32)
