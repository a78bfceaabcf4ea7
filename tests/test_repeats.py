"""Repeated parts: the pair rule against brute force, a table's legs and a stack of books."""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest
import torch

from thgs import Gaussians
from thgs.errors import InputError
from thgs.hierarchy import RegionLevels, RepeatConfig, group_repeated_parts
from thgs.hierarchy.repeats import repeated_part_pairs, residual_part_features


def brute_force_pairs(touching, objects, features, config):
    """The rule of docs/build.md, one pair and one common neighbour at a time."""
    count = len(objects)
    adjacent = {(int(a), int(b)) for a, b in touching} | {(int(b), int(a)) for a, b in touching}
    cos = features @ features.T
    pairs = []
    for a, b in itertools.combinations(range(count), 2):
        if objects[a] != objects[b] or (a, b) in adjacent or cos[a, b] < config.similarity:
            continue
        for c in range(count):
            if (
                objects[c] == objects[a]
                and (a, c) in adjacent
                and (b, c) in adjacent
                and cos[a, b] - max(cos[a, c], cos[b, c]) >= config.margin
            ):
                pairs.append((a, b))
                break
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


@pytest.mark.parametrize("seed", range(6))
def test_pairs_match_brute_force(seed):
    rng = np.random.default_rng(seed)
    count = 24
    touching = rng.integers(0, count, (50, 2))
    objects = rng.integers(0, 3, count)
    centres = rng.normal(size=(4, 6))
    features = centres[rng.integers(0, 4, count)] + rng.normal(scale=0.25, size=(count, 6))
    features /= np.linalg.norm(features, axis=1, keepdims=True)
    features[rng.random(count) < 0.1] = 0.0  # never seen
    config = RepeatConfig(similarity=0.7, margin=0.05 * (seed % 3))
    expected = brute_force_pairs(touching, objects, features, config)
    found = repeated_part_pairs(touching, objects, features, config)
    np.testing.assert_array_equal(found, expected)
    assert seed != 0 or len(expected) > 0  # the case is not empty


def gaussians_at(means: np.ndarray) -> Gaussians:
    n = len(means)
    return Gaussians(
        means=torch.as_tensor(means, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 3), -4.0),
        opacities=torch.zeros(n),
        sh=torch.zeros(n, 16, 3),
    )


def table() -> tuple[Gaussians, np.ndarray]:
    """A 1.1 × 1.1 top of 12 × 12 points at z = 1 (unit 0) and four legs of 10 points under
    its corners (units 1–4): the legs touch the top and not each other."""
    grid = np.arange(12) * 0.1
    x, y = np.meshgrid(grid, grid, indexing="ij")
    top = np.stack([x.ravel(), y.ravel(), np.ones(144)], axis=1)
    legs = [
        np.stack([np.full(10, cx), np.full(10, cy), np.arange(10) * 0.1], axis=1)
        for cx, cy in [(0.0, 0.0), (1.1, 0.0), (0.0, 1.1), (1.1, 1.1)]
    ]
    units = np.repeat(np.arange(5), [144, 10, 10, 10, 10])
    return gaussians_at(np.concatenate([top, *legs])), units


def levels_of(units: np.ndarray, objects: np.ndarray) -> RegionLevels:
    """Levels 0–2 = ``units``; level 3 = ``objects[unit]``."""
    return RegionLevels.from_labels(np.stack([units, units, units, objects[units]], axis=1))


def unit(*rows) -> np.ndarray:
    rows = np.asarray(rows, dtype=np.float64)
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


LEG_FEATURES = unit([0.1, 1, 0], [0, 1, 0.1], [0.05, 1, 0.05], [0, 1, -0.1])


def test_a_tables_legs_become_one_part():
    gaussians, units = table()
    merged = levels_of(units, np.zeros(5, dtype=np.int64))
    features = np.concatenate([unit([1, 0, 0]), LEG_FEATURES])
    grouped = group_repeated_parts(gaussians, merged, features)
    np.testing.assert_array_equal(grouped.labels[:, 2], np.minimum(units, 1))
    for k in (0, 1, 3):
        np.testing.assert_array_equal(grouped.labels[:, k], merged.labels[:, k])
    assert grouped.counts == (5, 5, 2, 1)
    for k in (1, 2, 3):
        parent = grouped.parents[k - 1]
        np.testing.assert_array_equal(grouped.labels[:, k], parent[grouped.labels[:, k - 1]])
    # legs as alike as the top they hang from are not a repeated part
    alike_top = np.concatenate([unit([0, 1, 0]), LEG_FEATURES])
    same = group_repeated_parts(gaussians, merged, alike_top)
    np.testing.assert_array_equal(same.labels, merged.labels)
    # switched off (the reference): nothing changes
    off = group_repeated_parts(gaussians, merged, features, RepeatConfig(enabled=False))
    np.testing.assert_array_equal(off.labels, merged.labels)


