"""Range data: crop to [min_range, max_range], turn far returns into misses, accumulate scans.

A return farther than ``max_range`` (including +inf, the "no echo" code of
many drivers) still proves that the beam travelled through free space, so it
becomes a *miss* at ``missing_data_ray_length`` along the beam: the inserter
then clears the cells along it without marking an obstacle at its end.

A scanner sweeps its beams over a time (``time_increment`` per beam): a robot
turning at 1 rad/s rotates 4° during a 66 ms Hokuyo sweep, bending walls by
tens of centimetres at 5 m. As in Cartographer, ``crop_polar`` can place every
beam with the pose the robot had when that beam was measured (constant
velocity over the sweep), expressing all points in the tracking frame at the
scan's own time: de-skewing.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from carto_cli.core import transform

if TYPE_CHECKING:
    from carto_cli.core.records import Scan

Pose = Sequence[float] | np.ndarray  # (x, y, theta), or (x, y) for a position


@dataclass(frozen=True, eq=False)
class RangeData:
    """Returns (hits) and misses as (n, 2) float64 points, plus the sensor origin, in one frame."""

    origin: np.ndarray  # (2,)
    returns: np.ndarray  # (n, 2)
    misses: np.ndarray  # (m, 2)

    @staticmethod
    def empty() -> RangeData:
        return RangeData(np.zeros(2), np.empty((0, 2)), np.empty((0, 2)))

    def transformed(self, pose: Pose) -> RangeData:
        x, y, theta = (float(v) for v in pose)
        c, s = math.cos(theta), math.sin(theta)
        ox, oy = float(self.origin[0]), float(self.origin[1])
        return RangeData(
            np.array([c * ox - s * oy + x, s * ox + c * oy + y]),
            _transform_points(np.ascontiguousarray(self.returns, dtype=np.float64), x, y, c, s),
            _transform_points(np.ascontiguousarray(self.misses, dtype=np.float64), x, y, c, s),
        )


@njit(cache=True, nogil=True)
def _transform_points(points, x, y, c, s):
    """(n, 2) points mapped by the rigid transform (x, y, rotation with cos c, sin s); runs per node."""
    n = points.shape[0]
    out = np.empty((n, 2))
    for i in range(n):
        px = points[i, 0]
        py = points[i, 1]
        out[i, 0] = c * px - s * py + x
        out[i, 1] = s * px + c * py + y
    return out


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _crop_polar_moving(ranges, angles, min_range, max_range, missing_data_ray_length, mx, my, mth,
                       times, ux, uy, w):
    """``_crop_polar`` with the sensor mounted at (mx, my, mth) on a body moving at (ux, uy, w).

    Beam i is measured ``times[i]`` after the reference time (before it when negative); the body
    has then moved by (ux, uy) · dt and turned by w · dt (its own frame at the reference time,
    constant velocity as the extrapolator predicts). Returns and misses come out in the body
    frame at the reference time.
    """
    n = ranges.shape[0]
    returns = np.empty((n, 2))
    misses = np.empty((n, 2))
    nr = 0
    nm = 0
    for i in range(n):
        r = ranges[i]
        if not (r >= min_range) or r <= 0.0:
            continue
        dt = times[i]
        turn = w * dt
        ct = np.cos(turn)
        st = np.sin(turn)
        ox = ct * mx - st * my + ux * dt
        oy = st * mx + ct * my + uy * dt
        a = angles[i] + mth + turn
        if r <= max_range:
            returns[nr, 0] = ox + r * np.cos(a)
            returns[nr, 1] = oy + r * np.sin(a)
            nr += 1
        else:
            misses[nm, 0] = ox + missing_data_ray_length * np.cos(a)
            misses[nm, 1] = oy + missing_data_ray_length * np.sin(a)
            nm += 1
    return returns[:nr].copy(), misses[:nm].copy()


def crop_polar(ranges: ArrayLike, angles: ArrayLike, *, min_range: float = 0.0, max_range: float = 30.0,
               missing_data_ray_length: float = 5.0, mount: Pose | None = None, time_increment: float = 0.0,
               motion: Pose = (0.0, 0.0, 0.0), times: ArrayLike | None = None) -> RangeData:
    """Range data from beam ranges and bearings.

    Without ``mount``, in the sensor frame (origin at 0). With ``mount`` (the
    sensor's pose on the body), in the body frame, origin at the sensor; and
    with a ``motion`` (vx, vy, yaw rate of the body in its own frame) and the
    beams' times (``times``, seconds after the reference time, else the
    scanner's ``time_increment`` per beam), de-skewed to the reference time.
    """
    r = np.ascontiguousarray(ranges, dtype=np.float64)
    a = np.ascontiguousarray(angles, dtype=np.float64)
    if mount is None:
        returns, misses = _crop_polar(r, a, float(min_range), float(max_range), float(missing_data_ray_length))
        return RangeData(np.zeros(2), returns, misses)
    mx, my, mth = (float(v) for v in mount)
    ux, uy, w = (float(v) for v in motion)
    if times is None:
        dt = np.arange(r.shape[0], dtype=np.float64) * float(time_increment)
    else:
        dt = np.ascontiguousarray(times, dtype=np.float64)
        if dt.shape != r.shape:
            raise ValueError(f"{dt.shape[0]} beam times for {r.shape[0]} beams")
    returns, misses = _crop_polar_moving(r, a, float(min_range), float(max_range), float(missing_data_ray_length),
                                         mx, my, mth, dt, ux, uy, w)
    return RangeData(np.array([mx, my]), returns, misses)


def crop_scan(scan: Scan, *, mount: Pose | None = None, motion: Pose | None = None, **kwargs: Any) -> RangeData:
    """``crop_polar`` for a :class:`carto_cli.core.records.Scan`.

    The scan's own limits come first, as REP 117 has them: a reading above its ``range_max`` is no return (as
    +inf: a miss beyond ``max_range``), one below its ``range_min`` is dropped. A driver that reports "no
    return" as a value past its maximum would otherwise put phantom walls there, out to ``max_range``.

    With a ``motion``, beams are de-skewed by the times they were measured (``Scan.beam_times``: a per-point time,
    else the scan's ``time_increment``); a scan with neither, such as a CARMEN log, is taken as instantaneous.
    """
    ranges = within_sensor_limits(scan.ranges, float(scan.range_min), float(scan.range_max))
    if mount is None:
        if motion is not None:
            raise ValueError("de-skewing (motion) needs the sensor's mount on the body")
        return crop_polar(ranges, scan.angles, **kwargs)
    if motion is None or not scan.timed:
        return crop_polar(ranges, scan.angles, mount=mount, **kwargs)
    return crop_polar(ranges, scan.angles, mount=mount, times=scan.beam_times(), motion=motion, **kwargs)


def within_sensor_limits(ranges: ArrayLike, range_min: float, range_max: float) -> np.ndarray:
    """``ranges`` with readings above ``range_max`` set to +inf and those below ``range_min`` to NaN (a copy only
    when one is out of its limits; non-finite or non-positive limits are no limits)."""
    r = np.asarray(ranges)
    above = r > range_max if math.isfinite(range_max) and range_max > 0 else None
    below = r < range_min if math.isfinite(range_min) and range_min > 0 else None
    if (above is None or not above.any()) and (below is None or not below.any()):
        return r
    r = r.astype(np.float64, copy=True)
    if above is not None:
        r[above] = np.inf
    if below is not None:
        r[below] = np.nan
    return r


def crop_points(points: ArrayLike, origin: Pose = (0.0, 0.0), *, min_range: float = 0.0, max_range: float = 30.0,
                missing_data_ray_length: float = 5.0) -> RangeData:
    """Same rules for Cartesian points measured from ``origin`` (e.g. a sliced point cloud)."""
    origin = np.asarray(origin, dtype=np.float64)
    returns, misses = _crop_points(
        np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2),
        float(origin[0]), float(origin[1]),
        float(min_range), float(max_range), float(missing_data_ray_length),
    )
    return RangeData(origin.copy(), returns, misses)


def accumulate(parts: Sequence[RangeData], poses: Sequence, frame: Pose | None = None) -> RangeData:
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
