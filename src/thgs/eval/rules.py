"""The per-image and per-point scoring rules of the benchmark protocols.

Pure functions on arrays; reading labels, rendering and averaging over prompts, frames and
scenes belong to the dataset-level evaluator (``docs/protocols.md`` says how the references
average). Each rule below was read in the reference code (repository and file named).

THGS / P-3D on LERF-OVS (``docs/design.md`` §6):

- :func:`mask_iou`: tp / (tp + fp + fn) of a predicted mask against the category's mask.
- :func:`pixel_accuracy`: (tp + tn) / (H·W), what the THGS code calls "mAcc".

LangSplat's 2D protocol (github.com/minghanqin/LangSplat, ``eval/evaluate_iou_loc.py``
``activate_stream`` and ``lerf_localization``; ``eval/utils.py`` ``smooth``):

- :func:`box_filter`: ``cv2.filter2D(r, -1, np.ones((30, 30)) / 900)``, a mean over a 30×30
  window with OpenCV's default anchor (``ksize / 2``: offsets −15 … 14, as ``normalizeAnchor`` in
  OpenCV's imgproc sets it) and default border ``BORDER_REFLECT_101`` (``gfedcb|abcdefgh|gfedcba``,
  the rule of OpenCV's ``borderInterpolate``, repeated for windows wider than the image).
- :func:`langsplat_mask`: per level, the map mixed ``0.5 * (box + raw)``; ``x − min``, divided by
  ``max + 1e-9``; ``2x − 1``; clipped to [0, 1]; ``> 0.4`` (the ``--mask_thresh`` default); then
  ``smooth``.
- :func:`majority_filter`: ``smooth``, the majority (mode) of a binary mask over the window
  ``mask[max(0, i−3) : min(i+4, h−1), max(0, j−3) : min(j+4, w−1)]`` (the upper bounds clip to
  h − 1 and w − 1, so the last row and column never vote), ties to 0
  (``argmax(bincount(...))``).
- :func:`langsplat_level`: the level whose mixed map has the highest peak
  (``torch.argmax``: the first on ties); its mask is the one scored.
- :func:`langsplat_localized`: per level the peak of the smoothed map only (not mixed; the
  function recomputes the raw maps), the level with the highest peak (``np.argmax``), and a hit
  when any pixel attaining that peak, as (x = column, y = row), lies in any ground-truth box with
  inclusive bounds ``min(x1, x2) ≤ x ≤ max(x1, x2)``, ``min(y1, y2) ≤ y ≤ max(y1, y2)``.

OpenGaussian's LERF protocol (github.com/yanmin-wu/OpenGaussian, read in the copy
github.com/zhgulden/OpenGaussian-, ``render_lerf_by_text.py``): the rendered silhouette of the
selected clusters is kept where ``> 0.7`` (:data:`OPENGAUSSIAN_THRESHOLD`), for the fixed prompt
lists ``scene_texts`` (:data:`OPENGAUSSIAN_LERF_PROMPTS`).

OpenGaussian's ScanNet protocol (same repository, ``scripts/eval_scannet.py``,
``calculate_metrics``): :func:`scannet_scores`.

OpenHype's ScanNet++ protocol (github.com/lisaweijler/openhype,
``openhype/openhype_eval/scannetpp_evaluator.py``): :func:`openhype_localized`, LangSplat's
localization on the map its mask step has already mixed in place, applied to a predicted mask.

Deviations, all documented per function: arithmetic is float64 (the references use float32,
and OpenCV may filter the 30×30 kernel through the DFT), so pixels within ~1e-7 of a threshold
or a peak may decide differently; :func:`mask_iou` scores two empty masks 1.0 (LangSplat divides
0 by 0, OpenGaussian's ``compute_lerf_iou.py`` returns 0; ground-truth masks are never empty);
:func:`majority_filter` rejects masks narrower than 2 pixels (the reference's window is empty
there and its ``argmax`` fails); :func:`scannet_scores` reports NaN, not 0, for classes absent
from the ground truth (they are left out of the means either way).
"""

from __future__ import annotations

import types
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from thgs.errors import InputError

