"""LERF-OVS label files and polygon rasterization."""

from __future__ import annotations

import json

import numpy as np
import pytest

from thgs import InputError
from thgs.eval import (
    FrameLabels,
    LabelledObject,
    mask_to_polygons,
    rasterize_polygon,
    read_lerf_labels,
    write_lerf_labels,
)

REAL_FILES = ("teatime/frame_00002.json", "waldo_kitchen/frame_00053.json")


def point_in_polygon(x, y, vertices):
    """Textbook ray casting for one point (the slow reference)."""
    inside = False
    n = len(vertices)
    for i in range(n):
        (xa, ya), (xb, yb) = vertices[i], vertices[(i + 1) % n]
        if (ya <= y) != (yb <= y) and x >= xa + (y - ya) * (xb - xa) / (yb - ya):
            inside = not inside
    return inside


def test_rectangle_covers_its_area():
    mask = rasterize_polygon(np.array([[2, 1], [5, 1], [5, 3], [2, 3]]), 6, 8)
    expected = np.zeros((6, 8), dtype=bool)
    expected[1:3, 2:5] = True
    np.testing.assert_array_equal(mask, expected)
    # the same rectangle, the other way round
    np.testing.assert_array_equal(
        rasterize_polygon(np.array([[2, 3], [5, 3], [5, 1], [2, 1]]), 6, 8), expected
    )


def test_adjacent_polygons_share_no_pixel():
    left = rasterize_polygon(np.array([[0, 0], [3.3, 0], [2.2, 6], [0, 6]]), 6, 6)
    right = rasterize_polygon(np.array([[3.3, 0], [6, 0], [6, 6], [2.2, 6]]), 6, 6)
    assert not (left & right).any() and (left | right).all()


def test_random_polygons_match_ray_casting():
    rng = np.random.default_rng(0)
    for _ in range(5):
        vertices = rng.uniform(-2, 22, size=(int(rng.integers(3, 9)), 2))
        mask = rasterize_polygon(vertices, 20, 20)
        expected = np.array(
            [[point_in_polygon(u + 0.5, v + 0.5, vertices) for u in range(20)] for v in range(20)]
        )
        np.testing.assert_array_equal(mask, expected)


def shoelace(polygon):
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def test_real_labels(shared_data):
    frame = read_lerf_labels(shared_data / "lerf_ovs_labels" / "waldo_kitchen" / "frame_00053.json")
    assert (frame.image_name, frame.width, frame.height) == ("frame_00053.jpg", 985, 725)
    assert len(frame.objects) == 8
    assert frame.categories == (
        "knife",
        "yellow desk",
        "toaster",
        "Stainless steel pots",
        "pour-over vessel",
        "ottolenghi",
    )
    stored = json.loads(
        (shared_data / "lerf_ovs_labels/waldo_kitchen/frame_00053.json").read_text()
    )
    for obj, raw in zip(frame.objects, stored["objects"], strict=True):
        area = shoelace(obj.polygon)
        assert area == pytest.approx(raw["area"])
        pixels = rasterize_polygon(obj.polygon, 725, 985).sum()
        perimeter = np.linalg.norm(obj.polygon - np.roll(obj.polygon, -1, axis=0), axis=1).sum()
        assert abs(pixels - area) <= 0.5 * perimeter
    knives = frame.category_mask("knife")
    union = np.zeros_like(knives)
    for obj in frame.objects[:3]:
        union |= rasterize_polygon(obj.polygon, 725, 985)
    np.testing.assert_array_equal(knives, union)
    assert len(frame.category_boxes("knife")) == 3
    double = frame.category_mask("toaster", height=1450, width=1970)
    assert double.sum() == pytest.approx(4 * frame.category_mask("toaster").sum(), rel=0.02)
    with pytest.raises(InputError, match="no category 'spoon'"):
        frame.category_mask("spoon")


def test_teatime_labels(shared_data):
    frame = read_lerf_labels(shared_data / "lerf_ovs_labels" / "teatime" / "frame_00002.json")
    assert (frame.width, frame.height, len(frame.objects)) == (988, 730, 11)
    assert "bear nose" in frame.categories and "stuffed bear" in frame.categories
    nose, bear = frame.category_mask("bear nose"), frame.category_mask("stuffed bear")
    assert nose.sum() > 0 and (nose & bear).sum() > 0.5 * nose.sum()  # the nose lies on the bear


