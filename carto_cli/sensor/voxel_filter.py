"""Voxel filter and adaptive voxel filter on (n, 2) point arrays.

The voxel filter keeps the first point that falls into each square voxel (as
Cartographer's original filter did), so the output is a subset of the input in
its original order: deterministic, and no point is moved off the surface.
"""
from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _voxel_keys(points, length):
    n = points.shape[0]
    inv = 1.0 / length
    keys = np.empty(n, dtype=np.int64)
    for i in range(n):
        ix = np.int64(np.floor(points[i, 0] * inv))
        iy = np.int64(np.floor(points[i, 1] * inv))
        keys[i] = (ix << 32) + (iy & 0xFFFFFFFF)
    return keys


def _first_in_voxel_mask(points, length):
    keys = _voxel_keys(points, length)
    # np.unique's return_index is the first occurrence of each key (it sorts stably).
    _, first = np.unique(keys, return_index=True)
    keep = np.zeros(points.shape[0], dtype=bool)
    keep[first] = True
    return keep


@njit(cache=True)
def _within_range_mask(points, max_range):
    n = points.shape[0]
    keep = np.empty(n, dtype=np.bool_)
    r2 = max_range * max_range
    for i in range(n):
        keep[i] = points[i, 0] * points[i, 0] + points[i, 1] * points[i, 1] <= r2
    return keep


def _as_points(points) -> np.ndarray:
    return np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)


def voxel_filter(points, length: float = 0.025) -> np.ndarray:
    """Keep the first point of every occupied ``length`` x ``length`` voxel."""
    if length <= 0:
        raise ValueError("voxel length must be positive")
    points = _as_points(points)
    return points[_first_in_voxel_mask(points, float(length))]


def adaptive_voxel_filter(points, *, max_length: float = 0.5, min_num_points: int = 200,
                          max_range: float = 50.0) -> np.ndarray:
    """Coarsest voxel filter that still leaves at least ``min_num_points`` points.

    Points farther than ``max_range`` from the frame origin are dropped first.
    If ``max_length`` is too coarse, the edge is halved until the cloud is
    dense enough (giving up below 1% of ``max_length`` and returning the finest
    attempt), then bisected. Cartographer stops bisecting at 10% edge
    precision; we also keep bisecting while the count exceeds
    1.1 x ``min_num_points`` so the result lands in [min, 1.1 min] whenever the
    cloud's voxel counts allow it.
    """
    points = _as_points(points)
    points = points[_within_range_mask(points, float(max_range))]
    if points.shape[0] <= min_num_points:
        return points
    result = voxel_filter(points, max_length)
    if result.shape[0] >= min_num_points:
        return result
    high = float(max_length)
    while high > 1e-2 * max_length:
        low = high / 2.0
        result = voxel_filter(points, low)
        if result.shape[0] >= min_num_points:
            while (high - low) / low > 1e-1 or (
                    result.shape[0] > 1.1 * min_num_points and (high - low) / low > 1e-4):
                mid = 0.5 * (low + high)
                candidate = voxel_filter(points, mid)
                if candidate.shape[0] >= min_num_points:
                    low = mid
                    result = candidate
                else:
                    high = mid
            return result
        high = low
    return result
