"""Simulated recordings: order, counts, determinism, drift, ground truth, IMU."""
from __future__ import annotations

import math

import numpy as np
import pytest

from carto_cli.core.errors import TopicError
from carto_cli.core.records import Imu, Odometry, Scan
from carto_cli.io.recording import Recording
from carto_cli.sim import (
    ImuModel,
    Lidar,
    OdometryModel,
    SimulatedRecording,
    loop_building,
    loop_trajectory,
    room,
    simulate,
)
from carto_cli.sim.odometry import relative_motion
from carto_cli.sim.recording import compose
from carto_cli.sim.trajectory import Trajectory, wrap_angle


@pytest.fixture(scope="module")
def building():
    return loop_building()


@pytest.fixture(scope="module")
def lap(building):
    return loop_trajectory(building)


@pytest.fixture(scope="module")
def short(building, lap):
    return simulate(building, lap, duration=20.0, seed=4)


def test_time_order_and_counts(short):
    recs = list(short.records())
    assert sum(isinstance(r, Scan) for r in recs) == 200
    assert sum(isinstance(r, Odometry) for r in recs) == 1000
    assert sum(isinstance(r, Imu) for r in recs) == 2000
    key = {Imu: 0, Odometry: 1, Scan: 2}
    order = [(r.time, key[type(r)]) for r in recs]
    assert order == sorted(order)  # and at equal times: IMU, then odometry, then the scan
    assert recs[0].time == 1000.0 and isinstance(recs[0], Imu)
    scans = [r for r in recs if isinstance(r, Scan)]
    assert {(s.topic, s.frame, s.num_beams) for s in scans} == {("/scan", "laser", 360)}
    np.testing.assert_allclose(np.diff([s.time for s in scans]), 0.1)
    odo = [r for r in recs if isinstance(r, Odometry)]
    assert {(o.topic, o.frame, o.child_frame) for o in odo} == {("/odom", "odom", "base_link")}
    assert {(i.topic, i.frame) for i in recs if isinstance(i, Imu)} == {("/imu", "imu")}


def test_recording_adapter(short):
    with short.recording() as rec:
        assert isinstance(rec, Recording) and isinstance(rec, SimulatedRecording) and rec.format == "sim"
        assert {(t.name, t.msgtype, t.count, t.kind) for t in rec.topics()} == {
            ("/scan", "sensor_msgs/msg/LaserScan", 200, "scan"),
            ("/odom", "nav_msgs/msg/Odometry", 1000, "odometry"),
            ("/imu", "sensor_msgs/msg/Imu", 2000, "imu"),
        }
        assert [t.child for t in rec.static_transforms()] == ["laser", "imu"]
        assert {type(r) for r in rec.records(["/odom"])} == {Odometry}
        with pytest.raises(TopicError):
            list(rec.records(["/nope"]))


def test_sensors_can_be_turned_off(building, lap):
    sim = simulate(building, lap, duration=5.0, imu_rate=0, odom_rate=0)
    assert [t.name for t in sim.recording().topics()] == ["/scan"]


def same(a, b):
    return a.same_as(b) if isinstance(a, (Scan, Imu)) else a == b


def test_deterministic_for_a_seed(building, lap):
    a = list(simulate(building, lap, duration=3.0, seed=11).records())
    b = list(simulate(building, lap, duration=3.0, seed=11).records())
    c = list(simulate(building, lap, duration=3.0, seed=12).records())
    assert len(a) == len(b) and all(same(x, y) for x, y in zip(a, b))
    assert not all(same(x, y) for x, y in zip(a, c))


def test_reading_again_or_in_part_gives_the_same_data(short):
    all_scans = [r for r in short.records() if isinstance(r, Scan)]
    only = list(short.records(["/scan"]))
    again = list(short.records(["/scan"]))
    assert all(x.same_as(y) and y.same_as(z) for x, y, z in zip(all_scans, only, again))
    only[0].ranges[0] = -1.0  # records never share buffers
    assert next(short.records(["/scan"])).ranges[0] != -1.0


def test_ground_truth_is_exact(building, lap):
    # Scan points placed with the ground truth and the laser mount land on the walls.
    mount = (0.15, -0.05, 0.1)
    sim = simulate(building, lap, duration=60.0, lidar=Lidar(noise=0.0, dropout=0.0), laser_pose=mount, seed=2)
    gt = sim.ground_truth
    assert gt.shape == (600, 4)
    np.testing.assert_allclose(gt[:, 0], [s.time for s in sim.records(["/scan"])])
    np.testing.assert_allclose(gt[:, 1:], lap.poses(gt[:, 0] - 1000.0))
    (tf_laser, _) = sim.static_transforms
    np.testing.assert_allclose(tf_laser.pose2d(), mount, atol=1e-12)
    for (_t, x, y, yaw), scan in list(zip(gt, sim.records(["/scan"])))[::50]:
        lx, ly, lyaw = compose(np.array([[x, y, yaw]]), mount)[0]
        ok = np.isfinite(scan.ranges)
        r, a = scan.ranges[ok].astype(float), scan.angles[ok].astype(float) + lyaw
        pts = np.column_stack([lx + r * np.cos(a), ly + r * np.sin(a)])
        assert building.distance_to_walls(pts).max() < 1e-4


