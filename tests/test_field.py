"""The semantic field: the documented mug example by hand, its file format and every invariant."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import re
import struct
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.numpy import save

from conftest import random_gaussians
from thgs import InputError
from thgs.field import FORMAT_VERSION, SemanticField, load_field, save_field, scene_fingerprint
from thgs.hierarchy import RegionLevels
from thgs.provenance import Provenance, SceneRecord

FINGERPRINT = "sha256:" + "ab" * 32


def mug_field() -> SemanticField:
    """The worked example of docs/field.md: 6 Gaussians, 4 superpoints → 3 sub-parts (rim, wall,
    handle) → 2 parts (body, handle) → 1 object (mug); the handle sub-part was never seen."""
    return SemanticField(
        levels=RegionLevels(
            labels=np.array(
                [
                    [0, 0, 0, 0],
                    [0, 0, 0, 0],
                    [1, 1, 0, 0],
                    [2, 1, 0, 0],
                    [3, 2, 1, 0],
                    [3, 2, 1, 0],
                ],
                dtype=np.int32,
            ),
            parents=(
                np.array([0, 1, 1, 2], dtype=np.int32),
                np.array([0, 0, 1], dtype=np.int32),
                np.array([0, 0], dtype=np.int32),
            ),
            counts=(4, 3, 2, 1),
        ),
        features=(
            np.array([[1, 0, 0], [0, 1, 0], [0, 0, 0]], dtype=np.float32),
            np.array([[0.6, 0.8, 0], [0, 0, 1]], dtype=np.float32),
            np.array([[0, 0.6, 0.8]], dtype=np.float32),
        ),
        seen=(np.array([True, True, False]), np.array([True, True]), np.array([True])),
        space="sentence-transformers/all-MiniLM-L6-v2",
        fingerprint=FINGERPRINT,
        config={"partition": {"regularization": 0.1, "levels": ["s", "m", "l"]}, "seed": 0},
        timings={"lift": 1.5, "knn": 0.25, "partition": 3.0, "merge": 0.125},
    ).check()


def replace_level(field: SemanticField, name: str, k: int, value: np.ndarray) -> SemanticField:
    """``field`` with ``getattr(field, name)[k - 1]`` (levels 1..3) replaced by ``value``
    (``parents`` in the field's levels)."""
    arrays = list(getattr(field, name))
    arrays[k - 1] = value
    if name == "parents":
        return with_levels(field, parents=tuple(arrays))
    return dataclasses.replace(field, **{name: tuple(arrays)})


def with_levels(field: SemanticField, **changes) -> SemanticField:
    """``field`` with its levels' attributes replaced."""
    return dataclasses.replace(field, levels=dataclasses.replace(field.levels, **changes))


def with_labels(field: SemanticField, edit: Callable[[np.ndarray], None]) -> SemanticField:
    labels = field.labels.copy()
    edit(labels)
    return with_levels(field, labels=labels)


def write_raw(path: Path, tensors: dict[str, np.ndarray], header: dict | None) -> None:
    """A safetensors file as save_field would write it, but with any tensors and metadata."""
    metadata = None if header is None else {"thgs": json.dumps(header, sort_keys=True)}
    path.write_bytes(save(tensors, metadata=metadata))


def checksum(tensors: dict[str, np.ndarray]) -> str:
    """The documented checksum, by hand: SHA-256 over each tensor in name order of
    ``name \\0 dtype \\0 [shape] \\0`` and its bytes."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        array = np.ascontiguousarray(tensors[name])
        digest.update(f"{name}\0{array.dtype.str}\0{list(array.shape)}\0".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def read_raw(path: Path) -> tuple[dict[str, np.ndarray], dict]:
    with safe_open(str(path), framework="numpy") as handle:
        tensors = {key: handle.get_tensor(key) for key in handle.keys()}
        return tensors, json.loads(handle.metadata()["thgs"])


# accessors


def test_accessors_give_the_hand_computed_answers():
    field = mug_field()
    assert len(field) == 6
    assert field.dim == 3
    assert field.region_counts == (4, 3, 2, 1)
    expected_sizes = [[2, 1, 1, 2], [2, 2, 2], [4, 2], [6]]
    for level, expected in enumerate(expected_sizes):
        sizes = field.sizes(level)
        assert sizes.dtype == np.int64
        np.testing.assert_array_equal(sizes, expected)
    assert [field.parent(0, r) for r in range(4)] == [0, 1, 1, 2]
    assert [field.parent(1, r) for r in range(3)] == [0, 0, 1]
    assert [field.parent(2, r) for r in range(2)] == [0, 0]
    assert isinstance(field.parent(np.int64(0), np.int32(3)), int)
    expected_children = {(1, 0): [0], (1, 1): [1, 2], (1, 2): [3], (2, 0): [0, 1], (2, 1): [2]}
    expected_children[(3, 0)] = [0, 1]
    for (level, region), expected in expected_children.items():
        children = field.children(level, region)
        assert children.dtype == np.int32
        np.testing.assert_array_equal(children, expected)
    expected_members = {
        (0, 0): [0, 1],
        (0, 3): [4, 5],
        (1, 1): [2, 3],
        (2, 0): [0, 1, 2, 3],
        (2, 1): [4, 5],
        (3, 0): [0, 1, 2, 3, 4, 5],
    }
    for (level, region), expected in expected_members.items():
        members = field.members(level, region)
        assert members.dtype == np.int64
        np.testing.assert_array_equal(members, expected)
    assert repr(field) == (
        "SemanticField(gaussians=6, region_counts=(4, 3, 2, 1), dim=3, "
        "space='sentence-transformers/all-MiniLM-L6-v2')"
    )


def test_walking_up_and_down_agrees_with_the_labels():
    field = mug_field()
    for i in range(len(field)):
        region = int(field.labels[i, 0])
        for level in range(3):
            region = field.parent(level, region)
            assert region == field.labels[i, level + 1]
    for level in range(1, 4):
        for region in range(field.region_counts[level]):
            below = np.concatenate(
                [field.members(level - 1, c) for c in field.children(level, region)]
            )
            np.testing.assert_array_equal(np.sort(below), field.members(level, region))


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda f: f.parent(3, 0), "level must be in 0..2 here, got 3"),
        (lambda f: f.parent(-1, 0), "level must be in 0..2 here, got -1"),
        (lambda f: f.parent(0, 4), "level 0 has regions 0..3, got region 4"),
        (lambda f: f.parent(1, -1), "level 1 has regions 0..2, got region -1"),
        (lambda f: f.children(0, 0), "level must be in 1..3 here, got 0"),
        (lambda f: f.children(2, 2), "level 2 has regions 0..1, got region 2"),
        (lambda f: f.members(4, 0), "level must be in 0..3 here, got 4"),
        (lambda f: f.members(3, 1), "level 3 has regions 0..0, got region 1"),
        (lambda f: f.members(1, 1.0), "region must be an integer, got 1.0"),
        (lambda f: f.sizes(True), "level must be an integer, got True"),
        (lambda f: f.sizes("0"), "level must be an integer, got '0'"),
    ],
)
def test_accessors_refuse_bad_levels_and_regions(call, message):
    with pytest.raises(InputError, match=re.escape(message)):
        call(mug_field())


# check()


CHECK_FAILURES = {
    "labels dtype": (
        lambda f: with_levels(f, labels=f.labels.astype(np.int64)),
        "labels must have dtype int32, got int64 array of shape [6, 4]",
    ),
    "labels shape": (
        lambda f: with_levels(f, labels=f.labels[:, :3].copy()),
        "labels must be [N, 4], got [6, 3]",
    ),
    "parents not a tuple": (
        lambda f: with_levels(f, parents=list(f.parents)),
        "parents must be a tuple of 3 arrays",
    ),
    "seen has two levels": (
        lambda f: dataclasses.replace(f, seen=f.seen[:2]),
        "seen must be a tuple of 3 arrays",
    ),
    "parents dtype": (
        lambda f: replace_level(f, "parents", 2, f.parents[1].astype(np.int64)),
        "parents[1] must have dtype int32, got int64 array of shape [3]",
    ),
    "features dtype": (
        lambda f: replace_level(f, "features", 1, f.features[0].astype(np.float64)),
        "features[0] must have dtype float32, got float64",
    ),
    "seen dtype": (
        lambda f: replace_level(f, "seen", 1, f.seen[0].astype(np.uint8)),
        "seen[0] must have dtype bool, got uint8",
    ),
    "features not 2-d": (
        lambda f: replace_level(f, "features", 3, f.features[2][0]),
        "features[2] must have 2 dimension(s), got 1",
    ),
    "parents too short": (
        lambda f: replace_level(f, "parents", 2, f.parents[1][:2]),
        "parents[1] has 2 entries, level 1 has 3 regions",
    ),
    "level-0 parents too short": (
        lambda f: replace_level(f, "parents", 1, f.parents[0][:3]),
        "parents[0] has 3 entries, level 0 has 4 regions",
    ),
    "level-0 count too small": (
        lambda f: with_levels(f, counts=(3, 3, 2, 1), parents=(f.parents[0][:3], *f.parents[1:])),
        "labels[:, 0] must be in 0..2, Gaussian 4 has 3",
    ),
    "levels do not nest": (
        lambda f: with_levels(f, parents=None),
        "levels must nest (parents), a field's levels always do",
    ),
    "levels not RegionLevels": (
        lambda f: dataclasses.replace(f, levels=f.labels),
        "levels must be RegionLevels, got int32 array of shape [6, 4]",
    ),
    "seen too long": (
        lambda f: replace_level(f, "seen", 2, np.ones(3, dtype=bool)),
        "seen[1] has 3 rows, level 2 has 2 regions",
    ),
    "features short": (
        lambda f: replace_level(f, "features", 1, f.features[0][:2]),
        "features[0] has 2 rows, level 1 has 3 regions",
    ),
    "widths differ": (
        lambda f: replace_level(f, "features", 3, np.array([[0, 0, 0, 1]], dtype=np.float32)),
        "features have different widths over levels: [3, 4]",
    ),
    "width zero": (
        lambda f: dataclasses.replace(
            f,
            features=tuple(np.zeros((r, 0), np.float32) for r in (3, 2, 1)),
            seen=tuple(np.zeros(r, bool) for r in (3, 2, 1)),
        ),
        "features have width D = 0",
    ),
    "label out of range": (
        lambda f: with_labels(f, lambda labels: labels.__setitem__((4, 0), 4)),
        "labels[:, 0] must be in 0..3, Gaussian 4 has 4",
    ),
    "negative label": (
        lambda f: with_labels(f, lambda labels: labels.__setitem__((2, 2), -1)),
        "labels[:, 2] must be in 0..1, Gaussian 2 has -1",
    ),
    "ids not contiguous": (
        lambda f: with_labels(f, lambda labels: labels.__setitem__((slice(4, 6), 0), 2)),
        "level 0 ids are not contiguous: 1 of 4 regions have no Gaussian (first: region 3)",
    ),
    "parent out of range": (
        lambda f: replace_level(f, "parents", 3, np.array([0, 1], dtype=np.int32)),
        "parents[2] must be level-3 ids in 0..0, region 1 has 1",
    ),
    "not nested": (
        lambda f: replace_level(f, "parents", 1, np.array([0, 1, 2, 2], dtype=np.int32)),
        "labels are not nested between levels 0 and 1: 1 Gaussians disagree with parents[0] "
        "(first: Gaussian 3, level-0 region 2 has parent 2, label says 1)",
    ),
    "label edited at one level": (
        lambda f: with_labels(f, lambda labels: labels.__setitem__((1, 0), 3)),
        "labels are not nested between levels 0 and 1",
    ),
    "seen feature not unit": (
        lambda f: replace_level(f, "features", 2, f.features[1] * np.float32(1.001)),
        "features[1] rows of seen regions must be unit vectors: 2 are not (first: region 0",
    ),
    "seen feature zero": (
        lambda f: replace_level(f, "seen", 1, np.array([True, True, True])),
        "features[0] rows of seen regions must be unit vectors: 1 are not (first: region 2, "
        "norm 0)",
    ),
    "unseen feature not zero": (
        lambda f: replace_level(f, "seen", 2, np.array([True, False])),
        "features[1] rows of unseen regions must be zero: 1 are not (first: region 1)",
    ),
    "feature not finite": (
        lambda f: replace_level(f, "features", 3, np.array([[np.nan, 0.6, 0.8]], dtype=np.float32)),
        "features[2] row 0 has NaN or infinite values",
    ),
    "space empty": (
        lambda f: dataclasses.replace(f, space=" "),
        "space must name the embedding space",
    ),
    "fingerprint malformed": (
        lambda f: dataclasses.replace(f, fingerprint="sha256:abc"),
        "fingerprint must be 'sha256:' and 64 hex digits",
    ),
    "config not a dict": (
        lambda f: dataclasses.replace(f, config=[1, 2]),
        "config must be a dict, got list",
    ),
    "config holds NumPy": (
        lambda f: dataclasses.replace(f, config={"graph": {"k": np.int64(8)}}),
        "config['graph']['k'] is of type int64, not a JSON value",
    ),
    "config holds NaN": (
        lambda f: dataclasses.replace(f, config={"tau": [0.5, float("nan")]}),
        "config['tau'][1] is nan, which JSON cannot hold",
    ),
    "config has an int key": (
        lambda f: dataclasses.replace(f, config={"levels": {1: "s"}}),
        "config['levels'] has a non-string key 1",
    ),
    "timing negative": (
        lambda f: dataclasses.replace(f, timings={"lift": 1.0, "knn": -0.5}),
        "timings['knn'] must be finite seconds >= 0, got -0.5",
    ),
    "timing infinite": (
        lambda f: dataclasses.replace(f, timings={"lift": float("inf")}),
        "timings['lift'] must be finite seconds >= 0, got inf",
    ),
    "timing not a number": (
        lambda f: dataclasses.replace(f, timings={"lift": "1 s"}),
        "timings['lift'] must be finite seconds >= 0, got '1 s'",
    ),
    "timing key not a name": (
        lambda f: dataclasses.replace(f, timings={0: 1.0}),
        "timings keys must be stage names, got 0",
    ),
}


@pytest.mark.parametrize("case", CHECK_FAILURES, ids=list(CHECK_FAILURES))
def test_check_names_each_broken_invariant(case):
    edit, message = CHECK_FAILURES[case]
    broken = edit(mug_field())
    assert repr(broken).startswith("SemanticField(")
    with pytest.raises(InputError, match=re.escape(message)) as caught:
        broken.check(source="my field")
    assert caught.value.source == "my field"


def test_check_accepts_unit_rows_within_tolerance_and_an_empty_field():
    field = mug_field()
    nearly = field.features[1] * np.float32(1 + 5e-5)
    assert replace_level(field, "features", 2, nearly).check() is not None
    empty = SemanticField(
        levels=RegionLevels(
            np.zeros((0, 4), np.int32), tuple(np.zeros(0, np.int32) for _ in range(3)), (0,) * 4
        ),
        features=tuple(np.zeros((0, 5), np.float32) for _ in range(3)),
        seen=tuple(np.zeros(0, bool) for _ in range(3)),
        space="x",
        fingerprint=FINGERPRINT,
        config={},
        timings={},
    )
    assert empty.check().region_counts == (0, 0, 0, 0)
    assert empty.dim == 5


# file format


def test_round_trip_is_exact(tmp_path):
    field = mug_field()
    path = tmp_path / "field.safetensors"
    save_field(path, field)
    loaded = load_field(path)
    np.testing.assert_array_equal(loaded.labels, field.labels)
    assert loaded.labels.dtype == np.int32
    for name, dtype in (("parents", np.int32), ("features", np.float32), ("seen", np.bool_)):
        for got, expected in zip(getattr(loaded, name), getattr(field, name), strict=True):
            assert got.dtype == dtype
            np.testing.assert_array_equal(got, expected)
    assert loaded.space == field.space
    assert loaded.fingerprint == field.fingerprint
    assert loaded.config == field.config
    assert field.timings and loaded.timings == {}  # timings are not written (version 2)
    assert loaded.region_counts == field.region_counts


def test_file_layout_is_the_documented_one(tmp_path):
    path = tmp_path / "field.safetensors"
    save_field(path, mug_field())
    with safe_open(str(path), framework="numpy") as handle:
        assert list(handle.metadata()) == ["thgs"]
    tensors, header = read_raw(path)
    assert {name: (str(t.dtype), list(t.shape)) for name, t in tensors.items()} == {
        "labels": ("int32", [6, 4]),
        "parents_1": ("int32", [4]),
        "parents_2": ("int32", [3]),
        "parents_3": ("int32", [2]),
        "features_1": ("float32", [3, 3]),
        "features_2": ("float32", [2, 3]),
        "features_3": ("float32", [1, 3]),
        "seen_1": ("uint8", [3]),
        "seen_2": ("uint8", [2]),
        "seen_3": ("uint8", [1]),
    }
    np.testing.assert_array_equal(tensors["seen_1"], [1, 1, 0])
    assert header == {
        "format": "thgs.semantic_field",
        "version": 4,
        "space": "sentence-transformers/all-MiniLM-L6-v2",
        "fingerprint": FINGERPRINT,
        "config": {"partition": {"levels": ["s", "m", "l"], "regularization": 0.1}, "seed": 0},
        "gaussians": 6,
        "region_counts": [4, 3, 2, 1],
        "checksum": checksum(tensors),
        "provenance": {"scene": None, "text_model": None, "thgs_version": None},
    }
    with safe_open(str(path), framework="numpy") as handle:
        raw = handle.metadata()["thgs"]
    assert raw == json.dumps(header, sort_keys=True)


def test_same_field_gives_the_same_bytes(tmp_path):
    first, second, third = (tmp_path / f"{name}.safetensors" for name in ("a", "b", "c"))
    save_field(first, mug_field())
    save_field(second, mug_field())
    save_field(third, load_field(first))
    assert first.read_bytes() == second.read_bytes() == third.read_bytes()


def test_saving_an_invalid_field_leaves_the_old_file_and_no_temporary(tmp_path):
    path = tmp_path / "field.safetensors"
    save_field(path, mug_field())
    before = path.read_bytes()
    broken = replace_level(mug_field(), "parents", 1, np.array([0, 1, 2, 2], dtype=np.int32))
    with pytest.raises(InputError, match="not nested") as caught:
        save_field(path, broken)
    assert str(path) in caught.value.source
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["field.safetensors"]
    with pytest.raises(InputError):
        save_field(tmp_path / "new.safetensors", broken)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["field.safetensors"]


def test_save_creates_missing_folders(tmp_path):
    path = tmp_path / "out" / "scene" / "field.safetensors"
    save_field(path, mug_field())
    assert load_field(path).region_counts == (4, 3, 2, 1)


@pytest.mark.parametrize("keep", [0, 5, 8, 60, -1])
def test_truncated_file_is_refused_with_its_path(tmp_path, keep):
    path = tmp_path / "field.safetensors"
    save_field(path, mug_field())
    data = path.read_bytes()
    path.write_bytes(data[: keep if keep >= 0 else len(data) + keep])
    with pytest.raises(InputError, match="not a readable safetensors file") as caught:
        load_field(path)
    assert caught.value.source == str(path)


def test_missing_file_and_folder_are_refused(tmp_path):
    with pytest.raises(InputError, match="semantic field file not found") as caught:
        load_field(tmp_path / "absent.safetensors")
    assert caught.value.source == str(tmp_path / "absent.safetensors")
    with pytest.raises(InputError, match="not found"):
        load_field(tmp_path)


def _label_offset(data: bytes, row: int, column: int) -> int:
    """Byte offset of ``labels[row, column]`` in a safetensors file's bytes."""
    header_size = struct.unpack("<Q", data[:8])[0]
    header = json.loads(data[8 : 8 + header_size])
    start = header["labels"]["data_offsets"][0]
    return 8 + header_size + start + 4 * (row * header["labels"]["shape"][1] + column)


def test_label_edited_in_the_file_bytes_is_refused(tmp_path):
    path = tmp_path / "field.safetensors"
    save_field(path, mug_field())
    data = bytearray(path.read_bytes())
    offset = _label_offset(bytes(data), row=1, column=0)
    assert struct.unpack("<i", data[offset : offset + 4])[0] == 0
    data[offset : offset + 4] = struct.pack("<i", 3)  # Gaussian 1 moved to the handle superpoint
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match="labels are not nested between levels 0 and 1") as caught:
        load_field(path)
    assert caught.value.source == str(path)


