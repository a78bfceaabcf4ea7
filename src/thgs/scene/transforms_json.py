"""``transforms.json`` camera files of nerfstudio and instant-ngp (and the NeRF Blender scenes).

Layout::

    {"camera_model": "OPENCV",                     # optional; OPENCV, PINHOLE or SIMPLE_PINHOLE
     "fl_x": …, "fl_y": …, "cx": …, "cy": …, "w": …, "h": …,   # pixels, global (optional)
     "k1": …, "k2": …, "k3": …, "p1": …, "p2": …,   # lens distortion (optional, default 0)
     "camera_angle_x": …,                          # instant-ngp / Blender: horizontal FoV (rad)
     "frames": [{"file_path": "images/frame_00001.png",
                 "transform_matrix": [[…4×4…]],    # camera→world, OpenGL axes
                 "fl_x": …, …}]}                   # per-frame intrinsics override global ones

The NeRF Blender scenes, and OpenGaussian's ScanNet scenes, split the frames into
``transforms_train.json`` and ``transforms_test.json`` of this same layout, with ``file_path``
given without an extension (``color/0``; the image is ``color/0.jpg``).
:func:`thgs.scene.load_cameras` decides which of them a folder's cameras come from.

Missing values are completed as the 3DGS Blender loader does: ``fl_x`` from ``camera_angle_x``,
``fl_y = fl_x`` unless ``fl_y`` or ``camera_angle_y`` is given, ``cx, cy`` at the image centre,
``w, h`` from the image file. Poses are converted once to world→camera OpenCV axes.

Lens distortion (instant-ngp's fox capture, nerfstudio's ``OPENCV`` cameras) is OpenCV's model with
``k1 k2 k3`` radial and ``p1 p2`` tangential; such cameras become the pinhole cameras their images
are undistorted into, as nerfstudio and gsplat train (:mod:`thgs.scene.distortion`). Fisheye
cameras (``OPENCV_FISHEYE``, instant-ngp's ``is_fisheye``) must be undistorted first.
"""

from __future__ import annotations

import json
import logging
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
from PIL import Image, UnidentifiedImageError

from thgs._atomic import atomic_output
from thgs._json import get_matrix, get_number, load_json
from thgs.errors import InputError
from thgs.scene.cameras import MAX_IMAGE_SIDE, Cameras, refuse_distortion, viewmat_from_pose
from thgs.scene.images import image_candidates

__all__ = ["read_transforms_json", "write_transforms_json"]

logger = logging.getLogger(__name__)

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
"""Flips camera y and z: OpenGL (x right, y up, z back) ↔ OpenCV (x right, y down, z forward)."""

_INTRINSIC_KEYS = (
    "fl_x",
    "fl_y",
    "cx",
    "cy",
    "w",
    "h",
    "camera_angle_x",
    "camera_angle_y",
    "k1",
    "k2",
    "k3",
    "k4",
    "p1",
    "p2",
    "camera_model",
    "is_fisheye",
)
_OPENCV_SLOTS = {"k1": 0, "k2": 1, "p1": 2, "p2": 3, "k3": 4}
"""Where each transforms.json coefficient goes in OpenCV's (k1, k2, p1, p2, k3, k4, k5, k6)."""
_PERSPECTIVE_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")


def _image_size(root: Path, file_path: str, path: Path, where: str) -> tuple[int, int]:
    candidates = image_candidates(root, file_path)
    found = next((candidate for candidate in candidates if candidate.is_file()), None)
    if found is None:
        raise InputError(
            path, f"{where} gives no image size (w, h) and its image {candidates[0]} does not exist"
        )
    try:
        with Image.open(found) as opened:
            return opened.size
    except (OSError, UnidentifiedImageError) as exc:
        raise InputError(found, f"not a readable image ({exc})") from exc


def _not_finite(matrix: Any) -> bool:
    """Whether ``matrix`` is numeric but holds NaN or infinite values (ScanNet's lost poses)."""
    try:
        array = np.asarray(matrix, dtype=np.float64)
    except (TypeError, ValueError):
        return False
    return not bool(np.isfinite(array).all())


