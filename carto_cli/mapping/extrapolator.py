"""Pose extrapolator: predicts where the tracking frame is at a scan's time.

Translation: constant linear velocity, from wheel odometry when at least two
odometry samples are known, otherwise from the recent matched poses.
Rotation: the IMU's yaw rate integrated over the interval when IMU data is
used, else the odometry yaw rate, else the yaw rate of the recent poses.

Odometry velocity is measured in the body frame (displacement between the
two retained odometry samples, seen from the newer one) and rotated into the
local frame with the *estimated* heading, as Cartographer does: odometry's own
heading drifts, its short-term body-frame motion is what it is good at.
The IMU's z axis is assumed parallel to the tracking frame's (2D).
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from carto_cli.core.records import Imu, Odometry
from carto_cli.core.transform import wrap_angle_scalar
from carto_cli.sensor.range_filter import Pose


class PoseExtrapolator:
    def __init__(self, *, pose_queue_duration: float = 0.001, use_imu_data: bool = False):
        self.pose_queue_duration = float(pose_queue_duration)
        self.use_imu_data = bool(use_imu_data)
        self._poses: deque[tuple[float, tuple[float, float, float]]] = deque()
        self._odometry: deque[tuple[float, tuple[float, float, float]]] = deque()
        self._imu: deque[tuple[float, float]] = deque()
        self._linear_velocity_from_poses = (0.0, 0.0)
        self._angular_velocity_from_poses = 0.0

    # --- inputs ---------------------------------------------------------------------------

    def add_pose(self, time: float, pose: Pose) -> None:
        """A matched pose of the tracking frame in the local frame."""
        x, y, theta = pose
        self._poses.append((float(time), (float(x), float(y), float(theta))))
        while len(self._poses) > 2 and self._poses[1][0] <= time - self.pose_queue_duration:
            self._poses.popleft()
        self._update_velocities_from_poses()
        self._trim()

    def add_odometry(self, odometry: Odometry) -> None:
        """A :class:`carto_cli.core.records.Odometry`; out-of-order samples are ignored."""
        if self._odometry and odometry.time <= self._odometry[-1][0]:
            return
        self._odometry.append((float(odometry.time), (float(odometry.x), float(odometry.y), float(odometry.yaw))))
        self._trim()

    def add_imu(self, imu: Imu) -> None:
        """A :class:`carto_cli.core.records.Imu`; only its yaw rate is used, and only with ``use_imu_data``."""
        if not self.use_imu_data or (self._imu and imu.time <= self._imu[-1][0]):
            return
        self._imu.append((float(imu.time), float(imu.angular_velocity[2])))
        self._trim()

    # --- outputs --------------------------------------------------------------------------

    @property
    def last_pose_time(self) -> float | None:
        return self._poses[-1][0] if self._poses else None

    def extrapolate(self, time: float) -> np.ndarray:
        """Predicted (x, y, theta) at ``time``; identity before any pose was added."""
        if not self._poses:
            return np.zeros(3)
        t0, last = self._poses[-1]
        theta = last[2] + self._yaw_delta(t0, time)
        if len(self._odometry) >= 2:
            vx, vy = self._linear_velocity_from_odometry()
        else:
            vx, vy = self._linear_velocity_from_poses
        dt = time - t0
        return np.array([last[0] + dt * vx, last[1] + dt * vy, wrap_angle_scalar(theta)])

    def body_motion(self, time: float, duration: float = 0.0, start: float = 0.0) -> tuple[float, float, float]:
        """(vx, vy, yaw rate) of the tracking frame at ``time``, velocity in its own frame.

        What de-skewing beams measured over [time + start, time + start +
        duration] needs (``start`` < 0 for beams measured before ``time``):
        odometry's own motion over that window where it covers it (the IMU's yaw
        rate, if used); else the motion ``extrapolate`` assumes, its linear
        velocity seen from the predicted heading at ``time`` and the yaw rate
        averaged over the window; before any pose, odometry's velocity (zero
        without odometry).
        """
        window = self._odometry_window(time + start, time + start + duration)
        if window is not None:
            vx, vy, w_odometry = window
            w = w_odometry if not self._imu else self._yaw_delta(time + start, time + start + duration) / duration
            return vx, vy, w
        if not self._poses:
            return self._first_motion(time, duration, start)
        t0, last = self._poses[-1]
        theta = last[2] + self._yaw_delta(t0, time)
        if len(self._odometry) >= 2:
            vx, vy = self._linear_velocity_from_odometry()
        else:
            vx, vy = self._linear_velocity_from_poses
        c, s = math.cos(theta), math.sin(theta)
        if duration == 0.0:
            duration = 1e-3
        w = self._yaw_delta(time + start, time + start + duration) / duration
        return c * vx + s * vy, -s * vx + c * vy, w

    def _odometry_window(self, t0: float, t1: float) -> tuple[float, float, float] | None:
        """(vx, vy, yaw rate) of the body over [t0, t1], velocity in its own frame at t0, from odometry interpolated
        at both ends; None unless odometry covers t0 and at least half the window (a sweep is logged when it
        ends, after its odometry: then a sweep is de-skewed by its own motion, not by the motion before it)."""
        odometry = self._odometry
        if len(odometry) < 2 or t1 <= t0 or odometry[0][0] > t0:
            return None
        wanted = t1 - t0
        t1 = min(t1, odometry[-1][0])
        if t1 - t0 < 0.5 * wanted:
            return None
        a, b = self._odometry_at(t0), self._odometry_at(t1)
        dt = t1 - t0
        return (*_velocity_seen_from(a, b, dt, a[2]), wrap_angle_scalar(b[2] - a[2]) / dt)

    def _odometry_at(self, t: float) -> tuple[float, float, float]:
        """Odometry's pose at ``t`` (within the queue), linear between its samples. (A plain loop: the queue holds
        only the samples since the last pose.)"""
        previous = self._odometry[0]
        for sample in self._odometry:
            if sample[0] >= t:
                (ta, pa), (tb, pb) = previous, sample
                u = 0.0 if tb == ta else (t - ta) / (tb - ta)
                return (pa[0] + u * (pb[0] - pa[0]), pa[1] + u * (pb[1] - pa[1]),
                        pa[2] + u * wrap_angle_scalar(pb[2] - pa[2]))
            previous = sample
        return previous[1]

    def _first_motion(self, time: float, duration: float, start: float) -> tuple[float, float, float]:
        """Before any pose: odometry's own velocity (the body's, seen from its newest sample) and the yaw rate, so
        that the first sweep is de-skewed too; zero without odometry. The first sweep anchors the map: left
        smeared, it would shift every later wall by half its motion."""
        if len(self._odometry) < 2:
            return 0.0, 0.0, 0.0
        (t_old, p_old), (t_new, p_new) = self._odometry[0], self._odometry[-1]
        if duration == 0.0:
            duration = 1e-3
        w = self._yaw_delta(time + start, time + start + duration) / duration
        return (*_velocity_seen_from(p_old, p_new, t_new - t_old, p_new[2]), w)

    # --- internals ------------------------------------------------------------------------

    def _update_velocities_from_poses(self) -> None:
        if len(self._poses) < 2:
            return
        (t_old, p_old), (t_new, p_new) = self._poses[0], self._poses[-1]
        dt = t_new - t_old
        if dt < self.pose_queue_duration or dt <= 0.0:
            return
        self._linear_velocity_from_poses = ((p_new[0] - p_old[0]) / dt, (p_new[1] - p_old[1]) / dt)
        self._angular_velocity_from_poses = wrap_angle_scalar(p_new[2] - p_old[2]) / dt

    def _trim(self) -> None:
        if not self._poses:
            # Only the latest samples can matter once the first pose arrives.
            while len(self._odometry) > 2:
                self._odometry.popleft()
            while len(self._imu) > 1:
                self._imu.popleft()
            return
        t_last = self._poses[-1][0]
        # Keep the newest sample at or before the last pose: it still describes the motion after it.
        while len(self._odometry) > 2 and self._odometry[1][0] <= t_last:
            self._odometry.popleft()
        while len(self._imu) > 1 and self._imu[1][0] <= t_last:
            self._imu.popleft()

    def _angular_velocity_without_imu(self) -> float:
        if len(self._odometry) >= 2:
            (t_old, p_old), (t_new, p_new) = self._odometry[0], self._odometry[-1]
            return wrap_angle_scalar(p_new[2] - p_old[2]) / (t_new - t_old)
        return self._angular_velocity_from_poses

    def _linear_velocity_from_odometry(self) -> tuple[float, float]:
        (t_old, p_old), (t_new, p_new) = self._odometry[0], self._odometry[-1]
        # The newer sample's displacement since the older one, in the newer sample's frame
        # (Cartographer: -(pose_new⁻¹ · pose_old).translation / dt).
        bx, by = _velocity_seen_from(p_old, p_new, t_new - t_old, p_new[2])
        t_pose, pose = self._poses[-1]
        heading = pose[2] + self._yaw_delta(t_pose, t_new)
        c, s = math.cos(heading), math.sin(heading)
        return c * bx - s * by, s * bx + c * by

    def _yaw_delta(self, t0: float, t1: float) -> float:
        if t1 < t0:
            return -self._yaw_delta(t1, t0)
        fallback = self._angular_velocity_without_imu()
        if not self._imu:
            return fallback * (t1 - t0)
        # Zero-order hold: each IMU rate holds from its sample until the next one;
        # before the first sample the non-IMU estimate stands in. (A plain loop: the
        # queue holds only the samples since the last pose.)
        total = 0.0
        t = t0
        rate = fallback
        for ts, w in self._imu:
            if ts <= t0:
                rate = w
                continue
            if ts >= t1:
                break
            total += rate * (ts - t)
            t = ts
            rate = w
        return total + rate * (t1 - t)


def _velocity_seen_from(a: tuple[float, float, float], b: tuple[float, float, float], dt: float,
                        heading: float) -> tuple[float, float]:
    """The displacement from pose ``a`` to pose ``b`` over ``dt`` seconds, per second, seen from ``heading``."""
    dx, dy = b[0] - a[0], b[1] - a[1]
    c, s = math.cos(heading), math.sin(heading)
    return (c * dx + s * dy) / dt, (-s * dx + c * dy) / dt
