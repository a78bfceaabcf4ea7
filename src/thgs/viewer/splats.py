"""The scene's Gaussians as viser splat nodes: geometry sent once, colours re-sent by chunk.

viser (``SceneApi.add_gaussian_splats``) keeps one buffer per splat node in which geometry and
colour are interleaved: each Gaussian is 8 uint32 (32 bytes) ``[x, y, z, reserved, c0c1, c2c3,
c4c5, rgba]``, the centre as three float32 (world frame, scene units), a word reserved for the
renderer, the six upper-triangular covariance terms ``Σ00, Σ01, Σ02, Σ11, Σ12, Σ22`` as float16
(scene units²) and the colour as four uint8 R, G, B, A. Changing any colour therefore re-sends the
node's whole buffer, geometry included.

To keep large scenes responsive, :class:`SplatChunks` splits the scene into several splat nodes
("chunks") of at most ``chunk_size`` Gaussians. viser's client sorts the Gaussians of all splat
nodes together, so the split renders exactly like one node. The Gaussians are laid out in an
order (:func:`hierarchy_order`) in which every semantic region is a contiguous run, so colouring
one region touches few chunks; :meth:`SplatChunks.update` re-sends only the chunks whose packed
RGBA actually changed. The geometry is packed and sent once, when the chunks are created.

Colours are packed exactly as viser packs float colours (:func:`pack_rgba`): ``value · 255``,
clipped to [0, 255] and truncated towards zero, so 0.5 becomes 127 and only 1.0 becomes 255.
"""

from __future__ import annotations

import logging
from typing import TYPE_CHECKING, Any

import numpy as np
import torch

from thgs.errors import InputError
from thgs.scene import Gaussians

if TYPE_CHECKING:
    import viser

__all__ = ["SplatChunks", "hierarchy_order", "pack_rgba", "splat_covariances"]

logger = logging.getLogger(__name__)

_FLOAT16_MAX = float(np.finfo(np.float16).max)
"""Largest finite float16 (65504): larger covariance terms reach the client as infinity."""

BYTES_PER_GAUSSIAN = 32
"""Size of one Gaussian in a viser splat buffer: 8 uint32."""


def _to_numpy(value: Any) -> np.ndarray:
    """``value`` (NumPy array, torch tensor or nested sequence) as a NumPy array, not copied if
    it already is one."""
    if isinstance(value, torch.Tensor):
        value = value.detach().cpu()
        if value.dtype == torch.bfloat16:
            value = value.float()
        return value.numpy()
    return np.asarray(value)


def _finite_floats(value: Any, argument: str, shape: str) -> np.ndarray:
    """``value`` as a floating NumPy array whose values are all finite, else :class:`InputError`.

    ``shape`` is the expected shape in words, for the message only (shapes are checked by the
    callers).
    """
    array = _to_numpy(value)
    if not np.issubdtype(array.dtype, np.floating):
        raise InputError(argument, f"must be a floating {shape} array, got dtype {array.dtype}")
    if array.size == 0:
        return array
    finite = np.isfinite(array.reshape(len(array), -1)).all(axis=1)
    if not finite.all():
        first = int(np.flatnonzero(~finite)[0])
        raise InputError(
            argument,
            f"has NaN or infinite values in {int((~finite).sum())} of {len(array)} rows "
            f"(first: row {first}, value {array[first].tolist()})",
        )
    return array


def splat_covariances(gaussians: Gaussians) -> np.ndarray:
    """World-frame covariances of the Gaussians, as viser's splat nodes take them.

    ``Σ = R · diag(s²) · Rᵀ`` with ``R`` the normalised rotation (column j = world direction of
    local axis j) and ``s`` the activated scales (standard deviations, scene units). A 2DGS surfel
    has no extent along its normal, the third local axis: its covariance is flat (rank 2), with
    the normal as a null vector.

    Computed in the Gaussians' dtype on their device as ``M · Mᵀ`` with ``M = R · diag(s)``, which
    is symmetric positive semi-definite by construction.

    Args:
        gaussians: the N Gaussians (2DGS or 3DGS).

    Returns:
        [N, 3, 3] float32 covariances, world frame, scene units².

    Raises:
        InputError: ``gaussians`` is not a :class:`~thgs.scene.Gaussians`, or a covariance is not
            finite (an overflowing scale).
    """
    if not isinstance(gaussians, Gaussians):
        raise InputError("gaussians", f"must be thgs.scene.Gaussians, got {type(gaussians)}")
    n = len(gaussians)
    scales = gaussians.activated_scales()
    if tuple(scales.shape) not in ((n, 2), (n, 3)) or tuple(gaussians.quats.shape) != (n, 4):
        raise InputError(
            "gaussians",
            f"needs quats [N, 4] and scales [N, 2|3] with N = {n}, got "
            f"{list(gaussians.quats.shape)} and {list(scales.shape)}",
        )
    if scales.shape[1] == 2:
        scales = torch.cat([scales, torch.zeros_like(scales[:, :1])], dim=1)
    factors = gaussians.rotation_matrices() * scales[:, None, :]  # column j scaled by s_j
    covariances = (factors @ factors.transpose(1, 2)).float().cpu().numpy()
    bad = ~np.isfinite(covariances.reshape(n, 9)).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise InputError(
            "gaussians",
            f"{int(bad.sum())} covariances are not finite (first: Gaussian {first}, "
            f"log scales {gaussians.scales[first].tolist()})",
        )
    return covariances