def _coefficients(values: dict[str, Any], path: Path, where: str) -> np.ndarray:
    model = values.get("camera_model")
    if values.get("is_fisheye"):
        also = f" (camera_model {model!r} says otherwise)" if model is not None else ""
        raise InputError(
            path,
            f"{where}: is_fisheye is true{also}: fisheye lenses are not read; undistort the "
            "images to pinhole ones first (e.g. colmap image_undistorter) and drop is_fisheye",
        )
    if model is not None and model not in _PERSPECTIVE_MODELS:
        raise InputError(
            path,
            f"{where}: camera_model {model!r} is not a perspective model; thgs reads "
            f"{', '.join(_PERSPECTIVE_MODELS)} (with k1 k2 k3 p1 p2): undistort the images to "
            "pinhole ones first (e.g. colmap image_undistorter)",
        )
    coeffs = np.zeros(8)
    for key, slot in _OPENCV_SLOTS.items():
        if key in values:
            coeffs[slot] = get_number(values, key, path, where)
    if "k4" in values and get_number(values, "k4", path, where) != 0.0:
        raise InputError(
            path,
            f"{where}: k4 = {values['k4']} on a perspective camera; its meaning differs between "
            "tools (a fourth radial term or OpenCV's rational one): undistort the images first",
        )
    return coeffs


def _intrinsics(
    values: dict[str, Any], root: Path, file_path: str, path: Path, where: str
) -> tuple[list[list[float]], int, int]:
    if "w" in values and "h" in values:
        width, height = get_number(values, "w", path, where), get_number(values, "h", path, where)
        if width != int(width) or height != int(height) or width <= 0 or height <= 0:
            raise InputError(path, f"{where}: size {width}×{height} is not positive integers")
        if max(width, height) > MAX_IMAGE_SIDE:
            raise InputError(
                path, f"{where}: size {width:g}×{height:g} exceeds {MAX_IMAGE_SIDE:,} pixels"
            )
        width, height = int(width), int(height)
    else:
        width, height = _image_size(root, file_path, path, where)
    if "fl_x" in values:
        fx = get_number(values, "fl_x", path, where)
    elif "camera_angle_x" in values:
        fx = 0.5 * width / math.tan(0.5 * get_number(values, "camera_angle_x", path, where))
    else:
        raise InputError(path, f"{where} has neither 'fl_x' nor 'camera_angle_x'")
    if "fl_y" in values:
        fy = get_number(values, "fl_y", path, where)
    elif "camera_angle_y" in values:
        fy = 0.5 * height / math.tan(0.5 * get_number(values, "camera_angle_y", path, where))
    else:
        fy = fx
    cx = get_number(values, "cx", path, where) if "cx" in values else width / 2
    cy = get_number(values, "cy", path, where) if "cy" in values else height / 2
    return [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], width, height


