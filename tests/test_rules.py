"""Protocol scoring rules against hand-computed cases and brute-force transcriptions."""

from __future__ import annotations

import numpy as np
import pytest

from thgs.errors import InputError
from thgs.eval.rules import (
    OPENGAUSSIAN_LERF_PROMPTS,
    OPENGAUSSIAN_THRESHOLD,
    box_filter,
    langsplat_level,
    langsplat_localized,
    langsplat_mask,
    langsplat_query,
    majority_filter,
    mask_iou,
    pixel_accuracy,
    scannet_scores,
)

# 3×4 masks: tp at (0, 0) and (1, 0); fp at (0, 1); fn at (1, 1) and (2, 3); 7 tn
PREDICTED = np.array([[1, 1, 0, 0], [1, 0, 0, 0], [0, 0, 0, 0]], dtype=bool)
TRUTH = np.array([[1, 0, 0, 0], [1, 1, 0, 0], [0, 0, 0, 1]], dtype=bool)
EMPTY = np.zeros((3, 4), dtype=bool)


def test_mask_iou_and_pixel_accuracy_hand_cases():
    assert mask_iou(PREDICTED, TRUTH) == pytest.approx(2 / 5)
    assert pixel_accuracy(PREDICTED, TRUTH) == pytest.approx(9 / 12)
    assert mask_iou(TRUTH, TRUTH) == 1.0
    assert pixel_accuracy(TRUTH, TRUTH) == 1.0
    assert mask_iou(EMPTY, TRUTH) == 0.0
    assert pixel_accuracy(EMPTY, TRUTH) == pytest.approx(8 / 12)
    assert mask_iou(PREDICTED, EMPTY) == 0.0
    assert pixel_accuracy(PREDICTED, EMPTY) == pytest.approx(9 / 12)
    assert mask_iou(EMPTY, EMPTY) == 1.0
    assert pixel_accuracy(EMPTY, EMPTY) == 1.0
    assert mask_iou(PREDICTED.astype(np.uint8) * 255, TRUTH.astype(np.int64)) == pytest.approx(0.4)


def test_masks_are_checked():
    with pytest.raises(InputError, match=r"mask_iou: .*\(3, 4\).*\(4, 3\)"):
        mask_iou(PREDICTED, TRUTH.T)
    with pytest.raises(InputError, match=r"pixel_accuracy: .*same"):
        pixel_accuracy(PREDICTED.ravel(), TRUTH.ravel())
    with pytest.raises(InputError, match="predicted is float64"):
        mask_iou(PREDICTED.astype(float), TRUTH)


def _reflect_101(p: int, length: int) -> int:
    """OpenCV's borderInterpolate for BORDER_REFLECT_101, one step at a time."""
    if length == 1:
        return 0
    while not 0 <= p < length:
        p = -p if p < 0 else 2 * (length - 1) - p
    return p


def _brute_force_filter2d(image: np.ndarray, size: int) -> np.ndarray:
    """filter2D with a size×size kernel of 1/size², anchor (size//2, size//2)."""
    height, width = image.shape
    anchor = size // 2
    out = np.zeros_like(image, dtype=np.float64)
    for i in range(height):
        for j in range(width):
            total = 0.0
            for u in range(size):
                for v in range(size):
                    row = _reflect_101(i + u - anchor, height)
                    col = _reflect_101(j + v - anchor, width)
                    total += image[row, col] / size**2
            out[i, j] = total
    return out


def test_box_filter_hand_case():
    # an even window covers offsets −1 … 0; the single row repeats itself
    assert box_filter(np.array([[1.0, 2.0, 3.0]]), 2) == pytest.approx(np.array([[1.5, 1.5, 2.5]]))
    # reflect-101 at the left border reads column 1 for column −1: mean(1.5, 1, 1.5) = 4/3
    out = box_filter(np.array([[1.0, 1.5, 9.0]] * 3), 3)
    assert out[1, 0] == pytest.approx((1.5 + 1.0 + 1.5) / 3)
    assert np.array_equal(box_filter(np.full((7, 5), 0.3), 30), np.full((7, 5), 0.3))


