"""Building from the splat alone: view-dependent colour, camera placement, the views folder,
guidance on the renders (oracle and real-model paths) and the build against the real cameras'."""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch

import tiny_models
from conftest import random_gaussians, run_cli
from thgs.errors import InputError
from thgs.eval import find_ground_truth
from thgs.field_config import FieldConfig
from thgs.guidance import load_guidance, read_embedding_space
from thgs.scene import Cameras, Gaussians, load_scene, write_ply
from thgs.scene.gaussians import SH_C0, sh_basis
from thgs.splat_views import (
    VIEWS_RECORD,
    ModelGuidance,
    OracleGuidance,
    PlacementConfig,
    SplatViewsRequest,
    close_up_cameras,
    look_at,
    make_views_guidance,
    open_views_folder,
    orbit_cameras,
    place_cameras,
    prepare_splat_views,
    render_views,
    scene_frame,
    visibility_counts,
)
from thgs.workflows import BuildRequest, EvalRequest, build_field_file, evaluate_field_file

SMALL = PlacementConfig(
    width=160,
    height=120,
    orbit_views=(8, 4),
    core_percentiles=(50.0, 90.0),
    close_views=3,
    close_directions=6,
    min_gain=5,
)


# --- view-dependent colour ------------------------------------------------------------------------


def test_sh_basis_is_orthonormal_on_the_sphere():
    """The 16 basis functions integrate to the identity over the sphere (Monte Carlo), which
    pins every constant's magnitude independently of the implementation."""
    generator = torch.Generator().manual_seed(0)
    directions = torch.randn(400_000, 3, generator=generator, dtype=torch.float64)
    directions /= directions.norm(dim=1, keepdim=True)
    basis = sh_basis(directions, 3)
    gram = 4 * math.pi * basis.T @ basis / len(directions)
    np.testing.assert_allclose(gram.numpy(), np.eye(16), atol=0.02)


def test_view_colors_by_hand():
    """Degree 0 is the DC colour; degree 1 along +x is 0.5 + C0·dc − C1·sh₃ (3DGS's sign)."""
    gaussians = random_gaussians(5, sh_degree=1, seed=1)
    centre = gaussians.means[0] - torch.tensor([2.0, 0.0, 0.0])  # Gaussian 0 seen along +x
    colors = gaussians.view_colors(centre)
    c1 = 0.4886025119029199
    expected = (0.5 + SH_C0 * gaussians.sh[0, 0] - c1 * gaussians.sh[0, 3]).clamp(0, 1)
    torch.testing.assert_close(colors[0], expected)
    flat = random_gaussians(5, sh_degree=0, seed=2)
    torch.testing.assert_close(flat.view_colors(torch.zeros(3)), flat.dc_colors())
    with pytest.raises(InputError, match="sh degree"):
        sh_basis(torch.zeros(1, 3), 4)


# --- placement ------------------------------------------------------------------------------------


