"""Preprocessing with real models: multi-level SAM masks and CLIP mask features, written in
LangSplat's layout (:mod:`thgs.guidance.langsplat`).

- :class:`PointSegmenter` — SAM / SAM 2 through transformers, for point prompts;
- :func:`generate_masks` — SAM's automatic mask generator with its three outputs kept apart as
  levels s, m, l (and pooled as ``default``), SAM's filters and LangSplat's mask NMS;
- :class:`CLIPImageEncoder`, :func:`mask_features` — one CLIP feature per mask;
- :func:`preprocess_image`, :func:`preprocess_images` — images to a resumable
  ``language_features`` folder (``thgs preprocess``);
- :func:`preprocess_with_ray` — many folders' images as one Ray Data pipeline on a Ray cluster.
"""

from thgs.guidance.preprocess.clip_features import CLIPImageEncoder, mask_crops, mask_features
from thgs.guidance.preprocess.distributed import PreprocessTarget, preprocess_with_ray
from thgs.guidance.preprocess.generator import (
    LevelMasks,
    MaskGeneratorConfig,
    crop_boxes,
    generate_masks,
    point_grid,
    segment_map,
)
from thgs.guidance.preprocess.models import load_preprocess_models, local_model_folder
from thgs.guidance.preprocess.run import (
    MANIFEST_FILE,
    ImageJob,
    PreprocessConfig,
    PreprocessSummary,
    image_jobs,
    langsplat_size,
    preprocess_image,
    preprocess_images,
    read_image,
)
from thgs.guidance.preprocess.sam import DEFAULT_SAM, EmbeddedImage, PointSegmenter

__all__ = [
    "DEFAULT_SAM",
    "MANIFEST_FILE",
    "CLIPImageEncoder",
    "EmbeddedImage",
    "ImageJob",
    "LevelMasks",
    "MaskGeneratorConfig",
    "PointSegmenter",
    "PreprocessConfig",
    "PreprocessSummary",
    "PreprocessTarget",
    "crop_boxes",
    "generate_masks",
    "image_jobs",
    "langsplat_size",
    "load_preprocess_models",
    "local_model_folder",
    "mask_crops",
    "mask_features",
    "point_grid",
    "preprocess_image",
    "preprocess_images",
    "preprocess_with_ray",
    "read_image",
    "segment_map",
]
