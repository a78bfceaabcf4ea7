"""The Z-order the numba rasterizer and the KNN queries visit points in (thgs._spatial)."""

from __future__ import annotations

import numpy as np
import pytest

from thgs._spatial import spatial_order


def test_cube_corners_follow_the_z_curve():
    """Corner (x, y, z) of a box has the code x + 2y + 4z: x varies fastest."""
    corners = np.array([[x, y, z] for z in (0, 1) for y in (0, 1) for x in (0, 1)], dtype=float)
    shuffled = np.random.default_rng(0).permutation(8)
    order = spatial_order(corners[shuffled] * 3.0 - 1.0)
    np.testing.assert_array_equal(shuffled[order], np.arange(8))


def test_a_finer_grid_visits_each_octant_whole_before_the_next():
    """On a 4×4×4 grid the first 8 points are the lowest octant's, the next 8 the +x octant's."""
    grid = np.stack(np.meshgrid(*[np.arange(4.0)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    ordered = grid[spatial_order(grid)]
    assert (ordered[:8] < 2).all()
    assert (ordered[8:16, 0] >= 2).all() and (ordered[8:16, 1:] < 2).all()
    assert len({tuple(p) for p in ordered}) == 64


def test_ties_keep_index_order_and_non_finite_points_go_to_the_lower_corner():
    points = np.array(
        [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [np.nan, 5.0, 0.0], [0.5, 0.5, 0.5]]
    )
    np.testing.assert_array_equal(spatial_order(points), [1, 3, 4, 0, 2])


def test_degenerate_and_bad_inputs():
    np.testing.assert_array_equal(spatial_order(np.zeros((0, 3))), np.zeros(0, dtype=np.int64))
    np.testing.assert_array_equal(spatial_order(np.ones((3, 3))), [0, 1, 2])
    flat = np.array([[2.0, 0.0, 7.0], [1.0, 0.0, 7.0]])  # one axis with no extent
    np.testing.assert_array_equal(spatial_order(flat), [1, 0])
    with pytest.raises(ValueError, match=r"points must be \[N, 3\]"):
        spatial_order(np.zeros((4, 2)))
