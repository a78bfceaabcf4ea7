"""A scene's lift kept on disk and reused: sweeps, ablations and rebuilds lift once.

Lifting (one rasterization per view, :func:`thgs.lift.lift_views`) is most of a build. Its result
depends only on the Gaussians' geometry and opacity, the cameras, the guidance (masks and their
features) and the :class:`thgs.lift.LiftConfig`, so :func:`lift_key` hashes exactly those, and a
cache folder holds one safetensors file per key, ``lift-<key>.safetensors``:

    v<i>.gaussians    int32   [n_i]      view i's :class:`thgs.lift.ViewLift` tensors
    v<i>.labels       int16|int32 [n_i, 4]
    v<i>.depths       float32 [n_i]
    v<i>.max_weights  float32 [n_i]
    metadata          {"thgs": JSON: format, version, key, views, checksum}

A hit gives the very tensors the lift computed (bit for bit), so a field built from the cache
is the field built without it. A file that cannot be read or does not match (truncated,
another key, another view count, content that is not what was written: the SHA-256 of the
tensors' bytes in file order is stored and checked on every read, so zeroed or altered labels
are found with the header intact; indices outside the scene or non-finite depths) is not an
error: the lift is recomputed and the file rewritten, with a warning naming the file; a cache
must never stop a build, nor be trusted blindly. The rasterization's backend
and precision are part of the key, so a lift computed in float32 on a GPU is not reused for a
float64 CPU build or the reverse.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import numpy as np
import torch

from thgs._atomic import atomic_output
from thgs.field import scene_fingerprint
from thgs.guidance import ViewGuidance
from thgs.lift import LiftConfig, ViewLift
from thgs.scene import Cameras, Gaussians

__all__ = ["LIFT_CACHE_VERSION", "lift_cache_path", "lift_key", "read_cached_lift", "write_lift"]

logger = logging.getLogger(__name__)

LIFT_CACHE_VERSION = 2
"""Layout of the cache files; part of the key, so a new layout never reads an old file."""

_FORMAT = "thgs.lift"
_FIELDS = ("gaussians", "labels", "depths", "max_weights")
_UNSET = "?" * 64
"""The checksum's place in a header being written, filled in once the tensors are written."""


def _tensor_bytes(tensor: torch.Tensor) -> np.ndarray:
    """The tensor's bytes as a contiguous array (hashed and written without another copy)."""
    return np.ascontiguousarray(tensor.detach().cpu().numpy())


def _array_bytes(array: np.ndarray | torch.Tensor) -> bytes:
    if isinstance(array, torch.Tensor):
        array = array.detach().cpu().numpy()
    array = np.ascontiguousarray(array)
    return f"{array.dtype.str}{array.shape}".encode() + array.tobytes()


def lift_key(
    gaussians: Gaussians,
    cameras: Cameras,
    guidance: Sequence[ViewGuidance],
    config: LiftConfig,
) -> str:
    """64 hex digits identifying a lift: the Gaussians' :func:`thgs.field.scene_fingerprint`
    (geometry and opacity; colours do not change a lift), every camera's pose, intrinsics, size
    and stem, every view's masks and mask features (bytes, dtypes and shapes), and every
    setting of ``config`` (rasterization included)."""
    digest = hashlib.sha256()
    digest.update(f"{_FORMAT}\0{LIFT_CACHE_VERSION}\0".encode())
    digest.update(scene_fingerprint(gaussians).encode())
    settings = json.dumps(dataclasses.asdict(config), sort_keys=True, allow_nan=True)
    digest.update(settings.encode())
    for tensor in (cameras.viewmats, cameras.Ks, cameras.widths, cameras.heights):
        digest.update(_array_bytes(tensor))
    for stem in cameras.stems:
        digest.update(f"\0{stem}".encode())
    for view in guidance:
        digest.update(f"\0{view.stem}\0".encode())
        digest.update(_array_bytes(view.segments))
        digest.update(_array_bytes(view.features))
    return digest.hexdigest()


