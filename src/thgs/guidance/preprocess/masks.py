"""Mask post-processing of SAM's automatic mask generator and LangSplat's extra mask NMS.

Pure functions on torch tensors (any device) and, for connected components, numpy arrays. They
reproduce, rule for rule, what segment-anything's ``SamAutomaticMaskGenerator`` does to its
masks (``segment_anything/utils/amg.py`` plus the generator's calls to torchvision) and what
LangSplat's ``preprocess.py`` does after it (``mask_nms``):

- :func:`stability_score` — amg.py's ``calculate_stability_score``: the IoU of the masks
  thresholded at ``mask_threshold ± offset``;
- :func:`masks_to_boxes` — amg.py's ``batched_mask_to_box``: inclusive (x0, y0, x1, y1) extents;
- :func:`box_nms` — ``torchvision.ops.nms`` (which the generator calls through
  ``batched_nms`` with one category);
- :func:`is_box_near_crop_edge` — amg.py's rule that drops masks cut by an inner crop edge;
- :func:`remove_small_regions` — amg.py's hole filling and island removal (8-connectivity),
  with scipy instead of OpenCV;
- :func:`langsplat_mask_nms` — LangSplat's ``mask_nms``: IoU, score and containment ("inner")
  filtering, with the kept masks in input order (as its ``filter`` keeps them).

Deliberate differences from the references, all in cases the references get wrong or leave
undefined:

- the stability score of a mask with no pixel above ``mask_threshold − offset`` is 0, not
  SAM's 0 / 0 = NaN;
- sorts by score are stable, so equal scores keep input order (torch's default sort, used by
  torchvision and LangSplat, does not promise any order for ties) and results are deterministic;
- LangSplat's fallback "if no mask passes a criterion, keep the 3 best-scored" is written
  ``keep[index, 0] = True`` on 1-D tensors and so crashes whenever it runs; here it does what
  it evidently means (the 3 best-scored, or all masks when there are fewer than 3).

The heavy parts are vectorized on the tensors' device: pairwise mask intersections are one
float32 matrix product per pixel chunk (exact counts, even under TF32), pairwise box IoUs are
computed in row chunks; only the greedy pass of :func:`box_nms` (a loop over the sorted boxes)
and the connected components run on the CPU.
"""

from __future__ import annotations

import logging
from typing import Literal

import numpy as np
import torch
from scipy import ndimage

__all__ = [
    "FALLBACK_TOP_K",
    "INNER_CONTAINED_FRACTION",
    "INNER_CONTAINER_FRACTION",
    "box_nms",
    "is_box_near_crop_edge",
    "langsplat_mask_nms",
    "masks_to_boxes",
    "remove_small_regions",
    "stability_score",
]

logger = logging.getLogger(__name__)

INNER_CONTAINED_FRACTION = 0.85
"""LangSplat's fixed bound: a mask counts as contained in another when at least this fraction of
its area lies in the other …"""

INNER_CONTAINER_FRACTION = 0.5
"""… and the other (the container) has less than this fraction of its area in the first."""

FALLBACK_TOP_K = 3
"""LangSplat's fallback: a criterion that keeps no mask keeps this many best-scored ones."""

_EIGHT_CONNECTED = np.ones((3, 3), dtype=bool)

_INTERSECTION_CHUNK_BYTES = 128 * 2**20
"""Memory bound of the float32 mask block of one pixel chunk in :func:`langsplat_mask_nms`."""

_MAX_CHUNK_PIXELS = 2**24
"""Pixel chunks stay below 2^24 so that float32 partial counts are exact."""

_NMS_CHUNK_ELEMENTS = 2**22
"""Pairs of boxes per IoU chunk in :func:`box_nms` (float32 temporaries of 16 MiB each)."""


