"""Multi-level automatic mask generation: SAM's point-grid generator with its three multimask
outputs kept apart, as LangSplat runs it.

For each crop (the whole image, then ``crop_layers`` layers of overlapping 2×2, 4×4, … crops),
the image is embedded once and a grid of single-point prompts (``points_per_side``² per crop) is
decoded in batches; only masks passing the predicted-IoU threshold are upsampled to full size.
Every prompt gives three masks (SAM's small/medium/large outputs). Level
``default`` pools all three, levels ``s``, ``m``, ``l`` take one output each; every level is then
filtered on its own, exactly as segment-anything's ``SamAutomaticMaskGenerator`` filters its one
pooled list:

1. predicted IoU > ``pred_iou_threshold``; stability score ≥ ``stability_threshold``
   (logits against ``mask_threshold ± stability_offset``); masks touching an inner crop edge
   (within 20 px) dropped; masks without pixels dropped (ours: SAM keeps them when its
   thresholds are 0);
2. box NMS per crop (score: predicted IoU), then across crops (score: 1 / crop area, favouring
   masks from smaller crops);
3. holes and islands under ``min_region_area`` px removed, then box NMS favouring the masks this
   left unchanged;
4. LangSplat's mask NMS (IoU ``nms_iou_threshold``, score = stability × predicted IoU over
   ``nms_score_threshold``, containment ``nms_containment_threshold``).

Masks come out in the order these steps leave them (LangSplat paints them in that order, later
masks over earlier ones; :func:`segment_map`). All tensor work stays on the model's device; only
step 3's connected components run on the CPU (scipy).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from itertools import product

import numpy as np
import torch

from thgs.errors import InputError
from thgs.guidance.langsplat import LEVELS
from thgs.guidance.preprocess.masks import (
    box_nms,
    is_box_near_crop_edge,
    langsplat_mask_nms,
    masks_to_boxes,
    remove_small_regions,
    stability_score,
)
from thgs.guidance.preprocess.sam import PointSegmenter

__all__ = [
    "LevelMasks",
    "MaskGeneratorConfig",
    "crop_boxes",
    "generate_masks",
    "point_grid",
    "segment_map",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class MaskGeneratorConfig:
    """Settings of multi-level mask generation; the defaults are LangSplat's.

    Lower ``pred_iou_threshold``, ``stability_threshold`` or ``min_region_area`` keep more
    masks (SAM's ``pred_iou_thresh``, ``stability_score_thresh`` and ``min_mask_region_area``;
    ``thgs preprocess --pred-iou-threshold``, ``--stability-threshold``, ``--min-region-area``).

    Attributes:
        points_per_side: prompts per crop side (the grid has this many squared points).
        points_per_batch: prompts decoded together (memory: 3 × this many masks at crop size).
        pred_iou_threshold: keep masks whose predicted IoU is above this, in [0, 1] (0
            disables).
        stability_threshold: keep masks whose stability score is at least this, in [0, 1] (0
            disables).
        stability_offset: the logit offset of the stability score.
        mask_threshold: a pixel is in a mask where its logit is above this.
        box_nms_threshold: box IoU above which the lower-scored of two masks is dropped, within a
            crop and after the small-region cleanup.
        crop_layers: layers of crops after the whole image (layer i has 2^i × 2^i crops).
        crop_overlap_ratio: crop overlap, as a fraction of the image's shorter side (at layer 1).
        crop_points_downscale: points per side shrink by this factor per crop layer.
        crop_nms_threshold: box IoU for removing duplicates between crops.
        min_region_area: holes and islands smaller than this many pixels are removed (0
            disables the cleanup).
        nms_iou_threshold, nms_score_threshold, nms_containment_threshold: LangSplat's mask NMS.
    """

    points_per_side: int = 32
    points_per_batch: int = 64
    pred_iou_threshold: float = 0.7
    stability_threshold: float = 0.85
    stability_offset: float = 1.0
    mask_threshold: float = 0.0
    box_nms_threshold: float = 0.7
    crop_layers: int = 1
    crop_overlap_ratio: float = 512 / 1500
    crop_points_downscale: int = 1
    crop_nms_threshold: float = 0.7
    min_region_area: int = 100
    nms_iou_threshold: float = 0.8
    nms_score_threshold: float = 0.7
    nms_containment_threshold: float = 0.5

    def __post_init__(self) -> None:
        """Raise :class:`InputError` naming the first invalid setting (its field name)."""
        for name, least in (
            ("points_per_side", 1),
            ("points_per_batch", 1),
            ("crop_layers", 0),
            ("crop_points_downscale", 1),
            ("min_region_area", 0),
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < least:
                raise InputError(name, f"must be an integer ≥ {least}, got {value!r}")
        for name in (
            "pred_iou_threshold",
            "stability_threshold",
            "box_nms_threshold",
            "crop_nms_threshold",
            "nms_iou_threshold",
            "nms_score_threshold",
            "nms_containment_threshold",
        ):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise InputError(name, f"must be in [0, 1], got {value!r}")


@dataclass(frozen=True, eq=False)
class LevelMasks:
    """The masks of one level of one image, in output order.

    Attributes:
        masks: [n, H, W] bool, on the model's device.
        boxes: [n, 4] int64 (x0, y0, x1, y1), inclusive pixel extent of each mask.
        predicted_iou: [n] float32 SAM's predicted IoU.
        stability: [n] float32 stability score.
    """

    masks: torch.Tensor
    boxes: torch.Tensor
    predicted_iou: torch.Tensor
    stability: torch.Tensor

    def __len__(self) -> int:
        return int(self.masks.shape[0])

    def select(self, index: torch.Tensor) -> LevelMasks:
        return LevelMasks(
            self.masks[index], self.boxes[index], self.predicted_iou[index], self.stability[index]
        )


def point_grid(points_per_side: int) -> np.ndarray:
    """[n², 2] float64 (x, y) prompt positions in [0, 1], row by row: an n × n grid of cell
    centres, ``(i + 0.5) / n``."""
    centres = (np.arange(points_per_side) + 0.5) / points_per_side
    ys, xs = np.meshgrid(centres, centres, indexing="ij")
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def crop_boxes(
    height: int, width: int, layers: int, overlap_ratio: float
) -> list[tuple[tuple[int, int, int, int], int]]:
    """SAM's crops: ``[((x0, y0, x1, y1), layer), …]`` in pixels, x1 and y1 exclusive.

    Layer 0 is the whole image; layer i ≥ 1 has 2^i × 2^i crops overlapping by
    ``int(overlap_ratio · min(H, W) · 2 / 2^i)`` px, listed column of crops by column.
    """
    boxes = [((0, 0, width, height), 0)]
    short_side = min(height, width)
    for layer in range(1, layers + 1):
        per_side = 2**layer
        overlap = int(overlap_ratio * short_side * (2 / per_side))
        crop_w = math.ceil((overlap * (per_side - 1) + width) / per_side)
        crop_h = math.ceil((overlap * (per_side - 1) + height) / per_side)
        xs = [int((crop_w - overlap) * i) for i in range(per_side)]
        ys = [int((crop_h - overlap) * i) for i in range(per_side)]
        for x0, y0 in product(xs, ys):
            boxes.append(((x0, y0, min(x0 + crop_w, width), min(y0 + crop_h, height)), layer))
    return boxes


@dataclass(frozen=True, eq=False)
class _CropCandidates:
    """The masks of one crop that survived step 1, at crop size."""

    box: tuple[int, int, int, int]
    masks: torch.Tensor  # [k, h, w] bool
    boxes: torch.Tensor  # [k, 4] int64, image coordinates
    predicted_iou: torch.Tensor  # [k]
    stability: torch.Tensor  # [k]
    output: torch.Tensor  # [k] int64, SAM's multimask output 0, 1, 2


def _crop_candidates(
    segmenter: PointSegmenter,
    image: np.ndarray,
    box: tuple[int, int, int, int],
    layer: int,
    config: MaskGeneratorConfig,
) -> _CropCandidates:
    height, width = image.shape[:2]
    x0, y0, x1, y1 = box
    embedded = segmenter.embed(np.ascontiguousarray(image[y0:y1, x0:x1]))
    side = int(config.points_per_side / config.crop_points_downscale**layer)
    points = torch.from_numpy(point_grid(side) * [x1 - x0, y1 - y0]).float()
    offset = torch.tensor([x0, y0, x0, y0], device=segmenter.device)
    parts: list[tuple[torch.Tensor, ...]] = []
    for start in range(0, len(points), config.points_per_batch):
        low_res, iou = segmenter.decode(embedded, points[start : start + config.points_per_batch])
        low_res, iou = low_res.flatten(0, 1), iou.flatten()
        output = torch.arange(3, device=iou.device).repeat(len(iou) // 3)
        if config.pred_iou_threshold > 0:
            # SAM filters after upsampling; the predicted IoU does not depend on it, so only the
            # masks that pass are upsampled
            keep = iou > config.pred_iou_threshold
            low_res, iou, output = low_res[keep], iou[keep], output[keep]
        logits = segmenter.upsample(low_res, embedded)
        del low_res
        stability = stability_score(logits, config.mask_threshold, config.stability_offset)
        if config.stability_threshold > 0:
            keep = stability >= config.stability_threshold
            logits, iou, output, stability = logits[keep], iou[keep], output[keep], stability[keep]
        masks = logits > config.mask_threshold
        del logits
        boxes = masks_to_boxes(masks)
        keep = masks.flatten(1).any(dim=1) & ~is_box_near_crop_edge(
            boxes, box, (0, 0, width, height)
        )
        parts.append((masks[keep], boxes[keep] + offset, iou[keep], stability[keep], output[keep]))
    masks, boxes, iou, stability, output = (torch.cat(values) for values in zip(*parts))
    return _CropCandidates(box, masks, boxes, iou, stability, output)


def _level_members(candidates: _CropCandidates, level: int) -> torch.Tensor:
    """Indices of a crop's candidates that belong to ``level`` (0 default, 1–3 outputs 0–2)."""
    if level == 0:
        return torch.arange(len(candidates.output), device=candidates.output.device)
    return torch.nonzero(candidates.output == level - 1).flatten()


