"""Lens distortion: distorted COLMAP and transforms.json cameras become the pinhole cameras their
images are undistorted into, and masks made on the distorted image files are warped into them.

Known answers: OpenCV's distortion model written out by hand (the fox capture's coefficients), and
a synthetic round trip: a label picture defined on the pinhole camera's rays is "photographed"
through the lens (each distorted pixel takes the label of its undistorted ray, found with
cv2.undistortPointsIter), saved as LangSplat masks, read back through the COLMAP reader and
load_guidance, and compared with the same picture drawn directly on the pinhole camera.
"""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch
from PIL import Image

from thgs import InputError, load_cameras, read_colmap, read_transforms_json
from thgs.guidance import ViewGuidance, load_guidance, write_view_guidance
from thgs.guidance.preprocess import image_jobs
from thgs.scene import write_cameras_json, write_colmap, write_transforms_json
from thgs.scene.distortion import (
    pinhole_camera,
    undistort_image,
    undistort_labels,
    undistortion_map,
)

cv2 = pytest.importorskip("cv2", reason="opencv-python-headless (a core dependency) is missing")

# instant-ngp's data/nerf/fox/transforms.json: a phone's lens, OpenCV's k1 k2 p1 p2
FOX = {
    "camera_angle_x": 0.7481849417937728,
    "camera_angle_y": 1.2193576119562444,
    "fl_x": 1375.52,
    "fl_y": 1374.49,
    "k1": 0.0578421,
    "k2": -0.0805099,
    "p1": -0.000980296,
    "p2": 0.00015575,
    "cx": 554.558,
    "cy": 965.268,
    "w": 1080.0,
    "h": 1920.0,
    "aabb_scale": 4,
}
FOX_FRAME = [
    [0.8926439112348871, 0.08799600283226543, 0.4420900262071262, 3.168359405609479],
    [0.4464189982715247, -0.03675452191179031, -0.8940689141475064, -5.4794898611466945],
    [-0.062425682580756266, 0.995442519072023, -0.07209178487538156, -0.9791660699008925],
    [0.0, 0.0, 0.0, 1.0],
]


def distort_by_hand(x, y, k1, k2, p1, p2):
    """OpenCV's (and COLMAP's OPENCV) model on normalised coordinates, written out."""
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2 * r2
    return (
        x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x),
        y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y,
    )


def write_fox(tmp_path, frames=2):
    document = {
        **FOX,
        "frames": [
            {
                "file_path": f"images/{i + 1:04d}.jpg",
                "sharpness": 30.0,
                "transform_matrix": FOX_FRAME,
            }
            for i in range(frames)
        ],
    }
    path = tmp_path / "transforms.json"
    path.write_text(json.dumps(document))
    return path


def test_fox_transforms_json_is_read_as_its_undistorted_pinhole(tmp_path):
    cameras = read_transforms_json(write_fox(tmp_path))
    assert cameras.distortion is not None
    np.testing.assert_allclose(
        cameras.distortion.coeffs[0].numpy(),
        [0.0578421, -0.0805099, -0.000980296, 0.00015575, 0, 0, 0, 0],
    )
    assert cameras.distortion.widths.tolist() == [1080, 1080]
    assert cameras.distortion.heights.tolist() == [1920, 1920]
    width, height = int(cameras.widths[0]), int(cameras.heights[0])
    assert 1000 < width < 1080 and 1800 < height < 1920  # the valid region of the undistortion
    # a world point seen by the camera: its pinhole pixel, looked up in the undistortion map,
    # lands where the lens model by hand puts it in the distorted file
    mapping = cameras.undistortion_map(0)
    assert mapping.shape == (height, width, 2)
    viewmat = cameras.viewmats[0].numpy()
    for depth, (ox, oy) in [(4.0, (0.1, -0.2)), (6.0, (-0.25, 0.4)), (5.0, (0.0, 0.0))]:
        point_cam = np.array([ox * depth, oy * depth, depth])
        world = np.linalg.solve(viewmat[:3, :3], point_cam - viewmat[:3, 3])
        pixels, _ = cameras.project(torch.tensor(world[None]))
        u, v = pixels[0, 0].numpy()
        xd, yd = distort_by_hand(ox, oy, *[FOX[k] for k in ("k1", "k2", "p1", "p2")])
        expected = np.array([FOX["fl_x"] * xd + FOX["cx"], FOX["fl_y"] * yd + FOX["cy"]])
        # the map is sampled at pixel centres: evaluate it exactly at this point's pixel
        K_pin = cameras.Ks[0].numpy()
        exact = undistortion_map(
            cameras.distortion.Ks[0].numpy(),
            cameras.distortion.coeffs[0].numpy(),
            K_pin - np.array([[0, 0, u - 0.5], [0, 0, v - 0.5], [0, 0, 0]]),
            1,
            1,
        )
        np.testing.assert_allclose(exact[0, 0], expected, atol=2e-3)


