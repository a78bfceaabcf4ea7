"""INRIA-layout PLY files of 3DGS and 2DGS scenes: read and write.

Layout (one ``vertex`` element, one row per Gaussian, float32 properties in this order)::

    x y z [nx ny nz] f_dc_0..2 f_rest_0..(3·(K−1)−1) opacity scale_0..(1|2) rot_0..3 [others]

2 scales mean 2DGS surfels, 3 mean 3DGS ellipsoids; the number of ``f_rest_*`` (0, 9, 24 or 45)
gives the SH degree (0–3). Values are the stored, pre-activation parameters. Properties outside this
list are kept in :attr:`Gaussians.extras` and written back after the standard ones, so a file in
this layout round-trips byte for byte.
"""

from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np
import plyfile
import torch

from thgs._atomic import atomic_output
from thgs.errors import InputError
from thgs.scene.gaussians import Gaussians, warn_if_invisible

__all__ = ["read_ply", "write_ply"]

logger = logging.getLogger(__name__)

_BASE_PROPERTIES = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity")
_REST_FOR_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}
_NUMBERED = re.compile(r"^(f_dc|f_rest|scale|rot)_(\d+)$")


def _numbered(names: list[str], prefix: str) -> list[str]:
    found = sorted(
        (int(m.group(2)), name)
        for name in names
        if (m := _NUMBERED.match(name)) and m.group(1) == prefix
    )
    indices = [i for i, _ in found]
    if indices != list(range(len(indices))):
        raise ValueError(f"{prefix}_* properties are not numbered 0..{len(indices) - 1}: {indices}")
    return [name for _, name in found]


def read_ply_data(path: Path) -> plyfile.PlyData:
    """Parse any PLY file that has a ``vertex`` element (Gaussians, ScanNet labels, …).

    Raises:
        InputError: the file is missing, empty, not a readable PLY, or has no ``vertex`` element.
    """
    if not path.is_file():
        raise InputError(path, "no such file")
    if path.stat().st_size == 0:
        raise InputError(path, "the file is empty")
    try:
        ply = plyfile.PlyData.read(str(path))
    except Exception as exc:  # plyfile raises several unrelated types for malformed files
        raise InputError(path, f"not a readable PLY file ({type(exc).__name__}: {exc})") from exc
    if "vertex" not in ply:
        elements = [element.name for element in ply.elements]
        raise InputError(path, f"no 'vertex' element (elements: {elements})")
    return ply