def _raw_field(**changes) -> tuple[dict[str, np.ndarray], dict]:
    """The tensors and header save_field writes for the mug, with header keys changed."""
    field = mug_field()
    tensors = {"labels": field.labels}
    for k in (1, 2, 3):
        tensors[f"parents_{k}"] = field.parents[k - 1]
        tensors[f"features_{k}"] = field.features[k - 1]
        tensors[f"seen_{k}"] = field.seen[k - 1].astype(np.uint8)
    header = {
        "format": "thgs.semantic_field",
        "version": FORMAT_VERSION,
        "space": field.space,
        "fingerprint": field.fingerprint,
        "config": field.config,
        "gaussians": 6,
        "region_counts": [4, 3, 2, 1],
        "checksum": checksum(tensors),
        "provenance": field.provenance.to_json(),
    }
    header.update(changes)
    if header["version"] in (1, 2, 3):  # the record had no place of its own before version 4
        header.pop("provenance")
    return tensors, header


def test_raw_writer_matches_save_field(tmp_path):
    """Guards the tampering tests below: unchanged, _raw_field writes save_field's bytes."""
    save_field(tmp_path / "saved.safetensors", mug_field())
    write_raw(tmp_path / "raw.safetensors", *_raw_field())
    saved = (tmp_path / "saved.safetensors").read_bytes()
    assert (tmp_path / "raw.safetensors").read_bytes() == saved


