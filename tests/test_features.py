"""Region features (design §4.7): a loop-by-loop reference, hand-computed cases, synthetic truth."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import thgs.features
from conftest import look_at, random_gaussians
from test_pipeline import oracle_views, plane_scene
from test_synthetic import _FakeEncoder
from thgs import Cameras, InputError
from thgs.features import FeatureConfig, centre_masks, level_features, region_features
from thgs.guidance import ViewGuidance
from thgs.lift import LiftConfig, ViewLift, lift_views
from thgs.render import project
from thgs.synthetic import OracleConfig

MODES = ["shares", "centres"]
HEIGHT, WIDTH = 6, 8


# --- the slow, obvious reference ---------------------------------------------------------------


def _unit(vector: np.ndarray) -> np.ndarray:
    return vector / np.linalg.norm(vector)


def median_direction(units, weights, steps, softness):
    """The weighted mean direction of unit vectors, then ``steps`` reweighted steps, each view
    weighing ``w / (‖u − m‖ + ε)`` with m the previous direction."""
    units, weights = np.asarray(units, float), np.asarray(weights, float)
    direction = _unit(weights @ units)
    for _ in range(steps):
        distances = np.linalg.norm(units - direction, axis=1)
        direction = _unit((weights / (distances + softness)) @ units)
    return direction


def reference_features(labels, level, lifted, guidance, config, regions, centres=None):
    """The formulas of docs/features.md, one region and one view at a time.

    ``centres[v][i]`` is the mask under Gaussian i's centre in view v (mode centres only).
    """
    dim = guidance[0].features.shape[1]
    out = np.zeros((regions, dim))
    for r in range(regions):
        units, weights = [], []
        members = [int(i) for i in np.flatnonzero(labels == r)]
        if not members:
            continue
        for v, (view, masks) in enumerate(zip(lifted, guidance)):
            row = {int(g): j for j, g in enumerate(view.gaussians)}
            seen = [i for i in members if i in row]
            features = masks.features.astype(np.float64)
            total = np.zeros(dim)
            if config.mode == "shares":
                counted = [i for i in seen if view.max_weights[row[i]] >= config.min_max_weight]
                power = config.visibility_power
                weigh = {i: float(view.max_weights[row[i]]) ** power for i in seen}
                marks = {i: int(view.labels[row[i], level]) for i in counted}
                marks = {i: m for i, m in marks.items() if m >= 0}
                labelled = sum(weigh[i] for i in marks)
                fit = kept = 0.0
                for mask in sorted(set(marks.values())):
                    inside = sum(weigh[i] for i, m in marks.items() if m == mask)
                    share = inside / labelled
                    if share >= config.min_share:
                        total += share * features[mask]
                        # the mask's counted weight over every Gaussian of the view
                        everywhere = sum(
                            float(w) ** power
                            for w, m in zip(view.max_weights, view.labels[:, level])
                            if m == mask and w >= config.min_max_weight
                        )
                        fit += share * inside / everywhere
                        kept += share
                visible = [i for i in counted if view.max_weights[row[i]] > config.visible_weight]
                weight = sum(weigh[i] for i in visible) / len(members)
                if kept > 0:
                    weight *= (fit / kept) ** config.fit_power
            else:
                used = [i for i in seen if view.max_weights[row[i]] > config.centre_weight]
                weight = len(used) / len(members)
                if not used or weight < config.min_visible:
                    continue
                for i in used:
                    if centres[v][i] >= 0:
                        total += float(view.max_weights[row[i]]) * features[centres[v][i]]
            if np.linalg.norm(total) > 0 and weight > 0:
                units.append(_unit(total))
                weights.append(weight)
        if units:
            out[r] = median_direction(units, weights, config.median_steps, config.median_softness)
    seen = np.linalg.norm(out, axis=1) > 0
    return out, seen


# --- random data ---------------------------------------------------------------------------------


@dataclasses.dataclass
class Case:
    labels: np.ndarray
    lifted: list[ViewLift]
    guidance: list[ViewGuidance]
    centres: list[np.ndarray]
    gaussians: object
    cameras: Cameras
    regions: int


def cameras_for(count: int) -> Cameras:
    return Cameras.from_lists(
        [np.eye(4)] * count,
        [np.eye(3)] * count,
        [WIDTH] * count,
        [HEIGHT] * count,
        [f"view_{i}" for i in range(count)],
    )


def random_case(seed: int, count: int = 240, regions: int = 9, views: int = 6, dim: int = 8):
    """Views that see random subsets; each region prefers one mask per view (so shares ≥ 0.3
    occur), view 1 has no masks and view 2 sees nothing; two extra regions have no Gaussians."""
    rng = np.random.default_rng(seed)
    labels = rng.integers(0, regions, count).astype(np.int32)
    labels[:regions] = np.arange(regions)
    lifted, guidance, centres = [], [], []
    for v in range(views):
        masks = 0 if v == 1 else int(rng.integers(4, 12))
        n = 0 if v == 2 else int(rng.integers(count // 3, count))
        seen = np.sort(rng.choice(count, size=n, replace=False)).astype(np.int32)
        columns = np.full((n, 4), -1, dtype=np.int16)
        table = np.full(count, -1)
        if masks:
            favourite = rng.integers(0, masks, (4, regions))
            for level in range(4):
                mark = np.where(
                    rng.random(n) < 0.6, favourite[level, labels[seen]], rng.integers(0, masks, n)
                )
                columns[:, level] = np.where(rng.random(n) < 0.2, -1, mark)
            table = np.where(
                rng.random(count) < 0.7, favourite[1, labels], rng.integers(-1, masks, count)
            )
        features = rng.normal(size=(masks, dim))
        features /= np.linalg.norm(features, axis=1, keepdims=True)
        segments = rng.integers(-1, max(masks, 1) if masks else 0, (4, HEIGHT, WIDTH))
        lifted.append(
            ViewLift(
                seen,
                columns,
                rng.uniform(0.5, 3, n).astype(np.float32),
                (10 ** rng.uniform(-6, 0, n)).astype(np.float32),
            )
        )
        guidance.append(
            ViewGuidance(f"view_{v}", segments.astype(np.int32), features.astype(np.float32))
        )
        centres.append(table)
    return Case(
        labels, lifted, guidance, centres, random_gaussians(count), cameras_for(views), regions + 2
    )


@pytest.fixture
def known_centres(monkeypatch):
    """Replace the projection step by a table: ``table[v][i]`` is Gaussian i's mask in view v."""

    def use(table):
        def lookup(means, camera, segments, indices):
            return table[int(camera.stems[0].split("_")[1])][indices]

        monkeypatch.setattr(thgs.features, "centre_masks", lookup)

    return use


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("level", [1, 3])
@pytest.mark.parametrize("authors", [False, True])
def test_matches_the_reference_on_random_views(seed, mode, level, authors, known_centres):
    """Ours (two median steps, visibility weights) and the authors' (the weighted mean)."""
    case = random_case(seed)
    config = FeatureConfig(mode=mode, min_visible=0.2)
    config = config.as_reference() if authors else config
    known_centres(case.centres)
    features, seen = region_features(
        case.labels,
        level,
        case.lifted,
        case.guidance,
        config,
        gaussians=case.gaussians,
        cameras=case.cameras,
        regions=case.regions,
    )
    expected, expected_seen = reference_features(
        case.labels, level, case.lifted, case.guidance, config, case.regions, case.centres
    )
    assert features.dtype == np.float32 and features.shape == (case.regions, 8)
    np.testing.assert_array_equal(seen, expected_seen)
    np.testing.assert_allclose(features, expected, atol=1e-6)
    assert 0 < seen.sum() <= case.regions - 2 and not seen[-2:].any()
    np.testing.assert_allclose(np.linalg.norm(features[seen], axis=1), 1.0, atol=1e-6)


