"""GMapping's odometry motion model: a particle moves by the odometry increment, with noise that grows
with the translation and rotation of that increment.

For an increment (dx, dy, dtheta) in the frame of the previous odometry pose, the noise standard
deviations are ``srr |dx| + str |dtheta| + SIDEWAYS srr |dy|`` along the robot's axis (and its
mirror for the lateral one) and ``stt |dtheta| + srt sqrt(dx^2 + dy^2)`` in heading: srr is metres of
translation error per metre, str metres per radian turned, stt radians per radian, srt radians per
metre (slam_gmapping's parameters).
"""
from __future__ import annotations

import math

import numpy as np

from carto_cli.core import transform

SIDEWAYS = 0.3  # lateral slip per unit of the other axis' motion, relative to srr (GMapping's sxy)
MIN_SIGMA_XY = 1e-3  # metres: keeps the Gaussian proper when the robot stands still
MIN_SIGMA_THETA = math.radians(0.05)


def increment(previous, current) -> np.ndarray:
    """Odometry ``current`` seen from ``previous`` (both (x, y, theta)): the motion to apply to particles."""
    return transform.relative(previous, current)


def sigmas(delta, srr: float, srt: float, str_: float, stt: float) -> np.ndarray:
    """Standard deviations (along, lateral, heading) of the noise on one increment."""
    dx, dy, dt = (abs(float(v)) for v in delta)
    return np.array([
        max(MIN_SIGMA_XY, srr * dx + str_ * dt + SIDEWAYS * srr * dy),
        max(MIN_SIGMA_XY, srr * dy + str_ * dt + SIDEWAYS * srr * dx),
        max(MIN_SIGMA_THETA, stt * dt + srt * math.hypot(dx, dy)),
    ])


def predict(poses: np.ndarray, delta, noise: np.ndarray) -> np.ndarray:
    """Each particle moved by ``delta`` (robot frame) perturbed by its row of ``noise`` (same frame)."""
    return transform.compose(np.asarray(poses, dtype=np.float64), np.asarray(delta, dtype=np.float64)[None, :] + noise)


def sample(poses: np.ndarray, delta, sigma: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Draw every particle's next pose from the motion model."""
    return predict(poses, delta, rng.standard_normal((poses.shape[0], 3)) * sigma[None, :])


def world_sigmas(poses: np.ndarray, sigma: np.ndarray) -> np.ndarray:
    """The (x, y, heading) standard deviations of the motion Gaussian in the world frame, per particle: the
    robot-frame ellipse's axis-aligned extent (what the proposal weights its lattice with)."""
    c, s = np.abs(np.cos(poses[:, 2])), np.abs(np.sin(poses[:, 2]))
    out = np.empty((poses.shape[0], 3))
    out[:, 0] = np.hypot(c * sigma[0], s * sigma[1])
    out[:, 1] = np.hypot(s * sigma[0], c * sigma[1])
    out[:, 2] = sigma[2]
    return out