def test_version_1_files_are_read_with_their_timings(tmp_path):
    timings = [["lift", 1.5], ["knn", 0.25], ["partition", 3.0], ["merge", 0.125]]
    write_raw(tmp_path / "v1.safetensors", *_raw_field(version=1, timings=timings))
    loaded = load_field(tmp_path / "v1.safetensors")
    assert list(loaded.timings.items()) == [tuple(pair) for pair in timings]
    np.testing.assert_array_equal(loaded.labels, mug_field().labels)


def test_timings_do_not_change_the_bytes(tmp_path):
    save_field(tmp_path / "a.thgs", mug_field())
    save_field(tmp_path / "b.thgs", dataclasses.replace(mug_field(), timings={"lift": 99.0}))
    assert (tmp_path / "a.thgs").read_bytes() == (tmp_path / "b.thgs").read_bytes()


def _drop(tensors: dict, name: str) -> dict:
    return {key: value for key, value in tensors.items() if key != name}


def _retype(tensors: dict, name: str, dtype: type) -> dict:
    return {**tensors, name: tensors[name].astype(dtype)}


TAMPERED = {
    "newer version": (
        lambda t, h: (t, {**h, "version": 5}),
        "written by a newer thgs (version 5), this one reads 4",
    ),
    "version zero": (lambda t, h: (t, {**h, "version": 0}), "invalid format version 0"),
    "version as text": (lambda t, h: (t, {**h, "version": "1"}), "invalid format version '1'"),
    "no metadata": (lambda t, h: (t, None), "not a thgs semantic field file (no 'thgs' metadata)"),
    "other format": (
        lambda t, h: (t, {**h, "format": "thgs.hierarchy"}),
        "not a thgs semantic field file (format 'thgs.hierarchy')",
    ),
    "version 1 without timings": (
        lambda t, h: (t, {**h, "version": 1}),
        "metadata lacks ['timings']",
    ),
    "metadata key missing": (
        lambda t, h: (t, {k: v for k, v in h.items() if k != "space"}),
        "metadata lacks ['space']",
    ),
    "timings not pairs": (
        lambda t, h: (t, {**h, "version": 1, "timings": {"lift": 1.0}}),
        "metadata 'timings' must be a list of [stage, seconds] pairs",
    ),
    "timings repeat a stage": (
        lambda t, h: (t, {**h, "version": 1, "timings": [["lift", 1.0], ["lift", 2.0]]}),
        "metadata 'timings' names a stage twice",
    ),
    "timing negative": (
        lambda t, h: (t, {**h, "version": 1, "timings": [["lift", -1.0]]}),
        "timings['lift'] must be finite seconds >= 0",
    ),
    "tensor missing": (
        lambda t, h: (_drop(t, "seen_2"), h),
        "missing tensors ['seen_2']",
    ),
    "tensor unexpected": (
        lambda t, h: ({**t, "names": np.zeros(1, np.uint8)}, h),
        "unexpected tensors ['names'] in format version 4",
    ),
    "labels as int64": (
        lambda t, h: (_retype(t, "labels", np.int64), h),
        "tensor 'labels' is int64, expected int32",
    ),
    "seen as bool": (
        lambda t, h: (_retype(t, "seen_1", np.bool_), h),
        "tensor 'seen_1' is bool, expected uint8",
    ),
    "seen not 0/1": (
        lambda t, h: ({**t, "seen_3": np.array([2], np.uint8)}, h),
        "tensor 'seen_3' must hold 0 or 1, found 2",
    ),
    "gaussian count": (
        lambda t, h: (t, {**h, "gaussians": 7}),
        "metadata says 7 Gaussians, labels have 6 rows",
    ),
    "region counts": (
        lambda t, h: (t, {**h, "region_counts": [4, 3, 2, 2]}),
        "metadata says region counts [4, 3, 2, 2], tensors have [4, 3, 2, 1]",
    ),
    "fingerprint": (
        lambda t, h: (t, {**h, "fingerprint": "md5:1234"}),
        "fingerprint must be 'sha256:'",
    ),
    "feature no longer unit": (
        lambda t, h: ({**t, "features_3": np.array([[0, 0.6, 0.9]], np.float32)}, h),
        "features[2] rows of seen regions must be unit vectors",
    ),
}


