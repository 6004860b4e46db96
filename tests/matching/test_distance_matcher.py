import math

import numpy as np
import pytest

from carto_cli.core import transform
from carto_cli.grid.distance_map import DistanceMap
from carto_cli.matching.distance_matcher import evaluate, match, match_multires
from carto_cli.sim import Lidar, World, loop_building, loop_trajectory, simulate

RES = 0.05


# Each scenario inserts a simulated building scan by scan: minutes in pure Python. The field itself is checked without
# the JIT in tests/grid/test_distance_map.py.
pytestmark = pytest.mark.slow_without_jit

def _scenario(shift: float):
    """The loop building (moved by ``shift`` m in x and y), noise-free scans; a map from the first scans at their
    true poses, and the (pose, points) of later ones."""
    base = loop_building()
    world = World(base.segments + shift, route=base.route + shift, closed=base.closed, name=base.name)
    sim = simulate(world, loop_trajectory(world), duration=20.0,
                   lidar=Lidar(beams=720, fov=2 * math.pi, noise=0.0, dropout=0.0), scan_rate=2.0, odom_rate=10.0,
                   imu_rate=0.0)
    angles = sim.lidar.angles()
    scans = []
    for pose, ranges in zip(sim.laser_poses(sim.scan_times), sim.scan_ranges()):
        ok = np.isfinite(ranges)
        pts = ranges[ok, None] * np.stack([np.cos(angles[ok]), np.sin(angles[ok])], axis=1)
        scans.append((pose, pts))
    dm = DistanceMap(resolution=RES, max_distance=0.5)
    coarse = DistanceMap(resolution=4 * RES, max_distance=2.0)
    for pose, pts in scans[:30]:
        for m in (dm, coarse):
            m.insert(pose[:2], transform.apply(pose, pts))
    return dm, coarse, scans


@pytest.fixture(scope="module")
def centred():
    # Walls on cell centres: what is left is the solver's own precision.
    return _scenario(RES / 2)


@pytest.fixture(scope="module")
def on_edges():
    # Walls on cell edges (the building's coordinates are multiples of the cell size): the map's obstacles sit
    # half a cell off the walls.
    return _scenario(0.0)


def _errors(result, truth):
    return float(np.hypot(*(result.pose[:2] - truth[:2]))), abs(math.degrees(transform.wrap_angle_scalar(
        result.pose[2] - truth[2])))


@pytest.mark.parametrize("offset, dtheta_deg", [(0.1, 3.0), (0.2, -5.0), (0.3, 5.0), (0.2, 10.0), (0.0, -10.0)])
def test_converges_from_offsets_to_sub_centimetre(centred, offset, dtheta_deg):
    dm, _, scans = centred
    worst = (0.0, 0.0)
    for k, (truth, pts) in enumerate(scans[2:30:3]):
        a = 2.4 * k
        start = truth + np.array([offset * math.cos(a), offset * math.sin(a), math.radians(dtheta_deg)])
        result = match(dm, pts, start)
        assert result.converged and result.cost < result.initial_cost
        assert result.iterations < 40
        worst = tuple(max(w, e) for w, e in zip(worst, _errors(result, truth)))
    assert worst[0] < 0.01 and worst[1] < 0.1, worst


def test_cell_edge_walls_bias_less_than_half_a_cell(on_edges):
    dm, _, scans = on_edges
    for truth, pts in scans[2:30:4]:
        result = match(dm, pts, truth + np.array([0.1, -0.1, 0.05]))
        dt, dth = _errors(result, truth)
        assert dt < 0.75 * RES and dth < 0.3


def test_unseen_scans_far_from_the_map_poses(centred):
    # Scans after the 30 that built the map: the robot went on round the loop, the map covers only part of view.
    dm, _, scans = centred
    truth, pts = scans[33]
    result = match(dm, pts, truth + np.array([0.15, 0.1, math.radians(4)]))
    dt, dth = _errors(result, truth)
    assert dt < 0.02 and dth < 0.2


def test_outliers_are_damped_by_the_loss(centred):
    dm, _, scans = centred
    truth, pts = scans[10]
    rng = np.random.default_rng(3)
    clutter = rng.uniform(-3, 3, (pts.shape[0] // 4, 2))  # a quarter as many returns from things not in the map
    result = match(dm, np.concatenate([pts, clutter]), truth + np.array([0.15, -0.15, math.radians(5)]))
    dt, dth = _errors(result, truth)
    assert dt < 0.015 and dth < 0.15


def test_coarse_map_first_widens_the_basin(centred):
    dm, coarse, scans = centred
    truth, pts = scans[12]
    start = truth + np.array([0.45, -0.4, math.radians(12)])
    result = match_multires([coarse, dm], pts, start)
    dt, dth = _errors(result, truth)
    assert dt < 0.01 and dth < 0.1


def test_gradient_and_information(centred):
    dm, _, scans = centred
    truth, pts = scans[8]
    pose = truth + np.array([0.013, -0.021, 0.011])
    kwargs = dict(prior_pose=truth, translation_weight=3.0, rotation_weight=2.0)
    _, jtj, jtr = evaluate(dm, pts, pose, **kwargs)
    h = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        fd = (evaluate(dm, pts, pose + d, **kwargs)[0] - evaluate(dm, pts, pose - d, **kwargs)[0]) / (2 * h)
        assert jtr[k] == pytest.approx(fd, rel=1e-3, abs=1e-6)
    np.testing.assert_allclose(jtj, jtj.T)
    result = match(dm, pts, truth)
    assert np.all(np.linalg.eigvalsh(result.information) > 0)
    np.testing.assert_allclose(result.covariance @ result.information, np.eye(3), atol=1e-8)
    assert result.rms < RES


def test_prior_alone_and_empty_scan():
    dm = DistanceMap(RES, 0.5)
    result = match(dm, np.empty((0, 2)), (1.0, 2.0, 0.3), prior_pose=(1.5, 1.0, 0.1), translation_weight=1.0,
                   rotation_weight=1.0)
    np.testing.assert_allclose(result.pose, [1.5, 1.0, 0.1], atol=1e-6)
    flat = match(dm, np.ones((5, 2)), (1.0, 2.0, 0.3))  # nothing in the map: no gradient, nothing moves
    np.testing.assert_allclose(flat.pose, [1.0, 2.0, 0.3])
