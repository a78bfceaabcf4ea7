"""The protocols run on a scene: two opaque patches ("mug" left, "bear" right) in front of one
camera, so every predicted mask and ground truth is known pixel for pixel."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from thgs.confidence import NULL_PHRASES
from thgs.errors import InputError
from thgs.eval import (
    FrameLabels,
    LabelledObject,
    PointLabels,
    SegmentationSet,
    mask_to_polygons,
)
from thgs.eval.evaluate import (
    evaluate_3dovs,
    evaluate_hierarchy,
    evaluate_lerf,
    evaluate_lerf_langsplat,
    evaluate_lerf_opengaussian,
    evaluate_scannet,
    frame_mean,
)
from thgs.eval.ground_truth import Hierarchy
from thgs.eval.rules import langsplat_level, langsplat_localized, langsplat_mask
from thgs.hierarchy import RegionLevels
from thgs.query import CANONICAL_PHRASES, FieldQuery, QueryConfig, Regions
from thgs.scene import Cameras, Gaussians
from thgs.views import relevancy_map, selection_masks

WIDTH, HEIGHT = 160, 120
SPACE = "test-space"


def _unit(*values: float) -> np.ndarray:
    vector = np.asarray(values, dtype=np.float64)
    return vector / np.linalg.norm(vector)


class _TableEncoder:
    """Text → a fixed unit vector; unknown phrases raise KeyError (so a test sees which texts
    were asked)."""

    space, dim = SPACE, 4

    def __init__(self):
        self.table = {phrase: _unit(0, 0, 0, 1) for phrase in CANONICAL_PHRASES}
        self.table |= {
            "mug": _unit(1, 0, 0, 0),
            "bear": _unit(0, 1, 0, 0),
            "wood": _unit(0, 0, 1, 0),
        }
        generic = np.random.default_rng(0).normal(size=(len(NULL_PHRASES), 4))
        self.table |= {phrase: _unit(*v) for phrase, v in zip(NULL_PHRASES, generic)}

    def encode(self, texts):
        return np.stack([self.table[t] for t in texts]).astype(np.float32).reshape(-1, 4)


def _scene() -> tuple[Gaussians, Cameras]:
    """Two 6×6 grids of opaque, camera-facing surfels at depth 5 centred at x = −0.7 ("mug",
    Gaussians 0–35) and x = 0.7 ("bear", 36–71); a 160×120 camera at the origin, focal 240."""
    xs = np.linspace(-0.4, 0.4, 6)
    means = []
    for centre in (-0.7, 0.7):
        for y in xs:
            for x in xs:
                means.append([centre + x, y, 5.0])
    n = len(means)
    gaussians = Gaussians(
        means=torch.tensor(means, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]] * n),
        scales=torch.full((n, 2), math.log(0.09)),
        opacities=torch.full((n,), math.log(0.99 / 0.01)),
        sh=torch.zeros(n, 1, 3),
    ).check()
    K = torch.tensor([[[240.0, 0.0, WIDTH / 2], [0.0, 240.0, HEIGHT / 2], [0.0, 0.0, 1.0]]])
    cameras = Cameras(
        viewmats=torch.eye(4, dtype=torch.float64)[None],
        Ks=K.double(),
        widths=torch.tensor([WIDTH]),
        heights=torch.tensor([HEIGHT]),
        names=("frame_00001.jpg",),
    )
    return gaussians, cameras


def _regions(seen: bool = True) -> Regions:
    labels = np.repeat(np.array([[0, 0, 0, 0], [1, 1, 1, 1]]), 36, axis=0)
    features = np.stack([_unit(1, 0, 0.05, 0), _unit(0, 1, 0.05, 0)]).astype(np.float32)
    flags = np.array([seen, seen])
    if not seen:
        features = np.zeros_like(features)
    return Regions(RegionLevels.from_labels(labels), (features,) * 3, (flags,) * 3, SPACE)


@pytest.fixture(scope="module")
def scene():
    return _scene()


def _truth_masks(gaussians, cameras, threshold=0.5):
    """The rendered masks of the two patches (what a perfect selection predicts)."""
    selected = np.zeros((len(gaussians), 2), dtype=bool)
    selected[:36, 0] = selected[36:, 1] = True
    return selection_masks(gaussians, cameras.select([0]), selected, threshold=threshold)


def _frame(masks: dict[str, np.ndarray], scale: float = 1.0) -> FrameLabels:
    objects = []
    for category, mask in masks.items():
        for polygon in mask_to_polygons(mask):
            polygon = polygon * scale
            low, high = polygon.min(axis=0), polygon.max(axis=0)
            box = (float(low[0]), float(low[1]), float(high[0]), float(high[1]))
            objects.append(LabelledObject(category, polygon, box))
    return FrameLabels("frame_00001.jpg", round(WIDTH * scale), round(HEIGHT * scale), objects)


def test_lerf_perfect_selection_scores_one_and_reference_pools_both(scene):
    gaussians, cameras = scene
    masks = _truth_masks(gaussians, cameras)
    mug, bear = masks[..., 0], masks[..., 1]
    assert mug.sum() > 1000 and bear.sum() > 1000 and not (mug & bear).any()
    # labels stated at twice the render resolution: polygons are scaled down, exactly
    frames = [("frame_00001", _frame({"mug": mug, "bear": bear}, scale=2.0))]
    best = FieldQuery(_regions(), _TableEncoder(), QueryConfig(mode="level", level=3))
    result = evaluate_lerf(best, gaussians, cameras, frames)
    assert result.metrics == {"miou": 1.0, "accuracy": 1.0}
    assert [(i["prompt"], i["iou"]) for i in result.items] == [("mug", 1.0), ("bear", 1.0)]

    # the paper's selection pools levels 2 and 3 (top 3 each, best 3 kept): with only two
    # regions per level it always keeps the other patch too, so IoU = |own| / |both|
    reference = FieldQuery(_regions(), _TableEncoder(), QueryConfig(mode="paper"))
    result = evaluate_lerf(reference, gaussians, cameras, frames)
    both = (mug | bear).sum()
    expected_iou = {"mug": mug.sum() / both, "bear": bear.sum() / both}
    for item in result.items:
        assert item["iou"] == pytest.approx(expected_iou[item["prompt"]])
    # pixel accuracy: the other patch is the only error
    expected_acc = {"mug": 1 - bear.sum() / mug.size, "bear": 1 - mug.sum() / mug.size}
    for item in result.items:
        assert item["accuracy"] == pytest.approx(expected_acc[item["prompt"]])
    assert result.metrics["miou"] == pytest.approx(np.mean(list(expected_iou.values())))
    # the automatic selection takes only the patch named like the query (two regions are too
    # few for a scene null: the relevancy decides whether anything is relevant)
    engine = FieldQuery(_regions(), _TableEncoder(), QueryConfig(min_relevancy=0.5))
    result = evaluate_lerf(engine, gaussians, cameras, frames)
    assert result.metrics == {"miou": 1.0, "accuracy": 1.0}
    assert result.settings["selection"] == "auto"


def test_lerf_category_of_several_polygons_is_their_union(scene):
    gaussians, cameras = scene
    masks = _truth_masks(gaussians, cameras)
    # "mug" labels both patches (two objects, two polygons); the threshold mode selects every
    # region above a tiny relevancy, i.e. both patches: exactly the union
    frame = _frame({"mug": masks[..., 0] | masks[..., 1]})
    assert len(frame.objects) == 2
    both = FieldQuery(
        _regions(), _TableEncoder(), QueryConfig(mode="threshold", level=3, threshold=1e-6)
    )
    result = evaluate_lerf(both, gaussians, cameras, [("frame_00001", frame)])
    assert result.metrics == {"miou": 1.0, "accuracy": 1.0}


def test_empty_prediction_scores_zero_under_every_mask_protocol(scene):
    gaussians, cameras = scene
    masks = _truth_masks(gaussians, cameras)
    frames = [("frame_00001", _frame({"mug": masks[..., 0]}))]
    unseen = FieldQuery(_regions(seen=False), _TableEncoder(), QueryConfig(mode="level"))
    result = evaluate_lerf(unseen, gaussians, cameras, frames)
    assert result.metrics["miou"] == 0.0
    assert result.items[0]["predicted_pixels"] == 0
    result = evaluate_lerf_opengaussian(unseen, gaussians, cameras, frames)
    assert result.metrics == {"miou": 0.0, "acc@0.25": 0.0, "acc@0.5": 0.0}
    views = {"00": {"mug": masks[..., 0]}}
    result = evaluate_3dovs(unseen, gaussians, cameras, SegmentationSet(("mug",), views))
    assert result.metrics == {"miou": 0.0, "accuracy": pytest.approx(1 - masks[..., 0].mean())}


def test_opengaussian_thresholds_the_silhouette_at_07(scene):
    gaussians, cameras = scene
    truth = _truth_masks(gaussians, cameras, threshold=0.7)
    loose = _truth_masks(gaussians, cameras, threshold=0.5)
    assert (loose[..., 0] & ~truth[..., 0]).any()  # the patch edges differ between thresholds
    frames = [("frame_00001", _frame({"mug": truth[..., 0]}))]
    best = FieldQuery(_regions(), _TableEncoder(), QueryConfig(mode="level"))
    result = evaluate_lerf_opengaussian(best, gaussians, cameras, frames)
    assert result.protocol == "lerf-opengaussian"
    assert result.metrics == {"miou": 1.0, "acc@0.25": 1.0, "acc@0.5": 1.0}
    # the same frame under the 0.5 threshold is not perfect
    assert evaluate_lerf(best, gaussians, cameras, frames).metrics["miou"] < 1.0


def test_opengaussian_says_which_prompt_list_the_scene_name_chose(scene):
    gaussians, cameras = scene
    truth = _truth_masks(gaussians, cameras, threshold=0.7)
    frames = [("frame_00001", _frame({"mug": truth[..., 0], "bear": truth[..., 1]}))]
    best = FieldQuery(_regions(), _TableEncoder(), QueryConfig(mode="level"))
    # any other name: every labelled category is queried (both perfect)
    other = evaluate_lerf_opengaussian(best, gaussians, cameras, frames, scene_name="desk")
    assert other.metrics["miou"] == 1.0
    assert other.notes == (
        "scene name 'desk' is none of OpenGaussian's (figurines, ramen, teatime, "
        "waldo_kitchen): every labelled category is queried",
    )
    # "teatime": only OpenGaussian's teatime prompts, which name neither, so both score 0
    teatime = evaluate_lerf_opengaussian(best, gaussians, cameras, frames, scene_name="teatime")
    assert teatime.metrics["miou"] == 0.0
    assert [item["iou"] for item in teatime.items] == [0.0, 0.0]
    assert teatime.notes == (
        "scene name 'teatime' → OpenGaussian's fixed prompt list for teatime (14 prompts); "
        "2 labelled (frame, category) pairs outside it score 0",
    )
    assert teatime.settings["scene_name"] == "teatime" and len(teatime.settings["prompts"]) == 14
    assert teatime.to_json()["notes"] == list(teatime.notes)


def test_langsplat_protocol_composes_the_rules_on_rendered_relevancy(scene):
    gaussians, cameras = scene
    masks = _truth_masks(gaussians, cameras)
    frames = [("frame_00001", _frame({"mug": masks[..., 0], "bear": masks[..., 1]}))]
    engine = FieldQuery(_regions(), _TableEncoder())
    result = evaluate_lerf_langsplat(engine, gaussians, cameras, frames)
    for q, item in enumerate(result.items):
        per_gaussian = np.stack(
            [engine.gaussian_relevancies([item["prompt"]], k)[:, 0] for k in (1, 2, 3)], axis=1
        )
        stack = np.moveaxis(relevancy_map(gaussians, cameras.select([0]), per_gaussian), 2, 0)
        chosen = langsplat_level(stack)
        predicted = langsplat_mask(stack[chosen])
        truth = masks[..., q]
        assert item["level"] == chosen + 1
        assert item["iou"] == pytest.approx((predicted & truth).sum() / (predicted | truth).sum())
        # the named patch's relevancy dominates: its mask is most of the patch (the 30-px
        # smoothing rounds the corners off: IoU 0.78), and the smoothed peak lies inside its box
        assert item["iou"] > 0.7 and item["localized"]
        assert langsplat_localized(stack, frames[0][1].category_boxes(item["prompt"]))
    assert result.metrics == {
        "miou": pytest.approx(np.mean([i["iou"] for i in result.items])),
        "localization": 1.0,
    }


def test_3dovs_queries_wood_wall_as_wood_at_the_masks_resolution(scene):
    gaussians, cameras = scene
    big = cameras.resized([2 * WIDTH], [2 * HEIGHT])
    selected = np.zeros((len(gaussians), 2), dtype=bool)
    selected[:36, 0] = selected[36:, 1] = True
    truth = selection_masks(gaussians, big, selected)
    segmentations = SegmentationSet(
        classes=("mug", "wood wall"),
        views={"00": {"mug": truth[..., 0], "wood wall": truth[..., 1]}},
    ).check()
    encoder = _TableEncoder()
    regions = _regions()
    # "wood" names the right patch here; "wood wall" is not in the encoder's table at all
    features = np.stack([_unit(1, 0, 0, 0), _unit(0, 0, 1, 0)]).astype(np.float32)
    regions = Regions(regions.levels, (features,) * 3, regions.seen, SPACE)
    result = evaluate_3dovs(
        FieldQuery(regions, encoder, QueryConfig(mode="level")), gaussians, cameras, segmentations
    )
    assert [(i["prompt"], i["query"], i["iou"]) for i in result.items] == [
        ("mug", "mug", 1.0),
        ("wood wall", "wood", 1.0),
    ]
    bad = SegmentationSet(classes=("mug",), views={"07": {"mug": truth[..., 0]}})
    with pytest.raises(InputError, match="segmentations/07"):
        evaluate_3dovs(FieldQuery(regions, encoder), gaussians, cameras, bad)


def test_scannet_classifies_by_region_feature(scene):
    gaussians, _ = scene
    labels = np.repeat(np.array([1, 2]), 36)
    labels[0] = 3  # a class outside the subset: ignored
    points = PointLabels(
        gaussians.means.numpy().astype(np.float32), labels, {1: "mug", 2: "bear", 3: "wood"}
    )
    engine = FieldQuery(_regions(), _TableEncoder())
    (result,) = evaluate_scannet(engine, gaussians, points, subsets={"2": (1, 2)})
    assert result.protocol == "scannet-2"
    assert result.metrics == {"miou": 1.0, "macc": 1.0}
    assert result.settings["points"] == 71
    # with "wood" evaluated, point 0 (wood, in the mug's region) is a mug false positive and
    # a missed wood: mug 35/36, bear 1, wood 0
    (result,) = evaluate_scannet(engine, gaussians, points, subsets={"3": (1, 2, 3)})
    assert [i["iou"] for i in result.items] == pytest.approx([35 / 36, 1.0, 0.0])
    assert result.metrics["miou"] == pytest.approx((35 / 36 + 1) / 3)
    short = PointLabels(points.points[:10], labels[:10], points.class_names)
    with pytest.raises(InputError, match="10 points for 72 Gaussians"):
        evaluate_scannet(engine, gaussians, short)


def test_hierarchy_scores_levels_against_ground_truth():
    hierarchy = Hierarchy.from_subparts(
        np.arange(4),
        np.array([0, 0, 1, 1], dtype=np.int32),
        np.array([0, 1], dtype=np.int32),
        (("a", "b", "c", "d"), ("ab", "cd"), ("x", "y")),
    )
    truth = np.array([[0, 0, 0, 0], [1, 1, 0, 0], [2, 2, 1, 1], [3, 3, 1, 1]], dtype=np.int32)
    np.testing.assert_array_equal(hierarchy.labels, truth)
    exact = RegionLevels.from_labels(truth)
    result = evaluate_hierarchy(exact, hierarchy)
    assert result.metrics == {
        "miou_subpart": 1.0,
        "miou_part": 1.0,
        "miou_object": 1.0,
        "purity": 1.0,
    }
    # level 3 as one region: each object scores 2/4
    coarse = truth.copy()
    coarse[:, 3] = 0
    assert (
        evaluate_hierarchy(RegionLevels.from_labels(coarse), hierarchy).metrics["miou_object"]
        == 0.5
    )
    fewer, _ = exact.select(np.arange(3))
    with pytest.raises(InputError, match="hierarchy's 4 Gaussians, got 3"):
        evaluate_hierarchy(fewer, hierarchy)


def test_frame_mean_weighs_frames_equally():
    items = [
        {"frame": "a", "iou": 1.0},
        {"frame": "a", "iou": 0.0},
        {"frame": "a", "iou": 0.0},
        {"frame": "b", "iou": 1.0},
    ]
    assert frame_mean(items, "iou") == pytest.approx((1 / 3 + 1) / 2)
    assert math.isnan(frame_mean([], "iou"))
