"""The synthetic scene generator and its oracle guidance, against known answers."""

from __future__ import annotations

import math
import zlib
from collections import deque
from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy import ndimage

from thgs.errors import InputError
from thgs.synthetic import (
    FaultRates,
    LevelMasks,
    OracleConfig,
    SceneConfig,
    generate_scene,
    preset,
    render_view,
)
from thgs.synthetic.catalog import FLOOR_OBJECTS, TABLE_OBJECTS
from thgs.synthetic.oracle import mask_context, mask_features, oracle_guidance
from thgs.synthetic.sam_masks import apply_faults, clean_masks, ground_truth_maps, pool_default
from thgs.synthetic.shapes import Box, Disc, Ellipsoid, Frustum, Rect, TorusArc

TINY = SceneConfig(gaussians=8000, views=3, width=120, height=90, table_objects=5, seed=3)


@pytest.fixture(scope="module")
def scene():
    return generate_scene(TINY)


@pytest.fixture(scope="module")
def view(scene):
    """View 0: its max-weight ids and ground-truth maps."""
    _, max_id = render_view(scene, 0, (0.5, 0.5, 0.5))
    return max_id, ground_truth_maps(max_id, scene.hierarchy)


# --- shapes ---------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("surface", "on_surface", "share"),
    [
        # (surface, residual of the implicit equation, (indicator of a region, its area share))
        (Rect(2.0, 1.0), lambda p: p[:, 2], (lambda p: p[:, 0] > 0.5, 0.25)),
        (
            Disc(1.0),
            lambda p: p[:, 2],
            (lambda p: np.hypot(p[:, 0], p[:, 1]) < 0.5, 0.25),
        ),
        (
            Frustum(1.0, 0.5, 2.0),
            lambda p: np.hypot(p[:, 0], p[:, 1]) - (1.0 - 0.25 * p[:, 2]),
            # lateral area below z = 1 over the whole: (1 + 0.75) / (1 + 0.5) · 1/2
            (lambda p: p[:, 2] < 1.0, 1.75 / 3.0),
        ),
        (
            Ellipsoid((1.0, 1.0, 1.0)),
            lambda p: np.linalg.norm(p, axis=1) - 1.0,
            (lambda p: p[:, 2] > 0.5, 0.25),  # Archimedes: a cap's area ∝ its height
        ),
        (
            TorusArc(1.0, 0.25, 0.0, math.pi),
            lambda p: np.hypot(np.hypot(p[:, 0], p[:, 1]) - 1.0, p[:, 2]) - 0.25,
            # outer half of the tube: ∫(R + r cos φ) over |φ| < π/2 / (2πR) = (πR + 2r) / (2πR)
            (lambda p: np.hypot(p[:, 0], p[:, 1]) > 1.0, (math.pi + 0.5) / (2 * math.pi)),
        ),
        (
            Box(1.0, 2.0, 3.0, faces=("+x", "+y", "+z")),
            lambda p: np.minimum.reduce([abs(p[:, 0] - 0.5), abs(p[:, 1] - 1.0), abs(p[:, 2] - 3)]),
            (lambda p: np.isclose(p[:, 0], 0.5), 6.0 / 11.0),
        ),
    ],
)
def test_surfaces_sample_uniformly_on_the_surface(surface, on_surface, share):
    rng = np.random.default_rng(0)
    points, normals = surface.sample(rng, 40_000)
    assert points.shape == normals.shape == (40_000, 3)
    np.testing.assert_allclose(on_surface(points), 0.0, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-9)
    region, expected = share
    # binomial standard error at 40k samples is below 0.0025: 4 of them
    assert abs(region(points).mean() - expected) < 0.01


def test_normals_point_along_the_implicit_gradient():
    rng = np.random.default_rng(1)
    radii = np.array([0.5, 1.0, 2.0])
    points, normals = Ellipsoid(tuple(radii)).sample(rng, 1000)
    gradient = points / radii**2
    gradient /= np.linalg.norm(gradient, axis=1, keepdims=True)
    np.testing.assert_allclose(normals, gradient, atol=1e-9)
    points, normals = Frustum(1.0, 0.5, 1.0, inward=True).sample(rng, 1000)
    radial = points[:, :2] / np.linalg.norm(points[:, :2], axis=1, keepdims=True)
    assert (np.sum(normals[:, :2] * radial, axis=1) < 0).all()  # inward
    assert (normals[:, 2] < 0).all()  # a narrowing cone's inner wall looks down


