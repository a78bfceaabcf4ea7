"""partition_scene end to end: known answers from synthetic ground truth, and bad input."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import pytest
import torch

from conftest import look_at
from test_synthetic import _FakeEncoder
from thgs import Cameras, Gaussians
from thgs.errors import InputError
from thgs.eval import purity
from thgs.eval.ground_truth import Hierarchy
from thgs.graph import ReweightConfig
from thgs.guidance import ViewGuidance
from thgs.lift import LiftConfig
from thgs.pipeline import PosedScene, SuperpointConfig, partition_scene
from thgs.render import render
from thgs.synthetic import OracleConfig, generate_scene, oracle_guidance, preset


@dataclass(frozen=True)
class Posed:
    gaussians: Gaussians
    cameras: Cameras | None


def flat_square(side: int) -> tuple[Gaussians, np.ndarray, np.ndarray]:
    """side² grey, opaque surfels filling the unit square at z = 0 (centres jittered by 1e-3),
    and their x and y."""
    xs = (np.arange(side) + 0.5) / side - 0.5
    x, y = (a.ravel() for a in np.meshgrid(xs, xs, indexing="ij"))
    n = x.size
    jitter = np.random.default_rng(0).normal(scale=1e-3, size=(n, 3))
    means = np.stack([x, y, np.zeros(n)], axis=1) + jitter
    gaussians = Gaussians(
        means=torch.tensor(means, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0.0, 0.0, 0.0]]).repeat(n, 1),
        scales=torch.full((n, 2), math.log(0.8 / side)),
        opacities=torch.full((n,), 3.0),
        sh=torch.zeros(n, 1, 3),
    )
    return gaussians, x, y


def ring_cameras(views: int, radius: float, focal: float) -> Cameras:
    """``views`` 160×120 cameras on a circle of ``radius`` at height 1.2, looking at the origin."""
    angles = 2 * math.pi * np.arange(views) / views
    eyes = [np.array([radius * math.cos(a), radius * math.sin(a), 1.2]) for a in angles]
    return Cameras(
        viewmats=torch.tensor(np.stack([look_at(eye, np.zeros(3)) for eye in eyes])),
        Ks=torch.tensor([[[focal, 0, 80], [0, focal, 60], [0, 0, 1]]] * views, dtype=torch.float64),
        widths=torch.full((views,), 160),
        heights=torch.full((views,), 120),
        names=tuple(f"view_{i}" for i in range(views)),
    )


def plane_scene(side: int = 80, views: int = 8) -> tuple[Posed, Hierarchy]:
    """A flat, uniformly grey square of side² surfels split into four regions along a wavy line
    and a straight one: geometry and colour say nothing about where the regions meet."""
    gaussians, x, y = flat_square(side)
    region = (x > 0.1 * np.sin(6 * y)).astype(np.int32) + 2 * (y > 0.05).astype(np.int32)
    names = tuple(f"region {i}" for i in range(4))
    hierarchy = Hierarchy.from_subparts(
        region, np.arange(4), np.zeros(4, np.int32), (names, names, ("plane",))
    )
    return Posed(gaussians, ring_cameras(views, 0.6, 200.0)), hierarchy


def oracle_views(
    scene: PosedScene, hierarchy: Hierarchy, config: OracleConfig
) -> list[ViewGuidance]:
    """The synthetic oracle's masks (with its SAM-like faults) for every camera."""
    encoder = _FakeEncoder()
    guidance = []
    for i, stem in enumerate(scene.cameras.stems):
        colors = torch.zeros(len(scene.gaussians), 1, dtype=torch.float64)
        max_id = render(scene.gaussians, scene.cameras.select([i]), colors).max_id.numpy()
        guidance.append(oracle_guidance(stem, max_id, hierarchy, encoder, config, i))
    return guidance


@pytest.fixture(scope="module")
def plane():
    return plane_scene()


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reweighting_raises_purity_on_noisy_guidance(plane, seed):
    # measured over oracle seeds 0–7 at its default severity 0.5 (docs/partition.md): no
    # reweighting 0.855 (it ignores the masks; 0.833 with the plane solved on one thread), ours
    # and the reference's 0.998–1.000
    scene, hierarchy = plane
    guidance = oracle_views(scene, hierarchy, OracleConfig(seed=seed))
    truth = hierarchy.labels[:, 1]
    config = SuperpointConfig()
    none = replace(config, reweight=ReweightConfig(mode="none"))
    plain, _ = partition_scene(scene, guidance, none)
    ours, report = partition_scene(scene, guidance, config)
    reference, _ = partition_scene(scene, guidance, config.as_reference())
    assert purity(plain, truth) < 0.87
    assert purity(ours, truth) > 0.99
    assert purity(reference, truth) > 0.99
    assert purity(ours, truth) - purity(plain, truth) > 0.12
    assert report.superpoints <= 16 and report.voted_edges > 0.9 * report.edges


