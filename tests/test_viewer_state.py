"""The viewer's state logic and camera conversions, without a browser.

The field is the small synthetic dataset's (conftest's ``small_field``: `thgs synth` + `thgs
build`, 4,000 Gaussians, 8 views, real MiniLM names); every expectation comes from the library's
public API or from the field's own parent/children maps.
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
import pytest
import torch

from thgs.errors import InputError
from thgs.export import region_colors
from thgs.field_scene import open_field_scene
from thgs.query import FieldQuery, QueryConfig
from thgs.render import render
from thgs.scene import read_ply
from thgs.text import load_text_encoder
from thgs.viewer.camera import camera_pose, click_pixel, viewport_camera, viewport_size
from thgs.viewer.state import ViewerConfig, ViewerState, relevancy_colors
from thgs.views import pick, selection_masks


@pytest.fixture(scope="module")
def opened(small_field):
    field, scene = open_field_scene(small_field)
    return field, scene, FieldQuery(field, load_text_encoder(field.space))


@pytest.fixture
def state(opened):
    field, scene, query = opened
    return ViewerState(field, scene.gaussians, query)


def _object_pixel(state, scene):
    """A view and a pixel of it whose max-weight Gaussian is known (from a full render)."""
    camera = scene.cameras.select([0])
    zeros = torch.zeros(len(scene.gaussians), 1, dtype=torch.float64)
    max_id = render(scene.gaussians, camera, zeros).max_id.numpy()
    # a pixel on an object other than the floor: its level-1 region has a parent with siblings
    rows, cols = np.nonzero(max_id >= 0)
    for y, x in zip(rows[:: max(1, len(rows) // 400)], cols[:: max(1, len(rows) // 400)]):
        labels = state.field.labels[max_id[y, x]]
        if len(state.field.children(2, labels[2])) > 1:
            return camera, (int(x), int(y)), int(max_id[y, x])
    raise AssertionError("no pixel on a part with several sub-parts")


# Camera conversions -------------------------------------------------------------------------


def test_viewport_camera_projects_like_a_pinhole_with_centred_principal_point():
    angle = 0.3
    wxyz = (math.cos(angle / 2), 0.0, math.sin(angle / 2), 0.0)  # rotation about +Y
    position = np.array([1.0, -2.0, 0.5])
    fov = math.radians(60)
    camera = viewport_camera(wxyz, position, fov, 640, 480)
    rotation = np.array(
        [[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]]
    )
    # a point 3 units along the view axis lands on the image centre
    pixels, depths = camera.project(torch.tensor(np.array([position + 3.0 * rotation[:, 2]])))
    np.testing.assert_allclose(pixels[0, 0].numpy(), [320.0, 240.0], atol=1e-9)
    np.testing.assert_allclose(depths[0, 0].item(), 3.0, atol=1e-12)
    # a point at the top edge of the vertical field of view lands on row 0 (OpenCV: −Y is up)
    up = position + 2.0 * rotation[:, 2] - 2.0 * math.tan(fov / 2) * rotation[:, 1]
    pixels, _ = camera.project(torch.tensor(up[None]))
    np.testing.assert_allclose(pixels[0, 0].numpy(), [320.0, 0.0], atol=1e-9)
    assert camera.widths.tolist() == [640] and camera.heights.tolist() == [480]


def test_camera_pose_is_the_inverse_of_viewport_camera():
    rng = np.random.default_rng(3)
    for _ in range(5):
        wxyz = rng.normal(size=4)
        wxyz /= np.linalg.norm(wxyz)
        wxyz *= np.sign(wxyz[0])
        position = rng.normal(size=3)
        camera = viewport_camera(wxyz, position, 0.9, 300, 200)
        pose = camera_pose(camera, 0, distance=2.0)
        np.testing.assert_allclose(pose.wxyz * np.sign(pose.wxyz[0]), wxyz, atol=1e-9)
        np.testing.assert_allclose(pose.position, position, atol=1e-9)
        assert pose.fov == pytest.approx(0.9)
        rotation = camera.camtoworlds()[0, :3, :3].numpy()
        np.testing.assert_allclose(pose.look_at, position + 2.0 * rotation[:, 2], atol=1e-9)
        np.testing.assert_allclose(pose.up, -rotation[:, 1], atol=1e-9)


def test_click_pixels_and_viewport_sizes():
    assert click_pixel((0.0, 0.0), 640, 480) == (0, 0)
    assert click_pixel((0.5, 0.5), 640, 480) == (320, 240)
    assert click_pixel((1.0, 1.0), 640, 480) == (639, 479)
    assert click_pixel((0.9999, 0.0021), 640, 480) == (639, 1)
    assert viewport_size(640, 480, 480) == (640, 480)
    assert viewport_size(1280, 960, 480) == (640, 480)
    assert viewport_size(1000, 333, 100) == (300, 100)
    with pytest.raises(InputError, match="screen position"):
        click_pixel((1.2, 0.5), 640, 480)
    with pytest.raises(InputError, match="fov"):
        viewport_camera((1, 0, 0, 0), (0, 0, 0), 0.0, 10, 10)
    with pytest.raises(InputError, match="wxyz"):
        viewport_camera((0, 0, 0, 0), (0, 0, 0), 1.0, 10, 10)
    with pytest.raises(InputError, match="1×1"):
        viewport_camera((1, 0, 0, 0), (0, 0, 0), 1.0, 0, 10)


# Queries ------------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize(
    ("mode", "expected"),
    [
        ("level", QueryConfig(mode="level", level=2, top=1)),
        ("threshold", QueryConfig(mode="threshold", level=2, threshold=0.6)),
        ("paper", QueryConfig(mode="paper")),
    ],
)
def test_a_query_highlights_what_the_query_api_selects(opened, mode, expected):
    field, scene, query = opened
    state = ViewerState(field, scene.gaussians, query, ViewerConfig(level=2, mode=mode))
    state.set_mode(mode, 0.6)
    highlight = state.ask("  mug ")
    selection = query.select(["mug"], expected)[0]
    assert highlight.kind == "query" and highlight.text == "mug"
    assert highlight.regions == selection.regions and highlight.regions
    np.testing.assert_array_equal(highlight.gaussians, selection.gaussians)
    scores = query.relevancy(["mug"], 2)[0]
    assert [r for _, r, _ in highlight.ranking] == list(np.argsort(-scores, kind="stable")[:5])
    assert [s for _, _, s in highlight.ranking] == pytest.approx(np.sort(scores)[::-1][:5])
    # the calibrated confidences: the query's, and every listed region's
    assert highlight.confidence == selection.confidence
    listed = {(k, r) for k, r, _ in (*highlight.ranking, *highlight.regions)}
    assert set(highlight.region_confidence) == listed
    for (k, r), value in highlight.region_confidence.items():
        assert value == pytest.approx(query.confidence(["mug"], k)[0, r])


def test_query_level_and_mode_changes_ask_again(state, opened):
    _, _, query = opened
    assert state.ask("mug").regions == query.select(["mug"], QueryConfig(mode="auto"))[0].regions
    state.set_mode("level")
    state.set_level(2)
    expected = query.select(["mug"], QueryConfig(mode="level", level=2, top=1))[0]
    assert state.highlight.regions == expected.regions
    state.set_mode("threshold", 0.99)
    expected = query.select(["mug"], QueryConfig(mode="threshold", level=2, threshold=0.99))[0]
    assert state.highlight.regions == expected.regions
    nothing = state.ask("xqzv blorf")
    assert nothing.regions == () and not nothing.gaussians.any() and nothing.primary is None
    assert nothing.reason is None  # threshold mode: no region reached the slider's value
    state.set_mode("auto")
    abstained = state.ask("xqzv blorf")
    assert abstained.regions == () and abstained.reason.startswith("nothing relevant to 'xqzv")
    with pytest.raises(InputError, match="nothing is selected"):
        state.parent()


def test_queries_need_a_text_model_and_a_text(opened):
    field, scene, query = opened
    with pytest.raises(InputError, match="no text model"):
        ViewerState(field, scene.gaussians, None).ask("mug")
    with pytest.raises(InputError, match="type something"):
        ViewerState(field, scene.gaussians, query).ask("   ")
    with pytest.raises(InputError, match="4000 Gaussians, the scene 10"):
        ViewerState(field, scene.gaussians.select(np.arange(10)), query)
    with pytest.raises(InputError, match=r"ViewerConfig\.level"):
        ViewerConfig(level=0).check()


# Picking and the hierarchy ------------------------------------------------------------------


def test_pick_then_climb_and_descend_through_the_clicked_point(state, opened):
    field, scene, _ = opened
    camera, pixel, gaussian = _object_pixel(state, scene)
    assert state.pick(camera, (pixel[0], pixel[1])) is not None
    picked = pick(field, scene.gaussians, camera, pixel)
    assert picked.gaussian == gaussian
    chain = picked.regions
    assert state.highlight.primary == (3, chain[3]) and state.highlight.anchor == gaussian
    np.testing.assert_array_equal(state.highlight.gaussians, field.labels[:, 3] == chain[3])
    state.set_level(1)
    assert state.highlight.primary == (1, chain[1]) and state.level == 1
    assert state.parent().primary == (2, field.parent(1, chain[1])) == (2, chain[2])
    assert state.parent().primary == (3, chain[3])
    with pytest.raises(InputError, match="top of the hierarchy"):
        state.parent()
    assert state.child().primary == (2, chain[2])
    assert state.child().primary == (1, chain[1])
    with pytest.raises(InputError, match="finest level"):
        state.child()
    np.testing.assert_array_equal(state.highlight.gaussians, field.labels[:, 1] == chain[1])


def test_clicks_share_one_pick_index_and_match_the_full_render(state, opened):
    _, scene, _ = opened
    camera = scene.cameras.select([1])
    zeros = torch.zeros(len(scene.gaussians), 1, dtype=torch.float64)
    max_id = render(scene.gaussians, camera, zeros).max_id.numpy()
    index = state.pick_index
    assert len(index) == len(scene.gaussians)
    rng = np.random.default_rng(0)
    height, width = max_id.shape
    for x, y in zip(rng.integers(0, width, 25), rng.integers(0, height, 25)):
        highlight = state.pick(camera, (int(x), int(y)))
        if max_id[y, x] < 0:
            assert highlight is None
        else:
            assert highlight.anchor == max_id[y, x]
    assert state.pick_index is index


def test_siblings_cycle_in_id_order_and_children_default_to_the_largest(state, opened):
    field, scene, _ = opened
    camera, pixel, _ = _object_pixel(state, scene)
    state.set_level(2)
    state.pick(camera, pixel)
    _, region = state.highlight.primary
    siblings = field.children(3, field.parent(2, region)).tolist()
    visited = [region]
    for _ in siblings:
        visited.append(state.sibling().primary[1])
        assert state.highlight.anchor is None and state.highlight.primary[0] == 2
    start = siblings.index(region)
    assert visited == [siblings[(start + k) % len(siblings)] for k in range(len(siblings) + 1)]
    children = field.children(2, visited[-1])
    sizes = field.sizes(1)[children]
    largest = int(children[np.lexsort((children, -sizes))[0]])
    assert state.child().primary == (1, largest)
    objects = state.set_level(3)
    first = objects.primary[1]
    assert state.sibling(-1).primary == (3, (first - 1) % field.region_counts[3])


def test_a_click_on_the_background_keeps_the_highlight(state, opened):
    _, scene, _ = opened
    camera = scene.cameras.select([0])
    far = viewport_camera((1, 0, 0, 0), (0, 0, 1e4), 0.1, 8, 8)  # looking away from the scene
    state.ask("mug")
    before = state.highlight
    assert state.pick(far, (4, 4)) is None and state.highlight is before
    with pytest.raises(InputError, match="outside"):
        state.pick(camera, (int(camera.widths[0]), 0))


# What is drawn --------------------------------------------------------------------------------


def test_colours_dim_everything_outside_the_highlight(state, opened):
    field, scene, query = opened
    base_rgb = scene.gaussians.dc_colors().numpy()
    base_opacity = scene.gaussians.activated_opacities().numpy()
    rgb, opacity = state.colors()
    np.testing.assert_allclose(rgb, base_rgb, rtol=1e-6)
    np.testing.assert_allclose(opacity, base_opacity, rtol=1e-6)
    inside = state.ask("mug").gaussians
    rgb, opacity = state.colors()
    np.testing.assert_allclose(rgb[inside], base_rgb[inside], rtol=1e-6)
    np.testing.assert_allclose(opacity[inside], base_opacity[inside], rtol=1e-6)
    np.testing.assert_allclose(rgb[~inside], 0.3 * base_rgb[~inside], rtol=1e-6)
    np.testing.assert_allclose(opacity[~inside], 0.1 * base_opacity[~inside], rtol=1e-6)
    state.set_color("regions")
    rgb, _ = state.colors()
    expected = region_colors(field.labels[:, 3], seed=0)
    np.testing.assert_allclose(rgb[inside], expected[inside], rtol=1e-6)
    state.set_color("relevancy")
    state.clear()
    rgb, _ = state.colors()
    np.testing.assert_allclose(rgb, relevancy_colors(query.gaussian_relevancy("mug", 3)), rtol=1e-6)
    with pytest.raises(InputError, match=r"ViewerConfig\.color"):
        state.set_color("rainbow")


def test_relevancy_colours_run_from_the_indifference_point_to_one():
    colours = relevancy_colors(np.array([0.0, 0.5, 0.75, 1.0, 2.0]))
    np.testing.assert_allclose(colours[0], colours[1])
    np.testing.assert_allclose(colours[1], [0.19, 0.07, 0.23], rtol=1e-6)
    np.testing.assert_allclose(colours[2], [0.46, 0.99, 0.35], rtol=1e-6)
    np.testing.assert_allclose(colours[3], colours[4])
    np.testing.assert_allclose(colours[3], [0.48, 0.02, 0.01], rtol=1e-6)


def test_the_view_mask_is_the_selection_mask(state, opened):
    _, scene, _ = opened
    camera = scene.cameras.select([1])
    with pytest.raises(InputError, match="nothing is selected"):
        state.view_mask(camera)
    highlight = state.ask("mug")
    view = state.view_mask(camera)
    expected = selection_masks(scene.gaussians, camera, highlight.gaussians)
    assert expected.any()
    np.testing.assert_array_equal(view.mask, expected)
    assert view.picture.shape == (*expected.shape, 3)
    assert (view.picture[view.mask][:, 0] > view.picture[view.mask][:, 1]).all()
    assert view.picture.min() >= 0.0 and view.picture.max() <= 1.0


# Export ---------------------------------------------------------------------------------------


def test_export_writes_the_highlight_with_its_labels(state, opened, tmp_path):
    field, scene, _ = opened
    with pytest.raises(InputError, match="nothing is selected"):
        state.export(tmp_path)
    highlight = state.ask("teddy bear")
    paths = state.export(tmp_path / "out")
    assert [p.name for p in paths] == [
        "teddy-bear.ply",
        "teddy-bear-labels.npy",
        "teddy-bear-indices.npy",
        "teddy-bear.json",
    ]
    index = np.flatnonzero(highlight.gaussians)
    written = read_ply(paths[0])
    torch.testing.assert_close(written.means, scene.gaussians.means[index])
    torch.testing.assert_close(written.sh, scene.gaussians.sh[index])
    labels = np.load(paths[1])
    assert labels.dtype == np.int32 and labels.shape == (index.size, 4)
    np.testing.assert_array_equal(labels, field.labels[index])
    np.testing.assert_array_equal(np.load(paths[2]), index)
    summary = json.loads(paths[3].read_text())
    assert summary["text"] == "teddy bear" and summary["gaussians"] == index.size
    assert [(r["level"], r["region"]) for r in summary["regions"]] == [
        (k, r) for k, r, _ in highlight.regions
    ]
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(p.name for p in paths)


def test_export_to_a_folder_that_cannot_be_written_leaves_nothing(state, tmp_path):
    state.ask("mug")
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(InputError, match="cannot write the selection there") as error:
        state.export(blocker / "out")
    assert str(blocker / "out") in str(error.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    if os.geteuid() != 0:  # root writes anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(InputError, match="Permission denied"):
            state.export(locked)
        assert list(locked.iterdir()) == []


def test_a_failure_part_way_removes_the_files_already_written(state, tmp_path, monkeypatch):
    import thgs.export

    state.ask("mug")

    def fail(path, value, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(thgs.export, "write_json", fail)
    with pytest.raises(InputError, match="No space left on device"):
        state.export(tmp_path / "out")
    assert list((tmp_path / "out").iterdir()) == []


@pytest.mark.parametrize("replace_call", [1, 3, 4])
def test_ctrl_c_during_an_export_leaves_none_of_its_files(
    state, tmp_path, monkeypatch, replace_call
):
    """thgs view's export, interrupted at its first, third or last (the summary's) rename: no
    file of the selection and no temporary is left; the next export writes all four."""
    state.ask("mug")
    real, calls = os.replace, []

    def interrupted(source, target):
        calls.append(os.path.basename(target))
        if len(calls) == replace_call:
            raise KeyboardInterrupt
        real(source, target)

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        state.export(tmp_path / "out")
    monkeypatch.setattr(os, "replace", real)
    assert len(calls) == replace_call and os.listdir(tmp_path / "out") == []
    paths = state.export(tmp_path / "out")
    assert sorted(os.listdir(tmp_path / "out")) == sorted(p.name for p in paths)