def test_legs_of_another_object_or_never_seen_stay_apart():
    gaussians, units = table()
    features = np.concatenate([unit([1, 0, 0]), LEG_FEATURES])
    # legs 3 and 4 belong to another object: no part of it touches both
    split = group_repeated_parts(gaussians, levels_of(units, np.array([0, 0, 0, 1, 1])), features)
    np.testing.assert_array_equal(split.labels[:, 2], np.array([0, 1, 1, 2, 3])[units])
    # leg 2 was never seen (zero feature): it joins nothing
    unseen = features.copy()
    unseen[2] = 0.0
    merged = levels_of(units, np.zeros(5, dtype=np.int64))
    grouped = group_repeated_parts(gaussians, merged, unseen)
    np.testing.assert_array_equal(grouped.labels[:, 2], np.array([0, 1, 2, 1, 1])[units])


def test_a_stack_of_alike_books_stays_apart():
    # three 5 × 5 × 2 blocks stacked along z: book 0 and book 2 both touch book 1 and look alike,
    # but no more alike than book 1 is to them
    grid = np.arange(5) * 0.1
    block = np.stack(np.meshgrid(grid, grid, [0.0, 0.1], indexing="ij"), axis=-1).reshape(-1, 3)
    means = np.concatenate([block + np.array([0.0, 0.0, 0.2 * i]) for i in range(3)])
    units = np.repeat(np.arange(3), 50)
    merged = levels_of(units, np.zeros(3, dtype=np.int64))
    books = unit([1, 0.1, 0], [1, 0, 0.1], [1, -0.1, 0])
    grouped = group_repeated_parts(gaussians_at(means), merged, books)
    np.testing.assert_array_equal(grouped.labels, merged.labels)
    # the same stack with a differently-looking middle book: the outer books are one part
    sandwich = unit([1, 0.1, 0], [0, 0, 1], [1, -0.1, 0])
    grouped = group_repeated_parts(gaussians_at(means), merged, sandwich)
    np.testing.assert_array_equal(grouped.labels[:, 2], np.array([0, 1, 0])[units])


def test_bad_input_is_named():
    gaussians, units = table()
    merged = levels_of(units, np.zeros(5, dtype=np.int64))
    with pytest.raises(InputError, match="part_features"):
        group_repeated_parts(gaussians, merged, np.zeros((4, 3)))
    with pytest.raises(InputError, match="levels: must be nested levels of the 184"):
        group_repeated_parts(gaussians, replace(merged, parents=None), np.zeros((5, 3)))
    with pytest.raises(InputError, match="levels: must be nested levels of the 3"):
        group_repeated_parts(gaussians_at(np.zeros((3, 3))), merged, np.zeros((5, 3)))
    for fields in ({"similarity": 0.0}, {"similarity": 1.5}, {"margin": -0.1}, {"neighbors": 1}):
        with pytest.raises(InputError, match="RepeatConfig"):
            RepeatConfig(**fields)


def test_residual_features_match_a_hand_computation():
    rng = np.random.default_rng(3)
    parts = unit(*rng.normal(size=(6, 5)))
    parts[4] = 0.0  # never seen
    whole = unit(*rng.normal(size=(2, 5)))
    whole[1] = 0.0  # an object never seen: nothing is projected out of its parts
    objects = np.array([0, 0, 0, 1, 1, 1])
    found = residual_part_features(parts, whole, objects)
    mean = parts[[0, 1, 2, 3, 5]].mean(axis=0)
    for r in range(6):
        if r == 4:
            np.testing.assert_array_equal(found[r], 0.0)
            continue
        centred = (parts[r] - mean) / np.linalg.norm(parts[r] - mean)
        if objects[r] == 0:
            axis = (whole[0] - mean) / np.linalg.norm(whole[0] - mean)
            centred = centred - (centred @ axis) * axis
        np.testing.assert_allclose(found[r], centred / np.linalg.norm(centred), atol=1e-12)
    # a part that looks exactly like its object keeps nothing, and joins nothing
    alike = residual_part_features(np.stack([whole[0], parts[1]]), whole[:1], np.zeros(2, int))
    np.testing.assert_array_equal(alike[0], 0.0)