@pytest.mark.parametrize("mode", MODES)
def test_several_levels_in_one_pass_and_within_a_subset(mode, known_centres):
    """level_features gives each level what region_features gives it alone; restricted to the
    Gaussians of some regions, those regions' features are unchanged and the others unseen."""
    case = random_case(5)
    known_centres(case.centres)
    config = FeatureConfig(mode=mode, min_visible=0.2)
    kwargs = {"gaussians": case.gaussians, "cameras": case.cameras}
    coarse = case.labels // 3
    columns = np.stack([case.labels, coarse, case.labels], axis=1)
    together = level_features(columns, (1, 2, 3), case.lifted, case.guidance, config, **kwargs)
    for (features, seen), level, labels in zip(together, (1, 2, 3), columns.T):
        alone = region_features(labels, level, case.lifted, case.guidance, config, **kwargs)
        np.testing.assert_array_equal(features, alone[0])
        np.testing.assert_array_equal(seen, alone[1])
    inside = np.isin(case.labels, [0, 4])
    (features, seen), *_ = level_features(
        case.labels[:, None], (2,), case.lifted, case.guidance, config, within=inside, **kwargs
    )
    full = region_features(case.labels, 2, case.lifted, case.guidance, config, **kwargs)
    np.testing.assert_array_equal(features[[0, 4]], full[0][[0, 4]])
    assert not seen[[1, 2, 3, 5, 6]].any() and seen[[0, 4]].all()