def _uncrop(masks: torch.Tensor, box: tuple[int, int, int, int], height: int, width: int):
    x0, y0, x1, y1 = box
    full = torch.zeros((len(masks), height, width), dtype=torch.bool, device=masks.device)
    full[:, y0:y1, x0:x1] = masks
    return full


def _gather_level(
    crops: list[_CropCandidates], level: int, height: int, width: int, config: MaskGeneratorConfig
) -> LevelMasks:
    """Step 2 for one level (box NMS per crop, then across crops), masks at full image size."""
    picks = []
    for crop in crops:
        members = _level_members(crop, level)
        order = box_nms(crop.boxes[members], crop.predicted_iou[members], config.box_nms_threshold)
        picks.append((crop, members[order]))
    level_masks = LevelMasks(
        torch.cat([_uncrop(crop.masks[kept], crop.box, height, width) for crop, kept in picks]),
        torch.cat([crop.boxes[kept] for crop, kept in picks]),
        torch.cat([crop.predicted_iou[kept] for crop, kept in picks]),
        torch.cat([crop.stability[kept] for crop, kept in picks]),
    )
    if len(crops) == 1:
        return level_masks
    crop_areas = torch.cat(
        [
            torch.full((len(kept),), float((x1 - x0) * (y1 - y0)), device=kept.device)
            for (x0, y0, x1, y1), kept in ((crop.box, kept) for crop, kept in picks)
        ]
    )
    return level_masks.select(
        box_nms(level_masks.boxes, 1.0 / crop_areas, config.crop_nms_threshold)
    )


