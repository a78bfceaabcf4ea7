"""Pinhole cameras: world→camera poses in OpenCV axes and intrinsics in pixels."""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import PurePosixPath

import numpy as np
import torch
from torch import Tensor

from thgs.errors import InputError
from thgs.scene.distortion import Distortion, pinhole_camera, undistortion_map

__all__ = ["MAX_IMAGE_SIDE", "Cameras", "refuse_distortion", "round_half_up", "viewmat_from_pose"]

MAX_IMAGE_SIDE = 1 << 20
"""The largest image width or height a camera file may state (1,048,576 pixels); larger values
are corrupt files, not cameras."""


def round_half_up(value: float) -> int:
    """Round to the nearest integer, halves up (164.5 → 165), as image resizers do."""
    return math.floor(value + 0.5)


def refuse_distortion(cameras: Cameras, path: str | os.PathLike[str]) -> None:
    """Raise :class:`InputError` naming ``path`` if ``cameras`` describe distorted image files:
    the camera writers store pinhole cameras, which would not fit those files."""
    if cameras.distortion is not None:
        raise InputError(
            path,
            "the cameras' image files have lens distortion and this format would store them as "
            "pinhole cameras; write undistorted images (thgs.scene.distortion.undistort_image) "
            "and dataclasses.replace(cameras, distortion=None)",
        )


