import math

import numpy as np

from carto_cli.sensor.voxel_filter import adaptive_voxel_filter, voxel_filter


def reference_voxel_filter(points, length):
    seen = set()
    kept = []
    for p in points:
        key = (math.floor(p[0] / length), math.floor(p[1] / length))
        if key not in seen:
            seen.add(key)
            kept.append(p)
    return np.array(kept).reshape(-1, 2)


def dense_scan(n=2000, seed=0):
    """A room-like outline sampled densely, with noise."""
    rng = np.random.default_rng(seed)
    a = rng.uniform(-math.pi, math.pi, n)
    r = 3.0 / np.maximum(np.abs(np.cos(a)), np.abs(np.sin(a))) + rng.normal(0, 0.01, n)
    return np.c_[r * np.cos(a), r * np.sin(a)]


def test_voxel_filter_keeps_first_point_per_voxel():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-2, 2, size=(3000, 2))
    for length in (0.05, 0.3, 1.0):
        np.testing.assert_array_equal(voxel_filter(pts, length), reference_voxel_filter(pts, length))
    assert voxel_filter(np.empty((0, 2)), 0.1).shape == (0, 2)


def test_adaptive_voxel_filter_sparse_input_returned_as_is():
    pts = dense_scan(150)
    np.testing.assert_array_equal(adaptive_voxel_filter(pts, min_num_points=200), pts)


def test_adaptive_voxel_filter_max_length_suffices():
    pts = dense_scan()
    out = adaptive_voxel_filter(pts, max_length=0.05, min_num_points=50)
    np.testing.assert_array_equal(out, voxel_filter(pts, 0.05))


def test_adaptive_voxel_filter_lands_in_bounds():
    pts = dense_scan()
    for min_num_points in (100, 200, 400):
        out = adaptive_voxel_filter(pts, max_length=0.5, min_num_points=min_num_points)
        assert min_num_points <= len(out) <= 1.1 * min_num_points


def test_adaptive_voxel_filter_drops_points_beyond_max_range():
    pts = dense_scan()
    out = adaptive_voxel_filter(pts, max_length=0.5, min_num_points=100, max_range=3.5)
    assert np.hypot(out[:, 0], out[:, 1]).max() <= 3.5
    near = pts[np.hypot(pts[:, 0], pts[:, 1]) <= 3.2]
    np.testing.assert_array_equal(adaptive_voxel_filter(pts, min_num_points=len(near) + 10, max_range=3.2), near)
