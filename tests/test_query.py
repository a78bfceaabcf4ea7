"""Relevancy against a hand computation; the selection modes, caching and space checks on a
hand-built field."""

from __future__ import annotations

import logging
import math
from dataclasses import replace

import numpy as np
import pytest

from thgs.confidence import (
    NULL_PHRASES,
    PRESENCE_CALIBRATION,
    REGION_CALIBRATION,
    NullModel,
    presence_confidence,
    region_confidence,
)
from thgs.errors import InputError
from thgs.field import SemanticField
from thgs.hierarchy import RegionLevels
from thgs.query import (
    CANONICAL_PHRASES,
    FieldQuery,
    QueryConfig,
    Regions,
    default_threshold,
    relevancy,
    select,
    select_auto,
    select_paper,
    small_region_size,
    unselectable_reason,
)
from thgs.text import MINILM_SPACE, SpaceMismatchError


def _unit(*values: float) -> np.ndarray:
    v = np.array(values, dtype=np.float64)
    return v / np.linalg.norm(v)


def test_relevancy_hand_case():
    features = np.stack([_unit(1, 0, 0), _unit(0, 1, 0), _unit(1, 1, 0), np.zeros(3)])
    query = _unit(1, 0, 0)
    canonical = np.stack([_unit(0, 1, 0), _unit(0, 0, 1)])

    def lerf(phi_q: float, phi_c: float) -> float:
        return math.exp(10 * phi_q) / (math.exp(10 * phi_q) + math.exp(10 * phi_c))

    expected = [
        min(lerf(1, 0), lerf(1, 0)),
        min(lerf(0, 1), lerf(0, 0)),
        min(lerf(math.sqrt(0.5), math.sqrt(0.5)), lerf(math.sqrt(0.5), 0)),
        0.0,  # unseen: no feature, never relevant
    ]
    np.testing.assert_allclose(relevancy(features, query, canonical), expected, rtol=1e-12)
    both = relevancy(features, np.stack([query, _unit(0, 1, 0)]), canonical)
    assert both.shape == (2, 4)
    np.testing.assert_allclose(both[0], expected, rtol=1e-12)
    # large margins either way neither overflow nor warn
    np.testing.assert_array_equal(
        relevancy(features[:2], query, canonical, temperature=1e4), [1.0, 0.0]
    )


def test_relevancy_rejects_mismatched_dimensions():
    with pytest.raises(InputError, match="share D"):
        relevancy(np.zeros((2, 3)), np.zeros(4), np.zeros((1, 3)))
    with pytest.raises(InputError, match="canonical"):
        relevancy(np.zeros((2, 3)), np.zeros(3), np.zeros((0, 3)))