@pytest.mark.parametrize(
    ("height", "width", "size"),
    [(6, 7, 1), (6, 7, 2), (5, 8, 3), (9, 6, 4), (1, 5, 3), (4, 1, 6), (3, 5, 7), (4, 3, 30)],
)
def test_box_filter_matches_brute_force(height, width, size):
    rng = np.random.default_rng(height * 100 + width * 10 + size)
    image = rng.normal(size=(height, width))
    assert np.allclose(box_filter(image, size), _brute_force_filter2d(image, size), atol=1e-12)


def test_box_filter_checks_inputs():
    with pytest.raises(InputError, match=r"box_filter: expected an \[H, W\] image"):
        box_filter(np.zeros((2, 2, 3)))
    with pytest.raises(InputError, match="box_filter: size"):
        box_filter(np.zeros((2, 2)), 0)
    with pytest.raises(InputError, match="box_filter: has NaN"):
        box_filter(np.array([[0.0, np.nan]]))


def _brute_force_smooth(mask: np.ndarray, radius: int = 3) -> np.ndarray:
    """LangSplat's smooth(): the most common value of each clipped window, 0 on ties."""
    height, width = mask.shape
    binary = mask.astype(np.int64)
    out = np.zeros_like(mask, dtype=bool)
    for i in range(height):
        for j in range(width):
            window = binary[
                max(0, i - radius) : min(i + radius + 1, height - 1),
                max(0, j - radius) : min(j + radius + 1, width - 1),
            ]
            out[i, j] = np.argmax(np.bincount(window.ravel(), minlength=2)) == 1
    return out


@pytest.mark.parametrize("seed", range(6))
def test_majority_filter_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    height, width = rng.integers(2, 15, size=2)
    mask = rng.random((height, width)) < rng.uniform(0.3, 0.7)
    assert np.array_equal(majority_filter(mask), _brute_force_smooth(mask))
    assert np.array_equal(majority_filter(mask, radius=1), _brute_force_smooth(mask, 1))


def test_majority_filter_ignores_last_row_and_column():
    mask = np.ones((6, 6), dtype=bool)
    mask[-1, :] = False
    mask[:, -1] = False
    assert majority_filter(mask).all()
    assert not majority_filter(~mask).any()
    # 2×2: every window is the top-left pixel alone
    assert majority_filter(np.array([[1, 0], [0, 0]])).all()
    with pytest.raises(InputError, match=r"majority_filter: .*\(1, 5\)"):
        majority_filter(np.ones((1, 5), dtype=bool))


def test_langsplat_mask_band_is_kept_exactly():
    # a 30-row band of 1 on 0: the mixed map is 1 in its middle and 0 far from it, so the
    # normalized map is the mixed map; band pixels mix to ≥ 0.75 > 0.7, outside ≤ 0.5
    relevancy = np.zeros((100, 50))
    relevancy[40:70] = 1.0
    expected = np.zeros((100, 50), dtype=bool)
    expected[40:70] = True
    assert np.array_equal(langsplat_mask(relevancy), expected)


def test_langsplat_mask_square_loses_its_corners():
    relevancy = np.zeros((100, 100))
    relevancy[30:70, 30:70] = 1.0
    mask = langsplat_mask(relevancy)
    # edge midpoints keep half their window (0.5 > 0.4), corners a quarter
    assert mask[30, 50] and mask[50, 30] and mask[69, 50] and mask[50, 69] and mask[50, 50]
    assert not mask[30, 30] and not mask[69, 69]
    assert not mask[:30].any() and not mask[70:].any()
    # away from the image border the box mean is (rows inside / 30) · (columns inside / 30); the
    # mixed map spans [0, 1], so a square pixel is kept when that product exceeds 0.4 (a product
    # of exactly 0.4 is cut by the 1e-9 in the normalization)
    offsets = np.arange(-15, 15)
    inside = np.array([np.isin(i + offsets, np.arange(30, 70)).sum() for i in range(100)])
    kept = np.outer(inside, inside) > 360
    kept[relevancy == 0] = False
    assert np.array_equal(mask, _brute_force_smooth(kept))