def read_ply(path: str | os.PathLike[str]) -> Gaussians:
    """Read an INRIA-layout 3DGS or 2DGS PLY file.

    Args:
        path: the ``.ply`` file (binary or ASCII).

    Returns:
        :class:`Gaussians` with float32 CPU tensors, checked (:meth:`Gaussians.check`).

    Raises:
        InputError: the file is missing, empty, truncated or not a PLY; a required property is
            missing; the scale or SH counts are not a valid layout; a value is NaN or infinite; a
            quaternion is zero. The message names the file.
    """
    path = Path(path)
    ply = read_ply_data(path)
    vertex = ply["vertex"]
    others = [element.name for element in ply.elements if element.name != "vertex"]
    if others:
        logger.warning("%s: ignoring PLY elements %s", path, others)
    names = [prop.name for prop in vertex.properties]
    if vertex.count == 0:
        raise InputError(path, "the PLY holds no Gaussians (vertex count 0)")

    required = [*_BASE_PROPERTIES, "rot_0", "rot_1", "rot_2", "rot_3", "scale_0", "scale_1"]
    missing = [name for name in required if name not in names]
    if missing:
        raise InputError(
            path,
            f"missing properties {missing}; an INRIA 3DGS/2DGS PLY has x y z f_dc_0..2 f_rest_* "
            "opacity scale_0..1(2) rot_0..3 (exports from other tools may differ: convert them)",
        )
    try:
        scale_names = _numbered(names, "scale")
        rest_names = _numbered(names, "f_rest")
        rot_names = _numbered(names, "rot")
    except ValueError as exc:
        raise InputError(path, str(exc)) from exc
    if len(scale_names) not in (2, 3):
        raise InputError(
            path,
            f"{len(scale_names)} scale properties ({', '.join(scale_names)}); expected 2 (2DGS) "
            "or 3 (3DGS)",
        )
    if len(rot_names) != 4:
        raise InputError(path, f"{len(rot_names)} rot_* properties, expected 4 (w, x, y, z)")
    if len(rest_names) not in _REST_FOR_DEGREE:
        raise InputError(
            path,
            f"{len(rest_names)} f_rest_* properties; expected 0, 9, 24 or 45 (SH degree 0-3)",
        )
    normal_names = [name for name in ("nx", "ny", "nz") if name in names]
    if normal_names and len(normal_names) != 3:
        raise InputError(path, f"partial normals {normal_names}; expected nx, ny, nz or none")

    data = vertex.data
    n = vertex.count

    def column_block(columns: list[str]) -> torch.Tensor:
        block = np.empty((n, len(columns)), dtype=np.float32)
        for j, name in enumerate(columns):
            block[:, j] = data[name]
        return torch.from_numpy(block)

    k = len(rest_names) // 3 + 1
    sh = torch.empty((n, k, 3), dtype=torch.float32)
    sh[:, 0] = column_block(["f_dc_0", "f_dc_1", "f_dc_2"])
    if k > 1:
        sh[:, 1:] = column_block(rest_names).reshape(n, 3, k - 1).transpose(1, 2)
    standard = {*_BASE_PROPERTIES, *scale_names, *rot_names, *rest_names, *normal_names}
    non_float = [name for name in names if name in standard and data[name].dtype.str[1:] != "f4"]
    if non_float:
        logger.info("%s: converting %s to float32", path, non_float)
    gaussians = Gaussians(
        means=column_block(["x", "y", "z"]),
        quats=column_block(rot_names),
        scales=column_block(scale_names),
        opacities=column_block(["opacity"])[:, 0].contiguous(),
        sh=sh,
        normals=column_block(normal_names) if normal_names else None,
        extras={name: np.ascontiguousarray(data[name]) for name in names if name not in standard},
    )
    gaussians.check(source=str(path))
    warn_if_invisible(gaussians, str(path))
    logger.debug("%s: %d Gaussians, %s, SH degree %d", path, n, gaussians.kind, gaussians.sh_degree)
    return gaussians


def _layout(gaussians: Gaussians) -> list[tuple[str, np.ndarray]]:
    n = len(gaussians)
    sh = gaussians.sh.detach().cpu().numpy().astype(np.float32, copy=False)
    columns: list[tuple[str, np.ndarray]] = []

    def add(prefix: str, block: np.ndarray) -> None:
        block = np.asarray(block, dtype=np.float32).reshape(n, -1)
        columns.extend((f"{prefix}{j}", block[:, j]) for j in range(block.shape[1]))

    means = gaussians.means.detach().cpu().numpy()
    columns.extend((axis, means[:, j].astype(np.float32)) for j, axis in enumerate("xyz"))
    if gaussians.normals is not None:
        normals = gaussians.normals.detach().cpu().numpy()
        columns.extend(
            (axis, normals[:, j].astype(np.float32)) for j, axis in enumerate(("nx", "ny", "nz"))
        )
    add("f_dc_", sh[:, 0])
    add("f_rest_", sh[:, 1:].transpose(0, 2, 1))
    columns.append(("opacity", gaussians.opacities.detach().cpu().numpy().astype(np.float32)))
    add("scale_", gaussians.scales.detach().cpu().numpy())
    add("rot_", gaussians.quats.detach().cpu().numpy())
    columns.extend(gaussians.extras.items())
    return columns


def write_ply(path: str | os.PathLike[str], gaussians: Gaussians) -> None:
    """Write ``gaussians`` as a binary little-endian INRIA-layout PLY, atomically.

    The property order is the trainers' (see the module docstring); ``normals`` are written only if
    present and ``extras`` after the standard properties. Writing what :func:`read_ply` read from
    a file in this layout reproduces the file byte for byte.

    Raises:
        InputError: the Gaussians fail :meth:`Gaussians.check` (nothing is written then).
    """
    gaussians.check(source=f"Gaussians to write to {os.fspath(path)}")
    columns = _layout(gaussians)
    records = np.empty(len(gaussians), dtype=[(name, values.dtype) for name, values in columns])
    for name, values in columns:
        records[name] = values
    element = plyfile.PlyElement.describe(records, "vertex")
    with atomic_output(path, "wb") as handle:
        plyfile.PlyData([element], text=False, byte_order="<").write(handle)