# --- scenes ---------------------------------------------------------------------------------


def test_catalog_has_at_least_six_object_types_with_named_parts():
    assert len(TABLE_OBJECTS) + len(FLOOR_OBJECTS) >= 6
    rng = np.random.default_rng(0)
    for build in [*TABLE_OBJECTS.values(), *FLOOR_OBJECTS.values()]:
        model = build(rng)
        assert model.name and model.parts
        assert all(part.name and part.subparts for part in model.parts)
        assert all(sub.area > 0 for part in model.parts for sub in part.subparts)


def test_scene_ground_truth_is_nested_and_covers_every_node(scene):
    hierarchy = scene.hierarchy
    assert len(hierarchy) == len(scene.gaussians) == TINY.gaussians
    labels = hierarchy.labels
    floaters = labels[:, 1] < 0
    assert floaters.sum() == round(TINY.floaters * TINY.gaussians)
    assert (labels[floaters] == -1).all()
    kept = labels[~floaters]
    np.testing.assert_array_equal(kept[:, 0], kept[:, 1])  # level 0 repeats the sub-parts
    parents = hierarchy.levels.parents
    np.testing.assert_array_equal(parents[1][kept[:, 1]], kept[:, 2])
    np.testing.assert_array_equal(parents[2][kept[:, 2]], kept[:, 3])
    for level in (1, 2, 3):  # every node has Gaussians
        counts = np.bincount(kept[:, level], minlength=len(hierarchy.names[level]))
        assert counts.min() >= 30
    objects = hierarchy.names[3]
    assert objects[:3] == ("floor", "table", "chair")
    assert len(objects) == 3 + TINY.table_objects
    assert len(set(objects[3:])) >= 4
    assert "mug handle" in hierarchy.names[2] or "mug" not in objects


def test_scene_gaussians_sit_on_their_surfaces_like_trained_ones(scene):
    gaussians = scene.gaussians
    assert gaussians.kind == "2dgs" and gaussians.sh_degree == 0
    opacity = gaussians.activated_opacities()
    assert 0.7 < float((opacity > 0.7).float().mean()) < 0.95
    means = gaussians.means.double()
    labels = scene.hierarchy.labels
    floor = np.flatnonzero(labels[:, 3] == 0)
    np.testing.assert_allclose(means[floor, 2].numpy(), 0.0, atol=1e-6)
    normals = gaussians.surface_normals()[floor].double()
    np.testing.assert_allclose(normals[:, 2].abs().numpy(), 1.0, atol=1e-5)
    top = scene.hierarchy.names[2].index("table top")
    on_top = np.flatnonzero(labels[:, 2] == top)
    assert float(means[on_top, 2].max()) == pytest.approx(0.75, abs=1e-6)
    # colours jitter around the palette colour (σ = 0.03 per channel)
    colors = gaussians.dc_colors()[floor]
    assert float((colors - colors.mean(0)).std()) == pytest.approx(0.03, rel=0.2)


def test_same_seed_same_scene_other_seed_other_scene():
    a, b = generate_scene(TINY), generate_scene(TINY)
    for name in ("means", "quats", "scales", "opacities", "sh"):
        assert torch.equal(getattr(a.gaussians, name), getattr(b.gaussians, name))
    np.testing.assert_array_equal(a.hierarchy.labels, b.hierarchy.labels)
    assert torch.equal(a.cameras.viewmats, b.cameras.viewmats)
    c = generate_scene(replace(TINY, seed=4))
    assert not torch.equal(a.gaussians.means, c.gaussians.means)


def test_3dgs_scenes_are_flat_ellipsoids():
    scene = generate_scene(replace(TINY, kind="3dgs", views=1))
    scales = scene.gaussians.activated_scales()
    assert scales.shape[1] == 3
    surface = scene.hierarchy.labels[:, 1] >= 0
    np.testing.assert_allclose((scales[surface, 2] / scales[surface, 0]).numpy(), 0.05, rtol=1e-4)