__all__ = [
    "OPENGAUSSIAN_LERF_PROMPTS",
    "OPENGAUSSIAN_THRESHOLD",
    "ClassScores",
    "box_filter",
    "langsplat_level",
    "langsplat_localized",
    "langsplat_mask",
    "langsplat_query",
    "majority_filter",
    "mask_iou",
    "openhype_localized",
    "pixel_accuracy",
    "scannet_scores",
]

OPENGAUSSIAN_THRESHOLD: float = 0.7
"""OpenGaussian's LERF masks: rendered silhouette ``> 0.7`` (strictly), per prompt and frame."""

OPENGAUSSIAN_LERF_PROMPTS: Mapping[str, tuple[str, ...]] = types.MappingProxyType(
    {
        "figurines": (
            "jake",
            "pirate hat",
            "pikachu",
            "rubber duck with hat",
            "porcelain hand",
            "red apple",
            "tesla door handle",
            "waldo",
            "bag",
            "toy cat statue",
            "miffy",
            "green apple",
            "pumpkin",
            "rubics cube",
            "old camera",
            "rubber duck with buoy",
            "red toy chair",
            "pink ice cream",
            "spatula",
            "green toy chair",
            "toy elephant",
        ),
        "ramen": (
            "nori",
            "sake cup",
            "kamaboko",
            "corn",
            "spoon",
            "egg",
            "onion segments",
            "plate",
            "napkin",
            "bowl",
            "glass of water",
            "hand",
            "chopsticks",
            "wavy noodles",
        ),
        "teatime": (
            "sheep",
            "yellow pouf",
            "stuffed bear",
            "coffee mug",
            "tea in a glass",
            "apple",
            "coffee",
            "hooves",
            "bear nose",
            "dall-e brand",
            "plate",
            "paper napkin",
            "three cookies",
            "bag of cookies",
        ),
        "waldo_kitchen": (
            "Stainless steel pots",
            "dark cup",
            "refrigerator",
            "frog cup",
            "pot",
            "spatula",
            "plate",
            "spoon",
            "toaster",
            "ottolenghi",
            "plastic ladle",
            "sink",
            "ketchup",
            "cabinet",
            "red cup",
            "pour-over vessel",
            "knife",
            "yellow desk",
        ),
    }
)
"""OpenGaussian's LERF text queries per scene (``scene_texts``), spelled as in its source and in
LangSplat's labels. A labelled category outside its scene's list has no rendered mask and scores
IoU 0 in OpenGaussian's ``scripts/compute_lerf_iou.py``."""

_LANGSPLAT_WINDOW = 30
_LANGSPLAT_EPSILON = 1e-9


def _mask_pair(name: str, predicted: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, ...]:
    """``predicted`` and ``truth`` as [H, W] bool, after checking shapes and dtypes."""
    predicted = np.asarray(predicted)
    truth = np.asarray(truth)
    if predicted.shape != truth.shape or predicted.ndim != 2 or predicted.size == 0:
        raise InputError(
            name, f"predicted {predicted.shape} and truth {truth.shape} must be the same [H, W]"
        )
    for label, mask in (("predicted", predicted), ("truth", truth)):
        if mask.dtype != bool and not np.issubdtype(mask.dtype, np.integer):
            raise InputError(name, f"{label} is {mask.dtype}; expected a bool or integer mask")
    return predicted != 0, truth != 0


def mask_iou(predicted: np.ndarray, truth: np.ndarray) -> float:
    """Intersection over union of two masks: tp / (tp + fp + fn).

    Args:
        predicted: [H, W] bool (or integer, nonzero = in) predicted mask.
        truth: [H, W] bool (or integer) ground-truth mask, same shape.

    Returns:
        IoU in [0, 1]. Both masks empty → 1.0 (they agree); an empty truth with a non-empty
        prediction → 0.0, as is an empty prediction against a non-empty truth.

    Raises:
        InputError: shapes differ, are not 2-D or empty, or a mask is not bool or integer.
    """
    predicted, truth = _mask_pair("mask_iou", predicted, truth)
    union = np.count_nonzero(predicted | truth)
    if union == 0:
        return 1.0
    return np.count_nonzero(predicted & truth) / union