@pytest.mark.parametrize(
    ("value", "threshold", "kept"),
    [(0.69, 0.4, False), (0.71, 0.4, True), (0.69, 0.3, True), (0.41, 0.4, False)],
)
def test_langsplat_mask_thresholds_after_the_2x_minus_1_map(value, threshold, kept):
    # 60-column bands 0 | value | 1: in the middle band's interior both the raw and the box map
    # equal `value`, min 0 and max 1, so its normalized value is `value`
    relevancy = np.zeros((40, 180))
    relevancy[:, 60:120] = value
    relevancy[:, 120:] = 1.0
    mask = langsplat_mask(relevancy, threshold)
    assert (mask[:, 80:100] == kept).all()
    assert mask[:, 140:].all() and not mask[:, :40].any()


def test_langsplat_mask_constant_and_tiny_range_are_empty():
    assert not langsplat_mask(np.full((20, 30), 0.8)).any()
    tiny = np.zeros((60, 60))
    tiny[10:50, 10:50] = 1e-12  # the 1e-9 epsilon dominates: normalized values stay ≤ 0.001
    assert not langsplat_mask(tiny).any()
    assert langsplat_mask(tiny * 1e12).any()
    with pytest.raises(InputError, match="langsplat_mask: has NaN"):
        langsplat_mask(np.full((4, 4), np.inf))


def _spike_over_background() -> np.ndarray:
    """Background 0.2 with one pixel at 1.0: mixed peak 0.6004, smoothed peak 0.2009."""
    level = np.full((60, 60), 0.2)
    level[30, 30] = 1.0
    return level


def test_langsplat_level_uses_the_mixed_peak():
    flat = np.full((60, 60), 0.55)  # mixed and smoothed peaks 0.55
    stack = np.stack([flat, _spike_over_background()])
    assert langsplat_level(stack) == 1
    assert langsplat_level(stack[::-1]) == 0
    assert langsplat_level(np.stack([flat, flat, flat + 0.1, flat + 0.1])) == 2  # first on ties
    with pytest.raises(InputError, match=r"langsplat_level: expected \[L, H, W\]"):
        langsplat_level(flat)


def _block(rows: slice, cols: slice, value: float = 1.0) -> np.ndarray:
    level = np.zeros((80, 100))
    level[rows, cols] = value
    return level


def test_langsplat_localized_peak_inside_or_outside_boxes():
    # a 40×40 block: the smoothed map peaks (1.0) on rows 35..45, cols 45..55
    stack = np.stack([_block(slice(20, 60), slice(30, 70)), np.zeros((80, 100))])
    assert langsplat_localized(stack, [(45, 35, 45, 35)])  # one peak pixel, bounds inclusive
    assert langsplat_localized(stack, [(55.0, 45.0, 50.0, 40.0)])  # corners reversed
    assert not langsplat_localized(stack, [(0, 0, 44, 80)])  # left of every peak pixel
    assert not langsplat_localized(stack, [(0, 0, 100, 34)])  # above them
    assert langsplat_localized(stack, [(0, 0, 10, 10), (56, 46, 55, 40)])  # the second box
    # x is the column: the same numbers read as (row, col) would miss
    assert not langsplat_localized(
        np.stack([_block(slice(0, 40), slice(60, 100))]), [(0, 60, 10, 80)]
    )
    assert langsplat_localized(np.stack([_block(slice(0, 40), slice(60, 100))]), [(60, 0, 80, 10)])


def test_langsplat_localized_chooses_the_smoothed_peak_level():
    # the spike level wins on the mixed map (langsplat_level) but loses on the smoothed one
    stack = np.stack([_spike_over_background(), np.zeros((60, 60))])
    stack[1, 5:55, 0:20] = 0.55  # smoothed peak 0.55 on rows 20..40, columns 0..5
    assert langsplat_level(stack) == 0
    assert langsplat_localized(stack, [(0, 0, 4, 59)])
    assert not langsplat_localized(stack, [(30, 30, 30, 30)])
    # ties between levels go to the first
    left, right = _block(slice(0, 80), slice(0, 40)), _block(slice(0, 80), slice(60, 100))
    assert langsplat_localized(np.stack([left, right]), [(0, 0, 30, 80)])
    assert not langsplat_localized(np.stack([right, left]), [(0, 0, 30, 80)])


