"""Write a synthetic scene as a complete dataset in the real benchmarks' file formats.

Layout of ``OUT/`` (one folder is both the trained-model folder and the training-data folder)::

    point_cloud/iteration_30000/point_cloud.ply   the Gaussians (INRIA layout)
    cameras.json                                  3DGS cameras
    sparse/0/{cameras,images,points3D}.bin         COLMAP model (PINHOLE, no points)
    transforms.json                                nerfstudio cameras
    images/frame_00001.jpg …                      rendered RGB
    language_features/frame_00001_{s,f}.npy …     oracle guidance, LangSplat layout
    language_features/embedding.json              the features' embedding space
    label/frame_000xx.json                        LERF-OVS-style labels of the evaluation frames
    segmentations/classes.txt, <NN>/<class>.png   3DOVS-style masks of the evaluation frames
                                                  (NN = view index, as 3D-OVS names them)
    scannet/synthetic_vh_clean_2.labels.ply        ScanNet-style per-Gaussian class labels
    ground_truth.safetensors                       per-Gaussian sub-part / part / object ids + names
    synthetic.json                                 how it was made (configs, seed, counts)

Everything is written into a hidden sibling folder first and renamed to ``OUT`` at the end, so an
interrupted run never leaves a half-written dataset (one killed outright leaves its hidden folder,
which the next run writing ``OUT`` removes; see :mod:`thgs._atomic`). Same scene and configs →
the same bytes.

``synthetic.json`` (``"format": "thgs.synthetic"``) is the marker of a dataset thgs wrote:
``overwrite`` replaces only a folder that has it and nothing but the entries listed above, and
never the current folder, a folder holding it, or the home folder
(:func:`check_dataset_output`).
"""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Callable
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from thgs._atomic import atomic_folder
from thgs.errors import InputError
from thgs.eval.ground_truth import write_hierarchy
from thgs.eval.lerf_ovs import FrameLabels, LabelledObject, write_lerf_labels
from thgs.eval.polygons import mask_to_polygons
from thgs.eval.scannet import PointLabels, write_scannet_labels
from thgs.eval.three_dovs import SegmentationSet, write_3dovs_segmentations
from thgs.guidance import write_embedding_space, write_view_guidance
from thgs.hierarchy.levels import LEVEL_NAMES
from thgs.render import render
from thgs.scene import write_cameras_json, write_colmap, write_ply, write_transforms_json
from thgs.synthetic.oracle import OracleConfig, oracle_guidance
from thgs.synthetic.sam_masks import ground_truth_maps
from thgs.synthetic.scene import SyntheticScene
from thgs.text import TextEncoder

__all__ = [
    "DATASET_VERSION",
    "SCANNET_LABELS",
    "DatasetConfig",
    "DatasetSummary",
    "check_dataset_output",
    "evaluation_views",
    "is_current_dataset",
    "label_categories",
    "render_view",
    "write_dataset",
]

logger = logging.getLogger(__name__)

SCANNET_LABELS = "scannet/synthetic_vh_clean_2.labels.ply"
"""Where the ScanNet-style labels go inside a dataset."""

DATASET_VERSION = "2"
"""The ``"version"`` in ``synthetic.json`` of what :func:`write_dataset` writes now. 2: a
class covering fewer than ``min_label_pixels`` pixels of an evaluation view gets no 3DOVS mask
there (1 wrote one)."""

_MARKER = "synthetic.json"
"""The file whose ``"format": "thgs.synthetic"`` says thgs wrote the folder."""

_ENTRIES = frozenset(
    {
        "point_cloud",
        "cameras.json",
        "sparse",
        "transforms.json",
        "images",
        "language_features",
        "label",
        "segmentations",
        "scannet",
        "ground_truth.safetensors",
        _MARKER,
    }
)
"""Everything :func:`write_dataset` puts at the top of a dataset folder."""


@dataclass(frozen=True)
class DatasetConfig:
    """How the dataset is written.

    Attributes:
        evaluation_views: how many views (evenly spread) get LERF-OVS and 3DOVS labels; None:
            :data:`EVALUATION_VIEWS`, or every view of a scene with fewer. More than the scene's
            views is an error (never silently fewer).
        min_label_pixels: a node must cover at least this many pixels of a frame to be labelled
            in it.
        jpeg_quality: quality of the RGB images.
        background: RGB in [0, 1] behind the scene.
    """

    evaluation_views: int | None = None
    min_label_pixels: int = 20
    jpeg_quality: int = 95
    background: tuple[float, float, float] = (0.80, 0.82, 0.86)

    def __post_init__(self) -> None:
        if self.evaluation_views is not None and self.evaluation_views < 0:
            raise InputError(
                "DatasetConfig.evaluation_views", f"must be ≥ 0, got {self.evaluation_views}"
            )