def pixel_accuracy(predicted: np.ndarray, truth: np.ndarray) -> float:
    """The share of pixels where the masks agree: (tp + tn) / (H·W), the THGS code's "mAcc".

    Args:
        predicted: [H, W] bool (or integer, nonzero = in) predicted mask.
        truth: [H, W] bool (or integer) ground-truth mask, same shape.

    Returns:
        accuracy in [0, 1].

    Raises:
        InputError: shapes differ, are not 2-D or empty, or a mask is not bool or integer.
    """
    predicted, truth = _mask_pair("pixel_accuracy", predicted, truth)
    return np.count_nonzero(predicted == truth) / predicted.size


def _real_maps(name: str, maps: np.ndarray, ndim: int, shape: str) -> np.ndarray:
    """``maps`` as float64 after checking it is a finite, non-empty array of ``ndim`` axes."""
    maps = np.asarray(maps)
    if maps.ndim != ndim or maps.size == 0:
        raise InputError(name, f"expected {shape}, got shape {maps.shape}")
    if maps.dtype == bool or not np.issubdtype(maps.dtype, np.number):
        raise InputError(name, f"expected real values, got {maps.dtype}")
    maps = maps.astype(np.float64)
    if not np.isfinite(maps).all():
        raise InputError(name, "has NaN or infinite values")
    return maps


def _reflect_101(positions: np.ndarray, length: int) -> np.ndarray:
    """Indices into an axis of ``length`` for ``positions`` outside it, mirrored about the end
    pixels without repeating them (OpenCV's ``BORDER_REFLECT_101``, periodic beyond one mirror)."""
    if length == 1:
        return np.zeros_like(positions)
    period = 2 * (length - 1)
    folded = np.mod(positions, period)
    return np.where(folded < length, folded, period - folded)


def box_filter(image: np.ndarray, size: int = 30) -> np.ndarray:
    """The mean over a ``size``×``size`` window, as ``cv2.filter2D(image, -1, ones / size²)``.

    The window around pixel (i, j) spans rows ``i − size//2 … i + size − size//2 − 1`` (and the
    same for columns): OpenCV's default anchor at ``(size/2, size/2)`` of the kernel, so an even
    window reaches one pixel further up and left than down and right. Pixels outside the image
    are read mirrored without repeating the edge (``BORDER_REFLECT_101``: ``cba|abc`` → ``b``
    before ``a``), repeatedly for windows wider than the image; a one-pixel-wide axis repeats its
    pixel. Each output sums its own window in the same order, so equal windows give bit-equal
    means (plateaus stay exactly flat).

    Args:
        image: [H, W] real values.
        size: window side in pixels, ≥ 1 (LangSplat: 30).

    Returns:
        [H, W] float64 window means.

    Raises:
        InputError: ``image`` is not a finite non-empty [H, W] array, or ``size`` < 1.
    """
    image = _real_maps("box_filter", image, 2, "an [H, W] image")
    if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size < 1:
        raise InputError("box_filter", f"size must be an integer ≥ 1, got {size!r}")
    height, width = image.shape
    before = size // 2
    after = size - before - 1
    rows = _reflect_101(np.arange(-before, height + after), height)
    cols = _reflect_101(np.arange(-before, width + after), width)
    padded = image[np.ix_(rows, cols)]
    sums = sliding_window_view(padded, size, axis=0).sum(axis=-1)
    sums = sliding_window_view(sums, size, axis=1).sum(axis=-1)
    return sums / (size * size)