@pytest.mark.parametrize("mode", MODES)
def test_is_deterministic(mode, known_centres):
    case = random_case(7)
    known_centres(case.centres)
    config = FeatureConfig(mode=mode)
    kwargs = {"gaussians": case.gaussians, "cameras": case.cameras}
    first = region_features(case.labels, 2, case.lifted, case.guidance, config, **kwargs)
    second = region_features(case.labels, 2, case.lifted, case.guidance, config, **kwargs)
    np.testing.assert_array_equal(first[0], second[0])
    np.testing.assert_array_equal(first[1], second[1])


# --- known answers ---------------------------------------------------------------------------


def one_level_view(gaussians, marks, max_weights, level=1) -> ViewLift:
    """A ViewLift whose labels at ``level`` are ``marks`` (−1 elsewhere)."""
    n = len(gaussians)
    labels = np.full((n, 4), -1, dtype=np.int16)
    labels[:, level] = marks
    return ViewLift(
        np.asarray(gaussians, dtype=np.int32),
        labels,
        np.ones(n, dtype=np.float32),
        np.asarray(max_weights, dtype=np.float32),
    )


def guidance_with(features, stem="view_0") -> ViewGuidance:
    return ViewGuidance(
        stem, np.full((4, HEIGHT, WIDTH), -1, np.int32), np.asarray(features, np.float32)
    )


@pytest.mark.parametrize("mode", MODES)
def test_a_region_under_one_mask_takes_its_feature(mode, known_centres):
    # region 0 = Gaussians 0–9 lies under one mask in every view (a different row each time);
    # region 1 = 10–19 is seen under random masks; region 2 = 20–24 is in no view at all
    rng = np.random.default_rng(3)
    target = _unit(rng.normal(size=5))
    labels = np.repeat(np.arange(3, dtype=np.int32), [10, 10, 5])
    lifted, guidance, table = [], [], []
    for v, row in enumerate([0, 3, 1]):
        features = rng.normal(size=(4, 5))
        features[row] = target
        features /= np.linalg.norm(features, axis=1, keepdims=True)
        marks = np.concatenate([np.full(10, row), rng.integers(0, 4, 10)])
        weights = rng.uniform(0.02, 1.0, 20)
        lifted.append(one_level_view(np.arange(20), marks, weights))
        guidance.append(guidance_with(features, f"view_{v}"))
        table.append(np.concatenate([marks, np.full(5, -1)]))
    known_centres(table)
    features, seen = region_features(
        labels,
        1,
        lifted,
        guidance,
        FeatureConfig(mode=mode),
        gaussians=random_gaussians(25),
        cameras=cameras_for(3),
    )
    np.testing.assert_allclose(features[0], target, atol=1e-6)
    np.testing.assert_array_equal(seen, [True, True, False])
    np.testing.assert_array_equal(features[2], np.zeros(5))


def test_labelled_but_invisible_or_unlabelled_regions_stay_unseen():
    # region 0 is labelled but never visible (max w ≤ 1e-4): p = 0; region 1 is visible but
    # carries no label; region 2 spreads over four masks of 25 % each: every share is dropped
    labels = np.repeat(np.arange(3, dtype=np.int32), 4)
    marks = np.array([0, 0, 0, 0, -1, -1, -1, -1, 0, 1, 2, 3])
    weights = np.array([1e-5] * 4 + [0.5] * 8)
    view = one_level_view(np.arange(12), marks, weights)
    features, seen = region_features(labels, 1, [view], [guidance_with(np.eye(4))])
    assert not seen.any() and not features.any()