def lift_cache_path(folder: str | os.PathLike[str], key: str) -> Path:
    """The cache file of ``key`` in ``folder``."""
    return Path(folder) / f"lift-{key}.safetensors"


def read_cached_lift(
    path: str | os.PathLike[str],
    key: str,
    views: int,
    collect: Callable[[Iterator[ViewLift]], Sequence[ViewLift]] = list,
) -> Sequence[ViewLift] | None:
    """The ``views`` lifts stored at ``path`` for ``key``, on the CPU; None when there is no
    such file, or (with a logged warning) when it cannot be read or does not match.

    ``collect`` receives the views one at a time, in order, and returns what is kept (default:
    a list); an error it raises while collecting (:class:`thgs.InputError` included) makes the
    cache unusable like a damaged file, and so does content whose SHA-256 is not the one
    written, or non-finite depths."""
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    if not path.is_file():
        return None
    try:
        with safe_open(str(path), framework="pt") as handle:
            header = json.loads((handle.metadata() or {})["thgs"])
            if (header.get("format"), header.get("key"), header.get("views")) != (
                _FORMAT,
                key,
                views,
            ):
                raise ValueError("written for other inputs")
            digest = hashlib.sha256()

            def read() -> Iterator[ViewLift]:
                for i in range(views):
                    tensors = [handle.get_tensor(f"v{i}.{name}") for name in _FIELDS]
                    for tensor in tensors:
                        digest.update(_tensor_bytes(tensor))
                    if not bool(torch.isfinite(tensors[2]).all()):
                        raise ValueError(f"view {i} has non-finite depths")
                    yield ViewLift(*tensors)

            lifted = collect(read())
            if digest.hexdigest() != header.get("checksum"):
                raise ValueError("its content is not what was written (checksum)")
    except (SafetensorError, OSError, KeyError, ValueError, TypeError) as error:
        logger.warning("lift cache %s unusable (%s): lifting again", path, error)
        return None
    logger.info("lift read from the cache %s", path)
    return lifted


_SAFETENSORS_DTYPES = {
    torch.int16: "I16",
    torch.int32: "I32",
    torch.int64: "I64",
    torch.float32: "F32",
    torch.float64: "F64",
}
"""safetensors' names of the dtypes a :class:`ViewLift` holds."""


def write_lift(path: str | os.PathLike[str], key: str, lifted: Sequence[ViewLift]) -> None:
    """Store ``lifted`` (one :class:`ViewLift` per view) for ``key`` at ``path``, atomically.

    The file is safetensors, written one view at a time (the library writes only from tensors
    all held at once, and a lift kept in a :class:`thgs.lift_store.LiftStore` is not): a header
    listing every tensor's dtype, shape and byte range, padded to 8 bytes, then the tensors'
    bytes in that order. The header's checksum, the SHA-256 of those bytes, is written last,
    in its place. It is read back through safetensors (:func:`read_cached_lift`).
    """
    entries, offset = {}, 0
    for i, view in enumerate(lifted):
        for name in _FIELDS:
            tensor = getattr(view, name)
            size = tensor.numel() * tensor.element_size()
            entries[f"v{i}.{name}"] = {
                "dtype": _SAFETENSORS_DTYPES[tensor.dtype],
                "shape": list(tensor.shape),
                "data_offsets": [offset, offset + size],
            }
            offset += size
    header = {
        "format": _FORMAT,
        "version": LIFT_CACHE_VERSION,
        "key": key,
        "views": len(lifted),
        "checksum": _UNSET,
    }
    entries["__metadata__"] = {"thgs": json.dumps(header, sort_keys=True)}
    text = json.dumps(entries, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)
    digest = hashlib.sha256()
    with atomic_output(path) as handle:
        handle.write(len(text).to_bytes(8, "little"))
        handle.write(text)
        for view in lifted:
            for name in _FIELDS:
                data = _tensor_bytes(getattr(view, name))
                digest.update(data)
                handle.write(data)
        handle.seek(8 + text.index(_UNSET.encode()))
        handle.write(digest.hexdigest().encode())
    logger.info("lift written to the cache %s (%.1f MB)", path, (8 + len(text) + offset) / 1e6)