def _table_scene(n_floor: int = 3000, seed: int = 0, up: int = 1) -> Gaussians:
    """Opaque round Gaussians: a dense floor at z = 0 (4 × 4), a box on it (up = 1) or hanging
    under it (up = −1)."""
    rng = np.random.default_rng(seed)
    floor = np.c_[rng.uniform(-2, 2, (n_floor, 2)), np.zeros(n_floor)]
    box = rng.uniform([-0.3, -0.3, 0.0], [0.3, 0.3, 0.6], (n_floor // 3, 3))
    box[:, 2] *= up
    means = np.concatenate([floor, box])
    n = len(means)
    return Gaussians(
        means=torch.tensor(means, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        scales=torch.full((n, 3), math.log(0.03)),
        opacities=torch.full((n,), 4.0),
        sh=torch.tensor(rng.normal(size=(n, 1, 3)), dtype=torch.float32),
    )


@pytest.mark.parametrize("up", [1, -1])
def test_scene_frame_finds_up_from_the_floor(up):
    frame = scene_frame(_table_scene(up=up), SMALL)
    np.testing.assert_allclose(frame.up, [0, 0, up], atol=0.05)
    assert frame.radii[0] < frame.radii[1]  # half the Gaussians are nearer than 90 %
    given = scene_frame(_table_scene(up=up), PlacementConfig(up=(0.0, 0.0, -2.0 * up)))
    np.testing.assert_allclose(given.up, [0, 0, -up])


def test_model_cameras_give_up(small_dataset):
    scene = load_scene(small_dataset)
    frame = scene_frame(scene.gaussians, cameras=scene.cameras)
    assert frame.up @ np.array([0.0, 0.0, 1.0]) > 0.95  # the synthetic world is z-up


def test_look_at_projects_the_target_to_the_centre_and_up_upwards():
    eye, target, up = np.array([3.0, -1.0, 2.0]), np.array([0.5, 0.2, 0.1]), np.array([0, 0, 1.0])
    viewmat = look_at(eye, target, up)
    K = [[100, 0, 50], [0, 100, 40], [0, 0, 1]]
    camera = Cameras.from_lists([viewmat], [K], [100], [80], ["v"])
    camera.check()
    pixels, depth = camera.project(torch.tensor(np.stack([target, target + 0.1 * up])))
    np.testing.assert_allclose(pixels[0, 0].numpy(), [50, 40], atol=1e-9)
    assert pixels[0, 1, 1] < 40  # up is towards the top of the image (smaller y)
    np.testing.assert_allclose(depth[0, 0].item(), np.linalg.norm(target - eye))


def test_orbit_sees_its_core_sphere():
    gaussians = _table_scene()
    frame = scene_frame(gaussians, SMALL)
    cameras = orbit_cameras(frame, SMALL)
    assert len(cameras) == sum(SMALL.orbit_views)
    assert cameras.stems[0] == "orbit_00001"
    # every orbit camera looks at the centre, and the outer ring frames the 90 % sphere
    pixels, depth = cameras.project(torch.tensor(frame.centre)[None])
    np.testing.assert_allclose(pixels[:, 0].numpy(), [[80, 60]] * len(cameras), atol=1e-6)
    sphere = torch.tensor(frame.centre) + frame.radii[1] * torch.tensor(
        [[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    )
    pixels, depth = cameras.select(range(8, 12)).project(sphere)
    assert (depth > 0).all()
    assert (pixels[..., 0] >= 0).all() and (pixels[..., 0] <= 160).all()
    assert (pixels[..., 1] >= 0).all() and (pixels[..., 1] <= 120).all()


def test_visibility_counts_by_hand():
    """Two opaque Gaussians on the x axis: camera A looks along +x (the nearer hides the other),
    camera B looks down from above (both seen)."""
    gaussians = Gaussians(
        means=torch.tensor([[0.0, 0, 0], [1.0, 0, 0]]),
        quats=torch.tensor([[1.0, 0, 0, 0]] * 2),
        scales=torch.full((2, 3), math.log(0.2)),
        opacities=torch.full((2,), 8.0),
        sh=torch.zeros(2, 1, 3),
    )
    K = [[100.0, 0, 50], [0, 100, 50], [0, 0, 1]]
    cameras = Cameras.from_lists(
        [
            look_at(np.array([-3.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0, 0, 1.0])),
            look_at(np.array([0.5, 0, 4.0]), np.array([0.5, 0, 0]), np.array([0, 1.0, 0])),
        ],
        [K, K],
        [100, 100],
        [100, 100],
        ["a", "b"],
    )
    assert visibility_counts(gaussians, cameras).tolist() == [2, 1]


def test_close_ups_see_what_the_orbit_misses():
    """A box hidden under a slab: no orbit view sees it, a close-up does."""
    rng = np.random.default_rng(3)
    slab = np.c_[rng.uniform(-1, 1, (3000, 2)), np.full(3000, 1.0)]
    hidden = rng.uniform([-0.2, -0.2, 0.05], [0.2, 0.2, 0.3], (400, 3))
    means = np.concatenate([slab, hidden])
    n = len(means)
    gaussians = Gaussians(
        means=torch.tensor(means, dtype=torch.float32),
        quats=torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1),
        scales=torch.full((n, 3), math.log(0.04)),
        opacities=torch.full((n,), 6.0),
        sh=torch.zeros(n, 1, 3),
    )
    config = PlacementConfig(
        width=128,
        height=96,
        orbit_views=(6,),
        elevations_deg=(60.0,),
        core_percentiles=(90.0,),
        close_views=4,
        min_gain=20,
        up=(0.0, 0.0, 1.0),
    )
    frame = scene_frame(gaussians, config)
    orbit = orbit_cameras(frame, config)
    seen = visibility_counts(gaussians, orbit, scale=config.coverage_scale)
    box = np.arange(3000, n)
    assert (seen[box] == 0).all()
    close, after = close_up_cameras(gaussians, frame, seen, config)
    assert close is not None and close.stems[0] == "close_00001"
    assert (after[box] > 0).sum() >= 20
    # the counts are those of rendering the chosen cameras
    np.testing.assert_array_equal(
        after, seen + visibility_counts(gaussians, close, scale=config.coverage_scale)
    )


def test_placement_refuses_scenes_without_usable_gaussians(tmp_path):
    faint = random_gaussians(50, seed=4)
    faint = Gaussians(faint.means, faint.quats, faint.scales, torch.full((50,), -8.0), faint.sh)
    with pytest.raises(InputError, match="no usable Gaussians") as error:
        place_cameras(faint, SMALL, source="faint.ply")
    assert "faint.ply" in str(error.value)
    point = random_gaussians(50, seed=5)
    opaque = torch.full((50,), 5.0)
    point = Gaussians(torch.zeros(50, 3), point.quats, point.scales, opaque, point.sh)
    with pytest.raises(InputError, match="degenerate"):
        place_cameras(point, SMALL, source="point.ply")
    with pytest.raises(InputError, match=r"PlacementConfig\.core_percentiles"):
        PlacementConfig(orbit_views=(4, 4)).check()


# --- the views folder -----------------------------------------------------------------------------


def test_views_folder_is_kept_reused_and_guarded(tmp_path):
    gaussians = _table_scene(n_floor=1500)
    folder = tmp_path / "views"
    views = open_views_folder(folder, gaussians, tmp_path / "scene.ply", SMALL)
    assert views.placed and (folder / VIEWS_RECORD).is_file()
    assert len(views.cameras) == views.record["views"] >= views.record["base_views"] == 12
    assert render_views(views, gaussians) == len(views.cameras)
    again = open_views_folder(folder, gaussians, tmp_path / "scene.ply", SMALL)
    assert not again.placed and again.cameras.names == views.cameras.names
    torch.testing.assert_close(again.cameras.viewmats, views.cameras.viewmats)
    assert render_views(again, gaussians) == 0  # resumed: nothing left to render
    (folder / "images" / f"{views.cameras.stems[2]}.jpg").unlink()
    assert render_views(again, gaussians) == 1

    other = PlacementConfig(**{**SMALL.__dict__, "close_views": 0})
    with pytest.raises(InputError, match="other placement settings") as error:
        open_views_folder(folder, gaussians, tmp_path / "scene.ply", other)
    assert VIEWS_RECORD in str(error.value)
    moved = _table_scene(n_floor=1500, seed=9)
    with pytest.raises(InputError, match="another scene"):
        open_views_folder(folder, moved, tmp_path / "scene.ply", SMALL)
    replaced = open_views_folder(folder, moved, tmp_path / "scene.ply", SMALL, overwrite=True)
    assert replaced.placed and not (folder / "images").exists()

    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(InputError, match=r"holds no views\.json"):
        open_views_folder(foreign, gaussians, tmp_path / "scene.ply", SMALL)
    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(InputError, match="is a file"):
        open_views_folder(afile, gaussians, tmp_path / "scene.ply", SMALL)


def test_renders_use_view_dependent_colour(tmp_path):
    """A Gaussian whose degree-1 term makes it red from +x and dark from −x."""
    gaussians = Gaussians(
        means=torch.zeros(1, 3),
        quats=torch.tensor([[1.0, 0, 0, 0]]),
        scales=torch.full((1, 3), math.log(0.3)),
        opacities=torch.full((1,), 8.0),
        sh=torch.zeros(1, 4, 3),
    )
    gaussians.sh[0, 3, 0] = -0.8  # red rises with the direction's x (camera on −x looking +x)
    from thgs.splat_views import render_view

    K = [[100.0, 0, 32], [0, 100, 32], [0, 0, 1]]
    cams = Cameras.from_lists(
        [
            look_at(np.array([-3.0, 0, 0]), np.zeros(3), np.array([0, 0, 1.0])),
            look_at(np.array([3.0, 0, 0]), np.zeros(3), np.array([0, 0, 1.0])),
        ],
        [K, K],
        [64, 64],
        [64, 64],
        ["a", "b"],
    )
    red_from_minus, _ = render_view(gaussians, cams.select([0]))
    red_from_plus, max_id = render_view(gaussians, cams.select([1]))
    assert red_from_minus[32, 32, 0] > red_from_plus[32, 32, 0] + 100
    assert max_id[32, 32] == 0 and max_id[0, 0] == -1


# --- guidance and the build -----------------------------------------------------------------------


def _ply(dataset) -> os.PathLike:
    return dataset / "point_cloud" / "iteration_30000" / "point_cloud.ply"


def test_oracle_guidance_matches_the_dataset_oracle_on_the_real_cameras(small_dataset, tmp_path):
    """Views placed at the dataset's own cameras get the very guidance the dataset holds."""
    scene = load_scene(small_dataset)
    views = open_views_folder(
        tmp_path / "views",
        scene.gaussians,
        _ply(small_dataset),
        PlacementConfig(close_views=0, max_width=4096),
        model_cameras=scene.cameras,
    )
    assert views.cameras.stems == scene.cameras.stems
    make_views_guidance(views, scene.gaussians, OracleGuidance(small_dataset))
    assert read_embedding_space(views.guidance) == read_embedding_space(
        small_dataset / "language_features"
    )
    made = load_guidance(views.guidance, scene.cameras)
    truth = load_guidance(small_dataset / "language_features", scene.cameras)
    for ours, theirs in zip(made, truth):
        np.testing.assert_array_equal(ours.segments, theirs.segments)
        np.testing.assert_allclose(ours.features, theirs.features, atol=1e-6)


def test_oracle_refuses_another_scenes_ground_truth(small_dataset, tmp_path):
    gaussians = _table_scene(n_floor=600)
    views = open_views_folder(tmp_path / "views", gaussians, tmp_path / "x.ply", SMALL)
    with pytest.raises(InputError, match="not this scene's ground truth"):
        make_views_guidance(views, gaussians, OracleGuidance(small_dataset))
    with pytest.raises(InputError, match=r"synthetic\.json"):
        make_views_guidance(views, gaussians, OracleGuidance(tmp_path))


@pytest.mark.slow
def test_build_from_the_splat_alone_scores_like_the_real_cameras(
    small_dataset, small_field, tmp_path
):
    """The PLY alone (no cameras.json beside it), the oracle on virtual views: every level and
    the LERF-style answers close to the build from the dataset's own cameras."""
    ply = tmp_path / "scene.ply"
    ply.write_bytes(_ply(small_dataset).read_bytes())
    request = SplatViewsRequest(tmp_path / "views", OracleGuidance(small_dataset))
    out = tmp_path / "splat.thgs"
    built = build_field_file(
        BuildRequest(scene=ply, out=out, config=FieldConfig.lerf(), splat_views=request)
    )
    assert built.field.provenance.scene.source == "views"  # relative to the field file

    def scores(field):
        report = evaluate_field_file(
            EvalRequest(
                dataset=small_dataset,
                field=field,
                out=field.with_suffix(".json"),
                protocols=("hierarchy", "lerf"),
                scene=small_dataset,
            ),
            find_ground_truth(small_dataset),
        ).report
        return {
            key: report.metric(*key.split(":"))
            for key in ("hierarchy:miou_part", "hierarchy:miou_object", "lerf:miou")
        }

    splat, real = scores(out), scores(small_field)
    for key in splat:
        assert splat[key] >= real[key] - 0.05, (key, splat, real)
    # a rerun resumes: nothing rendered again
    again = prepare_splat_views(ply, request)
    assert again.rendered == 0 and not again.views.placed


def test_model_guidance_runs_sam_and_clip_on_the_renders(tmp_path):
    """Random tiny SAM and CLIP of the real architectures, on renders of a small scene."""
    from thgs.guidance.preprocess import MaskGeneratorConfig

    sam = tiny_models.tiny_sam(tmp_path / "sam")
    clip = tiny_models.tiny_clip(tmp_path / "clip")
    gaussians = _table_scene(n_floor=600)
    ply = tmp_path / "scene.ply"
    write_ply(ply, gaussians)
    masks = MaskGeneratorConfig(
        points_per_side=4,
        crop_layers=0,
        pred_iou_threshold=0.0,
        stability_threshold=0.0,
        min_region_area=0,
    )
    placement = PlacementConfig(width=64, height=48, orbit_views=(4,), close_views=0)
    request = SplatViewsRequest(
        tmp_path / "views", ModelGuidance(sam=str(sam), clip=str(clip), masks=masks), placement
    )
    prepared = prepare_splat_views(ply, request)
    views = prepared.views
    assert prepared.rendered == 4
    guidance = load_guidance(views.guidance, views.cameras)
    assert [view.stem for view in guidance] == list(views.cameras.stems)
    assert all(view.segments.shape == (4, 48, 64) for view in guidance)
    assert sum(len(view.features) for view in guidance) > 0
    assert read_embedding_space(views.guidance)[1] == 16
    assert prepare_splat_views(ply, request).rendered == 0


def test_cli_from_splat_options(small_dataset, tmp_path, capsys):
    out = tmp_path / "f.thgs"

    def run(argv):
        code, _, err = run_cli(argv, capsys)
        return code, " ".join(err.split())

    code, err = run(["build", str(small_dataset), "-o", str(out), "--oracle", str(small_dataset)])
    assert code != 0 and "--oracle" in err and "only with --from-splat" in err
    splat = ["build", str(_ply(small_dataset)), "-o", str(out), "--from-splat"]
    oracle = ["--oracle", str(small_dataset)]
    code, err = run([*splat, *oracle, "--source", str(small_dataset)])
    assert code != 0 and "leave out --source" in err
    code, err = run([*splat, *oracle, "--sam", "x"])
    assert code != 0 and "leave out --sam" in err
    code, err = run([*splat, "--orbit-views", "5", "6"])
    assert code != 0 and "--orbit-views" in err and "one count per orbit sphere" in err
    code, err = run([*splat, "--orbit-views", "5", "6", "--orbit-spheres", "50", "120"])
    assert code != 0 and "--orbit-spheres" in err
    code, err = run([*splat, "--view-size", "8", "8"])
    assert code != 0 and "--view-size" in err
    assert not out.exists()
    code, err = run(["build", str(_ply(small_dataset)), "-o", str(out)])
    assert code != 0 and "--from-splat" in err


@pytest.mark.slow
def test_cli_builds_from_the_splat_and_queries(small_dataset, tmp_path, capsys):
    ply = tmp_path / "scene.ply"
    ply.write_bytes(_ply(small_dataset).read_bytes())
    out = tmp_path / "f.thgs"
    argv = [
        "build",
        str(ply),
        "-o",
        str(out),
        "--from-splat",
        "--oracle",
        str(small_dataset),
        "--orbit-views",
        "8",
        "4",
        "--orbit-spheres",
        "50",
        "90",
        "--close-views",
        "3",
        "--view-size",
        "160",
        "120",
    ]
    code, stdout, err = run_cli(argv, capsys)
    assert code == 0, err
    assert "wrote" in stdout
    record = json.loads((tmp_path / "f.views" / VIEWS_RECORD).read_text())
    assert record["placement"]["orbit_views"] == [8, 4] and record["views"] >= 12
    code, _, err = run_cli(["query", str(out), "mug", "-o", str(tmp_path / "q")], capsys)
    assert code == 0, err
    # scored on the dataset's frames only with the dataset's cameras (--scene), and told so
    report = tmp_path / "r.json"
    code, _, err = run_cli(["eval", str(small_dataset), str(out), "-o", str(report)], capsys)
    assert code != 0 and "virtual views" in err and "--scene" in " ".join(err.split())
    assert not report.exists()
    argv = ["eval", str(small_dataset), str(out), "-o", str(report), "--scene", str(small_dataset)]
    code, _, err = run_cli(argv, capsys)
    assert code == 0, err
    assert json.loads(report.read_text())["results"]
    assert json.loads((tmp_path / "q" / "results.json").read_text())["queries"][0]["gaussians"] > 0