def test_langsplat_localized_checks_boxes():
    stack = np.zeros((1, 8, 8))
    for boxes in ([], [(1, 2, 3)], [(0, 0, 1, np.nan)], [("a", 0, 1, 1)]):
        with pytest.raises(InputError, match="langsplat_localized: boxes"):
            langsplat_localized(stack, boxes)


def test_opengaussian_constants():
    assert OPENGAUSSIAN_THRESHOLD == 0.7
    assert sorted(OPENGAUSSIAN_LERF_PROMPTS) == ["figurines", "ramen", "teatime", "waldo_kitchen"]
    assert [len(v) for v in OPENGAUSSIAN_LERF_PROMPTS.values()] == [21, 14, 14, 18]
    assert "Stainless steel pots" in OPENGAUSSIAN_LERF_PROMPTS["waldo_kitchen"]
    with pytest.raises(TypeError):
        OPENGAUSSIAN_LERF_PROMPTS["ramen"] = ()  # type: ignore[index]


def test_scannet_scores_hand_case():
    classes = [5, 1, 3]  # class 3 never appears in the kept ground truth
    truth = np.array([1, 1, 1, 5, 5, 0, 1, 3, 40])
    predicted = np.array([1, 1, 5, 5, 1, 5, 3, 3, 1])
    opacity = np.array([0.9, 0.5, 0.1, 0.3, 0.8, 0.9, 0.2, 0.05, 1.0])
    scores = scannet_scores(predicted, truth, opacity, classes)
    # scored: points 0-4 and 6 (5 and 8 have ids outside classes, 7 is below 0.1 opacity)
    # class 5: tp 1 (3), fp 1 (2), fn 1 (4); class 1: tp 2, fp 1 (4), fn 2 (2, 6)
    assert scores.classes == (5, 1, 3)
    assert scores.points == 6
    assert np.allclose(scores.iou, [1 / 3, 2 / 5, np.nan], equal_nan=True)
    assert np.allclose(scores.accuracy, [1 / 2, 2 / 4, np.nan], equal_nan=True)
    assert scores.miou == pytest.approx((1 / 3 + 2 / 5) / 2)
    assert scores.macc == pytest.approx(0.5)
    # opacity exactly 0.1 is kept; dropping it with a higher cut removes class 1's fn at point 2
    harder = scannet_scores(predicted, truth, opacity, classes, min_opacity=0.15)
    assert harder.points == 5
    assert harder.iou[1] == pytest.approx(2 / 4)
    perfect = scannet_scores(truth[:5], truth[:5], opacity[:5], classes)
    assert perfect.miou == 1.0 and perfect.macc == 1.0
    nothing = scannet_scores(predicted, np.zeros(9, int), opacity, classes)
    assert nothing.points == 0 and np.isnan(nothing.miou) and np.isnan(nothing.macc)
    # −1 predicts no class: point 2 (truth 1, predicted 5) becomes a plain miss of class 1,
    # so class 5 loses its false positive: 1 / 2; class 1 keeps 2 / 5
    unsure = predicted.copy()
    unsure[2] = -1
    scores = scannet_scores(unsure, truth, opacity, classes)
    assert np.allclose(scores.iou, [1 / 2, 2 / 5, np.nan], equal_nan=True)
    assert np.allclose(scores.accuracy, [1 / 2, 2 / 4, np.nan], equal_nan=True)


def _brute_force_scannet(predicted, truth, opacity, classes, min_opacity=0.1):
    """OpenGaussian's rule spelled out: remap to 1…K, zero ignored points, count per class."""
    gt = np.array([classes.index(t) + 1 if t in classes else 0 for t in truth])
    gt[opacity < min_opacity] = 0
    pred = np.array([classes.index(p) + 1 if p != -1 else -1 for p in predicted])
    pred[gt == 0] = 0
    ious, accs = [], []
    for c in range(1, len(classes) + 1):
        both = ((gt == c) & (pred == c)).sum()
        present = (gt == c).any()
        ious.append(both / ((gt == c) | (pred == c)).sum() if present else np.nan)
        accs.append(both / (gt == c).sum() if present else np.nan)
    return np.array(ious), np.array(accs)


