"""gmapping.loops: a revisit that came back off is pulled onto the first pass; nothing moves without one."""
import math

import numpy as np

from carto_cli.core import transform
from carto_cli.gmapping.loops import CHUNK, close_loops
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