@pytest.mark.parametrize("case", TAMPERED, ids=list(TAMPERED))
def test_tampered_file_is_refused_with_its_path(tmp_path, case):
    tamper, message = TAMPERED[case]
    path = tmp_path / "field.safetensors"
    write_raw(path, *tamper(*_raw_field()))
    with pytest.raises(InputError, match=re.escape(message)) as caught:
        load_field(path)
    assert caught.value.source == str(path)


# fingerprint


def test_fingerprint_follows_the_documented_recipe():
    gaussians = random_gaussians(5, kind="2dgs", seed=3)
    digest = hashlib.sha256(b"thgs.scene_fingerprint\x005\x002dgs\x00")
    for tensor in (gaussians.means, gaussians.quats, gaussians.scales, gaussians.opacities):
        digest.update(tensor.numpy().astype("<f4").tobytes())
    assert scene_fingerprint(gaussians) == f"sha256:{digest.hexdigest()}"


def test_fingerprint_is_geometry_identity():
    gaussians = random_gaussians(200, seed=1)
    fingerprint = scene_fingerprint(gaussians)
    assert re.fullmatch(r"sha256:[0-9a-f]{64}", fingerprint)
    copy = dataclasses.replace(gaussians, means=gaussians.means.clone())
    assert scene_fingerprint(copy) == fingerprint
    as_float64 = {
        name: getattr(gaussians, name).double()
        for name in ("means", "quats", "scales", "opacities", "sh")
    }
    assert scene_fingerprint(dataclasses.replace(gaussians, **as_float64)) == fingerprint
    recoloured = dataclasses.replace(
        gaussians, sh=gaussians.sh + 1.0, normals=None, extras={"note": np.ones(200)}
    )
    assert scene_fingerprint(recoloured) == fingerprint
    means = gaussians.means.clone()
    means[17, 2] = torch.nextafter(means[17, 2], torch.tensor(np.inf))
    assert scene_fingerprint(dataclasses.replace(gaussians, means=means)) != fingerprint
    for name in ("quats", "scales", "opacities"):
        values = getattr(gaussians, name).clone()
        values[0] *= 2
        assert scene_fingerprint(dataclasses.replace(gaussians, **{name: values})) != fingerprint
    reordered = gaussians.select(torch.arange(199, -1, -1))
    assert scene_fingerprint(reordered) != fingerprint
    assert scene_fingerprint(gaussians.select(torch.arange(199))) != fingerprint