def read_transforms_json(
    path: str | os.PathLike[str],
    *,
    undo_applied_transform: bool = False,
    skip_invalid_poses: bool = False,
) -> Cameras:
    """Read a nerfstudio / instant-ngp ``transforms.json`` (or a Blender split file such as
    ``transforms_train.json``).

    Args:
        path: the JSON file; image paths in it are relative to its folder.
        undo_applied_transform: nerfstudio's ``ns-process-data`` stores poses in a frame rotated
            from COLMAP's and records the rotation as ``applied_transform``; True maps the poses
            back to the COLMAP world frame (what a 3DGS model trained from that COLMAP model
            uses). False (default) keeps the file's frame, as the 3DGS Blender loader does.
        skip_invalid_poses: leave out, with a warning, the frames whose ``transform_matrix``
            holds NaN or infinite values instead of refusing the file: ScanNet marks the frames
            where its tracking was lost with ``-inf`` poses, and OpenGaussian's ScanNet release
            keeps them (scene0200_00, scene0400_00). A file with no valid frame is still an error.

    Returns:
        :class:`Cameras` in file order; names are the ``file_path`` values (without a leading ./).
        Cameras with lens distortion are the pinhole cameras of their undistorted images, with
        :attr:`Cameras.distortion` set (the intrinsics, coefficients and sizes of the files).

    Raises:
        InputError: unreadable file, no frames, a missing or non-finite value, a fisheye or other
            non-perspective model, a non-zero ``k4``, a non-rigid ``transform_matrix``, an image
            needed for its size that does not exist.
    """
    path = Path(path)
    data = load_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise InputError(
            path, "expected an object with a non-empty 'frames' list (transforms.json)"
        )
    root = path.parent
    shared = {key: data[key] for key in _INTRINSIC_KEYS if key in data}
    applied = None
    if "applied_transform" in data:
        applied = np.eye(4)
        applied[:3, :] = get_matrix(data, "applied_transform", (3, 4), path, "the file")
        if undo_applied_transform:
            logger.info("%s: undoing applied_transform (back to the COLMAP world frame)", path)
        else:
            logger.info("%s: poses kept in the file's frame (applied_transform not undone)", path)
    elif undo_applied_transform:
        raise InputError(
            path, "undo_applied_transform was asked but the file has no applied_transform"
        )
    viewmats, Ks, coeffs, widths, heights, names = [], [], [], [], [], []
    invalid: list[str] = []
    for index, frame in enumerate(data["frames"]):
        if not isinstance(frame, dict) or not isinstance(frame.get("file_path"), str):
            raise InputError(path, f"frame {index} has no 'file_path' string")
        file_path = frame["file_path"]
        name = file_path[2:] if file_path.startswith("./") else file_path
        where = f"frame {index} ({file_path!r})"
        if skip_invalid_poses and _not_finite(frame.get("transform_matrix")):
            invalid.append(name)
            continue
        values = {**shared, **{key: frame[key] for key in _INTRINSIC_KEYS if key in frame}}
        K, width, height = _intrinsics(values, root, name, path, where)
        coeffs.append(_coefficients(values, path, where))
        camtoworld = get_matrix(frame, "transform_matrix", (4, 4), path, where)
        rotation = camtoworld[:3, :3]
        if (
            not np.allclose(camtoworld[3], [0, 0, 0, 1], atol=1e-6)
            or np.abs(rotation).max() > 1.0 + 1e-4  # not a rotation, and would overflow below
            or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-4)
            or np.linalg.det(rotation) < 0
        ):
            raise InputError(path, f"{where}: transform_matrix is not a rigid camera→world pose")
        if applied is not None and undo_applied_transform:
            camtoworld = np.linalg.inv(applied) @ camtoworld
        camtoworld = camtoworld @ OPENGL_TO_OPENCV
        viewmats.append(viewmat_from_pose(camtoworld[:3, :3], camtoworld[:3, 3]))
        Ks.append(K)
        widths.append(width)
        heights.append(height)
        names.append(name)
    if invalid:
        if not names:
            raise InputError(path, f"all {len(invalid)} frames have NaN or infinite poses")
        logger.warning(
            "%s: %d frames left out, their transform_matrix is not finite (first: %s)",
            path,
            len(invalid),
            ", ".join(invalid[:5]),
        )
    if any(row.any() for row in coeffs):
        logger.info("%s: cameras with lens distortion; masks are undistorted into pinholes", path)
    cameras = Cameras.from_distorted(viewmats, Ks, coeffs, widths, heights, names, str(path))
    return cameras.check(source=str(path))


def write_transforms_json(path: str | os.PathLike[str], cameras: Cameras) -> None:
    """Write ``cameras`` as a nerfstudio ``transforms.json`` (atomically).

    ``file_path`` is each camera's name as is (write names relative to the JSON's folder).
    Intrinsics are written once at the top when all cameras share them, per frame otherwise.

    Raises:
        InputError: the cameras fail :meth:`Cameras.check`, have a skewed K or lens distortion.
    """
    cameras.check(source=f"cameras to write to {os.fspath(path)}")
    refuse_distortion(cameras, path)
    if bool((cameras.Ks[:, 0, 1] != 0).any()):
        raise InputError(path, "transforms.json cannot store skew (K[0, 1] != 0)")

    def intrinsics(i: int) -> dict[str, float | int]:
        K = cameras.Ks[i].numpy()
        return {
            "fl_x": float(K[0, 0]),
            "fl_y": float(K[1, 1]),
            "cx": float(K[0, 2]),
            "cy": float(K[1, 2]),
            "w": int(cameras.widths[i]),
            "h": int(cameras.heights[i]),
        }

    per_camera = [intrinsics(i) for i in range(len(cameras))]
    shared = all(values == per_camera[0] for values in per_camera)
    camtoworlds = (cameras.camtoworlds().numpy() @ OPENGL_TO_OPENCV).tolist()
    document: dict[str, Any] = {"camera_model": "PINHOLE"}
    if shared:
        document.update(per_camera[0])
    document["frames"] = [
        {"file_path": name, "transform_matrix": camtoworld, **({} if shared else values)}
        for name, camtoworld, values in zip(cameras.names, camtoworlds, per_camera)
    ]
    with atomic_output(path, "w") as handle:
        json.dump(document, handle, indent=2)