def hierarchy_order(labels: Any) -> np.ndarray:
    """A layout of the Gaussians in which every region of every level is one contiguous run.

    Sorts by (last column, …, column 0, original index): coarsest level first, ties kept in their
    original order. When the levels nest (every region of a finer level lies inside one region of
    each coarser level, as in a semantic field's hierarchy) each region at each level is then one
    contiguous run of the result; when they do not, only the regions of the last column are
    guaranteed to be runs.

    Args:
        labels: [N, L] integer region ids (L ≥ 1), column 0 the finest level and the last column
            the coarsest (a semantic field's labels are [N, 4]). Any integer values, negative ones
            (e.g. "unassigned") included.

    Returns:
        [N] int64 permutation: ``order[p]`` is the Gaussian at layout position ``p``.

    Raises:
        InputError: ``labels`` is not a 2D integer array with at least one column.
    """
    labels = _to_numpy(labels)
    if labels.ndim != 2 or labels.shape[1] < 1:
        raise InputError("labels", f"must be [N, L] with L ≥ 1, got shape {list(labels.shape)}")
    if not np.issubdtype(labels.dtype, np.integer):
        raise InputError("labels", f"must hold integer region ids, got dtype {labels.dtype}")
    n = labels.shape[0]
    # np.lexsort sorts by its last key first; the index key makes ties explicit.
    keys = (np.arange(n, dtype=np.int64), *(labels[:, level] for level in range(labels.shape[1])))
    return np.lexsort(keys).astype(np.int64, copy=False)


def _colors_to_uint8(colors: np.ndarray) -> np.ndarray:
    """viser's float colour conversion (``viser._assignable_props_api.colors_to_uint8``,
    viser 1.1.1), reproduced because it lives in a private module: ``clip(c · 255, 0, 255)``
    computed in the input's floating dtype, then cast to uint8, i.e. truncated."""
    return np.clip(colors * 255.0, 0, 255).astype(np.uint8)


def pack_rgba(rgb: Any, opacity: Any) -> np.ndarray:
    """Colours and opacities as the RGBA bytes of a viser splat buffer.

    Converts exactly as viser converts float colours and opacities: ``v · 255`` computed in the
    input's floating dtype, clipped to [0, 255], then truncated to uint8 (not rounded): 0 → 0,
    0.5 → 127, 0.999 → 254, 1 → 255. Values outside [0, 1] are clipped.

    Args:
        rgb: [N, 3] float colours in [0, 1] (NumPy array or torch tensor).
        opacity: [N] float opacities in [0, 1].

    Returns:
        [N, 4] uint8 R, G, B, A.

    Raises:
        InputError: wrong shapes or dtypes (integers are refused: viser would read them as
            0–255), or NaN / infinite values.
    """
    rgb_array = _to_numpy(rgb)
    opacity_array = _to_numpy(opacity)
    if rgb_array.ndim != 2 or rgb_array.shape[1] != 3:
        raise InputError("rgb", f"must be [N, 3], got shape {list(rgb_array.shape)}")
    n = rgb_array.shape[0]
    if opacity_array.shape != (n,):
        raise InputError(
            "opacity",
            f"must be [N] with N = {n} (from rgb), got shape {list(opacity_array.shape)}",
        )
    rgb_array = _finite_floats(rgb_array, "rgb", "[N, 3]")
    opacity_array = _finite_floats(opacity_array, "opacity", "[N]")
    rgba = np.empty((n, 4), dtype=np.uint8)
    rgba[:, :3] = _colors_to_uint8(rgb_array)
    rgba[:, 3] = _colors_to_uint8(opacity_array)
    return rgba