@dataclass(frozen=True)
class DatasetSummary:
    """What was written: the folder, counts, and the size on disk in bytes."""

    path: Path
    gaussians: int
    views: int
    masks: int
    evaluation_views: tuple[str, ...]
    categories: tuple[str, ...]
    bytes: int


def render_view(
    scene: SyntheticScene, index: int, background: tuple[float, float, float]
) -> tuple[np.ndarray, np.ndarray]:
    """View ``index`` as ([H, W, 3] uint8 RGB over ``background``, [H, W] int64 max-weight ids)."""
    gaussians = scene.gaussians
    colors = gaussians.dc_colors().to(torch.float64)
    out = render(gaussians, scene.cameras.select([index]), colors)
    image = out.image + (1.0 - out.alpha)[..., None] * torch.tensor(background, dtype=torch.float64)
    rgb = np.floor(image.clamp(0.0, 1.0).numpy() * 255.0 + 0.5).astype(np.uint8)
    return rgb, out.max_id.numpy()


EVALUATION_VIEWS = 4
"""How many views get labels by default (:attr:`DatasetConfig.evaluation_views`)."""


def evaluation_views(count: int, evaluate: int | None = None) -> list[int]:
    """``evaluate`` view indices spread evenly over ``count`` views, first and last included.

    ``evaluate`` None takes :data:`EVALUATION_VIEWS`, or all ``count`` views if fewer.

    Raises:
        InputError: ``evaluate`` is negative or more than ``count`` (named as
            ``DatasetConfig.evaluation_views``).
    """
    if evaluate is None:
        evaluate = min(EVALUATION_VIEWS, count)
    if evaluate < 0 or evaluate > count:
        raise InputError(
            "DatasetConfig.evaluation_views",
            f"{evaluate} evaluation views asked of a scene with {count} views; give at most "
            f"{count}",
        )
    if evaluate == 0:
        return []
    return sorted({int(i) for i in np.round(np.linspace(0, count - 1, evaluate))})


def label_categories(
    maps: np.ndarray, scene: SyntheticScene, min_pixels: int
) -> dict[str, tuple[int, list[int]]]:
    """The LERF-OVS-style prompts of one frame: category → (index into ``maps``, its nodes).

    Categories are the names of the objects (except the floor), of the parts named differently
    from their object, and of the sub-parts named differently from their part, among the nodes
    covering at least ``min_pixels`` pixels. A category's mask is the union of its nodes' pixels.

    Args:
        maps: [3, H, W] the frame's ground-truth node ids at levels 1, 2, 3 (sub-part, part,
            object; :func:`thgs.synthetic.ground_truth_maps`).
    """
    hierarchy = scene.hierarchy
    parents = hierarchy.levels.parents
    assert parents is not None  # ground truth always nests
    categories: dict[str, tuple[int, list[int]]] = {}
    for index in (2, 1, 0):
        level = index + 1
        names = hierarchy.names[level]
        counts = np.bincount(maps[index][maps[index] >= 0], minlength=len(names))
        for node in np.flatnonzero(counts >= min_pixels):
            name = names[node]
            if level == 3 and name == "floor":
                continue
            if level < 3 and name == hierarchy.names[level + 1][parents[level][node]]:
                continue
            categories.setdefault(name, (index, []))[1].append(int(node))
    return categories


def _frame_labels(
    stem: str, maps: np.ndarray, scene: SyntheticScene, min_pixels: int
) -> FrameLabels:
    """LERF-OVS labels of one frame: one object per connected component of every node; the
    nodes of one category are numbered as its groups."""
    height, width = maps.shape[1:]
    objects = []
    for category, (level, nodes) in label_categories(maps, scene, min_pixels).items():
        for group, node in enumerate(nodes, start=1):
            for polygon in mask_to_polygons(maps[level] == node):
                x, y = polygon[:, 0], polygon[:, 1]
                bbox = (float(x.min()), float(y.min()), float(x.max()), float(y.max()))
                objects.append(LabelledObject(category, polygon, bbox, group))
    return FrameLabels(f"{stem}.jpg", int(width), int(height), tuple(objects))


