"""Posed images → LangSplat-format guidance: masks at four levels and one CLIP feature per mask.

:func:`preprocess_image` does one image; :func:`preprocess_images` does a list of them into a
``language_features`` folder, resumably:

- each view's two files are written atomically, ``<stem>_f.npy`` first and ``<stem>_s.npy``
  last, so a view is finished exactly when its ``_s.npy`` exists; a restarted run skips finished
  views and rewrites any other (an ``_f.npy`` left alone by a crash is replaced);
- ``preprocess.json`` records the models and settings; a restart with different ones is refused
  rather than mixing two kinds of masks in one folder;
- ``embedding.json`` names the features' embedding space (:mod:`thgs.guidance.langsplat`).

Resolution: LangSplat's rule (images taller than 1080 px are scaled to 1080 px tall; an explicit
width scales to that width), or each camera's own size when cameras are given, so the masks match
the views the field is built from without resampling.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from thgs._atomic import atomic_output
from thgs._json import load_json
from thgs.errors import InputError
from thgs.guidance.langsplat import (
    LEVELS,
    ViewGuidance,
    read_embedding_space,
    write_embedding_space,
    write_view_guidance,
)
from thgs.guidance.preprocess.clip_features import CLIPImageEncoder, mask_features
from thgs.guidance.preprocess.generator import MaskGeneratorConfig, generate_masks, segment_map
from thgs.guidance.preprocess.sam import PointSegmenter
from thgs.scene import Cameras, find_images

__all__ = [
    "MANIFEST_FILE",
    "ImageJob",
    "PreprocessConfig",
    "PreprocessSummary",
    "image_jobs",
    "langsplat_size",
    "preprocess_image",
    "preprocess_images",
    "read_image",
]

logger = logging.getLogger(__name__)

MANIFEST_FILE = "preprocess.json"
"""The file in a ``language_features`` folder recording how its views were made."""

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True)
class PreprocessConfig:
    """Settings of preprocessing; the defaults are LangSplat's.

    Attributes:
        masks: the mask generator's settings.
        clip_batch_size: mask crops encoded together.
        max_height: without an explicit size, images taller than this are scaled to this height
            (LangSplat's 1080 px rule).
    """

    masks: MaskGeneratorConfig = field(default_factory=MaskGeneratorConfig)
    clip_batch_size: int = 64
    max_height: int = 1080


@dataclass(frozen=True)
class ImageJob:
    """One image to preprocess.

    Attributes:
        path: the image file.
        stem: the view's name, used for its output files (``<stem>_s.npy``, ``<stem>_f.npy``).
        size: (width, height) in pixels the masks are made at, or None for LangSplat's rule.
    """

    path: Path
    stem: str
    size: tuple[int, int] | None = None


@dataclass(frozen=True)
class PreprocessSummary:
    """What :func:`preprocess_images` did.

    Attributes:
        done: stems processed in this run, with seconds per image.
        skipped: stems already finished by an earlier run.
        masks: masks with at least one pixel in the id map, per level (``LEVELS`` order),
            summed over the images done.
        empty: stems of the images done whose masks are empty at every level (SAM kept no
            mask: its thresholds, :class:`MaskGeneratorConfig`, were too strict for them).
    """

    done: dict[str, float]
    skipped: list[str]
    masks: tuple[int, int, int, int]
    empty: list[str] = field(default_factory=list)


def langsplat_size(
    width: int, height: int, *, target_width: int | None = None, max_height: int = 1080
) -> tuple[int, int]:
    """LangSplat's preprocessing size of a ``width`` × ``height`` image, as (width, height).

    Without ``target_width``, an image taller than ``max_height`` is scaled by
    ``max_height / height``; with it, by ``target_width / width``. Sizes are truncated, as the
    reference's ``int(side / scale)``.
    """
    if target_width is not None:
        scale = width / target_width
    else:
        scale = height / max_height if height > max_height else 1.0
    return int(width / scale), int(height / scale)


def read_image(
    path: str | os.PathLike[str],
    size: tuple[int, int] | None = None,
    *,
    max_height: int | None = None,
) -> np.ndarray:
    """An image as [H, W, 3] uint8 RGB, resized to ``size`` = (width, height) if given, else
    to LangSplat's size under ``max_height`` if that is given (:func:`langsplat_size`).

    Resizing is bilinear with antialiasing (PIL); an alpha channel is dropped.

    Raises:
        InputError: the file is missing or not a readable image.
    """
    path = Path(path)
    try:
        with Image.open(path) as image:
            image = image.convert("RGB")
            if size is None and max_height is not None:
                size = langsplat_size(*image.size, max_height=max_height)
            if size is not None and image.size != tuple(size):
                image = image.resize(tuple(size), Image.BILINEAR)
            return np.array(image)
    except FileNotFoundError as error:
        raise InputError(path, "no such image") from error
    except (UnidentifiedImageError, OSError) as error:
        raise InputError(path, f"not a readable image ({error})") from error


def image_jobs(
    image_dir: str | os.PathLike[str],
    *,
    cameras: Cameras | None = None,
    target_width: int | None = None,
) -> list[ImageJob]:
    """The images to preprocess.

    Args:
        image_dir: the folder of images (``images/`` of a dataset).
        cameras: if given, exactly the cameras' images, each at its image file's size
            (:meth:`thgs.Cameras.file_sizes`: with lens distortion, the distorted file's, and
            :func:`thgs.guidance.load_guidance` undistorts the masks); otherwise every
            .png/.jpg/.jpeg in ``image_dir`` (sorted by name) at LangSplat's size.
        target_width: LangSplat's explicit resolution (output width in pixels); not with
            ``cameras``.

    Raises:
        InputError: the folder is missing or holds no images, two images share a stem, a camera's
            image is missing, or both ``cameras`` and ``target_width`` are given.
    """
    image_dir = Path(image_dir)
    if not image_dir.is_dir():
        raise InputError(image_dir, "image folder not found")
    if cameras is not None:
        if target_width is not None:
            raise InputError(image_dir, "give either cameras or an explicit width, not both")
        paths = find_images(cameras, image_dir)
        missing = [name for name, path in zip(cameras.names, paths) if path is None]
        if missing:
            raise InputError(
                image_dir,
                f"no image for {len(missing)} of {len(cameras)} cameras (first: {missing[:5]})",
            )
        widths, heights = cameras.file_sizes()
        return [
            ImageJob(path, stem, (int(width), int(height)))
            for path, stem, width, height in zip(paths, cameras.stems, widths, heights)
        ]
    paths = sorted(
        path
        for path in image_dir.iterdir()
        if path.is_file() and path.suffix.lower() in IMAGE_SUFFIXES
    )
    if not paths:
        raise InputError(image_dir, "no .png/.jpg/.jpeg images in the folder")
    stems = [path.stem for path in paths]
    duplicates = sorted({stem for stem in stems if stems.count(stem) > 1})
    if duplicates:
        raise InputError(
            image_dir, f"several images share a name stem: {duplicates[:5]}; keep one of each"
        )
    jobs = []
    for path in paths:
        size = None
        if target_width is not None:
            with Image.open(path) as image:
                size = langsplat_size(*image.size, target_width=target_width)
        jobs.append(ImageJob(path, path.stem, size))
    return jobs


def preprocess_image(
    image: np.ndarray,
    stem: str,
    segmenter: PointSegmenter,
    encoder: CLIPImageEncoder,
    config: PreprocessConfig = PreprocessConfig(),
) -> ViewGuidance:
    """Masks at the levels default, s, m, l and their CLIP features, in LangSplat's layout.

    Args:
        image: [H, W, 3] uint8 RGB, at the resolution the masks are wanted at.
        stem: the view's name.
        segmenter: SAM or SAM 2.
        encoder: the CLIP image encoder.
        config: settings.

    Returns:
        A :class:`ViewGuidance` with [4, H, W] ids (−1 = no mask; level k's ids follow level
        k−1's) and [n, D] unit feature rows; a level without masks is all −1.
    """
    levels = generate_masks(segmenter, image, config.masks)
    pixels = torch.from_numpy(image).to(encoder.device).float() / 255.0
    segments, features, first_id = [], [], 0
    for name in LEVELS:
        level = levels[name]
        masks, boxes = level.masks.to(encoder.device), level.boxes.to(encoder.device)
        features.append(
            mask_features(encoder, pixels, masks, boxes, batch_size=config.clip_batch_size)
        )
        segments.append(segment_map(level.masks, first_id))
        first_id += len(level)
    return ViewGuidance(stem, np.stack(segments), np.concatenate(features).astype(np.float32))


# The steps of preprocess_images, shared with preprocess_with_ray (distributed.py), which runs
# them in the driver (the folder's record, skipping, the summary) and in Ray workers (the views);
# not in __all__.


@dataclass(frozen=True)
class FolderRecord:
    """What a ``language_features`` folder records of the models and settings its views were made
    with: the manifest (``preprocess.json``) and the features' space, dimension and local model
    folder (``embedding.json``)."""

    manifest: dict
    space: str
    dim: int
    model: Path | None

    @classmethod
    def of(
        cls, segmenter: PointSegmenter, encoder: CLIPImageEncoder, config: PreprocessConfig
    ) -> FolderRecord:
        manifest = {
            "format": "LangSplat language_features",
            "sam": segmenter.name,
            "clip": encoder.space,
            "config": asdict(config),
        }
        return cls(manifest, encoder.space, encoder.dim, getattr(encoder, "model_path", None))


def _check_or_write_manifest(output: Path, manifest: dict, overwrite: bool) -> None:
    path = output / MANIFEST_FILE
    if not path.is_file() and not overwrite and any(output.glob("*_s.npy")):
        raise InputError(
            output,
            "holds views made by another tool (no preprocess.json); write to a new folder, or "
            "replace them with --overwrite",
        )
    if path.is_file() and not overwrite:
        previous = load_json(path)
        if previous != json.loads(json.dumps(manifest)):
            raise InputError(
                path,
                "this folder was preprocessed with other models or settings "
                f"({previous.get('sam') if isinstance(previous, dict) else previous!r}); "
                "write to a new folder, or start again with --overwrite",
            )
        return
    with atomic_output(path, "w") as handle:
        json.dump(manifest, handle, indent=2)
        handle.write("\n")


def prepare_folder(output: Path, record: FolderRecord, overwrite: bool) -> None:
    """Create ``output`` if missing, refuse it if it was made with other models or settings (or
    features of another space) unless ``overwrite``, and record ``record`` in it."""
    output.mkdir(parents=True, exist_ok=True)
    _check_or_write_manifest(output, record.manifest, overwrite)
    recorded = read_embedding_space(output)
    if recorded is not None and recorded != (record.space, record.dim) and not overwrite:
        raise InputError(
            output,
            f"holds {recorded[0]} features ({recorded[1]}-D), not {record.space} "
            f"({record.dim}-D); write to a new folder, or start again with --overwrite",
        )
    write_embedding_space(output, record.space, record.dim, model=record.model)


def is_finished(output: Path, stem: str) -> bool:
    return (output / f"{stem}_s.npy").is_file()


@dataclass(frozen=True)
class ViewResult:
    """One image preprocessed: its stem, seconds taken and masks per level (``LEVELS`` order)."""

    stem: str
    seconds: float
    masks: tuple[int, int, int, int]


def preprocess_view(
    job: ImageJob,
    output: Path,
    segmenter: PointSegmenter,
    encoder: CLIPImageEncoder,
    config: PreprocessConfig,
) -> ViewResult:
    """Read, preprocess and write one view (its two files atomically, ``_s.npy`` last)."""
    start = time.perf_counter()
    image = read_image(job.path, job.size, max_height=config.max_height)
    guidance = preprocess_image(image, job.stem, segmenter, encoder, config)
    write_view_guidance(output, guidance)
    found = tuple(len(guidance.level_ids(level)) for level in range(len(LEVELS)))
    seconds = time.perf_counter() - start
    logger.info("%s: %d masks in %.2f s", job.stem, len(guidance.features), seconds)
    return ViewResult(job.stem, seconds, found)


def summarize(
    output: Path, results: Sequence[ViewResult], skipped: list[str], config: PreprocessConfig
) -> PreprocessSummary:
    """The summary of one folder's run, warning when SAM kept no mask in most images done."""
    counts = np.zeros(len(LEVELS), dtype=np.int64)
    for result in results:
        counts += result.masks
    empty = [result.stem for result in results if not any(result.masks)]
    if results and 2 * len(empty) > len(results):
        logger.warning(
            "%s: SAM kept no mask in %d of %d images (first: %s), and a field needs masks; "
            "lower SAM's thresholds: --pred-iou-threshold (now %g), --stability-threshold "
            "(now %g), --min-region-area (now %d)",
            output,
            len(empty),
            len(results),
            empty[0],
            config.masks.pred_iou_threshold,
            config.masks.stability_threshold,
            config.masks.min_region_area,
        )
    done = {result.stem: result.seconds for result in results}
    return PreprocessSummary(done, skipped, tuple(int(c) for c in counts), empty)


def preprocess_images(
    jobs: Sequence[ImageJob],
    output: str | os.PathLike[str],
    segmenter: PointSegmenter,
    encoder: CLIPImageEncoder,
    config: PreprocessConfig = PreprocessConfig(),
    *,
    overwrite: bool = False,
    on_image: Callable[[str, float | None], None] | None = None,
) -> PreprocessSummary:
    """Preprocess images into a ``language_features`` folder, skipping finished views.

    Args:
        jobs: the images, from :func:`image_jobs`.
        output: the ``language_features`` folder (created if missing).
        segmenter, encoder, config: the models and settings.
        overwrite: redo every view and replace the folder's record of models and settings.
        on_image: called after each image with its stem and seconds (None when skipped).

    Each image whose masks come out empty at every level is named in the summary's ``empty``;
    a warning is logged at the end when most images done are empty (``thgs build`` refuses a
    folder without a single mask).

    Raises:
        InputError: the folder was made with other models or settings (unless ``overwrite``),
            its embedding space differs, or an image is unreadable.
    """
    output = Path(output)
    prepare_folder(output, FolderRecord.of(segmenter, encoder, config), overwrite)
    results: list[ViewResult] = []
    skipped: list[str] = []
    for job in jobs:
        if not overwrite and is_finished(output, job.stem):
            skipped.append(job.stem)
            if on_image is not None:
                on_image(job.stem, None)
            continue
        results.append(preprocess_view(job, output, segmenter, encoder, config))
        if on_image is not None:
            on_image(job.stem, results[-1].seconds)
    return summarize(output, results, skipped, config)