# docs/field.md


def _doc_blocks() -> list[str]:
    text = (Path(__file__).resolve().parents[1] / "docs" / "field.md").read_text()
    return re.findall(r"```python\n(.*?)```", text, re.S)


def test_documented_example_is_the_tested_one():
    blocks = _doc_blocks()
    example = next(block for block in blocks if "SemanticField(" in block)
    namespace: dict = {}
    exec(example, namespace)
    documented, expected = namespace["field"], mug_field()
    np.testing.assert_array_equal(documented.labels, expected.labels)
    for name in ("parents", "features", "seen"):
        for got, want in zip(getattr(documented, name), getattr(expected, name), strict=True):
            np.testing.assert_array_equal(got, want)
    assert (documented.config, documented.timings) == (expected.config, expected.timings)
    navigation = next(block for block in blocks if "argsort" in block)
    namespace = {"np": np, "field": expected, "query": np.array([0, 0, 1], np.float32)}
    exec(navigation, namespace)
    assert [group.tolist() for group in namespace["groups"]] == [[0, 1, 2, 3], [4, 5]]
    np.testing.assert_array_equal(namespace["objects_of_superpoints"], [0, 0, 0, 0])
    np.testing.assert_array_equal(namespace["scores"], [0, 1])
    np.testing.assert_array_equal(namespace["selected"], [False] * 4 + [True] * 2)


