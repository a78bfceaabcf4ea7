"""LERF-OVS ground-truth labels (LangSplat's release): one JSON file per evaluated frame.

Layout (ISAT-style)::

    {"info": {"name": "frame_00053.jpg", "width": 985, "height": 725, ...},
     "objects": [{"category": "knife", "group": 1,
                  "segmentation": [[x, y], ...],      # one polygon, pixel coordinates
                  "bbox": [x1, y1, x2, y2], "area": ..., "iscrowd": 0 | false, ...}, ...]}

Several objects can share a category (three knives); a category's mask is the union of its
objects' polygons. Coordinates refer to ``info.width × info.height``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from thgs.errors import InputError
from thgs.eval.polygons import rasterize_polygon
from thgs.scene._json import get_number, load_json

__all__ = ["FrameLabels", "LabelledObject", "read_lerf_labels"]


@dataclass(frozen=True)
class LabelledObject:
    """One annotated object: its category, polygon [K, 2] (x, y pixels) and box (x1, y1, x2, y2)."""

    category: str
    polygon: np.ndarray
    bbox: tuple[float, float, float, float]


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
            category or with a polygon of fewer than 3 finite points.
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
        try:
            polygon = np.asarray(entry.get("segmentation"), dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(path, f"{where}: 'segmentation' is not a list of points") from exc
        if polygon.ndim != 2 or polygon.shape[1] != 2 or len(polygon) < 3:
            raise InputError(path, f"{where}: 'segmentation' must be ≥ 3 [x, y] points")
        if not np.isfinite(polygon).all():
            raise InputError(path, f"{where}: 'segmentation' has NaN or infinite values")
        bbox = entry.get("bbox")
        if bbox is None:
            low, high = polygon.min(axis=0), polygon.max(axis=0)
            bbox = [low[0], low[1], high[0], high[1]]
        if len(bbox) != 4:
            raise InputError(path, f"{where}: 'bbox' must be [x1, y1, x2, y2]")
        objects.append(LabelledObject(entry["category"], polygon, tuple(float(v) for v in bbox)))  # type: ignore[arg-type]
    return FrameLabels(str(info.get("name", path.stem)), int(width), int(height), tuple(objects))