def test_two_masks_by_hand():
    # view 0 sees 8 of region 0's 10 Gaussians: 4 under mask a, 3 under b, 1 under c (shares
    # 0.5, 0.375, 0.125 → c dropped); 6 of them are visible: p = 0.6. View 1 sees all ten,
    # visible, under b: p = 1. f = 0.6 · (4a + 3b) / 5 + b = 0.48 a + 1.36 b, then normalized.
    a, b, c = np.eye(4)[:3]
    labels = np.array([0] * 10 + [1] * 2, dtype=np.int32)
    view0 = one_level_view(np.arange(8), [0, 0, 0, 0, 1, 1, 1, 2], [0.5] * 6 + [1e-5] * 2, level=2)
    view1 = one_level_view(np.arange(12), [0] * 10 + [-1] * 2, [0.9] * 12, level=2)
    guidance = [guidance_with([a, b, c]), guidance_with([b, a], "view_1")]
    reference = FeatureConfig().as_reference()
    features, seen = region_features(labels, 2, [view0, view1], guidance, reference)
    np.testing.assert_allclose(features[0], _unit(0.48 * a + 1.36 * b), atol=1e-6)
    np.testing.assert_array_equal(seen, [True, False])
    # a share of exactly min_share is kept; without the drop rule c would enter
    kept, _ = region_features(
        labels, 2, [view0], guidance[:1], dataclasses.replace(reference, min_share=0.125)
    )
    np.testing.assert_allclose(kept[0], _unit(4 * a + 3 * b + c), atol=1e-6)


def test_faintly_seen_gaussians_weigh_little_by_hand():
    # ours: a label counts where max w ≥ 0.05 and weighs (max w)². A region of 10 Gaussians,
    # one view: 6 seen well (max w 1.0) under mask a, 3 seen faintly (0.2) under mask b (an
    # occluder's), 1 at 0.01 under b (not counted). Shares: a 6 / 6.12, b 0.12 / 6.12 < 0.3
    # (dropped); p = 6.12 / 10. The reference keeps b at 4 / 10 of the labels.
    a, b = np.eye(3)[:2]
    labels = np.zeros(10, dtype=np.int32)
    view = one_level_view(np.arange(10), [0] * 6 + [1] * 4, [1.0] * 6 + [0.2] * 3 + [0.01])
    guidance = [guidance_with([a, b])]
    ours, _ = region_features(labels, 1, [view], guidance, FeatureConfig.lerf())
    np.testing.assert_allclose(ours[0], a, atol=1e-6)
    theirs, _ = region_features(labels, 1, [view], guidance, FeatureConfig.lerf().as_reference())
    np.testing.assert_allclose(theirs[0], _unit(0.6 * a + 0.4 * b), atol=1e-6)


def test_a_view_whose_mask_fits_the_region_weighs_more_by_hand():
    # a table: leg = Gaussians 0–3 (region 0), top = 4–11 (region 1), all seen well (max w 1).
    # View 0's mask a holds leg and top (a table's mask): leg's precision 4 / 12; view 1's
    # mask b holds the leg alone (precision 1) and mask c the top. Each view sees the whole leg
    # (p = 1), so the reference weighs them alike: f = normalize(a + b); ours (fit, no median
    # steps) f = normalize(a / 3 + b). The top keeps a in view 0 (precision 8 / 12) and c in
    # view 1 (precision 1): normalize(2/3 a + c).
    a, b, c = np.eye(3)
    labels = np.array([0] * 4 + [1] * 8, dtype=np.int32)
    view0 = one_level_view(np.arange(12), [0] * 12, [1.0] * 12, level=2)
    view1 = one_level_view(np.arange(12), [0] * 4 + [1] * 8, [1.0] * 12, level=2)
    guidance = [guidance_with([a]), guidance_with([b, c], "view_1")]
    ours = dataclasses.replace(FeatureConfig(), median_steps=0)
    features, seen = region_features(labels, 2, [view0, view1], guidance, ours)
    assert seen.all()
    np.testing.assert_allclose(features[0], _unit(a / 3 + b), atol=1e-6)
    np.testing.assert_allclose(features[1], _unit(2 / 3 * a + c), atol=1e-6)
    theirs, _ = region_features(labels, 2, [view0, view1], guidance, ours.as_reference())
    np.testing.assert_allclose(theirs[0], _unit(a + b), atol=1e-6)
    # q = 2 squares the leg's precision in view 0
    squared = dataclasses.replace(ours, fit_power=2.0)
    features, _ = region_features(labels, 2, [view0, view1], guidance, squared)
    np.testing.assert_allclose(features[0], _unit(a / 9 + b), atol=1e-6)


def smoothed_l1(direction, units, weights, softness):
    """Σ w ρ(‖u − m‖) with ρ(d) = d − ε ln(1 + d/ε): what the median steps minimise."""
    distances = np.linalg.norm(np.asarray(units) - direction, axis=1)
    return float(np.sum(weights * (distances - softness * np.log1p(distances / softness))))


