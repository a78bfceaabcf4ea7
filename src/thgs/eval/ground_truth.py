"""Per-Gaussian hierarchy ground truth (the synthetic benchmark's answer key).

Three nested levels, finest first, matching the method's merged levels 1/2/3 and SAM's s/m/l:
sub-part, part, object. In memory they are a :class:`thgs.hierarchy.RegionLevels` in the one
level numbering (level 1 sub-parts, 2 parts, 3 objects; level 0, the superpoints the ground
truth does not have, repeats the sub-parts). Stored as one safetensors file::

    labels          int32 [N, 3]   node id per Gaussian at levels 1, 2, 3, −1 = none (floaters)
    subpart_parent  int32 [S]      part id of each sub-part
    part_parent     int32 [P]      object id of each part
    metadata        {"thgs": JSON {"format": "thgs.hierarchy", "version": "1",
                                   "names": [[sub-part names], [part names], [object names]]}}

(One metadata key: safetensors writes metadata from a hash map, so several keys would come out in
a different order on every run and the same hierarchy would not give the same bytes.)

Names are the text at each level ("bear nose", "bear head", "teddy bear"); several nodes may
share a name (two mugs are both "mug"). The file is written atomically.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thgs._atomic import atomic_output
from thgs.errors import InputError
from thgs.hierarchy.levels import LEVEL_NAMES, RegionLevels

__all__ = ["Hierarchy", "read_hierarchy", "write_hierarchy"]

_FORMAT = "thgs.hierarchy"
_VERSION = "1"


@dataclass(frozen=True, eq=False)
class Hierarchy:
    """Nested ground-truth labels of N Gaussians.

    Attributes:
        levels: the nodes as regions (:class:`thgs.hierarchy.RegionLevels`, −1 = floaters,
            which are in no node): ``levels.labels[:, k]`` is the level-k node (k = 1 sub-part,
            2 part, 3 object; column 0 repeats column 1), ``levels.parents[k − 1]`` the level-k
            node of each level-(k − 1) node. A node may hold no Gaussian.
        names: level k = 1..3 → the text name of every level-k node.
    """

    levels: RegionLevels
    names: Mapping[int, tuple[str, ...]]

    @classmethod
    def from_subparts(
        cls,
        subparts: np.ndarray,
        subpart_parent: np.ndarray,
        part_parent: np.ndarray,
        names: Sequence[Sequence[str]],
        source: str = "Hierarchy",
    ) -> Hierarchy:
        """The hierarchy defined by each Gaussian's sub-part and the node tree.

        Args:
            subparts: [N] int sub-part of each Gaussian, −1 = none (floaters).
            subpart_parent: [S] int part of each sub-part.
            part_parent: [P] int object of each part.
            names: the sub-part, part and object names (S, P and O of them).
            source: what to name in errors.

        Raises:
            InputError: ids out of range or parent arrays that do not match the names.
        """
        if len(names) != 3:
            raise InputError(source, "names must list three levels (sub-part, part, object)")
        counts = tuple(len(level) for level in names)
        subparts = np.asarray(subparts)
        subpart_parent = np.asarray(subpart_parent).astype(np.int32)
        part_parent = np.asarray(part_parent).astype(np.int32)
        if subpart_parent.shape != (counts[0],) or part_parent.shape != (counts[1],):
            raise InputError(source, "parent arrays do not match the number of names per level")
        parents = (np.arange(counts[0], dtype=np.int32), subpart_parent, part_parent)
        for k, (parent, upper) in enumerate(zip(parents[1:], counts[1:]), start=2):
            if parent.size and (parent.min() < 0 or parent.max() >= upper):
                raise InputError(
                    source,
                    f"{LEVEL_NAMES[k - 1]} parents must be {LEVEL_NAMES[k]} ids in 0..{upper - 1}",
                )
        if subparts.ndim != 1 or (
            subparts.size and (subparts.min() < -1 or subparts.max() >= counts[0])
        ):
            raise InputError(source, f"subpart ids outside [-1, {counts[0]})")
        labels = np.full((len(subparts), 4), -1, dtype=np.int32)
        has = subparts >= 0
        labels[has, 0] = labels[has, 1] = subparts[has]
        labels[has, 2] = subpart_parent[subparts[has]]
        labels[has, 3] = part_parent[labels[has, 2]]
        levels = RegionLevels(labels, parents, (counts[0], *counts))  # type: ignore[arg-type]
        named = {k: tuple(str(name) for name in names[k - 1]) for k in (1, 2, 3)}
        return cls(levels, named).check(source)

    def __len__(self) -> int:
        return len(self.levels)

    @property
    def labels(self) -> np.ndarray:
        """[N, 4] int32 node per Gaussian at levels 0–3 (0 repeats 1), −1 = none."""
        return self.levels.labels

    def level_names(self, level: int) -> np.ndarray:
        """[N] object array: the name of each Gaussian's node at ``level`` (1 = sub-part,
        2 = part, 3 = object), or None where it has none."""
        level = self.levels.checked_level(level, range(1, 4))
        names = np.array([*self.names[level], None], dtype=object)
        return names[self.labels[:, level]]

    def select(self, gaussians: np.ndarray) -> Hierarchy:
        """The ground truth of a subset of the Gaussians (:meth:`RegionLevels.select`): nodes
        left without a Gaussian are dropped with their names.

        Args:
            gaussians: [N] bool mask or [M] int indices of the Gaussians to keep.
        """
        levels, kept = self.levels.select(gaussians)
        names = {k: tuple(self.names[k][i] for i in kept[k]) for k in (1, 2, 3)}
        return Hierarchy(levels, names)

    def check(self, source: str = "Hierarchy") -> Hierarchy:
        """Raise :class:`InputError` unless shapes, ranges, names and nesting are consistent."""
        levels = self.levels
        if not isinstance(levels, RegionLevels) or levels.parents is None:
            raise InputError(source, "levels must be nested RegionLevels")
        levels.check(source, unlabelled=True, contiguous=False)
        if sorted(self.names) != [1, 2, 3]:
            raise InputError(source, "names must be given for levels 1, 2 and 3")
        for k in (1, 2, 3):
            if len(self.names[k]) != levels.counts[k]:
                raise InputError(
                    source,
                    f"{len(self.names[k])} {LEVEL_NAMES[k]} names for {levels.counts[k]} nodes",
                )
        if not (levels.labels[:, 0] == levels.labels[:, 1]).all():
            raise InputError(source, "level 0 must repeat the sub-parts")
        return self


def write_hierarchy(path: str | os.PathLike[str], hierarchy: Hierarchy) -> None:
    """Write ``hierarchy`` as one safetensors file, atomically.

    Raises:
        InputError: the hierarchy fails :meth:`Hierarchy.check` (nothing is written).
    """
    from safetensors.numpy import save

    path = Path(path)
    hierarchy.check(source=f"hierarchy to write to {path}")
    parents = hierarchy.levels.parents
    assert parents is not None  # check() requires nested levels
    tensors = {
        "labels": np.ascontiguousarray(hierarchy.labels[:, 1:], dtype=np.int32),
        "subpart_parent": np.ascontiguousarray(parents[1], dtype=np.int32),
        "part_parent": np.ascontiguousarray(parents[2], dtype=np.int32),
    }
    header = {
        "format": _FORMAT,
        "version": _VERSION,
        "names": [list(hierarchy.names[k]) for k in (1, 2, 3)],
    }
    data = save(tensors, metadata={"thgs": json.dumps(header, sort_keys=True)})
    with atomic_output(path) as handle:
        handle.write(data)


def read_hierarchy(path: str | os.PathLike[str]) -> Hierarchy:
    """Read a file written by :func:`write_hierarchy`.

    Raises:
        InputError: the file is missing, not a thgs hierarchy, or inconsistent.
    """
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "ground-truth hierarchy file not found")
    try:
        with safe_open(str(path), framework="numpy") as handle:
            metadata = handle.metadata() or {}
            tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    except SafetensorError as error:
        raise InputError(path, f"not a safetensors file ({error})") from error
    try:
        header = json.loads(metadata["thgs"])
    except (KeyError, json.JSONDecodeError) as error:
        raise InputError(path, "not a thgs hierarchy file (no 'thgs' metadata)") from error
    if not isinstance(header, dict) or header.get("format") != _FORMAT:
        raise InputError(path, "not a thgs hierarchy file")
    missing = {"labels", "subpart_parent", "part_parent"} - set(tensors)
    if missing:
        raise InputError(path, f"missing tensors {sorted(missing)}")
    names = header.get("names")
    if not (isinstance(names, list) and len(names) == 3):
        raise InputError(path, "metadata 'names' must list three levels")
    labels = tensors["labels"]
    if labels.ndim != 2 or labels.shape[1] != 3:
        raise InputError(path, f"labels must be [N, 3], got {list(labels.shape)}")
    hierarchy = Hierarchy.from_subparts(
        labels[:, 0], tensors["subpart_parent"], tensors["part_parent"], names, source=str(path)
    )
    stored = labels.astype(np.int32)
    if not ((stored < 0) == (stored[:, :1] < 0)).all():
        raise InputError(path, "a Gaussian is labelled at some levels but not others")
    if not np.array_equal(stored, hierarchy.labels[:, 1:]):
        raise InputError(path, "labels are not nested (a node's parent disagrees)")
    return hierarchy