def test_perfect_odometry_is_the_trajectory_seen_from_its_start(building, lap):
    sim = simulate(building, lap, duration=60.0, odom_noise=OdometryModel.perfect())
    odo = sim.odometry
    truth = lap.poses(odo[:, 0] - 1000.0)
    # odometry starts at zero; express the truth in the frame of its first pose
    x0, y0, th0 = truth[0]
    c, s = math.cos(th0), math.sin(th0)
    rel = np.column_stack([c * (truth[:, 0] - x0) + s * (truth[:, 1] - y0),
                           -s * (truth[:, 0] - x0) + c * (truth[:, 1] - y0), wrap_angle(truth[:, 2] - th0)])
    np.testing.assert_allclose(odo[:, 1:3], rel[:, :2], atol=1e-9)
    np.testing.assert_allclose(wrap_angle(odo[:, 3] - rel[:, 2]), 0.0, atol=1e-9)
    v = lap.velocities(odo[1:, 0] - 1000.0 - 0.01)
    np.testing.assert_allclose(odo[1:, 4], v[:, 0], atol=0.02)


def test_odometry_drift_grows_with_distance(building, lap):
    sim = simulate(building, lap, odom_rate=50.0, scan_rate=1.0, imu_rate=0.0, seed=5)
    odo = sim.odometry
    truth = lap.poses(odo[:, 0] - 1000.0)
    dist = lap.travelled(odo[:, 0] - 1000.0)
    # relative motion over 5 m windows: error grows with the distance driven
    def window_error(metres):
        errs = []
        for i in range(0, len(odo) - 1, 200):
            j = int(np.searchsorted(dist, dist[i] + metres))
            if j >= len(odo):
                break
            t_rel = relative_motion(truth[[i, j]])[0]
            o_rel = relative_motion(odo[[i, j], 1:4])[0]
            errs.append(np.hypot(*(t_rel[:2] - o_rel[:2])))
        return np.mean(errs)
    e1, e5, e20 = window_error(1.0), window_error(5.0), window_error(20.0)
    assert e1 < e5 < e20
    assert 0.01 < e5 / 5.0 < 0.2  # a few per cent of the distance, as the model says
    # over the whole lap the odometry no longer closes the loop, the ground truth does
    end_truth = np.hypot(*(truth[-1, :2] - truth[0, :2]))
    assert end_truth < 0.1
    assert np.hypot(*odo[-1, 1:3]) > 0.5


def test_imu_yaw_rate_matches_the_trajectory(building, lap):
    bias, sigma = 0.003, 0.004
    sim = simulate(building, lap, duration=120.0, imu_noise=ImuModel(gyro_bias=bias, gyro_noise=sigma), seed=9)
    t = sim.imu_times - 1000.0
    h = 1e-4
    rate = (lap.yaw_unwrapped(t + h) - lap.yaw_unwrapped(t - h)) / (2 * h)
    err = sim.imu_gyro[:, 2] - rate
    assert err.mean() == pytest.approx(bias, abs=4 * sigma / math.sqrt(len(t)))
    assert err.std() == pytest.approx(sigma, rel=0.1)
    assert np.abs(rate).max() > 0.5  # the lap does turn
    assert np.abs(sim.imu_gyro[:, :2]).max() == 0.0
    np.testing.assert_allclose(sim.imu_accel[:, 2].mean(), 9.80665, atol=0.01)
    # a gyro without noise gives the trajectory's yaw rate exactly
    perfect = simulate(building, lap, duration=30.0, imu_noise=ImuModel.perfect())
    t = perfect.imu_times - 1000.0
    np.testing.assert_allclose(perfect.imu_gyro[:, 2], lap.velocities(t)[:, 1], atol=1e-12)


def test_a_few_thousand_scans(building):
    tr = loop_trajectory(building, laps=2)
    sim = simulate(building, tr, imu_rate=0)
    n = sum(1 for _ in sim.records(["/scan"]))
    assert n == len(sim.ground_truth) > 2500


def test_room_and_a_full_circle_laser():
    w = room(6, 4)
    tr = Trajectory.follow([(1, 1), (5, 1), (5, 3)])
    sim = simulate(w, tr, lidar=Lidar(fov=2 * math.pi, beams=720, max_range=10.0, dropout=0.0, noise=0.0))
    scan = next(sim.records(["/scan"]))
    assert scan.num_beams == 720 and np.isfinite(scan.ranges).all()
    assert scan.ranges.min() == pytest.approx(1.0, abs=1e-4)  # 1 m from two walls at the start
