"""SAM's mask post-processing and LangSplat's mask NMS: hand-computed answers and brute-force
references (SAM's and LangSplat's algorithms transcribed literally, run on random inputs)."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy import ndimage

from thgs.guidance.preprocess import masks as masks_module
from thgs.guidance.preprocess.masks import (
    box_nms,
    is_box_near_crop_edge,
    langsplat_mask_nms,
    masks_to_boxes,
    remove_small_regions,
    stability_score,
)


def rect(shape, rows, cols):
    """A bool mask with the inclusive row range ``rows`` and column range ``cols`` set."""
    mask = np.zeros(shape, dtype=bool)
    mask[rows[0] : rows[1] + 1, cols[0] : cols[1] + 1] = True
    return mask


def stack(*arrays):
    return torch.from_numpy(np.stack(arrays))


# --------------------------------------------------------------------------- stability_score


def test_stability_score_counts_strictly_above_both_thresholds():
    logits = torch.tensor(
        [
            [[2.0, 1.5, 0.5], [-0.5, -1.0, -3.0]],  # > 1: 2 px; > −1: 4 px (−1.0 is not > −1)
            [[-5.0, -5.0, -5.0], [-5.0, -5.0, -5.0]],  # nothing above −1: 0, not NaN
            [[3.0, 3.0, 3.0], [3.0, 3.0, 3.0]],
            [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]],  # nothing strictly above 1
        ]
    )
    score = stability_score(logits, 0.0, 1.0)
    assert score.dtype == torch.float32 and score.shape == (4,)
    assert score.tolist() == [0.5, 0.0, 1.0, 0.0]
    # thresholds 0.75 and 0.25: 2 px and 3 px in the first mask
    other = stability_score(logits, 0.5, 0.25)
    assert other[0].item() == torch.tensor(2 / 3, dtype=torch.float32).item()
    assert stability_score(torch.zeros(0, 4, 5), 0.0, 1.0).shape == (0,)


# --------------------------------------------------------------------------- masks_to_boxes


def test_masks_to_boxes_hand_built():
    shape = (8, 10)
    l_shape = rect(shape, (2, 6), (1, 1)) | rect(shape, (6, 6), (1, 4))
    pixel = rect(shape, (0, 0), (9, 9))
    empty = np.zeros(shape, dtype=bool)
    full = np.ones(shape, dtype=bool)
    boxes = masks_to_boxes(stack(l_shape, pixel, empty, full))
    assert boxes.dtype == torch.int64
    assert boxes.tolist() == [[1, 2, 4, 6], [9, 0, 9, 0], [0, 0, 0, 0], [0, 0, 9, 7]]
    assert masks_to_boxes(torch.zeros(0, 8, 10, dtype=torch.bool)).shape == (0, 4)
    assert masks_to_boxes(torch.zeros(3, 0, 10, dtype=torch.bool)).tolist() == [[0] * 4] * 3


def test_masks_to_boxes_matches_pixel_extents():
    rng = np.random.default_rng(1)
    masks = rng.random((50, 13, 17)) < rng.random((50, 1, 1)) * 0.05
    boxes = masks_to_boxes(torch.from_numpy(masks)).tolist()
    for mask, box in zip(masks, boxes):
        ys, xs = np.nonzero(mask)
        expected = [xs.min(), ys.min(), xs.max(), ys.max()] if len(xs) else [0, 0, 0, 0]
        assert box == [int(v) for v in expected]


# --------------------------------------------------------------------------- box_nms


def reference_nms(boxes: np.ndarray, scores: np.ndarray, threshold: float) -> list[int]:
    """Plain greedy NMS with torchvision's float32 arithmetic (threshold in float32)."""
    b = boxes.astype(np.float32)
    areas = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    order = sorted(range(len(b)), key=lambda i: -scores[i])  # stable: ties keep input order
    suppressed = [False] * len(b)
    keep = []
    with np.errstate(divide="ignore", invalid="ignore"):
        for rank, i in enumerate(order):
            if suppressed[i]:
                continue
            keep.append(i)
            for j in order[rank + 1 :]:
                w = max(np.float32(0), min(b[i, 2], b[j, 2]) - max(b[i, 0], b[j, 0]))
                h = max(np.float32(0), min(b[i, 3], b[j, 3]) - max(b[i, 1], b[j, 1]))
                inter = w * h
                if inter / (areas[i] + areas[j] - inter) > np.float32(threshold):
                    suppressed[j] = True
    return keep


