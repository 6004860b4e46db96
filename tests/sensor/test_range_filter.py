import math

import numpy as np
import pytest

from carto_cli.core import transform as tf
from carto_cli.core.records import Scan
from carto_cli.sensor.range_filter import RangeData, accumulate, crop_points, crop_polar, crop_scan


def test_crop_polar_sorts_returns_misses_and_drops_invalid():
    angles = np.array([0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, -1.0], dtype=np.float32)
    ranges = np.array([1.0, np.nan, np.inf, -np.inf, 0.1, 40.0, 0.0, 30.0], dtype=np.float32)
    rd = crop_polar(ranges, angles, min_range=0.2, max_range=30.0, missing_data_ray_length=5.0)
    a = angles.astype(np.float64)
    np.testing.assert_allclose(rd.returns, [[1.0, 0.0], [30 * math.cos(a[7]), 30 * math.sin(a[7])]], atol=1e-12)
    # +inf and beyond max_range become misses at missing_data_ray_length along the beam.
    np.testing.assert_allclose(rd.misses, [[5 * math.cos(a[2]), 5 * math.sin(a[2])],
                                           [5 * math.cos(a[5]), 5 * math.sin(a[5])]], atol=1e-12)
    np.testing.assert_array_equal(rd.origin, [0.0, 0.0])


@pytest.mark.parametrize("mount", [None, (0.1, 0.0, 0.0)])
def test_crop_scan_keeps_to_the_scans_own_limits(mount):
    """REP 117: a reading above the LaserScan's range_max is no return (a miss), one below its range_min is not a
    reading; the options' wider limits do not make either a wall."""
    angles = np.array([0.0, 0.5, 1.0, 1.5, 2.0], dtype=np.float32)
    ranges = np.array([1.0, 5.5, 0.05, 4.0, np.inf], dtype=np.float32)
    scan = Scan(0.0, ranges, angles, "laser", range_min=0.1, range_max=5.0)
    rd = crop_scan(scan, mount=mount, min_range=0.0, max_range=30.0, missing_data_ray_length=2.0)
    ox = rd.origin[0]
    np.testing.assert_allclose(rd.returns - rd.origin, [[1.0, 0.0], [4 * math.cos(1.5), 4 * math.sin(1.5)]],
                               atol=1e-6)
    np.testing.assert_allclose(rd.misses - [ox, 0.0], [[2 * math.cos(0.5), 2 * math.sin(0.5)],
                                                       [2 * math.cos(2.0), 2 * math.sin(2.0)]], atol=1e-6)
    assert scan.ranges[1] == np.float32(5.5)  # the record itself is left as recorded
    # without limits of its own (a CARMEN log's range_min 0, no range_max) the options decide
    free = Scan(0.0, ranges, angles, "laser")
    assert len(crop_scan(free, mount=mount, min_range=0.0, max_range=30.0).returns) == 4


def test_crop_points_measures_from_origin():
    origin = np.array([1.0, 2.0])
    pts = np.array([[1.0, 2.05], [4.0, 2.0], [1.0, 12.0], [np.inf, 0.0], [np.nan, 1.0]])
    rd = crop_points(pts, origin, min_range=0.1, max_range=5.0, missing_data_ray_length=2.0)
    np.testing.assert_allclose(rd.returns, [[4.0, 2.0]])
    np.testing.assert_allclose(rd.misses, [[1.0, 4.0]])


def test_accumulate_expresses_everything_in_the_last_frame():
    a = RangeData(np.zeros(2), np.array([[1.0, 0.0]]), np.array([[0.0, 5.0]]))
    b = RangeData(np.zeros(2), np.array([[2.0, 0.0], [0.0, 1.0]]), np.empty((0, 2)))
    pose_a = np.array([0.0, 0.0, 0.0])
    pose_b = np.array([1.0, 0.0, math.pi / 2])
    merged = accumulate([a, b], [pose_a, pose_b])
    # The first scan's hit at world (1, 0) is the second sensor's own position.
    np.testing.assert_allclose(merged.returns[0], [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(merged.returns[1:], b.returns, atol=1e-12)
    np.testing.assert_allclose(merged.misses, tf.apply(tf.inverse(pose_b), [[0.0, 5.0]]), atol=1e-12)
    np.testing.assert_allclose(merged.origin, [0.0, 0.0], atol=1e-12)
    world = accumulate([a, b], [pose_a, pose_b], frame=np.zeros(3))
    np.testing.assert_allclose(world.returns, [[1.0, 0.0], [1.0, 2.0], [0.0, 0.0]], atol=1e-12)
    np.testing.assert_allclose(world.origin, [1.0, 0.0], atol=1e-12)
    with pytest.raises(ValueError):
        accumulate([a], [pose_a, pose_b])


def test_crop_polar_with_mount_gives_body_frame_points():
    angles = np.linspace(-1.0, 1.0, 5)
    ranges = np.array([1.0, 2.0, 50.0, 3.0, 0.01])
    mount = (0.3, -0.1, 0.4)
    rd = crop_polar(ranges, angles, min_range=0.05, max_range=30.0, missing_data_ray_length=5.0, mount=mount)
    plain = crop_polar(ranges, angles, min_range=0.05, max_range=30.0, missing_data_ray_length=5.0)
    np.testing.assert_allclose(rd.returns, tf.apply(mount, plain.returns), atol=1e-12)
    np.testing.assert_allclose(rd.misses, tf.apply(mount, plain.misses), atol=1e-12)
    np.testing.assert_allclose(rd.origin, [0.3, -0.1])


def test_deskewing_puts_a_sweep_taken_while_turning_back_on_the_walls():
    """Each beam ray cast from the pose the robot had when it was measured; de-skewed, all lie on the walls."""
    from carto_cli.sim import room
    from carto_cli.sim.lidar import cast

    world = room(8.0, 6.0)
    n = 271
    angles = np.linspace(-0.75 * math.pi, 0.75 * math.pi, n)
    time_increment = 0.1 / n  # a 10 Hz scanner sweeping 270° of its 360°
    mount = np.array([0.2, 0.05, 0.1])
    start = np.array([4.0, 3.0, 0.3])
    ux, uy, w = 0.6, 0.1, 2.0  # body frame velocity, yaw rate: 11° turned during the sweep
    dt = np.arange(n) * time_increment
    # Cartographer's constant-velocity extrapolation: straight line in the local frame, constant turn rate.
    c, s = math.cos(start[2]), math.sin(start[2])
    body = np.column_stack([start[0] + (c * ux - s * uy) * dt, start[1] + (s * ux + c * uy) * dt, start[2] + w * dt])
    laser = tf.compose(body, mount)
    ranges = np.array([cast(laser[i], angles[i:i + 1], world.segments)[0] for i in range(n)])
    kwargs = dict(min_range=0.05, max_range=30.0, missing_data_ray_length=5.0, mount=mount)
    deskewed = crop_polar(ranges, angles, time_increment=time_increment, motion=(ux, uy, w), **kwargs)
    naive = crop_polar(ranges, angles, **kwargs)
    assert len(deskewed.returns) == n
    assert world.distance_to_walls(tf.apply(start, deskewed.returns)).max() < 1e-9
    assert world.distance_to_walls(tf.apply(start, naive.returns)).max() > 0.2  # what de-skewing removes
