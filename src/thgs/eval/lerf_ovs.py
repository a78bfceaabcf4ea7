"""LERF-OVS ground-truth labels (LangSplat's release): one JSON file per evaluated frame.

Layout (ISAT's, as in LangSplat's ``label/<scene>/frame_XXXXX.json``), keys in this order::

    {"info": {"name": "frame_00053.jpg", "width": 985, "height": 725, "depth": 3, "note": ""},
     "objects": [{"category": "knife",              # the text query
                  "group": 1,                       # int: ISAT's instance group
                  "segmentation": [[x, y], ...],    # one polygon, float pixel coordinates
                  "area": 4679.0,                   # float: shoelace area of the polygon
                  "layer": 1.0,                     # float: 1.0, 2.0, ... in file order
                  "bbox": [x1, y1, x2, y2],         # floats: the polygon's min and max corners
                  "iscrowd": 0,                     # int (ISAT itself may write false)
                  "note": ""}, ...]}

The two files in ``shared/data/lerf_ovs_labels`` (teatime ``frame_00002``, waldo_kitchen
``frame_00053``) are ``json.dumps(document, indent=4)`` with CRLF line ends, every object has all
eight keys, and ``area`` is the sequentially summed shoelace area of ``segmentation``;
:func:`write_lerf_labels` reproduces them byte for byte.

Several objects can share a category (three knives); a category's mask is the union of its
objects' polygons. Coordinates refer to ``info.width × info.height``.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thgs._atomic import atomic_output
from thgs._json import get_number, load_json
from thgs.errors import InputError
from thgs.eval.polygons import rasterize_polygon

__all__ = ["FrameLabels", "LabelledObject", "read_lerf_labels", "write_lerf_labels"]


@dataclass(frozen=True)
class LabelledObject:
    """One annotated object.

    Attributes:
        category: the text query it answers.
        polygon: [K, 2] float64 (x, y) pixel coordinates at the frame's label resolution.
        bbox: (x1, y1, x2, y2) pixels, the polygon's min and max corners in LangSplat's files.
        group: ISAT's group id (an instance number within the frame; 0 when the file has none).
    """

    category: str
    polygon: np.ndarray
    bbox: tuple[float, float, float, float]
    group: int = 0


@dataclass(frozen=True)
class FrameLabels:
    """The labels of one frame.

    Attributes:
        image_name: the labelled image (e.g. ``frame_00053.jpg``).
        width, height: the resolution the coordinates refer to.
        objects: the annotated objects, in file order.
    """

    image_name: str
    width: int
    height: int
    objects: tuple[LabelledObject, ...]

    @property
    def categories(self) -> tuple[str, ...]:
        """The distinct categories in order of first appearance (the prompts of this frame)."""
        return tuple(dict.fromkeys(obj.category for obj in self.objects))

    def category_mask(
        self, category: str, height: int | None = None, width: int | None = None
    ) -> np.ndarray:
        """[H, W] bool union of the category's polygons.

        At the label resolution by default; for another render resolution pass ``height`` and
        ``width`` and the polygons are scaled by ``width / self.width`` and ``height / self.height``
        before rasterizing (never implicitly).

        Raises:
            InputError: the category is not in this frame.
        """
        if category not in self.categories:
            raise InputError(self.image_name, f"no category {category!r} (has {self.categories})")
        height = self.height if height is None else height
        width = self.width if width is None else width
        scale = np.array([width / self.width, height / self.height])
        mask = np.zeros((height, width), dtype=bool)
        for obj in self.objects:
            if obj.category == category:
                mask |= rasterize_polygon(obj.polygon * scale, height, width)
        return mask

    def category_boxes(self, category: str) -> list[tuple[float, float, float, float]]:
        """The boxes of the category's objects (label resolution), for localization accuracy."""
        return [obj.bbox for obj in self.objects if obj.category == category]