def test_cameras_look_at_the_table_from_above(scene):
    cameras = scene.cameras
    centres = cameras.centers().numpy()
    assert (centres[:, 2] > 0.75).all()
    distance = np.linalg.norm(centres[:, :2], axis=1)
    assert (distance > 0.3).all() and (distance < 2.0).all()
    table_centre = torch.tensor([[0.0, 0.0, 0.75]], dtype=torch.float64)
    for i in range(len(cameras)):
        pixels, depth = cameras.select([i]).project(table_centre)
        assert depth.item() > 0
        assert 0 < pixels[0, 0, 0].item() < TINY.width and 0 < pixels[0, 0, 1].item() < TINY.height
    assert cameras.stems == ("frame_00001", "frame_00002", "frame_00003")


def test_presets_and_bad_configs():
    assert preset("synth-small").gaussians == 50_000
    assert (preset("synth-large").width, preset("synth-large").height) == (986, 728)
    assert preset("synth-medium", seed=5).seed == 5
    with pytest.raises(InputError, match="unknown preset"):
        preset("synth-huge")
    with pytest.raises(InputError, match="kind"):
        generate_scene(replace(TINY, kind="4dgs"))
    with pytest.raises(InputError, match="gaussians"):
        generate_scene(replace(TINY, gaussians=10))


# --- oracle ---------------------------------------------------------------------------------


def _flood_components(node_map: np.ndarray) -> set[frozenset[int]]:
    """Brute-force 4-connected components of equal non-negative values, as pixel-index sets."""
    height, width = node_map.shape
    seen = np.zeros(node_map.shape, dtype=bool)
    components = set()
    for y in range(height):
        for x in range(width):
            if seen[y, x] or node_map[y, x] < 0:
                continue
            value, queue, pixels = node_map[y, x], deque([(y, x)]), []
            seen[y, x] = True
            while queue:
                cy, cx = queue.popleft()
                pixels.append(cy * width + cx)
                for ny, nx in ((cy + 1, cx), (cy - 1, cx), (cy, cx + 1), (cy, cx - 1)):
                    if 0 <= ny < height and 0 <= nx < width and not seen[ny, nx]:
                        if node_map[ny, nx] == value:
                            seen[ny, nx] = True
                            queue.append((ny, nx))
            components.add(frozenset(pixels))
    return components


def _mask_sets(masks: LevelMasks) -> list[frozenset[int]]:
    flat = masks.ids.ravel()
    return [frozenset(np.flatnonzero(flat == i).tolist()) for i in range(len(masks))]


def test_ground_truth_maps_follow_the_max_weight_gaussian(scene, view):
    max_id, maps = view
    y, x = np.nonzero(max_id >= 0)
    np.testing.assert_array_equal(maps[:, y, x], scene.hierarchy.labels[max_id[y, x], 1:].T)
    assert (maps[:, max_id < 0] == -1).all()


def test_severity_zero_reproduces_the_ground_truth_components(scene, view):
    _, maps = view
    config = OracleConfig(severity=0.0, min_pixels=1, feature_noise=0.0)
    clean = clean_masks(maps, scene.hierarchy)
    faulty = apply_faults(clean, maps, scene.hierarchy, config.faults(), np.random.default_rng(0))
    for level in range(3):
        expected = _flood_components(maps[level])
        assert set(_mask_sets(faulty[level])) == expected
        # every mask is named after the node under it
        names = np.array(scene.hierarchy.names[level + 1], dtype=object)
        for i, name in enumerate(faulty[level].names):
            nodes = np.unique(maps[level][faulty[level].ids == i])
            assert list(names[nodes]) == [name]


class _FakeEncoder:
    """A deterministic stand-in for tests of plumbing (not of text semantics)."""

    space = "test/hash"
    dim = 16

    def encode(self, texts):
        rows = [np.random.default_rng(zlib.crc32(t.encode())).normal(size=16) for t in texts]
        rows = np.array(rows, dtype=np.float64).reshape(-1, 16)
        return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


