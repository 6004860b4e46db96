"""gmapping.refine: scans put back where the map of all of them says they belong."""
import math

import numpy as np

from carto_cli.core import transform
from carto_cli.gmapping.refine import map_of, refine_poses
from carto_cli.sensor.range_filter import RangeData
from carto_cli.sim import room
from carto_cli.sim.lidar import cast
from carto_cli.sim.world import World, box, merge


def _scans(world, poses, beams=360):
    """Exact scans from ``poses`` (the sensor at the tracking frame's origin), as RangeData in that frame."""
    angles = np.linspace(-math.pi, math.pi, beams, endpoint=False)
    ranges = cast(poses, angles, world.segments, 15.0)
    out = []
    for r in ranges:
        ok = np.isfinite(r)
        pts = np.column_stack([r[ok] * np.cos(angles[ok]), r[ok] * np.sin(angles[ok])])
        out.append(RangeData(np.zeros(2), pts, np.empty((0, 2))))
    return out


def _world():
    """A room with two pillars: no direction in which a scan can slide along the walls unnoticed. Its walls run
    through the centres of 5 cm cells: on a cell boundary the endpoints fall on either side, and every scan
    would move by the same half cell to put them on a cell's centre."""
    r = room(8.0, 6.0)
    return World(merge(r.segments, box(2.5, 2.0, 0.6, 0.6), box(5.5, 4.0, 0.4, 0.8)) + 0.025)


def _error(poses, truth):
    """Mean position error of every pose relative to the first, against the truth."""
    rel = np.array([transform.relative(poses[0], p) for p in poses])
    rel_truth = np.array([transform.relative(truth[0], p) for p in truth])
    return float(np.mean(np.hypot(*(rel - rel_truth)[:, :2].T)))


def test_jittered_poses_move_back_towards_the_truth():
    rng = np.random.default_rng(0)
    world = _world()
    n = 40
    t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    truth = np.column_stack([4.0 + 2.5 * np.cos(t), 3.0 + 1.5 * np.sin(t), t + math.pi / 2])
    scans = _scans(world, truth)
    # What the filter leaves: every pose a few centimetres and about a degree off, independently.
    noisy = truth + np.column_stack([rng.normal(0, 0.03, n), rng.normal(0, 0.03, n), rng.normal(0, 0.015, n)])
    refined = refine_poses(noisy, scans, resolution=0.05, iterations=2, jobs=2)

    assert _error(refined, truth) < 0.5 * _error(noisy, truth)
    assert np.array_equal(refine_poses(noisy, scans, resolution=0.05, iterations=2, jobs=1), refined)
    assert np.array_equal(refine_poses(noisy, scans, resolution=0.05, iterations=0), noisy)


def test_exact_poses_stay_put():
    world = _world()
    truth = np.array([[2.0, 1.0, 0.3], [6.0, 2.0, 1.8], [4.0, 5.0, -2.0], [1.5, 4.5, 0.0]]) + [0.025, 0.025, 0.0]
    scans = _scans(world, truth)
    refined = refine_poses(truth, scans, resolution=0.05, iterations=2)
    assert np.max(np.hypot(*(refined - truth)[:, :2].T)) < 0.01
    assert np.max(np.abs(transform.wrap_angle(refined[:, 2] - truth[:, 2]))) < math.radians(0.5)


def test_the_map_holds_every_scan():
    world = _world()
    poses = np.array([[2.0, 1.0, 0.3], [6.0, 5.0, 1.8]])
    grid = map_of(poses, _scans(world, poses), 0.05)
    walls = np.array([[0.0, 3.0], [8.0, 3.0], [4.0, 0.0], [4.0, 6.0]])
    assert grid.contains(grid.cell_index(walls)).all()
    # Both ends of the room are known, whoever saw them.
    assert np.all(grid.is_known(grid.cell_index(np.array([[1.0, 1.0], [7.0, 5.0]]))))


def test_a_scan_left_decimetres_off_finds_its_place():
    """Beyond least squares' reach from where the filter left it: the correlative search before it finds it."""
    world = _world()
    n = 30
    t = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    truth = np.column_stack([4.0 + 2.5 * np.cos(t), 3.0 + 1.5 * np.sin(t), t + math.pi / 2]) + [0.025, 0.025, 0.0]
    scans = _scans(world, truth)
    off = truth.copy()
    off[7, :2] += (0.3, -0.25)
    refined = refine_poses(off, scans, resolution=0.05, iterations=2)
    assert np.hypot(*(refined[7, :2] - truth[7, :2])) < 0.03
