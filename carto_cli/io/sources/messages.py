"""Decoded ROS messages -> records.

Every reader decodes through rosbags (numpy arrays, ``sec/nanosec`` stamps),
but this works on any object with the ROS field names: sequences as lists,
tuples or bytes, stamps spelled ``secs/nsecs`` as ROS1's Python classes do.
"""
from __future__ import annotations

import math
from operator import attrgetter
from typing import Any

import numpy as np

from carto_cli.core.errors import CartoError, TopicError
from carto_cli.core.parse import height_band
from carto_cli.core.records import Imu, Odometry, Record, Scan, Transform, beam_angles, quaternion_yaw
from carto_cli.io.recording import ReadOptions, kind_of, normalise_type
from carto_cli.sensor.height_band import (
    MIN_POINTS,
    HeightBand,
    auto_band,
    given_band,
    nearest_per_bearing,
    sensor_band,
)

LASER_SCAN = "sensor_msgs/msg/LaserScan"
MULTI_ECHO = "sensor_msgs/msg/MultiEchoLaserScan"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
LIVOX_TYPES = ("livox_ros_driver/msg/CustomMsg", "livox_ros_driver2/msg/CustomMsg")

# sensor_msgs/PointField datatypes carto accepts for x, y and z.
_FLOAT_FIELDS = {7: "f4", 8: "f8"}  # FLOAT32, FLOAT64
# Every sensor_msgs/PointField datatype, INT8 (1) to FLOAT64 (8).
_POINT_FIELDS = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
# A cloud's per-point time, by the names drivers give it (Ouster, Velodyne, Livox, Hesai / Robosense).
TIME_FIELDS = ("t", "time", "offset_time", "timestamp")
_MAX_SWEEP = 10.0  # s: no lidar takes longer over one cloud, so a wider float time field counts nanoseconds
_ABSOLUTE = 86400.0  # s: a per-point time further than a day from the stamp is a time of day, not an offset
_NS_PER_S = 1_000_000_000


# --- time -------------------------------------------------------------------

def stamp_ns(stamp: Any) -> int:
    """Integer nanoseconds of a ROS time (``sec/nanosec``, or ROS1 Python's ``secs/nsecs``)."""
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
    columns = cloud_columns(msg, topic, ("x", "y", "z"))
    return columns["x"], columns["y"], columns["z"]


