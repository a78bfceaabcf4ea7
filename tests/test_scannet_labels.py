"""ScanNet per-point labels: the class subsets, the PLY layout, the class sidecar, bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest

from thgs import InputError
from thgs.eval import (
    SCANNET10_IDS,
    SCANNET15_IDS,
    SCANNET19_IDS,
    SCANNET19_NAMES,
    PointLabels,
    read_scannet_labels,
    scannet_classes_path,
    write_scannet_labels,
)

# ScanNet's BenchmarkScripts/3d_evaluation/evaluate_semantic_label.py
BENCHMARK_IDS = [1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39]
BENCHMARK_NAMES = [
    "wall", "floor", "cabinet", "bed", "chair", "sofa", "table", "door", "window", "bookshelf",
    "picture", "counter", "desk", "curtain", "refrigerator", "shower curtain", "toilet", "sink",
    "bathtub", "otherfurniture",
]  # fmt: skip


def test_class_subsets():
    assert (len(SCANNET19_IDS), len(SCANNET15_IDS), len(SCANNET10_IDS)) == (19, 15, 10)
    assert dict(SCANNET19_NAMES) == dict(zip(BENCHMARK_IDS[:-1], BENCHMARK_NAMES[:-1]))
    assert list(SCANNET19_IDS) == BENCHMARK_IDS[:-1]
    dropped_15 = [SCANNET19_NAMES[i] for i in SCANNET19_IDS if i not in SCANNET15_IDS]
    assert dropped_15 == ["picture", "refrigerator", "shower curtain", "bathtub"]
    dropped_10 = [SCANNET19_NAMES[i] for i in SCANNET15_IDS if i not in SCANNET10_IDS]
    assert dropped_10 == ["cabinet", "counter", "desk", "curtain", "sink"]
    assert [SCANNET19_NAMES[i] for i in SCANNET10_IDS] == [
        "wall", "floor", "bed", "chair", "sofa", "table", "door", "window", "bookshelf", "toilet"
    ]  # fmt: skip
    with pytest.raises(TypeError):
        SCANNET19_NAMES[40] = "otherprop"  # type: ignore[index]


def scannet_style_file(path, points, labels, faces):
    """A label PLY laid out like ScanNet's, written by hand (header as in ScanNet's files)."""
    header = (
        "ply\nformat binary_little_endian 1.0\ncomment MLIB generated\n"
        f"element vertex {len(points)}\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n"
        "property ushort label\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    vertex = np.zeros(
        len(points),
        dtype=[("xyz", "<f4", 3), ("rgba", "u1", 4), ("label", "<u2")],
    )
    vertex["xyz"], vertex["rgba"], vertex["label"] = points, (174, 199, 232, 255), labels
    face = np.zeros(len(faces), dtype=[("n", "u1"), ("indices", "<i4", 3)])
    face["n"], face["indices"] = 3, faces
    path.write_bytes(header.encode() + vertex.tobytes() + face.tobytes())


def test_reads_a_scannet_layout_file(tmp_path):
    points = np.array([[0.5, 1.25, -2.0], [3.0, 0.0, 0.75], [1.0, 1.0, 1.0], [2.0, 2.0, 2.0]])
    labels = [1, 0, 39, 65535]
    path = tmp_path / "scene0000_00_vh_clean_2.labels.ply"
    scannet_style_file(path, points, labels, [[0, 1, 2], [1, 2, 3]])
    read = read_scannet_labels(path)
    assert read.points.dtype == np.float32 and read.labels.dtype == np.int64
    np.testing.assert_array_equal(read.points, points.astype(np.float32))
    assert read.labels.tolist() == [1, 0, 39, 65535]
    assert read.class_names == dict(SCANNET19_NAMES) and 39 not in read.class_names


def test_round_trip_with_nyu40_names(tmp_path):
    rng = np.random.default_rng(0)
    labels = PointLabels(
        rng.normal(size=(50, 3)).astype(np.float32),
        rng.choice([0, *SCANNET19_IDS], size=50).astype(np.int64),
        dict(SCANNET19_NAMES),
    )
    path = tmp_path / "scene_vh_clean_2.labels.ply"
    write_scannet_labels(path, labels)
    assert not scannet_classes_path(path).exists()
    data = path.read_bytes()
    header = data[: data.index(b"end_header\n") + len(b"end_header\n")].decode()
    assert header == (
        "ply\nformat binary_little_endian 1.0\nelement vertex 50\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n"
        "property ushort label\nend_header\n"
    )
    assert len(data) == len(header) + 50 * (3 * 4 + 4 + 2)
    first = np.frombuffer(data, dtype="<f4", count=3, offset=len(header))
    np.testing.assert_array_equal(first, labels.points[0])
    assert data[len(header) + 12 : len(header) + 16] == bytes([128, 128, 128, 255])
    assert int.from_bytes(data[len(header) + 16 : len(header) + 18], "little") == labels.labels[0]
    back = read_scannet_labels(path)
    np.testing.assert_array_equal(back.points, labels.points)
    np.testing.assert_array_equal(back.labels, labels.labels)
    assert back.class_names == dict(SCANNET19_NAMES)


def test_round_trip_with_synthetic_names_and_sidecar(tmp_path):
    points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    names = {3: "teddy bear", 1: "mug", 2: "tasse à café"}
    labels = PointLabels(points, np.array([1, 3, 0]), names)
    path = tmp_path / "synthetic.labels.ply"
    write_scannet_labels(path, labels)
    sidecar = tmp_path / "synthetic.labels.classes.json"
    assert scannet_classes_path(path) == sidecar
    assert json.loads(sidecar.read_text(encoding="utf-8")) == {
        "1": "mug", "2": "tasse à café", "3": "teddy bear"
    }  # fmt: skip
    assert list(json.loads(sidecar.read_text(encoding="utf-8"))) == ["1", "2", "3"]
    back = read_scannet_labels(path)
    assert back.class_names == names and back.labels.tolist() == [1, 3, 0]
    # an explicit table wins over the sidecar
    assert read_scannet_labels(path, {1: "cup"}).class_names == {1: "cup"}
    # a later write with the NYU40 table removes the now wrong sidecar
    write_scannet_labels(path, PointLabels(points, np.array([1, 3, 0]), dict(SCANNET19_NAMES)))
    assert not sidecar.exists()
    assert read_scannet_labels(path).class_names == dict(SCANNET19_NAMES)
    # a subset of the NYU40 table is kept exactly through the sidecar
    subset = {i: SCANNET19_NAMES[i] for i in SCANNET10_IDS}
    write_scannet_labels(path, PointLabels(points, np.array([1, 2, 0]), subset))
    assert read_scannet_labels(path).class_names == subset


def test_missing_label_property(tmp_path):
    path = tmp_path / "scene_vh_clean_2.ply"
    header = (
        "ply\nformat ascii 1.0\nelement vertex 1\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    path.write_text(header + "0 0 0\n")
    with pytest.raises(InputError, match=r"no vertex properties \['label'\]") as info:
        read_scannet_labels(path)
    assert info.value.source == str(path)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (None, "no such file"),
        (b"", "the file is empty"),
        (b"not a ply at all", "not a readable PLY file"),
        (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", "no 'vertex' element"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            b"property float z\nproperty float label\nend_header\n0 0 0 1.5\n",
            "non-integer values",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            b"property float z\nproperty int label\nend_header\n0 0 0 -1\n",
            r"ranges over \[-1, -1\]",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
            b"property float z\nproperty ushort label\nend_header\nnan 0 0 1\n",
            "NaN or infinite",
        ),
    ],
)
def test_bad_files(tmp_path, content, message):
    path = tmp_path / "labels.ply"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(InputError, match=message) as info:
        read_scannet_labels(path)
    assert info.value.source == str(path)


@pytest.mark.parametrize(
    ("sidecar", "message"),
    [
        ("[1, 2]", "expected an object"),
        ('{"one": "mug"}', "not an integer class id"),
        ('{"0": "mug"}', "not a class id in 1-65535"),
        ('{"01": "mug"}', "not a class id"),
        ('{"1": ""}', "not a non-empty string"),
        ("{", "not valid JSON"),
    ],
)
def test_bad_sidecar(tmp_path, sidecar, message):
    path = tmp_path / "x.labels.ply"
    write_scannet_labels(
        path, PointLabels(np.zeros((1, 3), np.float32), np.array([1]), dict(SCANNET19_NAMES))
    )
    scannet_classes_path(path).write_text(sidecar)
    with pytest.raises(InputError, match=message) as info:
        read_scannet_labels(path)
    assert info.value.source == str(scannet_classes_path(path))


@pytest.mark.parametrize(
    ("labels", "message"),
    [
        (PointLabels(np.zeros((2, 3), np.float64), np.zeros(2, np.int64), {}), "float32"),
        (PointLabels(np.zeros((2, 2), np.float32), np.zeros(2, np.int64), {}), r"\[N, 3\]"),
        (PointLabels(np.zeros((2, 3), np.float32), np.zeros(3, np.int64), {}), r"labels must be"),
        (PointLabels(np.zeros((2, 3), np.float32), np.zeros(2, np.int32), {}), "int64"),
        (PointLabels(np.zeros((1, 3), np.float32), np.array([70000]), {}), "not \\[0, 65535\\]"),
        (PointLabels(np.zeros((1, 3), np.float32), np.array([1]), {0: "none"}), "0 = unannotated"),
        (PointLabels(np.zeros((1, 3), np.float32), np.array([1]), {1: ""}), "has no name"),
    ],
)
def test_bad_labels_are_not_written(tmp_path, labels, message):
    path = tmp_path / "out.ply"
    with pytest.raises(InputError, match=message) as info:
        write_scannet_labels(path, labels)
    assert str(info.value).startswith(f"labels to write to {path}")
    assert list(tmp_path.iterdir()) == []