def test_box_nms_suppresses_the_middle_box():
    boxes = torch.tensor([[0, 0, 10, 10], [0, 0, 10, 9], [20, 20, 30, 30]])  # IoU(0, 1) = 0.9
    assert box_nms(boxes, torch.tensor([0.9, 0.8, 0.7]), 0.7).tolist() == [0, 2]
    # descending score order: the last box is kept first
    assert box_nms(boxes, torch.tensor([0.2, 0.1, 0.7]), 0.7).tolist() == [2, 0]


def test_box_nms_is_greedy():
    # IoU(A, B) = 100/120, IoU(B, C) = 100/140 > 0.7, IoU(A, C) = 80/140 < 0.7:
    # B is suppressed by A, so it cannot suppress C.
    boxes = torch.tensor([[0.0, 0, 10, 10], [0, 0, 10, 12], [0, 2, 10, 14]])
    assert box_nms(boxes, torch.tensor([0.9, 0.8, 0.7]), 0.7).tolist() == [0, 2]


def test_box_nms_ties_keep_input_order():
    boxes = torch.tensor([[0, 0, 5, 5], [0, 0, 5, 5], [10, 10, 15, 15], [10, 10, 15, 15]])
    assert box_nms(boxes, torch.tensor([0.5, 0.5, 0.9, 0.9]), 0.7).tolist() == [2, 0]
    assert box_nms(boxes, torch.ones(4), 0.7).tolist() == [0, 2]


def test_box_nms_threshold_edges():
    half = torch.tensor([[0.0, 0, 10, 10], [0, 0, 10, 5]])  # IoU exactly 0.5: not > 0.5
    assert box_nms(half, torch.tensor([0.9, 0.8]), 0.5).tolist() == [0, 1]
    assert box_nms(half, torch.tensor([0.9, 0.8]), 0.49).tolist() == [0]
    # IoU 4/5 is float32(0.8), compared with float32(0.8) (torchvision's CUDA kernel): kept
    fifths = torch.tensor([[0.0, 0, 5, 1], [0, 0, 4, 1]])
    assert box_nms(fifths, torch.tensor([0.9, 0.8]), 0.8).tolist() == [0, 1]
    # zero-area boxes: zero union never suppresses
    points = torch.tensor([[5.0, 5, 5, 5], [5, 5, 5, 5]])
    assert box_nms(points, torch.tensor([0.9, 0.8]), 0.0).tolist() == [0, 1]
    empty = box_nms(torch.zeros(0, 4), torch.zeros(0), 0.7)
    assert empty.dtype == torch.int64 and empty.shape == (0,)
    assert box_nms(torch.tensor([[1, 2, 3, 4]]), torch.tensor([0.1]), 0.7).tolist() == [0]


@pytest.mark.parametrize("integer", [True, False])
def test_box_nms_matches_plain_greedy(integer):
    rng = np.random.default_rng(2)
    for case in range(40):
        n = int(rng.integers(1, 60))
        x0 = rng.integers(0, 30, n)
        y0 = rng.integers(0, 30, n)
        boxes = np.stack([x0, y0, x0 + rng.integers(0, 15, n), y0 + rng.integers(0, 15, n)], 1)
        if not integer:
            boxes = boxes + rng.random((n, 4)) * 0.5
        scores = rng.integers(0, 6, n) / 5.0  # many ties
        threshold = [0.3, 0.5, 0.7][case % 3]
        expected = reference_nms(boxes, scores, threshold)
        kept = box_nms(torch.from_numpy(boxes), torch.from_numpy(scores), threshold)
        assert kept.tolist() == expected