def cloud_columns(msg: Any, topic: str, names: tuple[str, ...],
                  optional: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """float64 columns of a PointCloud2's fields: every one of ``names`` (x, y and z must be float), and those of
    ``optional`` that the cloud has (of any PointField datatype)."""
    fields = {str(f.name): f for f in msg.fields}
    missing = [n for n in names if n not in fields]
    if missing:
        raise TopicError(f"PointCloud2 on {topic} has no {'/'.join(missing)} field(s); carto needs x, y and z")
    wanted = list(names) + [n for n in optional if n in fields and n not in names]
    order = ">" if msg.is_bigendian else "<"
    formats, offsets = [], []
    for name in wanted:
        f = fields[name]
        table = _FLOAT_FIELDS if name in ("x", "y", "z") else _POINT_FIELDS
        code = table.get(int(f.datatype))
        if code is None:
            if name in ("x", "y", "z"):
                raise TopicError(
                    f"PointCloud2 on {topic}: field {name} has datatype {int(f.datatype)}; "
                    "carto reads FLOAT32 (7) and FLOAT64 (8) coordinates")
            raise TopicError(f"PointCloud2 on {topic}: field {name} has datatype {int(f.datatype)}, "
                             "which is no sensor_msgs/PointField type (1 to 8)")
        formats.append(order + code)
        offsets.append(int(f.offset))
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    # itemsize covers only the fields read: the explicit strides below step over any padding,
    # and a last point whose trailing padding was not sent still reads.
    itemsize = max(o + np.dtype(c).itemsize for o, c in zip(offsets, formats))
    if height * width == 0:
        return {n: np.empty(0, dtype=np.float64) for n in wanted}
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
    dtype = np.dtype({"names": wanted, "formats": formats, "offsets": offsets, "itemsize": itemsize})
    points = np.ndarray(shape=(height, width), dtype=dtype, buffer=data, strides=(row_step, point_step))
    points = points.reshape(-1)
    return {n: points[n].astype(np.float64) for n in wanted}


def point_times(values: np.ndarray, integer: bool, stamp: float) -> np.ndarray:
    """Seconds after the header stamp of a cloud's per-point time field.

    Drivers differ: Ouster's ``t`` is uint32 ns since the scan's start, Livox's ``offset_time`` uint32 ns after
    the stamp, Velodyne's ``time`` float32 s relative to the stamp (negative where the stamp is the sweep's end),
    Hesai's and Robosense's ``timestamp`` float64 absolute s, the old Ouster OS1's ``t`` float ns. So: integers are
    nanoseconds; floats are seconds unless they span more than any sweep lasts, then nanoseconds; times further
    from zero than a day are absolute."""
    t = values * 1e-9 if integer else values
    if not integer and t.shape[0] and float(np.ptp(t)) > _MAX_SWEEP:
        t = t * 1e-9
    if t.shape[0] and abs(float(np.median(t))) > _ABSOLUTE:
        t = t - stamp
    return t


def livox_columns(msg: Any) -> dict[str, np.ndarray]:
    """float64 x, y, z and ``offset_time`` (integer nanoseconds after the header's stamp) of a Livox CustomMsg.

    Its points arrive as objects (the decoder's per-point work is done already); ``map`` with ``attrgetter`` walks
    them in C. A point's ``offset_time`` counts from ``timebase`` (its first point's time), which the driver also
    stamps the header with; any difference between the two is added."""
    points = msg.points
    n = len(points)

    def column(name: str) -> np.ndarray:
        return np.fromiter(map(attrgetter(name), points), dtype=np.float64, count=n)

    base = int(msg.timebase) - stamp_ns(msg.header.stamp)
    return {"x": column("x"), "y": column("y"), "z": column("z"), "offset_time": column("offset_time") + base}


def cloud_scan(msg: Any, topic: str, band: HeightBand, columns: dict[str, np.ndarray] | None = None, *,
               integer_times: bool | None = None) -> Scan:
    """The points of a cloud that ``band`` keeps, as a scan sorted by bearing, with per-point times when the cloud
    has a time field (``integer_times``: whether it counts nanoseconds; None: as its PointField says)."""
    if columns is None:
        columns = cloud_columns(msg, topic, ("x", "y", "z"), TIME_FIELDS)
    x, y, z = columns["x"], columns["y"], columns["z"]
    keep = np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & band.keep(z)
    # Ouster and others publish organised clouds with (0, 0, 0) where a beam had no return.
    keep &= (x != 0.0) | (y != 0.0) | (z != 0.0)
    x, y = x[keep], y[keep]
    angles = np.arctan2(y, x)
    order = np.argsort(angles, kind="stable")
    if band.bearing_step is not None:
        order = order[nearest_per_bearing(angles[order], np.hypot(x[order], y[order]), band.bearing_step)]
    angles = angles[order].astype(np.float32)
    ranges = np.hypot(x[order], y[order]).astype(np.float32)
    stamp = stamp_seconds(msg.header.stamp)
    times = None
    field = next((n for n in TIME_FIELDS if n in columns), None)
    if field is not None:
        if integer_times is None:
            integer_times = next(int(f.datatype) for f in msg.fields if str(f.name) == field) not in (7, 8)
        times = point_times(columns[field][keep][order], integer_times, stamp)
    return Scan(
        time=stamp,
        ranges=ranges,
        angles=angles,
        frame=str(msg.header.frame_id),
        topic=topic,
        angle_min=float(angles[0]) if angles.shape[0] else 0.0,
        angle_increment=None,
        source_type=POINT_CLOUD2,
        point_times=times,
    )


def scan_from_pointcloud2(msg: Any, topic: str = "", options: ReadOptions | None = None) -> Scan:
    """The horizontal slice min_z <= z <= max_z (sensor frame) of a cloud, as a scan sorted by bearing: how a cloud
    reads without the floor-relative band of a ``Decoder``."""
    options = options or ReadOptions()
    return cloud_scan(msg, topic, sensor_band(options.min_z, options.max_z))


class Decoder:
    """Messages -> records for one pass over a recording: a cloud topic's band is chosen from its first cloud and
    kept for the rest of the pass (a band that moved from sweep to sweep would move the walls with it), and told
    to ``bands`` (the recording's, which `carto info` reports)."""

    def __init__(self, options: ReadOptions | None = None, bands: dict[str, HeightBand] | None = None):
        self.options = options or ReadOptions()
        self.bands: dict[str, HeightBand] = {} if bands is None else bands
        self._chosen: dict[str, HeightBand] = {}

    def to_records(self, msg: Any, msgtype: str, topic: str = "") -> list[Record]:
        t = normalise_type(msgtype)
        if t == POINT_CLOUD2:
            return [self.cloud(msg, topic)]
        if t in LIVOX_TYPES:
            return [self.cloud(msg, topic, livox_columns(msg))]
        return to_records(msg, msgtype, topic, self.options)

    def cloud(self, msg: Any, topic: str, columns: dict[str, np.ndarray] | None = None) -> Scan:
        livox = columns is not None
        if columns is None:
            columns = cloud_columns(msg, topic, ("x", "y", "z"), TIME_FIELDS)
        band = self._chosen.get(topic)
        if band is None:
            band = self._choose(columns)
            self.bands[topic] = band
            # A cloud too sparse to tell anything (a driver's first, half-filled message) is read in the fallback
            # slice and the choice is left to the next one.
            if int(np.isfinite(columns["z"]).sum()) >= MIN_POINTS or band.how in ("sensor", "given"):
                self._chosen[topic] = band
        return cloud_scan(msg, topic, band, columns, integer_times=True if livox else None)

    def _choose(self, columns: dict[str, np.ndarray]) -> HeightBand:
        options = self.options
        sensor = sensor_band(options.min_z, options.max_z)
        mode = options.cloud_band.strip().lower()
        if mode == "sensor":
            return sensor
        x, y, z = columns["x"], columns["y"], columns["z"]
        finite = np.isfinite(x) & np.isfinite(y) & np.isfinite(z) & ((x != 0.0) | (y != 0.0) | (z != 0.0))
        try:
            given = height_band(mode)
        except ValueError as e:
            raise CartoError(f"trajectory_builder_2d.cloud_band: {e}") from None
        if given is None:
            return auto_band(x[finite], y[finite], z[finite], sensor)
        return given_band(x[finite], y[finite], z[finite], given, sensor)


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
    if t in LIVOX_TYPES:
        options = options or ReadOptions()
        return cloud_scan(msg, topic, sensor_band(options.min_z, options.max_z), livox_columns(msg),
                          integer_times=True)
    if t == "nav_msgs/msg/Odometry":
        return odometry_from_msg(msg, topic)
    if t == "sensor_msgs/msg/Imu":
        return imu_from_msg(msg, topic)
    raise TopicError(f"topic {topic} has type {t}, which carto does not read as scans, odometry or IMU")