def test_oracle_guidance_at_severity_zero_is_the_clean_layout(scene, view):
    max_id, maps = view
    encoder = _FakeEncoder()
    config = OracleConfig(severity=0.0, min_pixels=1, feature_noise=0.0)
    guidance = oracle_guidance("frame_00001", max_id, scene.hierarchy, encoder, config, 0)
    offset = len(np.unique(guidance.segments[0])) - 1
    for level in range(3):
        segments = guidance.segments[level + 1]
        assert {
            frozenset(np.flatnonzero(segments.ravel() == i).tolist())
            for i in np.unique(segments[segments >= 0])
        } == _flood_components(maps[level])
        names = scene.hierarchy.names[level + 1]
        for i in np.unique(segments[segments >= 0]):
            node = int(np.unique(maps[level][segments == i])[0])
            np.testing.assert_allclose(
                guidance.features[i], encoder.encode([names[node]])[0], atol=1e-6
            )
        assert segments[segments >= 0].min() == offset
        offset = segments.max() + 1
    # default: the smallest mask over a pixel wins, so with clean masks it is level s
    np.testing.assert_array_equal(guidance.segments[0] >= 0, guidance.segments[1] >= 0)


def test_oracle_guidance_of_an_empty_view_has_no_masks(scene):
    # every fault enabled at full rate, nothing in view: no masks, no feature rows, no crash
    config = OracleConfig(severity=1.0, min_pixels=1)
    empty = np.full((24, 32), -1, dtype=np.int64)
    guidance = oracle_guidance("frame_00001", empty, scene.hierarchy, _FakeEncoder(), config, 0)
    assert (guidance.segments == -1).all() and guidance.features.shape == (0, 16)


def _only(**rates) -> OracleConfig:
    zero = {name: 0.0 for name in ("wrong_level", "merge", "split", "drop", "jitter", "spurious")}
    return OracleConfig(severity=1.0, rates=FaultRates(**{**zero, **rates}), min_pixels=1)


def _faults(scene, maps, config, seed=0):
    clean = clean_masks(maps, scene.hierarchy)
    rng = np.random.default_rng(seed)
    return clean, apply_faults(clean, maps, scene.hierarchy, config.faults(), rng)


def test_drop_only_removes_whole_masks(scene, view):
    _, maps = view
    clean, faulty = _faults(scene, maps, _only(drop=0.5))
    for before, after in zip(clean, faulty):
        kept = set(_mask_sets(after))
        assert kept < set(_mask_sets(before))
        dropped = after.ids < 0
        assert (before.ids[~dropped] >= 0).all()


def test_merge_only_unites_touching_pairs(scene, view):
    _, maps = view
    clean, faulty = _faults(scene, maps, _only(merge=1.0))
    merges = 0
    for before, after in zip(clean, faulty):
        np.testing.assert_array_equal(after.ids < 0, before.ids < 0)
        for i, pixels in enumerate(_mask_sets(after)):
            parts = np.unique(before.ids.ravel()[list(pixels)])
            assert len(parts) in (1, 2)
            union = np.isin(before.ids, parts)
            assert (union.ravel()[list(pixels)]).all() and union.sum() == len(pixels)
            if len(parts) == 2:
                merges += 1
                a, b = before.ids == parts[0], before.ids == parts[1]
                touching = (a[:, :-1] & b[:, 1:]) | (b[:, :-1] & a[:, 1:])
                touching_v = (a[:-1] & b[1:]) | (b[:-1] & a[1:])
                assert touching.any() or touching_v.any()
                larger = parts[np.argmax([a.sum(), b.sum()])]
                assert after.names[i] == before.names[larger]
    assert merges > 0


def test_split_only_cuts_masks_in_two(scene, view):
    _, maps = view
    clean, faulty = _faults(scene, maps, _only(split=1.0))
    splits = 0
    for before, after in zip(clean, faulty):
        np.testing.assert_array_equal(after.ids < 0, before.ids < 0)
        for j in range(len(before)):
            pieces = np.unique(after.ids[before.ids == j])
            assert len(pieces) in (1, 2)
            # a piece never leaves its mask, and keeps its name
            for piece in pieces:
                assert (before.ids[after.ids == piece] == j).all()
                assert after.names[piece] == before.names[j]
            if len(pieces) == 2:
                splits += 1
                assert (before.ids == j).sum() >= OracleConfig().min_split_pixels
    assert splits > 0