def test_box_nms_chunks_give_the_same_answer(monkeypatch):
    rng = np.random.default_rng(3)
    x0, y0 = rng.integers(0, 200, (2, 300))
    boxes = torch.from_numpy(np.stack([x0, y0, x0 + 40, y0 + rng.integers(20, 60, 300)], 1))
    scores = torch.from_numpy(rng.integers(0, 20, 300).astype(np.float32))
    whole = box_nms(boxes, scores, 0.5)
    monkeypatch.setattr(masks_module, "_NMS_CHUNK_ELEMENTS", 7 * 300)  # 7 rows per chunk
    assert box_nms(boxes, scores, 0.5).tolist() == whole.tolist()
    assert len(whole) < 300


# --------------------------------------------------------------------------- crop edges


def test_is_box_near_crop_edge():
    image = (0, 0, 100, 80)
    top_left = (0, 0, 60, 50)
    boxes = torch.tensor(
        [
            [10, 10, 59, 30],  # x1 = 59 is 1 px from the crop's right edge, 41 from the image's
            [0, 0, 20, 20],  # at the crop's left/top edges, which are the image's too
            [10, 5, 39, 29],  # 21 px from the crop's right and bottom edges
            [10, 5, 40, 29],  # exactly 20 px from the crop's right edge: near (inclusive)
        ]
    )
    assert is_box_near_crop_edge(boxes, top_left, image).tolist() == [True, False, False, True]
    assert is_box_near_crop_edge(boxes.float(), top_left, image).tolist() == [
        True,
        False,
        False,
        True,
    ]
    bottom_right = (40, 30, 100, 80)
    boxes = torch.tensor(
        [
            [0, 0, 10, 10],  # image (40, 30, 50, 40): at the crop's left edge, inside the image
            [21, 21, 59, 49],  # image (61, 51, 99, 79): right/bottom edges are the image's
            [20, 25, 59, 49],  # image x0 = 60, 20 px from the crop's left edge
        ]
    )
    assert is_box_near_crop_edge(boxes, bottom_right, image).tolist() == [True, False, True]
    assert is_box_near_crop_edge(boxes, bottom_right, image, atol=19.0).tolist() == [
        True,
        False,
        False,
    ]
    # the whole image as crop: no edge is inner
    boxes = torch.tensor([[0, 0, 5, 5], [90, 70, 99, 79], [30, 30, 40, 40]])
    assert not is_box_near_crop_edge(boxes, image, image).any()
    assert is_box_near_crop_edge(torch.zeros(0, 4), top_left, image).shape == (0,)


# --------------------------------------------------------------------------- small regions


def reference_remove_small_regions(mask, area_threshold, mode):
    """SAM's remove_small_regions on the full image, scipy's 8-connected labels for OpenCV's."""
    holes = mode == "holes"
    working = holes ^ mask
    labels, count = ndimage.label(working, structure=np.ones((3, 3), dtype=bool))
    sizes = np.bincount(labels.ravel(), minlength=count + 1)[1:]
    small = [i + 1 for i, s in enumerate(sizes) if s < area_threshold]
    if not small:
        return mask, False
    fill = [0, *small]
    if not holes:
        fill = [i for i in range(count + 1) if i not in fill]
        if not fill:
            fill = [int(np.argmax(sizes)) + 1]
    return np.isin(labels, fill), True


def test_remove_small_regions_hole_and_island():
    mask = rect((10, 10), (2, 8), (2, 8))
    mask[5, 4:6] = False  # a 2 px hole
    island = rect((10, 10), (0, 0), (6, 8))  # 3 px, two rows above the square
    mask |= island
    filled, changed = remove_small_regions(mask, 5, "holes")
    assert changed
    np.testing.assert_array_equal(filled, rect((10, 10), (2, 8), (2, 8)) | island)
    cleaned, changed = remove_small_regions(mask, 5, "islands")
    assert changed
    np.testing.assert_array_equal(cleaned, mask & ~island)
    for mode in ("holes", "islands"):  # 2 px and 3 px are not < 2
        same, changed = remove_small_regions(mask, 2, mode)
        assert same is mask and not changed


