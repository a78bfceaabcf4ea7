"""The browser's viewport camera as a pinhole :class:`~thgs.scene.Cameras`, and back.

viser reports the viewport camera in OpenCV convention (+X right, +Y down, +Z forward): a
camera→world rotation as a unit quaternion ``wxyz``, the camera centre ``position`` in world
coordinates, the vertical field of view in radians and the viewport size in CSS pixels. Its
renderer (three.js) puts the principal point at the centre of the viewport with square pixels,
so the intrinsics are ``fx = fy = (H / 2) / tan(fov / 2)``, ``cx = W / 2``, ``cy = H / 2``.

:func:`camera_pose` goes the other way, to fly the browser to one of the scene's cameras.

A click arrives as a screen position in [0, 1]² (OpenCV image coordinates: (0, 0) the top-left
corner); :func:`click_pixel` turns it into the integer pixel ``(x, y)`` that covers it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation

from thgs.errors import InputError
from thgs.scene import Cameras
from thgs.scene.cameras import viewmat_from_pose
from thgs.scene.gaussians import quaternions_to_matrices

__all__ = ["ViewportPose", "camera_pose", "click_pixel", "viewport_camera", "viewport_size"]


def viewport_size(width: int, height: int, max_height: int) -> tuple[int, int]:
    """``(width, height)`` scaled down so that the height is at most ``max_height`` (aspect kept,
    each side at least 1 pixel)."""
    if width < 1 or height < 1:
        raise InputError("viewport", f"size must be at least 1×1 pixel, got {width}×{height}")
    if max_height < 1:
        raise InputError("max_height", f"must be ≥ 1, got {max_height}")
    if height <= max_height:
        return int(width), int(height)
    scale = max_height / height
    return max(1, round(width * scale)), int(max_height)


def viewport_camera(
    wxyz: np.ndarray | tuple[float, float, float, float],
    position: np.ndarray | tuple[float, float, float],
    fov: float,
    width: int,
    height: int,
    name: str = "viewer",
) -> Cameras:
    """One pinhole camera equal to a viser viewport.

    Args:
        wxyz: [4] camera→world rotation (w, x, y, z), OpenCV axes.
        position: [3] camera centre, world frame, scene units.
        fov: vertical field of view in radians, in (0, π).
        width: viewport width in pixels.
        height: viewport height in pixels.
        name: the camera's name.

    Returns:
        A one-camera :class:`Cameras` (float64) of ``width`` × ``height`` pixels.

    Raises:
        InputError: a zero or non-finite quaternion or position, a field of view outside (0, π),
            or a size below 1×1.
    """
    wxyz = np.asarray(wxyz, dtype=np.float64)
    position = np.asarray(position, dtype=np.float64)
    if wxyz.shape != (4,) or not np.isfinite(wxyz).all() or not np.linalg.norm(wxyz) > 0:
        raise InputError("viewport camera", f"wxyz must be a non-zero finite [4], got {wxyz}")
    if position.shape != (3,) or not np.isfinite(position).all():
        raise InputError("viewport camera", f"position must be a finite [3], got {position}")
    if not 0.0 < fov < math.pi:
        raise InputError("viewport camera", f"fov must be in (0, π) radians, got {fov}")
    if width < 1 or height < 1:
        raise InputError("viewport camera", f"size must be at least 1×1, got {width}×{height}")
    rotation = quaternions_to_matrices(torch.from_numpy(wxyz)[None])[0].numpy()
    focal = (height / 2.0) / math.tan(fov / 2.0)
    K = np.array([[focal, 0.0, width / 2.0], [0.0, focal, height / 2.0], [0.0, 0.0, 1.0]])
    return Cameras.from_lists(
        [viewmat_from_pose(rotation, position)], [K], [int(width)], [int(height)], [name]
    )


def click_pixel(screen_pos: tuple[float, float], width: int, height: int) -> tuple[int, int]:
    """The pixel ``(x, y)`` of a ``width`` × ``height`` image under a click at ``screen_pos``
    ([0, 1]², OpenCV image coordinates); a click on the right or bottom edge lands in the last
    column or row."""
    u, v = (float(s) for s in screen_pos)
    if not (0.0 <= u <= 1.0 and 0.0 <= v <= 1.0):
        raise InputError("click", f"screen position must be in [0, 1]², got ({u}, {v})")
    return min(int(u * width), width - 1), min(int(v * height), height - 1)


@dataclass(frozen=True)
class ViewportPose:
    """Where to put the browser's camera to look through a scene camera.

    Attributes:
        wxyz: [4] camera→world rotation (w, x, y, z), OpenCV axes.
        position: [3] camera centre, world frame.
        look_at: [3] the point the orbit controls turn around: ``distance`` along the view axis.
        up: [3] unit world direction of the image's up (−Y of the camera).
        fov: vertical field of view in radians.
    """

    wxyz: np.ndarray
    position: np.ndarray
    look_at: np.ndarray
    up: np.ndarray
    fov: float


def camera_pose(cameras: Cameras, index: int, distance: float = 1.0) -> ViewportPose:
    """The viewport pose of camera ``index`` (the inverse of :func:`viewport_camera` up to the
    image size: the vertical field of view is kept, the principal point is taken as centred).

    Args:
        cameras: the scene's cameras.
        index: which one.
        distance: scene units from the centre to the orbit point ``look_at`` (> 0).
    """
    if not 0 <= index < len(cameras):
        raise InputError("camera", f"index {index} is outside 0..{len(cameras) - 1}")
    if not distance > 0:
        raise InputError("distance", f"must be > 0, got {distance}")
    rotation = cameras.viewmats[index, :3, :3].numpy().T
    position = cameras.centers()[index].numpy()
    height, fy = float(cameras.heights[index]), float(cameras.Ks[index, 1, 1])
    return ViewportPose(
        wxyz=Rotation.from_matrix(rotation).as_quat(scalar_first=True),
        position=position,
        look_at=position + distance * rotation[:, 2],
        up=-rotation[:, 1],
        fov=2.0 * math.atan(height / (2.0 * fy)),
    )
