"""The semantic field: the method's output, a four-level region hierarchy with text features.

Every Gaussian belongs to exactly one region at each of four nested levels: 0, the level-0
superpoints of the graph partition; 1, sub-parts (superpoints merged with SAM's ``s`` masks);
2, parts (``m``); 3, objects (``l``). Regions of levels 1–3 carry one unit feature vector in a
text-embedding space, or a zero row where no view saw them. See docs/field.md for the layout, a
worked example and the file format.

One field is stored as one safetensors file::

    labels       int32   [N, 4]        region id of each Gaussian at levels 0..3
    parents_k    int32   [R_{k-1}]     level-k region containing each level-(k-1) region, k = 1..3
    features_k   float32 [R_k, D]      level-k features, k = 1..3
    seen_k       uint8   [R_k]         1 = the level-k region got a feature from some view
    metadata     {"thgs": JSON, sorted keys}

The file is written atomically, and the same field always gives the same bytes; the build's
timings are not in it (version 2), so building the same inputs twice gives the same file. The
metadata holds the SHA-256 of the tensors (version 3), checked on every read: a file altered
after it was written (zeroed labels with the header intact) is refused, not trusted. Beside the
build config, the metadata keeps the field's provenance (version 4: the scene to reload, the
text model, the thgs that built it; :mod:`thgs.provenance`); older files keep the scene and the
text model inside the config and are read into the same record.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import re
from dataclasses import dataclass
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from thgs._atomic import atomic_output
from thgs.errors import InputError
from thgs.hierarchy.levels import RegionLevels
from thgs.provenance import Provenance
from thgs.scene import Gaussians

__all__ = [
    "FORMAT_VERSION",
    "SemanticField",
    "load_field",
    "save_field",
    "scene_fingerprint",
]

logger = logging.getLogger(__name__)

FORMAT_VERSION = 4
"""Version of the semantic-field file layout this thgs writes (and the newest it reads)."""

_FORMAT = "thgs.semantic_field"
_FINGERPRINT = re.compile(r"sha256:[0-9a-f]{64}")
_UNIT_TOLERANCE = 1e-4
_METADATA_KEYS = ("config", "fingerprint", "gaussians", "region_counts", "space")
_V1_METADATA_KEYS = (*_METADATA_KEYS, "timings")
"""Version 1 also stored the build's timings, which made every build's bytes differ."""
_V3_METADATA_KEYS = (*_METADATA_KEYS, "checksum")
"""Version 3 adds the SHA-256 of the tensors (:func:`_tensors_checksum`)."""
_V4_METADATA_KEYS = (*_V3_METADATA_KEYS, "provenance")
"""Version 4 keeps the provenance beside the config (before, inside it)."""


def _tensors_checksum(tensors: dict[str, np.ndarray]) -> str:
    """SHA-256 of the tensors' names, dtypes, shapes and bytes, in name order."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        array = np.ascontiguousarray(tensors[name])
        digest.update(f"{name}\0{array.dtype.str}\0{list(array.shape)}\0".encode())
        digest.update(array)
    return digest.hexdigest()


_TENSOR_DTYPES: dict[str, type[np.generic]] = {
    "labels": np.int32,
    **{f"parents_{k}": np.int32 for k in (1, 2, 3)},
    **{f"features_{k}": np.float32 for k in (1, 2, 3)},
    **{f"seen_{k}": np.uint8 for k in (1, 2, 3)},
}