def majority_filter(mask: np.ndarray, *, radius: int = 3) -> np.ndarray:
    """LangSplat's ``smooth``: each pixel becomes the majority value of a window around it.

    The window of pixel (i, j) is rows ``max(0, i − radius) … min(i + radius + 1, H − 1) − 1``
    and columns likewise: LangSplat's slice bounds, whose upper end is clipped to H − 1 (W − 1),
    so the last row and column never vote (not even for themselves). A pixel is on when more
    than half of its window is on; ties turn it off.

    Args:
        mask: [H, W] bool (or integer, nonzero = on) with H, W ≥ 2.
        radius: window half-size in pixels (LangSplat: 3, a 7×7 window inside the image).

    Returns:
        [H, W] bool filtered mask.

    Raises:
        InputError: ``mask`` is not a bool or integer [H, W] array with H, W ≥ 2, or ``radius``
            < 0.
    """
    mask = np.asarray(mask)
    if mask.ndim != 2 or min(mask.shape) < 2:
        raise InputError("majority_filter", f"expected an [H, W] mask, H, W ≥ 2, got {mask.shape}")
    if mask.dtype != bool and not np.issubdtype(mask.dtype, np.integer):
        raise InputError("majority_filter", f"mask is {mask.dtype}; expected bool or integer")
    if isinstance(radius, bool) or not isinstance(radius, (int, np.integer)) or radius < 0:
        raise InputError("majority_filter", f"radius must be an integer ≥ 0, got {radius!r}")
    height, width = mask.shape
    counts = np.zeros((height + 1, width + 1), dtype=np.int64)
    counts[1:, 1:] = np.cumsum(np.cumsum(mask != 0, axis=0, dtype=np.int64), axis=1)
    row_low = np.maximum(np.arange(height) - radius, 0)[:, None]
    row_high = np.minimum(np.arange(height) + radius + 1, height - 1)[:, None]
    col_low = np.maximum(np.arange(width) - radius, 0)[None, :]
    col_high = np.minimum(np.arange(width) + radius + 1, width - 1)[None, :]
    on = (
        counts[row_high, col_high]
        - counts[row_low, col_high]
        - counts[row_high, col_low]
        + counts[row_low, col_low]
    )
    area = (row_high - row_low) * (col_high - col_low)
    return 2 * on > area


def _mixed(relevancy: np.ndarray, smoothed: np.ndarray) -> np.ndarray:
    """LangSplat's per-level map: the raw map mixed half-half with its 30×30 box mean
    (``smoothed``, :func:`box_filter` of ``relevancy``)."""
    return 0.5 * (smoothed + relevancy)


def _mask_of_mixed(mixed: np.ndarray, threshold: float) -> np.ndarray:
    shifted = mixed - mixed.min()
    normalized = shifted / (shifted.max() + _LANGSPLAT_EPSILON)
    scaled = np.clip(2.0 * normalized - 1.0, 0.0, 1.0)
    return majority_filter(scaled > threshold)


def _level_of(relevancy: np.ndarray, smoothed: list[np.ndarray]) -> int:
    return int(np.argmax([_mixed(r, b).max() for r, b in zip(relevancy, smoothed)]))


def _peak_in_boxes(smoothed: list[np.ndarray], boxes: np.ndarray) -> bool:
    chosen = smoothed[int(np.argmax([level.max() for level in smoothed]))]
    rows, cols = np.nonzero(chosen == chosen.max())
    x_low = np.minimum(boxes[:, 0], boxes[:, 2])[:, None]
    x_high = np.maximum(boxes[:, 0], boxes[:, 2])[:, None]
    y_low = np.minimum(boxes[:, 1], boxes[:, 3])[:, None]
    y_high = np.maximum(boxes[:, 1], boxes[:, 3])[:, None]
    inside = (cols >= x_low) & (cols <= x_high) & (rows >= y_low) & (rows <= y_high)
    return bool(inside.any())


def langsplat_mask(relevancy: np.ndarray, threshold: float = 0.4) -> np.ndarray:
    """LangSplat's predicted mask from the relevancy map of one level.

    Steps (``activate_stream`` in ``eval/evaluate_iou_loc.py``): mix
    ``m = 0.5 * (box_filter(r, 30) + r)``; normalize ``n = (m − min m) / (max(m − min m) + 1e-9)``;
    map ``2n − 1`` and clip to [0, 1]; keep ``> threshold``; then :func:`majority_filter`. With the
    default 0.4 a pixel is kept when its normalized mixed value exceeds 0.7. A constant map gives
    an empty mask, and so does a map whose range is far below 1e-9.

    Args:
        relevancy: [H, W] relevancy of one query at one level, H, W ≥ 2.
        threshold: cut on the ``2n − 1`` value (LangSplat's ``--mask_thresh``, 0.4).

    Returns:
        [H, W] bool mask.

    Raises:
        InputError: ``relevancy`` is not a finite [H, W] array with H, W ≥ 2.
    """
    relevancy = _real_maps("langsplat_mask", relevancy, 2, "an [H, W] relevancy map")
    if min(relevancy.shape) < 2:
        raise InputError("langsplat_mask", f"needs H, W ≥ 2, got {relevancy.shape}")
    smoothed = box_filter(relevancy, _LANGSPLAT_WINDOW)
    return _mask_of_mixed(_mixed(relevancy, smoothed), threshold)