@pytest.mark.parametrize(
    ("document", "message"),
    [
        ([], "expected an object with 'info'"),
        ({"info": {"width": 10}, "objects": []}, "info has no 'height'"),
        ({"info": {"width": 10, "height": 0}, "objects": []}, "not positive"),
        ({"info": {"width": 10, "height": 5}}, "no 'objects' list"),
        (
            {
                "info": {"width": 10, "height": 5},
                "objects": [{"category": "cup", "segmentation": [[12, 1], [15, 1], [14, 4]]}],
            },
            r"object 0 \('cup'\): 'segmentation' lies wholly outside the 10×5 image \(x 12 "
            r"to 15, y 1 to 4\), so its mask would be empty$",
        ),
        (
            {"info": {"width": 10, "height": 5}, "objects": [{"segmentation": []}]},
            "object 0 has no 'category'",
        ),
        (
            {
                "info": {"width": 10, "height": 5},
                "objects": [{"category": "a", "segmentation": [[0, 0], [1, 1]]}],
            },
            r"object 0: 'segmentation' must have at least 3 points, got 2$",
        ),
        (
            {
                "info": {"width": 10, "height": 5},
                "objects": [{"category": "a", "segmentation": [[0, 0, 1], [1, 1, 1], [2, 0, 1]]}],
            },
            r"object 0: 'segmentation' must hold 2-D \[x, y\] points, got 3-D points$",
        ),
        (
            {
                "info": {"width": 10, "height": 5},
                "objects": [{"category": "a", "segmentation": [1, 2, 3, 4, 5, 6]}],
            },
            r"must be a list of \[x, y\] points, got an array of shape \[6\]$",
        ),
        (
            {
                "info": {"width": 10, "height": 5},
                "objects": [
                    {"category": "a", "segmentation": [[0, 0], [2, 0], [2, 2]]},
                    {"category": " ", "segmentation": [[0, 0], [2, 0], [2, 2]]},
                ],
            },
            r"object 1: 'category' is empty; it is the text queried$",
        ),
    ],
)
def test_bad_label_files(tmp_path, document, message):
    path = tmp_path / "frame.json"
    path.write_text(json.dumps(document))
    with pytest.raises(InputError, match=message) as info:
        read_lerf_labels(path)
    assert str(info.value).startswith(str(path))


def assert_same_objects(a, b):
    assert (a.image_name, a.width, a.height) == (b.image_name, b.width, b.height)
    assert len(a.objects) == len(b.objects)
    for x, y in zip(a.objects, b.objects):
        assert (x.category, x.group, x.bbox) == (y.category, y.group, y.bbox)
        np.testing.assert_array_equal(x.polygon, y.polygon)


def test_groups_of_the_real_files(shared_data):
    kitchen = read_lerf_labels(shared_data / "lerf_ovs_labels" / REAL_FILES[1])
    # as stored: the three knives are groups 1-3, then 4, 5, 6, and two objects back in group 1
    assert [obj.group for obj in kitchen.objects] == [1, 2, 3, 4, 5, 6, 1, 1]
    teatime = read_lerf_labels(shared_data / "lerf_ovs_labels" / REAL_FILES[0])
    assert [obj.group for obj in teatime.objects] == [1] * 11


@pytest.mark.parametrize("name", REAL_FILES)
def test_real_files_write_back_byte_for_byte(shared_data, tmp_path, name):
    source = shared_data / "lerf_ovs_labels" / name
    frame = read_lerf_labels(source)
    target = tmp_path / "out.json"
    write_lerf_labels(target, frame)
    assert_same_objects(read_lerf_labels(target), frame)
    assert target.read_bytes() == source.read_bytes()


def key_paths(document):
    """Every key path in document order, lists reduced to their first element's keys."""
    if isinstance(document, dict):
        return [(key, key_paths(value)) for key, value in document.items()]
    if isinstance(document, list) and document and isinstance(document[0], dict):
        return [key_paths(entry) for entry in document]
    return type(document).__name__


def test_written_layout_matches_the_real_file(shared_data, tmp_path):
    real = json.loads((shared_data / "lerf_ovs_labels" / REAL_FILES[1]).read_text())
    square = np.array([[1.0, 1.0], [4.0, 1.0], [4.0, 3.0], [1.0, 3.0]])
    frame = FrameLabels(
        "frame_00001.jpg",
        20,
        10,
        tuple(LabelledObject(f"thing {i}", square + i, (1.0 + i, 1.0 + i, 4.0 + i, 3.0 + i), i)
              for i in range(8)),
    )  # fmt: skip
    path = tmp_path / "frame_00001.json"
    write_lerf_labels(path, frame)
    written = json.loads(path.read_text())
    # same keys in the same order, same value types (int group/depth, float area/layer/bbox)
    assert key_paths(written) == key_paths(real)
    assert list(written["info"]) == ["name", "width", "height", "depth", "note"]
    assert written["info"] == {
        "name": "frame_00001.jpg", "width": 20, "height": 10, "depth": 3, "note": ""
    }  # fmt: skip
    first = written["objects"][0]
    assert list(first) == [
        "category", "group", "segmentation", "area", "layer", "bbox", "iscrowd", "note"
    ]  # fmt: skip
    assert first["area"] == 6.0 and first["bbox"] == [1.0, 1.0, 4.0, 3.0]
    assert [obj["layer"] for obj in written["objects"]] == [float(i) for i in range(1, 9)]
    assert all(obj["iscrowd"] == 0 and obj["note"] == "" for obj in written["objects"])
    assert path.read_bytes().startswith(b'{\r\n    "info": {\r\n        "name": "frame_00001.jpg"')