def test_distortion_the_readers_refuse(tmp_path):
    path = tmp_path / "transforms.json"
    path.write_text(
        json.dumps(
            {**FOX, "k4": 0.01, "frames": [{"file_path": "a.jpg", "transform_matrix": FOX_FRAME}]}
        )
    )
    with pytest.raises(InputError, match=r"k4 = 0\.01 on a perspective camera") as info:
        read_transforms_json(path)
    assert str(info.value).startswith(str(path))
    path.write_text(
        json.dumps(
            {
                **FOX,
                "is_fisheye": True,
                "camera_model": "PINHOLE",
                "frames": [{"file_path": "a.jpg", "transform_matrix": FOX_FRAME}],
            }
        )
    )
    with pytest.raises(
        InputError, match=r"is_fisheye is true \(camera_model 'PINHOLE' says otherwise\)"
    ):
        read_transforms_json(path)
    path.write_text(
        json.dumps(
            {
                **FOX,
                "camera_model": "OPENCV_FISHEYE",
                "frames": json.loads(path.read_text())["frames"],
            }
        )
    )
    with pytest.raises(InputError, match="'OPENCV_FISHEYE' is not a perspective model"):
        read_transforms_json(path)


@pytest.mark.parametrize("k1", [50.0, -5.0, -0.9])
def test_a_lens_that_cannot_be_undone_over_its_image_is_refused(tmp_path, k1):
    """k1 = 50 (OpenCV's inversion diverges), −5 and −0.9 (the radius folds back inside the
    frame): refused naming the file and the camera, where they were read as 57 objects."""
    path = tmp_path / "transforms.json"
    frames = [{"file_path": "images/a.jpg", "transform_matrix": FOX_FRAME}]
    path.write_text(json.dumps({**FOX, "k1": k1, "frames": frames}))
    with pytest.raises(InputError, match=r"cannot be undone over the 1080×1920 image") as info:
        read_transforms_json(path)
    assert str(info.value).startswith(f"{path}, camera images/a.jpg: lens distortion")


def test_writers_refuse_distorted_cameras(tmp_path):
    cameras = read_transforms_json(write_fox(tmp_path))
    for write, name in [
        (write_colmap, "sparse"),
        (write_transforms_json, "out.json"),
        (write_cameras_json, "cameras.json"),
    ]:
        with pytest.raises(InputError, match="lens distortion") as info:
            write(tmp_path / name, cameras)
        assert str(info.value).startswith(str(tmp_path / name))
    plain = replace(cameras, distortion=None)
    write_transforms_json(tmp_path / "out.json", plain)
    assert read_transforms_json(tmp_path / "out.json").distortion is None


