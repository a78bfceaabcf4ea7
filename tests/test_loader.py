"""load_scene: recognising model folders, PLY + source, and what it reports."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
from PIL import Image

from conftest import random_cameras, random_gaussians
from thgs import (
    InputError,
    load_cameras,
    load_scene,
    summarize,
    write_cameras_json,
    write_colmap,
    write_ply,
    write_transforms_json,
)


def make_model(root, iterations=(7000, 30000), cameras=True):
    for iteration in iterations:
        write_ply(
            root / "point_cloud" / f"iteration_{iteration}" / "point_cloud.ply",
            random_gaussians(iteration // 1000, kind="2dgs", sh_degree=0, seed=iteration),
        )
    (root / "point_cloud" / "iteration_99").mkdir()  # an unfinished iteration, no PLY
    if cameras:
        write_cameras_json(root / "cameras.json", random_cameras(4, centred=True))
    return root


def test_model_folder_newest_iteration(tmp_path):
    scene = load_scene(make_model(tmp_path))
    assert len(scene.gaussians) == 30 and scene.gaussians.kind == "2dgs"
    assert scene.ply_path == tmp_path / "point_cloud" / "iteration_30000" / "point_cloud.ply"
    assert scene.cameras is not None and len(scene.cameras) == 4
    assert scene.cameras_path == tmp_path / "cameras.json"
    assert scene.found[0] == f"trained model folder {tmp_path}, iteration 30000"
    assert any("3DGS cameras.json" in line for line in scene.found)


def test_model_folder_chosen_iteration(tmp_path):
    scene = load_scene(make_model(tmp_path), iteration=7000)
    assert len(scene.gaussians) == 7
    with pytest.raises(InputError, match=r"no iteration 5; the folder has \[7000, 30000\]"):
        load_scene(tmp_path, iteration=5)


def test_model_folder_without_cameras(tmp_path):
    scene = load_scene(make_model(tmp_path, cameras=False))
    assert scene.cameras is None and scene.cameras_path is None
    assert "no cameras" in scene.found[-1]


def test_not_a_model_folder(tmp_path):
    with pytest.raises(InputError, match="not a trained model folder") as info:
        load_scene(tmp_path)
    assert str(info.value).startswith(str(tmp_path))
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(InputError, match=r"expected a \.ply file"):
        load_scene(tmp_path / "notes.txt")
    with pytest.raises(InputError, match="no such file"):
        load_scene(tmp_path / "missing.ply")


def test_ply_with_colmap_source(shared_data, tmp_path):
    source = tmp_path / "garden"
    shutil.copytree(shared_data / "colmap_small", source)
    scene = load_scene(shared_data / "ply_3dgs_train1000.ply", source=source, scale=0.25)
    assert len(scene.gaussians) == 1000 and len(scene.cameras) == 23
    assert scene.cameras_path == source / "sparse" / "0"
    assert scene.cameras.widths.tolist() == [250] * 23
    assert any(line.startswith(f"images {source / 'images'} checked") for line in scene.found)
    # the same images under another name, chosen explicitly
    (source / "images").rename(source / "images_4")
    scene = load_scene(
        shared_data / "ply_3dgs_train1000.ply", source=source, images="images_4", scale=0.25
    )
    assert scene.cameras.widths.tolist() == [250] * 23
    # without images the cameras keep the model's resolution, scaled only if asked
    scene = load_scene(shared_data / "ply_3dgs_train1000.ply", source=source)
    assert scene.cameras.widths.tolist() == [1000] * 23
    assert "images not checked" in scene.found[-1]
    with pytest.raises(InputError, match="image folder not found"):
        load_scene(shared_data / "ply_3dgs_train1000.ply", source=source, images="images_8")


def test_model_folder_with_source_overrides_cameras_json(shared_data, tmp_path):
    make_model(tmp_path / "model")
    scene = load_scene(tmp_path / "model", source=shared_data / "colmap_small", scale=0.25)
    assert len(scene.cameras) == 23


def test_transforms_source_checks_images(tmp_path):
    cameras = random_cameras(3, centred=True)
    write_ply(tmp_path / "scene.ply", random_gaussians(20))
    renamed = type(cameras)(
        cameras.viewmats,
        cameras.Ks,
        cameras.widths,
        cameras.heights,
        tuple(f"images/{name}" for name in cameras.names),
    )
    write_transforms_json(tmp_path / "data" / "transforms.json", renamed)
    scene = load_scene(tmp_path / "scene.ply", source=tmp_path / "data")
    assert "images not checked" in scene.found[-1]
    (tmp_path / "data" / "images").mkdir()
    for name, width, height in zip(cameras.names, cameras.widths, cameras.heights):
        Image.new("RGB", (int(width) // 2, int(height) // 2)).save(tmp_path / "data/images" / name)
    with pytest.raises(InputError, match=r"suggests scale 0\.49|suggests scale 0\.5"):
        load_scene(tmp_path / "scene.ply", source=tmp_path / "data")
    scene = load_scene(
        tmp_path / "scene.ply", source=tmp_path / "data" / "transforms.json", scale=0.5
    )
    np.testing.assert_array_equal(scene.cameras.widths.numpy(), cameras.widths.numpy() // 2)


def test_load_cameras_recognises_content_not_names(tmp_path):
    cameras = random_cameras(2, centred=True)
    write_cameras_json(tmp_path / "a.json", cameras)
    write_transforms_json(tmp_path / "b.json", cameras)
    assert load_cameras(tmp_path / "a.json")[2][0].startswith("3DGS cameras.json")
    assert load_cameras(tmp_path / "b.json")[2][0].startswith("transforms.json")
    (tmp_path / "c.json").write_text(json.dumps({"camera": 1}))
    with pytest.raises(InputError, match=r"neither a 3DGS cameras\.json"):
        load_cameras(tmp_path / "c.json")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no cameras found"):
        load_cameras(tmp_path / "empty")


def test_summary_numbers(shared_data):
    scene = load_scene(shared_data / "ply_3dgs_train1000.ply")
    summary = summarize(scene)
    means = scene.gaussians.means.double().numpy()
    opacity = 1 / (1 + np.exp(-scene.gaussians.opacities.double().numpy()))
    assert (summary.count, summary.kind, summary.sh_degree) == (1000, "3dgs", 3)
    np.testing.assert_allclose(summary.bbox_min, means.min(axis=0))
    np.testing.assert_allclose(summary.bbox_max, means.max(axis=0))
    np.testing.assert_allclose(summary.opacity_quantiles[2], np.median(opacity), rtol=1e-6)
    assert summary.low_opacity_share == pytest.approx((opacity < 0.1).mean())
    assert summary.cameras is None


def _moved(cameras, rotation, scale, shift):
    """The same cameras in a world rotated by ``rotation``, scaled by ``scale`` and shifted:
    p' = scale · rotation · p + shift (what nerfstudio's processing does to COLMAP's world)."""
    import torch

    viewmats = cameras.viewmats.clone()
    r = torch.as_tensor(rotation, dtype=viewmats.dtype)
    centres = scale * cameras.centers() @ r.T + torch.as_tensor(shift, dtype=viewmats.dtype)
    viewmats[:, :3, :3] = cameras.viewmats[:, :3, :3] @ r.T
    viewmats[:, :3, 3] = -(viewmats[:, :3, :3] @ centres[:, :, None])[:, :, 0]
    return type(cameras)(viewmats, cameras.Ks, cameras.widths, cameras.heights, cameras.names)


