"""gmapping.loops: a revisit that came back off is pulled onto the first pass; nothing moves without one (nor\nalong one pass); a search that ends on its window's edge is followed, not taken for a peak."""
import math

import numpy as np
import pytest

from carto_cli.core import transform
from carto_cli.gmapping import loops
from carto_cli.gmapping.loops import CHUNK, close_loops, follow_to_peak
from carto_cli.gmapping.refine import map_of
from carto_cli.matching import correlative
from carto_cli.sensor.range_filter import RangeData
from carto_cli.sim import loop_building
from carto_cli.sim.lidar import cast
from tests.gmapping.test_refine import _error, _scans, _world


def _laps(n, laps):
    """``laps`` times round the room's pillars, ``n`` poses a lap."""
    t = np.linspace(0.0, 2.0 * math.pi * laps, n * laps, endpoint=False)
    return np.column_stack([4.0 + 2.5 * np.cos(t), 3.0 + 1.5 * np.sin(t), transform.wrap_angle(t + math.pi / 2)])


def test_a_drifted_second_lap_is_pulled_onto_the_first():
    world = _world()
    n = 40
    truth = _laps(n, 2)
    scans = _scans(world, truth)
    # The filter's trajectory: the first lap right, the second drifting away to 0.25 m and 1.5 degrees.
    drift = np.zeros_like(truth)
    ramp = np.linspace(0.0, 1.0, n)
    drift[n:] = np.column_stack([0.25 * ramp, -0.15 * ramp, math.radians(1.5) * ramp])
    drifted = truth + drift

    out = close_loops(drifted, scans, resolution=0.05, jobs=2)

    assert out.accepted > 0
    assert _error(out.poses, truth) < 0.5 * _error(drifted, truth)
    # The matches ran on two threads; one thread gives the very same graph and poses.
    alone = close_loops(drifted, scans, resolution=0.05, jobs=1)
    assert (alone.accepted, alone.candidates) == (out.accepted, out.candidates)
    assert np.array_equal(alone.poses, out.poses)


def test_without_a_revisit_nothing_moves():
    world = _world()
    n = 3 * CHUNK
    t = np.linspace(0.0, 1.2 * math.pi, n)  # a little over half a lap: no place is passed twice
    poses = np.column_stack([4.0 + 2.5 * np.cos(t), 3.0 + 1.5 * np.sin(t), t + math.pi / 2])
    scans = _scans(world, poses)
    jitter = poses + np.random.default_rng(1).normal(0.0, 0.01, poses.shape)

    out = close_loops(jitter, scans, resolution=0.05)

    assert out.accepted == 0
    assert np.array_equal(out.poses, jitter)


def test_too_few_scans_for_three_chunks_are_returned_as_they_are():
    poses = np.zeros((2 * CHUNK, 3))
    out = close_loops(poses, _scans(_world(), poses + [4.0, 3.0, 0.0]), resolution=0.05)
    assert out.candidates == 0 and np.array_equal(out.poses, poses)


def _one_pass_down_a_corridor():
    """A dense pass (0.1 m steps) down 8 m of the simulated loop building's corridor, seen by a 270 degree
    laser with 1 cm range noise as the filter would have placed it (poses 1 cm off): (truth, poses, scans)."""
    world = loop_building()
    a, b = world.route[0], world.route[1]
    heading = math.atan2(b[1] - a[1], b[0] - a[0])
    s = np.linspace(0.0, 8.0, 80)
    truth = np.column_stack([a[0] + s * math.cos(heading), a[1] + s * math.sin(heading), np.full(s.size, heading)])
    angles = np.linspace(-0.75 * math.pi, 0.75 * math.pi, 270)
    rng = np.random.default_rng(2)
    scans = []
    for r in cast(truth, angles, world.segments, 30.0):
        r = r + rng.normal(0.0, 0.01, r.shape)
        ok = np.isfinite(r)
        scans.append(RangeData(np.zeros(2), np.column_stack([r[ok] * np.cos(angles[ok]), r[ok] * np.sin(angles[ok])]),
                               np.empty((0, 2))))
    poses = truth + np.random.default_rng(1).normal(0.0, 0.01, truth.shape) * [1.0, 1.0, 0.2]
    return truth, poses, scans


def test_the_next_metres_of_a_dense_pass_are_not_a_revisit():
    # Chunks of ten processed scans 0.1 m apart: two chunks on is a metre or two down the same corridor. Matched as
    # revisits, 88 "loop closures" moved these poses from 0.016 m to 0.23 m off.
    _, poses, scans = _one_pass_down_a_corridor()
    out = close_loops(poses, scans, resolution=0.05)
    assert out.accepted == 0 and out.candidates == 0
    assert np.array_equal(out.poses, poses)


def test_a_search_on_its_windows_edge_is_followed_to_the_peak_or_dropped():
    world = _world()
    truth = np.array([[2.0, 1.0, 0.3], [6.0, 2.0, 1.8], [4.0, 5.0, -2.0], [1.5, 4.5, 0.0], [4.0, 3.0, 1.0]]) + [0.025, 0.025, 0.0]
    scans = _scans(world, truth)
    chunk = map_of(truth[:4], scans[:4], 0.05, hit_probability=loops.HIT_PROBABILITY,
                   miss_probability=loops.MISS_PROBABILITY)
    points, pose = scans[4].returns, truth[4]
    # 0.7 m off: beyond one search's reach, within the largest correction
    start = pose + [0.0, 0.7, 0.0]
    one = correlative.match(chunk, points, start, linear_search_window=loops.WINDOW_M,
                            angular_search_window=loops.WINDOW_RAD).pose
    assert abs(one[1] - start[1]) == pytest.approx(loops.WINDOW_M)  # the best of one search: on its edge
    found = follow_to_peak(chunk, points, start)
    assert found is not None and np.hypot(*(found[:2] - pose[:2])) < 0.05
    # 1.4 m off: the slope leads beyond the largest correction; no match rather than the edge's pose
    assert follow_to_peak(chunk, points, pose + [1.0, 1.0, 0.0]) is None
