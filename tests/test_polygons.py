"""mask_to_polygons: exact pixel-edge polygons, checked by rasterizing them back."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from thgs import InputError
from thgs.eval import mask_to_polygons, rasterize_polygon


def signed_area(polygon):
    """Shoelace area, positive for polygons clockwise on screen (x right, y down)."""
    x, y = polygon[:, 0], polygon[:, 1]
    return 0.5 * (np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def winding_numbers(polygon, height, width):
    """[H, W] winding number of the polygon around each pixel centre (slow reference)."""
    ys, xs = np.mgrid[0:height, 0:width] + 0.5
    winding = np.zeros((height, width), dtype=int)
    for (xa, ya), (xb, yb) in zip(polygon, np.roll(polygon, -1, axis=0)):
        if ya == yb:
            continue
        crossing = (ya <= ys) != (yb <= ys)
        x_at = xa + (ys - ya) * (xb - xa) / (yb - ya)
        # a downward edge (y grows) with the centre on its left adds +1 for clockwise-on-screen
        winding += np.where(crossing & (xs < x_at), 1 if yb > ya else -1, 0)
    return winding


def check_exact(mask):
    """Every component rasterizes back exactly; areas equal pixel counts; returns the polygons."""
    labels, count = ndimage.label(mask)
    polygons = mask_to_polygons(mask)
    assert len(polygons) == count
    height, width = mask.shape
    for index, polygon in enumerate(polygons):
        component = labels == index + 1
        assert polygon.dtype == np.float64 and polygon.ndim == 2 and polygon.shape[1] == 2
        np.testing.assert_array_equal(polygon, np.round(polygon))
        np.testing.assert_array_equal(rasterize_polygon(polygon, height, width), component)
        assert abs(signed_area(polygon)) == component.sum()
        assert signed_area(polygon) > 0  # clockwise on screen, as documented
    return polygons


def test_empty_mask():
    assert mask_to_polygons(np.zeros((4, 5), dtype=bool)) == []
    assert mask_to_polygons(np.zeros((0, 0), dtype=bool)) == []


def test_single_pixel():
    mask = np.zeros((4, 5), dtype=bool)
    mask[2, 3] = True
    (polygon,) = mask_to_polygons(mask)
    np.testing.assert_array_equal(polygon, [[3, 2], [4, 2], [4, 3], [3, 3]])


def test_rectangle_touching_the_border():
    mask = np.ones((3, 4), dtype=bool)
    (polygon,) = check_exact(mask)
    np.testing.assert_array_equal(polygon, [[0, 0], [4, 0], [4, 3], [0, 3]])
    mask = np.zeros((5, 6), dtype=bool)
    mask[2:, 4:] = True  # bottom-right corner of the image
    (polygon,) = check_exact(mask)
    np.testing.assert_array_equal(polygon, [[4, 2], [6, 2], [6, 5], [4, 5]])


def test_l_shape_has_six_corners():
    mask = np.array([[1, 0], [1, 0], [1, 1]], dtype=bool)
    (polygon,) = check_exact(mask)
    np.testing.assert_array_equal(polygon, [[0, 0], [1, 0], [1, 2], [2, 2], [2, 3], [0, 3]])


def test_ring_is_one_polygon_with_a_bridge():
    mask = np.ones((3, 3), dtype=bool)
    mask[1, 1] = False
    (polygon,) = check_exact(mask)
    # outer loop from its top-left corner; at (0, 0), the nearest corner to the hole's first
    # vertex (1, 1), an L-shaped bridge via (1, 0) to the hole, round it (anticlockwise on
    # screen) and back the same way
    expected = [
        [0, 0], [1, 0], [1, 1], [1, 2], [2, 2], [2, 1], [1, 1], [1, 0], [0, 0],
        [3, 0], [3, 3], [0, 3],
    ]  # fmt: skip
    np.testing.assert_array_equal(polygon, expected)
    assert signed_area(polygon) == 8


def test_several_holes_and_nested_components():
    mask = np.zeros((9, 12), dtype=bool)
    mask[1:8, 1:11] = True
    mask[2:4, 2:4] = False  # hole 1
    mask[4:7, 7:10] = False  # hole 2
    mask[2, 9] = False  # hole 3, a single pixel
    mask[2:7, 5] = False  # hole 4, a slit
    island = np.zeros_like(mask)
    island[5, 8] = True  # an island inside hole 2: its own component
    mask[5, 8] = True
    assert (ndimage.label(~mask)[1]) == 5  # outside + 4 holes
    polygons = check_exact(mask)
    assert len(polygons) == 2
    # label order: the island starts later in raster order
    np.testing.assert_array_equal(rasterize_polygon(polygons[1], 9, 12), island)
    np.testing.assert_array_equal(polygons[1], [[8, 5], [9, 5], [9, 6], [8, 6]])


def test_diagonal_pixels():
    # separate components where they touch only at a corner (4-connectivity)
    polygons = check_exact(np.eye(4, dtype=bool))
    assert [p.tolist() for p in polygons] == [
        [[i, i], [i + 1, i], [i + 1, i + 1], [i, i + 1]] for i in range(4)
    ]
    # one component whose own pixels touch diagonally at (2, 2): the background pixel (1, 1)
    # reaches the outside through that corner, and the boundary passes the corner twice
    mask = np.array([[1, 1, 1], [1, 0, 1], [1, 1, 0]], dtype=bool)
    (polygon,) = check_exact(mask)
    assert sum(vertex == [2, 2] for vertex in polygon.tolist()) == 2
    # a checkerboard: every pixel its own component
    checker = (np.indices((5, 7)).sum(axis=0) % 2).astype(bool)
    assert len(check_exact(checker)) == checker.sum()


def test_random_masks_rasterize_back_exactly():
    holes_seen = 0
    for seed in range(200):
        rng = np.random.default_rng(seed)
        height, width = (int(v) for v in rng.integers(1, 24, size=2))
        if seed % 3 == 0:  # smooth blobs with larger holes
            mask = ndimage.gaussian_filter(rng.random((height, width)), 1.2) > 0.5
        else:  # speckle: single pixels, diagonal contacts, many small holes
            mask = rng.random((height, width)) < rng.uniform(0.2, 0.85)
        check_exact(mask)
        holes_seen += int((ndimage.binary_fill_holes(mask) & ~mask).any())
    assert holes_seen > 20  # the sample does exercise holes


def test_non_zero_winding_also_fills_exactly():
    for seed in range(30):
        rng = np.random.default_rng(1000 + seed)
        mask = rng.random((12, 15)) < 0.6
        labels, _ = ndimage.label(mask)
        for index, polygon in enumerate(mask_to_polygons(mask)):
            winding = winding_numbers(polygon, 12, 15)
            np.testing.assert_array_equal(winding, (labels == index + 1).astype(int))


def test_larger_blob():
    rng = np.random.default_rng(7)
    mask = ndimage.gaussian_filter(rng.random((120, 160)), 3) > 0.5
    check_exact(mask)


@pytest.mark.parametrize(
    "mask", [np.zeros((3, 3), dtype=np.uint8), np.zeros(5, dtype=bool), np.zeros((2, 2, 2), bool)]
)
def test_bad_input(mask):
    with pytest.raises(InputError, match="mask_to_polygons: expected an \\[H, W\\] bool mask"):
        mask_to_polygons(mask)


def test_arbitrary_polygons_match_the_even_odd_reference_everywhere():
    # real label polygons: non-integer vertices, self-intersections, parts outside the image
    # above and below, vertices exactly on pixel-centre rows; only the rows the polygon spans are
    # scanned, so the rows outside must stay empty and the rest match the all-pixel reference
    rng = np.random.default_rng(5)
    height, width = 23, 31
    for case in range(60):
        count = int(rng.integers(3, 9))
        polygon = rng.uniform([-6, -6], [width + 6, height + 6], size=(count, 2))
        if case % 3 == 0:
            polygon[:, 1] = np.round(polygon[:, 1]) + 0.5  # on centre rows
        if case % 5 == 0:
            polygon[1, 1] = polygon[0, 1]  # a horizontal edge
        expected = winding_numbers(polygon, height, width) % 2 == 1
        np.testing.assert_array_equal(rasterize_polygon(polygon, height, width), expected)
    far = np.array([[0.0, -9.0], [5.0, -9.0], [5.0, -2.0]])
    assert not rasterize_polygon(far, height, width).any()
    assert not rasterize_polygon(far + np.array([0.0, 40.0]), height, width).any()


def test_rasterize_refuses_points_that_are_not_2d():
    """3-D points were reshaped into a different 2-D polygon without a word."""
    square = np.array([[1.0, 1.0, 0.0], [4.0, 1.0, 0.0], [4.0, 4.0, 0.0], [1.0, 4.0, 0.0]])
    with pytest.raises(
        InputError,
        match=r"^rasterize_polygon: vertices must be \[K, 2\] \(x, y\) pixel coordinates, got "
        r"shape \[4, 3\]$",
    ):
        rasterize_polygon(square, 6, 6)
    with pytest.raises(InputError, match=r"got shape \[8\]$"):
        rasterize_polygon(square[:, :2].ravel(), 6, 6)
    assert not rasterize_polygon(square[:2, :2], 6, 6).any()  # fewer than 3 vertices: nothing
