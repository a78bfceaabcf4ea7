"""Lens distortion: the image files of a distorting lens and the pinhole cameras thgs uses for them.

A Gaussian model trained on a capture with lens distortion (a COLMAP ``OPENCV`` or
``SIMPLE_RADIAL`` model, a nerfstudio / instant-ngp ``transforms.json`` with ``k1 … p2``) was
trained on *undistorted* images: gsplat's COLMAP parser and nerfstudio's splatfacto both undistort
every image with OpenCV into a pinhole camera before training. thgs does the same: a reader turns
each distorted camera into the pinhole camera of :func:`pinhole_camera` (OpenCV's
``getOptimalNewCameraMatrix`` with ``alpha = 0``, cropped to its valid region, as gsplat does),
keeps the distorted camera in :class:`Distortion`, and whatever is per pixel in the image files
(SAM masks, images) is warped into the pinhole camera with :func:`undistortion_map`,
:func:`undistort_labels` (nearest neighbour) and :func:`undistort_image` (bilinear).

Coefficients are OpenCV's ``(k1, k2, p1, p2, k3, k4, k5, k6)``: radial ``k1 k2 k3`` in the
numerator, ``k4 k5 k6`` in the denominator, tangential ``p1 p2``, on normalised image coordinates
(so they do not change when images are resized). Intrinsics use thgs's pixel convention (pixel
centres at integer + 0.5, docs/conventions.md); OpenCV puts them at integers, and the functions
here shift by half a pixel on the way in and out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from thgs.errors import InputError

__all__ = [
    "COEFFICIENTS",
    "Distortion",
    "pinhole_camera",
    "undistort_image",
    "undistort_labels",
    "undistortion_map",
]

COEFFICIENTS = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
"""The order of :attr:`Distortion.coeffs`: OpenCV's rational model."""


def _cv2():
    try:
        import cv2
    except ImportError as error:
        raise InputError(
            "opencv",
            "undistorting images needs OpenCV: pip install opencv-python-headless",
        ) from error
    return cv2


@dataclass(frozen=True, eq=False)
class Distortion:
    """The distorted cameras of M image files (the lens as calibrated).

    Attributes:
        Ks: [M, 3, 3] float64 intrinsics of the image files, pixels, thgs's pixel convention.
        coeffs: [M, 8] float64 OpenCV coefficients (:data:`COEFFICIENTS` order); a row of zeros
            is a camera without distortion.
        widths: [M] int64 image file widths in pixels.
        heights: [M] int64 image file heights in pixels.
    """

    Ks: Tensor
    coeffs: Tensor
    widths: Tensor
    heights: Tensor

    def __len__(self) -> int:
        return int(self.Ks.shape[0])

    def distorted(self, index: int) -> bool:
        """Whether camera ``index`` has any non-zero coefficient."""
        return bool((self.coeffs[index] != 0).any())

    def select(self, index: Sequence[int] | Tensor) -> Distortion:
        """The cameras at ``index`` ([K] int indices), in that order."""
        index_t = torch.as_tensor(index, dtype=torch.int64).reshape(-1)
        return Distortion(
            self.Ks[index_t], self.coeffs[index_t], self.widths[index_t], self.heights[index_t]
        )

    def resized(
        self, widths: Tensor | Sequence[int], heights: Tensor | Sequence[int]
    ) -> Distortion:
        """The same lenses for image files of ``widths × heights`` ([M] each): K's rows scale by
        new / old size; the coefficients (on normalised coordinates) stay."""
        widths = torch.as_tensor(widths, dtype=torch.int64).reshape(len(self))
        heights = torch.as_tensor(heights, dtype=torch.int64).reshape(len(self))
        Ks = self.Ks.clone()
        Ks[:, 0, :] *= (widths.double() / self.widths.double())[:, None]
        Ks[:, 1, :] *= (heights.double() / self.heights.double())[:, None]
        return Distortion(Ks, self.coeffs.clone(), widths, heights)

    def check(self, m: int, source: str = "Distortion") -> Distortion:
        """Verify shapes ([m, 3, 3], [m, 8], [m], [m]), dtypes and finite values.

        Returns ``self``."""
        shapes = {
            "Ks": (self.Ks, (m, 3, 3)),
            "coeffs": (self.coeffs, (m, 8)),
            "widths": (self.widths, (m,)),
            "heights": (self.heights, (m,)),
        }
        for name, (tensor, shape) in shapes.items():
            if tuple(tensor.shape) != shape:
                raise InputError(
                    source, f"distortion {name} must be {list(shape)}, got {list(tensor.shape)}"
                )
        for name in ("Ks", "coeffs"):
            tensor = getattr(self, name)
            if tensor.dtype != torch.float64 or not bool(torch.isfinite(tensor).all()):
                raise InputError(source, f"distortion {name} must be finite float64")
        if bool((self.widths <= 0).any() or (self.heights <= 0).any()):
            raise InputError(source, "distortion image sizes must be positive")
        return self