def _class_masks(
    maps: np.ndarray, class_objects: dict[str, list[int]], min_pixels: int
) -> dict[str, np.ndarray]:
    """The 3DOVS masks of one frame: class → [H, W] bool, True where the class's objects are.

    A class covering no pixel gets an empty mask (absent from the view, as in the 3D-OVS
    release). A class covering fewer than ``min_pixels`` pixels gets no mask at all: like the
    LERF-OVS labels, a sliver that small is not labelled, and its IoU would be 0 or 1 by chance.
    """
    masks = {name: np.isin(maps[2], nodes) for name, nodes in class_objects.items()}
    return {
        name: mask for name, mask in masks.items() if not 0 < np.count_nonzero(mask) < min_pixels
    }


def _object_classes(scene: SyntheticScene) -> tuple[str, ...]:
    return tuple(sorted(set(scene.hierarchy.names[3])))


def _scannet_labels(scene: SyntheticScene) -> PointLabels:
    classes = _object_classes(scene)
    class_of_object = np.array(
        [classes.index(name) + 1 for name in scene.hierarchy.names[3]] + [0], dtype=np.int64
    )
    return PointLabels(
        points=scene.gaussians.means.numpy().astype(np.float32),
        labels=class_of_object[scene.hierarchy.labels[:, 3]],
        class_names={i + 1: name for i, name in enumerate(classes)},
    )


def _folder_bytes(folder: Path) -> int:
    return sum(path.stat().st_size for path in folder.rglob("*") if path.is_file())


def _protected(folder: Path) -> str | None:
    """Why ``folder`` (resolved) must never be replaced, or None."""
    cwd = Path.cwd().resolve()
    if folder == cwd:
        return "is the current folder"
    if folder in cwd.parents:
        return f"holds the current folder {cwd}"
    try:
        home = Path.home().resolve()
    except RuntimeError:
        return None
    if folder == home or folder in home.parents:
        return "is the home folder or holds it"
    return None


def _record(folder: Path) -> dict | None:
    """``folder``'s ``synthetic.json`` if it is the marker of a dataset thgs wrote, else None."""
    try:
        record = json.loads((folder / _MARKER).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError):
        return None
    if isinstance(record, dict) and record.get("format") == "thgs.synthetic":
        return record
    return None


def _is_dataset(folder: Path) -> bool:
    """Whether ``folder`` holds the marker of a dataset thgs wrote."""
    return _record(folder) is not None


def is_current_dataset(folder: str | os.PathLike[str]) -> bool:
    """Whether ``folder`` holds a dataset that :func:`write_dataset` wrote in the current
    :data:`DATASET_VERSION` (a cache of an older version is written again)."""
    record = _record(Path(folder))
    return record is not None and record.get("version") == DATASET_VERSION


