"""Voxel filter and adaptive voxel filter on (n, 2) point arrays.

The voxel filter keeps the first point that falls into each square voxel (as
Cartographer's original filter did), so the output is a subset of the input in
its original order: deterministic, and no point is moved off the surface.

Both filters are single numba kernels with an open-addressing hash set of
voxel keys: O(n) per voxel size tried, no sorting, no Python loop over the
adaptive filter's bisection (which runs twice per scan, for the matching
points and for the loop-closure points).
"""
from __future__ import annotations

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

_HASH_MULTIPLIER = np.uint64(0x9E3779B97F4A7C15)  # Fibonacci hashing


@njit(cache=True, nogil=True)
def _table_bits(n):
    bits = 4
    while (1 << bits) < 2 * n:
        bits += 1
    return bits


@njit(cache=True, nogil=True)
def _first_in_voxel(points, inv_length, keep, keys, used, bits):
    """Mark in ``keep`` the first point of every voxel; returns how many were marked.

    ``keys`` / ``used`` are a hash table of ``1 << bits`` slots (at least 2n), cleared here.
    """
    n = points.shape[0]
    size = 1 << bits
    mask = size - 1
    shift = np.uint64(64 - bits)
    used[:size] = False
    count = 0
    for i in range(n):
        ix = np.int64(np.floor(points[i, 0] * inv_length))
        iy = np.int64(np.floor(points[i, 1] * inv_length))
        key = (ix << 32) + (iy & 0xFFFFFFFF)
        h = np.int64((np.uint64(key) * _HASH_MULTIPLIER) >> shift)
        while True:
            if not used[h]:
                used[h] = True
                keys[h] = key
                keep[i] = True
                count += 1
                break
            if keys[h] == key:
                keep[i] = False
                break
            h = (h + 1) & mask
    return count


@njit(cache=True, nogil=True)
def _voxel_mask(points, length):
    n = points.shape[0]
    bits = _table_bits(n)
    keep = np.zeros(n, dtype=np.bool_)
    _first_in_voxel(points, 1.0 / length, keep, np.empty(1 << bits, np.int64), np.zeros(1 << bits, np.bool_), bits)
    return keep


@njit(cache=True, nogil=True)
def _adaptive_mask(points, max_length, min_num_points, max_range):
    """Mask over ``points`` of the adaptive filter's result (see ``adaptive_voxel_filter``)."""
    n = points.shape[0]
    r2 = max_range * max_range
    inside = np.empty(n, dtype=np.bool_)
    m = 0
    for i in range(n):
        inside[i] = points[i, 0] * points[i, 0] + points[i, 1] * points[i, 1] <= r2
        if inside[i]:
            m += 1
    if m <= min_num_points:
        return inside
    near = np.empty((m, 2))
    index = np.empty(m, dtype=np.int64)
    j = 0
    for i in range(n):
        if inside[i]:
            near[j, 0] = points[i, 0]
            near[j, 1] = points[i, 1]
            index[j] = i
            j += 1
    bits = _table_bits(m)
    keys = np.empty(1 << bits, np.int64)
    used = np.zeros(1 << bits, np.bool_)
    result = np.zeros(m, dtype=np.bool_)
    trial = np.zeros(m, dtype=np.bool_)
    count = _first_in_voxel(near, 1.0 / max_length, result, keys, used, bits)
    if count < min_num_points:
        high = max_length
        while high > 1e-2 * max_length:
            low = high / 2.0
            count = _first_in_voxel(near, 1.0 / low, result, keys, used, bits)
            if count >= min_num_points:
                while (high - low) / low > 1e-1 or (count > 1.1 * min_num_points and (high - low) / low > 1e-4):
                    mid = 0.5 * (low + high)
                    c = _first_in_voxel(near, 1.0 / mid, trial, keys, used, bits)
                    if c >= min_num_points:
                        low = mid
                        count = c
                        result, trial = trial, result
                    else:
                        high = mid
                break
            high = low
    keep = np.zeros(n, dtype=np.bool_)
    for j in range(m):
        if result[j]:
            keep[index[j]] = True
    return keep


def _as_points(points: ArrayLike) -> np.ndarray:
    return np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)


def voxel_filter(points: ArrayLike, length: float = 0.025) -> np.ndarray:
    """Keep the first point of every occupied ``length`` x ``length`` voxel."""
    if length <= 0:
        raise ValueError("voxel length must be positive")
    points = _as_points(points)
    return points[_voxel_mask(points, float(length))]


def adaptive_voxel_filter(points: ArrayLike, *, max_length: float = 0.5, min_num_points: int = 200,
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
    return points[_adaptive_mask(points, float(max_length), int(min_num_points), float(max_range))]
