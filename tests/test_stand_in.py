"""The oracle's CLIP stand-in: parent drift, surroundings, confusion and compression against
hand-computed mixtures, the named settings and their specs, and the refusals."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from thgs.errors import InputError
from thgs.eval.ground_truth import Hierarchy
from thgs.synthetic import (
    CLIP_GRID,
    STAND_INS,
    OracleConfig,
    SceneConfig,
    generate_scene,
    render_view,
    stand_in,
    stand_in_spec,
)
from thgs.synthetic.catalog import CONFUSABLE_NAMES, FLOOR_OBJECTS, TABLE_OBJECTS
from thgs.synthetic.oracle import (
    MaskContext,
    compression_direction,
    mask_context,
    mask_contexts,
    mask_embeddings,
    mask_features,
    oracle_guidance,
)
from thgs.synthetic.sam_masks import LevelMasks, clean_masks, ground_truth_maps

VOCABULARY = (
    "mug", "mug body", "coffee", "mug handle", "table", "table top", "bottle", "bottle body",
    "soil", "chair", "chair seat", "floor",
)  # fmt: skip


class OneHot:
    """Each word of :data:`VOCABULARY` is its own axis, so a mixture's coordinates are its
    weights."""

    space = "test/one-hot"
    dim = len(VOCABULARY)

    def encode(self, texts):
        return np.eye(self.dim, dtype=np.float32)[[VOCABULARY.index(t) for t in texts]]


def _weights(vector: np.ndarray) -> dict[str, float]:
    return {word: round(float(v), 6) for word, v in zip(VOCABULARY, vector) if abs(v) > 1e-9}


@pytest.fixture(scope="module")
def toy():
    """A 6 × 12 view: the table top on the left (columns 0–3), a mug on the right, its body
    (sub-parts mug body, columns 4–7, and coffee, 8–9) and its handle (10–11)."""
    subparts = ("table top", "mug body", "coffee", "mug handle")
    parts = ("table top", "mug body", "mug handle")
    objects = ("table", "mug")
    hierarchy = Hierarchy.from_subparts(
        np.arange(4), np.array([0, 1, 1, 2]), np.array([0, 1, 1]), (subparts, parts, objects)
    )
    columns = np.repeat(np.arange(4), [4, 4, 2, 2])  # sub-part per column
    sub = np.tile(columns, (6, 1)).astype(np.int32)
    maps = np.stack([sub, np.array([0, 1, 1, 2])[sub], np.array([0, 1, 1, 1])[sub]])
    return hierarchy, maps


def test_stand_in_mixes_drift_confusion_and_surroundings_as_computed_by_hand(toy):
    hierarchy, maps = toy
    config = OracleConfig(subpart_drift=0.6, part_drift=0.5, surroundings=0.2, confusion=0.25)
    masks = clean_masks(maps, hierarchy)
    contexts = [mask_contexts(masks[k], k, maps, hierarchy, radius=3) for k in range(3)]
    subparts = dict(zip(masks[0].names, contexts[0]))
    assert subparts["coffee"] == MaskContext(("mug body", "mug"), None)  # the ring is all mug
    assert subparts["mug handle"] == MaskContext(("mug handle", "mug"), None)
    assert subparts["mug body"] == MaskContext(("mug body", "mug"), "table")
    assert dict(zip(masks[2].names, contexts[2]))["table"] == MaskContext((), "mug")
    embeddings = [mask_embeddings(masks[k].names, k, contexts[k], OneHot(), config) for k in (0, 1)]
    # coffee: 0.4·b(coffee) + 0.6·(0.5·b(mug body) + 0.5·b(mug)), b(x) = 0.75·x + 0.25·x's
    # look-alike (coffee/soil, mug body/bottle body, mug/bottle); no other object borders it
    assert _weights(embeddings[0][masks[0].names.index("coffee")]) == pytest.approx({
        "coffee": 0.3, "soil": 0.1, "mug body": 0.225, "bottle body": 0.075, "mug": 0.225,
        "bottle": 0.075,
    })  # fmt: skip
    # the handle's sub-part is the handle's part (same name, same crop): it starts at the part,
    # 0.5·handle + 0.5·b(mug)
    handle = pytest.approx({"mug handle": 0.5, "mug": 0.375, "bottle": 0.125})
    assert _weights(embeddings[0][masks[0].names.index("mug handle")]) == handle
    assert _weights(embeddings[1][masks[1].names.index("mug handle")]) == handle
    # the mug body sub-part is its part's crop and borders the table: 0.8·(0.5·b(mug body) +
    # 0.5·b(mug)) + 0.2·b(table), b(table) = 0.75·table + 0.25·chair
    assert _weights(embeddings[0][masks[0].names.index("mug body")]) == pytest.approx({
        "mug body": 0.3, "bottle body": 0.1, "mug": 0.3, "bottle": 0.1, "table": 0.15,
        "chair": 0.05,
    })  # fmt: skip
    # objects have no parent: the table is b(table) with 0.2 of the mug beside it
    objects = mask_embeddings(masks[2].names, 2, contexts[2], OneHot(), config)
    assert _weights(objects[masks[2].names.index("table")]) == pytest.approx({
        "table": 0.6, "chair": 0.2, "mug": 0.15, "bottle": 0.05,
    })  # fmt: skip
    # every mixture's weights sum to 1
    for rows in (*embeddings, objects):
        np.testing.assert_allclose(rows.sum(axis=1), 1.0)


def test_the_older_knob_reads_the_same_context(toy):
    hierarchy, maps = toy
    masks = clean_masks(maps, hierarchy)
    for k in range(3):
        expected = tuple(
            (*context.ancestors[:1], *([context.surroundings] if context.surroundings else []))
            for context in mask_contexts(masks[k], k, maps, hierarchy, radius=3)
        )
        assert mask_context(masks[k], k, maps, hierarchy, radius=3) == expected


def test_compression_shrinks_every_cosine_by_the_stated_factor():
    encoder = OneHot()
    names = tuple(VOCABULARY)
    kappa = 0.85
    plain = mask_features(names, encoder, 0.0, np.random.default_rng(0))
    pressed = mask_features(names, encoder, 0.0, np.random.default_rng(0), compression=kappa)
    u = compression_direction(encoder.dim)
    np.testing.assert_allclose(np.linalg.norm(u), 1.0)
    np.testing.assert_array_equal(u, compression_direction(encoder.dim))  # fixed: the model's
    for row, name in zip(pressed, names):
        e = encoder.encode([name])[0].astype(np.float64)
        mixed = (1 - kappa) * e + kappa * u
        np.testing.assert_allclose(row, mixed / np.linalg.norm(mixed), atol=1e-6)
    # with a direction orthogonal to the texts, a match's cosine is (1 − κ) / √((1 − κ)² + κ²)
    cosines = np.sum(pressed * plain, axis=1)
    orthogonal = (1 - kappa) / math.hypot(1 - kappa, kappa)
    expected = ((1 - kappa) + kappa * (plain @ u)) / np.sqrt(
        (1 - kappa) ** 2 + kappa**2 + 2 * kappa * (1 - kappa) * (plain @ u)
    )
    np.testing.assert_allclose(cosines, expected, atol=1e-6)
    assert orthogonal == pytest.approx(0.174, abs=0.001)


def test_clip_like_guidance_is_the_mixture_with_noise_then_compression():
    scene = generate_scene(SceneConfig(gaussians=6000, views=2, width=96, height=72, seed=4))
    _, max_id = render_view(scene, 0, (0.5, 0.5, 0.5))
    maps = ground_truth_maps(max_id, scene.hierarchy)
    encoder = _Hash()
    config = OracleConfig(severity=0.0, feature_noise=0.0).with_stand_in("clip-like")
    guidance = oracle_guidance("frame_00001", max_id, scene.hierarchy, encoder, config, 0)
    masks = clean_masks(maps, scene.hierarchy, config.min_pixels)
    offset = int(guidance.segments[0].max()) + 1
    u = compression_direction(encoder.dim)
    for level in range(3):
        contexts = mask_contexts(masks[level], level, maps, scene.hierarchy, 6)
        mixed = mask_embeddings(masks[level].names, level, contexts, encoder, config)
        mixed /= np.linalg.norm(mixed, axis=1, keepdims=True)
        expected = 0.15 * mixed + 0.85 * u
        expected /= np.linalg.norm(expected, axis=1, keepdims=True)
        rows = guidance.features[offset : offset + len(masks[level])]
        np.testing.assert_allclose(rows, expected, atol=1e-5)
        offset += len(masks[level])
    # the named setting at 0 is the name-perfect oracle, draw for draw
    plain = oracle_guidance("frame_00001", max_id, scene.hierarchy, encoder, OracleConfig(), 0)
    named = OracleConfig().with_stand_in("name-perfect")
    assert named == OracleConfig()
    again = oracle_guidance("frame_00001", max_id, scene.hierarchy, encoder, named, 0)
    np.testing.assert_array_equal(plain.features, again.features)
    faulty = oracle_guidance(
        "frame_00001",
        max_id,
        scene.hierarchy,
        encoder,
        OracleConfig().with_stand_in("clip-like"),
        0,
    )
    np.testing.assert_array_equal(plain.segments, faulty.segments)  # the masks never change


class _Hash:
    space = "test/hash"
    dim = 32

    def encode(self, texts):
        import zlib

        rows = [np.random.default_rng(zlib.crc32(t.encode())).normal(size=32) for t in texts]
        rows = np.array(rows).reshape(-1, 32)
        return (rows / np.linalg.norm(rows, axis=1, keepdims=True)).astype(np.float32)


def test_named_settings_meet_their_floor_and_specs_read_back():
    clip = stand_in("clip-like")
    assert clip["subpart_drift"] >= 0.6 and clip["part_drift"] >= 0.6
    assert clip["surroundings"] >= 0.1 and clip["confusion"] > 0 and clip["context_mix"] == 0
    assert stand_in("name-perfect") == dict.fromkeys(clip, 0.0)
    assert set(STAND_INS) == {"name-perfect", "clip-like"}
    grid = [stand_in(spec) for spec in CLIP_GRID]
    assert {(s["part_drift"], s["surroundings"]) for s in grid} == {
        (0.6, 0.1), (0.8, 0.1), (0.6, 0.3), (0.8, 0.3),
    }  # fmt: skip
    for spec in (*CLIP_GRID, "name-perfect", "name-perfect:context_mix=0.8"):
        config = OracleConfig(seed=3).with_stand_in(spec)
        assert stand_in_spec(config) == spec
        assert stand_in(stand_in_spec(config)) == config.stand_in
    config = OracleConfig().with_stand_in("clip-like:subpart_drift=0.7")
    assert (config.subpart_drift, config.part_drift) == (0.7, 0.6)
    assert stand_in_spec(config) == "clip-like:subpart_drift=0.7"


def test_every_confusable_name_is_a_catalog_name():
    rng = np.random.default_rng(0)
    names = set()
    for build in (*TABLE_OBJECTS.values(), *FLOOR_OBJECTS.values()):
        for _ in range(8):  # optional sub-parts (coffee) appear with some seeds
            model = build(rng)
            names.add(model.name)
            for part in model.parts:
                names.add(part.name)
                names.update(sub.name for sub in part.subparts)
    names.update({"table", "table top", "table leg", "table legs"})
    flat = [name for pair in CONFUSABLE_NAMES for name in pair]
    assert set(flat) <= names
    assert len(flat) == len(set(flat))  # one look-alike per name


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("clip", r"^stand-in: unknown 'clip' in 'clip'; choose from name-perfect, clip-like$"),
        ("clip-like:drift=0.8", r"'drift=0.8' in 'clip-like:drift=0.8' is not KEY=VALUE"),
        ("clip-like:surroundings", r"is not KEY=VALUE"),
        ("clip-like:surroundings=lots", r"^stand-in: surroundings in .* got 'lots'$"),
        ("clip-like:surroundings=1.5", r"surroundings=1.5': .*surroundings must be in \[0, 1\]"),
        ("clip-like:confusion=0.6", r"confusion must be in \[0, 0.5\], got 0.6"),
        ("clip-like:compression=1", r"compression must be in \[0, 1\), got 1.0"),
        ("clip-like:context_mix=0.5", r"context_mix is the older single knob"),
    ],
)
def test_bad_specs_are_refused(spec, message):
    with pytest.raises(InputError, match=message):
        stand_in(spec)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"subpart_drift": -0.1}, r"^OracleConfig\.subpart_drift: must be in \[0, 1\], got -0\.1$"),
        ({"part_drift": 1.2}, r"^OracleConfig\.part_drift: must be in \[0, 1\], got 1\.2$"),
        ({"surroundings": math.nan}, r"^OracleConfig\.surroundings: must be in \[0, 1\]"),
        ({"confusion": 0.7}, r"^OracleConfig\.confusion: must be in \[0, 0\.5\], got 0\.7$"),
        ({"compression": 1.0}, r"^OracleConfig\.compression: must be in \[0, 1\), got 1\.0$"),
        ({"context_mix": 0.5, "part_drift": 0.5}, r"^OracleConfig\.context_mix: is the older"),
    ],
)
def test_bad_settings_are_refused(settings, message):
    with pytest.raises(InputError, match=message):
        OracleConfig(**settings)


def test_a_view_without_masks_has_no_features():
    encoder = OneHot()
    empty = LevelMasks(np.full((4, 4), -1, dtype=np.int32), ())
    config = OracleConfig().with_stand_in("clip-like")
    assert mask_embeddings((), 0, (), encoder, config).shape == (0, encoder.dim)
    assert mask_contexts(empty, 0, np.full((3, 4, 4), -1), None, 3) == ()  # type: ignore[arg-type]


@pytest.mark.slow
def test_the_selection_benchmark_builds_the_field_thgs_synth_and_build_give(tmp_path):
    """benchmarks/bench_selection.py makes each stand-in's features again on the masks of one
    name-perfect dataset and reuses its lift and merging: the regions and features must be those
    of a dataset written with that stand-in and built from scratch."""
    import sys

    from thgs.pipeline import FieldConfig, build_field
    from thgs.scene import load_scene
    from thgs.synthetic import DatasetConfig, preset, write_dataset
    from thgs.text import MiniLMEncoder

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from bench_selection import Scene

    encoder, config = MiniLMEncoder(), FieldConfig.lerf()
    size = (3000, 4)
    scene = Scene(tmp_path / "bench", 2, "2dgs", 0.5, encoder, config, size)
    spec = "clip-like:parent_drift=0.8"
    regions = scene.regions(spec)
    again = scene.regions(spec)  # kept in the bench folder with its settings, read back
    np.testing.assert_array_equal(again.labels, regions.labels)
    oracle = OracleConfig(severity=0.5, seed=2).with_stand_in(spec)
    folder = tmp_path / "direct"
    synthetic = generate_scene(preset("synth-small", seed=2, gaussians=3000, views=4))
    write_dataset(folder, synthetic, encoder, oracle=oracle, config=DatasetConfig())
    from thgs.guidance import load_guidance

    loaded = load_scene(folder)
    guidance = load_guidance(folder / "language_features", loaded.cameras)
    field = build_field(loaded, guidance, config, space=encoder.space)
    np.testing.assert_array_equal(regions.labels, field.labels)
    for k in range(3):
        np.testing.assert_allclose(regions.features[k], field.features[k], atol=1e-6)