def check_dataset_output(out: str | os.PathLike[str], *, overwrite: bool = False) -> Path:
    """Check that :func:`write_dataset` may write ``out``, before any work is done.

    ``out`` may be absent or an empty folder. An existing non-empty folder needs ``overwrite``,
    and then it must be a dataset thgs wrote: ``synthetic.json`` with ``"format":
    "thgs.synthetic"`` (the marker) and nothing at its top but the entries a dataset has (so no
    file of the user's is deleted with it). The current folder, a folder holding it (``/``
    included) and the home folder are never written in place (the new dataset is renamed into
    place, which would pull the folder from under the shell), even empty.

    Returns:
        The folder to write: ``out`` with symbolic links resolved, so that replacing a linked
        dataset replaces the folder it points to and keeps the link.

    Raises:
        InputError: naming ``out`` and why it cannot be written; nothing is deleted.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(out, "exists and is not a folder")
    folder = out.resolve()
    if not out.is_dir():
        return folder
    refusal = _protected(folder)
    if refusal is not None:
        raise InputError(out, f"{refusal}; a dataset is never written in its place")
    if not any(out.iterdir()):
        return folder
    if not overwrite:
        raise InputError(out, "already exists and is not empty (replace it with --overwrite)")
    if not _is_dataset(folder):
        raise InputError(
            out,
            f"is not a dataset thgs wrote (no {_MARKER} with format thgs.synthetic); "
            "--overwrite replaces only those: choose another folder or empty it yourself",
        )
    foreign = sorted(name for name in os.listdir(folder) if name not in _ENTRIES)
    if foreign:
        more = len(foreign) - 5
        shown = ", ".join(foreign[:5]) + (f" and {more} more" if more > 0 else "")
        raise InputError(
            out,
            f"holds files thgs did not write ({shown}); --overwrite would delete them: "
            "move them out first",
        )
    return folder


def write_dataset(
    out: str | os.PathLike[str],
    scene: SyntheticScene,
    encoder: TextEncoder,
    *,
    oracle: OracleConfig = OracleConfig(),
    config: DatasetConfig = DatasetConfig(),
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
) -> DatasetSummary:
    """Render every view, make its oracle guidance and labels, and write the dataset to ``out``.

    Args:
        out: the dataset folder to create.
        scene: from :func:`thgs.synthetic.generate_scene`.
        encoder: the text model of the oracle features (its space is recorded).
        oracle: fault severity, feature noise and seed of the guidance.
        config: evaluation frames, image settings.
        overwrite: replace an existing ``out`` that thgs wrote (:func:`check_dataset_output`);
            otherwise an existing non-empty ``out`` is an error.
        progress: called with (views done, views) after each view.

    Raises:
        InputError: ``out`` cannot be written or replaced (:func:`check_dataset_output`).
    """
    out = Path(out)
    folder = check_dataset_output(out, overwrite=overwrite)
    with atomic_folder(folder, replace=True) as staging:
        summary = _write(staging, scene, encoder, oracle, config, progress)
    summary = replace(summary, path=out)
    logger.info("wrote %s (%.1f MB)", out, summary.bytes / 1e6)
    return summary


def _write(
    root: Path,
    scene: SyntheticScene,
    encoder: TextEncoder,
    oracle: OracleConfig,
    config: DatasetConfig,
    progress: Callable[[int, int], None] | None,
) -> DatasetSummary:
    cameras = scene.cameras
    stems = cameras.stems
    write_ply(root / "point_cloud" / "iteration_30000" / "point_cloud.ply", scene.gaussians)
    write_cameras_json(root / "cameras.json", cameras)
    write_colmap(root / "sparse" / "0", replace(cameras, names=tuple(f"{s}.jpg" for s in stems)))
    write_transforms_json(
        root / "transforms.json", replace(cameras, names=tuple(f"images/{s}.jpg" for s in stems))
    )
    features_dir = root / "language_features"
    features_dir.mkdir()
    write_embedding_space(features_dir, encoder.space, encoder.dim)
    (root / "images").mkdir()

    evaluated = evaluation_views(len(cameras), config.evaluation_views)
    classes = _object_classes(scene)
    object_names = scene.hierarchy.names[3]
    class_objects = {
        name: [i for i, node in enumerate(object_names) if node == name] for name in classes
    }
    segmentations: dict[str, dict[str, np.ndarray]] = {}
    categories: dict[str, None] = {}
    masks = 0
    for index, stem in enumerate(stems):
        rgb, max_id = render_view(scene, index, config.background)
        Image.fromarray(rgb).save(
            root / "images" / f"{stem}.jpg", quality=config.jpeg_quality, subsampling=0
        )
        guidance = oracle_guidance(stem, max_id, scene.hierarchy, encoder, oracle, index)
        write_view_guidance(features_dir, guidance)
        masks += guidance.features.shape[0]
        if index in evaluated:
            maps = ground_truth_maps(max_id, scene.hierarchy)
            labels = _frame_labels(stem, maps, scene, config.min_label_pixels)
            write_lerf_labels(root / "label" / f"{stem}.json", labels)
            categories.update(dict.fromkeys(labels.categories))
            segmentations[f"{index:02d}"] = _class_masks(
                maps, class_objects, config.min_label_pixels
            )
        if progress is not None:
            progress(index + 1, len(stems))
    write_3dovs_segmentations(
        root / "segmentations", SegmentationSet(classes=classes, views=segmentations)
    )
    write_scannet_labels(root / SCANNET_LABELS, _scannet_labels(scene))
    write_hierarchy(root / "ground_truth.safetensors", scene.hierarchy)
    record = {
        "format": "thgs.synthetic",
        "version": DATASET_VERSION,
        "scene": asdict(scene.config),
        "oracle": asdict(oracle),
        "dataset": asdict(replace(config, evaluation_views=len(evaluated))),
        "embedding_space": encoder.space,
        "embedding_dim": encoder.dim,
        "hierarchy_levels": list(LEVEL_NAMES[1:]),
        "objects": list(scene.hierarchy.names[2]),
        "evaluation_views": [stems[i] for i in evaluated],
        "gaussians": len(scene.gaussians),
        "masks": masks,
    }
    with open(root / "synthetic.json", "w", encoding="utf-8") as handle:
        json.dump(record, handle, indent=2)
        handle.write("\n")
    return DatasetSummary(
        path=root,
        gaussians=len(scene.gaussians),
        views=len(stems),
        masks=masks,
        evaluation_views=tuple(stems[i] for i in evaluated),
        categories=tuple(categories),
        bytes=_folder_bytes(root),
    )
