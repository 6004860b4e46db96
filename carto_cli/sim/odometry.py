"""Wheel odometry and a yaw-rate gyro, derived from a true trajectory.

Odometry integrates corrupted increments between consecutive samples, so its
error grows with the distance driven, as a real robot's does: a scale bias,
a heading bias per metre, and noise whose variance grows with each increment
(the model the bench cases use). It starts at (0, 0, 0) in its own 'odom'
frame, as a driver does, not at the robot's true pose.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from carto_cli.core.transform import wrap_angle
from carto_cli.sim.trajectory import Trajectory


@dataclass(frozen=True)
class OdometryModel:
    scale_bias: float = 0.02  # relative error of the distance driven
    heading_bias: float = math.radians(0.5)  # rad of yaw error per metre driven
    noise_forward: float = 0.02  # m per sqrt(m)
    noise_lateral: float = 0.01  # m per sqrt(m)
    noise_rotation: float = 0.02  # rad per sqrt(rad) turned
    noise_rotation_per_metre: float = math.radians(0.5)  # rad per sqrt(m) driven

    @classmethod
    def perfect(cls) -> OdometryModel:
        return cls(0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ImuModel:
    gyro_bias: float = 0.002  # rad/s, constant
    gyro_noise: float = 0.005  # rad/s, gaussian sigma per sample
    accel_noise: float = 0.05  # m/s^2
    gravity: float = 9.80665

    @classmethod
    def perfect(cls) -> ImuModel:
        return cls(0.0, 0.0, 0.0)


def relative_motion(poses: np.ndarray) -> np.ndarray:
    """(m-1, 3) motion from each pose to the next, in the frame of the first of the pair."""
    d = np.diff(poses[:, :2], axis=0)
    c, s = np.cos(poses[:-1, 2]), np.sin(poses[:-1, 2])
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1],
                     wrap_angle(np.diff(poses[:, 2]))], axis=1)


def compose_increments(increments: np.ndarray) -> np.ndarray:
    """Poses (m+1, 3) from (0, 0, 0) chaining body-frame increments (m, 3)."""
    yaw = np.concatenate([[0.0], np.cumsum(increments[:, 2])])
    c, s = np.cos(yaw[:-1]), np.sin(yaw[:-1])
    dx = c * increments[:, 0] - s * increments[:, 1]
    dy = s * increments[:, 0] + c * increments[:, 1]
    return np.stack([np.concatenate([[0.0], np.cumsum(dx)]), np.concatenate([[0.0], np.cumsum(dy)]),
                     wrap_angle(yaw)], axis=1)


def wheel_odometry(trajectory: Trajectory, times: np.ndarray, model: OdometryModel,
                   rng: np.random.Generator) -> np.ndarray:
    """(m, 5) x y yaw vx wz of the odometry at ``times`` (s from the trajectory's start)."""
    times = np.asarray(times, dtype=np.float64)
    truth = trajectory.poses(times)
    if len(times) < 2:
        return np.zeros((len(times), 5))
    inc = relative_motion(truth)
    # true yaw change, not wrapped, in case of a fast turn between samples
    inc[:, 2] = np.diff(trajectory.yaw_unwrapped(times))
    dist = np.hypot(inc[:, 0], inc[:, 1])
    z = rng.standard_normal((len(inc), 3))
    meas = np.empty_like(inc)
    meas[:, 0] = inc[:, 0] * (1 + model.scale_bias) + model.noise_forward * np.sqrt(dist) * z[:, 0]
    meas[:, 1] = inc[:, 1] + model.noise_lateral * np.sqrt(dist) * z[:, 1]
    rot_sigma = np.sqrt(model.noise_rotation ** 2 * np.abs(inc[:, 2]) + model.noise_rotation_per_metre ** 2 * dist)
    meas[:, 2] = inc[:, 2] + model.heading_bias * dist + rot_sigma * z[:, 2]
    poses = compose_increments(meas)
    dt = np.diff(times)
    vel = np.zeros((len(times), 2))
    vel[1:, 0] = meas[:, 0] / dt
    vel[1:, 1] = meas[:, 2] / dt
    return np.hstack([poses, vel])


def gyro_and_accel(trajectory: Trajectory, times: np.ndarray, model: ImuModel,
                   rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """(m, 3) angular velocity and (m, 3) linear acceleration of an IMU at the robot's origin."""
    times = np.asarray(times, dtype=np.float64)
    m = len(times)
    gyro = np.zeros((m, 3))
    gyro[:, 2] = trajectory.velocities(times)[:, 1] + model.gyro_bias + model.gyro_noise * rng.standard_normal(m)
    accel = np.zeros((m, 3))
    accel[:, :2] = trajectory.accelerations(times) + model.accel_noise * rng.standard_normal((m, 2))
    accel[:, 2] = model.gravity + model.accel_noise * rng.standard_normal(m)
    return gyro, accel