def label_picture(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Labels on normalised image coordinates: rings and a diagonal split, −1 in the corners."""
    r = np.hypot(x - 0.05, y + 0.03)
    labels = np.floor(r / 0.12).astype(np.int64) * 2 + (x + 0.6 * y > 0)
    return np.where(r > 0.75, -1, labels)


# COLMAP models whose images are distorted, with the coefficients each model carries
DISTORTED_MODELS = {
    "SIMPLE_RADIAL": ("f cx cy k", [300.0, 161.3, 118.7, -0.12]),
    "RADIAL": ("f cx cy k1 k2", [300.0, 161.3, 118.7, 0.09, -0.05]),
    "OPENCV": ("fx fy cx cy k1 k2 p1 p2", [300.0, 305.0, 161.3, 118.7, -0.2, 0.05, 0.002, -0.003]),
    "FULL_OPENCV": (
        "fx fy cx cy k1 k2 p1 p2 k3 k4 k5 k6",
        [300.0, 305.0, 161.3, 118.7, 0.15, -0.02, 0.001, 0.002, 0.01, 0.02, 0.0, 0.001],
    ),
}
WIDTH, HEIGHT = 320, 240


def write_distorted_scene(root, model, params):
    """A COLMAP model of one distorted camera, its label picture photographed through the lens,
    and the picture as LangSplat masks (4 levels, the same ids at each)."""
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    (sparse / "cameras.txt").write_text(
        f"1 {model} {WIDTH} {HEIGHT} {' '.join(str(p) for p in params)}\n"
    )
    (sparse / "images.txt").write_text("1 1 0 0 0 0 0 0 1 view.png\n\n")
    (sparse / "points3D.txt").write_text("")
    cameras = read_colmap(sparse)
    K = cameras.distortion.Ks[0].numpy()
    coeffs = cameras.distortion.coeffs[0].numpy()
    # every distorted pixel centre → its undistorted ray (OpenCV, pixel centres at integers)
    cols, rows = np.meshgrid(np.arange(WIDTH), np.arange(HEIGHT))
    centres = np.stack([cols, rows], -1).reshape(-1, 1, 2).astype(np.float64)
    K_cv = K.copy()
    K_cv[:2, 2] -= 0.5
    rays = cv2.undistortPointsIter(
        centres,
        K_cv,
        coeffs,
        None,
        None,
        (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12),
    ).reshape(HEIGHT, WIDTH, 2)
    ids = label_picture(rays[..., 0], rays[..., 1])
    n = int(ids.max()) + 1
    segments = np.stack([np.where(ids < 0, -1, ids + level * n) for level in range(4)])
    features = np.ones((4 * n, 8), dtype=np.float32)
    (root / "language_features").mkdir()
    write_view_guidance(root / "language_features", ViewGuidance("view", segments, features))
    images = root / "images"
    images.mkdir()
    Image.fromarray(((ids + 1) * 9 % 256).astype(np.uint8)).save(images / "view.png")
    return n


def pinhole_truth(cameras):
    """The label picture drawn directly on the pinhole camera."""
    K = cameras.Ks[0].numpy()
    cols, rows = np.meshgrid(np.arange(int(cameras.widths[0])), np.arange(int(cameras.heights[0])))
    x = (cols + 0.5 - K[0, 2]) / K[0, 0]
    y = (rows + 0.5 - K[1, 2]) / K[1, 1]
    return label_picture(x, y)


@pytest.mark.parametrize("model", sorted(DISTORTED_MODELS))
def test_masks_of_distorted_images_match_the_pinhole_picture(tmp_path, model):
    n = write_distorted_scene(tmp_path, model, DISTORTED_MODELS[model][1])
    cameras, _, _ = load_cameras(tmp_path)
    assert cameras.distortion is not None
    assert (int(cameras.widths[0]), int(cameras.heights[0])) != (WIDTH, HEIGHT)
    [view] = load_guidance(tmp_path / "language_features", cameras)
    assert (view.height, view.width) == (int(cameras.heights[0]), int(cameras.widths[0]))
    truth = pinhole_truth(cameras)
    for level in range(4):
        expected = np.where(truth < 0, -1, truth + level * n)
        agreement = (view.segments[level] == expected).mean()
        # nearest neighbour moves a boundary by at most about half a pixel: only boundary
        # pixels may differ (the picture has ~2,000 boundary pixels of ~75,000)
        assert agreement > 0.985, (model, level, agreement)
    # the undistorted masks are the warp of the file's masks, every pixel
    without = load_guidance(
        tmp_path / "language_features", replace(cameras, distortion=None), resize=True
    )
    assert not np.array_equal(without[0].segments, view.segments)


def test_undistorted_image_matches_the_pinhole_picture(tmp_path):
    write_distorted_scene(tmp_path, "OPENCV", DISTORTED_MODELS["OPENCV"][1])
    cameras, _, _ = load_cameras(tmp_path)
    photographed = np.asarray(Image.open(tmp_path / "images" / "view.png"))
    undistorted = undistort_labels(photographed.astype(np.int64), cameras.undistortion_map(0))
    smooth = undistort_image(photographed, cameras.undistortion_map(0))
    assert undistorted.shape == smooth.shape == (int(cameras.heights[0]), int(cameras.widths[0]))
    truth_grey = ((pinhole_truth(cameras) + 1) * 9 % 256).astype(np.uint8)
    assert (undistorted == truth_grey).mean() > 0.985
    # bilinear agrees away from boundaries
    assert (smooth == truth_grey).mean() > 0.9


def test_downscaled_distorted_images_keep_the_lens(tmp_path):
    """images_2 of a distorted camera: the files are checked at half the COLMAP size and the
    pinhole camera is recomputed there (as gsplat does for its downscaled folders)."""
    write_distorted_scene(tmp_path, "OPENCV", DISTORTED_MODELS["OPENCV"][1])
    (tmp_path / "images_2").mkdir()
    Image.new("L", (WIDTH // 2, HEIGHT // 2)).save(tmp_path / "images_2" / "view.png")
    full, _, _ = load_cameras(tmp_path)
    half, _, _ = load_cameras(tmp_path, images="images_2", scale=0.5)
    assert half.distortion.widths.tolist() == [WIDTH // 2]
    np.testing.assert_allclose(
        half.distortion.Ks[0].numpy()[:2], full.distortion.Ks[0].numpy()[:2] / 2
    )
    np.testing.assert_array_equal(half.distortion.coeffs, full.distortion.coeffs)
    K, w, h = pinhole_camera(
        half.distortion.Ks[0].numpy(), half.distortion.coeffs[0].numpy(), WIDTH // 2, HEIGHT // 2
    )
    np.testing.assert_allclose(half.Ks[0].numpy(), K)
    assert (int(half.widths[0]), int(half.heights[0])) == (w, h)
    # resizing the renders keeps the files: the map then samples the same files at the new size
    small = full.resized([100], [80])
    assert small.distortion is full.distortion and small.undistortion_map(0).shape == (80, 100, 2)
    # and full-size masks against half-size files need --resize
    with pytest.raises(InputError, match="the image file is 160×120") as info:
        load_guidance(tmp_path / "language_features", half)
    assert "resize" in str(info.value)
    assert load_guidance(tmp_path / "language_features", half, resize=True)[0].width == w


def test_preprocess_makes_masks_on_the_image_files(tmp_path):
    write_distorted_scene(tmp_path, "OPENCV", DISTORTED_MODELS["OPENCV"][1])
    cameras, _, _ = load_cameras(tmp_path)
    [job] = image_jobs(tmp_path / "images", cameras=cameras)
    assert job.size == (WIDTH, HEIGHT)
    assert cameras.select([0]).distortion.widths.tolist() == [WIDTH]