@pytest.mark.parametrize("seed", range(5))
def test_scannet_scores_matches_brute_force(seed):
    rng = np.random.default_rng(seed)
    classes = [int(c) for c in rng.choice(np.arange(1, 41), size=6, replace=False)]
    truth = rng.choice([*classes[1:], 0, 41, -1], size=300)  # classes[0] absent from the truth
    predicted = rng.choice([*classes, -1], size=300)  # −1: no class
    agree = (rng.random(300) < 0.5) & np.isin(truth, classes)
    predicted[agree] = truth[agree]
    opacity = rng.random(300)
    scores = scannet_scores(predicted, truth, opacity, classes, min_opacity=0.3)
    iou, accuracy = _brute_force_scannet(predicted, truth, opacity, classes, 0.3)
    assert np.allclose(scores.iou, iou, equal_nan=True)
    assert np.allclose(scores.accuracy, accuracy, equal_nan=True)
    assert np.isnan(scores.iou[0])
    assert scores.miou == pytest.approx(np.nanmean(iou))
    assert scores.macc == pytest.approx(np.nanmean(accuracy))
    assert scores.points == int((np.isin(truth, classes) & (opacity >= 0.3)).sum())


def test_scannet_scores_checks_inputs():
    ids, ones = np.array([1, 2, 1]), np.ones(3)
    with pytest.raises(InputError, match=r"scannet_scores: .*\(3,\).*\(2,\)"):
        scannet_scores(ids, ids[:2], ones, [1, 2])
    with pytest.raises(InputError, match="classes must be one or more"):
        scannet_scores(ids, ids, ones, [])
    with pytest.raises(InputError, match="classes repeat"):
        scannet_scores(ids, ids, ones, [1, 2, 1])
    with pytest.raises(InputError, match=r"predicted ids \[2\] are not in classes"):
        scannet_scores(ids, ids, ones, [1, 3])
    with pytest.raises(InputError, match="opacity must be finite"):
        scannet_scores(ids, ids, np.array([0.5, 1.5, 0.5]), [1, 2])
    with pytest.raises(InputError, match="min_opacity must be in"):
        scannet_scores(ids, ids, ones, [1, 2], min_opacity=float("nan"))
    with pytest.raises(InputError, match="must not hold −1"):
        scannet_scores(ids, ids, ones, [1, 2, -1])
    with pytest.raises(InputError, match="truth must be integer"):
        scannet_scores(ids, ids.astype(float), ones, [1, 2])


def test_langsplat_query_is_the_three_rules_at_once():
    # random maps with plateaus (ties between levels and inside a level) and random boxes: the
    # shared smoothing gives exactly what the three functions give one by one
    rng = np.random.default_rng(11)
    for case in range(12):
        levels, height, width = 3, int(rng.integers(2, 50)), int(rng.integers(2, 70))
        relevancy = rng.random((levels, height, width))
        if case % 2:
            relevancy = np.round(relevancy * 3) / 3  # plateaus
        if case % 3 == 0:
            relevancy[1] = relevancy[0]  # a tie between levels
        boxes = [tuple(rng.uniform(0, [width, height, width, height])) for _ in range(2)]
        threshold = float(rng.uniform(0.2, 0.6))
        chosen, mask, hit = langsplat_query(relevancy.astype(np.float32), boxes, threshold)
        assert chosen == langsplat_level(relevancy.astype(np.float32))
        np.testing.assert_array_equal(
            mask, langsplat_mask(relevancy.astype(np.float32)[chosen], threshold)
        )
        assert hit == langsplat_localized(relevancy.astype(np.float32), boxes)
    with pytest.raises(InputError, match="needs H, W ≥ 2"):
        langsplat_query(np.zeros((3, 1, 5)), [(0, 0, 1, 1)])
    with pytest.raises(InputError, match="boxes"):
        langsplat_query(np.zeros((3, 4, 5)), [])
