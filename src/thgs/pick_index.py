"""Which Gaussians can show at one pixel: a spatial index that makes a pick cost O(Gaussians near
the clicked ray) instead of O(N).

:class:`PickIndex` cuts the Gaussians, in Morton (Z-curve) order of their centres, into cells of
``cell_size`` and keeps per cell a ball holding its centres, its largest scale and its largest
opacity. :meth:`PickIndex.candidates` tests every cell (vectorized, N / cell_size of them), then
every member of the cells that pass, and returns a superset of the Gaussians whose α reaches
``alpha_min`` at the pixel's centre: those that :func:`thgs.render.render` composites there.
Rendering only them, in index order, gives exactly the full render's pixel (same depth order,
ties by index; the others are skipped there anyway), which is what :func:`thgs.views.pick` does.

The bound, in the camera frame (x right, y down, z forward), for pixel (x, y) of a camera with
focal lengths fx, fy and principal point (cx, cy): the ray through the pixel's centre has the
direction ``d = (dx, dy, 1)``, ``dx = (x + ½ − cx) / fx``, ``dy = (y + ½ − cy) / fy``. A point p
is offset from it by ``L(p) = (p_x − dx p_z, p_y − dy p_z)`` at its own depth; L is linear with
norm ``|d|``, p's distance to the line is ≥ ``|L(p)| / |d|``, and p projects at least
``f_min |L(p)| / p_z`` pixels from the pixel's centre (``f_min = min(fx, fy)``).

A Gaussian (centre μ at depth z, opacity o, largest activated scale s) has α ≥ alpha_min only
where its σ ≤ k²/2, ``k = √(2 ln(o / alpha_min))`` (never if o < alpha_min), and only with
near < z < far. Then:

- 3DGS: ``σ = ½ δᵀ (J Σ Jᵀ + eps2d I)⁻¹ δ`` with δ the pixel's offset from the projected centre,
  so ``|δ| ≤ k (‖J‖ s + √eps2d)``. ``J = diag(fx, fy) [[1, 0, −a], [0, 1, −b]] / z`` with (a, b)
  the centre's x/z, y/z clamped to 1.3× the half field of view of the camera rendered through —
  the pick's 1×1 camera, so ``|a| ≤ |dx| + 0.65 / fx`` (and b alike) — hence
  ``‖J‖ ≤ f_max √(1 + a² + b²) / z`` and
  ``|L(μ)| ≤ k s G + k √eps2d z / f_min``, ``G = (f_max / f_min) √(1 + a² + b²)``.
- 2DGS: ``σ = ½ min(ρ3d, ρ2d)``. ρ3d ≤ k²: the pixel's line meets the surfel's plane within
  k s of μ, so ``|L(μ)| ≤ |d| k s``. ρ2d ≤ k²: the pixel's centre is within ``r = k /
  √filter_inv_square`` pixels of the filter centre c, the centre of the image of the surfel's 1σ
  ellipse. When that ellipse lies in front of the camera (always when s < z: its depths are
  within s of z), c is the image of one of its points q (|q − μ| ≤ s, depth ≤ z + s), whose
  distance to the line is then ≤ ``r (z + s) / f_min``, so ``|L(μ)| ≤ |d| (s + r (z + s) /
  f_min)``. A surfel as large as its distance (s ≥ 0.999 z here) may put c anywhere: it is always
  a candidate.

Each reach is ``A + B z``, increasing in o, s and z; one more pixel (z / f_min) and 10⁻⁶ on
``ln(o / alpha_min)`` absorb rounding. A cell whose centres lie within R of C has, for every
member, ``|L(μ)| ≥ |L(C)| − |d| R`` and a depth in ``[z_C − R, z_C + R]``, so evaluating the reach
at the cell's largest opacity and scale and at depth ``min(z_C + R, far)`` keeps every cell that
holds a candidate. gsplat fixes alpha_min at 1/255 and filter_inv_square at 2 (RasterConfig), so
with it the smaller of these and the config's values are used.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
import torch

from thgs._spatial import spatial_order
from thgs.errors import InputError
from thgs.render import RasterConfig, resolve_backend
from thgs.scene import Cameras, Gaussians

__all__ = ["PickIndex", "check_pixel"]

logger = logging.getLogger(__name__)

_LOG_SLACK = 1e-6
"""Added to ``ln(o / alpha_min)``: the renderer lets σ exceed that reach by 1e-9 (rounding)."""

_SLACK_PX = 1.0
"""Pixels added to every reach for rounding (ray direction, projected centres)."""

_CLAMP_PX = 1.0
"""3DGS's Jacobian clamp reaches 0.65 px beyond the pixel's centre in a 1×1 camera; rounded up."""

_HUGE = 0.999
"""A 2DGS surfel with s ≥ _HUGE · z may have its 1σ ellipse behind the camera: always kept."""

_DEPTH_SLACK = 1e-9
"""Relative slack on the near and far planes (the renderer computes depths its own way)."""


def check_pixel(camera: Cameras, pixel: tuple[int, int]) -> tuple[int, int]:
    """``pixel`` as ``(x, y)`` ints after checking that ``camera`` is one camera and the pixel is
    inside its image.

    Raises:
        InputError: several cameras, or a pixel outside the image (named by the camera's stem).
    """
    if len(camera) != 1:
        raise InputError("pick", f"expected one camera, got {len(camera)}")
    x, y = (int(v) for v in pixel)
    width, height = int(camera.widths[0]), int(camera.heights[0])
    if not (0 <= x < width and 0 <= y < height):
        raise InputError(camera.stems[0], f"pixel ({x}, {y}) is outside the {width}×{height} image")
    return x, y


@dataclass(frozen=True)
class _Ray:
    """One pixel's ray and the constants of the reach (module docstring), float64."""

    kind: str
    rotation: np.ndarray  # [3, 3] world → camera
    translation: np.ndarray  # [3]
    dx: float
    dy: float
    norm: float  # |d|
    f_min: float
    gain: float  # 3DGS: G
    near: float
    far: float
    alpha_min: float
    eps2d: float
    filter_inv_square: float

    @classmethod
    def through(
        cls, gaussians: Gaussians, camera: Cameras, x: int, y: int, config: RasterConfig
    ) -> _Ray:
        backend, _ = resolve_backend(config, gaussians.device)
        alpha_min, filter_inv_square = config.alpha_min, config.filter_inv_square
        if backend.name == "gsplat":
            alpha_min, filter_inv_square = min(alpha_min, 1 / 255), min(filter_inv_square, 2.0)
        viewmat = camera.viewmats[0].to(torch.float64).numpy()
        K = camera.Ks[0].to(torch.float64).numpy()
        fx, fy, cx, cy = abs(K[0, 0]), abs(K[1, 1]), K[0, 2], K[1, 2]
        dx, dy = (x + 0.5 - cx) / K[0, 0], (y + 0.5 - cy) / K[1, 1]
        a, b = abs(dx) + _CLAMP_PX / fx, abs(dy) + _CLAMP_PX / fy
        f_min = min(fx, fy)
        return cls(
            kind=gaussians.kind,
            rotation=viewmat[:3, :3],
            translation=viewmat[:3, 3],
            dx=dx,
            dy=dy,
            norm=math.sqrt(1 + dx * dx + dy * dy),
            f_min=f_min,
            gain=max(fx, fy) / f_min * math.sqrt(1 + a * a + b * b),
            near=config.near,
            far=config.far,
            alpha_min=alpha_min,
            eps2d=config.eps2d,
            filter_inv_square=filter_inv_square,
        )

    def camera_frame(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Depths [M] and ray offsets |L| [M] of world points [M, 3]."""
        # R μ + t by columns: several times faster than a [M, 3] @ [3, 3] product
        x, y, z = (
            sum(points[:, j] * self.rotation[i, j] for j in range(3)) + self.translation[i]
            for i in range(3)
        )
        return z, np.hypot(x - self.dx * z, y - self.dy * z)

    def opaque(self, opacities: np.ndarray) -> np.ndarray:
        """[M] bool: opacity can reach alpha_min."""
        return np.log(opacities / self.alpha_min) >= -_LOG_SLACK

    def reach(self, opacities: np.ndarray, scales: np.ndarray, z: np.ndarray) -> np.ndarray:
        """[M] the largest |L(μ)| at which a Gaussian of this opacity, scale and depth can still
        reach alpha_min at the pixel (module docstring)."""
        k = np.sqrt(2 * (np.maximum(np.log(opacities / self.alpha_min), 0.0) + _LOG_SLACK))
        if self.kind == "3dgs":
            return k * scales * self.gain + (k * math.sqrt(self.eps2d) + _SLACK_PX) * z / self.f_min
        r = k / math.sqrt(self.filter_inv_square)
        near_part = self.norm * scales * np.maximum(k, 1 + r / self.f_min)
        return near_part + (self.norm * r + _SLACK_PX) * z / self.f_min

    def huge(self, scales: np.ndarray, z: np.ndarray) -> np.ndarray:
        """[M] bool: 2DGS surfels whose filter centre is unbounded (always kept)."""
        return (scales >= _HUGE * z) if self.kind == "2dgs" else np.zeros(len(z), dtype=bool)


@dataclass(frozen=True, eq=False)
class PickIndex:
    """N Gaussians grouped into cells of nearby centres, built once per scene by :meth:`build`.

    It keeps what the bound needs of each Gaussian (centre, largest scale, opacity) in cell order,
    so a pick reads contiguous memory and never the scene's tensors; it does not depend on the
    camera or the rasterization settings. Rebuild it when the Gaussians change.

    Attributes:
        kind: ``"2dgs"`` or ``"3dgs"``, the Gaussians' kind.
        cell_size: Gaussians per cell (the last cell may hold fewer).
        order: [N] int64 Gaussian indices in Morton order of their centres; position i of the
            arrays below is Gaussian ``order[i]``, and cell c holds positions
            ``c · cell_size … (c + 1) · cell_size − 1``.
        means: [N, 3] float64 centres, world frame, scene units, in cell order.
        scales: [N] float64 largest activated scale of each Gaussian (scene units), in cell order.
        opacities: [N] float64 activated opacities, in cell order.
        centers: [C, 3] float64, world frame: the centre of each cell's bounding box of centres.
        radii: [C] float64, scene units: every member's centre lies within this of its cell's
            centre.
        max_scales: [C] float64: each cell's largest ``scales``.
        max_opacities: [C] float64: each cell's largest ``opacities``.
    """

    kind: str
    cell_size: int
    order: np.ndarray
    means: np.ndarray
    scales: np.ndarray
    opacities: np.ndarray
    centers: np.ndarray
    radii: np.ndarray
    max_scales: np.ndarray
    max_opacities: np.ndarray

    def __len__(self) -> int:
        return len(self.order)

    @classmethod
    def build(cls, gaussians: Gaussians, *, cell_size: int = 64) -> PickIndex:
        """Index ``gaussians``: a Morton sort of the centres, then per-cell bounds; O(N log N).

        Args:
            gaussians: N Gaussians (2DGS or 3DGS), world frame.
            cell_size: Gaussians per cell: smaller cells fit the ray tighter (fewer members
                tested per pick), larger ones make the per-cell test (N / cell_size cells per
                pick) cheaper. With ``cell_size ≥ N`` there is one cell and no sort (O(N)): every
                pick then tests every Gaussian, which suits a single pick.

        Raises:
            InputError: ``cell_size`` < 1.
        """
        if cell_size < 1:
            raise InputError("PickIndex.cell_size", f"must be ≥ 1, got {cell_size}")
        means = gaussians.means.detach().to("cpu", torch.float64).numpy()
        n = len(means)
        # one cell needs no order (every member is tested): a one-off pick skips the sort
        order = spatial_order(means) if n > cell_size else np.arange(n)
        index = torch.from_numpy(order).to(gaussians.device)
        scales = torch.exp(gaussians.scales.detach()[index].to("cpu", torch.float64)).amax(dim=1)
        opacities = torch.sigmoid(gaussians.opacities.detach()[index].to("cpu", torch.float64))
        means, scales, opacities = means[order], scales.numpy(), opacities.numpy()
        starts = np.arange(0, n, cell_size)
        low = np.minimum.reduceat(means, starts, axis=0)
        high = np.maximum.reduceat(means, starts, axis=0)
        centers = 0.5 * (low + high)
        offsets = means - np.repeat(centers, np.diff(np.append(starts, n)), axis=0)
        radii = np.sqrt(np.maximum.reduceat(np.einsum("ij,ij->i", offsets, offsets), starts))
        logger.debug("pick index: %d Gaussians in %d cells of %d", n, len(starts), cell_size)
        return cls(
            kind=gaussians.kind,
            cell_size=cell_size,
            order=order.astype(np.int64),
            means=means,
            scales=scales,
            opacities=opacities,
            centers=centers,
            radii=radii,
            max_scales=np.maximum.reduceat(scales, starts),
            max_opacities=np.maximum.reduceat(opacities, starts),
        )

    def candidates(
        self,
        gaussians: Gaussians,
        camera: Cameras,
        pixel: tuple[int, int],
        *,
        config: RasterConfig = RasterConfig(),
    ) -> np.ndarray:
        """The Gaussians that may be composited at ``pixel`` of ``camera``.

        A superset of those with α ≥ ``alpha_min`` at the pixel's centre and a centre depth in
        (near, far), i.e. of every Gaussian with a nonzero blending weight there; the bound is
        derived in the module docstring. Costs one test per cell and per member of the cells the
        pixel's ray passes near.

        Args:
            gaussians: the N Gaussians this index was built on.
            camera: one camera (``cameras.select([i])``).
            pixel: ``(x, y)`` integer pixel (column, row), inside the image.
            config: the rasterization settings the pixel will be rendered with.

        Returns:
            [M] int64 Gaussian indices, ascending (so a render of ``gaussians.select(them)``
            keeps the full render's depth order and ties).

        Raises:
            InputError: Gaussians of another count than the index's, several cameras, a pixel
                outside the image.
        """
        if len(gaussians) != len(self) or gaussians.kind != self.kind:
            raise InputError(
                "PickIndex",
                f"built for {len(self)} {self.kind.upper()} Gaussians but given {len(gaussians)} "
                f"{gaussians.kind.upper()}: build the index from the Gaussians it is used with",
            )
        x, y = check_pixel(camera, pixel)
        ray = _Ray.through(gaussians, camera, x, y, config)
        low, high = config.near * (1 - _DEPTH_SLACK), config.far * (1 + _DEPTH_SLACK)

        z, lateral = ray.camera_frame(self.centers)
        reach = ray.reach(self.max_opacities, self.max_scales, np.minimum(z + self.radii, high))
        # "not beyond reach" rather than "within reach", so that a NaN (infinite scale) keeps it
        near_ray = ~(lateral - ray.norm * self.radii > reach)
        huge = ray.huge(self.max_scales, np.maximum(z - self.radii, low))
        cells = (
            (z + self.radii > low)
            & (z - self.radii < high)
            & ray.opaque(self.max_opacities)
            & (near_ray | huge)
        )
        positions = self._positions(np.flatnonzero(cells))

        scales, opacities = self.scales[positions], self.opacities[positions]
        z, lateral = ray.camera_frame(self.means[positions])
        keep = (
            (z > low)
            & (z < high)
            & ray.opaque(opacities)
            & (~(lateral > ray.reach(opacities, scales, z)) | ray.huge(scales, z))
        )
        chosen = np.sort(self.order[positions[keep]])
        logger.debug(
            "pick (%d, %d): %d of %d cells, %d members tested, %d candidates of %d",
            x,
            y,
            int(cells.sum()),
            len(cells),
            len(positions),
            len(chosen),
            len(self),
        )
        return chosen

    def _positions(self, cells: np.ndarray) -> np.ndarray:
        """[M] int64 positions (in cell order) of the members of the given cells."""
        starts = cells * self.cell_size
        lengths = np.minimum(starts + self.cell_size, len(self)) - starts
        offsets = np.cumsum(lengths) - lengths
        return np.arange(int(lengths.sum())) + np.repeat(starts - offsets, lengths)