def langsplat_level(relevancy: np.ndarray) -> int:
    """The level LangSplat scores: the highest peak of the mixed maps ``0.5 * (box + raw)``.

    Args:
        relevancy: [L, H, W] relevancy of one query at each of L levels.

    Returns:
        the level index in [0, L); the first on ties.

    Raises:
        InputError: ``relevancy`` is not a finite non-empty [L, H, W] array.
    """
    relevancy = _real_maps("langsplat_level", relevancy, 3, "[L, H, W] relevancy maps")
    return _level_of(relevancy, [box_filter(level, _LANGSPLAT_WINDOW) for level in relevancy])


def _checked_boxes(
    boxes: Sequence[tuple[float, float, float, float]], name: str = "langsplat_localized"
) -> np.ndarray:
    """``boxes`` as a [B, 4] float64 array of finite (x1, y1, x2, y2), B ≥ 1."""
    try:
        array = np.asarray(boxes, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(name, "boxes must be (x1, y1, x2, y2) numbers") from exc
    if array.ndim != 2 or array.shape[1] != 4 or len(array) == 0:
        raise InputError(
            name, f"boxes must be one or more (x1, y1, x2, y2), got shape {array.shape}"
        )
    if not np.isfinite(array).all():
        raise InputError(name, "boxes have NaN or infinite values")
    return array


def langsplat_localized(
    relevancy: np.ndarray, boxes: Sequence[tuple[float, float, float, float]]
) -> bool:
    """LangSplat's localization hit: is the smoothed relevancy peak inside a ground-truth box?

    Steps (``lerf_localization`` in ``eval/evaluate_iou_loc.py``): per level the 30×30
    :func:`box_filter` of the raw map (not mixed with it) and its peak; the level with the
    highest peak (the first on ties); every pixel of that level equal to the peak, as
    (x = column, y = row); a hit when any of them lies in any box, bounds inclusive, a box's
    corners taken in either order.

    Args:
        relevancy: [L, H, W] relevancy of one query at each of L levels.
        boxes: one or more (x1, y1, x2, y2) ground-truth boxes in the maps' pixel coordinates
            (x = column, y = row).

    Returns:
        True when a peak pixel of the chosen level lies in a box.

    Raises:
        InputError: ``relevancy`` is not a finite non-empty [L, H, W] array, or ``boxes`` is
            empty, not 4 numbers each, or not finite.
    """
    relevancy = _real_maps("langsplat_localized", relevancy, 3, "[L, H, W] relevancy maps")
    boxes = _checked_boxes(boxes)
    return _peak_in_boxes([box_filter(level, _LANGSPLAT_WINDOW) for level in relevancy], boxes)


def langsplat_query(
    relevancy: np.ndarray,
    boxes: Sequence[tuple[float, float, float, float]],
    threshold: float = 0.4,
) -> tuple[int, np.ndarray, bool]:
    """One query of LangSplat's protocol: :func:`langsplat_level`, then :func:`langsplat_mask`
    of that level and :func:`langsplat_localized`, with each level's 30×30 box mean computed
    once for the three (the same numbers, bit for bit, as calling them one by one).

    Args:
        relevancy: [L, H, W] relevancy of one query at each of L levels, H, W ≥ 2.
        boxes: one or more (x1, y1, x2, y2) ground-truth boxes (:func:`langsplat_localized`).
        threshold: the mask's cut (:func:`langsplat_mask`).

    Returns:
        ``(level index, [H, W] bool mask of that level, localization hit)``.

    Raises:
        InputError: what the three functions refuse.
    """
    relevancy = _real_maps("langsplat_query", relevancy, 3, "[L, H, W] relevancy maps")
    if min(relevancy.shape[1:]) < 2:
        raise InputError("langsplat_query", f"needs H, W ≥ 2, got {relevancy.shape[1:]}")
    boxes = _checked_boxes(boxes)
    smoothed = [box_filter(level, _LANGSPLAT_WINDOW) for level in relevancy]
    chosen = _level_of(relevancy, smoothed)
    mask = _mask_of_mixed(_mixed(relevancy[chosen], smoothed[chosen]), threshold)
    return chosen, mask, _peak_in_boxes(smoothed, boxes)


def openhype_localized(
    predicted: np.ndarray, boxes: Sequence[tuple[float, float, float, float]]
) -> bool:
    """OpenHype's localization hit, on a predicted mask: is the peak of the twice-smoothed
    prediction inside a ground-truth box?

    OpenHype's ``scannetpp_evaluator.py`` scores a relevancy map ``r`` twice per query: its mask
    step (``_get_mask_segmentation_results``) first overwrites ``r`` in place with the mixed
    ``m = 0.5 · (box_filter(r, 30) + r)``, and its localization step
    (``_get_localization_results``, LangSplat's ``lerf_localization``) then takes the 30×30
    :func:`box_filter` of that already mixed map, its peak, and every pixel attaining it as
    (x = column, y = row): a hit when one lies in one of the boxes, bounds inclusive, corners in
    either order (its two "levels" are copies of one map, so the first is chosen). Here ``r`` is
    the predicted mask as 0/1. An empty prediction is a miss: every pixel of a constant map
    attains its peak, so the reference rule would call it a hit whenever a box lies in the image.

    Args:
        predicted: [H, W] bool (or integer, nonzero = in) predicted mask.
        boxes: one or more (x1, y1, x2, y2) ground-truth boxes in the mask's pixel coordinates
            (x = column, y = row).

    Returns:
        True when a peak pixel lies in a box.

    Raises:
        InputError: ``predicted`` is not a non-empty [H, W] bool or integer mask, or ``boxes``
            is empty, not 4 numbers each, or not finite.
    """
    mask = np.asarray(predicted)
    if mask.ndim != 2 or mask.size == 0:
        raise InputError("openhype_localized", f"expected an [H, W] mask, got shape {mask.shape}")
    if mask.dtype != bool and not np.issubdtype(mask.dtype, np.integer):
        raise InputError("openhype_localized", f"expected a bool or integer mask, got {mask.dtype}")
    boxes = _checked_boxes(boxes, "openhype_localized")
    if not mask.any():
        return False
    relevancy = (mask != 0).astype(np.float64)
    mixed = _mixed(relevancy, box_filter(relevancy, _LANGSPLAT_WINDOW))
    return _peak_in_boxes([box_filter(mixed, _LANGSPLAT_WINDOW)], boxes)


@dataclass(frozen=True)
class ClassScores:
    """Per-class scores of a point labelling (OpenGaussian's ScanNet protocol).

    Attributes:
        classes: the evaluated class ids, in the order given.
        iou: [K] float64 tp / (tp + fp + fn) per class; NaN for classes absent from the kept
            ground truth. Read-only.
        accuracy: [K] float64 tp / (tp + fn) per class (recall); NaN when absent. Read-only.
        miou: mean of ``iou`` over the classes present; NaN when none is.
        macc: mean of ``accuracy`` over the classes present; NaN when none is.
        points: the points scored (opacity kept and ground truth among ``classes``).
    """

    classes: tuple[int, ...]
    iou: np.ndarray
    accuracy: np.ndarray
    miou: float
    macc: float
    points: int


def _int_labels(name: str, values: np.ndarray) -> np.ndarray:
    """``values`` as an [N] int64 array after checking it is an integer vector."""
    values = np.asarray(values)
    if values.ndim != 1:
        raise InputError("scannet_scores", f"{name} must be [N], got shape {values.shape}")
    if values.dtype == bool or not np.issubdtype(values.dtype, np.integer):
        raise InputError("scannet_scores", f"{name} must be integer ids, got {values.dtype}")
    return values.astype(np.int64)


def scannet_scores(
    predicted: np.ndarray,
    truth: np.ndarray,
    opacity: np.ndarray,
    classes: Sequence[int],
    *,
    min_opacity: float = 0.1,
) -> ClassScores:
    """Per-class IoU and accuracy of point labels, by OpenGaussian's ``eval_scannet.py`` rule.

    A point is scored when its opacity is ≥ ``min_opacity`` (OpenGaussian ignores
    ``sigmoid(opacity) < 0.1``) and its ground-truth id is one of ``classes`` (the others are
    remapped to 0 = ignored there). Only scored points count anywhere: OpenGaussian sets the
    prediction of ignored points to 0 before counting, so a prediction of class c on an ignored
    point is no false positive of c. Per class c over the scored points: tp = truth c and
    predicted c, fp = predicted c with another truth, fn = truth c predicted otherwise; IoU
    = tp / (tp + fp + fn), accuracy = tp / (tp + fn); both are averaged over the classes present
    in the scored ground truth. A point may also predict −1, no class (e.g. its region was
    never seen): a miss of its true class and a false positive of none (OpenGaussian assigns
    every point a class, so it has no such points).

    Args:
        predicted: [N] integer class id per point, each one of ``classes`` or −1.
        truth: [N] integer ground-truth id per point (NYU40 ids for ScanNet, 0 = unannotated);
            ids outside ``classes`` are ignored.
        opacity: [N] activated opacity per point, in [0, 1].
        classes: the K ≥ 1 distinct evaluated ids (e.g. :data:`~thgs.eval.SCANNET19_IDS`).
        min_opacity: points below it are dropped (OpenGaussian: 0.1).

    Returns:
        the scores, classes in the order given.

    Raises:
        InputError: arrays not [N] of one length, ``predicted`` or ``truth`` not integer,
            ``opacity`` or ``min_opacity`` not finite in [0, 1], ``classes`` empty or repeated,
            ``classes`` holding −1, or a prediction outside ``classes`` and not −1.
    """
    predicted = _int_labels("predicted", predicted)
    truth = _int_labels("truth", truth)
    opacity = np.asarray(opacity)
    if opacity.shape != predicted.shape or truth.shape != predicted.shape:
        raise InputError(
            "scannet_scores",
            f"predicted {predicted.shape}, truth {truth.shape} and opacity {opacity.shape} "
            "must be the same [N]",
        )
    if opacity.dtype == bool or not np.issubdtype(opacity.dtype, np.number):
        raise InputError("scannet_scores", f"opacity must be real values, got {opacity.dtype}")
    if not (np.isfinite(opacity).all() and (opacity >= 0).all() and (opacity <= 1).all()):
        raise InputError("scannet_scores", "opacity must be finite activated values in [0, 1]")
    if not 0 <= min_opacity <= 1:
        raise InputError("scannet_scores", f"min_opacity must be in [0, 1], got {min_opacity!r}")
    try:
        ids = np.asarray(classes)
    except (TypeError, ValueError) as exc:
        raise InputError("scannet_scores", "classes must be integer ids") from exc
    if ids.ndim != 1 or ids.size == 0 or not np.issubdtype(ids.dtype, np.integer):
        raise InputError("scannet_scores", f"classes must be one or more integer ids: {classes}")
    if np.unique(ids).size != ids.size:
        raise InputError("scannet_scores", f"classes repeat an id: {classes}")
    if (ids == -1).any():
        raise InputError("scannet_scores", "classes must not hold −1 (it means no prediction)")
    order = np.argsort(ids)
    sorted_ids = ids[order]
    slot = np.minimum(np.searchsorted(sorted_ids, predicted), ids.size - 1)
    unknown = (sorted_ids[slot] != predicted) & (predicted != -1)
    if unknown.any():
        raise InputError(
            "scannet_scores",
            f"predicted ids {np.unique(predicted[unknown])[:10].tolist()} are not in classes",
        )
    truth_slot = np.minimum(np.searchsorted(sorted_ids, truth), ids.size - 1)
    keep = (opacity >= min_opacity) & (sorted_ids[truth_slot] == truth)
    k = ids.size
    predicted_index = np.where(predicted[keep] == -1, k, order[slot[keep]])  # k: no class
    truth_index = order[truth_slot[keep]]
    confusion = np.bincount(truth_index * (k + 1) + predicted_index, minlength=k * (k + 1))
    confusion = confusion.reshape(k, k + 1)
    hits = np.diag(confusion[:, :k]).astype(np.float64)
    in_truth = confusion.sum(axis=1)
    in_prediction = confusion[:, :k].sum(axis=0)
    present = in_truth > 0
    iou = np.full(k, np.nan)
    accuracy = np.full(k, np.nan)
    iou[present] = hits[present] / (in_truth + in_prediction - hits)[present]
    accuracy[present] = hits[present] / in_truth[present]
    iou.setflags(write=False)
    accuracy.setflags(write=False)
    return ClassScores(
        classes=tuple(int(i) for i in ids),
        iou=iou,
        accuracy=accuracy,
        miou=float(iou[present].mean()) if present.any() else float("nan"),
        macc=float(accuracy[present].mean()) if present.any() else float("nan"),
        points=int(keep.sum()),
    )
