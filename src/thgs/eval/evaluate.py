"""The benchmark protocols run on a segmentation of one scene (design §6).

Each ``evaluate_*`` function takes the query engine (:class:`thgs.query.FieldQuery`: text →
Gaussians), the scene's Gaussians and cameras, and the benchmark's ground truth as the readers in
:mod:`thgs.eval` return it, and gives a :class:`ProtocolResult`: the protocol's headline
numbers and one item per scored (frame, prompt), (view, class) or class, so that every number
can be traced. The per-image and per-point rules are in :mod:`thgs.eval.rules`.

- ``lerf`` (THGS / P-3D): the reference selection (levels 2 and 3, top 3 each, best 3 kept)
  rendered as accumulated opacity and thresholded at 0.5, against the union of the category's
  polygons; IoU and pixel accuracy averaged over the prompts of a frame, then over frames.
- ``lerf-opengaussian``: the same with the silhouette threshold 0.7, prompts restricted to
  OpenGaussian's lists when the scene is one of its four; flat means over (frame, prompt).
- ``lerf-langsplat`` (P-2D): per level the rendered relevancy map, LangSplat's smoothing,
  normalization and threshold, the level with the highest smoothed peak; mIoU and localization
  accuracy as flat means over (frame, prompt).
- ``3dovs``: the ``lerf`` rule on 3D-OVS's per-class masks; "wood wall" is queried as "wood".
- ``openhype``: the ``lerf`` rule on OpenHype's ScanNet++ object and part masks; mIoU and
  localization accuracy as OpenHype averages them, flat over (frame, prompt), also per kind.
- ``scannet``: every Gaussian classified by the best-matching class text; mIoU and mAcc per
  class subset.
- ``hierarchy`` (synthetic): matched-region mIoU of levels 1–3 against the ground-truth
  sub-parts, parts and objects, and superpoint purity.

Masks are rendered at the camera's resolution; LERF polygons and boxes are scaled from the label
resolution to it. 3D-OVS and OpenHype masks cannot be rescaled without loss, so those views are
rendered at the masks' resolution (intrinsics scaled per axis).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from thgs.errors import InputError
from thgs.eval.ground_truth import Hierarchy
from thgs.eval.lerf_ovs import FrameLabels, read_lerf_labels
from thgs.eval.metrics import matched_miou, purity
from thgs.eval.openhype import OpenHypeFrame, openhype_views
from thgs.eval.rules import (
    OPENGAUSSIAN_LERF_PROMPTS,
    OPENGAUSSIAN_THRESHOLD,
    langsplat_query,
    mask_iou,
    openhype_localized,
    pixel_accuracy,
    scannet_scores,
)
from thgs.eval.scannet import (
    SCANNET10_IDS,
    SCANNET15_IDS,
    SCANNET19_IDS,
    SCANNET19_NAMES,
    PointLabels,
)
from thgs.eval.three_dovs import SegmentationSet, query_text
from thgs.field_scene import find_view
from thgs.hierarchy.levels import LEVEL_NAMES, RegionLevels
from thgs.query import FieldQuery
from thgs.render import RasterConfig
from thgs.scene import Cameras, Gaussians
from thgs.views import relevancy_map, selection_masks

__all__ = [
    "ProtocolResult",
    "evaluate_3dovs",
    "evaluate_hierarchy",
    "evaluate_lerf",
    "evaluate_lerf_langsplat",
    "evaluate_lerf_opengaussian",
    "evaluate_openhype",
    "evaluate_scannet",
    "frame_mean",
    "read_lerf_frames",
    "scannet_subsets",
]

logger = logging.getLogger(__name__)

Progress = Callable[[int, int], None]


@dataclass(frozen=True)
class ProtocolResult:
    """The scores of one protocol on one scene.

    Attributes:
        protocol: its name (``lerf``, ``lerf-langsplat``, ``lerf-opengaussian``, ``3dovs``,
            ``scannet-19`` …, ``hierarchy``).
        metrics: the headline numbers, in [0, 1] (e.g. ``miou``, ``accuracy``).
        items: one JSON-ready dict per scored unit: ``{"frame", "prompt", "iou", ...}``.
        settings: what the protocol was run with (thresholds, levels, prompt lists).
        notes: what a reader of the numbers must know, one sentence each (e.g. which prompt
            list applied and why); reports print them under the table.
    """

    protocol: str
    metrics: dict[str, float]
    items: list[dict[str, Any]] = field(default_factory=list)
    settings: dict[str, Any] = field(default_factory=dict)
    notes: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        """JSON values; NaN (a class absent from the ground truth) becomes null."""
        return {
            "protocol": self.protocol,
            "metrics": _finite(self.metrics),
            "settings": self.settings,
            "notes": list(self.notes),
            "items": [_finite(item) for item in self.items],
        }


def _finite(values: Mapping[str, Any]) -> dict[str, Any]:
    return {
        key: None if isinstance(value, float) and not math.isfinite(value) else value
        for key, value in values.items()
    }


def frame_mean(items: Sequence[Mapping[str, Any]], key: str, group: str = "frame") -> float:
    """Mean over groups (frames, views) of the mean of ``key`` over each group's items: the
    THGS averaging, so a frame with many prompts weighs as much as one with few. NaN if empty."""
    groups: dict[Any, list[float]] = {}
    for item in items:
        groups.setdefault(item[group], []).append(float(item[key]))
    if not groups:
        return float("nan")
    return float(np.mean([np.mean(values) for values in groups.values()]))


def read_lerf_frames(folder: str | os.PathLike[str]) -> list[tuple[str, FrameLabels]]:
    """Every ``*.json`` label file of one LERF-OVS scene as ``(stem, labels)``, by file name.

    The stem (``frame_00053``) names the view the frame belongs to.

    Raises:
        InputError: the folder is missing or holds no JSON file, or a file is malformed.
    """
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(folder, "LERF-OVS label folder not found")
    paths = sorted(p for p in folder.iterdir() if p.suffix == ".json" and p.is_file())
    if not paths:
        raise InputError(folder, "holds no LERF-OVS label files (frame_XXXXX.json)")
    return [(path.stem, read_lerf_labels(path)) for path in paths]


def _lerf_prompts(frame: FrameLabels, prompts: Sequence[str] | None) -> list[str]:
    categories = list(frame.categories)
    return categories if prompts is None else [c for c in categories if c in prompts]


def evaluate_lerf(
    engine: FieldQuery,
    gaussians: Gaussians,
    cameras: Cameras,
    frames: Sequence[tuple[str, FrameLabels]],
    *,
    protocol: str = "lerf",
    mask_threshold: float = 0.5,
    prompts: Sequence[str] | None = None,
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
    rescale_labels: bool = False,
) -> ProtocolResult:
    """The THGS LERF-OVS protocol (``lerf``), or OpenGaussian's with ``mask_threshold`` 0.7.

    Args:
        engine: the query engine (:class:`thgs.query.FieldQuery`; its config is the selection
            rule).
        gaussians: the N Gaussians the engine indexes.
        cameras: the scene's cameras; frame ``stem`` is the camera of that image stem.
        frames: ``(stem, labels)`` per evaluated frame (:func:`read_lerf_frames`).
        protocol: the name recorded in the result.
        mask_threshold: rendered opacity above which a pixel is predicted.
        prompts: evaluate only these categories (OpenGaussian's lists); default all.
        rescale_labels: stretch labels of another aspect ratio than their camera's
            (:func:`check_label_size`).

    Returns:
        metrics ``miou`` and ``accuracy`` (pixel accuracy), each the mean over frames of the
        mean over the frame's prompts; one item per (frame, prompt).
    """
    items = []
    for done, (stem, frame) in enumerate(frames):
        texts = _lerf_prompts(frame, prompts)
        if texts:
            camera = cameras.select([find_view(cameras, stem, f"label file {stem}.json")])
            height, width = int(camera.heights[0]), int(camera.widths[0])
            check_label_size(
                f"label file {stem}.json",
                (frame.width, frame.height),
                (width, height),
                rescale_labels,
            )
            selected = engine.selected(texts)
            masks = selection_masks(
                gaussians, camera, selected, threshold=mask_threshold, config=raster
            )
            for q, text in enumerate(texts):
                truth = frame.category_mask(text, height, width)
                items.append(
                    {
                        "frame": stem,
                        "prompt": text,
                        "iou": mask_iou(masks[..., q], truth),
                        "accuracy": pixel_accuracy(masks[..., q], truth),
                        "predicted_pixels": int(masks[..., q].sum()),
                        "truth_pixels": int(truth.sum()),
                    }
                )
        if progress is not None:
            progress(done + 1, len(frames))
    return ProtocolResult(
        protocol,
        {"miou": frame_mean(items, "iou"), "accuracy": frame_mean(items, "accuracy")},
        items,
        {
            "selection": engine.config.mode,
            "mask_threshold": mask_threshold,
            "prompts": None if prompts is None else list(prompts),
        },
    )


def evaluate_lerf_langsplat(
    engine: FieldQuery,
    gaussians: Gaussians,
    cameras: Cameras,
    frames: Sequence[tuple[str, FrameLabels]],
    *,
    levels: tuple[int, ...] = (1, 2, 3),
    mask_threshold: float = 0.4,
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
    rescale_labels: bool = False,
) -> ProtocolResult:
    """LangSplat's 2D LERF-OVS protocol on rendered relevancy maps (labels of another aspect
    ratio than their camera's refused unless ``rescale_labels``: :func:`check_label_size`).

    Per frame and prompt, each level's per-Gaussian relevancy is rendered into the view
    (:func:`thgs.views.relevancy_map`); :func:`thgs.eval.rules.langsplat_query` chooses a
    level (:func:`~thgs.eval.rules.langsplat_level`), makes its mask
    (:func:`~thgs.eval.rules.langsplat_mask`) and checks the peak against the boxes
    (:func:`~thgs.eval.rules.langsplat_localized`), smoothing each level once.

    Returns:
        metrics ``miou`` (flat mean over (frame, prompt)) and ``localization`` (share of
        prompts whose peak lies in one of the category's boxes); one item per (frame, prompt).
    """
    items = []
    for done, (stem, frame) in enumerate(frames):
        texts = list(frame.categories)
        camera = cameras.select([find_view(cameras, stem, f"label file {stem}.json")])
        height, width = int(camera.heights[0]), int(camera.widths[0])
        check_label_size(
            f"label file {stem}.json", (frame.width, frame.height), (width, height), rescale_labels
        )
        per_gaussian = np.concatenate(
            [engine.gaussian_relevancies(texts, k) for k in levels], axis=1
        )
        maps = relevancy_map(gaussians, camera, per_gaussian, config=raster)  # [H, W, L·Q]
        maps = maps.reshape(height, width, len(levels), len(texts))
        sx, sy = width / frame.width, height / frame.height
        for q, text in enumerate(texts):
            stack = np.moveaxis(maps[:, :, :, q], 2, 0)
            boxes = [
                (x1 * sx, y1 * sy, x2 * sx, y2 * sy)
                for x1, y1, x2, y2 in frame.category_boxes(text)
            ]
            chosen, predicted, localized = langsplat_query(stack, boxes, mask_threshold)
            truth = frame.category_mask(text, height, width)
            items.append(
                {
                    "frame": stem,
                    "prompt": text,
                    "level": levels[chosen],
                    "iou": mask_iou(predicted, truth),
                    "localized": localized,
                }
            )
        if progress is not None:
            progress(done + 1, len(frames))
    flat = [item["iou"] for item in items]
    hits = [item["localized"] for item in items]
    return ProtocolResult(
        "lerf-langsplat",
        {
            "miou": float(np.mean(flat)) if flat else float("nan"),
            "localization": float(np.mean(hits)) if hits else float("nan"),
        },
        items,
        {"levels": list(levels), "mask_threshold": mask_threshold},
    )


def evaluate_lerf_opengaussian(
    engine: FieldQuery,
    gaussians: Gaussians,
    cameras: Cameras,
    frames: Sequence[tuple[str, FrameLabels]],
    *,
    scene_name: str = "",
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
    rescale_labels: bool = False,
) -> ProtocolResult:
    """OpenGaussian's LERF-OVS protocol (``compute_lerf_iou.py``, docs/protocols.md).

    The ``lerf`` rule with silhouettes above 0.7. For its four scenes (figurines, ramen,
    teatime, waldo_kitchen) only its fixed prompts are queried, and a labelled category outside
    them scores 0, as there. Averages are flat over (frame, prompt).

    Args:
        scene_name: chooses the prompt list: OpenGaussian's list of the scene of that name, else
            none (every labelled category is queried). It is only a name (the dataset folder's):
            the result's ``notes`` say which list applied and why.

    Returns:
        metrics ``miou`` and ``acc@0.25`` / ``acc@0.5`` (share of (frame, prompt) pairs whose
        IoU exceeds 0.25 / 0.5); one item per (frame, category); one note on the prompt list.
    """
    prompts = OPENGAUSSIAN_LERF_PROMPTS.get(scene_name)
    result = evaluate_lerf(
        engine,
        gaussians,
        cameras,
        frames,
        protocol="lerf-opengaussian",
        mask_threshold=OPENGAUSSIAN_THRESHOLD,
        prompts=prompts,
        raster=raster,
        progress=progress,
        rescale_labels=rescale_labels,
    )
    scored = {(item["frame"], item["prompt"]): item for item in result.items}
    items = [
        scored.get((stem, category), {"frame": stem, "prompt": category, "iou": 0.0})
        for stem, frame in frames
        for category in frame.categories
    ]
    ious = np.array([item["iou"] for item in items])
    metrics = {
        "miou": float(ious.mean()) if ious.size else float("nan"),
        "acc@0.25": float((ious > 0.25).mean()) if ious.size else float("nan"),
        "acc@0.5": float((ious > 0.5).mean()) if ious.size else float("nan"),
    }
    if prompts is None:
        note = (
            f"scene name {scene_name!r} is none of OpenGaussian's "
            f"({', '.join(OPENGAUSSIAN_LERF_PROMPTS)}): every labelled category is queried"
        )
    else:
        outside = len(items) - len(scored)
        note = (
            f"scene name {scene_name!r} → OpenGaussian's fixed prompt list for {scene_name} "
            f"({len(prompts)} prompts); {outside} labelled (frame, category) pairs outside it "
            "score 0"
        )
    settings = {**result.settings, "scene_name": scene_name}
    return ProtocolResult("lerf-opengaussian", metrics, items, settings, (note,))


def check_label_size(
    source: str, label_size: tuple[int, int], camera_size: tuple[int, int], rescale: bool
) -> None:
    """Refuse 2-D labels of ``label_size`` (width, height) for a camera of ``camera_size`` when
    their aspect ratios differ by more than 1 % (they were drawn on another capture's images),
    unless ``rescale``; labels of the same aspect ratio are scaled to the camera.

    Raises:
        InputError: naming ``source``, both sizes and ``--rescale-labels``.
    """
    (label_width, label_height), (width, height) = label_size, camera_size
    if rescale or abs((label_width / label_height) / (width / height) - 1.0) <= 0.01:
        return
    raise InputError(
        source,
        f"labels are {label_width}×{label_height} but their camera is {width}×{height}, another "
        "aspect ratio: they belong to another capture (--rescale-labels stretches them anyway)",
    )


def evaluate_3dovs(
    engine: FieldQuery,
    gaussians: Gaussians,
    cameras: Cameras,
    segmentations: SegmentationSet,
    *,
    mask_threshold: float = 0.5,
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
    rescale_labels: bool = False,
) -> ProtocolResult:
    """The THGS rule on 3D-OVS: every class mask of every annotated view.

    View ``"03"`` is camera 3 (3D-OVS numbers views by image index). Each class is queried with
    :func:`thgs.eval.query_text` ("wood wall" → "wood").

    Returns:
        metrics ``miou`` and ``accuracy``, means over views of the means over their classes.
    """
    items = []
    views = list(segmentations.views.items())
    for done, (view, masks) in enumerate(views):
        if not view.isdigit() or int(view) >= len(cameras):
            raise InputError(
                f"segmentations/{view}",
                f"names no camera index (the scene has {len(cameras)} cameras)",
            )
        classes = list(masks)
        if classes:
            height, width = masks[classes[0]].shape
            camera = cameras.select([int(view)])
            camera_size = (int(camera.widths[0]), int(camera.heights[0]))
            check_label_size(f"segmentations/{view}", (width, height), camera_size, rescale_labels)
            camera = camera.resized([width], [height])
            selected = engine.selected([query_text(name) for name in classes])
            predicted = selection_masks(
                gaussians, camera, selected, threshold=mask_threshold, config=raster
            )
            for q, name in enumerate(classes):
                items.append(
                    {
                        "frame": view,
                        "prompt": name,
                        "query": query_text(name),
                        "iou": mask_iou(predicted[..., q], masks[name]),
                        "accuracy": pixel_accuracy(predicted[..., q], masks[name]),
                    }
                )
        if progress is not None:
            progress(done + 1, len(views))
    return ProtocolResult(
        "3dovs",
        {"miou": frame_mean(items, "iou"), "accuracy": frame_mean(items, "accuracy")},
        items,
        {"selection": engine.config.mode, "mask_threshold": mask_threshold},
    )


def _flat_mean(items: Sequence[Mapping[str, Any]], key: str, part: bool | None = None) -> float:
    values = [float(item[key]) for item in items if part is None or item["part"] == part]
    return float(np.mean(values)) if values else float("nan")


def evaluate_openhype(
    engine: FieldQuery,
    gaussians: Gaussians,
    cameras: Cameras,
    frames: Sequence[OpenHypeFrame],
    *,
    protocol: str = "openhype",
    mask_threshold: float = 0.5,
    source: str = "OpenHype annotations",
    raster: RasterConfig = RasterConfig(),
    progress: Progress | None = None,
    rescale_labels: bool = False,
) -> ProtocolResult:
    """OpenHype's ScanNet++ benchmark with the THGS rule (docs/protocols.md).

    Each frame is evaluated in the camera :func:`thgs.eval.openhype.openhype_views` matches it
    to, rendered at the masks' size (``info``'s width × height; another aspect ratio than the
    camera's is refused unless ``rescale_labels``: :func:`check_label_size`). Per prompt
    (:meth:`~thgs.eval.openhype.OpenHypeFrame.prompts`: one per category, the first mask), the
    selection rendered as accumulated opacity > ``mask_threshold`` is scored against the mask
    (:func:`thgs.eval.rules.mask_iou`) and localized in its boxes
    (:func:`thgs.eval.rules.openhype_localized`).

    Args:
        engine: the query engine (its config is the selection rule).
        frames: the annotation frames (:func:`thgs.eval.read_openhype_annotations`).
        protocol: the name recorded in the result.
        source: the annotation folder, for messages.

    Returns:
        metrics ``miou`` and ``localization`` (flat means over every (frame, prompt), as
        OpenHype's evaluator averages), and the same over the object prompts
        (``miou_objects``, ``localization_objects``) and the part prompts (``miou_parts``,
        ``localization_parts``; NaN when there are none); one item per (frame, prompt).
    """
    match = openhype_views(cameras, frames, source)
    items = []
    for done, (frame, index) in enumerate(zip(frames, match.indices)):
        prompts = frame.prompts()
        if prompts:
            camera = cameras.select([index])
            camera_size = (int(camera.widths[0]), int(camera.heights[0]))
            where = f"{source}/{frame.stem}.json"
            check_label_size(where, (frame.width, frame.height), camera_size, rescale_labels)
            camera = camera.resized([frame.width], [frame.height])
            selected = engine.selected([prompt.category for prompt in prompts])
            masks = selection_masks(
                gaussians, camera, selected, threshold=mask_threshold, config=raster
            )
            for q, prompt in enumerate(prompts):
                items.append(
                    {
                        "frame": frame.stem,
                        "view": cameras.stems[index],
                        "prompt": prompt.category,
                        "part": prompt.is_part,
                        "iou": mask_iou(masks[..., q], prompt.mask),
                        "localized": openhype_localized(masks[..., q], prompt.boxes),
                        "predicted_pixels": int(masks[..., q].sum()),
                        "truth_pixels": int(prompt.mask.sum()),
                    }
                )
        if progress is not None:
            progress(done + 1, len(frames))
    metrics = {}
    for suffix, part in (("", None), ("_objects", False), ("_parts", True)):
        metrics[f"miou{suffix}"] = _flat_mean(items, "iou", part)
        metrics[f"localization{suffix}"] = _flat_mean(items, "localized", part)
    settings = {
        "selection": engine.config.mode,
        "mask_threshold": mask_threshold,
        "views": match.rule,
        "prompts": len(items),
        "object_prompts": sum(not item["part"] for item in items),
        "part_prompts": sum(bool(item["part"]) for item in items),
    }
    return ProtocolResult(protocol, metrics, items, settings, (match.note,) if match.note else ())


def scannet_subsets(labels: PointLabels) -> dict[str, tuple[int, ...]]:
    """The class subsets to evaluate: 19 / 15 / 10 for ScanNet's NYU40 labels, else every class
    of the label table (``all``)."""
    if dict(labels.class_names) == dict(SCANNET19_NAMES):
        return {"19": SCANNET19_IDS, "15": SCANNET15_IDS, "10": SCANNET10_IDS}
    return {"all": tuple(sorted(labels.class_names))}


def evaluate_scannet(
    engine: FieldQuery,
    gaussians: Gaussians,
    labels: PointLabels,
    *,
    subsets: Mapping[str, Sequence[int]] | None = None,
    level: int = 3,
    min_opacity: float = 0.1,
) -> list[ProtocolResult]:
    """OpenGaussian's ScanNet protocol: Gaussian i is scan point i.

    Each Gaussian takes the class (of the subset) whose name's embedding is closest to its
    level-``level`` region feature; Gaussians of unseen regions predict no class (a miss).

    Args:
        labels: the scan's per-point labels; N must equal the number of Gaussians.
        subsets: name → class ids; default :func:`scannet_subsets`.
        level: the field level whose features classify (3: objects).
        min_opacity: Gaussians below this activated opacity are not evaluated.

    Returns:
        one result per subset (``scannet-19`` …) with ``miou`` and ``macc``, one item per class.
    """
    if len(labels.labels) != len(gaussians):
        raise InputError(
            "ScanNet labels",
            f"{len(labels.labels)} points for {len(gaussians)} Gaussians: the protocol needs "
            "Gaussian i to be scan point i",
        )
    opacity = gaussians.activated_opacities().detach().cpu().numpy().astype(np.float64)
    results = []
    for name, ids in (subsets or scannet_subsets(labels)).items():
        ids = tuple(int(i) for i in ids)
        missing = [i for i in ids if i not in labels.class_names]
        if missing:
            raise InputError("ScanNet labels", f"subset {name}: classes {missing} have no name")
        best = engine.classify([labels.class_names[i] for i in ids], level)
        predicted = np.where(best >= 0, np.asarray(ids)[np.maximum(best, 0)], -1)
        scores = scannet_scores(predicted, labels.labels, opacity, ids, min_opacity=min_opacity)
        items = [
            {
                "class": i,
                "name": labels.class_names[i],
                "iou": float(scores.iou[k]),
                "accuracy": float(scores.accuracy[k]),
            }
            for k, i in enumerate(scores.classes)
        ]
        results.append(
            ProtocolResult(
                f"scannet-{name}",
                {"miou": scores.miou, "macc": scores.macc},
                items,
                {"level": level, "min_opacity": min_opacity, "points": scores.points},
            )
        )
    return results


def evaluate_hierarchy(levels: RegionLevels, hierarchy: Hierarchy) -> ProtocolResult:
    """Agreement of regions at levels 0–3 with a ground-truth hierarchy, level k against level k.

    Returns:
        metrics ``miou_subpart``, ``miou_part``, ``miou_object`` (level k against ground-truth
        level k: :func:`thgs.eval.matched_miou`) and ``purity`` (level-0 superpoints against
        sub-parts); one item per level with the region and node counts.

    Raises:
        InputError: levels of another number of Gaussians than the hierarchy's.
    """
    if len(levels) != len(hierarchy):
        raise InputError(
            "levels", f"must be of the hierarchy's {len(hierarchy)} Gaussians, got {len(levels)}"
        )
    labels, truth = levels.labels, hierarchy.labels
    metrics, items = {}, []
    for k in (1, 2, 3):
        name = LEVEL_NAMES[k]
        score = matched_miou(labels[:, k], truth[:, k])
        metrics[f"miou_{name}"] = score
        items.append(
            {
                "level": k,
                "truth": name,
                "miou": score,
                "regions": levels.counts[k],
                "nodes": len(hierarchy.names[k]),
            }
        )
    metrics["purity"] = purity(labels[:, 0], truth[:, 1])
    return ProtocolResult("hierarchy", metrics, items, {"superpoints": levels.counts[0]})
