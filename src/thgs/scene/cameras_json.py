"""``cameras.json`` as written by the 3DGS and 2DGS trainers.

A JSON list, one entry per camera::

    {"id": 0, "img_name": "DSC_5283", "width": 1000, "height": 658,
     "position": [x, y, z],             # camera centre, world frame
     "rotation": [[...], [...], [...]], # camera→world rotation (columns: camera x, y, z axes)
     "fx": 2048.05, "fy": 2046.56}      # pixels, for width × height

Camera axes are OpenCV's (the trainers take them from COLMAP). The format has no principal point:
it is the image centre, ``(width / 2, height / 2)``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from thgs._atomic import atomic_output
from thgs._json import get_matrix, get_number, load_json
from thgs.errors import InputError
from thgs.scene.cameras import MAX_IMAGE_SIDE, Cameras, refuse_distortion, viewmat_from_pose

__all__ = ["read_cameras_json", "write_cameras_json"]


def read_cameras_json(path: str | os.PathLike[str]) -> Cameras:
    """Read a 3DGS/2DGS ``cameras.json``.

    Returns:
        :class:`Cameras` in file order, names = ``img_name`` (stems, no extension), checked.

    Raises:
        InputError: missing or unreadable file, not a list, an entry missing a key or holding a
            non-numeric or non-finite value, an improper rotation, a non-positive size.
    """
    path = Path(path)
    entries = load_json(path)
    if not isinstance(entries, list) or not entries:
        raise InputError(path, "expected a non-empty JSON list of cameras (3DGS cameras.json)")
    viewmats, Ks, widths, heights, names = [], [], [], [], []
    for index, entry in enumerate(entries):
        where = f"camera {index}"
        if not isinstance(entry, dict):
            raise InputError(path, f"{where} is not an object")
        if not isinstance(entry.get("img_name"), str):
            raise InputError(path, f"{where} has no 'img_name' string")
        where = f"camera {index} ({entry['img_name']!r})"
        width = get_number(entry, "width", path, where)
        height = get_number(entry, "height", path, where)
        if width != int(width) or height != int(height) or width <= 0 or height <= 0:
            raise InputError(path, f"{where}: size {width}×{height} is not positive integers")
        if max(width, height) > MAX_IMAGE_SIDE:
            raise InputError(
                path, f"{where}: size {width:g}×{height:g} exceeds {MAX_IMAGE_SIDE:,} pixels"
            )
        fx = get_number(entry, "fx", path, where)
        fy = get_number(entry, "fy", path, where)
        rotation = get_matrix(entry, "rotation", (3, 3), path, where)
        position = get_matrix(entry, "position", (3,), path, where)
        if (
            np.abs(rotation).max() > 1.0 + 1e-5  # not a rotation, and would overflow below
            or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5)
            or np.linalg.det(rotation) < 0
        ):
            raise InputError(path, f"{where}: 'rotation' is not a proper rotation matrix")
        viewmats.append(viewmat_from_pose(rotation, position))
        Ks.append([[fx, 0.0, width / 2], [0.0, fy, height / 2], [0.0, 0.0, 1.0]])
        widths.append(int(width))
        heights.append(int(height))
        names.append(entry["img_name"])
    cameras = Cameras.from_lists(viewmats, Ks, widths, heights, names)
    return cameras.check(source=str(path))


def write_cameras_json(path: str | os.PathLike[str], cameras: Cameras) -> None:
    """Write ``cameras`` as a 3DGS ``cameras.json`` (atomically).

    ``img_name`` is each camera's stem. The format cannot store a principal point, so every camera
    must have it at the image centre (within 1e-6 px).

    Raises:
        InputError: the cameras fail :meth:`Cameras.check`, a principal point is off-centre, or
            the cameras have lens distortion.
    """
    cameras.check(source=f"cameras to write to {os.fspath(path)}")
    refuse_distortion(cameras, path)
    entries = []
    camtoworlds = cameras.camtoworlds().numpy()
    for i, stem in enumerate(cameras.stems):
        K = cameras.Ks[i].numpy()
        width, height = int(cameras.widths[i]), int(cameras.heights[i])
        if abs(K[0, 2] - width / 2) > 1e-6 or abs(K[1, 2] - height / 2) > 1e-6 or K[0, 1] != 0:
            raise InputError(
                path,
                f"camera {cameras.names[i]!r} has its principal point at ({K[0, 2]}, {K[1, 2]}), "
                f"not the image centre ({width / 2}, {height / 2}); cameras.json cannot store it "
                "(write COLMAP or transforms.json instead)",
            )
        entries.append(
            {
                "id": i,
                "img_name": stem,
                "width": width,
                "height": height,
                "position": camtoworlds[i, :3, 3].tolist(),
                "rotation": camtoworlds[i, :3, :3].tolist(),
                "fy": float(K[1, 1]),
                "fx": float(K[0, 0]),
            }
        )
    with atomic_output(path, "w") as handle:
        json.dump(entries, handle, indent=1)