def read_lerf_labels(path: str | os.PathLike[str]) -> FrameLabels:
    """Read one LERF-OVS label JSON.

    Raises:
        InputError: unreadable JSON, missing ``info`` size or ``objects``, an object without a
            category or with an empty one, with a polygon that is not ≥ 3 finite 2-D [x, y]
            points or lies wholly outside the image, or a ``group`` that is not an integer (a
            missing or null ``group`` reads as 0, as ISAT does).
    """
    path = Path(path)
    document = load_json(path)
    if not isinstance(document, dict) or not isinstance(document.get("info"), dict):
        raise InputError(path, "expected an object with 'info' and 'objects' (LERF-OVS labels)")
    info = document["info"]
    width = get_number(info, "width", path, "info")
    height = get_number(info, "height", path, "info")
    if width <= 0 or height <= 0 or width != int(width) or height != int(height):
        raise InputError(path, f"info: size {width}×{height} is not positive integers")
    objects_json = document.get("objects")
    if not isinstance(objects_json, list):
        raise InputError(path, "no 'objects' list")
    objects = []
    for index, entry in enumerate(objects_json):
        where = f"object {index}"
        if not isinstance(entry, dict) or not isinstance(entry.get("category"), str):
            raise InputError(path, f"{where} has no 'category' string")
        if not entry["category"].strip():
            raise InputError(path, f"{where}: 'category' is empty; it is the text queried")
        try:
            polygon = np.asarray(entry.get("segmentation"), dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(path, f"{where}: 'segmentation' is not a list of points") from exc
        problem = _polygon_problem(polygon)
        if problem is not None:
            raise InputError(path, f"{where}: 'segmentation' {problem}")
        if not np.isfinite(polygon).all():
            raise InputError(path, f"{where}: 'segmentation' has NaN or infinite values")
        low, high = polygon.min(axis=0), polygon.max(axis=0)
        if high[0] <= 0 or high[1] <= 0 or low[0] >= width or low[1] >= height:
            raise InputError(
                path,
                f"{where} ({entry['category']!r}): 'segmentation' lies wholly outside the "
                f"{width:g}×{height:g} image (x {low[0]:g} to {high[0]:g}, y {low[1]:g} to "
                f"{high[1]:g}), so its mask would be empty",
            )
        bbox = entry.get("bbox")
        if bbox is None:
            low, high = polygon.min(axis=0), polygon.max(axis=0)
            bbox = [low[0], low[1], high[0], high[1]]
        if (
            not isinstance(bbox, (list, tuple))
            or len(bbox) != 4
            or not all(
                isinstance(v, (int, float, np.floating)) and not isinstance(v, bool) for v in bbox
            )
            or not np.isfinite(np.asarray(bbox, dtype=np.float64)).all()
        ):
            raise InputError(path, f"{where}: 'bbox' must be [x1, y1, x2, y2], finite numbers")
        group = entry.get("group")
        if group is None:
            group = 0
        if isinstance(group, bool) or not isinstance(group, int):
            raise InputError(path, f"{where}: 'group' is {group!r}, not an integer")
        box = tuple(float(v) for v in bbox)
        objects.append(LabelledObject(entry["category"], polygon, box, group))  # type: ignore[arg-type]
    return FrameLabels(str(info.get("name", path.stem)), int(width), int(height), tuple(objects))


def _polygon_problem(polygon: np.ndarray) -> str | None:
    """What is wrong with a polygon that should be [P ≥ 3, 2] (x, y) pixel coordinates, or None."""
    if polygon.ndim != 2:
        return f"must be a list of [x, y] points, got an array of shape {list(polygon.shape)}"
    if polygon.shape[1] != 2:
        return f"must hold 2-D [x, y] points, got {polygon.shape[1]}-D points"
    if len(polygon) < 3:
        return f"must have at least 3 points, got {len(polygon)}"
    return None


def _shoelace_area(polygon: np.ndarray) -> float:
    """|½ Σ x_i·y_{i+1} − x_{i+1}·y_i| in pixels², summed in vertex order as ISAT does.

    Sequential summation (``cumsum``, not numpy's pairwise ``sum``) reproduces the ``area`` values
    of LangSplat's files exactly, not just to rounding.
    """
    x, y = polygon[:, 0], polygon[:, 1]
    terms = x * np.roll(y, -1) - np.roll(x, -1) * y
    return abs(float(np.cumsum(terms)[-1])) / 2


def write_lerf_labels(path: str | os.PathLike[str], labels: FrameLabels) -> None:
    """Write one frame's labels in the ISAT layout of LangSplat's release, atomically.

    Keys, value types, indentation (4 spaces) and line ends (CRLF) are those of the real files (see
    the module docstring): ``info`` holds ``name`` (``labels.image_name``), ``width``, ``height``,
    ``depth`` = 3 and ``note`` = ""; each object holds its ``category``, ``group``,
    ``segmentation`` (the polygon as floats), ``area`` (its shoelace area, pixels²), ``layer``
    (1.0, 2.0, ... in order), ``bbox`` (the polygon's [min x, min y, max x, max y]),
    ``iscrowd`` = 0 and ``note`` = "". Non-ASCII categories are written as UTF-8, as ISAT does.
    Reading a file of that release and writing it back reproduces it byte for byte.

    Raises:
        InputError: a size that is not positive, a category that is not a string, a polygon that
            is not ≥ 3 finite [x, y] points, or an object whose ``bbox`` is not its polygon's
            bounds (nothing is written then).
    """
    source = f"labels to write to {os.fspath(path)}"
    if labels.width <= 0 or labels.height <= 0:
        raise InputError(source, f"size {labels.width}×{labels.height} is not positive")
    objects = []
    for index, obj in enumerate(labels.objects):
        if not isinstance(obj.category, str):
            raise InputError(source, f"object {index}: category {obj.category!r} is not a string")
        polygon = np.asarray(obj.polygon, dtype=np.float64)
        problem = _polygon_problem(polygon)
        if problem is not None:
            raise InputError(source, f"object {index}: the polygon {problem}")
        if not np.isfinite(polygon).all():
            raise InputError(source, f"object {index}: the polygon has NaN or infinite values")
        low, high = polygon.min(axis=0), polygon.max(axis=0)
        bbox = [float(low[0]), float(low[1]), float(high[0]), float(high[1])]
        if [float(v) for v in obj.bbox] != bbox:
            raise InputError(
                source, f"object {index}: bbox {list(obj.bbox)} is not the polygon's bounds {bbox}"
            )
        objects.append(
            {
                "category": obj.category,
                "group": int(obj.group),
                "segmentation": polygon.tolist(),
                "area": _shoelace_area(polygon),
                "layer": float(index + 1),
                "bbox": bbox,
                "iscrowd": 0,
                "note": "",
            }
        )
    document = {
        "info": {
            "name": labels.image_name,
            "width": int(labels.width),
            "height": int(labels.height),
            "depth": 3,
            "note": "",
        },
        "objects": objects,
    }
    text = json.dumps(document, indent=4, ensure_ascii=False).replace("\n", "\r\n")
    with atomic_output(path, "wb") as handle:
        handle.write(text.encode("utf-8"))
