"""Rigid 2D poses as (x, y, theta) float64 arrays.

A pose maps points from its child frame into its parent frame:
``apply(pose, p) = R(theta) @ p + (x, y)``. Every function accepts a single
pose of shape (3,) or a stack of shape (n, 3) and broadcasts like numpy.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

IDENTITY = np.zeros(3)


def as_pose(pose: ArrayLike) -> np.ndarray:
    return np.asarray(pose, dtype=np.float64)


# The one home of angle wrapping. Every angle carto computes with is wrapped to [-pi, pi) by floored
# modulo; the pair below differ only in what they accept (the scalar one skips numpy's per-call overhead
# in code that runs several times per scan) and give bit-identical results on floats.
_TWO_PI = 2.0 * math.pi


def wrap_angle(theta):
    """Wrap to [-pi, pi). Works on scalars and arrays (a scalar comes back as a float)."""
    wrapped = np.mod(np.asarray(theta, dtype=np.float64) + math.pi, _TWO_PI) - math.pi
    return float(wrapped) if np.ndim(wrapped) == 0 else wrapped


def wrap_angle_scalar(theta: float) -> float:
    """:func:`wrap_angle` for one plain float."""
    return (theta + math.pi) % _TWO_PI - math.pi


@njit(cache=True, nogil=True)
def wrap_angle_kernel(theta: float) -> float:
    """:func:`wrap_angle_scalar` callable from numba kernels."""
    return (theta + math.pi) % _TWO_PI - math.pi


def unwrap_angle(theta: float, reference: float) -> float:
    """``theta`` moved by whole turns to within half a turn of ``reference`` (for interpolating a yaw sequence)."""
    return reference + math.remainder(theta - reference, _TWO_PI)


def compose(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """a ∘ b: first b, then a (b expressed in a's child frame)."""
    a = as_pose(a)
    b = as_pose(b)
    if a.shape == (3,) and b.shape == (3,):
        # One pose each (most calls, several per scan and per search): plain floats skip numpy's per-call cost,
        # which is the GIL time that other threads wait for.
        ax, ay, at = a.tolist()
        bx, by, bt = b.tolist()
        c, s = math.cos(at), math.sin(at)
        return np.array([ax + c * bx - s * by, ay + s * bx + c * by, wrap_angle_scalar(at + bt)])
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = a[..., 0] + c * b[..., 0] - s * b[..., 1]
    y = a[..., 1] + s * b[..., 0] + c * b[..., 1]
    return np.stack([x, y, wrap_angle(a[..., 2] + b[..., 2])], axis=-1)


def inverse(a: ArrayLike) -> np.ndarray:
    a = as_pose(a)
    if a.shape == (3,):
        ax, ay, at = a.tolist()
        c, s = math.cos(at), math.sin(at)
        return np.array([-(c * ax + s * ay), -(-s * ax + c * ay), wrap_angle_scalar(-at)])
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    x = -(c * a[..., 0] + s * a[..., 1])
    y = -(-s * a[..., 0] + c * a[..., 1])
    return np.stack([x, y, wrap_angle(-a[..., 2])], axis=-1)


def relative(a: ArrayLike, b: ArrayLike) -> np.ndarray:
    """Pose of b in a's frame: inverse(a) ∘ b."""
    return compose(inverse(a), b)


def apply(pose: ArrayLike, points: ArrayLike) -> np.ndarray:
    """Map (n, 2) points from the pose's child frame into its parent frame."""
    pose = as_pose(pose)
    points = np.asarray(points, dtype=np.float64)
    c, s = math.cos(pose[2]), math.sin(pose[2])
    out = np.empty_like(points)
    out[:, 0] = c * points[:, 0] - s * points[:, 1] + pose[0]
    out[:, 1] = s * points[:, 0] + c * points[:, 1] + pose[1]
    return out


def rotate(theta: float, points: ArrayLike) -> np.ndarray:
    return apply((0.0, 0.0, theta), points)