def viewmat_from_pose(rotation: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """[4, 4] world→camera from a [3, 3] camera→world rotation and the [3] camera centre."""
    viewmat = np.eye(4)
    viewmat[:3, :3] = rotation.T
    viewmat[:3, 3] = -rotation.T @ centre
    return viewmat


@dataclass(frozen=True, eq=False)
class Cameras:
    """M undistorted pinhole cameras.

    Every reader converts its format into this once; nothing else in thgs knows about OpenGL,
    COLMAP or nerfstudio conventions. See docs/conventions.md.

    Image files taken through a distorting lens are described by the pinhole cameras they are
    undistorted into (:func:`thgs.scene.distortion.pinhole_camera`, as gsplat and nerfstudio do
    before training) plus :attr:`distortion`, the lens as calibrated: per-pixel data made on the
    image files (SAM masks) is warped into these cameras with :meth:`undistortion_map`.

    Attributes:
        viewmats: [M, 4, 4] float64 world→camera transforms, OpenCV camera axes (x right, y down,
            z forward): ``p_cam = R · p_world + t``. Scene units.
        Ks: [M, 3, 3] float64 intrinsics in pixels for the image of size ``widths[i] × heights[i]``;
            the point ``(x, y, z)`` in camera space lands at continuous pixel coordinates
            ``(fx·x/z + cx, fy·y/z + cy)``, and pixel ``(u, v)`` (column, row) covers
            ``[u, u+1) × [v, v+1)``, its centre at ``(u + 0.5, v + 0.5)``.
        widths: [M] int64 image widths in pixels.
        heights: [M] int64 image heights in pixels.
        names: M image names as the source states them (``DSC_5283.jpg`` from COLMAP,
            ``DSC_5283`` from cameras.json, ``images/frame_00001.png`` from transforms.json).
            :attr:`stems` (the file name without folder and extension) identify views across
            formats and guidance files, as in 3DGS and LangSplat.
        distortion: the distorted cameras of the image files (:class:`Distortion`, M rows), or
            None when the image files are the pinhole images themselves.
    """

    viewmats: Tensor
    Ks: Tensor
    widths: Tensor
    heights: Tensor
    names: tuple[str, ...]
    distortion: Distortion | None = None

    def __len__(self) -> int:
        return int(self.viewmats.shape[0])

    @classmethod
    def from_lists(
        cls,
        viewmats: Sequence[np.ndarray],
        Ks: Sequence,
        widths: Sequence[int],
        heights: Sequence[int],
        names: Sequence[str],
    ) -> Cameras:
        """Cameras from per-camera [4, 4] viewmats, [3, 3] Ks, sizes and names (not checked)."""
        return cls(
            viewmats=torch.tensor(np.stack(viewmats), dtype=torch.float64),
            Ks=torch.tensor(np.asarray(Ks), dtype=torch.float64),
            widths=torch.tensor(widths, dtype=torch.int64),
            heights=torch.tensor(heights, dtype=torch.int64),
            names=tuple(names),
        )

    @classmethod
    def from_distorted(
        cls,
        viewmats: Sequence[np.ndarray],
        Ks: Sequence,
        coeffs: Sequence,
        widths: Sequence[int],
        heights: Sequence[int],
        names: Sequence[str],
        source: str = "cameras",
    ) -> Cameras:
        """The pinhole cameras of image files taken through distorting lenses.

        Args:
            viewmats: M [4, 4] world→camera transforms.
            Ks: M [3, 3] intrinsics of the image files (pixels, thgs's convention).
            coeffs: M [8] OpenCV coefficients ``(k1, k2, p1, p2, k3, k4, k5, k6)``.
            widths, heights: the image files' sizes.
            names: image names.
            source: the file they come from, for errors.

        Returns:
            Cameras whose K and size are :func:`thgs.scene.distortion.pinhole_camera`'s, with
            :attr:`distortion` set, or plain cameras when every coefficient is zero.
        """
        coeffs_array = np.asarray(coeffs, dtype=np.float64).reshape(len(names), 8)
        if not coeffs_array.any():
            return cls.from_lists(viewmats, Ks, widths, heights, names)
        distortion = Distortion(
            torch.tensor(np.asarray(Ks), dtype=torch.float64),
            torch.from_numpy(coeffs_array),
            torch.tensor(widths, dtype=torch.int64),
            torch.tensor(heights, dtype=torch.int64),
        )
        return cls._undistorted(torch.tensor(np.stack(viewmats)), distortion, tuple(names), source)

    @classmethod
    def _undistorted(
        cls,
        viewmats: Tensor,
        distortion: Distortion,
        names: tuple[str, ...],
        source: str = "cameras",
    ):
        pinholes = [
            pinhole_camera(
                distortion.Ks[i].numpy(),
                distortion.coeffs[i].numpy(),
                int(distortion.widths[i]),
                int(distortion.heights[i]),
                source=f"{source}, camera {names[i]}",
            )
            for i in range(len(distortion))
        ]
        return cls(
            viewmats=viewmats.to(torch.float64),
            Ks=torch.tensor(np.stack([K for K, _, _ in pinholes]), dtype=torch.float64),
            widths=torch.tensor([w for _, w, _ in pinholes], dtype=torch.int64),
            heights=torch.tensor([h for _, _, h in pinholes], dtype=torch.int64),
            names=names,
            distortion=distortion,
        )

    def file_sizes(self) -> tuple[Tensor, Tensor]:
        """``(widths, heights)``, [M] int64 each: the sizes of the image files, which are the
        distorted images' where :attr:`distortion` is set and the cameras' own otherwise."""
        if self.distortion is None:
            return self.widths, self.heights
        return self.distortion.widths, self.distortion.heights

    def undistortion_map(self, index: int) -> np.ndarray | None:
        """Where each pixel of camera ``index`` looks in its (distorted) image file.

        Returns:
            [H, W, 2] float32 continuous image-file coordinates per pixel of this camera (see
            :func:`thgs.scene.distortion.undistortion_map`), or None when the image file needs
            no warp (no distortion).
        """
        distortion = self.distortion
        if distortion is None or not distortion.distorted(index):
            return None
        return undistortion_map(
            distortion.Ks[index].numpy(),
            distortion.coeffs[index].numpy(),
            self.Ks[index].numpy(),
            int(self.widths[index]),
            int(self.heights[index]),
        )

    def with_file_sizes(
        self, widths: Tensor | Sequence[int], heights: Tensor | Sequence[int]
    ) -> Cameras:
        """The cameras of the same image files resized to ``widths × heights`` ([M] each).

        Without distortion this is :meth:`resized`; with it, the distorted cameras are resized
        and the pinhole cameras recomputed at the new size (as gsplat does for its
        downscaled image folders).
        """
        if self.distortion is None:
            return self.resized(widths, heights)
        widths = torch.as_tensor(widths, dtype=torch.int64).reshape(len(self))
        heights = torch.as_tensor(heights, dtype=torch.int64).reshape(len(self))
        if bool((widths <= 0).any() or (heights <= 0).any()):
            raise InputError("Cameras.with_file_sizes", "image sizes must be positive")
        return Cameras._undistorted(
            self.viewmats.clone(), self.distortion.resized(widths, heights), self.names
        )

    @property
    def stems(self) -> tuple[str, ...]:
        """Image file names without folders and extension; unique per camera."""
        return tuple(PurePosixPath(name.replace("\\", "/")).stem for name in self.names)

    def camtoworlds(self) -> Tensor:
        """[M, 4, 4] camera→world transforms (OpenCV axes); column 3 is the camera centre."""
        camtoworlds = torch.zeros_like(self.viewmats)
        camtoworlds[:, :3, :3] = self.viewmats[:, :3, :3].transpose(1, 2)
        camtoworlds[:, :3, 3] = self.centers()
        camtoworlds[:, 3, 3] = 1.0
        return camtoworlds

    def centers(self) -> Tensor:
        """[M, 3] camera centres in world coordinates: ``−Rᵀ t``."""
        rotation = self.viewmats[:, :3, :3]
        translation = self.viewmats[:, :3, 3:]
        return -(rotation.transpose(1, 2) @ translation)[:, :, 0]

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Project world points into every camera.

        Args:
            points: [P, 3] world coordinates.

        Returns:
            ``(pixels, depths)``: [M, P, 2] continuous pixel coordinates (x = column, y = row;
            pixel (u, v) has its centre at (u + 0.5, v + 0.5)) and [M, P] camera-space z (scene
            units; points with z ≤ 0 are behind the camera and their pixels meaningless).
        """
        points = points.to(self.viewmats.dtype)
        cam = points @ self.viewmats[:, :3, :3].transpose(1, 2) + self.viewmats[:, None, :3, 3]
        depths = cam[..., 2]
        image = cam @ self.Ks.transpose(1, 2)
        return image[..., :2] / image[..., 2:3], depths

    def resized(self, widths: Tensor | Sequence[int], heights: Tensor | Sequence[int]) -> Cameras:
        """The same cameras for images resized to ``widths × heights`` ([M] each).

        Intrinsics scale per axis by ``new / old`` size, which keeps the field of view and the
        pixel-centre convention exact (a resize maps the image rectangle onto itself). The image
        files (:attr:`distortion`) stay as they are: :meth:`undistortion_map` then warps them to
        the new size. For image files of another size, use :meth:`with_file_sizes`.
        """
        widths = torch.as_tensor(widths, dtype=torch.int64).reshape(len(self))
        heights = torch.as_tensor(heights, dtype=torch.int64).reshape(len(self))
        if bool((widths <= 0).any() or (heights <= 0).any()):
            raise InputError("Cameras.resized", "image sizes must be positive")
        sx = widths.double() / self.widths.double()
        sy = heights.double() / self.heights.double()
        Ks = self.Ks.clone()
        Ks[:, 0, :] *= sx[:, None]
        Ks[:, 1, :] *= sy[:, None]
        return Cameras(self.viewmats.clone(), Ks, widths, heights, self.names, self.distortion)

    def scaled(self, scale: float) -> Cameras:
        """The cameras for image files resized by ``scale`` (0.25: 4× smaller), sizes rounded
        half up (:meth:`with_file_sizes`)."""
        if not scale > 0:
            raise InputError("Cameras.scaled", f"scale must be positive, got {scale}")
        file_widths, file_heights = self.file_sizes()
        widths = [round_half_up(float(w) * scale) for w in file_widths]
        heights = [round_half_up(float(h) * scale) for h in file_heights]
        return self.with_file_sizes(widths, heights)

    def select(self, index: Sequence[int] | Tensor) -> Cameras:
        """The cameras at ``index`` ([K] int indices), in that order."""
        index_t = torch.as_tensor(index, dtype=torch.int64).reshape(-1)
        names = tuple(self.names[int(i)] for i in index_t)
        return Cameras(
            self.viewmats[index_t],
            self.Ks[index_t],
            self.widths[index_t],
            self.heights[index_t],
            names,
            None if self.distortion is None else self.distortion.select(index_t),
        )

    def check(self, source: str = "Cameras") -> Cameras:
        """Verify shapes and values; raise :class:`InputError` naming ``source``.

        Invariants: consistent M ≥ 1; float64 poses and intrinsics, finite; each rotation
        orthonormal with determinant +1 and last row (0, 0, 0, 1); K upper triangular with
        positive focal lengths and K[2, 2] = 1; positive sizes; unique, non-empty stems.
        Returns ``self``.
        """
        m = len(self)
        if m == 0:
            raise InputError(source, "no cameras")
        shapes = {
            "viewmats": (self.viewmats, (m, 4, 4)),
            "Ks": (self.Ks, (m, 3, 3)),
            "widths": (self.widths, (m,)),
            "heights": (self.heights, (m,)),
        }
        for name, (tensor, shape) in shapes.items():
            if tuple(tensor.shape) != shape:
                raise InputError(source, f"{name} must be {list(shape)}, got {list(tensor.shape)}")
        if len(self.names) != m:
            raise InputError(source, f"{len(self.names)} names for {m} cameras")
        for name in ("viewmats", "Ks"):
            tensor = getattr(self, name)
            if tensor.dtype != torch.float64:
                raise InputError(source, f"{name} must be float64, got {tensor.dtype}")
            bad = ~torch.isfinite(tensor.reshape(m, -1)).all(dim=-1)
            if bool(bad.any()):
                raise InputError(
                    source,
                    f"{name} of camera {self.names[int(bad.nonzero()[0, 0])]!r} is not finite",
                )
        for i in range(m):
            self._check_one(i, source)
        if self.distortion is not None:
            self.distortion.check(m, source)
        stems = self.stems
        if len(set(stems)) != m:
            seen: set[str] = set()
            duplicates = sorted({stem for stem in stems if stem in seen or seen.add(stem)})
            raise InputError(source, f"image names are not unique per stem: {duplicates[:5]}")
        return self

    def _check_one(self, i: int, source: str) -> None:
        name = self.names[i]
        if not name or not self.stems[i]:
            raise InputError(source, f"camera {i} has an empty image name")
        viewmat = self.viewmats[i].numpy()
        rotation = viewmat[:3, :3]
        if not np.allclose(viewmat[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise InputError(source, f"camera {name!r}: viewmat last row is {viewmat[3].tolist()}")
        if (
            not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5)
            or np.linalg.det(rotation) < 0
        ):
            raise InputError(source, f"camera {name!r}: viewmat rotation is not a proper rotation")
        K = self.Ks[i].numpy()
        if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise InputError(source, f"camera {name!r}: K is not a pinhole matrix: {K.tolist()}")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise InputError(
                source, f"camera {name!r}: focal lengths must be positive: {K.tolist()}"
            )
        if int(self.widths[i]) <= 0 or int(self.heights[i]) <= 0:
            raise InputError(
                source, f"camera {name!r}: size {int(self.widths[i])}×{int(self.heights[i])}"
            )
