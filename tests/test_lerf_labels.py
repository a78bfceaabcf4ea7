"""LERF-OVS label files and polygon rasterization."""

from __future__ import annotations

import json

import numpy as np
import pytest

from thgs import InputError
from thgs.eval import rasterize_polygon, read_lerf_labels


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
            {"info": {"width": 10, "height": 5}, "objects": [{"segmentation": []}]},
            "object 0 has no 'category'",
        ),
        (
            {
                "info": {"width": 10, "height": 5},
                "objects": [{"category": "a", "segmentation": [[0, 0], [1, 1]]}],
            },
            "≥ 3",
        ),
    ],
)
def test_bad_label_files(tmp_path, document, message):
    path = tmp_path / "frame.json"
    path.write_text(json.dumps(document))
    with pytest.raises(InputError, match=message) as info:
        read_lerf_labels(path)
    assert str(info.value).startswith(str(path))