def test_remove_small_islands_keeps_the_largest_when_all_are_small():
    a = rect((10, 10), (0, 0), (0, 2))  # 3 px
    b = rect((10, 10), (5, 5), (3, 6))  # 4 px
    kept, changed = remove_small_regions(a | b, 10, "islands")
    assert changed
    np.testing.assert_array_equal(kept, b)
    # equal sizes: the component met first in row-major order
    first = rect((10, 10), (0, 0), (7, 9))
    second = rect((10, 10), (5, 5), (0, 2))
    kept, _ = remove_small_regions(first | second, 10, "islands")
    np.testing.assert_array_equal(kept, first)
    # one small island is kept as the largest, but SAM still reports a change
    kept, changed = remove_small_regions(a, 10, "islands")
    assert changed
    np.testing.assert_array_equal(kept, a)


def test_remove_small_regions_is_eight_connected():
    diagonal = np.eye(6, dtype=bool)
    diagonal[4:] = False  # 4 px on a diagonal
    same, changed = remove_small_regions(diagonal, 4, "islands")  # one 4 px component
    assert same is diagonal and not changed
    ring = rect((7, 7), (1, 5), (1, 5)) & ~rect((7, 7), (2, 4), (2, 4))  # 16 px outline
    filled, changed = remove_small_regions(ring, 20, "holes")
    assert changed
    np.testing.assert_array_equal(filled, rect((7, 7), (1, 5), (1, 5)))
    open_ring = ring.copy()
    open_ring[1, 1] = False  # the inside now touches the outside diagonally
    same, changed = remove_small_regions(open_ring, 20, "holes")
    assert same is open_ring and not changed


def test_remove_small_regions_empty_mask():
    empty = np.zeros((3, 3), dtype=bool)
    filled, changed = remove_small_regions(empty, 10, "holes")  # one 9 px hole: filled
    assert changed and filled.all()
    for threshold, mode in ((9, "holes"), (10, "islands")):
        same, changed = remove_small_regions(empty, threshold, mode)
        assert same is empty and not changed
    with pytest.raises(ValueError, match="mode"):
        remove_small_regions(empty, 10, "both")


def test_remove_small_holes_falls_back_when_the_outside_strips_are_small():
    mask = rect((10, 10), (1, 8), (0, 9))  # full width: 10 px strips above and below
    mask[4, 4] = False
    bbox = masks_module._bounding_box(mask)
    assert masks_module._holes_window(mask.shape, bbox, 15) is None
    assert masks_module._holes_window(mask.shape, bbox, 10) is not None
    filled, changed = remove_small_regions(mask, 15, "holes")  # both strips and the hole
    assert changed and filled.all()
    filled, changed = remove_small_regions(mask, 10, "holes")  # only the hole
    assert changed
    np.testing.assert_array_equal(filled, rect((10, 10), (1, 8), (0, 9)))


def random_masks(rng):
    """Masks of every kind that matters to the windowed labelling."""
    shapes = [(1, 1), (1, 5), (5, 1), (2, 2), (3, 3), (4, 7), (12, 9), (20, 24)]
    for _ in range(500):
        height, width = shapes[rng.integers(len(shapes))]
        kind = rng.integers(5)
        if kind == 0:  # noise: many small components
            mask = rng.random((height, width)) < rng.random()
        elif kind == 1:  # smooth blobs
            noise = ndimage.uniform_filter(rng.random((height, width)), 3)
            mask = noise > np.quantile(noise, rng.random())
        elif kind == 2:  # a rectangle touching borders, with holes punched in
            r0, c0 = rng.integers(0, 2, 2) * np.array([rng.integers(height), rng.integers(width)])
            mask = np.zeros((height, width), dtype=bool)
            mask[r0 : rng.integers(r0, height) + 1, c0 : rng.integers(c0, width) + 1] = True
            mask &= rng.random((height, width)) > 0.1
        elif kind == 3:  # a full-width or full-height band, with holes punched in
            vertical = rng.random() < 0.5
            rows, cols = (width, height) if vertical else (height, width)
            lo = rng.integers(rows)
            mask = np.zeros((rows, cols), dtype=bool)
            mask[lo : rng.integers(lo, rows) + 1] = True
            mask &= rng.random((rows, cols)) > 0.15
            mask = mask.T.copy() if vertical else mask
        else:
            mask = np.zeros((height, width), dtype=bool)
            if rng.random() < 0.5:
                mask[rng.integers(height), rng.integers(width)] = True
        yield mask, int(rng.choice([1, 2, 3, 5, 10, 30, 100]))