def test_content_altered_after_writing_is_refused_and_version_2_still_reads(tmp_path):
    """A feature nudged by 1e-6 (still a unit vector, every invariant holds) under an intact
    header: the checksum refuses it. A version-2 file has no checksum and reads as before."""
    tensors, header = _raw_field()
    tensors["features_1"] = tensors["features_1"].copy()
    tensors["features_1"][0, 0] += 1e-6
    write_raw(tmp_path / "altered.thgs", tensors, header)
    with pytest.raises(InputError, match="its content is not what was written") as caught:
        load_field(tmp_path / "altered.thgs")
    assert caught.value.source == str(tmp_path / "altered.thgs")
    tensors, header = _raw_field(version=2)
    del header["checksum"]
    write_raw(tmp_path / "v2.thgs", tensors, header)
    np.testing.assert_array_equal(load_field(tmp_path / "v2.thgs").labels, mug_field().labels)


def test_provenance_is_kept_beside_the_config_and_read_back_typed(tmp_path):
    record = Provenance(
        scene=SceneRecord(
            "../scene", source="/data/garden", iteration=30000, images="images_4", scale=0.25
        ),
        text_model="/models/clip",
        thgs_version="1.2.3",
    )
    field = dataclasses.replace(mug_field(), provenance=record)
    save_field(tmp_path / "f.thgs", field)
    loaded = load_field(tmp_path / "f.thgs")
    assert loaded.provenance == record
    assert loaded.config == mug_field().config  # the build settings alone
    _, header = read_raw(tmp_path / "f.thgs")
    assert header["provenance"] == {
        "scene": {
            "path": "../scene",
            "source": "/data/garden",
            "iteration": 30000,
            "images": "images_4",
            "scale": 0.25,
        },
        "text_model": "/models/clip",
        "thgs_version": "1.2.3",
    }