def outlier_views(angles_deg, seen):
    """Region 0 (Gaussians 0–9) under one mask per view whose 2-D feature points at the given
    angle; view v sees ``seen[v]`` of the ten (its weight p = seen / 10 with power 0)."""
    lifted, guidance, units = [], [], []
    for v, (angle, count) in enumerate(zip(angles_deg, seen)):
        unit = np.array([np.cos(np.radians(angle)), np.sin(np.radians(angle)), 0.0])
        lifted.append(one_level_view(np.arange(count), [0] * count, [0.9] * count))
        guidance.append(guidance_with([unit], f"view_{v}"))
        units.append(unit)
    return np.zeros(10, dtype=np.int32), lifted, guidance, np.array(units)


def test_median_steps_find_the_brute_force_median_of_views_with_one_outlier():
    # four views agree on a name (angles −6° … 4°), one sees the region through an occluder
    # (90°) with as much weight as two of them: the mean leans towards it, the median does not
    angles, seen = [-6.0, -1.0, 2.0, 4.0, 90.0], [5, 5, 5, 5, 10]
    labels, lifted, guidance, units = outlier_views(angles, seen)
    weights = np.array(seen) / 10
    plain = FeatureConfig(min_max_weight=0.0, visibility_power=0.0, median_steps=0)
    softness = plain.median_softness

    def angle_of(config):
        features, seen_rows = region_features(labels, 1, lifted, guidance, config)
        assert seen_rows[0] and abs(features[0, 2]) < 1e-7
        return np.degrees(np.arctan2(features[0, 1], features[0, 0]))

    grid = np.radians(np.linspace(-90.0, 180.0, 270_001))
    candidates = np.stack([np.cos(grid), np.sin(grid), np.zeros_like(grid)], axis=1)
    distances = np.linalg.norm(candidates[:, None, :] - units[None], axis=2)
    losses = (distances - softness * np.log1p(distances / softness)) @ weights
    best = np.degrees(grid[np.argmin(losses)])
    mean = angle_of(plain)
    assert mean == pytest.approx(np.degrees(np.arctan2(*(weights @ units)[[1, 0]])), abs=1e-4)
    assert mean > 25  # the outlier's pull on the mean
    converged = angle_of(dataclasses.replace(plain, median_steps=200))
    assert converged == pytest.approx(best, abs=2e-3) and 0 < best < 5  # mean: over 25°
    # every step lowers the smoothed L1 distance (a majorize–minimize step) and two already
    # bring the direction within 6° of the agreeing views'
    previous = math.inf
    for steps in range(6):
        angle = np.radians(angle_of(dataclasses.replace(plain, median_steps=steps)))
        loss = smoothed_l1(np.array([np.cos(angle), np.sin(angle), 0]), units, weights, softness)
        assert loss <= previous + 1e-9
        previous = loss
    assert abs(angle_of(dataclasses.replace(plain, median_steps=2)) - best) < 6


def test_median_steps_leave_agreeing_views_alone():
    # every view gives the same direction: mean and median are that direction
    labels, lifted, guidance, _ = outlier_views([30.0, 30.0, 30.0], [3, 7, 10])
    for steps in (0, 2, 5):
        config = FeatureConfig(median_steps=steps)
        features, _ = region_features(labels, 1, lifted, guidance, config)
        np.testing.assert_allclose(
            features[0], [np.cos(np.pi / 6), np.sin(np.pi / 6), 0], atol=1e-6
        )


def front_camera(count: int = 1) -> Cameras:
    """Identity pose, unit focal length, no offset: world (x, y, 1) lands on pixel (x, y)."""
    return cameras_for(count)


