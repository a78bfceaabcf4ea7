"""Per-Gaussian hierarchy ground truth (the synthetic benchmark's answer key).

Three nested levels, finest first, matching the method's merged levels 1/2/3 and SAM's s/m/l:
sub-part, part, object. Stored as one safetensors file::

    labels          int32 [N, 3]   node id per Gaussian at each level, −1 = none (floaters)
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
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thgs._atomic import atomic_output
from thgs.errors import InputError

__all__ = ["HIERARCHY_LEVELS", "Hierarchy", "read_hierarchy", "write_hierarchy"]

HIERARCHY_LEVELS = ("subpart", "part", "object")
"""Ground-truth levels, finest first: column k of :attr:`Hierarchy.labels` is level k + 1."""

_FORMAT = "thgs.hierarchy"
_VERSION = "1"


@dataclass(frozen=True, eq=False)
class Hierarchy:
    """Nested ground-truth labels of N Gaussians.

    Attributes:
        labels: [N, 3] int32 node ids per level (:data:`HIERARCHY_LEVELS` order), −1 = none.
        names: per level, the text name of every node at that level.
        subpart_parent: [S] int32 part id of each sub-part.
        part_parent: [P] int32 object id of each part.
    """

    labels: np.ndarray
    names: tuple[tuple[str, ...], tuple[str, ...], tuple[str, ...]]
    subpart_parent: np.ndarray
    part_parent: np.ndarray

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def level_names(self, level: int) -> np.ndarray:
        """[N] object array: the name of each Gaussian's node at ``level`` (0 = sub-part), or
        None where it has none."""
        names = np.array([*self.names[level], None], dtype=object)
        return names[self.labels[:, level]]

    def check(self, source: str = "Hierarchy") -> Hierarchy:
        """Raise :class:`InputError` unless shapes, ranges and nesting are consistent."""
        labels = self.labels
        if labels.ndim != 2 or labels.shape[1] != 3:
            raise InputError(source, f"labels must be [N, 3], got {list(labels.shape)}")
        sizes = [len(level) for level in self.names]
        if self.subpart_parent.shape != (sizes[0],) or self.part_parent.shape != (sizes[1],):
            raise InputError(source, "parent arrays do not match the number of names per level")
        for level, size in enumerate(sizes):
            column = labels[:, level]
            if column.size and (column.min() < -1 or column.max() >= size):
                raise InputError(source, f"{HIERARCHY_LEVELS[level]} ids outside [-1, {size})")
        if len(self.subpart_parent) and (
            self.subpart_parent.min() < 0 or self.subpart_parent.max() >= sizes[1]
        ):
            raise InputError(source, "a sub-part's parent is not a part")
        if len(self.part_parent) and (
            self.part_parent.min() < 0 or self.part_parent.max() >= sizes[2]
        ):
            raise InputError(source, "a part's parent is not an object")
        labelled = labels >= 0
        if not (labelled == labelled[:, :1]).all():
            raise InputError(source, "a Gaussian is labelled at some levels but not others")
        has = labelled[:, 0]
        if (
            not (self.subpart_parent[labels[has, 0]] == labels[has, 1]).all()
            or not (self.part_parent[labels[has, 1]] == labels[has, 2]).all()
        ):
            raise InputError(source, "labels are not nested (a node's parent disagrees)")
        return self


def write_hierarchy(path: str | os.PathLike[str], hierarchy: Hierarchy) -> None:
    """Write ``hierarchy`` as one safetensors file, atomically.

    Raises:
        InputError: the hierarchy fails :meth:`Hierarchy.check` (nothing is written).
    """
    from safetensors.numpy import save

    path = Path(path)
    hierarchy.check(source=f"hierarchy to write to {path}")
    tensors = {
        "labels": np.ascontiguousarray(hierarchy.labels, dtype=np.int32),
        "subpart_parent": np.ascontiguousarray(hierarchy.subpart_parent, dtype=np.int32),
        "part_parent": np.ascontiguousarray(hierarchy.part_parent, dtype=np.int32),
    }
    header = {
        "format": _FORMAT,
        "version": _VERSION,
        "names": [list(level) for level in hierarchy.names],
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
    hierarchy = Hierarchy(
        labels=tensors["labels"].astype(np.int32),
        names=tuple(tuple(str(name) for name in level) for level in names),  # type: ignore[arg-type]
        subpart_parent=tensors["subpart_parent"].astype(np.int32),
        part_parent=tensors["part_parent"].astype(np.int32),
    )
    return hierarchy.check(source=str(path))