@pytest.mark.parametrize("second", ["sparse", "root"])
def test_two_colmap_models_in_one_folder_must_agree(tmp_path, second):
    """sparse/0 and sparse/ (or the folder itself): read from the first when they describe the
    same cameras, refused naming both and --source when they do not."""
    cameras = random_cameras(5, centred=True)
    data = tmp_path / "data"
    first, other = data / "sparse" / "0", data / "sparse" if second == "sparse" else data
    write_colmap(first, cameras)
    write_colmap(other, cameras)
    _, path, found = load_cameras(data)
    expected = other if second == "root" else first  # the folder itself is read first
    unused = first if second == "root" else other
    assert path == expected and f"{unused} describes the same cameras as {expected}" in found[0]
    moved = cameras.viewmats.clone()
    moved[0, :3, 3] += 0.5
    write_colmap(
        unused, type(cameras)(moved, cameras.Ks, cameras.widths, cameras.heights, cameras.names)
    )
    with pytest.raises(InputError, match="different camera positions") as error:
        load_cameras(data)
    message = str(error.value)
    assert message.startswith(f"{data}: holds two COLMAP models, {expected} and {unused}")
    assert f"--source {expected}" in message and f"--source {unused}" in message


def test_images_do_not_apply_to_a_transforms_json(tmp_path):
    cameras = random_cameras(3, centred=True)
    write_transforms_json(tmp_path / "transforms.json", cameras)
    with pytest.raises(InputError, match=r"images='nope' \(--images\) does not apply"):
        load_cameras(tmp_path, images="nope")


def test_colmap_and_transforms_json_in_one_folder_must_agree(tmp_path):
    from scipy.spatial.transform import Rotation

    cameras = random_cameras(5, centred=True)
    data = tmp_path / "data"
    write_colmap(data / "sparse" / "0", cameras)
    turn = Rotation.from_euler("xyz", [0.3, -1.1, 2.0]).as_matrix()
    write_transforms_json(data / "transforms.json", _moved(cameras, turn, 0.37, [1.0, -2.0, 0.5]))
    # the same capture in nerfstudio's rescaled world: read from COLMAP, and said so
    loaded, path, found = load_cameras(data)
    assert path == data / "sparse" / "0" and "describes the same cameras" in found[0]
    np.testing.assert_allclose(loaded.viewmats.numpy(), cameras.viewmats.numpy(), atol=1e-6)
    # moved cameras, other intrinsics, other images: refused, naming both and the flag
    moved = cameras.viewmats.clone()
    moved[0, :3, 3] += 0.5
    longer = cameras.Ks.clone()
    longer[:, 0, 0] *= 1.01
    for other, what in (
        (type(cameras)(moved, cameras.Ks, cameras.widths, cameras.heights, cameras.names),
         "different camera positions"),
        (type(cameras)(cameras.viewmats, longer, cameras.widths, cameras.heights, cameras.names),
         "different intrinsics"),
        (cameras.select([0, 1, 2, 3]), "different images"),
    ):  # fmt: skip
        write_transforms_json(data / "transforms.json", other)
        with pytest.raises(InputError, match=what) as error:
            load_cameras(data)
        message = str(error.value)
        assert f"--source {data / 'sparse' / '0'}" in message
        assert f"--source {data / 'transforms.json'}" in message
        # either file named explicitly is read as it is
        assert load_cameras(data / "transforms.json")[1] == data / "transforms.json"
        assert load_cameras(data / "sparse" / "0")[1] == data / "sparse" / "0"