def _remove_small_regions(level: LevelMasks, config: MaskGeneratorConfig) -> LevelMasks:
    """Step 3: SAM's ``postprocess_small_regions``."""
    if config.min_region_area <= 0 or len(level) == 0:
        return level
    cleaned, unchanged = [], []
    for mask in level.masks.cpu().numpy():
        mask, changed_holes = remove_small_regions(mask, config.min_region_area, "holes")
        mask, changed_islands = remove_small_regions(mask, config.min_region_area, "islands")
        cleaned.append(mask)
        unchanged.append(not (changed_holes or changed_islands))
    masks = torch.from_numpy(np.stack(cleaned)).to(level.masks.device)
    boxes = masks_to_boxes(masks)
    scores = torch.tensor(unchanged, dtype=torch.float32, device=boxes.device)
    keep = box_nms(boxes, scores, config.box_nms_threshold)
    return LevelMasks(masks, boxes, level.predicted_iou, level.stability).select(keep)


def generate_masks(
    segmenter: PointSegmenter,
    image: np.ndarray,
    config: MaskGeneratorConfig = MaskGeneratorConfig(),
) -> dict[str, LevelMasks]:
    """Multi-level masks of one image.

    Args:
        segmenter: SAM or SAM 2.
        image: [H, W, 3] uint8 RGB.
        config: the generator's settings.

    Returns:
        ``{"default": …, "s": …, "m": …, "l": …}`` (:data:`thgs.guidance.LEVELS` order), each a
        :class:`LevelMasks` at the image's size; a level may have no masks.
    """
    height, width = image.shape[:2]
    crops = [
        _crop_candidates(segmenter, image, box, layer, config)
        for box, layer in crop_boxes(height, width, config.crop_layers, config.crop_overlap_ratio)
    ]
    levels = {}
    for index, name in enumerate(LEVELS):
        level = _remove_small_regions(_gather_level(crops, index, height, width, config), config)
        keep = langsplat_mask_nms(
            level.masks,
            level.stability * level.predicted_iou,
            config.nms_iou_threshold,
            config.nms_score_threshold,
            config.nms_containment_threshold,
        )
        levels[name] = level.select(keep)
    logger.debug(
        "masks per level: %s", ", ".join(f"{name} {len(level)}" for name, level in levels.items())
    )
    return levels


def segment_map(masks: torch.Tensor, first_id: int = 0) -> np.ndarray:
    """Paint masks into one id map, as LangSplat does: later masks over earlier ones.

    Args:
        masks: [n, H, W] bool.
        first_id: the id of mask 0 (LangSplat's level offset); mask i gets ``first_id + i``.

    Returns:
        [H, W] int32, −1 where no mask covers the pixel.
    """
    ids = torch.full(masks.shape[1:], -1, dtype=torch.int32, device=masks.device)
    for index, mask in enumerate(masks):
        ids = torch.where(mask, first_id + index, ids)
    return ids.cpu().numpy()