def test_remove_small_regions_matches_full_image_labelling():
    rng = np.random.default_rng(4)
    windowed = changed_count = 0
    for mask, threshold in random_masks(rng):
        for mode in ("holes", "islands"):
            result, changed = remove_small_regions(mask, threshold, mode)
            expected, expected_changed = reference_remove_small_regions(mask, threshold, mode)
            assert changed == expected_changed
            np.testing.assert_array_equal(result, expected)
            changed_count += changed
        bbox = masks_module._bounding_box(mask)
        windowed += masks_module._holes_window(mask.shape, bbox, threshold) is not None
    assert windowed > 200 and changed_count > 200  # the fast path and the fills both ran


# --------------------------------------------------------------------------- mask NMS


def reference_mask_nms(masks, scores, iou_thr, score_thr, inner_thr):
    """LangSplat's mask_nms transcribed literally (stable sort added), then its ``filter``.

    Raises IndexError where LangSplat's fallback runs (``keep[index, 0]`` on a 1-D tensor),
    RuntimeError there for fewer than 3 masks (``topk(3)``).
    Also returns which of the IoU and the two containment criteria dropped a mask.
    """
    scores, idx = scores.sort(dim=0, descending=True, stable=True)
    n = idx.shape[0]
    ordered = masks[idx.view(-1), :]
    area = torch.sum(ordered, dim=(1, 2), dtype=torch.float)
    iou_matrix = torch.zeros((n, n), dtype=torch.float)
    inner_matrix = torch.zeros((n, n), dtype=torch.float)
    for i in range(n):
        for j in range(i, n):
            inter = torch.sum(torch.logical_and(ordered[i], ordered[j]), dtype=torch.float)
            union = torch.sum(torch.logical_or(ordered[i], ordered[j]), dtype=torch.float)
            iou_matrix[i, j] = inter / union
            if inter / area[i] < 0.5 and inter / area[j] >= 0.85:
                inner_matrix[i, j] = 1 - (inter / area[j]) * (inter / area[i])
            if inter / area[i] >= 0.85 and inter / area[j] < 0.5:
                inner_matrix[j, i] = 1 - (inter / area[j]) * (inter / area[i])
    iou_matrix.triu_(diagonal=1)
    iou_max, _ = iou_matrix.max(dim=0)
    inner_max_u, _ = torch.triu(inner_matrix, diagonal=1).max(dim=0)
    inner_max_l, _ = torch.tril(inner_matrix, diagonal=1).max(dim=0)
    keep = iou_max <= iou_thr
    keep_conf = scores > score_thr
    keep_u = inner_max_u <= 1 - inner_thr
    keep_l = inner_max_l <= 1 - inner_thr
    dropped = (bool((~keep).any()), bool((~keep_u).any()), bool((~keep_l).any()))
    for criterion in (keep_conf, keep_u, keep_l):
        if criterion.sum() == 0:
            index = scores.topk(3).indices
            criterion[index, 0] = True
    keep *= keep_conf
    keep *= keep_u
    keep *= keep_l
    return sorted(idx[keep].tolist()), dropped


def nms(masks, scores, **kwargs):
    return langsplat_mask_nms(stack(*masks), torch.tensor(scores, dtype=torch.float64), **kwargs)