def test_a_version_3_field_keeps_its_scene_and_text_model_in_the_record(tmp_path):
    """Before version 4 the scene and the text model were entries of the config."""
    config = {**mug_field().config, "scene": {"path": "output/teatime", "scale": 0.5}}
    config["text_model"] = "/models/clip"
    write_raw(tmp_path / "v3.thgs", *_raw_field(version=3, config=config))
    loaded = load_field(tmp_path / "v3.thgs")
    assert loaded.config == mug_field().config
    assert loaded.provenance == Provenance(
        scene=SceneRecord("output/teatime", scale=0.5), text_model="/models/clip"
    )
    assert loaded.provenance.thgs_version is None  # not recorded then


@pytest.mark.parametrize(
    ("provenance", "message"),
    [
        ([], "provenance must be an object, got list"),
        ({"scene": None, "owner": "x"}, "provenance has unknown entries ['owner']"),
        ({"text_model": 3}, "provenance's text_model must be a string, got 3"),
        ({"scene": {"source": "x"}}, "the scene record must be an object with a 'path' string"),
        ({"scene": {"path": "x", "scale": 0}}, "the scene record's scale must be > 0, got 0"),
        ({"scene": {"path": "x", "iteration": True}}, "iteration must be an integer, got True"),
        ({"scene": {"path": "x", "zoom": 2}}, "the scene record has unknown entries ['zoom']"),
    ],
)
def test_a_bad_provenance_is_named(tmp_path, provenance, message):
    write_raw(tmp_path / "bad.thgs", *_raw_field(provenance=provenance))
    with pytest.raises(InputError, match=re.escape(message)) as caught:
        load_field(tmp_path / "bad.thgs")
    assert caught.value.source == str(tmp_path / "bad.thgs")
