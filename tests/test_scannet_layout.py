"""OpenGaussian's ScanNet scenes as they are on disk (``scannet/<scene>/{color,
transforms_train.json, transforms_test.json, language_features, <scene>_vh_clean_2.labels.ply}``
and the trained model ``output/<scene>`` whose ``cfg_args`` names it): loaded, built and scored
with no extra flags; the Blender split files read to the right matrices; inconsistent input
refused naming the file."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from conftest import run_cli as run
from thgs import InputError, load_cameras, load_scene
from thgs.eval import find_ground_truth
from thgs.guidance import guidance_folder, load_guidance
from thgs.scene import read_cameras_json, read_colmap
from thgs.synthetic import write_opengaussian_scannet

SCENE = "scene0000_00"


@pytest.fixture(scope="module")
def layout(small_dataset, tmp_path_factory) -> Path:
    """The small synthetic dataset laid out as OpenGaussian's ScanNet; returns the root."""
    root = tmp_path_factory.mktemp("opengaussian")
    write_opengaussian_scannet(small_dataset, root, SCENE)
    return root


def same_cameras(ours, theirs) -> None:
    """Same views in the same order: world→camera poses within 1e-6, intrinsics, sizes."""
    assert ours.stems == theirs.stems
    torch.testing.assert_close(ours.viewmats, theirs.viewmats, atol=1e-6, rtol=0)
    torch.testing.assert_close(ours.Ks, theirs.Ks, atol=1e-9, rtol=1e-9)
    assert ours.widths.tolist() == theirs.widths.tolist()
    assert ours.heights.tolist() == theirs.heights.tolist()


# the written layout


def test_the_layout_is_opengaussians(layout, small_dataset):
    data = layout / "scannet" / SCENE
    stems = read_cameras_json(small_dataset / "cameras.json").stems
    assert sorted(p.name for p in (data / "color").iterdir()) == [f"{s}.jpg" for s in stems]
    train = json.loads((data / "transforms_train.json").read_text())
    test = json.loads((data / "transforms_test.json").read_text())
    assert [f["file_path"] for f in train["frames"]] == [f"color/{s}" for s in stems]
    assert [f["file_path"] for f in test["frames"]] == [f"color/{stems[0]}"]  # every 8th of 8
    assert {"w", "h", "fl_x", "fl_y", "cx", "cy"} <= set(train)
    assert (data / "points3d.ply").is_file()
    assert (data / "language_features" / f"{stems[0]}_s.npy").is_file()
    assert (data / f"{SCENE}_vh_clean_2.labels.ply").is_file()
    model = layout / "output" / SCENE
    assert (model / "point_cloud" / "iteration_30000" / "point_cloud.ply").is_file()
    assert "eval=True" in (model / "cfg_args").read_text()


def test_the_layout_loads_with_no_flags(layout, small_dataset, monkeypatch):
    monkeypatch.chdir(layout)
    data = layout / "scannet" / SCENE
    scene = load_scene(f"output/{SCENE}")
    assert scene.source == data and scene.cameras_path == data / "transforms_train.json"
    assert scene.model_source is not None and scene.model_source.folder == data
    assert f"{data / 'transforms_test.json'} not read" in " ".join(scene.found)
    expected = read_cameras_json(small_dataset / "cameras.json")
    assert scene.cameras is not None
    same_cameras(scene.cameras, expected)
    colmap = read_colmap(small_dataset / "sparse" / "0")
    order = [colmap.stems.index(stem) for stem in expected.stems]
    same_cameras(scene.cameras, colmap.select(order))

    # the guidance and the ground truth are where the existing code looks
    assert guidance_folder(f"output/{SCENE}", scene.source) == data / "language_features"
    views = load_guidance(data / "language_features", scene.cameras)
    assert [view.stem for view in views] == list(expected.stems)
    truth = find_ground_truth(data)
    assert truth.available() == ("scannet",) and truth.scene_name == SCENE
    assert truth.path("scannet") == data / f"{SCENE}_vh_clean_2.labels.ply"