def test_masks_round_trip_through_label_files(tmp_path):
    rng = np.random.default_rng(3)
    height, width = 40, 60
    cup = np.zeros((height, width), dtype=bool)
    cup[5:25, 10:30] = True
    cup[10:15, 15:20] = False  # a hole: still one polygon
    saucer = np.zeros_like(cup)
    saucer[30:38, 5:58] = True
    speckle = rng.random((height, width)) < 0.02
    objects = []
    for group, (category, mask) in enumerate(
        [("cup", cup), ("saucer", saucer), ("crumbs", speckle)], start=1
    ):
        for polygon in mask_to_polygons(mask):
            low, high = polygon.min(axis=0), polygon.max(axis=0)
            bbox = (low[0], low[1], high[0], high[1])
            objects.append(LabelledObject(category, polygon, bbox, group))
    frame = FrameLabels("view_000.png", width, height, tuple(objects))
    path = tmp_path / "view_000.json"
    write_lerf_labels(path, frame)
    back = read_lerf_labels(path)
    assert_same_objects(back, frame)
    for category, mask in [("cup", cup), ("saucer", saucer), ("crumbs", speckle)]:
        np.testing.assert_array_equal(back.category_mask(category), mask)
    areas = [obj["area"] for obj in json.loads(path.read_text())["objects"]]
    assert areas[:2] == [375.0, 424.0]  # 20·20 − 5·5 (the hole) and 8·53 pixels


def test_group_defaults_and_non_ascii(tmp_path):
    document = {
        "info": {"name": "a.jpg", "width": 10, "height": 10},
        "objects": [
            {"category": "tasse à café", "segmentation": [[0, 0], [2, 0], [2, 2]]},
            {"category": "b", "group": None, "segmentation": [[0, 0], [2, 0], [2, 2]]},
            {"category": "c", "group": 7, "segmentation": [[0, 0], [2, 0], [2, 2]]},
        ],
    }
    path = tmp_path / "a.json"
    path.write_text(json.dumps(document), encoding="utf-8")
    frame = read_lerf_labels(path)
    assert [obj.group for obj in frame.objects] == [0, 0, 7]
    write_lerf_labels(tmp_path / "b.json", frame)
    assert "tasse à café" in (tmp_path / "b.json").read_text(encoding="utf-8")
    assert_same_objects(read_lerf_labels(tmp_path / "b.json"), frame)
    assert frame.objects[0].bbox == (0.0, 0.0, 2.0, 2.0)


@pytest.mark.parametrize("group", ["1", 1.5, True])
def test_bad_group(tmp_path, group):
    document = {
        "info": {"width": 10, "height": 5},
        "objects": [{"category": "a", "group": group, "segmentation": [[0, 0], [1, 0], [1, 1]]}],
    }
    path = tmp_path / "frame.json"
    path.write_text(json.dumps(document))
    with pytest.raises(InputError, match=r"object 0: 'group' is .* not an integer"):
        read_lerf_labels(path)


def test_bad_labels_are_not_written(tmp_path):
    path = tmp_path / "frame.json"
    path.write_text("previous")
    triangle = np.array([[0.0, 0.0], [4.0, 0.0], [0.0, 2.0]])
    cases = [
        (FrameLabels("a", 10, 5, (LabelledObject("a", triangle, (0, 0, 4, 3)),)), "bounds"),
        (
            FrameLabels("a", 10, 5, (LabelledObject("a", triangle[:2], (0, 0, 4, 0)),)),
            "must have at least 3 points, got 2",
        ),
        (FrameLabels("a", 0, 5, ()), "not positive"),
        (
            FrameLabels("a", 10, 5, (LabelledObject("a", triangle * np.nan, (0, 0, 4, 2)),)),
            "NaN",
        ),
    ]
    for frame, message in cases:
        with pytest.raises(InputError, match=message) as info:
            write_lerf_labels(path, frame)
        assert str(info.value).startswith(f"labels to write to {path}")
    assert path.read_text() == "previous"
    assert [p.name for p in tmp_path.iterdir()] == ["frame.json"]