def table_in_a_room() -> tuple[Gaussians, RegionLevels]:
    """:func:`table` (object 0: units 0–4) and six more parts of 10 points each, far apart, of a
    second object (units 5–10): a scene's parts are not all legs."""
    gaussians, units = table()
    others = [np.full((10, 3), 10.0 * (i + 1)) + np.arange(10)[:, None] * 0.1 for i in range(6)]
    means = np.concatenate([gaussians.means.numpy(), *others])
    units = np.concatenate([units, np.repeat(np.arange(5, 11), 10)])
    objects = np.array([0] * 5 + [1] * 6)
    return gaussians_at(means), levels_of(units, objects)


def clip_like_features(rng: np.random.Generator, drift: float, same_leg_name: bool = False):
    """Part and object features of :func:`table_in_a_room` as CLIP-like crops give them: every
    part ``drift`` its object's look and the rest its own name, plus noise, then pulled towards
    one direction all crops share (``normalize(0.15 f + 0.85 u)``). With ``same_leg_name`` the
    legs look like the top (one name for all five)."""
    names = unit(*rng.normal(size=(10, 32)))  # table, room, top, leg, six other part names
    shared = unit(rng.normal(size=32))[0]

    def crop(name: np.ndarray) -> np.ndarray:
        look = unit(name + rng.normal(scale=0.05, size=32))[0]
        return unit(0.15 * look + 0.85 * shared)[0]

    leg = names[2] if same_leg_name else names[3]
    parts = [crop((1 - drift) * names[2] + drift * names[0])]
    parts += [crop((1 - drift) * leg + drift * names[0]) for _ in range(4)]
    parts += [crop((1 - drift) * names[4 + i] + drift * names[1]) for i in range(6)]
    return np.stack(parts), np.stack([crop(names[0]), crop(names[1])])


def test_clip_like_legs_are_grouped_by_their_residuals_not_by_their_features():
    gaussians, merged = table_in_a_room()
    legs_one_part = np.array([0, 1, 1, 1, 1, 2, 3, 4, 5, 6, 7])[merged.labels[:, 1]]
    residual = RepeatConfig(compare="residual", similarity=0.3, margin=0.2)
    for seed in range(5):
        parts, objects = clip_like_features(np.random.default_rng(seed), drift=0.6)
        # the raw features are all alike: no difference reaches the margin
        assert (parts @ parts.T).min() > 0.95
        raw = group_repeated_parts(gaussians, merged, parts)
        np.testing.assert_array_equal(raw.labels, merged.labels)
        grouped = group_repeated_parts(gaussians, merged, parts, residual, object_features=objects)
        np.testing.assert_array_equal(grouped.labels[:, 2], legs_one_part)
    # legs that look like the top they hang from are not a repeated part
    parts, objects = clip_like_features(np.random.default_rng(0), 0.6, same_leg_name=True)
    same = group_repeated_parts(gaussians, merged, parts, residual, object_features=objects)
    np.testing.assert_array_equal(same.labels, merged.labels)


def test_residual_comparison_needs_the_object_features():
    gaussians, units = table()
    merged = levels_of(units, np.zeros(5, dtype=np.int64))
    features = np.concatenate([unit([1, 0, 0]), LEG_FEATURES])
    residual = RepeatConfig(compare="residual")
    with pytest.raises(InputError, match=r"object_features: must be \[R_3, D\] = \[1, 3\]"):
        group_repeated_parts(gaussians, merged, features, residual)
    with pytest.raises(InputError, match="object_features"):
        group_repeated_parts(gaussians, merged, features, residual, object_features=np.ones((2, 3)))
    with pytest.raises(InputError, match=r"RepeatConfig\.compare: must be 'raw' or 'residual'"):
        RepeatConfig(compare="centred")  # type: ignore[arg-type]
