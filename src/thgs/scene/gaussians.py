"""The Gaussians of a trained scene as stored (pre-activation), with activating accessors."""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from thgs.errors import InputError

__all__ = ["SH_C0", "Gaussians", "quaternions_to_matrices", "sh_basis"]

SH_C0 = 0.28209479177387814
"""Degree-0 real spherical-harmonics constant: colour = 0.5 + SH_C0 · DC coefficient."""


def sh_basis(directions: Tensor, degree: int) -> Tensor:
    """[N, (degree + 1)²] real spherical harmonics of unit ``directions`` [N, 3], in the order
    and with the signs of 3DGS's ``eval_sh`` (degree ≤ 3): coefficient ``k`` of a Gaussian's
    ``sh[:, k]`` multiplies column ``k``."""
    if not 0 <= degree <= 3:
        raise InputError("sh degree", f"must be 0–3, got {degree}")
    x, y, z = directions.unbind(-1)
    columns = [torch.full_like(x, SH_C0)]
    if degree >= 1:
        c1 = 0.4886025119029199
        columns += [-c1 * y, c1 * z, -c1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        columns += [
            1.0925484305920792 * x * y,
            -1.0925484305920792 * y * z,
            0.31539156525252005 * (2.0 * zz - xx - yy),
            -1.0925484305920792 * x * z,
            0.5462742152960396 * (xx - yy),
        ]
    if degree >= 3:
        columns += [
            -0.5900435899266435 * y * (3.0 * xx - yy),
            2.890611442640554 * x * y * z,
            -0.4570457994644658 * y * (4.0 * zz - xx - yy),
            0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            -0.4570457994644658 * x * (4.0 * zz - xx - yy),
            1.445305721320277 * z * (xx - yy),
            -0.5900435899266435 * x * (xx - 3.0 * yy),
        ]
    return torch.stack(columns, dim=-1)


logger = logging.getLogger(__name__)

_SH_COEFFS_PER_DEGREE = {1: 0, 4: 1, 9: 2, 16: 3}


def quaternions_to_matrices(quats: Tensor) -> Tensor:
    """[N, 3, 3] rotation matrices of [N, 4] quaternions (w, x, y, z), normalised first.

    Computed in the quaternions' dtype; column j is the image of the unit vector along axis j.
    """
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


@dataclass(frozen=True, eq=False)
class Gaussians:
    """N Gaussians (2DGS surfels or 3DGS ellipsoids) with their parameters exactly as stored.

    All tensors share one device and one floating dtype (float32 when read from a PLY). Values are
    the trainers' raw parameters; use the accessors for activated ones. See docs/conventions.md.

    Attributes:
        means: [N, 3] centres, world frame, scene units.
        quats: [N, 4] rotations as quaternions (w, x, y, z) = PLY ``rot_0..3``; not necessarily
            unit length, never zero.
        scales: [N, 2] (2DGS: in-plane axes of a surfel) or [N, 3] (3DGS) log standard deviations,
            scene units after ``exp``.
        opacities: [N] logits; ``sigmoid`` gives the opacity in [0, 1].
        sh: [N, K, 3] spherical-harmonics coefficients, K = (degree + 1)², ``sh[:, 0]`` is the DC
            term (PLY ``f_dc_0..2``), ``sh[:, 1:, c]`` is PLY
            ``f_rest_{c·(K−1)} … f_rest_{c·(K−1)+K−2}`` (channel-major).
        normals: [N, 3] the PLY's ``nx, ny, nz`` if it had them (trainers write zeros), else None.
            Carried for round trips only; :meth:`surface_normals` gives geometric normals.
        extras: other per-Gaussian PLY properties, name → [N] NumPy array, in file order, kept
            unchanged so that exports preserve them.
    """

    means: Tensor
    quats: Tensor
    scales: Tensor
    opacities: Tensor
    sh: Tensor
    normals: Tensor | None = None
    extras: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def kind(self) -> Literal["2dgs", "3dgs"]:
        """ "2dgs" for 2 scales per Gaussian (surfels), "3dgs" for 3 (ellipsoids)."""
        return "2dgs" if self.scales.shape[-1] == 2 else "3dgs"

    @property
    def sh_degree(self) -> int:
        """Spherical-harmonics degree (0–3), from K = (degree + 1)²."""
        return round(math.sqrt(self.sh.shape[1])) - 1

    @property
    def device(self) -> torch.device:
        return self.means.device

    def activated_opacities(self) -> Tensor:
        """[N] opacities in [0, 1] (sigmoid of the stored logits)."""
        return torch.sigmoid(self.opacities)

    def activated_scales(self) -> Tensor:
        """[N, 2|3] standard deviations along the local axes, scene units (exp of the logs)."""
        return torch.exp(self.scales)

    def unit_quats(self) -> Tensor:
        """[N, 4] unit quaternions (w, x, y, z)."""
        return torch.nn.functional.normalize(self.quats, dim=-1)

    def rotation_matrices(self) -> Tensor:
        """[N, 3, 3] local→world rotations; column j is the world direction of local axis j."""
        return quaternions_to_matrices(self.quats)

    def surface_normals(self) -> Tensor:
        """[N, 3] unit normals in the world frame, sign as given by the rotation.

        2DGS: the surfel normal, the third column of the rotation matrix. 3DGS: the local axis with
        the smallest scale.
        """
        rotations = self.rotation_matrices()
        if self.kind == "2dgs":
            return rotations[:, :, 2]
        axis = self.scales.argmin(dim=-1)
        return rotations.gather(2, axis.view(-1, 1, 1).expand(-1, 3, 1)).squeeze(-1)

    def dc_colors(self) -> Tensor:
        """[N, 3] view-independent RGB in [0, 1]: ``clamp(0.5 + SH_C0 · sh[:, 0], 0, 1)``."""
        return (0.5 + SH_C0 * self.sh[:, 0]).clamp(0.0, 1.0)

    def view_colors(self, camera_centre: Tensor | np.ndarray) -> Tensor:
        """[N, 3] RGB in [0, 1] seen from ``camera_centre`` ([3], world frame): the real
        spherical harmonics of degree :attr:`sh_degree` evaluated along the unit direction from
        the camera to each centre, plus 0.5, clamped (3DGS's colour model; degree 0 gives
        :meth:`dc_colors`)."""
        centre = torch.as_tensor(camera_centre, dtype=self.means.dtype, device=self.device)
        direction = self.means - centre.reshape(1, 3)
        direction = direction / direction.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        basis = sh_basis(direction, self.sh_degree)
        return (0.5 + torch.einsum("nk,nkc->nc", basis, self.sh)).clamp(0.0, 1.0)

    def select(self, index: Tensor | np.ndarray) -> Gaussians:
        """The Gaussians at ``index`` ([N] bool mask or [M] int64 indices), in that order."""
        index_t = torch.as_tensor(index, device=self.device)
        index_np = index_t.cpu().numpy()
        return Gaussians(
            means=self.means[index_t],
            quats=self.quats[index_t],
            scales=self.scales[index_t],
            opacities=self.opacities[index_t],
            sh=self.sh[index_t],
            normals=None if self.normals is None else self.normals[index_t],
            extras={name: values[index_np] for name, values in self.extras.items()},
        )

    def to(self, device: torch.device | str) -> Gaussians:
        """A copy on ``device`` (extras stay NumPy arrays)."""
        return Gaussians(
            means=self.means.to(device),
            quats=self.quats.to(device),
            scales=self.scales.to(device),
            opacities=self.opacities.to(device),
            sh=self.sh.to(device),
            normals=None if self.normals is None else self.normals.to(device),
            extras=dict(self.extras),
        )

    def state_key(self) -> tuple:
        """A key that changes whenever a tensor of these Gaussians is modified in place (the
        tensors themselves cannot be replaced): what caches of derived values compare."""
        tensors = (self.means, self.quats, self.scales, self.opacities, self.sh, self.normals)
        return tuple((id(t), t._version) for t in tensors if t is not None)

    def check(self, source: str = "Gaussians") -> Gaussians:
        """Verify shapes, dtypes, devices and values; raise :class:`InputError` naming ``source``.

        Invariants: N consistent across fields; scales [N, 2] or [N, 3]; sh [N, K, 3] with K in
        {1, 4, 9, 16}; one floating dtype and one device; every value finite; log-scales small
        enough that the variance ``exp(2 · scale)`` is finite in their dtype (≤ 44.36 in
        float32); no zero quaternion.
        Returns ``self`` so that it can be chained. A check that passed is remembered until a
        tensor is modified in place (rendering checks its Gaussians at every call; a scan of
        every value of 1M Gaussians takes about half a second).
        """
        if self.__dict__.get("_checked") == self.state_key():
            return self
        n = len(self)
        expected = {
            "means": (self.means, (n, 3)),
            "quats": (self.quats, (n, 4)),
            "opacities": (self.opacities, (n,)),
        }
        if self.normals is not None:
            expected["normals"] = (self.normals, (n, 3))
        if self.means.ndim != 2:
            raise InputError(source, f"means must be [N, 3], got shape {tuple(self.means.shape)}")
        for name, (tensor, shape) in expected.items():
            if tuple(tensor.shape) != shape:
                raise InputError(source, f"{name} must be {list(shape)}, got {list(tensor.shape)}")
        if (
            self.scales.ndim != 2
            or self.scales.shape[0] != n
            or (self.scales.shape[-1] not in (2, 3))
        ):
            raise InputError(
                source,
                f"scales must be [N, 2] (2DGS) or [N, 3] (3DGS) with N = {n}, "
                f"got {list(self.scales.shape)}",
            )
        if (
            self.sh.ndim != 3
            or self.sh.shape[0] != n
            or self.sh.shape[2] != 3
            or (self.sh.shape[1] not in _SH_COEFFS_PER_DEGREE)
        ):
            raise InputError(
                source, f"sh must be [N, K, 3] with K in 1, 4, 9, 16, got {list(self.sh.shape)}"
            )
        tensors = {
            "means": self.means,
            "quats": self.quats,
            "scales": self.scales,
            "opacities": self.opacities,
            "sh": self.sh,
        }
        if self.normals is not None:
            tensors["normals"] = self.normals
        for name, tensor in tensors.items():
            if not tensor.is_floating_point() or tensor.dtype != self.means.dtype:
                raise InputError(
                    source, f"{name} has dtype {tensor.dtype}, expected {self.means.dtype}"
                )
            if tensor.device != self.device:
                raise InputError(source, f"{name} is on {tensor.device}, means on {self.device}")
            bad = ~torch.isfinite(tensor.reshape(n, -1)).all(dim=-1)
            if bool(bad.any()):
                first = int(bad.nonzero()[0, 0])
                raise InputError(
                    source,
                    f"{name} has NaN or infinite values in {int(bad.sum())} Gaussians "
                    f"(first: Gaussian {first}, value {tensor[first].tolist()})",
                )
        limit = math.log(torch.finfo(self.scales.dtype).max) / 2
        huge = (self.scales > limit).any(dim=-1)
        if bool(huge.any()):
            first = int(huge.nonzero()[0, 0])
            raise InputError(
                source,
                f"{int(huge.sum())} Gaussians have log-scales above {limit:.1f} (up to "
                f"{float(self.scales.max()):.4g}; first: Gaussian {first}), whose variance "
                f"exp(2 · scale) overflows {self.scales.dtype}; scales must be log standard "
                "deviations",
            )
        zero = (self.quats == 0).all(dim=-1)
        if bool(zero.any()):
            first = int(zero.nonzero()[0, 0])
            raise InputError(
                source,
                f"{int(zero.sum())} Gaussians have a zero quaternion, which is no rotation "
                f"(first: Gaussian {first})",
            )
        for name, values in self.extras.items():
            if values.shape != (n,):
                raise InputError(source, f"extra property {name!r} must be [N], got {values.shape}")
        object.__setattr__(self, "_checked", self.state_key())
        return self


VISIBLE_OPACITY = 1 / 255
"""The opacity below which 3DGS's and gsplat's rasterizers skip a Gaussian's contribution."""


def warn_if_invisible(gaussians: Gaussians, source: str) -> None:
    """Log a warning naming ``source`` when every Gaussian's opacity is below
    :data:`VISIBLE_OPACITY`: nothing of the scene would show in a render and no mask could be
    lifted onto it (the opacities are probably not logits, or the file is not a trained scene)."""
    opacity = torch.sigmoid(gaussians.opacities)
    if len(gaussians) and bool((opacity < VISIBLE_OPACITY).all()):
        logger.warning(
            "%s: all %d Gaussians have an opacity below 1/255 (at most %.3g), so nothing of the "
            "scene is visible; opacities must be logits (sigmoid gives the opacity)",
            source,
            len(gaussians),
            float(opacity.max()),
        )