def _to_opencv(K: np.ndarray) -> np.ndarray:
    K = np.array(K, dtype=np.float64)
    K[0, 2] -= 0.5
    K[1, 2] -= 0.5
    return K


_ROUND_TRIP_PIXELS = 0.5
"""How far, in pixels, a border point of the image may land after undistorting it and
distorting it back before the lens model is refused as not invertible over the image."""


def _round_trip_error(K: np.ndarray, coeffs: np.ndarray, width: int, height: int) -> float:
    """The largest distance, in pixels, between points along the image's border and across it
    and the same points undistorted by OpenCV (its iterative inversion) and distorted back.

    A lens model that folds over itself inside the image (a radius reached twice), or one
    OpenCV's iteration cannot invert there (a very strong ``k1``), has no pinhole image: its
    points do not come back."""
    cv2 = _cv2()
    xs = np.linspace(0.0, width - 1.0, 33)
    ys = np.linspace(0.0, height - 1.0, 25)
    grid = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    K_cv = _to_opencv(K)
    normalised = cv2.undistortPoints(grid[:, None, :], K_cv, coeffs).reshape(-1, 2)
    if not np.isfinite(normalised).all():
        return float("inf")
    rays = np.concatenate([normalised, np.ones((len(normalised), 1))], axis=1)
    back, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K_cv, coeffs)
    return float(np.max(np.linalg.norm(back.reshape(-1, 2) - grid, axis=1)))