@dataclass(frozen=True, eq=False)
class SemanticField:
    """Hierarchical, open-vocabulary labels of N Gaussians: four nested levels of regions.

    Level k has R_k regions with ids 0..R_k−1, every id used by at least one Gaussian. Level 0
    (superpoints) has no features; levels 1..3 are indexed ``k − 1`` in the tuples below.

    Attributes:
        levels: the nested regions (:class:`thgs.hierarchy.RegionLevels`): ``levels.labels``
            [N, 4] int32 region of each Gaussian per level, ``levels.parents[k - 1]`` [R_{k−1}]
            the level-k region containing each level-(k−1) region (k = 1..3).
        features: three float32 arrays; ``features[k - 1]`` is [R_k, D], a unit row per seen
            level-k region and a zero row per unseen one.
        seen: three bool arrays; ``seen[k - 1]`` is [R_k], whether the level-k region got a
            feature from at least one view.
        space: the embedding space of the features, e.g.
            ``"sentence-transformers/all-MiniLM-L6-v2"``; queries must be encoded in it.
        fingerprint: :func:`scene_fingerprint` of the Gaussians the field was built on.
        config: the build config (:meth:`thgs.pipeline.FieldConfig.to_json`), JSON values only
            (nested dicts with string keys, lists, strings, finite numbers, booleans, None).
        timings: wall time per build stage in seconds, in the order the stages ran. Kept in
            memory only: :func:`save_field` does not write them (the same build must give the
            same bytes), so a loaded field has none (a version-1 file's stored ones excepted).
        provenance: where the field came from (:class:`thgs.provenance.Provenance`).
    """

    levels: RegionLevels
    features: tuple[np.ndarray, np.ndarray, np.ndarray]
    seen: tuple[np.ndarray, np.ndarray, np.ndarray]
    space: str
    fingerprint: str
    config: dict[str, Any]
    timings: dict[str, float]
    provenance: Provenance = dataclass_field(default_factory=Provenance)

    def __len__(self) -> int:
        return int(self.labels.shape[0])

    def __repr__(self) -> str:
        try:
            summary = f"gaussians={len(self)}, region_counts={self.region_counts}, dim={self.dim}"
        except (AttributeError, IndexError, TypeError):  # malformed arrays: check() says why
            summary = "malformed"
        return f"SemanticField({summary}, space={self.space!r})"

    @property
    def dim(self) -> int:
        """D, the length of a feature vector."""
        return int(self.features[0].shape[1])

    @property
    def labels(self) -> np.ndarray:
        """[N, 4] int32: ``labels[i, k]`` is the level-k region of Gaussian i."""
        return self.levels.labels

    @property
    def parents(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``parents[k - 1]`` [R_{k−1}] int32: the level-k region of each level-(k−1) region."""
        assert self.levels.parents is not None  # check() requires nested levels
        return self.levels.parents

    @property
    def region_counts(self) -> tuple[int, int, int, int]:
        """(R_0, R_1, R_2, R_3): the number of regions at each level."""
        return self.levels.counts

    def sizes(self, level: int) -> np.ndarray:
        """[R_level] int64: the number of Gaussians in each region of ``level`` (0..3)."""
        return self.levels.sizes(level)

    def parent(self, level: int, region: int) -> int:
        """The level + 1 region that contains ``region`` of ``level`` (0..2)."""
        return self.levels.parent(level, region)

    def children(self, level: int, region: int) -> np.ndarray:
        """[C] int32, sorted: the level − 1 regions inside ``region`` of ``level`` (1..3)."""
        return self.levels.children(level, region)

    def members(self, level: int, region: int) -> np.ndarray:
        """[M] int64, sorted: the indices of the Gaussians in ``region`` of ``level`` (0..3)."""
        return self.levels.members(level, region)

    def check(self, source: str = "SemanticField") -> SemanticField:
        """Verify every invariant; raise :class:`InputError` naming ``source`` and the problem.

        Invariants: ``labels`` [N, 4] int32; per level k = 1..3, ``parents[k - 1]`` [R_{k−1}]
        int32, ``features[k - 1]`` [R_k, D] float32 and ``seen[k - 1]`` [R_k] bool, with one
        D ≥ 1; region ids in range and contiguous (every id 0..R_k−1 used); parents in range and
        nested; features finite, unit (|‖f‖ − 1| < 1e-4) where seen and exactly zero where not;
        ``space`` non-empty; ``fingerprint`` ``"sha256:"`` + 64 hex digits; ``config`` a dict
        of JSON values; ``provenance`` a :class:`thgs.provenance.Provenance`; ``timings`` finite
        seconds ≥ 0. Returns ``self`` to allow chaining.
        """
        if not isinstance(self.levels, RegionLevels):
            raise InputError(source, f"levels must be RegionLevels, got {_describe(self.levels)}")
        if not self.levels.nested:
            raise InputError(source, "levels must nest (parents), a field's levels always do")
        self.levels.check(source)
        for name in ("features", "seen"):
            value = getattr(self, name)
            if not isinstance(value, tuple) or len(value) != 3:
                raise InputError(source, f"{name} must be a tuple of 3 arrays (levels 1..3)")
        counts = self.levels.counts
        for k in range(1, 4):
            self._check_level_arrays(source, k, counts)
        dims = {int(f.shape[1]) for f in self.features}
        if len(dims) != 1:
            raise InputError(source, f"features have different widths over levels: {sorted(dims)}")
        if dims == {0}:
            raise InputError(source, "features have width D = 0")
        for k in range(1, 4):
            self._check_features(source, k)
        self._check_metadata(source)
        return self

    def _check_level_arrays(self, source: str, k: int, counts: tuple[int, ...]) -> None:
        features, seen = self.features[k - 1], self.seen[k - 1]
        for name, array, dtype, ndim in (
            (f"features[{k - 1}]", features, np.float32, 2),
            (f"seen[{k - 1}]", seen, np.bool_, 1),
        ):
            if not isinstance(array, np.ndarray) or array.dtype != dtype:
                raise InputError(
                    source, f"{name} must have dtype {np.dtype(dtype)}, got {_describe(array)}"
                )
            if array.ndim != ndim:
                raise InputError(source, f"{name} must have {ndim} dimension(s), got {array.ndim}")
            if array.shape[0] != counts[k]:
                raise InputError(
                    source,
                    f"{name} has {array.shape[0]} rows, level {k} has {counts[k]} regions",
                )

    def _check_features(self, source: str, k: int) -> None:
        features, seen = self.features[k - 1], self.seen[k - 1]
        finite = np.isfinite(features).all(axis=1)
        if not finite.all():
            bad = int(np.flatnonzero(~finite)[0])
            raise InputError(source, f"features[{k - 1}] row {bad} has NaN or infinite values")
        norms = np.linalg.norm(features.astype(np.float64), axis=1)
        not_unit = np.flatnonzero(seen & (np.abs(norms - 1.0) >= _UNIT_TOLERANCE))
        if not_unit.size:
            bad = int(not_unit[0])
            raise InputError(
                source,
                f"features[{k - 1}] rows of seen regions must be unit vectors: {not_unit.size} "
                f"are not (first: region {bad}, norm {norms[bad]:.6g})",
            )
        not_zero = np.flatnonzero(~seen & (features != 0).any(axis=1))
        if not_zero.size:
            raise InputError(
                source,
                f"features[{k - 1}] rows of unseen regions must be zero: {not_zero.size} are "
                f"not (first: region {int(not_zero[0])})",
            )

    def _check_metadata(self, source: str) -> None:
        if not isinstance(self.space, str) or not self.space.strip():
            raise InputError(source, "space must name the embedding space, got an empty name")
        if not isinstance(self.fingerprint, str) or not _FINGERPRINT.fullmatch(self.fingerprint):
            raise InputError(
                source,
                f"fingerprint must be 'sha256:' and 64 hex digits (scene_fingerprint), "
                f"got {self.fingerprint!r}",
            )
        if not isinstance(self.config, dict):
            raise InputError(source, f"config must be a dict, got {type(self.config).__name__}")
        problem = _json_problem(self.config, "config")
        if problem:
            raise InputError(source, problem)
        if not isinstance(self.provenance, Provenance):
            raise InputError(
                source, f"provenance must be a Provenance, got {_describe(self.provenance)}"
            )
        if not isinstance(self.timings, dict):
            raise InputError(source, f"timings must be a dict, got {type(self.timings).__name__}")
        for stage, seconds in self.timings.items():
            if not isinstance(stage, str):
                raise InputError(source, f"timings keys must be stage names, got {stage!r}")
            if (
                isinstance(seconds, bool)
                or not isinstance(seconds, (int, float, np.integer, np.floating))
                or not math.isfinite(seconds)
                or seconds < 0
            ):
                raise InputError(
                    source, f"timings[{stage!r}] must be finite seconds >= 0, got {seconds!r}"
                )


def _describe(value: object) -> str:
    if isinstance(value, np.ndarray):
        return f"{value.dtype} array of shape {list(value.shape)}"
    return type(value).__name__


def _first_dim(array: object) -> int:
    """Length along the first axis, or 0 for a non-array or a 0-d array (reported later)."""
    if isinstance(array, np.ndarray) and array.ndim >= 1:
        return int(array.shape[0])
    return 0


def _json_problem(value: object, where: str) -> str | None:
    """Why ``value`` does not survive a JSON round trip (tuples excepted: they become lists)."""
    if value is None or isinstance(value, (bool, int, str)):
        return None
    if isinstance(value, float):
        return None if math.isfinite(value) else f"{where} is {value}, which JSON cannot hold"
    if isinstance(value, (list, tuple)):
        for i, item in enumerate(value):
            problem = _json_problem(item, f"{where}[{i}]")
            if problem:
                return problem
        return None
    if isinstance(value, dict):
        for key, item in value.items():
            if not isinstance(key, str):
                return f"{where} has a non-string key {key!r}"
            problem = _json_problem(item, f"{where}[{key!r}]")
            if problem:
                return problem
        return None
    return f"{where} is of type {type(value).__name__}, not a JSON value"


def scene_fingerprint(gaussians: Gaussians) -> str:
    """``"sha256:<64 hex digits>"`` identifying the geometry of ``gaussians``.

    Hashes N, the kind ("2dgs"/"3dgs") and the float32 little-endian bytes of ``means``,
    ``quats``, ``scales`` and ``opacities``, in that order (copied to the CPU; a float64 scene
    hashes as its float32 rounding). Colour (``sh``), ``normals`` and ``extras`` are left out:
    regions are made of Gaussians, and a recoloured scene has the same Gaussians, so a field
    built on it still applies. Moving, rotating, rescaling or re-weighting any Gaussian, or
    reordering them, changes the fingerprint.
    """
    digest = hashlib.sha256()
    digest.update(f"thgs.scene_fingerprint\0{len(gaussians)}\0{gaussians.kind}\0".encode())
    for tensor in (gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities):
        values = tensor.detach().to(device="cpu", dtype=torch.float32).contiguous().numpy()
        digest.update(values.astype("<f4", copy=False).tobytes())
    return f"sha256:{digest.hexdigest()}"


def save_field(path: str | os.PathLike[str], field: SemanticField) -> None:
    """Write ``field`` as one safetensors file at ``path``, atomically (see the module docstring).

    The same field always gives the same bytes: one metadata key, JSON with sorted keys.

    Raises:
        InputError: the field fails :meth:`SemanticField.check` (nothing is written).
    """
    from safetensors.numpy import save

    path = Path(path)
    field.check(source=f"semantic field to write to {path}")
    tensors = {"labels": np.ascontiguousarray(field.labels)}
    for k in range(1, 4):
        tensors[f"parents_{k}"] = np.ascontiguousarray(field.parents[k - 1])
        tensors[f"features_{k}"] = np.ascontiguousarray(field.features[k - 1])
        tensors[f"seen_{k}"] = field.seen[k - 1].astype(np.uint8)
    header = {
        "format": _FORMAT,
        "version": FORMAT_VERSION,
        "space": field.space,
        "fingerprint": field.fingerprint,
        "config": field.config,
        "gaussians": len(field),
        "region_counts": list(field.region_counts),
        "checksum": _tensors_checksum(tensors),
        "provenance": field.provenance.to_json(),
    }
    metadata = {"thgs": json.dumps(header, sort_keys=True, allow_nan=False)}
    data = save(tensors, metadata=metadata)
    with atomic_output(path) as handle:
        handle.write(data)
    logger.debug("wrote semantic field %s to %s (%d bytes)", field, path, len(data))


def load_field(path: str | os.PathLike[str]) -> SemanticField:
    """Read a file written by :func:`save_field`; the result has passed :meth:`check`.

    ``config`` comes back as parsed JSON (tuples saved as lists); ``timings`` are empty (a
    version-1 file's stored ones excepted, in their order).

    Raises:
        InputError: naming ``path``, if the file is missing, unreadable, not a safetensors
            file (or truncated), not a thgs semantic field, written by a newer thgs, lacks
            tensors or metadata, has metadata that disagrees with its tensors, holds a field
            that breaks an invariant, or (version 3) whose tensors are not what was written.
    """
    from safetensors import SafetensorError, safe_open

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "semantic field file not found")
    try:
        with safe_open(str(path), framework="numpy") as handle:
            metadata = handle.metadata() or {}
            tensors = {key: handle.get_tensor(key) for key in handle.keys()}
    except (SafetensorError, OSError) as error:
        raise InputError(path, f"not a readable safetensors file ({error})") from error
    header = _read_header(path, metadata)
    version = header["version"]
    missing = sorted(set(_TENSOR_DTYPES) - set(tensors))
    unexpected = sorted(set(tensors) - set(_TENSOR_DTYPES))
    if missing:
        raise InputError(path, f"missing tensors {missing}")
    if unexpected:
        raise InputError(path, f"unexpected tensors {unexpected} in format version {version}")
    for name, dtype in _TENSOR_DTYPES.items():
        if tensors[name].dtype != dtype:
            raise InputError(
                path, f"tensor {name!r} is {tensors[name].dtype}, expected {np.dtype(dtype)}"
            )
    for k in (1, 2, 3):
        seen = tensors[f"seen_{k}"]
        if seen.size and seen.max() > 1:
            raise InputError(path, f"tensor 'seen_{k}' must hold 0 or 1, found {int(seen.max())}")
    labels = tensors["labels"]
    n = int(labels.shape[0]) if labels.ndim else None
    if header["gaussians"] != n:
        raise InputError(
            path, f"metadata says {header['gaussians']} Gaussians, labels have {n} rows"
        )
    counts = [_first_dim(tensors["parents_1"])] + [
        _first_dim(tensors[f"features_{k}"]) for k in (1, 2, 3)
    ]
    if header["region_counts"] != counts:
        raise InputError(
            path,
            f"metadata says region counts {header['region_counts']}, tensors have {counts}",
        )
    config = header["config"]
    if version >= 4:
        provenance = Provenance.from_json(header["provenance"], str(path))
    elif isinstance(config, dict):
        provenance, config = Provenance.from_old_config(config, str(path))
    else:
        provenance = Provenance()  # check() names the config that is not a dict
    field = SemanticField(
        levels=RegionLevels(
            labels,
            tuple(tensors[f"parents_{k}"] for k in (1, 2, 3)),  # type: ignore[arg-type]
            tuple(counts),  # type: ignore[arg-type]
        ),
        features=tuple(tensors[f"features_{k}"] for k in (1, 2, 3)),  # type: ignore[arg-type]
        seen=tuple(tensors[f"seen_{k}"].astype(bool) for k in (1, 2, 3)),  # type: ignore[arg-type]
        space=header["space"],
        fingerprint=header["fingerprint"],
        config=config,
        timings=dict(header.get("timings", [])),
        provenance=provenance,
    )
    field.check(source=str(path))
    if version >= 3 and header["checksum"] != _tensors_checksum(tensors):
        raise InputError(
            path,
            "its content is not what was written (the checksum of its tensors differs): the "
            "file was damaged or altered; build the field again",
        )
    logger.debug("read semantic field %s from %s", field, path)
    return field


def _read_header(path: Path, metadata: dict[str, str]) -> dict[str, Any]:
    """The parsed ``"thgs"`` metadata of a field file, its format, version and keys checked."""
    try:
        header = json.loads(metadata["thgs"])
    except (KeyError, json.JSONDecodeError) as error:
        raise InputError(path, "not a thgs semantic field file (no 'thgs' metadata)") from error
    if not isinstance(header, dict) or header.get("format") != _FORMAT:
        found = header.get("format") if isinstance(header, dict) else None
        raise InputError(path, f"not a thgs semantic field file (format {found!r})")
    version = header.get("version")
    if isinstance(version, bool) or not isinstance(version, int) or version < 1:
        raise InputError(path, f"invalid format version {version!r}")
    if version > FORMAT_VERSION:
        raise InputError(
            path,
            f"written by a newer thgs (version {version}), this one reads {FORMAT_VERSION}",
        )
    expected = {1: _V1_METADATA_KEYS, 2: _METADATA_KEYS, 3: _V3_METADATA_KEYS}.get(
        version, _V4_METADATA_KEYS
    )
    missing = [key for key in expected if key not in header]
    if missing:
        raise InputError(path, f"metadata lacks {missing}")
    if version > 1:
        return header
    timings = header["timings"]
    if not isinstance(timings, list) or not all(
        isinstance(pair, list) and len(pair) == 2 and isinstance(pair[0], str) for pair in timings
    ):
        raise InputError(path, "metadata 'timings' must be a list of [stage, seconds] pairs")
    stages = [pair[0] for pair in timings]
    if len(set(stages)) != len(stages):
        raise InputError(path, f"metadata 'timings' names a stage twice: {stages}")
    return header
