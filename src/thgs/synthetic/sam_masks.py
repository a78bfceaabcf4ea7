"""SAM-like masks from the ground truth: clean components, SAM's faults, LangSplat's pooling.

Per view, the ground-truth label maps at the three levels (sub-part, part, object) come from the
max-weight Gaussian of every pixel (:func:`ground_truth_maps`). Their 4-connected components are
the clean masks of SAM's levels s, m and l (:func:`clean_masks`). Faults then make them look like
SAM's output (:func:`apply_faults`), in this order:

1. wrong level — a mask is replaced by the component of a neighbouring level that overlaps it most
   (a part-sized mask among the sub-parts, …), with that level's name;
2. merge — two touching masks become one (named after the larger);
3. split — a mask is cut in two by a random line through its pixels' median (both keep the name);
4. drop — a mask disappears (its pixels get no mask);
5. boundary jitter — a mask grows (taking pixels from whatever was there) or shrinks (leaving
   pixels without a mask) by 1 … ``max_jitter`` pixels;
6. spurious — small elliptical masks appear, named after the ground truth under their centre.

The ``default`` level pools the final s, m and l masks the way LangSplat stores SAM's automatic
masks (:func:`pool_default`): identical masks once, painted largest first so that the smallest
mask containing a pixel wins.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from thgs.eval.ground_truth import Hierarchy

__all__ = [
    "FaultRates",
    "LevelMasks",
    "MaskFaults",
    "apply_faults",
    "clean_masks",
    "disk",
    "ground_truth_maps",
    "grown_box",
    "pool_default",
]


@dataclass(frozen=True, eq=False)
class LevelMasks:
    """Non-overlapping masks of one level in one view.

    Attributes:
        ids: [H, W] int32 mask index per pixel, −1 = no mask.
        names: the text name of every mask (``len(names)`` masks, each with at least one pixel
            after :meth:`compact`).
    """

    ids: np.ndarray
    names: tuple[str, ...]

    def __len__(self) -> int:
        return len(self.names)

    def without_small(self, min_pixels: int) -> LevelMasks:
        """Masks with fewer than ``min_pixels`` pixels removed (their pixels get no mask)."""
        areas = np.bincount(self.ids[self.ids >= 0], minlength=len(self.names))
        small = np.concatenate([[False], areas < min_pixels])
        return LevelMasks(np.where(small[self.ids + 1], -1, self.ids).astype(np.int32), self.names)

    def compact(self) -> LevelMasks:
        """Drop masks with no pixels left and renumber the rest in order."""
        keep = np.bincount(self.ids.ravel() + 1, minlength=len(self.names) + 1)[1:] > 0
        new_index = np.full(len(self.names) + 1, -1, dtype=np.int32)
        new_index[1:][keep] = np.arange(int(keep.sum()), dtype=np.int32)
        names = tuple(name for name, kept in zip(self.names, keep) if kept)
        return LevelMasks(new_index[self.ids + 1], names)


def ground_truth_maps(max_id: np.ndarray, hierarchy: Hierarchy) -> np.ndarray:
    """[3, H, W] int32 ground-truth node ids per pixel at levels 1, 2, 3 (sub-part, part,
    object: SAM's s, m, l).

    Args:
        max_id: [H, W] index of each pixel's max-weight Gaussian, −1 where none.
        hierarchy: the per-Gaussian ground truth.
    """
    padded = np.concatenate([hierarchy.labels[:, 1:], np.full((1, 3), -1, dtype=np.int32)])
    return np.moveaxis(padded[max_id], -1, 0).astype(np.int32)


def _components(node_map: np.ndarray, names: tuple[str, ...]) -> LevelMasks:
    ids = np.full(node_map.shape, -1, dtype=np.int32)
    mask_names: list[str] = []
    for node, box in enumerate(ndimage.find_objects(node_map + 1)):
        if box is None:
            continue
        labelled, count = ndimage.label(node_map[box] == node)
        window = ids[box]
        inside = labelled > 0
        window[inside] = labelled[inside] - 1 + len(mask_names)
        mask_names.extend([names[node]] * count)
    return LevelMasks(ids, tuple(mask_names))


def clean_masks(maps: np.ndarray, hierarchy: Hierarchy, min_pixels: int = 1) -> list[LevelMasks]:
    """The 4-connected components of each level's ground-truth map (levels s, m, l), those
    under ``min_pixels`` pixels left out."""
    return [
        _components(maps[index], hierarchy.names[index + 1]).without_small(min_pixels).compact()
        for index in range(3)
    ]


def grown_box(box: tuple[slice, slice], radius: int, shape: tuple[int, int]) -> tuple[slice, slice]:
    """``box`` widened by ``radius`` pixels on every side, clipped to an image of ``shape``."""
    return tuple(  # type: ignore[return-value]
        slice(max(0, s.start - radius), min(size, s.stop + radius)) for s, size in zip(box, shape)
    )


def disk(radius: int) -> np.ndarray:
    """[2r + 1, 2r + 1] bool: the pixels within ``radius`` of the centre."""
    y, x = np.mgrid[-radius : radius + 1, -radius : radius + 1]
    return x * x + y * y <= radius * radius


def _wrong_level(
    masks: LevelMasks, level: int, clean: list[LevelMasks], p: float, rng: np.random.Generator
) -> LevelMasks:
    ids, names = masks.ids.copy(), list(masks.names)
    for index in range(len(masks)):
        if rng.uniform() >= p:
            continue
        other_levels = [k for k in (level - 1, level + 1) if 0 <= k < 3]
        other = clean[other_levels[int(rng.integers(len(other_levels)))]]
        own = masks.ids == index
        overlap = other.ids[own]
        overlap = overlap[overlap >= 0]
        if overlap.size == 0:
            continue
        chosen = int(np.bincount(overlap).argmax())
        ids[own & (ids == index)] = -1
        ids[other.ids == chosen] = index
        names[index] = other.names[chosen]
    return LevelMasks(ids, tuple(names))


def _merge(masks: LevelMasks, p: float, rng: np.random.Generator) -> LevelMasks:
    ids = masks.ids
    pairs = [
        np.stack([ids[:, :-1].ravel(), ids[:, 1:].ravel()], axis=1),
        np.stack([ids[:-1, :].ravel(), ids[1:, :].ravel()], axis=1),
    ]
    pairs = np.concatenate(pairs)
    pairs = pairs[(pairs[:, 0] >= 0) & (pairs[:, 1] >= 0) & (pairs[:, 0] != pairs[:, 1])]
    pairs = np.unique(np.sort(pairs, axis=1), axis=0)
    areas = np.bincount(ids[ids >= 0], minlength=len(masks))
    target = np.arange(len(masks))
    used = np.zeros(len(masks), dtype=bool)
    for a, b in pairs:
        if rng.uniform() >= p or used[a] or used[b]:
            continue
        used[a] = used[b] = True
        keep, gone = (a, b) if areas[a] >= areas[b] else (b, a)
        target[gone] = keep
    merged = np.full(ids.shape, -1, dtype=np.int32)
    inside = ids >= 0
    merged[inside] = target[ids[inside]]
    return LevelMasks(merged, masks.names)


def _split(masks: LevelMasks, p: float, min_pixels: int, rng: np.random.Generator) -> LevelMasks:
    ids, names = masks.ids.copy(), list(masks.names)
    for index, box in enumerate(ndimage.find_objects(masks.ids + 1, max_label=len(masks))):
        if box is None or rng.uniform() >= p:
            continue
        rows, cols = np.nonzero(masks.ids[box] == index)
        if rows.size < min_pixels:
            continue
        angle = rng.uniform(0.0, math.pi)
        along = cols * math.cos(angle) + rows * math.sin(angle)
        second = along > np.median(along)
        if not second.any() or second.all():
            continue
        window = ids[box]
        window[rows[second], cols[second]] = len(names)
        names.append(names[index])
    return LevelMasks(ids, tuple(names))


def _drop(masks: LevelMasks, p: float, rng: np.random.Generator) -> LevelMasks:
    dropped = np.concatenate([[False], rng.uniform(size=len(masks)) < p])
    ids = np.where(dropped[masks.ids + 1], -1, masks.ids).astype(np.int32)
    return LevelMasks(ids, masks.names)


def _jitter(masks: LevelMasks, p: float, max_shift: int, rng: np.random.Generator) -> LevelMasks:
    ids = masks.ids.copy()
    for index, box in enumerate(ndimage.find_objects(masks.ids + 1, max_label=len(masks))):
        if box is None or rng.uniform() >= p:
            continue
        radius = int(rng.integers(1, max_shift + 1))
        grow = rng.uniform() < 0.5
        window_box = grown_box(box, radius + 1, ids.shape)
        window = ids[window_box]
        own = masks.ids[window_box] == index
        if grow:
            window[ndimage.binary_dilation(own, disk(radius))] = index
        else:
            eroded = ndimage.binary_erosion(own, disk(radius), border_value=1)
            window[own & ~eroded & (window == index)] = -1
    return LevelMasks(ids, masks.names)


def _spurious(
    masks: LevelMasks,
    names_under: np.ndarray,
    expected: float,
    radius: tuple[int, int],
    rng: np.random.Generator,
) -> LevelMasks:
    ids, names = masks.ids.copy(), list(masks.names)
    height, width = ids.shape
    reach = math.ceil(radius[1])
    for _ in range(int(rng.poisson(expected))):
        cy, cx = int(rng.integers(height)), int(rng.integers(width))
        a, b = rng.uniform(radius[0], radius[1], size=2)
        angle = rng.uniform(0.0, math.pi)
        name = names_under[cy, cx]
        if name is None:
            continue
        window = grown_box((slice(cy, cy + 1), slice(cx, cx + 1)), reach, ids.shape)
        yy, xx = np.mgrid[window]
        dx, dy = xx - cx, yy - cy
        u = dx * math.cos(angle) + dy * math.sin(angle)
        v = -dx * math.sin(angle) + dy * math.cos(angle)
        ids[window][(u / a) ** 2 + (v / b) ** 2 <= 1.0] = len(names)
        names.append(str(name))
    return LevelMasks(ids, tuple(names))


@dataclass(frozen=True)
class FaultRates:
    """How often each fault strikes (:attr:`thgs.synthetic.OracleConfig.rates` holds them at
    severity 1, scaled linearly by its ``severity``).

    Attributes:
        wrong_level: probability per mask of being replaced by a neighbouring level's mask.
        merge: probability per pair of touching masks of being merged.
        split: probability per mask (of at least ``min_split_pixels``) of being split in two.
        drop: probability per mask of disappearing.
        jitter: probability per mask of growing or shrinking at its boundary.
        spurious: expected number of spurious small masks per view and level.
    """

    wrong_level: float = 0.06
    merge: float = 0.1
    split: float = 0.1
    drop: float = 0.08
    jitter: float = 0.4
    spurious: float = 2.0


@dataclass(frozen=True)
class MaskFaults:
    """The faults :func:`apply_faults` makes.

    Attributes:
        rates: how often each fault strikes.
        max_jitter: largest boundary shift in pixels.
        spurious_radius: range of the spurious ellipses' semi-axes in pixels.
        min_split_pixels: masks smaller than this are never split.
        min_pixels: masks smaller than this are removed after the faults.
    """

    rates: FaultRates
    max_jitter: int
    spurious_radius: tuple[int, int]
    min_split_pixels: int
    min_pixels: int


def apply_faults(
    clean: list[LevelMasks],
    maps: np.ndarray,
    hierarchy: Hierarchy,
    faults: MaskFaults,
    rng: np.random.Generator,
) -> list[LevelMasks]:
    """SAM-like faults on the clean masks of the three levels (see the module docstring).

    Args:
        clean: :func:`clean_masks` of the view.
        maps: [3, H, W] the view's :func:`ground_truth_maps` (names for spurious masks).
        hierarchy: the ground truth (node names).
        faults: the rates and sizes (:meth:`thgs.synthetic.oracle.OracleConfig.faults`).
        rng: the view's random generator.

    Returns:
        the faulty masks of levels s, m, l, compacted.
    """
    faulty = []
    for level, masks in enumerate(clean):
        rates = faults.rates
        masks = _wrong_level(masks, level, clean, rates.wrong_level, rng)
        masks = _merge(masks, rates.merge, rng)
        masks = _split(masks, rates.split, faults.min_split_pixels, rng)
        masks = _drop(masks, rates.drop, rng)
        masks = _jitter(masks, rates.jitter, faults.max_jitter, rng)
        names_under = np.array([*hierarchy.names[level + 1], None], dtype=object)[maps[level]]
        masks = _spurious(masks, names_under, rates.spurious, faults.spurious_radius, rng)
        faulty.append(masks.without_small(faults.min_pixels).compact())
    return faulty


def pool_default(levels: list[LevelMasks]) -> tuple[LevelMasks, list[tuple[int, int]]]:
    """The ``default`` level: all masks of s, m, l, identical ones once, largest painted first.

    Returns:
        the pooled masks and, for each, the (level, index) it came from (its feature's source).
    """
    height, width = levels[0].ids.shape
    candidates: list[tuple[int, int, int, np.ndarray]] = []
    seen: set[bytes] = set()
    for level, masks in enumerate(levels):
        flat = masks.ids.ravel()
        order = np.argsort(flat, kind="stable")
        starts = np.searchsorted(flat[order], np.arange(len(masks) + 1))
        for index in range(len(masks)):
            pixels = order[starts[index] : starts[index + 1]]
            key = pixels.tobytes()
            if key in seen:
                continue
            seen.add(key)
            candidates.append((-pixels.size, level, index, pixels))
    candidates.sort(key=lambda item: item[:3])
    ids = np.full(height * width, -1, dtype=np.int32)
    for slot, (_, _, _, pixels) in enumerate(candidates):
        ids[pixels] = slot
    visible = np.zeros(len(candidates), dtype=bool)
    visible[ids[ids >= 0]] = True  # masks painted over completely by smaller ones vanish
    kept = [candidate for candidate, shown in zip(candidates, visible) if shown]
    renumber = np.full(len(candidates) + 1, -1, dtype=np.int32)
    renumber[1:][visible] = np.arange(len(kept), dtype=np.int32)
    names = tuple(levels[level].names[index] for _, level, index, _ in kept)
    pooled = LevelMasks(renumber[ids + 1].reshape(height, width), names)
    return pooled, [(level, index) for _, level, index, _ in kept]