def pinhole_camera(
    K: np.ndarray, coeffs: np.ndarray, width: int, height: int, source: str = "distortion"
) -> tuple[np.ndarray, int, int]:
    """The pinhole camera an image of a distorted camera is undistorted into.

    OpenCV's ``getOptimalNewCameraMatrix`` with ``alpha = 0`` (every output pixel sees the
    image; no black borders), cropped to its valid rectangle with the principal point moved
    accordingly: the camera gsplat's COLMAP parser and nerfstudio train on.

    Args:
        K: [3, 3] intrinsics of the image file, pixels (thgs's convention).
        coeffs: [8] OpenCV coefficients (:data:`COEFFICIENTS`).
        width, height: the image file's size in pixels.
        source: the camera's file and name, for errors.

    Returns:
        ``(K_pinhole, width_pinhole, height_pinhole)``: [3, 3] float64 intrinsics in thgs's
        convention and the undistorted image size. A camera without distortion is returned as it is.

    Raises:
        InputError: the distortion cannot be undone over the image (points across it do not
            come back within half a pixel when undistorted and distorted again: the model folds
            over itself or OpenCV's inversion diverges), or is so strong that no valid rectangle
            remains.
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    if not coeffs.any():
        return np.array(K, dtype=np.float64), int(width), int(height)
    cv2 = _cv2()
    error = _round_trip_error(np.asarray(K, dtype=np.float64), coeffs, int(width), int(height))
    if not error <= _ROUND_TRIP_PIXELS:
        raise InputError(
            source,
            f"lens distortion {dict(zip(COEFFICIENTS, coeffs.tolist()))} cannot be undone over "
            f"the {width}×{height} image: points across it come back {error:.3g} px away when "
            "undistorted and distorted again (the model folds over itself, or is beyond what "
            "its calibration can mean); check the coefficients",
        )
    new_K, (x, y, roi_w, roi_h) = cv2.getOptimalNewCameraMatrix(
        _to_opencv(K), coeffs, (int(width), int(height)), 0
    )
    if roi_w < 2 or roi_h < 2:
        raise InputError(
            source,
            f"coefficients {coeffs.tolist()} leave no valid undistorted image of a "
            f"{width}×{height} camera",
        )
    new_K = np.array(new_K, dtype=np.float64)
    new_K[0, 2] += 0.5 - x
    new_K[1, 2] += 0.5 - y
    return new_K, int(roi_w), int(roi_h)


def undistortion_map(
    K: np.ndarray, coeffs: np.ndarray, K_pinhole: np.ndarray, width: int, height: int
) -> np.ndarray:
    """Where each pixel of the pinhole image looks in the distorted image file.

    Args:
        K, coeffs: the image file's intrinsics (pixels) and OpenCV coefficients.
        K_pinhole: [3, 3] the pinhole camera's intrinsics (:func:`pinhole_camera`).
        width, height: the pinhole image's size.

    Returns:
        [height, width, 2] float32: ``map[v, u] = (x, y)``, the continuous coordinates (thgs's
        convention: pixel (i, j) of the file covers [i, i+1) × [j, j+1)) in the image file of the
        ray through the centre of pinhole pixel (u, v). OpenCV's ``initUndistortRectifyMap``.
    """
    cv2 = _cv2()
    map_x, map_y = cv2.initUndistortRectifyMap(
        _to_opencv(K),
        np.asarray(coeffs, dtype=np.float64),
        None,
        _to_opencv(K_pinhole),
        (int(width), int(height)),
        cv2.CV_32FC1,
    )
    return np.stack([map_x, map_y], axis=-1) + np.float32(0.5)


def undistort_labels(labels: np.ndarray, mapping: np.ndarray, *, fill: int = -1) -> np.ndarray:
    """Warp per-pixel labels (mask ids) of an image file into the pinhole camera, nearest neighbour.

    Args:
        labels: [..., H, W] integer labels on the image file's pixel grid (e.g. LangSplat's
            [4, H, W] mask ids).
        mapping: [H', W', 2] from :func:`undistortion_map`.
        fill: the label of pinhole pixels whose ray leaves the image file (−1 = none).

    Returns:
        [..., H', W'] labels: each pinhole pixel takes the label of the file pixel its ray hits.
    """
    height, width = labels.shape[-2:]
    cols = np.floor(mapping[..., 0]).astype(np.int64)
    rows = np.floor(mapping[..., 1]).astype(np.int64)
    inside = (cols >= 0) & (cols < width) & (rows >= 0) & (rows < height)
    out = labels[..., np.clip(rows, 0, height - 1), np.clip(cols, 0, width - 1)]
    out[..., ~inside] = fill
    return out


def undistort_image(image: np.ndarray, mapping: np.ndarray) -> np.ndarray:
    """Warp an image file into the pinhole camera, bilinear (OpenCV's ``remap``), black outside.

    Args:
        image: [H, W] or [H, W, C] image (uint8 or float) on the image file's pixel grid.
        mapping: [H', W', 2] from :func:`undistortion_map`.

    Returns:
        [H', W'] or [H', W', C] of the same dtype.
    """
    cv2 = _cv2()
    shifted = mapping - np.float32(0.5)
    return cv2.remap(
        np.ascontiguousarray(image),
        np.ascontiguousarray(shifted[..., 0]),
        np.ascontiguousarray(shifted[..., 1]),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )
