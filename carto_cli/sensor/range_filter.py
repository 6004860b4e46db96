"""Range data: crop to [min_range, max_range], turn far returns into misses, accumulate scans.

A return farther than ``max_range`` (including +inf, the "no echo" code of
many drivers) still proves that the beam travelled through free space, so it
becomes a *miss* at ``missing_data_ray_length`` along the beam: the inserter
then clears the cells along it without marking an obstacle at its end.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from numba import njit

from carto_cli import transform


@dataclass(frozen=True, eq=False)
class RangeData:
    """Returns (hits) and misses as (n, 2) float64 points, plus the sensor origin, in one frame."""

    origin: np.ndarray  # (2,)
    returns: np.ndarray  # (n, 2)
    misses: np.ndarray  # (m, 2)

    @staticmethod
    def empty() -> "RangeData":
        return RangeData(np.zeros(2), np.empty((0, 2)), np.empty((0, 2)))

    def transformed(self, pose) -> "RangeData":
        pose = transform.as_pose(pose)
        return RangeData(
            transform.apply(pose, self.origin.reshape(1, 2))[0],
            transform.apply(pose, self.returns),
            transform.apply(pose, self.misses),
        )


@njit(cache=True)
def _crop_polar(ranges, angles, min_range, max_range, missing_data_ray_length):
    n = ranges.shape[0]
    returns = np.empty((n, 2))
    misses = np.empty((n, 2))
    nr = 0
    nm = 0
    for i in range(n):
        r = ranges[i]
        # NaN fails every comparison, -inf fails the first; 0 is the other common "no echo" code.
        if not (r >= min_range) or r <= 0.0:
            continue
        a = angles[i]
        if r <= max_range:
            returns[nr, 0] = r * np.cos(a)
            returns[nr, 1] = r * np.sin(a)
            nr += 1
        else:
            misses[nm, 0] = missing_data_ray_length * np.cos(a)
            misses[nm, 1] = missing_data_ray_length * np.sin(a)
            nm += 1
    return returns[:nr].copy(), misses[:nm].copy()


@njit(cache=True)
def _crop_points(points, ox, oy, min_range, max_range, missing_data_ray_length):
    n = points.shape[0]
    returns = np.empty((n, 2))
    misses = np.empty((n, 2))
    nr = 0
    nm = 0
    for i in range(n):
        dx = points[i, 0] - ox
        dy = points[i, 1] - oy
        r = np.sqrt(dx * dx + dy * dy)
        # A point with an infinite coordinate has no usable direction: dropped.
        if not np.isfinite(r) or r < min_range or r <= 0.0:
            continue
        if r <= max_range:
            returns[nr, 0] = points[i, 0]
            returns[nr, 1] = points[i, 1]
            nr += 1
        else:
            f = missing_data_ray_length / r
            misses[nm, 0] = ox + f * dx
            misses[nm, 1] = oy + f * dy
            nm += 1
    return returns[:nr].copy(), misses[:nm].copy()


def crop_polar(ranges, angles, *, min_range: float = 0.0, max_range: float = 30.0,
               missing_data_ray_length: float = 5.0) -> RangeData:
    """Range data in the sensor frame (origin at 0) from beam ranges and bearings."""
    returns, misses = _crop_polar(
        np.ascontiguousarray(ranges, dtype=np.float64),
        np.ascontiguousarray(angles, dtype=np.float64),
        float(min_range), float(max_range), float(missing_data_ray_length),
    )
    return RangeData(np.zeros(2), returns, misses)


def crop_scan(scan, **kwargs) -> RangeData:
    """``crop_polar`` for a :class:`carto_cli.records.Scan`."""
    return crop_polar(scan.ranges, scan.angles, **kwargs)


def crop_points(points, origin=(0.0, 0.0), *, min_range: float = 0.0, max_range: float = 30.0,
                missing_data_ray_length: float = 5.0) -> RangeData:
    """Same rules for Cartesian points measured from ``origin`` (e.g. a sliced point cloud)."""
    origin = np.asarray(origin, dtype=np.float64)
    returns, misses = _crop_points(
        np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2),
        float(origin[0]), float(origin[1]),
        float(min_range), float(max_range), float(missing_data_ray_length),
    )
    return RangeData(origin.copy(), returns, misses)


def accumulate(parts: Sequence[RangeData], poses: Sequence, frame=None) -> RangeData:
    """Merge ``num_accumulated_range_data`` scans into one.

    ``poses[i]`` places ``parts[i]`` (its sensor frame) in a common frame; the
    result is expressed in ``frame`` (a pose in that common frame, default the
    last part's pose). Like Cartographer, the merged data keeps the last
    part's origin: rays are cast from where the sensor was most recently.
    """
    if len(parts) != len(poses):
        raise ValueError(f"{len(parts)} range data but {len(poses)} poses")
    if not parts:
        return RangeData.empty()
    reference = transform.as_pose(poses[-1] if frame is None else frame)
    to_frame = transform.inverse(reference)
    moved = [p.transformed(transform.compose(to_frame, pose)) for p, pose in zip(parts, poses)]
    return RangeData(
        moved[-1].origin,
        np.concatenate([m.returns for m in moved]),
        np.concatenate([m.misses for m in moved]),
    )