def test_centres_by_hand():
    # region 0 (Gaussians 0–3) in view 0: three used (w 0.5 on a mask-0 pixel, 0.2 and 0.1 on
    # mask-1 pixels), one under centre_weight; portion 3/4. In view 1 all four sit on mask 2
    # with w 1: portion 1. The authors' f = 0.75 · normalize(0.5 a + 0.3 b) + c; ours takes
    # two median steps from there. Region 1 (4–13): one of ten used in view 0 (portion
    # 0.1 ≥ min_visible); region 2 (14–23): none used anywhere.
    a, b, c = np.eye(3)
    pixels = np.array([[0, 0], [1, 0], [2, 0], [3, 0]] + [[5, 5]] * 20) + 0.5
    means = np.concatenate([pixels, np.ones((24, 1))], axis=1)
    gaussians = dataclasses.replace(
        random_gaussians(24), means=torch.tensor(means, dtype=torch.float32)
    )
    segments = np.full((4, HEIGHT, WIDTH), -1, np.int32)
    segments[1, 0, 0] = 0
    segments[1, 0, 1:4] = 1
    segments[1, 5, 5] = 2
    weights0 = [0.5, 0.2, 0.1, 0.005] + [0.3] + [0.001] * 9 + [0.005] * 10
    view0 = one_level_view(np.arange(24), -1, weights0)
    view1 = one_level_view(np.arange(4), -1, [1.0] * 4)
    segments1 = np.full((4, HEIGHT, WIDTH), 2, np.int32)
    guidance = [
        ViewGuidance("view_0", segments, np.stack([a, b, c]).astype(np.float32)),
        ViewGuidance("view_1", segments1, np.stack([a, b, c]).astype(np.float32)),
    ]
    labels = np.repeat(np.arange(3, dtype=np.int32), [4, 10, 10])
    kwargs = {"gaussians": gaussians, "cameras": front_camera(2)}
    dovs = FeatureConfig.three_dovs()
    features, seen = region_features(labels, 1, [view0, view1], guidance, dovs, **kwargs)
    views = [_unit(0.5 * a + 0.3 * b), c]
    np.testing.assert_allclose(features[0], median_direction(views, [0.75, 1], 2, 0.1), atol=1e-6)
    np.testing.assert_allclose(features[1], c, atol=1e-6)
    np.testing.assert_array_equal(seen, [True, True, False])
    authors, _ = region_features(labels, 1, [view0, view1], guidance, dovs.as_reference(), **kwargs)
    np.testing.assert_allclose(authors[0], _unit(0.75 * views[0] + c), atol=1e-6)
    strict = FeatureConfig(mode="centres", min_visible=0.11)
    _, seen = region_features(
        labels, 1, [view0], guidance[:1], strict, gaussians=gaussians, cameras=front_camera()
    )
    np.testing.assert_array_equal(seen, [True, False, False])


def test_centre_masks_by_hand():
    segments = np.arange(HEIGHT * WIDTH).reshape(HEIGHT, WIDTH)
    segments[4, 2] = -1
    means = np.array(
        [
            [0.5, 0.5, 1.0],  # pixel (0, 0)
            [3.0, 2.0, 1.0],  # exactly on a corner: pixel (3, 2)
            [6.0, 4.0, 2.0],  # (3, 2) at depth 2
            [7.99, 5.99, 1.0],  # last pixel
            [8.0, 1.0, 1.0],  # right of the image
            [-0.01, 1.0, 1.0],  # left of it
            [1.0, 1.0, -1.0],  # behind the camera
            [1.0, 1.0, 0.0],  # in the camera plane
            [2.5, 4.5, 1.0],  # a pixel without a mask
        ]
    )
    masks = centre_masks(means, front_camera(), segments, np.arange(len(means)))
    np.testing.assert_array_equal(masks, [0, 19, 19, 47, -1, -1, -1, -1, -1])
    np.testing.assert_array_equal(
        centre_masks(means, front_camera(), segments, np.array([3, 0], dtype=np.int32)), [47, 0]
    )


def test_centre_masks_agree_with_the_projections():
    gaussians = random_gaussians(2000, seed=4)
    eye = np.array([7.0, 3.0, 4.0])
    camera = Cameras.from_lists(
        [look_at(eye, np.zeros(3))],
        [[[150.0, 0, 100], [0, 160, 70], [0, 0, 1]]],
        [200],
        [150],
        ["v"],
    )
    projection = project(gaussians, camera)
    centers = projection.centers.numpy()
    in_front = projection.depths.numpy() > 0.2
    inside = in_front & (centers >= 0).all(1) & (centers[:, 0] < 200) & (centers[:, 1] < 150)
    assert 100 < inside.sum() < len(gaussians)
    segments = np.arange(200 * 150).reshape(150, 200)
    means = gaussians.means.numpy()
    masks = centre_masks(means, camera, segments, np.flatnonzero(in_front))
    pixel = np.floor(centers[in_front]).astype(int)
    expected = np.where(inside[in_front], pixel[:, 1] * 200 + pixel[:, 0], -1)
    np.testing.assert_array_equal(masks, expected)
    # a skewed K, against Cameras.project (the rasterizer ignores skew)
    skewed = dataclasses.replace(camera, Ks=camera.Ks.clone())
    skewed.Ks[0, 0, 1] = 25.0
    pixels, depths = skewed.project(gaussians.means)
    x, y = pixels[0].numpy().T
    ok = (depths[0].numpy() > 0) & (x >= 0) & (x < 200) & (y >= 0) & (y < 150)
    expected = np.full(len(means), -1)
    expected[ok] = np.floor(y[ok]).astype(int) * 200 + np.floor(x[ok]).astype(int)
    everything = np.arange(len(means))
    np.testing.assert_array_equal(centre_masks(means, skewed, segments, everything), expected)


