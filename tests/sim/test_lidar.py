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


# ------------------------------------------------------------------ partly transparent segments (issue 43)

MASK = 2**64 - 1


def reference_uniform(key, p, b, s):
    """splitmix64 of (key, scan, beam, segment), in Python integers."""
    z = key ^ ((p * 0x9E3779B97F4A7C15) & MASK)
    z = z ^ ((b * 0xC2B2AE3D27D4EB4F) & MASK) ^ ((s * 0x165667B19E3779F9) & MASK)
    z = (z + 0x9E3779B97F4A7C15) & MASK
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK
    z ^= z >> 31
    return (z >> 11) / 2.0**53


def reference_partial_range(p, b, ox, oy, angle, segments, material, key, max_range=math.inf):
    """Every crossing of the ray, nearest first; the first whose segment returns it (within its incidence
    and reach, and its draw below its opacity) is the range."""
    d = np.array([math.cos(angle), math.sin(angle)])
    crossings = []
    for s, (x1, y1, x2, y2) in enumerate(segments):
        e = np.array([x2 - x1, y2 - y1])
        m = np.column_stack([d, -e])
        if abs(np.linalg.det(m)) < 1e-12:
            continue
        t, u = np.linalg.solve(m, np.array([x1 - ox, y1 - oy]))
        if t >= 0 and 0 <= u <= 1:
            crossings.append((t, s, abs(d[0] * e[1] - d[1] * e[0]) / np.hypot(*e)))
    for t, s, cos_incidence in sorted(crossings):
        opacity, min_cos, reach = material[s]
        if t <= reach and cos_incidence >= min_cos and (opacity >= 1 or reference_uniform(key, p, b, s) < opacity):
            return t if t <= max_range else math.inf
    return math.inf


def test_partial_segments_match_reference():
    rng = np.random.default_rng(5)
    segs = np.hstack([rng.uniform(-10, 10, (40, 2)), rng.uniform(-10, 10, (40, 2))])
    material = np.column_stack([rng.choice([1.0, 0.3, 0.7], 40), rng.choice([0.0, 0.0, math.cos(math.radians(30))], 40),
                                rng.choice([math.inf, math.inf, 6.0], 40)])
    poses = np.column_stack([rng.uniform(-8, 8, (10, 2)), rng.uniform(-math.pi, math.pi, 10)])
    angles = rng.uniform(-math.pi, math.pi, 40)
    key = 123456789
    got = cast(poses, angles, segs, max_range=15.0, material=material, key=key)
    want = np.array([[reference_partial_range(p, b, x, y, yaw + a, segs, material, key, 15.0)
                      for b, a in enumerate(angles)] for p, (x, y, yaw) in enumerate(poses)])
    assert (np.isinf(got) == np.isinf(want)).all()
    fin = np.isfinite(want)
    np.testing.assert_allclose(got[fin], want[fin], rtol=1e-9, atol=1e-9)
    # Some rays passed a segment they crossed: the opaque cast is nearer there.
    opaque = cast(poses, angles, segs, max_range=15.0)
    assert (np.nan_to_num(got, posinf=99) > np.nan_to_num(opaque, posinf=99) + 1e-9).sum() > 10


def test_glass_returns_its_share_and_passes_the_rest_to_the_wall_behind():
    glass = np.array([[2.0, -50.0, 2.0, 50.0]])
    wall = np.array([[5.0, -50.0, 5.0, 50.0]])
    angles = np.linspace(-0.3, 0.3, 4001)  # within 17 degrees of the normal
    material = np.array([[0.3, 0.0, math.inf], [1.0, 0.0, math.inf]])
    r = cast(np.zeros(3), angles, np.vstack([glass, wall]), material=material, key=7)
    on_glass = np.isclose(r * np.cos(angles), 2.0)
    assert on_glass.mean() == pytest.approx(0.3, abs=0.03)
    np.testing.assert_allclose((r * np.cos(angles))[~on_glass], 5.0)
    # Returned only within 10 degrees of its normal: beyond, every ray reaches the wall.
    material[0, 1] = math.cos(math.radians(10))
    r = cast(np.zeros(3), angles, np.vstack([glass, wall]), material=material, key=7)
    x = r * np.cos(angles)
    steep = np.abs(angles) > math.radians(10) + 1e-6
    assert np.allclose(x[steep], 5.0) and np.isclose(x[~steep], 2.0).mean() == pytest.approx(0.3, abs=0.05)


def test_a_hedge_is_seen_up_close_and_passed_over_from_afar():
    hedge = np.array([[0.0, -0.5, 0.0, 0.5]])
    behind = np.array([[3.0, -50.0, 3.0, 50.0]])
    material = np.array([[1.0, 0.0, 6.0], [1.0, 0.0, math.inf]])
    segs = np.vstack([hedge, behind])
    near = cast(np.array([-4.0, 0.0, 0.0]), np.zeros(1), segs, material=material)
    far = cast(np.array([-8.0, 0.0, 0.0]), np.zeros(1), segs, material=material)
    assert near[0] == pytest.approx(4.0) and far[0] == pytest.approx(11.0)


def test_without_materials_measure_draws_as_it_always_did():
    """Worlds of opaque walls only keep their recordings: the noise and dropouts come from the generator
    exactly as before partly transparent segments existed."""
    w = room(8, 6)
    lidar = Lidar(beams=90, fov=2 * math.pi, noise=0.02, dropout=0.1)
    poses = np.array([[4.0, 3.0, 0.1], [2.0, 2.0, -1.0]])
    got = lidar.measure(poses, w.segments, np.random.default_rng(11))
    rng = np.random.default_rng(11)
    true = cast(poses, lidar.angles(), w.segments, lidar.max_range)
    noisy = true + lidar.noise * rng.standard_normal(true.shape)
    noisy[noisy > lidar.max_range] = np.inf
    noisy[noisy < lidar.min_range] = -np.inf
    noisy[rng.random(true.shape) < lidar.dropout] = lidar.dropout_value
    np.testing.assert_array_equal(got, noisy.astype(np.float32))
    # An all-opaque material gives the same ranges (it only draws a key first).
    opaque = np.tile([1.0, 0.0, math.inf], (len(w.segments), 1))
    np.testing.assert_array_equal(cast(poses, lidar.angles(), w.segments, lidar.max_range, material=opaque), true)
