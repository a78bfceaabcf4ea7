"""ScanNet per-point class labels, as OpenGaussian's ScanNet protocol uses them.

The protocol fixes the Gaussians to the scan's points: Gaussian i is vertex i of the scene's
``<scene>_vh_clean_2.labels.ply``, whose ``label`` property is the ground truth.

The file (ScanNet README: "Visualization of aggregated semantic segmentation; colored by nyu40
labels (see img/legend; ply property 'label' denotes the nyu40 label id)"; header as quoted in
cnr-isti-vclab/meshlab issue #498, "comment MLIB generated")::

    ply
    format binary_little_endian 1.0
    element vertex N
    property float x            world frame of the scan, metres
    property float y
    property float z
    property uchar red          the NYU40 legend colour of the label
    property uchar green
    property uchar blue
    property uchar alpha
    property ushort label       NYU40 class id 1-40, 0 = unannotated
    element face M
    property list uchar int vertex_indices
    end_header

OpenGaussian's ``scripts/eval_scannet.py`` (github.com/yanmin-wu/OpenGaussian; read in the copy
github.com/zhgulden/OpenGaussian-) reads ``x, y, z``
and ``label`` with plyfile and evaluates one of three class subsets (``target_id``):

- 19 classes: the ScanNet benchmark's 20 (``BenchmarkScripts/3d_evaluation/
  evaluate_semantic_label.py``: ids 1-12, 14, 16, 24, 28, 33, 34, 36, 39) without
  ``otherfurniture`` (39);
- 15: the 19 without picture (11), refrigerator (24), shower curtain (28) and bathtub (36);
- 10: the 15 without cabinet (3), counter (12), desk (14), curtain (16) and sink (34).

It remaps the chosen ids to 1…K (everything else to 0 = ignored), drops points whose Gaussian has
opacity < 0.1, and averages IoU and accuracy over the classes present in the scene's ground truth.
Its query texts are its NYU40 table's names, which spell id 28 ``"showercurtain"``;
:data:`SCANNET19_NAMES` uses the ScanNet benchmark's ``"shower curtain"``.

A synthetic scene's classes are not NYU40: :func:`write_scannet_labels` then also writes the class
table to ``<file without .ply>.classes.json`` (``{"id": "name"}``), which
:func:`read_scannet_labels` reads when present.
"""

from __future__ import annotations

import json
import os
import types
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import plyfile

from thgs._atomic import atomic_output
from thgs._json import load_json
from thgs.errors import InputError
from thgs.scene.ply import read_ply_data

__all__ = [
    "SCANNET10_IDS",
    "SCANNET15_IDS",
    "SCANNET19_IDS",
    "SCANNET19_NAMES",
    "PointLabels",
    "read_scannet_labels",
    "scannet_classes_path",
    "write_scannet_labels",
]

SCANNET19_NAMES: Mapping[int, str] = types.MappingProxyType(
    {
        1: "wall",
        2: "floor",
        3: "cabinet",
        4: "bed",
        5: "chair",
        6: "sofa",
        7: "table",
        8: "door",
        9: "window",
        10: "bookshelf",
        11: "picture",
        12: "counter",
        14: "desk",
        16: "curtain",
        24: "refrigerator",
        28: "shower curtain",
        33: "toilet",
        34: "sink",
        36: "bathtub",
    }
)
"""NYU40 id → name of the 19 ScanNet classes OpenGaussian evaluates (read-only)."""

SCANNET19_IDS: tuple[int, ...] = tuple(SCANNET19_NAMES)
"""The 19 evaluated NYU40 ids, ascending."""

SCANNET15_IDS: tuple[int, ...] = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 12, 14, 16, 33, 34)
"""The 15-class subset: the 19 without picture, refrigerator, shower curtain and bathtub."""

SCANNET10_IDS: tuple[int, ...] = (1, 2, 4, 5, 6, 7, 8, 9, 10, 33)
"""The 10-class subset: the 15 without cabinet, counter, desk, curtain and sink."""

