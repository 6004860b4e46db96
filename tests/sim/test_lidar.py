"""The ray caster against a plain-Python reference, and the noise model."""
from __future__ import annotations

import math

import numpy as np
import pytest

from carto_cli.sim.lidar import Lidar, cast
from carto_cli.sim.world import room


def reference_range(ox, oy, angle, segments, max_range=math.inf):
    """Nearest hit by solving o + t d = a + u (b - a) as a 2x2 linear system, one segment at a time."""
    d = np.array([math.cos(angle), math.sin(angle)])
    best = math.inf
    for x1, y1, x2, y2 in segments:
        e = np.array([x2 - x1, y2 - y1])
        m = np.column_stack([d, -e])
        if abs(np.linalg.det(m)) < 1e-12:
            continue
        t, u = np.linalg.solve(m, np.array([x1 - ox, y1 - oy]))
        if t >= 0 and 0 <= u <= 1:
            best = min(best, t)
    return best if best <= max_range else math.inf


def test_matches_reference_on_random_segments_and_rays():
    rng = np.random.default_rng(1)
    segs = np.hstack([rng.uniform(-10, 10, (30, 2)), rng.uniform(-10, 10, (30, 2))])
    poses = np.column_stack([rng.uniform(-8, 8, (12, 2)), rng.uniform(-math.pi, math.pi, 12)])
    angles = rng.uniform(-math.pi, math.pi, 25)
    got = cast(poses, angles, segs, max_range=12.0)
    assert got.shape == (12, 25)
    want = np.array([[reference_range(x, y, yaw + a, segs, 12.0) for a in angles] for x, y, yaw in poses])
    assert (np.isinf(got) == np.isinf(want)).all()
    assert np.isinf(want).any() and np.isfinite(want).any()
    fin = np.isfinite(want)
    np.testing.assert_allclose(got[fin], want[fin], rtol=1e-9, atol=1e-9)


def test_known_ranges_in_a_room():
    w = room(8, 6)
    angles = np.array([0.0, math.pi / 2, math.pi, -math.pi / 2, 0.3, math.atan2(3, 4)])
    r = cast(np.array([4.0, 3.0, 0.0]), angles, w.segments)
    np.testing.assert_allclose(r, [4, 3, 4, 3, 4 / math.cos(0.3), 5.0], rtol=1e-12)
    # the sensor's yaw turns the fan
    r = cast(np.array([2.0, 3.0, math.pi / 2]), np.array([0.0, -math.pi / 2]), w.segments)
    np.testing.assert_allclose(r, [3.0, 6.0])


def test_beyond_max_range_is_inf():
    w = room(8, 6)
    r = cast(np.array([4.0, 3.0, 0.0]), np.array([0.0, math.pi / 2]), w.segments, max_range=3.5)
    assert math.isinf(r[0]) and r[1] == pytest.approx(3.0)
    assert math.isinf(cast(np.array([0.0, 0.0, 0.0]), np.array([0.0]), np.zeros((0, 4)))[0])


def test_beam_layout():
    fan = Lidar(beams=360, fov=1.5 * math.pi)
    a = fan.angles()
    assert a[0] == pytest.approx(-0.75 * math.pi) and a[-1] == pytest.approx(0.75 * math.pi)
    full = Lidar(beams=360, fov=2 * math.pi)
    a = full.angles()
    assert a[0] == pytest.approx(-math.pi) and a[-1] == pytest.approx(math.pi - 2 * math.pi / 360)


def test_noise_dropouts_and_limits():
    w = room(8, 6)
    pose = np.array([[4.0, 3.0, 0.0]])
    lidar = Lidar(beams=720, fov=2 * math.pi, max_range=30.0, noise=0.02, dropout=0.05)
    true = cast(pose, lidar.angles(), w.segments)[0]
    rng = np.random.default_rng(3)
    scans = np.vstack([lidar.measure(pose, w.segments, rng) for _ in range(40)])
    assert scans.dtype == np.float32
    dropped = np.isinf(scans)
    assert dropped.mean() == pytest.approx(0.05, abs=0.01)
    err = (scans - true)[~dropped]
    assert abs(err.mean()) < 0.002 and err.std() == pytest.approx(0.02, rel=0.05)

    nan_drops = Lidar(beams=720, fov=2 * math.pi, noise=0.0, dropout=0.5, dropout_value=math.nan)
    s = nan_drops.measure(pose, w.segments, np.random.default_rng(0))[0]
    assert np.isnan(s).mean() == pytest.approx(0.5, abs=0.08)
    np.testing.assert_allclose(s[~np.isnan(s)], true[~np.isnan(s)], rtol=1e-6)

    short = Lidar(beams=4, fov=2 * math.pi, max_range=3.5, min_range=0.05, noise=0.0, dropout=0.0)
    s = short.measure(pose, w.segments, rng)[0]  # beams at -pi, -pi/2, 0, pi/2
    assert np.isinf(s[0]) and s[1] == pytest.approx(3.0) and np.isinf(s[2]) and s[3] == pytest.approx(3.0)
    close = short.measure(np.array([[0.01, 3.0, math.pi]]), w.segments, rng)[0]
    assert close[2] == -np.inf  # facing the wall 1 cm away: too close


def test_same_generator_state_same_scan():
    w = room(8, 6)
    lidar = Lidar()
    pose = np.array([[2.0, 2.0, 0.5]])
    a = lidar.measure(pose, w.segments, np.random.default_rng(7))
    b = lidar.measure(pose, w.segments, np.random.default_rng(7))
    np.testing.assert_array_equal(a, b)