def test_jitter_only_moves_boundaries_by_at_most_max_jitter(scene, view):
    _, maps = view
    config = _only(jitter=1.0)
    clean, faulty = _faults(scene, maps, config)
    radius = config.max_jitter
    for before, after in zip(clean, faulty):
        changed = np.argwhere(after_ids_differ(before, after))
        assert len(changed) > 0
        padded = np.pad(before.ids, radius, constant_values=-1)
        for y, x in changed:
            window = padded[y : y + 2 * radius + 1, x : x + 2 * radius + 1]
            assert len(np.unique(window)) >= 2  # within max_jitter of a clean boundary
        assert set(after.names) <= set(before.names)


def after_ids_differ(before: LevelMasks, after: LevelMasks) -> np.ndarray:
    """[H, W] pixels whose mask changed, comparing masks by name (indices are renumbered)."""
    names_before = np.array([*before.names, None], dtype=object)[before.ids]
    names_after = np.array([*after.names, None], dtype=object)[after.ids]
    return names_before != names_after


def test_spurious_only_adds_small_masks_and_changes_nothing_else(scene, view):
    _, maps = view
    config = _only(spurious=6.0)
    clean, faulty = _faults(scene, maps, config)
    largest = math.pi * config.spurious_radius[1] ** 2 + 4 * config.spurious_radius[1] + 1
    added = 0
    for level, (before, after) in enumerate(zip(clean, faulty)):
        spurious = np.zeros(before.ids.shape, dtype=bool)
        for j in range(len(before)):
            own = before.ids == j
            pieces, overlap = np.unique(after.ids[own], return_counts=True)
            same_name = [
                (count, piece)
                for piece, count in zip(pieces, overlap)
                if piece >= 0 and after.names[piece] == before.names[j]
            ]
            # the piece of j with j's name and most of its pixels is what is left of j (a small
            # mask may be covered completely); every other pixel of j went to a spurious mask
            remnant = max(same_name)[1] if same_name else -2
            spurious |= own & (after.ids != remnant)
        spurious |= (before.ids < 0) & (after.ids >= 0)
        for i in np.unique(after.ids[spurious]):
            if i < 0:
                continue
            assert (after.ids == i).sum() <= largest
            added += 1
        names_under = np.array([*scene.hierarchy.names[level + 1], None], dtype=object)[maps[level]]
        for i in np.unique(after.ids[spurious & (after.ids >= 0)]):
            assert after.names[i] in set(names_under[after.ids == i])
    assert added > 0


def test_wrong_level_only_swaps_in_a_neighbouring_levels_mask(scene, view):
    _, maps = view
    clean, faulty = _faults(scene, maps, _only(wrong_level=0.6), seed=2)
    swapped = 0
    for level, after in enumerate(faulty):
        neighbours = [k for k in (level - 1, level, level + 1) if 0 <= k < 3]
        for i, pixels in enumerate(_mask_sets(after)):
            homes = [
                k
                for k in neighbours
                if len(np.unique(clean[k].ids.ravel()[list(pixels)])) == 1
                and clean[k].ids.ravel()[next(iter(pixels))] >= 0
                and clean[k].names[clean[k].ids.ravel()[next(iter(pixels))]] == after.names[i]
            ]
            assert homes, "every mask lies inside one clean mask of its level or a neighbour"
            if level not in homes and pixels in set(_mask_sets(clean[homes[0]])):
                swapped += 1
    assert swapped > 0


def test_pool_default_paints_the_smallest_mask_on_top():
    ids_s = np.full((4, 6), -1, dtype=np.int32)
    ids_s[1:3, 1:3] = 0
    ids_m = np.full((4, 6), -1, dtype=np.int32)
    ids_m[0:4, 0:4] = 0
    ids_m[:, 5] = 1
    ids_l = ids_m.copy()  # identical masks are pooled once
    levels = [
        LevelMasks(ids_s, ("nose",)),
        LevelMasks(ids_m, ("head", "ear")),
        LevelMasks(ids_l, ("bear", "ear")),
    ]
    pooled, sources = pool_default(levels)
    # by area (16, 4, 4), ties by level: the nose (level s) before the ear (level m)
    assert pooled.names == ("head", "nose", "ear")
    assert sources == [(1, 0), (0, 0), (1, 1)]
    expected = np.full((4, 6), -1)
    expected[0:4, 0:4] = 0
    expected[1:3, 1:3] = 1
    expected[:, 5] = 2
    np.testing.assert_array_equal(pooled.ids, expected)