_MAX_LABEL = np.iinfo(np.uint16).max
_GREY = 128
_VERTEX_DTYPE = np.dtype(
    [
        ("x", "<f4"),
        ("y", "<f4"),
        ("z", "<f4"),
        ("red", "u1"),
        ("green", "u1"),
        ("blue", "u1"),
        ("alpha", "u1"),
        ("label", "<u2"),
    ]
)


@dataclass(frozen=True, eq=False)
class PointLabels:
    """Per-point class labels of a scan.

    Attributes:
        points: [N, 3] float32 point positions, world frame, scene units (metres for ScanNet).
        labels: [N] int64 class id per point, 0 = unannotated, at most 65535 (ushort).
        class_names: class id → name (the text query). Ids without a name (e.g. NYU40 ids outside
            the 19 evaluated classes) are not evaluated; 0 never has a name.
    """

    points: np.ndarray
    labels: np.ndarray
    class_names: dict[int, str]

    def check(self, source: str = "PointLabels") -> PointLabels:
        """Verify the invariants above; raise :class:`InputError` naming ``source``."""
        points, labels = self.points, self.labels
        if not isinstance(points, np.ndarray) or points.ndim != 2 or points.shape[1] != 3:
            raise InputError(source, f"points must be [N, 3], got {np.shape(points)}")
        if points.dtype != np.float32:
            raise InputError(source, f"points must be float32, got {points.dtype}")
        if not np.isfinite(points).all():
            raise InputError(source, "points have NaN or infinite values")
        if not isinstance(labels, np.ndarray) or labels.shape != (len(points),):
            raise InputError(source, f"labels must be [{len(points)}], got {np.shape(labels)}")
        if labels.dtype != np.int64:
            raise InputError(source, f"labels must be int64, got {labels.dtype}")
        if len(labels) and (labels.min() < 0 or labels.max() > _MAX_LABEL):
            raise InputError(
                source, f"labels range over [{labels.min()}, {labels.max()}], not [0, {_MAX_LABEL}]"
            )
        for class_id, name in self.class_names.items():
            if isinstance(class_id, bool) or not isinstance(class_id, int):
                raise InputError(source, f"class id {class_id!r} is not an integer")
            if not 0 < class_id <= _MAX_LABEL:
                raise InputError(
                    source, f"class id {class_id} is outside 1-{_MAX_LABEL} (0 = unannotated)"
                )
            if not isinstance(name, str) or not name:
                raise InputError(source, f"class {class_id} has no name: {name!r}")
        return self


def scannet_classes_path(path: str | os.PathLike[str]) -> Path:
    """The class-name sidecar of a label PLY: ``x.labels.ply`` → ``x.labels.classes.json``."""
    return Path(path).with_suffix(".classes.json")


def _read_class_names(path: Path) -> dict[int, str]:
    document = load_json(path)
    if not isinstance(document, dict):
        raise InputError(path, 'expected an object {"id": "name", ...}')
    names: dict[int, str] = {}
    for key, name in document.items():
        try:
            class_id = int(key)
        except ValueError:
            raise InputError(path, f"key {key!r} is not an integer class id") from None
        if str(class_id) != key or not 0 < class_id <= _MAX_LABEL:
            raise InputError(path, f"key {key!r} is not a class id in 1-{_MAX_LABEL}")
        if not isinstance(name, str) or not name:
            raise InputError(path, f"class {key}: name {name!r} is not a non-empty string")
        names[class_id] = name
    return names


