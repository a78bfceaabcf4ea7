"""Camera files: hand-written files in each format project known points to hand-computed pixels;
one camera set written in every format reads back the same; the real COLMAP sample; bad files."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pycolmap
import pytest
import torch
from PIL import Image

from conftest import random_cameras
from test_cameras import HAND_DEPTHS, HAND_PIXELS, HAND_POINTS
from thgs import (
    InputError,
    read_cameras_json,
    read_colmap,
    read_transforms_json,
    write_cameras_json,
    write_colmap,
    write_transforms_json,
)

# The camera of test_cameras.hand_camera, encoded by hand in each format.
# World→camera rotation R = [[0,−1,0],[0,0,−1],[1,0,0]] is the quaternion (w,x,y,z) = ½(1,1,−1,1).
COLMAP_CAMERAS = "1 PINHOLE 320 240 100 110 160 120\n2 SIMPLE_PINHOLE 320 240 100 160 120\n"
COLMAP_IMAGES = "1 0.5 0.5 -0.5 0.5 0 0 5 1 hand.png\n\n2 0.5 0.5 -0.5 0.5 0 0 5 2 simple.png\n\n"
CAMERAS_JSON = [
    {
        "id": 0,
        "img_name": "hand",
        "width": 320,
        "height": 240,
        "position": [-5, 0, 0],
        "rotation": [[0, 0, 1], [-1, 0, 0], [0, -1, 0]],
        "fy": 110,
        "fx": 100,
    }
]
# camera→world in OpenGL axes: the OpenCV one with its y and z columns negated
TRANSFORM_MATRIX = [[0, 0, -1, -5], [-1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 1]]


def assert_projects_by_hand(cameras, index=0, fy=110.0):
    pixels, depths = cameras.project(torch.tensor(HAND_POINTS))
    expected = HAND_PIXELS.copy()
    expected[:, 1] = 120 + (HAND_PIXELS[:, 1] - 120) * fy / 110
    np.testing.assert_allclose(pixels[index].numpy(), expected, atol=1e-9)
    np.testing.assert_allclose(depths[index].numpy(), HAND_DEPTHS, atol=1e-9)


@pytest.mark.parametrize("text_format", [True, False])
def test_colmap_by_hand(tmp_path, text_format):
    (tmp_path / "cameras.txt").write_text(COLMAP_CAMERAS)
    (tmp_path / "images.txt").write_text(COLMAP_IMAGES)
    (tmp_path / "points3D.txt").write_text("")
    model = tmp_path
    if not text_format:  # the same model converted to binary by pycolmap itself
        model = tmp_path / "bin"
        model.mkdir()
        pycolmap.Reconstruction(str(tmp_path)).write_binary(str(model))
    cameras = read_colmap(model)
    assert cameras.names == ("hand.png", "simple.png")
    assert_projects_by_hand(cameras, 0)
    assert_projects_by_hand(cameras, 1, fy=100.0)
    assert cameras.widths.tolist() == [320, 320] and cameras.heights.tolist() == [240, 240]


def test_cameras_json_by_hand(tmp_path):
    (tmp_path / "cameras.json").write_text(json.dumps(CAMERAS_JSON))
    cameras = read_cameras_json(tmp_path / "cameras.json")
    assert cameras.names == ("hand",)
    assert_projects_by_hand(cameras)


def test_transforms_json_by_hand(tmp_path):
    document = {
        "fl_x": 100,
        "fl_y": 110,
        "cx": 160,
        "cy": 120,
        "w": 320,
        "h": 240,
        "frames": [{"file_path": "./images/hand.png", "transform_matrix": TRANSFORM_MATRIX}],
    }
    (tmp_path / "transforms.json").write_text(json.dumps(document))
    cameras = read_transforms_json(tmp_path / "transforms.json")
    assert cameras.names == ("images/hand.png",)
    assert_projects_by_hand(cameras)


def test_transforms_json_instant_ngp_style(tmp_path):
    """Blender/instant-ngp: FoV for focal, size from the image, file path without extension."""
    (tmp_path / "train").mkdir()
    Image.new("RGB", (320, 240)).save(tmp_path / "train" / "r_0.png")
    document = {
        "camera_angle_x": 2 * math.atan(160 / 100),
        "frames": [{"file_path": "./train/r_0", "transform_matrix": TRANSFORM_MATRIX}],
    }
    (tmp_path / "transforms.json").write_text(json.dumps(document))
    cameras = read_transforms_json(tmp_path / "transforms.json")
    assert (int(cameras.widths[0]), int(cameras.heights[0])) == (320, 240)
    assert_projects_by_hand(cameras, fy=100.0)  # fl_y = fl_x without camera_angle_y


def test_transforms_json_per_frame_intrinsics_and_applied_transform(tmp_path):
    applied = [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0]]  # nerfstudio's COLMAP → world rotation
    colmap_to_ns = np.eye(4)
    colmap_to_ns[:3] = applied
    document = {
        "fl_x": 100,
        "fl_y": 110,
        "cx": 160,
        "cy": 120,
        "w": 320,
        "h": 240,
        "applied_transform": applied,
        "frames": [
            {"file_path": "a.png", "transform_matrix": (colmap_to_ns @ TRANSFORM_MATRIX).tolist()},
            {"file_path": "b.png", "transform_matrix": TRANSFORM_MATRIX, "fl_y": 100},
        ],
    }
    (tmp_path / "transforms.json").write_text(json.dumps(document))
    undone = read_transforms_json(tmp_path / "transforms.json", undo_applied_transform=True)
    assert_projects_by_hand(undone, 0)
    kept = read_transforms_json(tmp_path / "transforms.json")
    torch.testing.assert_close(
        kept.viewmats[1], undone.viewmats[1] @ torch.tensor(np.linalg.inv(colmap_to_ns))
    )
    assert float(kept.Ks[1, 1, 1]) == 100.0 and float(kept.Ks[0, 1, 1]) == 110.0


def assert_same_cameras(a, b, *, by_stem=False):
    torch.testing.assert_close(a.viewmats, b.viewmats, atol=1e-9, rtol=0)
    torch.testing.assert_close(a.Ks, b.Ks, atol=1e-9, rtol=1e-12)
    assert a.widths.tolist() == b.widths.tolist() and a.heights.tolist() == b.heights.tolist()
    assert (a.stems == b.stems) if by_stem else (a.names == b.names)


def test_one_camera_set_in_every_format(tmp_path):
    cameras = random_cameras(9, centred=True, seed=4)
    write_colmap(tmp_path / "bin", cameras)
    write_colmap(tmp_path / "txt", cameras, text=True)
    write_cameras_json(tmp_path / "cameras.json", cameras)
    write_transforms_json(tmp_path / "transforms.json", cameras)
    assert sorted(p.name for p in (tmp_path / "txt").iterdir() if p.suffix == ".txt") == [
        "cameras.txt",
        "frames.txt",
        "images.txt",
        "points3D.txt",
        "rigs.txt",
    ]
    assert_same_cameras(read_colmap(tmp_path / "bin"), cameras)
    assert_same_cameras(read_colmap(tmp_path / "txt"), cameras)
    assert_same_cameras(read_transforms_json(tmp_path / "transforms.json"), cameras)
    assert_same_cameras(read_cameras_json(tmp_path / "cameras.json"), cameras, by_stem=True)


def test_off_centre_principal_points_round_trip(tmp_path):
    cameras = random_cameras(5, seed=7)
    write_colmap(tmp_path / "sparse", cameras)
    write_transforms_json(tmp_path / "transforms.json", cameras)
    assert_same_cameras(read_colmap(tmp_path / "sparse"), cameras)
    assert_same_cameras(read_transforms_json(tmp_path / "transforms.json"), cameras)
    with pytest.raises(InputError, match="cannot store it"):
        write_cameras_json(tmp_path / "cameras.json", cameras)
    assert not (tmp_path / "cameras.json").exists()


def test_shared_intrinsics_written_once(tmp_path):
    cameras = random_cameras(3, centred=True)
    same = cameras.resized([300] * 3, [200] * 3)
    same = type(same)(
        same.viewmats, same.Ks[[0, 0, 0]].clone(), same.widths, same.heights, same.names
    )
    write_transforms_json(tmp_path / "transforms.json", same)
    document = json.loads((tmp_path / "transforms.json").read_text())
    assert document["w"] == 300 and "fl_x" not in document["frames"][0]
    assert_same_cameras(read_transforms_json(tmp_path / "transforms.json"), same)


# --- the real COLMAP sample ---------------------------------------------------------------------

# Image sizes on disk, from SOURCE.txt of colmap_small (original 1000 × H, downscaled 4×).
SAMPLE_HEIGHTS = {
    "DSC_5283": 165,
    "DSC_5285": 164,
    "DSC_5288": 166,
    "DSC_5291": 166,
    "DSC_5299": 165,
    "DSC_5305": 164,
}


def test_real_colmap_full_resolution_matches_colmap_keypoints(shared_data):
    sparse = shared_data / "colmap_small" / "sparse" / "0"
    cameras = read_colmap(sparse)
    assert len(cameras) == 23 and cameras.names[0] == "DSC_5283.jpg"
    assert cameras.widths.tolist() == [1000] * 23
    assert 656 <= int(cameras.heights.min()) and int(cameras.heights.max()) <= 662
    reconstruction = pycolmap.Reconstruction(str(sparse))
    errors = []
    for i, name in enumerate(cameras.names):
        image = reconstruction.find_image_with_name(name)
        observed = [
            (p.xy, reconstruction.points3D[p.point3D_id].xyz)
            for p in image.points2D
            if p.has_point3D()
        ]
        keypoints = np.array([xy for xy, _ in observed])
        points = np.array([xyz for _, xyz in observed])
        pixels, depths = cameras.select([i]).project(torch.tensor(points))
        assert bool((depths > 0).all())
        # pycolmap's own projection is the reference for the pose and intrinsics conventions
        reference = np.array([image.project_point(xyz) for xyz in points])
        np.testing.assert_allclose(pixels[0].numpy(), reference, atol=1e-6)
        errors.append(np.linalg.norm(pixels[0].numpy() - keypoints, axis=1))
    errors = np.concatenate(errors)
    assert len(errors) == 5931  # every observation of the model
    assert errors.mean() < 0.5 and np.median(errors) < 0.5  # the detected keypoints


def test_real_colmap_downscaled_images(shared_data):
    root = shared_data / "colmap_small"
    full = read_colmap(root / "sparse" / "0")
    cameras = read_colmap(root / "sparse" / "0", images_dir=root / "images", scale=0.25)
    assert cameras.widths.tolist() == [250] * 23
    heights = dict(zip(cameras.stems, cameras.heights.tolist()))
    assert {stem: heights[stem] for stem in SAMPLE_HEIGHTS} == SAMPLE_HEIGHTS
    # intrinsics scale per axis by image size / camera size
    sy = cameras.heights.double() / full.heights.double()
    torch.testing.assert_close(cameras.Ks[:, 0, 0], full.Ks[:, 0, 0] * 0.25)
    torch.testing.assert_close(cameras.Ks[:, 1, 2], full.Ks[:, 1, 2] * sy)
    with pytest.raises(InputError, match=r"suggests scale 0\.25") as info:
        read_colmap(root / "sparse" / "0", images_dir=root / "images")
    assert "DSC_5283.jpg" in str(info.value)


# --- bad input -----------------------------------------------------------------------------------


def test_colmap_bad_input(tmp_path, shared_data):
    with pytest.raises(InputError, match="COLMAP model folder not found"):
        read_colmap(tmp_path / "nowhere")
    (tmp_path / "cameras.txt").write_text(COLMAP_CAMERAS)
    with pytest.raises(InputError, match="not a COLMAP model"):
        read_colmap(tmp_path)
    # a fisheye camera model (perspective models with distortion are read: test_distortion.py)
    (tmp_path / "cameras.txt").write_text(
        "1 OPENCV_FISHEYE 320 240 100 110 160 120 0.1 0 0 0\n2 SIMPLE_PINHOLE 320 240 100 160 120\n"
    )
    (tmp_path / "images.txt").write_text(COLMAP_IMAGES)
    (tmp_path / "points3D.txt").write_text("")
    with pytest.raises(InputError, match=r"OPENCV_FISHEYE model.*image_undistorter") as info:
        read_colmap(tmp_path)
    assert str(info.value).startswith(str(tmp_path))
    # a truncated binary file
    broken = tmp_path / "broken"
    broken.mkdir()
    sample = shared_data / "colmap_small" / "sparse" / "0"
    for name in ("cameras.bin", "points3D.bin"):
        (broken / name).write_bytes((sample / name).read_bytes())
    (broken / "images.bin").write_bytes((sample / "images.bin").read_bytes()[:1000])
    with pytest.raises(
        InputError,
        match=r"images\.bin: the COLMAP binary file is truncated or corrupt: entry 1 of 23 runs "
        r"past the end of the file \(1000 bytes\)$",
    ):
        read_colmap(broken)
    (broken / "cameras.bin").write_bytes(b"")
    with pytest.raises(InputError, match="empty or truncated") as info:
        read_colmap(broken)
    assert str(info.value).startswith(str(broken / "cameras.bin"))
    # text files with no image at all
    (tmp_path / "images.txt").write_text("# no images\n")
    (tmp_path / "cameras.txt").write_text(COLMAP_CAMERAS)
    with pytest.raises(InputError, match="no registered image"):
        read_colmap(tmp_path)


@pytest.mark.parametrize("name", ["cameras.bin", "images.bin", "points3D.bin"])
def test_colmap_truncated_binary_files(tmp_path, shared_data, name):
    """Every cut of a binary model file is refused naming it, before pycolmap reads garbage ids
    ("Rig with ID 1729189376 does not exist") or never returns (images.bin cut after 9 bytes,
    points3D.bin after 64); so are bytes after the last entry and an unknown camera model."""
    sample = shared_data / "colmap_small" / "sparse" / "0"
    data = (sample / name).read_bytes()
    counts = {"cameras.bin": 23, "images.bin": 23, "points3D.bin": 1443}
    for cut in (9, 20, 64, 1000, len(data) // 2, len(data) - 1):
        folder = tmp_path / f"cut{cut}"
        shutil.copytree(sample, folder)
        (folder / name).write_bytes(data[:cut])
        with pytest.raises(
            InputError,
            match=rf"^{folder / name}: the COLMAP binary file is truncated or corrupt: entry "
            rf"\d+ of {counts[name]} runs past the end of the file \({cut} bytes\)$",
        ):
            read_colmap(folder)
    folder = tmp_path / "longer"
    shutil.copytree(sample, folder)
    (folder / name).write_bytes(data + b"\0" * 5)
    with pytest.raises(
        InputError,
        match=rf"^{folder / name}: the COLMAP binary file is corrupt: 5 bytes follow its "
        rf"{counts[name]} entries$",
    ):
        read_colmap(folder)
    if name == "cameras.bin":
        corrupt = bytearray(data)
        corrupt[8 + 4 : 8 + 8] = (99).to_bytes(4, "little")  # the first camera's model id
        (folder / name).write_bytes(bytes(corrupt))
        with pytest.raises(InputError, match=r"entry 1 of 23 has unknown camera model id 99$"):
            read_colmap(folder)


def test_image_names_that_do_not_match(tmp_path, shared_data):
    images = tmp_path / "images"
    images.mkdir()
    for path in sorted((shared_data / "colmap_small" / "images").iterdir())[:20]:
        (images / path.name).write_bytes(path.read_bytes())
    (images / "DSC_5304.jpg").write_bytes(b"not an image")
    sparse = shared_data / "colmap_small" / "sparse" / "0"
    with pytest.raises(
        InputError, match=r"2 of 23 camera images are missing .first: \['DSC_5303.jpg', 'DSC_5305"
    ):
        read_colmap(sparse, images_dir=images, scale=0.25)
    (images / "DSC_5303.jpg").write_bytes(b"")
    (images / "DSC_5305.jpg").write_bytes(b"")
    with pytest.raises(InputError, match="not a readable image") as info:
        read_colmap(sparse, images_dir=images, scale=0.25)
    assert "DSC_530" in str(info.value)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("", "empty"),
        ("[{", "not valid JSON"),
        ("{}", "expected a non-empty JSON list"),
        ("[]", "expected a non-empty JSON list"),
        (
            json.dumps([{k: v for k, v in CAMERAS_JSON[0].items() if k != "fx"}]),
            r"camera 0 \('hand'\) has no 'fx'",
        ),
        (json.dumps([{**CAMERAS_JSON[0], "fy": "big"}]), "'fy' is 'big', not a number"),
        (json.dumps([{**CAMERAS_JSON[0], "position": [0, 0]}]), "'position' has shape"),
        (
            json.dumps([{**CAMERAS_JSON[0], "rotation": [[1, 0, 0], [0, 1, 0], [0, 0, 2]]}]),
            "not a proper rotation",
        ),
        (json.dumps([{**CAMERAS_JSON[0], "width": 0}]), "not positive integers"),
        (
            '[{"id": 0, "img_name": "a", "width": 4, "height": 4, "position": [NaN, 0, 0], '
            '"rotation": [[1,0,0],[0,1,0],[0,0,1]], "fx": 1, "fy": 1}]',
            "NaN or infinite",
        ),
        (json.dumps([CAMERAS_JSON[0], CAMERAS_JSON[0]]), "not unique"),
    ],
)
def test_cameras_json_bad_input(tmp_path, content, message):
    path = tmp_path / "cameras.json"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as info:
        read_cameras_json(path)
    assert str(info.value).startswith(f"{path}: ")


def transforms(**changes):
    frame = {"file_path": "a.png", "transform_matrix": TRANSFORM_MATRIX}
    document = {"fl_x": 100, "w": 320, "h": 240, "frames": [frame]}
    frame.update(changes.pop("frame", {}))
    document.update(changes)
    return json.dumps(document)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ('{"frames": []}', "non-empty 'frames'"),
        (transforms(k4=0.05), "k4 = 0.05 on a perspective camera"),
        (transforms(camera_model="OPENCV_FISHEYE"), "'OPENCV_FISHEYE' is not a perspective"),
        (transforms(is_fisheye=True), "is_fisheye is true: fisheye lenses are not read"),
        (
            transforms(
                frame={"transform_matrix": [[2, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}
            ),
            "not a rigid",
        ),
        (transforms(frame={"transform_matrix": [[1, 0, 0], [0, 1, 0]]}), "has shape"),
        (transforms(fl_x=float("nan")), "'fl_x' is nan"),
        (
            json.dumps(
                {
                    "frames": [{"file_path": "missing", "transform_matrix": TRANSFORM_MATRIX}],
                    "camera_angle_x": 1.0,
                }
            ),
            "gives no image size .* does not exist",
        ),
        (
            json.dumps(
                {
                    "w": 3,
                    "h": 3,
                    "frames": [{"file_path": "a.png", "transform_matrix": TRANSFORM_MATRIX}],
                }
            ),
            "neither 'fl_x' nor 'camera_angle_x'",
        ),
        (transforms(frame={"file_path": 3}), "frame 0 has no 'file_path'"),
    ],
)
def test_transforms_json_bad_input(tmp_path, content, message):
    path = tmp_path / "transforms.json"
    path.write_text(content)
    with pytest.raises(InputError, match=message) as info:
        read_transforms_json(path)
    assert str(info.value).startswith(f"{path}")


def test_undo_without_applied_transform_is_refused(tmp_path):
    path = tmp_path / "transforms.json"
    path.write_text(transforms())
    with pytest.raises(InputError, match="no applied_transform"):
        read_transforms_json(path, undo_applied_transform=True)
