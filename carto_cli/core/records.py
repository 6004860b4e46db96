"""The typed records every reader yields and every writer consumes.

Times are seconds (float64, the recording's clock); lengths metres; angles
radians. Arrays are numpy and never shared with the decoder's buffers.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Scan:
    """One 2D range scan in the sensor frame.

    ``angles[i]`` is the bearing of ``ranges[i]``. For a LaserScan the beams are
    evenly spaced (``angle_min + i * angle_increment``); for a sliced point cloud
    ``angle_increment`` is ``None`` and the angles are whatever the points give.
    Invalid returns are kept as they were recorded (NaN, Inf, out of limits):
    filtering them is local SLAM's job, counting them is ``carto info``'s.

    When each beam was measured is ``time`` plus ``beam_times()``: ``point_times`` when the source gives a time
    per point (a 3D lidar's per-point field, scans of several lasers merged), else ``i * time_increment``.
    """

    time: float
    ranges: np.ndarray  # float32 (n,)
    angles: np.ndarray  # float32 (n,)
    frame: str
    topic: str = ""
    range_min: float = 0.0
    range_max: float = math.inf
    angle_min: float = 0.0
    angle_increment: float | None = None
    time_increment: float = 0.0
    scan_time: float = 0.0
    intensities: np.ndarray | None = None  # float32 (n,) or None
    source_type: str = "sensor_msgs/msg/LaserScan"
    point_times: np.ndarray | None = None  # float64 (n,) seconds after ``time``, or None

    @property
    def timed(self) -> bool:
        """Whether the beams were measured over a time (a sweep to de-skew), not all at ``time``."""
        return self.point_times is not None or bool(self.time_increment)

    def beam_times(self) -> np.ndarray:
        """float64 (n,) seconds after ``time`` each beam was measured."""
        if self.point_times is not None:
            return np.asarray(self.point_times, dtype=np.float64)
        return np.arange(self.num_beams, dtype=np.float64) * float(self.time_increment)

    @property
    def num_beams(self) -> int:
        return int(self.ranges.shape[0])

    def points(self) -> np.ndarray:
        """(n, 2) float64 Cartesian points of every return, invalid ones included."""
        r = self.ranges.astype(np.float64)
        a = self.angles.astype(np.float64)
        return np.stack([r * np.cos(a), r * np.sin(a)], axis=1)

    def same_as(self, other: Scan) -> bool:
        """Equality of content, NaNs equal to NaNs (for round-trip checks)."""
        if not isinstance(other, Scan):
            return False
        def arr_eq(a, b):
            if a is None or b is None:
                return a is None and b is None
            return a.shape == b.shape and np.array_equal(a, b, equal_nan=True)
        return (
            self.time == other.time
            and self.frame == other.frame
            and arr_eq(self.ranges, other.ranges)
            and arr_eq(self.angles, other.angles)
            and arr_eq(self.intensities, other.intensities)
            and np.float32(self.range_min) == np.float32(other.range_min)
            and np.float32(self.range_max) == np.float32(other.range_max)
        )


@dataclass(frozen=True)
class Odometry:
    """Planar wheel odometry: pose of ``child_frame`` in ``frame`` and body-frame velocity."""

    time: float
    x: float
    y: float
    yaw: float
    frame: str = "odom"
    child_frame: str = "base_link"
    topic: str = ""
    vx: float = 0.0
    vy: float = 0.0
    wz: float = 0.0


@dataclass(frozen=True, eq=False)
class Imu:
    """Inertial sample; ``orientation`` is (x, y, z, w) or None when the IMU gives none."""

    time: float
    angular_velocity: np.ndarray  # float64 (3,) rad/s
    linear_acceleration: np.ndarray  # float64 (3,) m/s^2
    orientation: np.ndarray | None = None  # float64 (4,) x y z w
    frame: str = "imu"
    topic: str = ""

    def same_as(self, other: Imu) -> bool:
        if not isinstance(other, Imu):
            return False
        o1, o2 = self.orientation, other.orientation
        return (
            self.time == other.time
            and self.frame == other.frame
            and np.array_equal(self.angular_velocity, other.angular_velocity)
            and np.array_equal(self.linear_acceleration, other.linear_acceleration)
            and ((o1 is None and o2 is None) or (o1 is not None and o2 is not None and np.array_equal(o1, o2)))
        )


@dataclass(frozen=True)
class Transform:
    """A transform: pose of ``child`` in ``parent``; rotation as (x, y, z, w). ``topic`` is '' for a static one
    (/tf_static) and the topic for one read from a dynamic TF topic (/tf)."""

    parent: str
    child: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    time: float = 0.0
    topic: str = ""

    @property
    def yaw(self) -> float:
        return quaternion_yaw(*self.rotation)

    def pose2d(self) -> tuple[float, float, float]:
        return (self.translation[0], self.translation[1], self.yaw)


Record = Scan | Odometry | Imu | Transform


@dataclass(frozen=True, eq=False)
class Cloud:
    """A 3D lidar's sweep in the sensor frame, as a writer makes it a PointCloud2 (readers slice clouds into Scans,
    so this is no ``Record``). ``point_times`` (seconds after ``time``) go into the field ``time_field``, in the
    convention of the driver that names it so: 't' uint32 ns (Ouster), 'offset_time' uint32 ns (Livox), 'time'
    float32 s (Velodyne)."""

    time: float
    points: np.ndarray  # float32 (n, 3) x y z
    frame: str
    topic: str = ""
    point_times: np.ndarray | None = None  # float64 (n,) seconds after ``time``
    time_field: str = "t"


def quaternion_yaw(x: float, y: float, z: float, w: float) -> float:
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def yaw_quaternion(yaw: float) -> tuple[float, float, float, float]:
    return (0.0, 0.0, math.sin(yaw / 2.0), math.cos(yaw / 2.0))


def strip_frame(frame: str) -> str:
    """ROS1 frames may carry a leading slash ('/laser'); tf2 names do not."""
    return frame[1:] if frame.startswith("/") else frame


def beam_angles(angle_min: float, angle_increment: float, n: int) -> np.ndarray:
    """Bearings of a LaserScan's beams, computed in float32 exactly as every reader computes them,
    so that scans survive a write/read round trip bit for bit."""
    return np.float32(angle_min) + np.arange(n, dtype=np.float32) * np.float32(angle_increment)
