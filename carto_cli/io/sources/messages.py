"""Decoded ROS messages -> records.

Works on any object with the ROS field names: rosbags' dataclasses (numpy
arrays, ``sec/nanosec`` stamps), mcap_ros2's dynamic classes (lists) and
mcap_ros1's genpy classes (tuples and bytes, ``secs/nsecs`` stamps).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from carto_cli.core.errors import TopicError
from carto_cli.core.records import Imu, Odometry, Record, Scan, Transform, beam_angles, quaternion_yaw
from carto_cli.io.recording import ReadOptions, kind_of, normalise_type

LASER_SCAN = "sensor_msgs/msg/LaserScan"
MULTI_ECHO = "sensor_msgs/msg/MultiEchoLaserScan"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"

# sensor_msgs/PointField datatypes carto accepts for x, y and z.
_FLOAT_FIELDS = {7: "f4", 8: "f8"}  # FLOAT32, FLOAT64
_NS_PER_S = 1_000_000_000


# --- time -------------------------------------------------------------------

def stamp_ns(stamp: Any) -> int:
    """Integer nanoseconds of a ROS time (ROS2 ``sec/nanosec`` or genpy ``secs/nsecs``)."""
    sec = getattr(stamp, "sec", None)
    if sec is None:
        sec = stamp.secs
        nsec = stamp.nsecs
    else:
        nsec = stamp.nanosec
    return int(sec) * _NS_PER_S + int(nsec)


def ns_to_seconds(ns: int) -> float:
    # int / int is correctly rounded in Python, so times on the nanosecond grid
    # survive a write/read round trip bit for bit.
    return ns / _NS_PER_S


def seconds_to_ns(t: float) -> int:
    """Nearest nanosecond of ``t``; the inverse of ``ns_to_seconds`` on the nanosecond grid."""
    if not math.isfinite(t):
        raise ValueError(f"time {t} is not finite")
    sec = math.floor(t)
    # t - sec is exact in binary floating point, so only the last step rounds.
    return int(sec) * _NS_PER_S + round((t - sec) * 1e9)


def stamp_seconds(stamp: Any) -> float:
    return ns_to_seconds(stamp_ns(stamp))


# --- arrays -----------------------------------------------------------------

def _f32(values: Any) -> np.ndarray:
    # np.array (not asarray) copies: records never share the decoder's buffers.
    return np.array(values, dtype=np.float32).reshape(-1)


def _bytes_view(data: Any) -> np.ndarray:
    if isinstance(data, np.ndarray):
        return data.reshape(-1).view(np.uint8)
    if isinstance(data, (bytes, bytearray, memoryview)):
        return np.frombuffer(data, dtype=np.uint8)
    if isinstance(data, str):  # genpy under Python 2 semantics
        return np.frombuffer(data.encode("latin-1"), dtype=np.uint8)
    return np.asarray(data, dtype=np.uint8)


def _vec3(v: Any) -> np.ndarray:
    return np.array([v.x, v.y, v.z], dtype=np.float64)


# --- scans ------------------------------------------------------------------


def scan_from_laserscan(msg: Any, topic: str = "") -> Scan:
    ranges = _f32(msg.ranges)
    intensities = _f32(msg.intensities) if len(msg.intensities) else None
    return _uniform_scan(msg, topic, ranges, intensities, LASER_SCAN)


def scan_from_multiecho(msg: Any, topic: str = "") -> Scan:
    """First echo of every beam (NaN where a beam has none)."""
    nan = math.nan
    ranges = _f32([e.echoes[0] if len(e.echoes) else nan for e in msg.ranges])
    intensities = None
    if any(len(e.echoes) for e in msg.intensities):
        intensities = _f32([e.echoes[0] if len(e.echoes) else nan for e in msg.intensities])
        if intensities.shape != ranges.shape:
            intensities = None
    return _uniform_scan(msg, topic, ranges, intensities, MULTI_ECHO)


def _uniform_scan(msg: Any, topic: str, ranges: np.ndarray, intensities: np.ndarray | None,
                  source_type: str) -> Scan:
    angle_min = float(msg.angle_min)
    angle_increment = float(msg.angle_increment)
    return Scan(
        time=stamp_seconds(msg.header.stamp),
        ranges=ranges,
        angles=beam_angles(angle_min, angle_increment, ranges.shape[0]),
        frame=str(msg.header.frame_id),
        topic=topic,
        range_min=float(msg.range_min),
        range_max=float(msg.range_max),
        angle_min=angle_min,
        angle_increment=angle_increment,
        time_increment=float(msg.time_increment),
        scan_time=float(msg.scan_time),
        intensities=intensities,
        source_type=source_type,
    )


def cloud_xyz(msg: Any, topic: str = "") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """float64 x, y, z of every point of a PointCloud2, whatever its layout."""
    fields = {str(f.name): f for f in msg.fields}
    missing = [n for n in ("x", "y", "z") if n not in fields]
    if missing:
        raise TopicError(f"PointCloud2 on {topic} has no {'/'.join(missing)} field(s); carto needs x, y and z")
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for name in ("x", "y", "z"):
        f = fields[name]
        code = _FLOAT_FIELDS.get(int(f.datatype))
        if code is None:
            raise TopicError(
                f"PointCloud2 on {topic}: field {name} has datatype {int(f.datatype)}; "
                "carto reads FLOAT32 (7) and FLOAT64 (8) coordinates")
        formats.append(order + code)
        offsets.append(int(f.offset))
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    # itemsize covers only x, y, z: the explicit strides below step over any padding,
    # and a last point whose trailing padding was not sent still reads.
    itemsize = max(o + np.dtype(c).itemsize for o, c in zip(offsets, formats))
    empty = np.empty(0, dtype=np.float64)
    if height * width == 0:
        return empty, empty, empty
    if itemsize > point_step or point_step * width > row_step:
        raise TopicError(
            f"PointCloud2 on {topic} is malformed: fields end at byte {itemsize}, "
            f"point_step {point_step}, row_step {row_step}, width {width}")
    data = _bytes_view(msg.data)
    need = (height - 1) * row_step + (width - 1) * point_step + itemsize
    if data.shape[0] < need:
        raise TopicError(
            f"PointCloud2 on {topic} is malformed: {data.shape[0]} data bytes for "
            f"{height}x{width} points of {point_step} bytes")
    dtype = np.dtype({"names": ["x", "y", "z"], "formats": formats, "offsets": offsets, "itemsize": itemsize})
    points = np.ndarray(shape=(height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    points = points.reshape(-1)
    return (points["x"].astype(np.float64), points["y"].astype(np.float64), points["z"].astype(np.float64))


def scan_from_pointcloud2(msg: Any, topic: str = "", options: ReadOptions | None = None) -> Scan:
    """The horizontal slice min_z <= z <= max_z of a cloud, as a scan sorted by bearing."""
    options = options or ReadOptions()
    x, y, z = cloud_xyz(msg, topic)
    keep = np.isfinite(x) & np.isfinite(y) & (z >= options.min_z) & (z <= options.max_z)
    x, y = x[keep], y[keep]
    angles = np.arctan2(y, x)
    order = np.argsort(angles, kind="stable")
    angles = angles[order].astype(np.float32)
    ranges = np.hypot(x[order], y[order]).astype(np.float32)
    return Scan(
        time=stamp_seconds(msg.header.stamp),
        ranges=ranges,
        angles=angles,
        frame=str(msg.header.frame_id),
        topic=topic,
        angle_min=float(angles[0]) if angles.shape[0] else 0.0,
        angle_increment=None,
        source_type=POINT_CLOUD2,
    )


# --- odometry, imu, tf ------------------------------------------------------

def odometry_from_msg(msg: Any, topic: str = "") -> Odometry:
    pose = msg.pose.pose
    q = pose.orientation
    twist = msg.twist.twist
    return Odometry(
        time=stamp_seconds(msg.header.stamp),
        x=float(pose.position.x),
        y=float(pose.position.y),
        yaw=quaternion_yaw(float(q.x), float(q.y), float(q.z), float(q.w)),
        frame=str(msg.header.frame_id),
        child_frame=str(msg.child_frame_id),
        topic=topic,
        vx=float(twist.linear.x),
        vy=float(twist.linear.y),
        wz=float(twist.angular.z),
    )


def imu_from_msg(msg: Any, topic: str = "") -> Imu:
    q = msg.orientation
    # REP 145: orientation_covariance[0] == -1 means "no orientation estimate".
    has_orientation = len(msg.orientation_covariance) == 0 or float(msg.orientation_covariance[0]) != -1.0
    orientation = np.array([q.x, q.y, q.z, q.w], dtype=np.float64) if has_orientation else None
    return Imu(
        time=stamp_seconds(msg.header.stamp),
        angular_velocity=_vec3(msg.angular_velocity),
        linear_acceleration=_vec3(msg.linear_acceleration),
        orientation=orientation,
        frame=str(msg.header.frame_id),
        topic=topic,
    )


def transforms_from_tf(msg: Any, topic: str = "") -> list[Transform]:
    out = []
    for ts in msg.transforms:
        t, r = ts.transform.translation, ts.transform.rotation
        out.append(Transform(
            parent=str(ts.header.frame_id),
            child=str(ts.child_frame_id),
            translation=(float(t.x), float(t.y), float(t.z)),
            rotation=(float(r.x), float(r.y), float(r.z), float(r.w)),
            time=stamp_seconds(ts.header.stamp),
            topic=topic,
        ))
    return out


def merge_static_transforms(transforms: list[Transform]) -> list[Transform]:
    """One transform per (parent, child), the latest recorded, in order of first appearance.

    Latched /tf_static is recorded once per publisher and again after restarts,
    so a bag commonly holds the same transform several times.
    """
    latest: dict[tuple[str, str], Transform] = {}
    for t in transforms:
        latest[(t.parent, t.child)] = t
    return list(latest.values())


# --- dispatch ---------------------------------------------------------------

def is_supported(topic: str, msgtype: str) -> bool:
    """True for the message types ``to_record`` turns into Scan / Odometry / Imu."""
    return kind_of(topic, msgtype) in ("scan", "odometry", "imu")


def is_readable(topic: str, msgtype: str) -> bool:
    """What ``records`` yields when asked for the topic by name: the supported types and dynamic TF (/tf), whose
    transforms carry odometry when a recording has no Odometry topic (``io.tf_odometry``)."""
    return kind_of(topic, msgtype) in ("scan", "odometry", "imu", "tf")


def to_records(msg: Any, msgtype: str, topic: str = "", options: ReadOptions | None = None) -> list[Record]:
    """The records of one decoded message: one for a supported type, one per transform for dynamic TF."""
    if kind_of(topic, msgtype) == "tf":
        return list(transforms_from_tf(msg, topic))
    return [to_record(msg, msgtype, topic, options)]


def to_record(msg: Any, msgtype: str, topic: str = "", options: ReadOptions | None = None) -> Record:
    """The record for one decoded message of a supported type (see ``is_supported``)."""
    t = normalise_type(msgtype)
    if t == LASER_SCAN:
        return scan_from_laserscan(msg, topic)
    if t == MULTI_ECHO:
        return scan_from_multiecho(msg, topic)
    if t == POINT_CLOUD2:
        return scan_from_pointcloud2(msg, topic, options)
    if t == "nav_msgs/msg/Odometry":
        return odometry_from_msg(msg, topic)
    if t == "sensor_msgs/msg/Imu":
        return imu_from_msg(msg, topic)
    raise TopicError(f"topic {topic} has type {t}, which carto does not read as scans, odometry or IMU")