@pytest.mark.slow
def test_partition_scene_is_deterministic_and_reports(plane):
    scene, hierarchy = plane
    guidance = oracle_views(scene, hierarchy, OracleConfig(seed=3))
    first, report = partition_scene(scene, guidance)
    second, _ = partition_scene(scene, guidance)
    np.testing.assert_array_equal(first, second)
    assert first.dtype == np.int32 and first.shape == (len(scene.gaussians),)
    np.testing.assert_array_equal(np.unique(first), np.arange(report.superpoints))
    assert report.gaussians == len(scene.gaussians) and report.views == len(guidance)
    assert list(report.seconds) == ["lift", "knn", "votes", "reweight", "partition"]
    assert 0.5 < report.labelled_share <= 1.0
    assert any("superpoints" in line for line in report.lines())


@pytest.mark.slow
def test_synthetic_scene_superpoints_are_pure_and_coarse():
    # a reduced synth-small (20k Gaussians, 12 views) with the oracle's default faults
    synthetic = generate_scene(preset("synth-small", gaussians=20_000, views=12))
    guidance = oracle_views(synthetic, synthetic.hierarchy, OracleConfig())
    labels, report = partition_scene(synthetic, guidance)
    assert purity(labels, synthetic.hierarchy.labels[:, 1]) >= 0.95
    assert purity(labels, synthetic.hierarchy.labels[:, 3]) >= 0.99
    assert report.superpoints * 50 <= len(synthetic.gaussians)


# --- bad input ---------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("method", ["latent", "exact"])
def test_views_without_masks_give_a_geometric_partition(plane, caplog, method):
    scene, _ = plane
    cameras = scene.cameras
    empty = [
        ViewGuidance(
            stem,
            np.full((4, int(cameras.heights[i]), int(cameras.widths[i])), -1, np.int32),
            np.zeros((0, 16), np.float32),
        )
        for i, stem in enumerate(cameras.stems)
    ]
    config = replace(SuperpointConfig(), lift=LiftConfig(method=method))
    with caplog.at_level(logging.WARNING, logger="thgs.pipeline"):
        labels, report = partition_scene(scene, empty, config)
    assert "no view has any mask" in caplog.text
    assert report.views_without_masks == len(empty) and report.voted_edges == 0
    assert report.labelled_share == 0.0
    none = replace(config, reweight=ReweightConfig(mode="none"))
    np.testing.assert_array_equal(labels, partition_scene(scene, empty, none)[0])


def test_fewer_gaussians_than_neighbours(plane):
    scene, hierarchy = plane
    few = np.arange(0, len(scene.gaussians), len(scene.gaussians) // 5)[:5]
    small = Posed(scene.gaussians.select(torch.from_numpy(few)), scene.cameras)
    guidance = oracle_views(small, hierarchy.select(few), OracleConfig())
    labels, report = partition_scene(small, guidance)
    assert labels.shape == (5,) and report.superpoints == 1  # under min_comp_weight: one piece


def test_bad_scenes_and_guidance_are_named(plane):
    scene, hierarchy = plane
    guidance = oracle_views(scene, hierarchy, OracleConfig(seed=4))
    nothing = scene.gaussians.select(torch.zeros(0, dtype=torch.long))
    with pytest.raises(InputError, match="no Gaussians"):
        partition_scene(Posed(nothing, scene.cameras), guidance)
    with pytest.raises(InputError, match="no cameras"):
        partition_scene(Posed(scene.gaussians, None), guidance)
    with pytest.raises(InputError, match="7 views of guidance for 8 cameras"):
        partition_scene(scene, guidance[:7])
    with pytest.raises(InputError, match="camera order"):
        partition_scene(scene, guidance[::-1])
    outside = guidance[2].segments.copy()
    outside[1, 0, 0] = len(guidance[2].features)
    broken = replace(guidance[2], segments=outside)
    with pytest.raises(InputError, match=r"view_2.*no feature row"):
        partition_scene(scene, [*guidance[:2], broken, *guidance[3:]])
    coarse = replace(guidance[0], segments=guidance[0].segments[:, ::2, ::2])
    with pytest.raises(InputError, match="--resize"):
        partition_scene(scene, [coarse, *guidance[1:]])


def test_presets_and_reference_switch():
    lerf, dovs = SuperpointConfig.lerf(), SuperpointConfig.three_dovs()
    assert (lerf.partition.regularization, lerf.partition.spatial_weight) == (0.1, 0.1)
    assert (dovs.partition.regularization, dovs.partition.spatial_weight) == (0.3, 0.2)
    assert dovs.lift.cosine_threshold == 0.5 and lerf.lift.cosine_threshold == 0.85
    reference = lerf.as_reference()
    assert reference.reweight == ReweightConfig.reference()
    assert reference.partition == replace(
        lerf.partition,
        weight_scale="reweighted",
        split_alternatives=2,
        polish=False,
        threaded_largest=False,
    )
    assert reference.lift == lerf.lift and reference.graph == lerf.graph