class SplatChunks:
    """The scene's Gaussians as consecutive viser splat nodes, with cheap colour updates.

    The Gaussians are laid out in ``order`` and cut into consecutive chunks of ``chunk_size``
    (the last one possibly shorter); chunk ``i`` is the splat node ``f"{name}/{i:04d}"``, a child
    of a frame ``name`` that this object creates and owns (an existing node of that name is
    replaced). Every splat buffer is created once, here; afterwards the geometry (centres and
    covariances, already packed) stays in the handles' buffers and :meth:`update` only rewrites the
    RGBA word of the chunks whose colours changed, with one buffer assignment (one queued message)
    per such chunk.

    Centres are sent as float32 and covariances as float16 (viser's format): covariance terms
    above 65504 scene units² reach the client as infinity (a warning is logged), terms below about
    6·10⁻⁸ as zero.

    Args:
        scene: where to add the nodes, a server's or a client's ``SceneApi`` (``server.scene``).
        name: scene-node name of the group, e.g. ``"/splats"``.
        centers: [N, 3] float centres, world frame, scene units.
        covariances: [N, 3, 3] float covariances, world frame, scene units² (only the upper
            triangle is sent; see :func:`splat_covariances`).
        rgb: [N, 3] float colours in [0, 1], scene order.
        opacity: [N] float opacities in [0, 1], scene order.
        order: [N] permutation of ``range(N)``, ``order[p]`` = the Gaussian at layout position
            ``p`` (see :func:`hierarchy_order`); default the identity.
        chunk_size: most Gaussians per splat node, ≥ 1.

    Raises:
        InputError: a bad argument; the message names it and the shapes seen.
    """

    def __init__(
        self,
        scene: viser.SceneApi,
        name: str,
        centers: Any,
        covariances: Any,
        rgb: Any,
        opacity: Any,
        *,
        order: Any = None,
        chunk_size: int = 65536,
    ) -> None:
        if not isinstance(name, str) or not name.strip("/"):
            raise InputError("name", f"must be a scene-node name such as '/splats', got {name!r}")
        if name.endswith("/"):
            raise InputError("name", f"must not end with '/', got {name!r}")
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)):
            raise InputError("chunk_size", f"must be an integer, got {chunk_size!r}")
        if chunk_size < 1:
            raise InputError("chunk_size", f"must be ≥ 1, got {chunk_size}")

        centers_array = _to_numpy(centers)
        if centers_array.ndim != 2 or centers_array.shape[1] != 3:
            raise InputError("centers", f"must be [N, 3], got shape {list(centers_array.shape)}")
        n = centers_array.shape[0]
        centers_array = _finite_floats(centers_array, "centers", "[N, 3]")
        covariances_array = _to_numpy(covariances)
        if covariances_array.shape != (n, 3, 3):
            raise InputError(
                "covariances",
                f"must be [N, 3, 3] with N = {n} (from centers), "
                f"got shape {list(covariances_array.shape)}",
            )
        covariances_array = _finite_floats(covariances_array, "covariances", "[N, 3, 3]")
        rgba = self._pack_checked(rgb, opacity, n)
        layout = self._check_order(order, n)

        triu = covariances_array.reshape(n, 9)[:, [0, 1, 2, 4, 5, 8]]
        overflow = (np.abs(triu) > _FLOAT16_MAX).any(axis=1)
        if overflow.any():
            logger.warning(
                "%d of %d Gaussians have covariance terms above %g scene units², which viser's "
                "float16 buffer turns into infinity (first: Gaussian %d)",
                int(overflow.sum()),
                n,
                _FLOAT16_MAX,
                int(np.flatnonzero(overflow)[0]),
            )

        self._scene = scene
        self._name = name if name.startswith("/") else "/" + name
        self._n = n
        self._chunk_size = int(chunk_size)
        self._order = layout  # None for the identity
        self._bytes_sent = 0
        self._removed = False

        if layout is not None:
            centers_array = centers_array[layout]
            covariances_array = covariances_array[layout]
            rgba = rgba[layout]
        self._root = scene.add_frame(self._name, show_axes=False)
        handles = []
        for index, start in enumerate(range(0, n, self._chunk_size)):
            stop = min(start + self._chunk_size, n)
            handles.append(
                scene.add_gaussian_splats(
                    f"{self._name}/{index:04d}",
                    centers=centers_array[start:stop],
                    covariances=covariances_array[start:stop],
                    rgbs=rgba[start:stop, :3],  # uint8: viser takes these unchanged
                    opacities=rgba[start:stop, 3:4],
                )
            )
        self._handles: tuple[viser.GaussianSplatHandle, ...] = tuple(handles)
        logger.debug(
            "sent %d Gaussians as %d splat nodes under %s (%d bytes)",
            n,
            len(handles),
            self._name,
            BYTES_PER_GAUSSIAN * n,
        )

    @staticmethod
    def _pack_checked(rgb: Any, opacity: Any, n: int) -> np.ndarray:
        """:func:`pack_rgba` of ``rgb`` and ``opacity``, checked to hold ``n`` Gaussians."""
        rgb_array = _to_numpy(rgb)
        if rgb_array.shape != (n, 3):
            raise InputError(
                "rgb", f"must be [N, 3] with N = {n} Gaussians, got shape {list(rgb_array.shape)}"
            )
        return pack_rgba(rgb_array, opacity)

    @staticmethod
    def _check_order(order: Any, n: int) -> np.ndarray | None:
        """``order`` as an [N] int64 permutation, or None when it is absent or the identity."""
        if order is None:
            return None
        array = _to_numpy(order)
        if array.shape != (n,):
            raise InputError(
                "order", f"must be [N] with N = {n} (from centers), got shape {list(array.shape)}"
            )
        if not np.issubdtype(array.dtype, np.integer):
            raise InputError("order", f"must hold integer indices, got dtype {array.dtype}")
        array = array.astype(np.int64, copy=True)
        if n and (array.min() < 0 or array.max() >= n):
            raise InputError(
                "order", f"indices must be in [0, {n}), got [{array.min()}, {array.max()}]"
            )
        counts = np.bincount(array, minlength=n)
        if (counts != 1).any():
            raise InputError(
                "order",
                f"must be a permutation of range({n}): {int((counts == 0).sum())} indices are "
                f"missing (first: {int(np.flatnonzero(counts == 0)[0])})",
            )
        if np.array_equal(array, np.arange(n)):
            return None
        return array

    def __len__(self) -> int:
        """N, the number of Gaussians."""
        return self._n

    @property
    def chunk_count(self) -> int:
        """Number of splat nodes, ``ceil(N / chunk_size)``."""
        return len(self._handles)

    @property
    def order(self) -> np.ndarray:
        """[N] int64 layout: ``order[p]`` is the Gaussian at layout position ``p``; chunk ``i``
        holds positions ``i · chunk_size`` up to ``(i + 1) · chunk_size`` (exclusive)."""
        if self._order is None:
            return np.arange(self._n, dtype=np.int64)
        return self._order.copy()

    @property
    def handles(self) -> tuple[viser.GaussianSplatHandle, ...]:
        """The chunks' viser handles, chunk ``i`` at index ``i``."""
        return self._handles

    @property
    def bytes_sent(self) -> int:
        """Bytes of splat buffers queued by :meth:`update` so far (32 per Gaussian of every
        re-sent chunk; the initial send is not counted)."""
        return self._bytes_sent

    def _check_live(self) -> None:
        if self._removed:
            raise RuntimeError(f"the splat nodes under {self._name} have been removed")

    def update(self, rgb: Any, opacity: Any) -> list[int]:
        """Show new colours, re-sending only the chunks whose packed RGBA changed.

        A chunk is re-sent with one assignment of its handle's ``buffer`` (its geometry, already
        packed, with the new RGBA word), which queues exactly one message to the clients.

        Args:
            rgb: [N, 3] float colours in [0, 1], scene order (row i = Gaussian i).
            opacity: [N] float opacities in [0, 1], scene order.

        Returns:
            Indices of the chunks re-sent, ascending (empty when nothing changed after packing).

        Raises:
            InputError: wrong shapes, dtypes or non-finite values (see :func:`pack_rgba`).
            RuntimeError: after :meth:`remove`.
        """
        self._check_live()
        rgba = self._pack_checked(rgb, opacity, self._n)
        if self._order is not None:
            rgba = rgba[self._order]
        words = rgba.view(np.uint32)[:, 0]  # [N] layout order, the buffers' RGBA word
        resent = []
        for index, handle in enumerate(self._handles):
            start = index * self._chunk_size
            new = words[start : start + self._chunk_size]
            current = handle.buffer
            if np.array_equal(current[:, 7], new):
                continue
            buffer = current.copy()
            buffer[:, 7] = new
            handle.buffer = buffer
            resent.append(index)
            self._bytes_sent += BYTES_PER_GAUSSIAN * len(new)
        logger.debug(
            "colour update under %s: re-sent %d of %d chunks",
            self._name,
            len(resent),
            len(self._handles),
        )
        return resent

    def rgba(self) -> np.ndarray:
        """The colours currently held by the handles, decoded to scene order.

        Returns:
            [N, 4] uint8 R, G, B, A; row i is Gaussian i.
        """
        if not self._handles:
            return np.zeros((0, 4), dtype=np.uint8)
        words = np.ascontiguousarray(np.concatenate([h.buffer[:, 7] for h in self._handles]))
        layout = words.view(np.uint8).reshape(self._n, 4)
        if self._order is None:
            return layout.copy()
        rgba = np.empty_like(layout)
        rgba[self._order] = layout
        return rgba

    def remove(self) -> None:
        """Remove the group frame and every chunk from the scene; later calls do nothing."""
        if self._removed:
            return
        self._root.remove()  # cascades to the chunk nodes
        self._removed = True
        logger.debug("removed the splat nodes under %s", self._name)