def test_mask_nms_drops_duplicates_of_higher_scored_masks():
    shape = (10, 10)
    a, c = rect(shape, (0, 4), (0, 4)), rect(shape, (6, 9), (6, 9))
    kept = nms([a, a, c], [0.9, 0.95, 0.8])
    assert kept.dtype == torch.int64 and kept.tolist() == [1, 2]
    # IoU exactly 4/5: float32(0.8) <= float32(0.8), as the reference compares
    five, four = rect(shape, (0, 0), (0, 4)), rect(shape, (0, 0), (0, 3))
    assert nms([five, four], [0.9, 0.8]).tolist() == [0, 1]
    assert nms([five, four], [0.9, 0.8], iou_threshold=0.79).tolist() == [0]


def test_mask_nms_drops_contained_masks_whatever_their_rank():
    shape = (10, 10)
    large, small = np.ones(shape, dtype=bool), rect(shape, (2, 3), (2, 6))  # 100 px, 10 px
    assert nms([large, small], [0.9, 0.8]).tolist() == [0]  # contained, ranked below
    assert nms([large, small], [0.8, 0.9]).tolist() == [0]  # contained, ranked above
    # contained in a mask two ranks below (read through tril(diagonal=1))
    top, other = rect(shape, (0, 6), (0, 9)), rect(shape, (8, 9), (8, 9))  # other is outside
    assert nms([small, other, top], [0.95, 0.9, 0.85]).tolist() == [1, 2]
    # 1 − 1·0.1 = 0.9 is not above 1 − 0.05
    assert nms([large, small], [0.9, 0.8], containment_threshold=0.05).tolist() == [0, 1]
    # the container must have < 50 % of its area in the contained mask
    forty, fifty = rect(shape, (0, 3), (0, 9)), rect(shape, (0, 4), (0, 9))
    assert nms([large, forty], [0.9, 0.8]).tolist() == [0]  # inner = 0.6 > 0.5
    assert nms([large, fifty], [0.9, 0.8]).tolist() == [0, 1]


def test_mask_nms_containment_needs_85_percent_inside():
    shape = (20, 20)
    container = rect(shape, (0, 9), (0, 19))  # 200 px
    inside_17 = rect(shape, (9, 9), (0, 16)) | rect(shape, (10, 10), (0, 2))  # 17 of 20 inside
    inside_16 = rect(shape, (9, 9), (0, 15)) | rect(shape, (10, 10), (0, 3))  # 16 of 20 inside
    assert nms([container, inside_17], [0.9, 0.8]).tolist() == [0]
    assert nms([container, inside_16], [0.9, 0.8]).tolist() == [0, 1]


def test_mask_nms_score_threshold_and_fallback():
    shape = (10, 10)
    disjoint = [rect(shape, (2 * k, 2 * k), (0, 9)) for k in range(5)]
    assert nms(disjoint[:3], [0.9, 0.7, 0.71]).tolist() == [0, 2]  # 0.7 is not above 0.7
    # no score above the threshold: the 3 best-scored, in input order
    assert nms(disjoint, [0.1, 0.5, 0.3, 0.6, 0.2]).tolist() == [1, 2, 3]
    assert nms(disjoint, [0.5] * 5).tolist() == [0, 1, 2]
    assert nms(disjoint[:2], [0.1, 0.2]).tolist() == [0, 1]
    # the fallback is per criterion: the IoU criterion still drops the duplicate
    assert nms([disjoint[0], disjoint[0], *disjoint[1:3]], [0.5, 0.4, 0.3, 0.2]).tolist() == [0, 2]
    with pytest.raises(IndexError):  # where LangSplat's own fallback crashes
        reference_mask_nms(stack(*disjoint), torch.full((5,), 0.5), 0.8, 0.7, 0.5)