# --- synthetic ground truth --------------------------------------------------------------------


@pytest.fixture(scope="module")
def plane_lifted():
    scene, hierarchy = plane_scene()
    guidance = oracle_views(scene, hierarchy, OracleConfig(severity=0.0, feature_noise=0.0))
    lifted = lift_views(scene.gaussians, scene.cameras, guidance, LiftConfig())
    return scene, hierarchy, guidance, lifted


def plane_cosines(plane_lifted, guidance, mode, level):
    """Cosine of each ground-truth region's feature to its name's embedding, and all of them."""
    scene, hierarchy, _, lifted = plane_lifted
    features, seen = region_features(
        hierarchy.labels[:, level],
        level,
        lifted,
        guidance,
        FeatureConfig(mode=mode),
        gaussians=scene.gaussians,
        cameras=scene.cameras,
    )
    names = _FakeEncoder().encode(list(hierarchy.names[level]))
    assert seen.all() and features.shape == names.shape
    return np.sum(features * names, axis=1), features @ names.T


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("level", [1, 2, 3])
def test_plane_regions_take_their_names(plane_lifted, mode, level):
    # ground-truth regions, latent lifting of clean oracle masks with noise-free features: every
    # region's feature is its name's embedding (measured: cosine 1.0000 with shares, ≥ 0.99993
    # with centres, where a centre on a boundary pixel may take the neighbour's mask)
    cosines, table = plane_cosines(plane_lifted, plane_lifted[2], mode, level)
    assert (cosines > 0.99).all(), cosines
    assert (table - np.diag(cosines) < cosines[:, None] - 0.1).all()


@pytest.mark.parametrize("mode", MODES)
def test_plane_feature_noise_averages_out(plane_lifted, mode):
    # the oracle's default feature noise (0.5: cosine 1/√1.25 ≈ 0.89 per mask) over 8 views:
    # measured 0.979–0.995 at levels 1 and 2; the masks are the same at severity 0
    scene, hierarchy, clean, _ = plane_lifted
    noisy = oracle_views(scene, hierarchy, OracleConfig(severity=0.0))
    assert all(np.array_equal(a.segments, b.segments) for a, b in zip(clean, noisy))
    for level in (1, 2):
        cosines, table = plane_cosines(plane_lifted, noisy, mode, level)
        assert (cosines > 0.97).all(), cosines
        assert (table.argmax(axis=1) == np.arange(4)).all()


# --- configuration and bad input ----------------------------------------------------------------


def test_presets():
    assert FeatureConfig.lerf() == FeatureConfig()
    assert FeatureConfig.lerf().mode == "shares" and FeatureConfig.lerf().min_share == 0.3
    dovs = FeatureConfig.three_dovs()
    assert (dovs.mode, dovs.centre_weight, dovs.min_visible) == ("centres", 0.01, 0.1)
    authors = FeatureConfig.lerf().as_reference()
    assert (authors.min_max_weight, authors.visibility_power) == (0.0, 0.0)
    assert (FeatureConfig().fit_power, authors.fit_power) == (1.0, 0.0)
    assert (FeatureConfig().median_steps, authors.median_steps) == (2, 0)
    assert FeatureConfig.three_dovs().as_reference().median_steps == 0


@pytest.mark.parametrize(
    "fields",
    [
        {"mode": "mean"},
        {"min_share": 1.5},
        {"min_share": math.nan},
        {"min_visible": -0.1},
        {"visible_weight": 1.0},
        {"centre_weight": -1e-3},
        {"min_max_weight": 1.0},
        {"visibility_power": -1.0},
        {"visibility_power": math.nan},
        {"visibility_power": math.inf},
        {"fit_power": -0.5},
        {"fit_power": math.inf},
        {"median_steps": -1},
        {"median_steps": 1.5},
        {"median_steps": True},
        {"median_softness": 0.0},
        {"median_softness": math.nan},
    ],
)
def test_bad_config(fields):
    with pytest.raises(InputError, match="FeatureConfig"):
        FeatureConfig(**fields)