def _field() -> SemanticField:
    """8 Gaussians; objects {0–3} and {4–7}; parts {0, 1}, {2, 3}, {4, 5}, {6, 7}."""
    superpoint = np.arange(8)
    labels = np.stack([superpoint, superpoint // 2, superpoint // 2, superpoint // 4], axis=1)
    labels = labels.astype(np.int32)
    parents = (
        np.array([0, 0, 1, 1, 2, 2, 3, 3], np.int32),
        np.arange(4, dtype=np.int32),
        np.array([0, 0, 1, 1], np.int32),
    )
    parts = np.stack([_unit(1, 0, 0), _unit(1, 0.2, 0), _unit(0, 1, 0.1), np.zeros(3)])
    objects = np.stack([_unit(1, 0.1, 0), _unit(0, 1, 0)])
    features = (parts.astype(np.float32), parts.astype(np.float32), objects.astype(np.float32))
    seen = (np.array([1, 1, 1, 0], bool), np.array([1, 1, 1, 0], bool), np.ones(2, bool))
    levels = RegionLevels(labels, parents, (8, 4, 4, 2))
    return SemanticField(levels, features, seen, "test", "sha256:" + "0" * 64, {}, {}).check()


def test_paper_selection_pools_top_regions_of_levels_two_and_three():
    field = _field()
    canonical = np.stack([_unit(0, 0, 1)])
    query = _unit(1, 0, 0)
    scores = {(2, r): s for r, s in enumerate(relevancy(field.features[1], query, canonical))} | {
        (3, r): s for r, s in enumerate(relevancy(field.features[2], query, canonical))
    }
    # level 2 top 3: parts 0, 1, 2 (part 3 unseen); level 3: objects 0, 1; best 3 overall:
    expected = sorted(scores, key=lambda key: (-scores[key], key))[:3]
    selection = select_paper(field, query, canonical)
    assert [(level, region) for level, region, _ in selection.regions] == expected
    assert expected == [(2, 0), (3, 0), (2, 1)]
    np.testing.assert_array_equal(selection.gaussians, [1, 1, 1, 1, 0, 0, 0, 0])
    assert [s for _, _, s in selection.regions] == pytest.approx([scores[k] for k in expected])
    one = select_paper(field, query, canonical, levels=(3,), per_level=1, keep=1)
    assert one.regions[0][:2] == (3, 0)


def test_level_mode_takes_the_top_regions_of_one_level():
    scores = {2: np.array([0.2, 0.9, 0.0, 0.9, 0.5])}
    assert select(scores, QueryConfig(mode="level", level=2)) == ((2, 1, 0.9),)
    # ties go to the lower id; zero (unseen) regions are never chosen
    top = select(scores, QueryConfig(mode="level", level=2, top=10))
    assert [r for _, r, _ in top] == [1, 3, 4, 0]
    allowed = {2: np.array([True, False, True, True, True])}
    assert select(scores, QueryConfig(mode="level", level=2), allowed)[0][:2] == (2, 3)


def test_threshold_mode_selects_everything_relevant_or_nothing():
    scores = {3: np.array([0.95, 0.4, 0.85, 0.79])}
    chosen = select(scores, QueryConfig(mode="threshold", level=3, threshold=0.8))
    assert [(k, r) for k, r, _ in chosen] == [(3, 0), (3, 2)]
    assert select(scores, QueryConfig(mode="threshold", level=3, threshold=0.96)) == ()
    # without a configured threshold the caller's (the space's default) applies
    assert len(select(scores, QueryConfig(mode="threshold", level=3), threshold=0.3)) == 4


def test_paper_mode_always_selects_something():
    scores = {2: np.array([0.01, 0.02]), 3: np.array([0.03])}
    chosen = select(scores, QueryConfig(mode="paper"))
    assert [(k, r) for k, r, _ in chosen] == [(3, 0), (2, 1), (2, 0)]


@pytest.mark.parametrize(
    "changes",
    [
        {"mode": "best"},
        {"levels": (0, 3)},
        {"mode": "level", "level": 4},
        {"top": 0},
        {"threshold": 1.5},
        {"min_gaussians": -1},
        {"temperature": 0.0},
        {"descend": -0.1},
        {"siblings": 1.5},
        {"min_score": float("nan")},
        {"min_part_score": float("inf")},
        {"part_lead": -0.1},
        {"part_lead": float("nan")},
    ],
)
def test_invalid_query_configs_are_refused(changes):
    with pytest.raises(InputError, match="QueryConfig"):
        QueryConfig(**changes).check()


class _TableEncoder:
    """A text encoder over a fixed table of phrases; counts the phrases it encodes."""

    def __init__(self, space: str, table: dict[str, np.ndarray]):
        self.space, self.dim, self._table, self.encoded = space, 3, table, []

    def encode(self, texts):
        self.encoded += list(texts)
        return np.stack([self._table[t] for t in texts]).astype(np.float32).reshape(-1, 3)


def _encoder(space: str = "test") -> _TableEncoder:
    table = {phrase: _unit(0, 0, 1) for phrase in CANONICAL_PHRASES}
    table |= {"red": _unit(1, 0, 0), "green": _unit(0, 1, 0), "pinkish": _unit(1, 0.2, 0)}
    table |= {"nothing": _unit(0, 0, -1)}
    generic = np.random.default_rng(0).normal(size=(len(NULL_PHRASES), 3))
    table |= {phrase: _unit(*v) for phrase, v in zip(NULL_PHRASES, generic)}
    return _TableEncoder(space, table)


def test_field_query_batches_caches_and_matches_the_pure_functions():
    field, encoder = _field(), _encoder()
    fq = FieldQuery(field, encoder, QueryConfig(mode="paper"))
    canonical = encoder.encode(list(CANONICAL_PHRASES))
    np.testing.assert_allclose(
        fq.relevancy(["red", "green"], 2),
        relevancy(field.features[1], np.stack([_unit(1, 0, 0), _unit(0, 1, 0)]), canonical),
        rtol=1e-6,
    )
    red, green, red_again = fq.select(["red", "green", "red"])
    assert red is red_again
    expected = select_paper(field, _unit(1, 0, 0), canonical)
    assert [r[:2] for r in red.regions] == [r[:2] for r in expected.regions]
    assert [r[2] for r in red.regions] == pytest.approx([r[2] for r in expected.regions])
    np.testing.assert_array_equal(red.gaussians, expected.gaussians)
    assert red.text == "red" and not red.empty
    # green: object 1 and part 2 first, then part 1 (φ·q = 0.196) beats object 0 (0.0995)
    assert [r[:2] for r in green.regions] == [(3, 1), (2, 2), (2, 1)]
    np.testing.assert_array_equal(green.gaussians, [0, 0, 1, 1, 1, 1, 1, 1])
    encoder.encoded.clear()
    fq.select(["red"], fq.with_config(mode="level", level=2))
    assert encoder.encoded == []  # the embedding was cached
    level = fq.select(["pinkish"], fq.with_config(mode="level", level=2, top=2))[0]
    assert [r for _, r, _ in level.regions] == [1, 0]
    np.testing.assert_array_equal(level.gaussians, [1, 1, 1, 1, 0, 0, 0, 0])
    per_gaussian = fq.gaussian_relevancy("red", 3)
    np.testing.assert_allclose(per_gaussian, fq.relevancy(["red"], 3)[0][field.labels[:, 3]])
    summary = red.to_json(field)
    assert summary["gaussians"] == 4 and summary["regions"][0]["gaussians"] == 2


def test_one_engine_on_a_field_or_on_regions_that_need_not_nest():
    field = _field()
    on_field = FieldQuery(field, _encoder())
    regions = Regions.from_field(field)
    on_regions = FieldQuery(regions, _encoder())
    texts = ["red", "green", "pinkish"]
    np.testing.assert_array_equal(on_field.selected(texts), on_regions.selected(texts))
    # levels that do not nest: level 2 pairs Gaussians across the two objects
    labels = field.labels.copy()
    labels[:, 2] = np.array([0, 1, 2, 3, 0, 1, 2, 3])
    crossed_levels = RegionLevels.from_labels(labels, nested=False)
    crossed = FieldQuery(Regions(crossed_levels, field.features, field.seen, "test"), _encoder())
    masks = crossed.selected(texts)
    for q, text in enumerate(texts):  # brute force: the union of the chosen regions' members
        chosen = crossed.select([text])[0].regions
        expected = np.zeros(8, bool)
        for level, region, _ in chosen:
            expected |= labels[:, level] == region
        np.testing.assert_array_equal(masks[:, q], expected)
    scores = crossed.gaussian_relevancies(texts, 2)
    np.testing.assert_allclose(scores, crossed.relevancy(texts, 2).T[labels[:, 2]])
    # classify: the nearest text by cosine per Gaussian's region, −1 where unseen
    np.testing.assert_array_equal(crossed.classify(["red", "green"], 2), [0, 0, 1, -1] * 2)
    with pytest.raises(InputError, match=r"level must be in 1\.\.3 here, got 0"):
        crossed.classify(["red"], 0)
    with pytest.raises(InputError, match=r"level 2 has regions 0\.\.3, got region 4"):
        crossed.gaussians_of([(2, 4)])


def test_threshold_mode_returns_nothing_for_an_irrelevant_text():
    field = _field()
    encoder = _encoder()
    encoder._table["blue"] = _unit(-1, -1, 1)  # less like any region than the canonical phrase
    fq = FieldQuery(field, encoder, QueryConfig(mode="threshold", level=3, threshold=0.5))
    assert fq.select(["blue"])[0].empty
    assert not fq.select(["blue"])[0].gaussians.any()
    assert fq.select(["green"])[0].regions[0][:2] == (3, 1)


def test_small_regions_can_be_excluded():
    field = _field()
    paper = QueryConfig(mode="paper")
    fq = FieldQuery(field, _encoder(), paper)
    # every level-2 region has 2 Gaussians, level-3 regions 4
    chosen = fq.select(["red"], fq.with_config(min_gaussians=3))[0]
    assert {level for level, _, _ in chosen.regions} == {3}
    assert fq.min_gaussians == 0  # the field does not say
    # by default the field's own small-region size (thres_merge) applies
    small = replace(field, config={"merge": {"min_region_gaussians": 3}})
    fq = FieldQuery(small, _encoder(), paper)
    assert fq.min_gaussians == 3
    assert {level for level, _, _ in fq.select(["red"])[0].regions} == {3}
    everything = fq.select(["red"], fq.with_config(min_gaussians=0))[0]
    assert {level for level, _, _ in everything.regions} == {2, 3}


def test_queries_in_another_space_are_refused():
    with pytest.raises(SpaceMismatchError, match=r"'test'.*'other'"):
        FieldQuery(_field(), _encoder("other"))
    with pytest.raises(InputError, match="non-empty"):
        FieldQuery(_field(), _encoder()).select([" "])
    with pytest.raises(InputError, match="list of texts"):
        FieldQuery(_field(), _encoder()).select("red")


def test_queries_of_another_dimension_are_refused():
    encoder = _encoder()
    encoder.dim = 5
    with pytest.raises(SpaceMismatchError, match=r"^f\.thgs: features are 3-D but the text model "):
        FieldQuery(_field(), encoder, source="f.thgs")


def _unseen(field: SemanticField) -> SemanticField:
    """``field`` as if no view's masks had covered it: every feature zero, nothing seen."""
    return replace(
        field,
        features=tuple(np.zeros_like(f) for f in field.features),
        seen=tuple(np.zeros_like(s) for s in field.seen),
    ).check()


@pytest.mark.parametrize("mode", ["auto", "paper", "level", "threshold"])
def test_a_field_without_features_says_why_nothing_is_selected(mode):
    fq = FieldQuery(_unseen(_field()), _encoder(), QueryConfig(mode=mode))
    selection = fq.select(["red"])[0]
    assert selection.empty and not selection.gaussians.any()
    assert selection.reason is not None
    assert selection.reason.startswith("no region of level(s) ")
    assert "no view's masks covered them" in selection.reason
    # every seen region too small to be selected: that is said instead
    small = FieldQuery(_field(), _encoder(), QueryConfig(mode=mode, min_gaussians=5))
    assert "lower --min-gaussians" in small.select(["red"])[0].reason
    plain = QueryConfig(
        mode=mode,
        threshold=0.5 if mode == "threshold" else None,
        min_relevancy=0.5 if mode == "auto" else None,
    )
    assert FieldQuery(_field(), _encoder(), plain).select(["red"])[0].reason is None


def test_unselectable_reason_by_hand():
    seen = {2: np.array([True, False]), 3: np.array([False])}
    assert unselectable_reason(seen, {2: np.array([True, True]), 3: np.array([True])}) is None
    too_small = unselectable_reason(seen, {2: np.array([False, True]), 3: np.array([True])})
    assert too_small is not None and too_small.startswith("every region of level(s) 2, 3")
    nothing = {2: np.zeros(2, bool), 3: np.zeros(1, bool)}
    assert unselectable_reason(nothing, {2: np.ones(2, bool), 3: np.ones(1, bool)}).startswith(
        "no region of level(s) 2, 3 has a feature"
    )


def test_default_thresholds():
    assert default_threshold(MINILM_SPACE) == 0.8
    assert default_threshold("laion/CLIP-ViT-B-16-laion2B-s34B-b88K") == 0.5


def test_small_region_size_reads_the_recorded_merge_settings(caplog):
    field = _field()
    assert small_region_size(field) == 0  # no merge settings recorded
    recorded = replace(field, config={"merge": {"min_region_gaussians": 7}})
    assert small_region_size(recorded) == 7
    assert FieldQuery(recorded, _encoder()).min_gaussians == 7
    unreadable = replace(field, config={"merge": {"min_region_gaussians": "7"}})
    with caplog.at_level(logging.WARNING, logger="thgs.query"):
        assert small_region_size(unreadable) == 0
    assert "field config: merge" in caplog.text and "min_region_gaussians" in caplog.text


def test_the_flat_auto_rule_takes_every_region_named_like_the_query_or_abstains():
    field, encoder = _field(), _encoder()
    assert QueryConfig().mode == "auto" and QueryConfig().searched_levels == (1, 2, 3)
    # the rule before the hierarchy: raw cosines, every region past the cut, relevancy 0.8
    flat = QueryConfig(hierarchical=False, centred=False, min_relevancy=0.8)
    fq = FieldQuery(field, encoder, flat)
    # cosines with "red": levels 1 and 2 [1, 0.981, 0, unseen], level 3 [0.995, 0]; the median
    # of the 8 seen regions is 0.981, so the cut is 1 − 0.15 · (1 − 0.981) ≈ 0.997
    red = fq.select(["red"])[0]
    assert [r[:2] for r in red.regions] == [(1, 0), (2, 0)] and red.reason is None
    np.testing.assert_array_equal(red.gaussians, [1, 1, 0, 0, 0, 0, 0, 0])
    for extent in (0.15, 0.5, 0.9, 0.99):  # against the rule written out
        cos = {k: field.features[k - 1] @ _unit(1, 0, 0) for k in (1, 2, 3)}
        seen = [(k, r) for k in (1, 2, 3) for r in np.flatnonzero(field.seen[k - 1])]
        values = np.array([cos[k][r] for k, r in seen])
        cut = values.max() - extent * (values.max() - np.median(values))
        expected = {(k, int(r)) for (k, r), v in zip(seen, values) if v >= cut}
        chosen = fq.select(["red"], fq.with_config(extent=extent))[0]
        assert {r[:2] for r in chosen.regions} == expected
        assert [r[2] for r in chosen.regions] == pytest.approx(
            [fq.relevancy(["red"], k)[0][r] for k, r, _ in chosen.regions]
        )
    # an object named like the query at a coarser level than its parts: "green" is object 1
    # (cosine 1) and its part 2 (0.995)
    green = fq.select(["green"])[0]
    assert [r[:2] for r in green.regions] == [(3, 1), (1, 2), (2, 2)]
    # nothing reaches the relevancy the best region needs: abstain, saying why
    strict = fq.with_config(min_relevancy=0.9)
    nothing = fq.select(["nothing"], strict)[0]
    assert nothing.empty and not nothing.gaussians.any()
    assert nothing.reason.startswith("nothing relevant to 'nothing': the best region scores 0.500")
    assert nothing.to_json(field)["reason"] == nothing.reason
    assert "reason" not in red.to_json(field)
    with pytest.raises(InputError, match="auto mode needs"):
        select({1: np.ones(2)}, QueryConfig(levels=(1,)))
    with pytest.raises(InputError, match=r"extent"):
        QueryConfig(extent=1.0).check()


def _tree():
    """Objects 0 (parts 0, 1), 1 (part 2), 2 (part 3), 3 (part 4); part 0 holds sub-parts 0 and
    1, part 1 sub-part 2, parts 2–4 sub-parts 3–5: ``parents`` as RegionLevels gives them."""
    return (np.array([0, 0, 1, 2, 3, 4]), np.array([0, 0, 1, 2, 3]))


def _cosines(sub, part, obj):
    """Level → cosines; the regions of objects 1–3 are background (cosine 0)."""
    return {
        1: np.array([*sub, 0.0, 0.0, 0.0]),
        2: np.array([*part, 0, 0, 0]),
        3: np.array([obj, 0, 0, 0]),
    }


def _auto(cosines, **options):
    every = {k: np.arange(len(c)) for k, c in cosines.items()}
    scores = {k: np.full(len(c), 0.9) for k, c in cosines.items()}
    choice = select_auto(scores, cosines, every, 0.15, 0.5, parents=_tree(), **options)
    return [r[:2] for r in choice.regions]


def test_the_hierarchical_rule_by_hand():
    # 15 regions, 9 of them background at 0: the median is 0, the spread the best cosine, the
    # cut best − 0.15 · best, the margin 0.05 · best
    # a part named by the query: object 0 (0.6) is short of the cut (0.782) and part 0's
    # sub-part 0 rises 0.32 above it; part 1 rises nothing (best 0.5): left out. Part 0 (0.9)
    # is past the cut and sub-part 0 rises only 0.02 above it (margin 0.046): part 0 whole
    named_part = _cosines((0.92, 0.88, 0.5), (0.9, 0.5), 0.6)
    assert _auto(named_part) == [(2, 0)]
    # the flat rule takes part 0 and both its sub-parts (the same Gaussians) and nothing else
    flat = select_auto(
        {k: np.full(len(c), 0.9) for k, c in named_part.items()},
        named_part,
        {k: np.arange(len(c)) for k, c in named_part.items()},
    )
    assert [r[:2] for r in flat.regions] == [(1, 0), (2, 0), (1, 1)]
    # the object named: past the cut, nothing inside rises above it: the object whole
    assert _auto(_cosines((0.8, 0.8, 0.85), (0.9, 0.85), 0.95)) == [(3, 0)]
    # the object is past the cut (0.85 ≥ 0.8075) but part 0 rises 0.1 above it (margin 0.0475):
    # the query is about part 0; part 1 (0.84, below the object) is not followed
    about_part = _cosines((0.9, 0.9, 0.84), (0.95, 0.84), 0.85)
    assert _auto(about_part) == [(2, 0)]
    # two parts both rise well above their object (0.4 and 0.35 ≥ 0.6 · 0.4): both followed,
    # both past the cut (0.765): both taken
    assert _auto(_cosines((0.85, 0.85, 0.8), (0.9, 0.85), 0.5)) == [(2, 0), (2, 1)]
    # ... but with siblings 0.9 only the best (0.35 < 0.9 · 0.4)
    assert _auto(_cosines((0.85, 0.85, 0.8), (0.9, 0.85), 0.5), siblings=0.9) == [(2, 0)]
    # a region that may not be chosen (unseen, small) is passed through: part 0 out, its
    # sub-parts judged on their own
    every = {1: np.arange(6), 2: np.array([1, 2, 3, 4]), 3: np.arange(4)}
    cosines = _cosines((0.92, 0.88, 0.5), (0.9, 0.5), 0.6)
    scores = {k: np.full(len(c), 0.9) for k, c in cosines.items()}
    choice = select_auto(scores, cosines, every, 0.15, 0.5, parents=_tree())
    assert [r[:2] for r in choice.regions] == [(1, 0), (1, 1)]


def test_a_nested_field_is_searched_by_the_hierarchy():
    field, encoder = _field(), _encoder()
    # "pinkish" (1, 0.2, 0): part 1 (features (1, 0.2, 0)) is the query itself (cosine 1),
    # object 0 (1, 0.1, 0) is close (0.9955), part 0 (1, 0, 0) less (0.981); the median of the
    # 8 seen regions is 0.981, so with extent 0.9 the cut is 0.983: the flat rule takes part 1
    # and object 0 (Gaussians 0-3); the hierarchical one sees part 1 rise 0.0045 above object 0
    # (margin 0.05 · 0.019) and takes part 1 alone (Gaussians 2, 3)
    raw = QueryConfig(centred=False, min_relevancy=0.5, extent=0.9)
    hierarchical = FieldQuery(field, encoder, raw).select(["pinkish"])[0]
    flat = FieldQuery(field, encoder, replace(raw, hierarchical=False)).select(["pinkish"])[0]
    np.testing.assert_array_equal(flat.gaussians, [1, 1, 1, 1, 0, 0, 0, 0])
    assert [r[:2] for r in hierarchical.regions] == [(2, 1)]  # its sub-part is the same
    np.testing.assert_array_equal(hierarchical.gaussians, [0, 0, 1, 1, 0, 0, 0, 0])


def test_centred_cosines_by_hand():
    field, encoder = _field(), _encoder()
    fq = FieldQuery(field, encoder, QueryConfig(min_gaussians=0))
    seen = np.concatenate([f[s] for f, s in zip(field.features, field.seen)]).astype(np.float64)
    centre = seen.mean(axis=0)
    for level in (1, 2, 3):
        moved = field.features[level - 1].astype(np.float64) - centre
        unit = moved / np.linalg.norm(moved, axis=1, keepdims=True)
        expected = np.where(field.seen[level - 1], unit @ _unit(1, 0, 0), 0.0)
        np.testing.assert_allclose(fq.centred_similarity(["red"], level)[0], expected)
    # a direction every feature shares is gone: features pulled towards one direction (as CLIP's
    # image embeddings are) and renormalized read almost as before, while raw cosines shrink
    shared = _unit(0.3, -0.2, 1)
    pulled = tuple(
        np.where(s[:, None], (0.3 * f + 0.7 * shared), 0).astype(np.float32)
        for f, s in zip(field.features, field.seen)
    )
    pulled = tuple(
        np.where(s[:, None], f / np.maximum(np.linalg.norm(f, axis=1, keepdims=True), 1e-12), 0)
        for f, s in zip(pulled, field.seen)
    )
    moved = FieldQuery(
        replace(field, features=pulled).check(), encoder, QueryConfig(min_gaussians=0)
    )
    for level in (1, 2, 3):
        before = fq.centred_similarity(["red"], level)[0]
        after = moved.centred_similarity(["red"], level)[0]
        raw = moved.similarity(["red"], level)[0]
        assert np.corrcoef(before, after)[0, 1] > 0.99
        seen = field.seen[level - 1]
        assert np.ptp(raw[seen]) < 0.5 * np.ptp(fq.similarity(["red"], level)[0][seen])


def test_auto_abstains_below_the_scene_null():
    field, encoder = _field(), _encoder()
    fq = FieldQuery(field, encoder, QueryConfig(min_gaussians=0))
    null = fq.null_model(centred=True)
    best = max(float(fq.centred_similarity(["red"], k)[0].max()) for k in (1, 2, 3))
    score = float(null.score(best))
    below, above = (
        fq.with_config(min_score=score + change, min_part_score=score + change)
        for change in (-0.01, 0.01)
    )
    kept = fq.select(["red"], below)[0]
    assert not kept.empty and kept.reason is None
    dropped = fq.select(["red"], above)[0]
    assert dropped.empty and not dropped.gaussians.any()
    assert dropped.reason == (
        f"nothing relevant to 'red': the best region is {score:.2f} standard deviations above "
        f"what ordinary names reach in this scene, below the {score + 0.01:.2f} needed"
    )
    # a minimum relevancy given: the relevancy decides instead
    relevant = fq.select(["red"], replace(above, min_relevancy=0.5))[0]
    assert not relevant.empty


def test_a_part_that_stands_out_from_its_parent_needs_a_lower_score():
    # sub-parts 0, 1 in part 0; parts 0, 1 in object 0; the null: mean 0, spread 0.1, so a
    # cosine c scores 10 c, and the part lead 0.5 is a cosine 0.05 above the parent's
    parents = (np.array([0, 0]), np.array([0, 0]))
    null = NullModel(0.0, 0.1)
    everything = {1: np.array([0, 1]), 2: np.array([0, 1]), 3: np.array([0])}

    def choose(cosines, candidates=everything, **settings):
        scores = {k: np.full(len(c), 0.9) for k, c in cosines.items()}
        return select_auto(scores, cosines, candidates, parents=parents, null=null, **settings)

    specific = {1: np.array([0.12, 0.0]), 2: np.array([0.05, 0.0]), 3: np.array([0.04])}
    diffuse = {1: np.array([0.12, 0.0]), 2: np.array([0.1, 0.0]), 3: np.array([0.1])}
    # the sub-part scores 1.2: above its part by 0.07 it needs min(1.3, 1.05); by 0.02, 1.3
    chosen = choose(specific)
    assert (chosen.best_score, chosen.needed_score) == (pytest.approx(1.2), 1.05)
    assert [r[:2] for r in chosen.regions] == [(1, 0)]
    abstained = choose(diffuse)
    assert abstained.regions == () and abstained.needed_score == 1.3
    # a part lead of 0.8 (0.08) is more than the sub-part's 0.07
    assert choose(specific, part_lead=0.8).needed_score == 1.3
    # a parent that is no candidate cannot be stood out from
    alone = {1: np.array([0, 1]), 2: np.array([1]), 3: np.array([0])}
    assert choose(specific, alone).needed_score == 1.3
    # min_score below min_part_score: min_score is enough for every region
    assert choose(specific, min_score=0.5).needed_score == 0.5
    # an object has no parent: a best object needs min_score
    whole = {1: np.array([0.0, 0.0]), 2: np.array([0.0, 0.0]), 3: np.array([0.12])}
    assert choose(whole).needed_score == 1.3 and choose(whole).regions == ()
    # without the hierarchy (the flat rule) nothing has a parent
    flat = select_auto(
        {k: np.full(len(c), 0.9) for k, c in specific.items()}, specific, everything, null=null
    )
    assert flat.needed_score == 1.3 and flat.regions == ()


def test_select_auto_by_hand():
    # cosines 0.9, 0.85 (level 1), 0.2, 0.1 (level 3): median 0.525, lead 0.375, cut 0.84375
    scores = {1: np.array([0.99, 0.98]), 3: np.array([0.7, 0.6])}
    cosines = {1: np.array([0.9, 0.85]), 3: np.array([0.2, 0.1])}
    everything = {1: np.array([0, 1]), 3: np.array([0, 1])}
    choice = select_auto(scores, cosines, everything, extent=0.15, threshold=0.8)
    assert choice.regions == ((1, 0, 0.99), (1, 1, 0.98)) and choice.best_relevancy == 0.99
    # without region 1 of level 1 the median drops to 0.2: cut 0.795, region 0 alone
    fewer = {1: np.array([0]), 3: np.array([0, 1])}
    assert select_auto(scores, cosines, fewer, 0.15, 0.8).regions == ((1, 0, 0.99),)
    # the best relevancy below the threshold: abstain
    assert select_auto(scores, cosines, everything, 0.15, 0.995).regions == ()
    assert select_auto(scores, cosines, {1: np.array([], int)}, 0.15, 0.5).best_relevancy == 0.0


def test_null_model_hand_case():
    cosines = np.array([[0.1, 0.5, -0.2], [0.3, 0.2, 0.0], [0.9, 0.1, 0.4]])  # [P=3, C=3]
    null = NullModel.from_similarities(cosines)
    best = np.array([0.5, 0.3, 0.9])
    assert null.mean == pytest.approx(best.mean()) and null.std == pytest.approx(best.std())
    np.testing.assert_allclose(null.score([0.7, best.mean()]), [(0.7 - 17 / 30) / best.std(), 0])
    for bad in (np.zeros((1, 3)), np.zeros((3, 0)), np.zeros(3), np.ones((3, 2))):
        with pytest.raises(InputError, match="null phrases"):
            NullModel.from_similarities(bad)


def test_confidences_are_the_stated_logistic_curves():
    z = np.array([-2.0, 0.0, 1.5, 4.0])
    for curve, (slope, offset) in (
        (region_confidence, REGION_CALIBRATION),
        (presence_confidence, PRESENCE_CALIBRATION),
    ):
        np.testing.assert_allclose(curve(z), 1 / (1 + np.exp(-(slope * z + offset))))
        assert slope > 0 and np.all(np.diff(curve(z)) > 0)


def test_confidence_matches_a_brute_force_computation():
    field, encoder = _field(), _encoder()
    fq = FieldQuery(field, encoder, QueryConfig(min_gaussians=0))
    # the null by hand: every seen region of levels 1-3, its feature centred on their mean and
    # made unit again, each generic phrase's best cosine
    generic = encoder.encode(list(NULL_PHRASES)).astype(np.float64)
    seen = [field.features[k][field.seen[k]].astype(np.float64) for k in range(3)]
    centre = np.concatenate(seen).mean(axis=0)

    def centred(features):
        moved = features.astype(np.float64) - centre
        return moved / np.linalg.norm(moved, axis=1, keepdims=True)

    seen = [centred(features) for features in seen]
    best = np.max(generic @ np.concatenate(seen).T, axis=1)
    null = fq.null_model()
    assert null.mean == pytest.approx(best.mean()) and null.std == pytest.approx(best.std())
    raw = np.max(generic @ np.concatenate([f[s] for f, s in zip(field.features, field.seen)]).T, 1)
    assert fq.null_model(centred=False).mean == pytest.approx(raw.mean())
    for text, vector in (("red", _unit(1, 0, 0)), ("nothing", _unit(0, 0, -1))):
        for level in (1, 2, 3):
            cosine = centred(field.features[level - 1]) @ vector
            expected = np.where(
                field.seen[level - 1], region_confidence((cosine - best.mean()) / best.std()), 0
            )
            np.testing.assert_allclose(fq.confidence([text], level)[0], expected, rtol=1e-6)
        top = max(float((features @ vector).max()) for features in seen)
        expected_presence = presence_confidence((top - best.mean()) / best.std())
        selection = fq.select([text])[0]
        assert selection.confidence == pytest.approx(float(expected_presence))
        summary = selection.to_json(field)
        assert summary["confidence"] == selection.confidence
        assert [r["confidence"] for r in summary["regions"]] == list(selection.region_confidence)
    assert fq.presence(["red"])[0] > fq.presence(["nothing"])[0]
    # small regions are out of the null and of presence, as they are out of every selection
    assert fq.null_model(min_gaussians=100) is None
    assert np.isnan(fq.presence(["red"], min_gaussians=100)[0])
    unknown = fq.select(["red"], QueryConfig(min_gaussians=100))[0]
    assert unknown.confidence is None and unknown.region_confidence is None
    # generic phrases that all match equally well give no null either: no confidence, no error
    flat = _encoder()
    flat._table |= {phrase: _unit(0, 0, 1) for phrase in NULL_PHRASES}
    assert FieldQuery(field, flat).null_model() is None
    assert FieldQuery(field, flat).select(["red"])[0].confidence is None
    # the paper's pure rule does not compute confidences, and says so by omitting them
    canonical = encoder.encode(list(CANONICAL_PHRASES))
    paper = select_paper(field, _unit(1, 0, 0), canonical)
    assert paper.confidence is None and "confidence" not in paper.to_json(field)
    assert all("confidence" not in r for r in paper.to_json(field)["regions"])


@pytest.mark.parametrize(
    ("config", "message"),
    [
        (
            QueryConfig(threshold=0.5),
            "QueryConfig.threshold: only the threshold mode reads it, not the auto",
        ),
        (
            QueryConfig(mode="level", threshold=0.5),
            "QueryConfig.threshold: only the threshold mode reads it, not the level",
        ),
        (
            QueryConfig(mode="threshold", min_relevancy=0.5),
            "QueryConfig.min_relevancy: only the auto mode",
        ),
        (QueryConfig(min_relevancy=1.5), "QueryConfig.min_relevancy: must be in [0, 1], got 1.5"),
    ],
)
def test_each_relevancy_cut_belongs_to_one_mode(config, message):
    """The threshold mode's cut and the auto mode's minimum relevancy are two settings: one
    given to the other mode is refused, not ignored."""
    with pytest.raises(InputError) as caught:
        config.check()
    assert str(caught.value).startswith(message)
