import math

import numpy as np
import pytest

from carto_cli.core import transform as tf
from carto_cli.core.records import Imu, Odometry
from carto_cli.mapping.extrapolator import PoseExtrapolator


def test_identity_before_any_pose_and_hold_with_one():
    e = PoseExtrapolator()
    np.testing.assert_array_equal(e.extrapolate(3.0), np.zeros(3))
    e.add_pose(1.0, (1.0, 2.0, 0.5))
    np.testing.assert_allclose(e.extrapolate(2.0), [1.0, 2.0, 0.5])


def test_constant_velocity_from_poses():
    e = PoseExtrapolator()
    for k in range(5):
        t = 0.1 * k
        e.add_pose(t, (0.5 * t, -0.2 * t, 0.3 * t))
    np.testing.assert_allclose(e.extrapolate(0.6), [0.3, -0.12, 0.18], atol=1e-12)
    assert e.last_pose_time == pytest.approx(0.4)


def test_odometry_velocity_rotated_by_estimated_heading():
    e = PoseExtrapolator()
    e.add_pose(0.0, (0.0, 0.0, 0.0))
    e.add_pose(1.0, (10.0, 10.0, math.pi / 2))  # poses alone would say 10 m/s diagonal
    # Odometry's frame is rotated against the map: only its body-frame motion (2 m/s forward) counts.
    for t in (0.9, 1.0, 1.1, 1.2):
        p = tf.compose((5.0, 5.0, -1.0), (2.0 * t, 0.0, 0.0))
        e.add_odometry(Odometry(time=t, x=p[0], y=p[1], yaw=p[2]))
    np.testing.assert_allclose(e.extrapolate(1.5), [10.0, 11.0, math.pi / 2], atol=1e-9)


def test_odometry_yaw_rate_turns_the_velocity():
    e = PoseExtrapolator()
    e.add_pose(1.0, (0.0, 0.0, 0.0))
    for t in (1.0, 1.1):
        e.add_odometry(Odometry(time=t, x=0.0, y=0.0, yaw=0.3 * t))  # turning on the spot at 0.3 rad/s
    np.testing.assert_allclose(e.extrapolate(2.0), [0.0, 0.0, 0.3], atol=1e-9)
    e.add_odometry(Odometry(time=1.2, x=0.0, y=0.0, yaw=0.36))
    e.add_odometry(Odometry(time=1.15, x=9.0, y=9.0, yaw=9.0))  # out of order: ignored
    np.testing.assert_allclose(e.extrapolate(2.0), [0.0, 0.0, 0.3], atol=1e-9)


def test_imu_yaw_rate_integrated():
    e = PoseExtrapolator(use_imu_data=True)
    e.add_pose(0.0, (0.0, 0.0, 0.0))
    e.add_pose(1.0, (1.0, 0.0, 0.0))
    for t, w in [(0.95, 0.0), (1.05, 1.0), (1.15, -2.0)]:
        e.add_imu(Imu(time=t, angular_velocity=np.array([0.0, 0.0, w]), linear_acceleration=np.zeros(3)))
    # 0.05 s at 0, 0.1 s at 1 rad/s, 0.05 s at -2 rad/s.
    pred = e.extrapolate(1.2)
    assert pred[2] == pytest.approx(0.1 - 0.1, abs=1e-12)
    assert e.extrapolate(1.1)[2] == pytest.approx(0.05, abs=1e-12)
    np.testing.assert_allclose(pred[:2], [1.2, 0.0], atol=1e-12)
    ignored = PoseExtrapolator(use_imu_data=False)
    ignored.add_pose(0.0, (0.0, 0.0, 0.0))
    ignored.add_imu(Imu(time=0.0, angular_velocity=np.array([0.0, 0.0, 5.0]), linear_acceleration=np.zeros(3)))
    assert ignored.extrapolate(1.0)[2] == 0.0


def test_body_motion_is_the_velocity_extrapolate_uses_seen_from_the_robot():
    e = PoseExtrapolator()
    assert e.body_motion(0.0) == (0.0, 0.0, 0.0)
    # Driving along +y while turning left at 0.5 rad/s, heading +y (pi/2).
    e.add_pose(1.0, (0.0, 0.0, math.pi / 2))
    e.add_pose(1.1, (0.0, 0.1, math.pi / 2 + 0.05))
    vx, vy, w = e.body_motion(1.1, 0.05)
    assert w == pytest.approx(0.5)
    # Local velocity (0, 1) seen from heading pi/2 + 0.05: mostly forward, a little to the right.
    assert vx == pytest.approx(math.cos(0.05)) and vy == pytest.approx(-math.sin(0.05))
    p0, p1 = e.extrapolate(1.1), e.extrapolate(1.2)
    c, s = math.cos(p0[2]), math.sin(p0[2])
    assert (p1[0] - p0[0]) / 0.1 == pytest.approx(c * vx - s * vy)
    assert (p1[1] - p0[1]) / 0.1 == pytest.approx(s * vx + c * vy)


def test_a_sweep_whose_odometry_is_in_moves_by_its_own_window():
    """A cloud logged once its sweep has turned: odometry through the sweep is known, and the sweep moves as odometry
    says over the sweep itself (here: standing until t = 1, then 1 m/s forward turning at 0.5 rad/s), not at the
    average velocity since the last pose."""
    e = PoseExtrapolator()
    e.add_pose(0.9, (0.0, 0.0, 0.0))
    for k in range(12):
        t = 0.9 + 0.02 * k
        u = max(t - 1.0, 0.0)
        p = tf.compose((3.0, -1.0, 0.7), (math.sin(0.5 * u) / 0.5, (1 - math.cos(0.5 * u)) / 0.5, 0.5 * u))
        e.add_odometry(Odometry(time=t, x=p[0], y=p[1], yaw=p[2]))
    vx, vy, w = e.body_motion(1.0, 0.1)
    assert w == pytest.approx(0.5, rel=1e-6)
    assert math.hypot(vx, vy) == pytest.approx(math.sin(0.025) / 0.025, rel=1e-6)  # the chord over the arc's time
    assert vy == pytest.approx(math.hypot(vx, vy) * math.sin(0.025), rel=1e-6)  # the chord's bearing: half the turn
    # A window odometry does not reach yet falls back on the velocity it had.
    late = e.body_motion(1.5, 0.1)
    assert late[2] != pytest.approx(0.5)
