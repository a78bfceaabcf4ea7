"""COLMAP sparse models (``sparse/0``, binary or text), read and written through pycolmap.

Pinhole models (``PINHOLE``, ``SIMPLE_PINHOLE``) are read as they are. The perspective models with
lens distortion (``SIMPLE_RADIAL``, ``RADIAL``, ``OPENCV``, ``FULL_OPENCV``) become the pinhole
cameras their images are undistorted into, as gsplat and nerfstudio train
(:mod:`thgs.scene.distortion`). Fisheye and other models must be undistorted first
(``colmap image_undistorter``). COLMAP's camera axes and pixel convention (pixel centres at
integer + 0.5) are thgs's own, so poses and intrinsics are taken as they are.
"""

from __future__ import annotations

import logging
import os
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np

from thgs._atomic import staging_folder
from thgs.errors import InputError
from thgs.scene.cameras import Cameras, refuse_distortion
from thgs.scene.images import fit_to_images

__all__ = ["read_colmap", "write_colmap"]

logger = logging.getLogger(__name__)

_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")
_DISTORTED_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV")


def _intrinsics(model: str, params: np.ndarray) -> tuple[list[list[float]], np.ndarray]:
    """K (pixels) and the [8] OpenCV coefficients of a COLMAP camera model's parameters."""
    coeffs = np.zeros(8)
    if model in ("SIMPLE_PINHOLE", "SIMPLE_RADIAL", "RADIAL"):
        fx = fy = params[0]
        cx, cy = params[1:3]
        coeffs[: len(params) - 3] = params[3:]  # k, or k1 k2
    else:
        fx, fy, cx, cy = params[:4]
        coeffs[: len(params) - 4] = params[4:]  # k1 k2 p1 p2 [k3 k4 k5 k6]
    return [[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], coeffs


def _camera_sizes(data: bytes, offset: int) -> int:
    """The size of the ``cameras.bin`` entry at ``offset``: camera id (uint32), model id (int32),
    width and height (uint64), then the model's parameters (float64)."""
    import pycolmap

    (model_id,) = struct.unpack_from("<i", data, offset + 4)
    try:
        params = len(pycolmap.Camera.create_from_model_id(1, model_id, 1.0, 1, 1).params)
    except (ValueError, TypeError, RuntimeError) as exc:
        raise ValueError(f"unknown camera model id {model_id}") from exc
    return 24 + 8 * params


def _image_sizes(data: bytes, offset: int) -> int:
    """The size of the ``images.bin`` entry at ``offset``: image id (uint32), quaternion and
    translation (7 float64), camera id (uint32), NUL-terminated name, point count (uint64) and
    that many (x, y float64, point id uint64)."""
    end = data.find(b"\0", offset + 64)
    if end < 0:  # the name runs past the end of the file
        return len(data) + 1 - offset
    (points,) = struct.unpack_from("<Q", data, end + 1)
    return end + 9 - offset + 24 * points


def _point_sizes(data: bytes, offset: int) -> int:
    """The size of the ``points3D.bin`` entry at ``offset``: point id (uint64), xyz (3 float64),
    colour (3 uint8), error (float64), track length (uint64) and that many (uint32, uint32)."""
    (track,) = struct.unpack_from("<Q", data, offset + 43)
    return 51 + 8 * track


def _check_binary(file: Path, entry_size: Callable[[bytes, int], int]) -> None:
    """Walk a COLMAP binary file entry by entry (its uint64 count, then the entries) and refuse
    one that ends early or goes on after its last entry. pycolmap does not check this: a
    truncated file can make it read garbage ids ("Rig with ID … does not exist") or never
    return."""
    data = file.read_bytes()
    if len(data) < 8:
        raise InputError(file, "the COLMAP binary file is empty or truncated")
    (count,) = struct.unpack_from("<Q", data, 0)
    offset = 8
    for index in range(count):
        where = f"the COLMAP binary file is truncated or corrupt: entry {index + 1} of {count}"
        try:
            offset += entry_size(data, offset)
        except struct.error:
            offset = len(data) + 1
        except ValueError as exc:
            raise InputError(file, f"{where} has {exc}") from exc
        if offset > len(data):
            raise InputError(file, f"{where} runs past the end of the file ({len(data)} bytes)")
    if offset != len(data):
        raise InputError(
            file,
            f"the COLMAP binary file is corrupt: {len(data) - offset} bytes follow its "
            f"{count} entries",
        )


def _model_files(sparse_dir: Path) -> str:
    for ext in (".bin", ".txt"):
        files = [sparse_dir / f"{stem}{ext}" for stem in ("cameras", "images", "points3D")]
        if all(file.is_file() for file in files):
            if ext == ".bin":
                for file, walk in zip(files, (_camera_sizes, _image_sizes, _point_sizes)):
                    _check_binary(file, walk)
            return "binary" if ext == ".bin" else "text"
    raise InputError(
        sparse_dir,
        "not a COLMAP model: expected cameras, images and points3D as .bin or .txt files",
    )


def read_colmap(
    sparse_dir: str | os.PathLike[str],
    *,
    images_dir: str | os.PathLike[str] | None = None,
    scale: float = 1.0,
) -> Cameras:
    """Read the registered images of a COLMAP model as cameras.

    Args:
        sparse_dir: the model folder (``…/sparse/0``) with ``cameras``, ``images`` and ``points3D``
            as ``.bin`` or ``.txt``.
        images_dir: if given, every image must be there (names as in COLMAP, relative to it) and
            measure the camera size times ``scale`` within a pixel; the cameras then take the
            images' exact sizes (see :func:`thgs.scene.images.fit_to_images`).
        scale: image size / COLMAP camera size, e.g. 0.25 for images downscaled 4× (3DGS's
            ``images_4``). Never guessed from the images.

    Returns:
        :class:`Cameras`, one per registered image, sorted by image name (as the 3DGS loaders do);
        cameras with lens distortion are the pinhole cameras of their undistorted images, with
        :attr:`Cameras.distortion` set.

    Raises:
        InputError: missing or unreadable model files, a fisheye or other camera model thgs
            cannot undistort (undistort first), no registered image, or images that do not match.
    """
    import pycolmap

    sparse_dir = Path(sparse_dir)
    if not sparse_dir.is_dir():
        raise InputError(sparse_dir, "COLMAP model folder not found")
    kind = _model_files(sparse_dir)
    try:
        reconstruction = pycolmap.Reconstruction(str(sparse_dir))
    except Exception as exc:  # pycolmap raises ValueError, IndexError, RuntimeError …
        raise InputError(
            sparse_dir, f"cannot read the COLMAP {kind} model ({type(exc).__name__}: {exc})"
        ) from exc

    images = sorted(
        (image for image in reconstruction.images.values() if image.has_pose),
        key=lambda image: image.name,
    )
    unregistered = reconstruction.num_images() - len(images)
    if unregistered:
        logger.info("%s: skipping %d unregistered images", sparse_dir, unregistered)
    if not images:
        raise InputError(sparse_dir, "the COLMAP model has no registered image")
    viewmats, Ks, coeffs, widths, heights, names = [], [], [], [], [], []
    for image in images:
        camera = reconstruction.cameras[image.camera_id]
        model = camera.model.name
        if model not in _PINHOLE_MODELS + _DISTORTED_MODELS:
            raise InputError(
                sparse_dir,
                f"camera {image.camera_id} (image {image.name!r}) uses the {model} model; thgs "
                f"reads {', '.join(_PINHOLE_MODELS + _DISTORTED_MODELS)}: run "
                "`colmap image_undistorter` and use its sparse model and images",
            )
        K, camera_coeffs = _intrinsics(model, np.asarray(camera.params, dtype=np.float64))
        viewmat = np.eye(4)
        viewmat[:3, :] = image.cam_from_world().matrix()
        viewmats.append(viewmat)
        Ks.append(K)
        coeffs.append(camera_coeffs)
        widths.append(camera.width)
        heights.append(camera.height)
        names.append(image.name)
    distorted = sorted({reconstruction.cameras[image.camera_id].model.name for image in images})
    distorted = [model for model in distorted if model in _DISTORTED_MODELS]
    if distorted:
        logger.info(
            "%s: %s cameras with lens distortion; masks are undistorted into pinhole cameras",
            sparse_dir,
            "/".join(distorted),
        )
    cameras = Cameras.from_distorted(viewmats, Ks, coeffs, widths, heights, names, str(sparse_dir))
    cameras = cameras.check(source=str(sparse_dir))
    if images_dir is not None:
        return fit_to_images(cameras, images_dir, scale=scale)
    return cameras if scale == 1.0 else cameras.scaled(scale)


def write_colmap(
    sparse_dir: str | os.PathLike[str], cameras: Cameras, *, text: bool = False
) -> None:
    """Write ``cameras`` as a COLMAP model: one PINHOLE camera per image, no 3D points.

    Image ``i`` gets image and camera id ``i + 1`` and the name ``cameras.names[i]``. The files
    are written to a temporary folder beside ``sparse_dir`` and then moved in, one rename each.

    Raises:
        InputError: the cameras fail :meth:`Cameras.check`, have a skewed K or lens distortion.
    """
    import pycolmap

    sparse_dir = Path(sparse_dir)
    cameras.check(source=f"cameras to write to {sparse_dir}")
    refuse_distortion(cameras, sparse_dir)
    if bool((cameras.Ks[:, 0, 1] != 0).any()):
        raise InputError(sparse_dir, "COLMAP PINHOLE cameras cannot have skew (K[0, 1] != 0)")
    reconstruction = pycolmap.Reconstruction()
    for i in range(len(cameras)):
        K = cameras.Ks[i].numpy()
        camera = pycolmap.Camera(
            model="PINHOLE",
            width=int(cameras.widths[i]),
            height=int(cameras.heights[i]),
            params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]],
            camera_id=i + 1,
        )
        reconstruction.add_camera_with_trivial_rig(camera)
        image = pycolmap.Image(name=cameras.names[i], camera_id=i + 1, image_id=i + 1)
        pose = pycolmap.Rigid3d(cameras.viewmats[i, :3, :].numpy())
        reconstruction.add_image_with_trivial_frame(image, pose)
    sparse_dir.mkdir(parents=True, exist_ok=True)
    with staging_folder(sparse_dir) as staging:
        if text:
            reconstruction.write_text(str(staging))
        else:
            reconstruction.write_binary(str(staging))
        for file in sorted(staging.iterdir()):
            os.replace(file, sparse_dir / file.name)