def stability_score(logits: torch.Tensor, mask_threshold: float, offset: float) -> torch.Tensor:
    """SAM's stability score: the IoU of a mask thresholded at two levels.

    The mask at ``mask_threshold + offset`` lies inside the one at ``mask_threshold − offset``,
    so their IoU is the ratio of their pixel counts (counted in int64, then divided in float32
    as SAM divides its int32 counts).

    Args:
        logits: [n, H, W] float mask logits.
        mask_threshold: the logit threshold of a mask (SAM: 0.0).
        offset: the threshold offset (SAM: 1.0), in logits.

    Returns:
        [n] float32 in [0, 1]: |logits > t + offset| / |logits > t − offset| per mask, 0 where
        the denominator is 0 (SAM gives NaN there).
    """
    high = (logits > (mask_threshold + offset)).flatten(1).sum(dim=1)
    low = (logits > (mask_threshold - offset)).flatten(1).sum(dim=1)
    ratio = high.to(torch.float32) / low.to(torch.float32)
    return torch.where(low > 0, ratio, torch.zeros_like(ratio))


def masks_to_boxes(masks: torch.Tensor) -> torch.Tensor:
    """The bounding boxes of masks, as SAM's ``batched_mask_to_box``.

    Args:
        masks: [n, H, W] bool; n may be 0.

    Returns:
        [n, 4] int64 (x0, y0, x1, y1): inclusive pixel indices of each mask's extent (x is the
        column, y the row); [0, 0, 0, 0] for an empty mask.
    """
    n, height, width = masks.shape
    if masks.numel() == 0:
        return torch.zeros((n, 4), dtype=torch.int64, device=masks.device)
    masks = masks.bool()
    in_rows = masks.any(dim=2)  # [n, H]
    in_cols = masks.any(dim=1)  # [n, W]
    ys = torch.arange(height, device=masks.device)
    xs = torch.arange(width, device=masks.device)
    y0 = torch.where(in_rows, ys, height).amin(dim=1)
    y1 = torch.where(in_rows, ys, -1).amax(dim=1)
    x0 = torch.where(in_cols, xs, width).amin(dim=1)
    x1 = torch.where(in_cols, xs, -1).amax(dim=1)
    boxes = torch.stack([x0, y0, x1, y1], dim=1)
    empty = y1 < 0
    return torch.where(empty[:, None], torch.zeros_like(boxes), boxes)


