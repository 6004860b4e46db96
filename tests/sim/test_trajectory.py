"""Trajectories: limits, consistency of poses and velocities, following routes."""
from __future__ import annotations

import math

import numpy as np
import pytest

from carto_cli.sim.trajectory import Limits, Trajectory, follow_route, loop_trajectory, wrap_angle
from carto_cli.sim.world import corridor, loop_building, office, room


@pytest.fixture(scope="module")
def loop():
    return loop_trajectory(loop_building())


def test_limits_are_respected(loop):
    lim = Limits()
    assert np.abs(loop.v).max() <= lim.v_max + 1e-9
    assert np.abs(loop.w).max() <= lim.w_max + 1e-9
    assert np.abs(np.diff(loop.v)).max() <= lim.a_max * loop.dt + 1e-9
    assert np.abs(np.diff(loop.w)).max() <= lim.alpha_max * loop.dt + 1e-9
    assert loop.v.max() == pytest.approx(lim.v_max)  # it does reach cruising speed


def test_poses_and_velocities_agree_between_knots(loop):
    t = np.linspace(1.0, loop.duration - 1.0, 2000) + 0.00377  # off the knots
    h = 1e-5
    p0, p1 = loop.poses(t - h), loop.poses(t + h)
    vel = loop.velocities(t)
    yaw = loop.poses(t)[:, 2]
    d = (p1[:, :2] - p0[:, :2]) / (2 * h)
    forward = d[:, 0] * np.cos(yaw) + d[:, 1] * np.sin(yaw)
    lateral = -d[:, 0] * np.sin(yaw) + d[:, 1] * np.cos(yaw)
    np.testing.assert_allclose(forward, vel[:, 0], atol=1e-6)
    np.testing.assert_allclose(lateral, 0.0, atol=1e-6)  # a unicycle does not slide
    np.testing.assert_allclose(wrap_angle(p1[:, 2] - p0[:, 2]) / (2 * h), vel[:, 1], atol=1e-6)
    np.testing.assert_allclose((loop.travelled(t + h) - loop.travelled(t - h)) / (2 * h), np.abs(vel[:, 0]), atol=1e-6)


def test_poses_are_continuous(loop):
    t = np.arange(0, loop.duration, 0.001)
    p = loop.poses(t)
    assert np.hypot(*np.diff(p[:, :2], axis=0).T).max() <= 0.5 * 0.001 + 1e-9


def test_closed_loop_returns_to_start_at_rest(loop):
    start, end = loop.poses([0.0, loop.duration + 5.0])
    assert np.hypot(*(end[:2] - start[:2])) < 0.1
    assert (loop.velocities([loop.duration + 1.0]) == 0).all()
    assert loop.length == pytest.approx(2 * (21.5 + 13.5), rel=0.02)  # the centre line of the ring
    two = loop_trajectory(loop_building(), laps=2)
    assert two.length == pytest.approx(2 * loop.length, rel=0.01)


def test_sharp_turns_stop_and_turn_in_place():
    # out and back along the same line: the robot must reach the far end and come back
    tr = Trajectory.follow([(0, 0), (3, 0), (0, 0)])
    p = tr.poses(np.arange(0, tr.duration, 0.01))
    assert p[:, 0].max() == pytest.approx(3.0, abs=0.1)
    assert np.abs(p[:, 1]).max() < 0.1
    end = tr.poses([tr.duration])[0]
    assert np.hypot(end[0], end[1]) < 0.1 and abs(abs(end[2]) - math.pi) < 0.2


@pytest.mark.parametrize("build", [room, corridor, loop_building, office])
def test_routes_are_driven_without_touching_walls(build):
    w = build()
    tr = follow_route(w)
    p = tr.poses(np.arange(0, tr.duration, 0.05))
    assert w.distance_to_walls(p[:, :2]).min() > 0.3
    last = w.route[0] if w.closed else w.route[-1]
    assert np.hypot(*(p[-1, :2] - last)) < 0.15


def test_office_route_enters_the_rooms():
    w = office(corridor_width=2.0, room_depth=4.0)
    p = follow_route(w).poses(np.arange(0, 200, 0.1))
    assert p[:, 1].max() > 3.8


def test_slower_limits_take_longer():
    w = room(8, 6)
    fast = follow_route(w)
    slow = follow_route(w, limits=Limits(v_max=0.25))
    assert slow.duration > 1.6 * fast.duration
    assert slow.length == pytest.approx(fast.length, rel=0.05)
