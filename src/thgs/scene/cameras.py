"""Pinhole cameras: world→camera poses in OpenCV axes and intrinsics in pixels."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import PurePosixPath

import numpy as np
import torch
from torch import Tensor

from thgs.errors import InputError

__all__ = ["Cameras", "round_half_up", "viewmat_from_pose"]


def round_half_up(value: float) -> int:
    """Round to the nearest integer, halves up (164.5 → 165), as image resizers do."""
    return math.floor(value + 0.5)


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
    """

    viewmats: Tensor
    Ks: Tensor
    widths: Tensor
    heights: Tensor
    names: tuple[str, ...]

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
        pixel-centre convention exact (a resize maps the image rectangle onto itself).
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
        return Cameras(self.viewmats.clone(), Ks, widths, heights, self.names)

    def scaled(self, scale: float) -> Cameras:
        """The cameras for images resized by ``scale`` (0.25: 4× smaller), sizes rounded half up."""
        if not scale > 0:
            raise InputError("Cameras.scaled", f"scale must be positive, got {scale}")
        widths = [round_half_up(float(w) * scale) for w in self.widths]
        heights = [round_half_up(float(h) * scale) for h in self.heights]
        return self.resized(widths, heights)

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