def read_scannet_labels(
    path: str | os.PathLike[str], class_names: dict[int, str] | None = None
) -> PointLabels:
    """Read a ScanNet ``*_vh_clean_2.labels.ply`` (or one written by :func:`write_scannet_labels`).

    Args:
        path: the PLY file (binary or ASCII); only its ``vertex`` element's ``x, y, z, label`` are
            used (colours and faces are ignored).
        class_names: id → name; by default the sidecar ``<file without .ply>.classes.json`` if it
            exists, else :data:`SCANNET19_NAMES` (the NYU40 names of the 19 evaluated classes).

    Returns:
        :class:`PointLabels`: float32 points, int64 labels, the class table.

    Raises:
        InputError: the file is missing or not a PLY; no ``vertex`` element; no ``x``, ``y``, ``z``
            or ``label`` property; a label that is not a whole number in 0-65535; a point with NaN
            or infinite coordinates; a malformed sidecar. The message names the file.
    """
    path = Path(path)
    vertex = read_ply_data(path)["vertex"]
    names = [prop.name for prop in vertex.properties]
    missing = [name for name in ("x", "y", "z", "label") if name not in names]
    if missing:
        raise InputError(
            path,
            f"no vertex properties {missing}; a ScanNet label PLY has x y z red green blue "
            "alpha label (ushort NYU40 id)",
        )
    data = vertex.data
    raw = np.asarray(data["label"])
    if not np.issubdtype(raw.dtype, np.integer):
        if not np.array_equal(raw, np.round(raw)):
            raise InputError(path, f"'label' has non-integer values ({raw.dtype})")
    labels = raw.astype(np.int64)
    if len(labels) and (labels.min() < 0 or labels.max() > _MAX_LABEL):
        raise InputError(
            path, f"'label' ranges over [{labels.min()}, {labels.max()}], not [0, {_MAX_LABEL}]"
        )
    points = np.stack([data["x"], data["y"], data["z"]], axis=1).astype(np.float32)
    if not np.isfinite(points).all():
        raise InputError(path, "points have NaN or infinite coordinates")
    if class_names is None:
        sidecar = scannet_classes_path(path)
        class_names = _read_class_names(sidecar) if sidecar.is_file() else dict(SCANNET19_NAMES)
    return PointLabels(points, labels, dict(class_names)).check(source=str(path))


def write_scannet_labels(path: str | os.PathLike[str], labels: PointLabels) -> None:
    """Write ``labels`` as a ScanNet-style label PLY, atomically, plus a class sidecar if needed.

    The PLY is binary little-endian with ScanNet's vertex properties and types (``float x, y, z``,
    ``uchar red, green, blue, alpha``, ``ushort label``), one vertex per point in order, colour a
    fixed opaque grey (128, 128, 128, 255) and no ``face`` element (the points stand for
    Gaussians, not a mesh).

    Unless ``labels.class_names`` is exactly :data:`SCANNET19_NAMES`, the table is also written to
    :func:`scannet_classes_path` (``{"id": "name"}``, ids ascending), before the PLY; with the
    default table a sidecar left by an earlier write is removed. Reading the result with
    :func:`read_scannet_labels` gives back the same points, labels and class table.

    Raises:
        InputError: ``labels`` fails :meth:`PointLabels.check` (nothing is written then).
    """
    labels.check(source=f"labels to write to {os.fspath(path)}")
    records = np.empty(len(labels.points), dtype=_VERTEX_DTYPE)
    for axis, name in enumerate("xyz"):
        records[name] = labels.points[:, axis]
    records["red"] = records["green"] = records["blue"] = _GREY
    records["alpha"] = 255
    records["label"] = labels.labels
    sidecar = scannet_classes_path(path)
    if dict(labels.class_names) != dict(SCANNET19_NAMES):
        table = {str(k): labels.class_names[k] for k in sorted(labels.class_names)}
        with atomic_output(sidecar, "wb") as handle:
            handle.write((json.dumps(table, indent=2, ensure_ascii=False) + "\n").encode("utf-8"))
    elif sidecar.is_file():
        sidecar.unlink()
    element = plyfile.PlyElement.describe(records, "vertex")
    with atomic_output(path, "wb") as handle:
        plyfile.PlyData([element], text=False, byte_order="<").write(handle)