@pytest.mark.slow
def test_build_and_eval_score_as_on_the_synthetic_dataset(
    layout, small_dataset, small_field, monkeypatch, capsys
):
    monkeypatch.chdir(layout)
    code, _, err = run(["build", f"output/{SCENE}", "-o", "f.thgs"], capsys)
    assert code == 0, err
    code, _, err = run(["eval", f"scannet/{SCENE}", "f.thgs"], capsys)
    assert code == 0, err
    report = json.loads(Path("f.eval.json").read_text())
    assert report["info"]["ground_truth"]["scannet"] == str(
        Path("scannet") / SCENE / f"{SCENE}_vh_clean_2.labels.ply"
    )
    code, _, err = run(
        [
            *("eval", str(small_dataset), str(small_field)),
            *("--protocol", "scannet"),
            "-o",
            "o.json",
        ],
        capsys,
    )
    assert code == 0, err
    original = json.loads(Path("o.json").read_text())

    def scores(document: dict) -> dict:
        return {r["protocol"]: (r["metrics"], r["items"]) for r in document["results"]}

    assert scores(report).keys() == {"scannet-all"}
    assert scores(report) == scores(original)


# the Blender split files, by hand


def image(path: Path, size: tuple[int, int]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.new("RGB", size, (90, 120, 150)).save(path)


def split(path: Path, frames: list[dict], **shared) -> None:
    path.write_text(json.dumps({**shared, "frames": frames}))


ROTATED = [[0, -1, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]]
"""Camera→world, OpenGL axes: 90° about z, centre (1, 2, 3)."""


def two_frames(folder: Path) -> Path:
    """color/a.png and color/b.jpg (40×30), a transforms_train.json without sizes, a test split
    with a third frame."""
    image(folder / "color" / "a.png", (40, 30))
    image(folder / "color" / "b.jpg", (40, 30))
    image(folder / "color" / "c.jpg", (40, 30))
    split(
        folder / "transforms_train.json",
        [
            {"file_path": "color/a", "transform_matrix": np.eye(4).tolist()},
            {"file_path": "color/b", "transform_matrix": ROTATED, "fl_y": 55.0},
        ],
        fl_x=50.0,
    )
    split(
        folder / "transforms_test.json",
        [{"file_path": "color/c", "transform_matrix": np.eye(4).tolist()}],
        fl_x=50.0,
    )
    return folder


def test_two_hand_made_frames(tmp_path):
    folder = two_frames(tmp_path)
    cameras, path, found = load_cameras(folder)
    assert path == folder / "transforms_train.json"
    assert cameras.names == ("color/a", "color/b")  # the held-out split is not read
    # OpenGL camera→world I: the camera looks down world −z with y up; OpenCV flips y and z
    a = np.diag([1.0, -1.0, -1.0, 1.0])
    # b: R_c2w (OpenCV) = [[0, 1, 0], [1, 0, 0], [0, 0, −1]] (symmetric), t = −Rᵀ(1, 2, 3)
    b = np.array([[0, 1, 0, -2], [1, 0, 0, -1], [0, 0, -1, 3], [0, 0, 0, 1]], dtype=float)
    np.testing.assert_allclose(cameras.viewmats.numpy(), np.stack([a, b]), atol=1e-12)
    np.testing.assert_allclose(
        cameras.Ks.numpy(),
        [[[50, 0, 20], [0, 50, 15], [0, 0, 1]], [[50, 0, 20], [0, 55, 15], [0, 0, 1]]],
    )
    assert cameras.widths.tolist() == [40, 40] and cameras.heights.tolist() == [30, 30]
    assert found[-1] == f"images {folder} checked, 40×30 px"


def test_frames_with_lost_tracking_are_left_out(tmp_path, caplog):
    """ScanNet's −inf poses, as OpenGaussian's scene0200_00 carries them (JSON Infinity)."""
    folder = two_frames(tmp_path)
    document = json.loads((folder / "transforms_train.json").read_text())
    document["frames"][1]["transform_matrix"] = [[float("-inf"), float("inf")] * 2] * 4
    (folder / "transforms_train.json").write_text(json.dumps(document))
    assert "-Infinity" in (folder / "transforms_train.json").read_text()
    cameras, _, found = load_cameras(folder)
    assert cameras.names == ("color/a",)
    assert (
        "1 frames of transforms_train.json left out: their transform_matrix is not finite "
        "(ScanNet's frames with lost tracking)"
    ) in found
    assert "1 frames left out" in caplog.text

    document["frames"][0]["transform_matrix"] = document["frames"][1]["transform_matrix"]
    (folder / "transforms_train.json").write_text(json.dumps(document))
    with pytest.raises(InputError) as caught:
        load_cameras(folder)
    assert str(caught.value) == (
        f"{folder / 'transforms_train.json'}: all 2 frames have NaN or infinite poses"
    )


# bad input


def test_frames_naming_missing_images(tmp_path):
    folder = two_frames(tmp_path)
    (folder / "color" / "b.jpg").unlink()
    train = folder / "transforms_train.json"
    # without w, h the size of its image is needed
    with pytest.raises(InputError) as caught:
        load_cameras(folder)
    assert str(caught.value) == (
        f"{train}: frame 1 ('color/b') gives no image size (w, h) and its image "
        f"{folder / 'color' / 'b.png'} does not exist"
    )
    split(train, json.loads(train.read_text())["frames"], fl_x=50.0, w=40, h=30)
    with pytest.raises(InputError) as caught:
        load_cameras(folder)
    assert str(caught.value) == (
        f"{folder / 'transforms_train.json'}: 1 of 2 frames name images that do not exist "
        f"(first: ['color/b'], looked for under {folder} as written or with .png, .jpg, …); "
        "restore them or remove those frames"
    )


def test_transforms_json_beside_the_split(tmp_path):
    folder = two_frames(tmp_path)
    whole = json.loads((folder / "transforms_train.json").read_text())
    whole["frames"].append({"file_path": "color/c", "transform_matrix": np.eye(4).tolist()})
    (folder / "transforms.json").write_text(json.dumps(whole))
    # the same cameras, and more: the train split is read
    cameras, path, found = load_cameras(folder)
    assert path == folder / "transforms_train.json" and len(cameras) == 2
    assert f"{folder / 'transforms.json'} describes the same cameras; reading " in " ".join(found)

    whole["frames"][1]["fl_y"] = 80.0
    (folder / "transforms.json").write_text(json.dumps(whole))
    with pytest.raises(InputError) as caught:
        load_cameras(folder)
    assert str(caught.value) == (
        f"{folder}: holds transforms.json and transforms_train.json, and they disagree: "
        "different intrinsics (focal lengths or principal points); choose one with --source "
        f"{folder / 'transforms.json'} or --source {folder / 'transforms_train.json'}"
    )

    del whole["frames"][1]
    (folder / "transforms.json").write_text(json.dumps(whole))
    with pytest.raises(
        InputError, match=r"1 train frames are not in transforms.json \(e.g. \['b'\]"
    ):
        load_cameras(folder)


def test_a_split_file_given_itself_is_read_as_it_is(tmp_path):
    """Named as the source, transforms_train.json is one transforms.json: no image is needed."""
    folder = two_frames(tmp_path)
    shutil.rmtree(folder / "color")
    split(
        folder / "transforms_train.json",
        [{"file_path": "color/a", "transform_matrix": np.eye(4).tolist()}],
        fl_x=50.0,
        w=40,
        h=30,
    )
    cameras, path, found = load_cameras(folder / "transforms_train.json")
    assert path == folder / "transforms_train.json" and cameras.names == ("color/a",)
    assert found == [
        f"transforms.json {path} (1 frames)",
        "images not checked (none found), 40×30 px from the camera file",
    ]
    with pytest.raises(InputError, match="1 of 1 frames name images that do not exist"):
        load_cameras(folder)


def test_the_writer_refuses_what_it_cannot_lay_out(small_dataset, tmp_path):
    with pytest.raises(InputError) as caught:
        write_opengaussian_scannet(tmp_path, tmp_path / "out")
    assert str(caught.value) == f"{tmp_path}: not a synthetic dataset (thgs synth): no cameras.json"
    taken = tmp_path / "root" / "output" / SCENE
    taken.mkdir(parents=True)
    (taken / "keep.txt").write_text("mine")
    with pytest.raises(InputError, match="already exists and is not empty"):
        write_opengaussian_scannet(small_dataset, tmp_path / "root")
    assert not (tmp_path / "root" / "scannet").exists()  # nothing half-written