def test_mask_nms_containment_fallback():
    # with containment_threshold > 1 both containment arrays keep nothing (their maxima are
    # ≥ 0 > 1 − 1.5), so each falls back to the 3 best-scored masks
    disjoint = [rect((10, 10), (2 * k, 2 * k), (0, 9)) for k in range(5)]
    scores = [0.8, 0.95, 0.75, 0.9, 0.85]
    assert nms(disjoint, scores).tolist() == [0, 1, 2, 3, 4]
    assert nms(disjoint, scores, containment_threshold=1.5).tolist() == [1, 3, 4]


def test_mask_nms_small_cases():
    empty = langsplat_mask_nms(torch.zeros(0, 4, 4, dtype=torch.bool), torch.zeros(0))
    assert empty.dtype == torch.int64 and empty.shape == (0,)
    one = [rect((4, 4), (0, 1), (0, 1))]
    assert nms(one, [0.9]).tolist() == [0]
    assert nms(one, [0.1]).tolist() == [0]
    # two empty masks: the reference's NaN IoU drops the lower-ranked one
    nothing = np.zeros((4, 4), dtype=bool)
    assert nms([nothing, nothing, one[0]], [0.9, 0.8, 0.85]).tolist() == [0, 2]


def random_mask_set(rng, shape=(16, 16)):
    n = int(rng.integers(1, 13))
    masks = []
    for _ in range(n):
        kind = rng.integers(6)
        if kind <= 1 or not masks:  # a random rectangle
            r0, c0 = rng.integers(0, shape[0], 2)
            mask = rect(shape, (r0, rng.integers(r0, shape[0])), (c0, rng.integers(c0, shape[1])))
        elif kind == 2:  # a rectangle nested in an earlier mask's box
            ys, xs = np.nonzero(masks[rng.integers(len(masks))])
            if len(ys) == 0:
                mask = np.zeros(shape, dtype=bool)
            else:
                r0, c0 = rng.integers(ys.min(), ys.max() + 1), rng.integers(xs.min(), xs.max() + 1)
                r1, c1 = rng.integers(r0, ys.max() + 1), rng.integers(c0, xs.max() + 1)
                mask = rect(shape, (r0, r1), (c0, c1))
        elif kind == 3:  # a duplicate, maybe with a few pixels flipped
            mask = masks[rng.integers(len(masks))] ^ (rng.random(shape) < 0.02 * rng.integers(2))
        elif kind == 4:  # a blob
            noise = ndimage.uniform_filter(rng.random(shape), 5)
            mask = noise > np.quantile(noise, rng.uniform(0.3, 0.95))
        else:
            mask = np.zeros(shape, dtype=bool) if rng.random() < 0.3 else rng.random(shape) < 0.3
        masks.append(mask)
    scores = rng.integers(4, 11, n) / 10.0  # ties; sometimes none above 0.7
    return stack(*masks), torch.from_numpy(scores)


def test_mask_nms_matches_reference_transcription():
    rng = np.random.default_rng(5)
    compared = 0
    dropped = np.zeros(3, dtype=int)
    for case in range(300):
        masks, scores = random_mask_set(rng)
        thresholds = [(0.8, 0.7, 0.5), (0.5, 0.6, 0.2), (0.9, 0.45, 0.8)][case % 3]
        kept = langsplat_mask_nms(masks, scores, *thresholds).tolist()
        try:
            expected, why = reference_mask_nms(masks, scores, *thresholds)
        except (IndexError, RuntimeError):  # the reference's fallback (topk(3) of < 3 too)
            continue
        assert kept == expected
        compared += 1
        dropped += why
    assert compared > 200 and (dropped > 10).all()  # every criterion did drop masks


def test_mask_nms_pixel_chunks_give_the_same_answer(monkeypatch):
    rng = np.random.default_rng(6)
    cases = [random_mask_set(rng) for _ in range(20)]
    whole = [langsplat_mask_nms(m, s).tolist() for m, s in cases]
    monkeypatch.setattr(masks_module, "_INTERSECTION_CHUNK_BYTES", 4 * 12 * 7)
    assert [langsplat_mask_nms(m, s).tolist() for m, s in cases] == whole
