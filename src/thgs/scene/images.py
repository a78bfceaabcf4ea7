"""Match cameras to the image files on disk and fit their intrinsics to the images' sizes."""

from __future__ import annotations

import logging
import os
from pathlib import Path, PurePosixPath

from PIL import Image, UnidentifiedImageError

from thgs.errors import InputError
from thgs.scene.cameras import Cameras, round_half_up

__all__ = ["IMAGE_EXTENSIONS", "find_images", "fit_to_images", "image_candidates"]

logger = logging.getLogger(__name__)

IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg", ".JPG", ".JPEG", ".PNG")
"""Extensions tried, in this order, for image names given without one (cameras.json, Blender)."""


def image_candidates(root: Path, name: str) -> list[Path]:
    """Paths an image ``name`` may have under ``root``: as is, or with each known extension."""
    relative = PurePosixPath(name.replace("\\", "/"))
    path = root / relative
    if relative.suffix:
        return [path]
    return [path.with_name(path.name + ext) for ext in IMAGE_EXTENSIONS]


def find_images(cameras: Cameras, root: str | os.PathLike[str]) -> list[Path | None]:
    """The image file of each camera under ``root`` ([M], None where absent).

    A name with an extension is looked up as is (relative to ``root``); a name without one is
    tried with each of :data:`IMAGE_EXTENSIONS`.
    """
    root = Path(root)
    found: list[Path | None] = []
    for name in cameras.names:
        found.append(next((path for path in image_candidates(root, name) if path.is_file()), None))
    return found


def fit_to_images(cameras: Cameras, root: str | os.PathLike[str], *, scale: float = 1.0) -> Cameras:
    """Check every camera against its image under ``root`` and return cameras at the images' size.

    Each image must exist and measure ``round(width · scale) × round(height · scale)`` within one
    pixel (resizers round differently); the returned cameras take the images' exact sizes, their
    intrinsics scaled per axis by image size / camera size. ``scale`` is never guessed: a
    mismatch is an error that reports the scale the images suggest. Cameras with lens distortion
    are checked against their distorted image files (:meth:`Cameras.file_sizes`) and their
    pinhole cameras recomputed at the images' size (:meth:`Cameras.with_file_sizes`).

    Args:
        cameras: cameras at the resolution of the camera model (e.g. COLMAP's).
        root: the image folder the camera names are relative to.
        scale: image size / camera-model size (0.25 for images downscaled 4×).

    Raises:
        InputError: ``root`` or an image is missing, an image is unreadable, or a size differs.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "image folder not found")
    paths = find_images(cameras, root)
    missing = [name for name, path in zip(cameras.names, paths) if path is None]
    if missing:
        raise InputError(
            root,
            f"{len(missing)} of {len(cameras)} camera images are missing (first: {missing[:5]}); "
            "image names must match the camera names",
        )
    file_widths, file_heights = cameras.file_sizes()
    widths, heights = [], []
    for i, path in enumerate(paths):
        assert path is not None
        try:
            with Image.open(path) as image:
                width, height = image.size
        except (OSError, UnidentifiedImageError) as exc:
            raise InputError(path, f"not a readable image ({exc})") from exc
        expected_w = round_half_up(float(file_widths[i]) * scale)
        expected_h = round_half_up(float(file_heights[i]) * scale)
        if abs(width - expected_w) > 1 or abs(height - expected_h) > 1:
            suggested = width / float(file_widths[i])
            raise InputError(
                path,
                f"the image is {width}×{height} but camera {cameras.names[i]!r} is "
                f"{int(file_widths[i])}×{int(file_heights[i])} at scale {scale:g} "
                f"(expected {expected_w}×{expected_h}); the image suggests scale "
                f"{suggested:.4g}: pass it explicitly if that is right",
            )
        widths.append(width)
        heights.append(height)
    logger.info("matched %d cameras to the images in %s", len(cameras), root)
    return cameras.with_file_sizes(widths, heights)