def _suppression_matrix(boxes: torch.Tensor, iou_threshold: float) -> np.ndarray:
    """[n, n] bool on the CPU: entry (i, j), j > i, is True when IoU(i, j) > ``iou_threshold``.

    ``boxes`` [n, 4] float (sorted by score). Entries on and below the diagonal are False. The
    arithmetic is torchvision's, in the boxes' dtype.
    """
    n = boxes.shape[0]
    x0, y0, x1, y1 = boxes.unbind(dim=1)
    areas = (x1 - x0) * (y1 - y0)
    threshold = float(np.float32(iou_threshold))
    over = torch.zeros((n, n), dtype=torch.bool, device=boxes.device)
    rows = max(1, _NMS_CHUNK_ELEMENTS // n)
    for start in range(0, n, rows):
        stop = min(n, start + rows)
        width = torch.minimum(x1[start:stop, None], x1[None, start:]) - torch.maximum(
            x0[start:stop, None], x0[None, start:]
        )
        height = torch.minimum(y1[start:stop, None], y1[None, start:]) - torch.maximum(
            y0[start:stop, None], y0[None, start:]
        )
        inter = width.clamp_(min=0) * height.clamp_(min=0)
        union = areas[start:stop, None] + areas[None, start:] - inter
        # 0 / 0 = NaN compares False: a pair with no union never suppresses (as in torchvision).
        over[start:stop, start:] = (inter / union) > threshold
    return torch.triu(over, diagonal=1).cpu().numpy()


def box_nms(boxes: torch.Tensor, scores: torch.Tensor, iou_threshold: float) -> torch.Tensor:
    """Greedy box non-maximum suppression with ``torchvision.ops.nms``'s semantics.

    Boxes are visited by descending score; a box is kept unless its IoU with an already kept
    (higher-scored) box is > ``iou_threshold``. Area = (x1 − x0)·(y1 − y0); IoU =
    intersection / (area_i + area_j − intersection), computed in the boxes' float dtype (integer
    boxes are converted to float32 first, as SAM's ``.float()`` does) exactly as torchvision
    computes it; a pair with zero union never suppresses. The threshold is taken in float32, as
    torchvision's CUDA kernel takes it (its CPU kernel compares in float64, which differs only for
    an IoU equal to float32(threshold) > threshold, e.g. 4/5 against 0.8; never for 0.7).

    Ties in score keep input order (stable sort), so results are deterministic. The IoU matrix
    is computed on the boxes' device in row chunks; the greedy pass runs on the CPU, O(n²).

    Args:
        boxes: [n, 4] float or integer (x0, y0, x1, y1).
        scores: [n] float, higher is better (finite).
        iou_threshold: suppress at IoU strictly above this.

    Returns:
        [k] int64 indices into ``boxes`` of the kept boxes, by descending score, on the boxes'
        device.
    """
    n = boxes.shape[0]
    if n == 0:
        return torch.empty(0, dtype=torch.int64, device=boxes.device)
    if not boxes.is_floating_point():
        boxes = boxes.to(torch.float32)
    order = torch.sort(scores.to(boxes.device), descending=True, stable=True).indices
    over = _suppression_matrix(boxes[order], iou_threshold)
    removed = np.zeros(n, dtype=bool)
    kept = np.zeros(n, dtype=bool)
    for i in range(n):
        if removed[i]:
            continue
        kept[i] = True
        removed |= over[i]
    return order[torch.from_numpy(kept).to(order.device)]


def is_box_near_crop_edge(
    boxes: torch.Tensor,
    crop_box: tuple[int, int, int, int],
    image_box: tuple[int, int, int, int],
    atol: float = 20.0,
) -> torch.Tensor:
    """SAM's test for masks cut by an inner edge of their crop.

    The boxes are shifted from crop to image coordinates by the crop's (x0, y0). A box is near
    the crop edge when one of its 4 coordinates is within ``atol`` (inclusive) of the same
    coordinate of ``crop_box`` and not within ``atol`` of the same coordinate of ``image_box``
    (an edge the crop shares with the image does not cut masks). Compared in float32, as SAM.

    Args:
        boxes: [n, 4] (x0, y0, x1, y1) inclusive pixel boxes in crop coordinates.
        crop_box: (x0, y0, x1, y1) of the crop in the image, in pixels, x1 and y1 exclusive (the
            crop is ``image[y0:y1, x0:x1]``).
        image_box: (0, 0, W, H) of the image.
        atol: tolerance in pixels.

    Returns:
        [n] bool on the boxes' device.
    """
    crop = torch.as_tensor(crop_box, dtype=torch.float32, device=boxes.device)
    image = torch.as_tensor(image_box, dtype=torch.float32, device=boxes.device)
    x0, y0 = crop_box[0], crop_box[1]
    offset = torch.as_tensor([x0, y0, x0, y0], device=boxes.device)
    shifted = (boxes + offset).to(torch.float32)
    near_crop = torch.isclose(shifted, crop[None, :], rtol=0.0, atol=atol)
    near_image = torch.isclose(shifted, image[None, :], rtol=0.0, atol=atol)
    return (near_crop & ~near_image).any(dim=1)


def _bounding_box(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """(r0, r1, c0, c1) inclusive rows and columns of ``mask``'s pixels; None if it has none."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    return int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])


def _outside_component_areas(shape: tuple[int, int], bbox: tuple[int, int, int, int]) -> list[int]:
    """Areas of the 8-connected components of R = image minus the (inclusive) ``bbox``.

    R is one piece unless the box spans the full width (then the strips above and below it are
    apart) or the full height (the strips left and right of it), or R is empty.
    """
    height, width = shape
    r0, r1, c0, c1 = bbox
    full_width = c0 == 0 and c1 == width - 1
    full_height = r0 == 0 and r1 == height - 1
    if full_width and full_height:
        return []
    if full_width:
        strips = [r0 * width, (height - 1 - r1) * width]
    elif full_height:
        strips = [c0 * height, (width - 1 - c1) * height]
    else:
        strips = [height * width - (r1 - r0 + 1) * (c1 - c0 + 1)]
    return [area for area in strips if area > 0]


def _holes_window(
    shape: tuple[int, int], bbox: tuple[int, int, int, int] | None, area_threshold: float
) -> tuple[slice, slice] | None:
    """The window in which labelling the holes of a mask equals labelling the full image.

    The window is the mask's bounding box grown by 1 px (clipped to the image). A component of
    ~mask that does not reach the window's pixels outside the box has the same pixels in the
    window as in the image (all its neighbours lie in the window). One that reaches them is
    connected to R = image minus box (all of R is ~mask), so it is at least as large as a
    component of R; it is large, whatever its area in the window, when every component of R has
    ≥ ``area_threshold`` px. Returns None (label the full image) when that does not hold or the
    mask is empty.
    """
    if bbox is None:
        return None
    if any(area < area_threshold for area in _outside_component_areas(shape, bbox)):
        return None
    height, width = shape
    r0, r1, c0, c1 = bbox
    return slice(max(r0 - 1, 0), min(r1 + 2, height)), slice(max(c0 - 1, 0), min(c1 + 2, width))


def _label(region: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """8-connected labels of ``region`` (0 = outside) and the pixel count of each label."""
    labels, count = ndimage.label(region, structure=_EIGHT_CONNECTED)
    return labels, np.bincount(labels.ravel(), minlength=count + 1)


def _fill_small_holes(mask: np.ndarray, area_threshold: float) -> tuple[np.ndarray, bool]:
    bbox = _bounding_box(mask)
    window = _holes_window(mask.shape, bbox, area_threshold)
    if window is None:
        logger.debug("holes of a %s mask: labelling the full image", list(mask.shape))
        labels, sizes = _label(~mask)
        small = sizes < area_threshold
        region = (slice(None), slice(None))
    else:
        labels, sizes = _label(~mask[window])
        small = sizes < area_threshold
        # Components reaching the window's ring outside the box belong to a large component.
        rows, cols = window
        r0, r1, c0, c1 = bbox
        ring = []
        if rows.start < r0:
            ring.append(labels[0])
        if rows.stop - 1 > r1:
            ring.append(labels[-1])
        if cols.start < c0:
            ring.append(labels[:, 0])
        if cols.stop - 1 > c1:
            ring.append(labels[:, -1])
        if ring:
            small[np.concatenate(ring)] = False
        region = window
    small[0] = False  # label 0: the mask's own pixels
    if not small.any():
        return mask, False
    filled = mask.copy()
    filled[region] |= small[labels]
    return filled, True


def _remove_small_islands(mask: np.ndarray, area_threshold: float) -> tuple[np.ndarray, bool]:
    bbox = _bounding_box(mask)
    if bbox is None:
        return mask, False
    r0, r1, c0, c1 = bbox
    window = (slice(r0, r1 + 1), slice(c0, c1 + 1))  # holds every component, whole
    labels, sizes = _label(mask[window])
    small = sizes[1:] < area_threshold
    if not small.any():
        return mask, False
    keep = np.concatenate([[False], ~small])
    if not keep.any():
        keep[int(np.argmax(sizes[1:])) + 1] = True  # first largest in row-major order
    kept = np.zeros_like(mask)
    kept[window] = keep[labels]
    return kept, True


def remove_small_regions(
    mask: np.ndarray, area_threshold: int, mode: Literal["holes", "islands"]
) -> tuple[np.ndarray, bool]:
    """SAM's removal of small holes or islands of one mask (8-connectivity).

    - ``"holes"``: the 8-connected components of ``~mask`` with fewer than ``area_threshold``
      pixels are added to the mask;
    - ``"islands"``: the 8-connected components of ``mask`` with fewer than ``area_threshold``
      pixels are removed, except that when every component is small the largest is kept (the
      first in row-major order of their first pixels among equally large ones).

    ``changed`` is SAM's flag: True whenever a small component exists, even where the mask comes
    out the same (one small island is kept as the largest). An empty mask's ``~mask`` is the
    whole image, one hole that is filled if the image has fewer than ``area_threshold`` pixels.

    Exact and fast: islands are labelled inside the mask's bounding box only; holes inside the
    box grown by 1 px when that provably gives the full image's answer (see
    :func:`_holes_window`), else in the full image.

    Args:
        mask: [H, W] bool.
        area_threshold: region size in pixels; regions with fewer pixels are small.
        mode: ``"holes"`` or ``"islands"``.

    Returns:
        (mask, changed): the [H, W] bool result (``mask`` itself when nothing changed) and
        whether a small region was found.
    """
    if mode not in ("holes", "islands"):
        raise ValueError(f"mode must be 'holes' or 'islands', got {mode!r}")
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 2:
        raise ValueError(f"mask must be [H, W], got shape {list(mask.shape)}")
    if mode == "holes":
        return _fill_small_holes(mask, area_threshold)
    return _remove_small_islands(mask, area_threshold)


def _pairwise_intersections(masks: torch.Tensor) -> torch.Tensor:
    """[n, n] float64 exact pixel counts of pairwise intersections of [n, H, W] bool masks.

    One float32 matrix product per pixel chunk: the products are 0/1 and every partial sum is an
    integer below 2^24, so each chunk is exact even under TF32; chunks add up in float64.
    """
    n = masks.shape[0]
    flat = masks.reshape(n, -1)
    pixels = flat.shape[1]
    chunk = max(1, min(_MAX_CHUNK_PIXELS, _INTERSECTION_CHUNK_BYTES // (4 * n)))
    total = torch.zeros((n, n), dtype=torch.float64, device=masks.device)
    with torch.autocast(device_type=masks.device.type, enabled=False):
        for start in range(0, pixels, chunk):
            block = flat[:, start : start + chunk].to(torch.float32)
            total += (block @ block.T).to(torch.float64)
    return total


def _keep_or_top(keep: torch.Tensor) -> torch.Tensor:
    """``keep`` (in rank order), or the first FALLBACK_TOP_K ranks if it keeps nothing."""
    ranks = torch.arange(keep.shape[0], device=keep.device)
    return torch.where(keep.any(), keep, ranks < FALLBACK_TOP_K)


def langsplat_mask_nms(
    masks: torch.Tensor,
    scores: torch.Tensor,
    iou_threshold: float = 0.8,
    score_threshold: float = 0.7,
    containment_threshold: float = 0.5,
) -> torch.Tensor:
    """LangSplat's ``mask_nms``: drop duplicate, low-scored and contained masks.

    The masks are ranked by descending score (stable). With I the pairwise intersections and A
    the areas (pixel counts), ratios and IoUs in float32 as the reference computes them, and a
    pair (i, j) with i ranked above j:

    - IoU: IoU(i, j) = I / (A_i + A_j − I) counts against j; a mask is kept when its largest
      IoU with a higher-ranked mask is ≤ ``iou_threshold`` (two empty masks have the reference's
      0 / 0 = NaN IoU, which drops the lower-ranked one);
    - score: a mask is kept when its score > ``score_threshold`` (compared in the scores'
      dtype);
    - containment ("inner"): if I/A_i < 0.5 and I/A_j ≥ 0.85 (j lies in i) the value
      1 − (I/A_j)(I/A_i) counts against j; if I/A_i ≥ 0.85 and I/A_j < 0.5 (i lies in j) the
      same value counts against i. The reference keeps two arrays: ``u`` (upper triangle) takes
      the values against a mask contained in a higher-ranked one, ``l`` (read with
      ``tril(diagonal=1)``) those against a mask contained in a lower-ranked one plus, through
      the first superdiagonal, those against a mask contained in the mask ranked just above it;
      together every pair counts against the contained mask. A mask is kept by an array when its
      largest value there is ≤ 1 − ``containment_threshold``. The 0.5 and 0.85 are the
      reference's constants (:data:`INNER_CONTAINER_FRACTION`, :data:`INNER_CONTAINED_FRACTION`).

    If the score criterion or either containment array keeps no mask, it keeps the 3
    best-scored ones instead (all when n < 3); the IoU criterion has no such fallback. The
    reference means this but writes ``keep[index, 0] = True`` on 1-D tensors, which crashes.
    A mask is kept when it passes all four.

    Intersections are float32 matrix products of the flattened masks, chunked over pixels
    (≤ 128 MiB of temporaries per chunk besides the [n, n] matrices); no host synchronisation
    except for the final index list.

    Args:
        masks: [n, H, W] bool.
        scores: [n] float (LangSplat: stability score × predicted IoU).
        iou_threshold: largest IoU with a higher-ranked mask that a mask may have.
        score_threshold: scores must be above this.
        containment_threshold: LangSplat's ``inner_thr``.

    Returns:
        [k] int64 indices of the kept masks in input order, on the masks' device.
    """
    n = masks.shape[0]
    device = masks.device
    if n == 0:
        return torch.empty(0, dtype=torch.int64, device=device)
    scores = scores.to(device)
    order = torch.sort(scores, descending=True, stable=True).indices
    counts = _pairwise_intersections(masks.bool())[order][:, order]
    areas64 = counts.diagonal()
    union = (areas64[:, None] + areas64[None, :] - counts).to(torch.float32)
    inter = counts.to(torch.float32)
    areas = areas64.to(torch.float32)

    ranks = torch.arange(n, device=device)
    upper = ranks[:, None] < ranks[None, :]  # (i, j) with i ranked above j
    zero = torch.zeros((), dtype=torch.float32, device=device)

    iou = torch.where(upper, inter / union, zero)  # NaN for two empty masks, as the reference
    keep_iou = iou.amax(dim=0) <= iou_threshold

    in_i = inter / areas[:, None]  # I / A_i: the share of row mask i inside column mask j
    in_j = inter / areas[None, :]  # I / A_j
    value = 1 - in_j * in_i
    j_in_i = upper & (in_i < INNER_CONTAINER_FRACTION) & (in_j >= INNER_CONTAINED_FRACTION)
    i_in_j = upper & (in_i >= INNER_CONTAINED_FRACTION) & (in_j < INNER_CONTAINER_FRACTION)
    # The reference's matrix: entry (i, j) for j in i, entry (j, i) for i in j; zero elsewhere.
    inner = torch.where(j_in_i, value, torch.where(i_in_j.T, value.T, zero))
    read_u = ranks[:, None] < ranks[None, :]  # triu(diagonal=1)
    read_l = ranks[None, :] - ranks[:, None] <= 1  # tril(diagonal=1)
    inner_max_u = torch.where(read_u, inner, zero).amax(dim=0)
    inner_max_l = torch.where(read_l, inner, zero).amax(dim=0)
    keep_inner_u = _keep_or_top(inner_max_u <= 1 - containment_threshold)
    keep_inner_l = _keep_or_top(inner_max_l <= 1 - containment_threshold)
    keep_conf = _keep_or_top(scores[order] > score_threshold)

    keep_ranked = keep_iou & keep_conf & keep_inner_u & keep_inner_l
    keep = torch.zeros(n, dtype=torch.bool, device=device)
    keep[order] = keep_ranked
    return torch.nonzero(keep).squeeze(1)