def test_bad_input_is_named(known_centres):
    case = random_case(0)
    labels, lifted, guidance = case.labels, case.lifted, case.guidance

    def call(labels=labels, level=1, lifted=lifted, guidance=guidance, **kwargs):
        return region_features(labels, level, lifted, guidance, **kwargs)

    with pytest.raises(InputError, match=r"labels.*\[N\]"):
        call(labels=labels[:, None])
    with pytest.raises(InputError, match=r"labels.*integer"):
        call(labels=labels.astype(np.float32))
    negative = labels.copy()
    negative[5] = -1
    with pytest.raises(InputError, match=r"labels.*≥ 0"):
        call(labels=negative)
    with pytest.raises(InputError, match=r"regions.*ids up to 8"):
        call(regions=8)
    for level in (0, 4, True):
        with pytest.raises(InputError, match=r"level.*1, 2 or 3"):
            call(level=level)
    with pytest.raises(InputError, match="6 lifted views for 5"):
        call(guidance=guidance[:5])
    with pytest.raises(InputError, match="no views"):
        call(lifted=[], guidance=[])
    with pytest.raises(InputError, match=r"lifted view 0.*outside \[0, 100\)"):
        call(labels=labels[:100])
    bad = list(lifted)
    bad[3] = dataclasses.replace(bad[3], labels=bad[3].labels.clone())
    bad[3].labels[0, 1] = len(guidance[3].features)
    with pytest.raises(InputError, match=r"lifted view 3.*view_3 has \d+ feature rows"):
        call(lifted=bad)
    wide = [
        *guidance[:4],
        dataclasses.replace(guidance[4], features=np.zeros((12, 9))),
        guidance[5],
    ]
    with pytest.raises(InputError, match="feature dimension"):
        call(guidance=wide)
    centres = FeatureConfig(mode="centres")
    with pytest.raises(InputError, match="gaussians and cameras"):
        call(config=centres, gaussians=case.gaussians)
    with pytest.raises(InputError, match="gaussians and cameras"):
        call(config=centres, cameras=case.cameras)
    with pytest.raises(InputError, match="239 Gaussians but 240 labels"):
        call(config=centres, gaussians=case.gaussians.select(np.arange(239)), cameras=case.cameras)
    with pytest.raises(InputError, match=r"view_0: masks are 4×3 but the camera is 8×6"):
        small = [dataclasses.replace(guidance[0], segments=guidance[0].segments[:, :3, :4])]
        call(
            guidance=small + guidance[1:],
            config=centres,
            gaussians=case.gaussians,
            cameras=case.cameras,
        )
    with pytest.raises(InputError, match="camera order"):
        call(
            config=centres,
            gaussians=case.gaussians,
            cameras=case.cameras.select([1, 0, 2, 3, 4, 5]),
        )
    outside = dataclasses.replace(guidance[0], segments=guidance[0].segments.copy())
    outside.segments[1, 0, 0] = len(outside.features)
    with pytest.raises(InputError, match=r"view_0.*feature rows"):
        call(
            guidance=[outside, *guidance[1:]],
            config=centres,
            gaussians=case.gaussians,
            cameras=case.cameras,
        )


@pytest.mark.slow
def test_a_folder_read_lazily_gives_the_same_features_reading_only_their_files(
    small_dataset, monkeypatch
):
    """The shares read each view's mask features alone from a lazily read folder (not its
    masks): the same features as from the views held in memory, at every level."""
    from thgs import load_scene
    from thgs.guidance import load_guidance
    from thgs.pipeline import lift_scene

    scene = load_scene(small_dataset)
    folder = small_dataset / "language_features"
    eager = load_guidance(folder, scene.cameras)
    lazy = load_guidance(folder, scene.cameras, lazy=True)
    lifted = lift_scene(scene, eager, LiftConfig()).lifted
    labels = np.stack([np.arange(len(scene.gaussians)) % k for k in (29, 11, 5)], axis=1)
    expected = level_features(labels, (1, 2, 3), lifted, eager)
    monkeypatch.setattr(type(lazy), "__getitem__", lambda *args: pytest.fail("the masks were read"))
    for (features, seen), (want, want_seen) in zip(
        level_features(labels, (1, 2, 3), lifted, lazy), expected, strict=True
    ):
        np.testing.assert_array_equal(features, want)
        np.testing.assert_array_equal(seen, want_seen)
        assert seen.all()