def test_feature_noise_sets_the_expected_cosine():
    encoder = _FakeEncoder()
    names = tuple(f"thing {i}" for i in range(2000))
    exact = mask_features(names, encoder, 0.0, np.random.default_rng(0))
    np.testing.assert_allclose(exact, encoder.encode(list(names)), atol=1e-6)
    noisy = mask_features(names, encoder, 0.5, np.random.default_rng(0))
    np.testing.assert_allclose(np.linalg.norm(noisy, axis=1), 1.0, atol=1e-5)
    cosine = np.sum(noisy * exact, axis=1).mean()
    # e + 0.5 g / √D with |g|² ≈ D: cos ≈ 1 / √(1 + 0.25)
    assert cosine == pytest.approx(1 / math.sqrt(1.25), abs=0.03)


def test_context_mix_moves_each_mask_feature_towards_its_parent_and_surroundings(scene, view):
    # severity 0, no noise: the s-level mask of a sub-part is (1 − c)·e(own) + c·e(context),
    # its context the part above it and the most common other object in a 6-pixel ring around
    max_id, maps = view
    encoder = _FakeEncoder()
    hierarchy = scene.hierarchy
    clean = clean_masks(maps, hierarchy, min_pixels=10)
    context = mask_context(clean[0], 0, maps, hierarchy, 6)
    disk = np.add.outer(np.arange(-6, 7) ** 2, np.arange(-6, 7) ** 2) <= 36
    for index in range(0, len(clean[0]), 7):
        inside = clean[0].ids == index
        part = np.bincount(maps[1][inside]).argmax()
        own = np.bincount(maps[2][inside]).argmax()
        ring = ndimage.binary_dilation(inside, structure=disk) & ~inside
        around = maps[2][ring]
        around = around[(around >= 0) & (around != own)]
        expected = [hierarchy.names[2][part]]
        if around.size:
            expected.append(hierarchy.names[3][np.bincount(around).argmax()])
        assert context[index] == tuple(expected)
    # objects have no parent: only their surroundings
    for words in mask_context(clean[2], 2, maps, hierarchy, 6):
        assert len(words) <= 1
    mix = 0.4
    config = OracleConfig(severity=0.0, min_pixels=10, feature_noise=0.0, context_mix=mix)
    guidance = oracle_guidance("frame_00001", max_id, hierarchy, encoder, config, 0)
    first = guidance.segments[1][guidance.segments[1] >= 0].min()
    for index in range(0, len(clean[0]), 7):
        words = context[index]
        around = encoder.encode(list(words)).astype(np.float64).mean(axis=0)
        mixed = (1 - mix) * encoder.encode([clean[0].names[index]])[
            0
        ] + mix * around / np.linalg.norm(around)
        np.testing.assert_allclose(
            guidance.features[first + index], mixed / np.linalg.norm(mixed), atol=1e-6
        )
    # the knob at 0 is the name-perfect oracle, draw for draw
    plain = oracle_guidance("frame_00001", max_id, hierarchy, encoder, OracleConfig(), 0)
    same = oracle_guidance(
        "frame_00001", max_id, hierarchy, encoder, OracleConfig(context_mix=0.0), 0
    )
    np.testing.assert_array_equal(plain.features, same.features)
    for bad, message in [
        ({"context_mix": -0.1}, r"^OracleConfig\.context_mix: must be in \[0, 1\], got -0\.1$"),
        ({"context_mix": 1.5}, r"^OracleConfig\.context_mix: must be in \[0, 1\], got 1\.5$"),
        ({"context_radius": 0}, r"^OracleConfig\.context_radius: must be ≥ 1 pixel, got 0$"),
        ({"severity": -1.0}, r"^OracleConfig\.severity: must be a number ≥ 0, got -1\.0$"),
        ({"severity": math.inf}, r"^OracleConfig\.severity: must be a number ≥ 0, got inf$"),
        ({"feature_noise": math.nan}, r"^OracleConfig\.feature_noise: must be .* got nan$"),
        (
            {"rates": FaultRates(drop=-0.5)},
            r"^OracleConfig\.rates\.drop: must be ≥ 0, got -0\.5$",
        ),
    ]:
        with pytest.raises(InputError, match=message):
            OracleConfig(**bad)
