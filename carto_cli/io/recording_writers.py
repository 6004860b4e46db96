"""Write records as ROS1 bags, ROS2 bags (sqlite3 or mcap storage) or standalone MCAP: `carto convert`.

Scans with evenly spaced beams become sensor_msgs/LaserScan, other scans
PointCloud2 (float32 x, y, z=0); 3D clouds (``Cloud``, a simulated 3D lidar's) PointCloud2 with x, y, z and a
per-point time field as drivers write it; odometry nav_msgs/Odometry; IMU sensor_msgs/Imu;
static transforms one tf2_msgs/TFMessage on /tf_static. A message's bag/log
time is its record's time, so readers that order by bag time and readers that
use header stamps agree (a 3D cloud, stamped at its sweep's start, is logged at its end).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import itertools
import os
import shutil
import tempfile
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from carto_cli.core.errors import CartoError
from carto_cli.core.records import Cloud, Imu, Odometry, Record, Scan, Transform, yaw_quaternion
from carto_cli.io.recording import normalise_type
from carto_cli.io.sources.messages import seconds_to_ns

FORMATS = ("ros1", "ros2-sqlite3", "ros2-mcap", "mcap")

LASER_SCAN = "sensor_msgs/msg/LaserScan"
POINT_CLOUD2 = "sensor_msgs/msg/PointCloud2"
ODOMETRY = "nav_msgs/msg/Odometry"
IMU = "sensor_msgs/msg/Imu"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
TF_STATIC = "/tf_static"

DEFAULT_TOPICS = {Scan: "/scan", Odometry: "/odom", Imu: "/imu"}
# Per-point time fields drivers write as uint32 nanoseconds (Ouster's t, Livox's offset_time); others float32 s.
_INTEGER_TIME_FIELDS = ("t", "offset_time")

# What a topic of a source type is written as.
_OUTPUT_TYPE = {
    "sensor_msgs/msg/LaserScan": LASER_SCAN,
    "sensor_msgs/msg/MultiEchoLaserScan": LASER_SCAN,  # its first echo is what carto read
    "sensor_msgs/msg/PointCloud2": POINT_CLOUD2,
    "nav_msgs/msg/Odometry": ODOMETRY,
    "sensor_msgs/msg/Imu": IMU,
}


def format_for_output(path: Path, explicit: str | None = None) -> str:
    """The output format: ``explicit`` when given, else from the suffix (.bag, .mcap, none = ROS2 directory)."""
    if explicit is not None:
        fmt = explicit.strip().lower()
        if fmt not in FORMATS:
            raise CartoError(f"unknown output format {explicit!r} (choose one of {', '.join(FORMATS)})")
        return fmt
    suffix = Path(path).suffix.lower()
    if suffix == ".bag":
        return "ros1"
    if suffix == ".mcap":
        return "mcap"
    if suffix == "":
        return "ros2-sqlite3"
    raise CartoError(
        f"cannot tell the output format from the suffix {suffix!r}: name it .bag (ROS1), .mcap (MCAP) "
        "or without a suffix (ROS2 bag directory), or pass --format", path)


def write_recording(
    records: Iterable[Record | Cloud],
    out: Path,
    fmt: str,
    *,
    static_transforms: Sequence[Transform] = (),
    topics: dict[str, str] | None = None,
    on_record: Callable[[], None] | None = None,
    overwrite: bool = False,
) -> int:
    """Write ``records`` (in time order) to ``out``; returns the number of messages written.

    ``topics`` maps topic names to their source message types: those topics are
    created even when no record arrives for them, and a PointCloud2 source stays
    a PointCloud2. ``on_record()`` is called after each record is written.
    The output appears only when everything was written: an exception (from
    the records, the callback or the disk) leaves nothing at ``out``.
    """
    if fmt not in FORMATS:
        raise CartoError(f"unknown output format {fmt!r} (choose one of {', '.join(FORMATS)})")
    with _staged(out, overwrite) as staged:
        return _write(records, staged, fmt, static_transforms, topics, on_record)


@contextlib.contextmanager
def _staged(out: str | Path, overwrite: bool) -> Iterator[Path]:
    """A path to build ``out`` at, in a hidden sibling directory, moved into place when the block ends without
    an exception; refused up front when ``out`` exists and not ``overwrite``."""
    out = Path(out)
    if (out.exists() or out.is_symlink()) and not overwrite:
        raise CartoError("already exists (use --force to replace it)", out)
    parent = out.parent if str(out.parent) else Path(".")
    if not parent.is_dir():
        raise CartoError(f"directory {parent} does not exist", out)
    try:
        tmpdir = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".partial", dir=parent))
    except OSError as e:
        raise CartoError(f"cannot write here: {e.strerror}", out) from e
    try:
        # The output is built under its final name inside a hidden sibling directory:
        # a ROS2 bag names its storage file after its directory.
        staged = tmpdir / out.name
        yield staged
        _move_into_place(staged, out, tmpdir, overwrite)
    except OSError as e:
        raise CartoError(f"cannot write: {e.strerror or e}", out) from e
    finally:
        shutil.rmtree(tmpdir, ignore_errors=True)


def convert_bag(source: Path | Sequence[Path], out: Path, fmt: str, *, overwrite: bool = False) -> None:
    """A ROS1 bag to a ROS2 bag or back through rosbags' own converter: every topic and message as recorded,
    stamps exact (carto's writer carries only what carto reads). ``source``: the bag, or the storage files to
    read (a ROS2 bag without its metadata.yaml). ``fmt``: 'ros1', 'ros2-sqlite3' or 'ros2-mcap'. Staged and
    moved into place like :func:`write_recording`."""
    from rosbags.convert import ConverterError, convert
    from rosbags.rosbag2 import Writer

    with _staged(out, overwrite) as staged:
        storage = "mcap" if fmt == "ros2-mcap" else "sqlite3"
        try:
            sources = [Path(source)] if isinstance(source, (str, Path)) else [Path(p) for p in source]
            convert(sources, staged, storage, Writer.VERSION_LATEST, None, "file", None, None, [], [], [], [])
        except ConverterError as e:
            raise CartoError(f"cannot convert: {e}", sources[0]) from None


def repair_bag(source, out: Path, fmt: str, *, overwrite: bool = False,
               on_record: Callable[[], None] | None = None) -> int:
    """A ROS1 bag read without its index (``io.sources.ros1_salvage.SalvagedBag``) written again whole: every
    recovered message's bytes, connection and time as recorded, with a fresh index (what ``rosbag reindex``
    gives); for a ROS2 ``fmt`` that bag then goes through :func:`convert_bag`. Returns the messages written."""
    from rosbags.rosbag1 import Writer

    n = 0
    with _staged(out, overwrite) as staged:
        bag = staged if fmt == "ros1" else staged.parent / "repaired.bag"
        writer = Writer(bag)
        writer.open()
        try:
            conns = {k: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef, md5sum=c.md5sum,
                                              callerid=c.callerid, latching=c.latching)
                     for k, c in source.connections.items()}
            for conn, time_ns, raw in source.raw_messages():
                writer.write(conns[conn], time_ns, raw)
                n += 1
                if on_record is not None:
                    on_record()
        finally:
            writer.close()
        if fmt != "ros1":
            convert_bag(bag, staged, fmt)
    return n


def _move_into_place(staged: Path, out: Path, tmpdir: Path, overwrite: bool) -> None:
    if not (out.exists() or out.is_symlink()):
        os.rename(staged, out)
        return
    if not overwrite:
        raise CartoError("already exists (use --force to replace it)", out)
    if staged.is_file() and out.is_file() and not out.is_symlink():
        os.replace(staged, out)
        return
    # Directories cannot be swapped atomically: move the old one aside, put the new one
    # in, and put the old one back if that fails; tmpdir's cleanup deletes it otherwise.
    old = tmpdir / ".replaced"
    os.rename(out, old)
    try:
        os.rename(staged, out)
    except BaseException:
        os.rename(old, out)
        raise


# --- the writing loop --------------------------------------------------------

def _write(records, path, fmt, static_transforms, topics, on_record) -> int:
    it = iter(records)
    first = next(it, None)
    static_transforms = list(static_transforms)
    if first is not None:
        tf_time = first.time
    else:
        tf_time = min((t.time for t in static_transforms), default=0.0)

    sink = _open_sink(fmt, path)
    try:
        build = _Builder(sink.typestore)
        channels = _Channels(sink)
        declared = [(name, _OUTPUT_TYPE.get(normalise_type(kind))) for name, kind in (topics or {}).items()]
        # rosbags reads a ROS1 bag's messages of one stamp in the order of their connections, not as written: the
        # scans' connections last keep an odometry pose stamped with its scan (CARMEN's) ahead of it, as written.
        for name, out_type in sorted(declared, key=lambda d: d[1] in (LASER_SCAN, POINT_CLOUD2)):
            if out_type is not None:
                channels.get(name, out_type)
        n = 0
        if static_transforms:
            ns = _ns(tf_time)
            sink.write(channels.get(TF_STATIC, TF_MESSAGE), ns, build.tf(static_transforms))
            n += 1
        for rec in itertools.chain(() if first is None else (first,), it):
            topic, msgtype, msg = build.message(rec, channels)
            sink.write(channels.get(topic, msgtype), _ns(_log_time(rec)), msg)
            n += 1
            if on_record is not None:
                on_record()
        sink.close()
    except BaseException:
        sink.abort()
        raise
    return n


def _log_time(rec: Record | Cloud) -> float:
    """When a record is logged: its time, but a cloud's once its last point is measured, when a driver can
    publish it (its stamp is often the sweep's start); so a reader in log order has the odometry and IMU of the
    whole sweep before the sweep, as from a real recording."""
    if isinstance(rec, Cloud) and rec.point_times is not None and len(rec.point_times):
        return rec.time + max(float(np.max(rec.point_times)), 0.0)
    return rec.time


def _ns(t: float) -> int:
    try:
        ns = seconds_to_ns(t)
    except ValueError:
        raise CartoError(f"record time {t} cannot be written") from None
    if not 0 <= ns < 2**63:
        raise CartoError(f"record time {t} s is outside what ROS bags store (1970 to 2262)")
    return ns


class _Channels:
    """One connection per topic, of the type its first use decides."""

    def __init__(self, sink):
        self._sink = sink
        self._by_topic: dict[str, tuple[str, object]] = {}

    def type_of(self, topic: str) -> str | None:
        entry = self._by_topic.get(topic)
        return entry[0] if entry else None

    def get(self, topic: str, msgtype: str):
        entry = self._by_topic.get(topic)
        if entry is None:
            entry = (msgtype, self._sink.add(topic, msgtype))
            self._by_topic[topic] = entry
        elif entry[0] != msgtype:
            raise CartoError(f"topic {topic} would carry both {entry[0]} and {msgtype} messages")
        return entry[1]


class _Builder:
    """Typestore message objects for records, serialised by the sink."""

    def __init__(self, typestore):
        self.ts = typestore
        T = typestore.types
        self.T = T
        self._header_has_seq = "seq" in {f.name for f in dataclasses.fields(T["std_msgs/msg/Header"])}
        self._seq: dict[str, int] = {}
        self._zeros9 = np.zeros(9, dtype=np.float64)
        self._zeros36 = np.zeros(36, dtype=np.float64)
        self._no_orientation = np.zeros(9, dtype=np.float64)
        self._no_orientation[0] = -1.0  # REP 145

    def header(self, t: float, frame: str, topic: str = ""):
        ns = _ns(t)
        stamp = self.T["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
        if self._header_has_seq:
            seq = self._seq.get(topic, 0)
            self._seq[topic] = seq + 1
            return self.T["std_msgs/msg/Header"](seq=seq & 0xFFFFFFFF, stamp=stamp, frame_id=frame)
        return self.T["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)

    def message(self, rec: Record | Cloud, channels: _Channels):
        if isinstance(rec, Cloud):
            topic = rec.topic or DEFAULT_TOPICS[Scan]
            return topic, POINT_CLOUD2, self.cloud(rec, topic)
        if isinstance(rec, Scan):
            topic = rec.topic or DEFAULT_TOPICS[Scan]
            declared = channels.type_of(topic)
            if declared == POINT_CLOUD2 or (declared is None and rec.angle_increment is None):
                return topic, POINT_CLOUD2, self.point_cloud(rec, topic)
            if rec.angle_increment is None:
                raise CartoError(f"a scan on {topic} has no even beam spacing and cannot be written as a LaserScan")
            return topic, LASER_SCAN, self.laser_scan(rec, topic)
        if isinstance(rec, Odometry):
            topic = rec.topic or DEFAULT_TOPICS[Odometry]
            return topic, ODOMETRY, self.odometry(rec, topic)
        if isinstance(rec, Imu):
            topic = rec.topic or DEFAULT_TOPICS[Imu]
            return topic, IMU, self.imu(rec, topic)
        if isinstance(rec, Transform):
            return rec.topic or TF_STATIC, TF_MESSAGE, self.tf([rec])
        raise CartoError(f"cannot write a {type(rec).__name__} record")

    def laser_scan(self, s: Scan, topic: str):
        n = s.num_beams
        angle_max = float(s.angles[-1]) if n else s.angle_min
        intensities = s.intensities if s.intensities is not None else np.empty(0, dtype=np.float32)
        return self.T[LASER_SCAN](
            header=self.header(s.time, s.frame, topic),
            angle_min=s.angle_min,
            angle_max=angle_max,
            angle_increment=s.angle_increment,
            time_increment=s.time_increment,
            scan_time=s.scan_time,
            range_min=s.range_min,
            range_max=s.range_max,
            ranges=np.ascontiguousarray(s.ranges, dtype=np.float32),
            intensities=np.ascontiguousarray(intensities, dtype=np.float32),
        )

    def point_cloud(self, s: Scan, topic: str):
        r = s.ranges.astype(np.float64)
        a = s.angles.astype(np.float64)
        xyz = np.column_stack([r * np.cos(a), r * np.sin(a), np.zeros(s.num_beams)]).astype(np.float32)
        # A flattened 3D sweep keeps its points' times (Velodyne's 'time' field: float32 s after the stamp), so
        # that the converted recording is de-skewed as the original was.
        return self.cloud(Cloud(s.time, xyz, s.frame, topic, s.point_times, "time"), topic)

    def cloud(self, c: Cloud, topic: str):
        n = int(c.points.shape[0])
        formats, names = ["<f4", "<f4", "<f4"], ["x", "y", "z"]
        datatypes = [7, 7, 7]  # FLOAT32
        if c.point_times is not None:
            float_time = c.time_field not in _INTEGER_TIME_FIELDS
            formats.append("<f4" if float_time else "<u4")
            names.append(c.time_field)
            datatypes.append(7 if float_time else 6)  # FLOAT32 s, or UINT32 ns
        dtype = np.dtype({"names": names, "formats": formats})
        rows = np.zeros(n, dtype=dtype)
        for k, name in enumerate("xyz"):
            rows[name] = c.points[:, k]
        if c.point_times is not None:
            times = np.asarray(c.point_times, dtype=np.float64)
            if c.time_field in _INTEGER_TIME_FIELDS:
                if n and float(times.min()) < 0.0:
                    raise CartoError(f"a cloud on {topic} has points before its stamp, which {c.time_field} "
                                     "(unsigned nanoseconds) cannot hold")
                rows[c.time_field] = np.round(times * 1e9).astype(np.uint32)
            else:
                rows[c.time_field] = times
        field = self.T["sensor_msgs/msg/PointField"]
        offsets = [4 * k for k in range(len(names))]  # every column is 4 bytes, packed
        fields = [field(name=name, offset=o, datatype=d, count=1) for name, o, d in zip(names, offsets, datatypes)]
        return self.T[POINT_CLOUD2](
            header=self.header(c.time, c.frame, topic),
            height=1,
            width=n,
            fields=fields,
            is_bigendian=False,
            point_step=dtype.itemsize,
            row_step=dtype.itemsize * n,
            data=np.frombuffer(rows.tobytes(), dtype=np.uint8),
            is_dense=bool(np.isfinite(c.points).all()),
        )

    def _point(self, x, y, z):
        return self.T["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z))

    def _vector(self, v):
        return self.T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))

    def _quaternion(self, q):
        return self.T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))

    def odometry(self, o: Odometry, topic: str):
        T = self.T
        pose = T["geometry_msgs/msg/Pose"](position=self._point(o.x, o.y, 0.0),
                                            orientation=self._quaternion(yaw_quaternion(o.yaw)))
        twist = T["geometry_msgs/msg/Twist"](linear=self._vector((o.vx, o.vy, 0.0)),
                                              angular=self._vector((0.0, 0.0, o.wz)))
        return T[ODOMETRY](
            header=self.header(o.time, o.frame, topic),
            child_frame_id=o.child_frame,
            pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=self._zeros36),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=self._zeros36),
        )

    def imu(self, m: Imu, topic: str):
        has_q = m.orientation is not None
        return self.T[IMU](
            header=self.header(m.time, m.frame, topic),
            orientation=self._quaternion(m.orientation if has_q else (0.0, 0.0, 0.0, 1.0)),
            orientation_covariance=self._zeros9 if has_q else self._no_orientation,
            angular_velocity=self._vector(m.angular_velocity),
            angular_velocity_covariance=self._zeros9,
            linear_acceleration=self._vector(m.linear_acceleration),
            linear_acceleration_covariance=self._zeros9,
        )

    def tf(self, transforms: Sequence[Transform]):
        T = self.T
        stamped = [
            T["geometry_msgs/msg/TransformStamped"](
                header=self.header(t.time, t.parent, TF_STATIC),
                child_frame_id=t.child,
                transform=T["geometry_msgs/msg/Transform"](translation=self._vector(t.translation),
                                                          rotation=self._quaternion(t.rotation)),
            )
            for t in transforms
        ]
        return T[TF_MESSAGE](transforms=stamped)


# --- sinks: one per output format ----------------------------------------------

def _open_sink(fmt: str, path: Path):
    if fmt == "ros1":
        return _Ros1Sink(path)
    if fmt == "mcap":
        return _McapSink(path)
    return _Ros2Sink(path, storage=fmt.split("-", 1)[1])


@functools.cache
def _ros1_typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    # rosbags' noetic store lacks tf2_msgs; this is its noetic definition (md5 9481...7eec).
    ts.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", TF_MESSAGE))
    return ts


# Cached: rosbags compiles (de)serialisers per typestore instance, which costs more
# than writing a small bag; the stores are never modified after this.
@functools.cache
def _ros2_typestore():
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_HUMBLE)


class _Ros1Sink:
    def __init__(self, path: Path):
        from rosbags.rosbag1 import Writer

        self.typestore = _ros1_typestore()
        self._writer = Writer(path)
        self._writer.open()

    def add(self, topic: str, msgtype: str):
        # /tf_static is latched in ROS1: players re-deliver it to late subscribers.
        latching = 1 if topic == TF_STATIC else None
        return (self._writer.add_connection(topic, msgtype, typestore=self.typestore, latching=latching), msgtype)

    def write(self, handle, ns: int, msg) -> None:
        conn, msgtype = handle
        self._writer.write(conn, ns, self.typestore.serialize_ros1(msg, msgtype))

    def close(self) -> None:
        self._writer.close()

    def abort(self) -> None:
        try:
            self._writer.close()
        except Exception:
            pass


class _Ros2Sink:
    def __init__(self, path: Path, storage: str):
        from rosbags.rosbag2 import StoragePlugin, Writer

        self.typestore = _ros2_typestore()
        plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
        self._writer = Writer(path, version=Writer.VERSION_LATEST, storage_plugin=plugin)
        self._writer.open()

    def add(self, topic: str, msgtype: str):
        qos = [_static_qos()] if topic == TF_STATIC else ()
        return (self._writer.add_connection(topic, msgtype, typestore=self.typestore, offered_qos_profiles=qos),
                msgtype)

    def write(self, handle, ns: int, msg) -> None:
        conn, msgtype = handle
        self._writer.write(conn, ns, self.typestore.serialize_cdr(msg, msgtype))

    def close(self) -> None:
        self._writer.close()

    def abort(self) -> None:
        try:
            self._writer.close()
        except Exception:
            pass


def _static_qos():
    """Transient-local, as tf2's static broadcaster offers it, so `ros2 bag play` latches /tf_static."""
    from rosbags.interfaces import Qos, QosDurability, QosHistory, QosLiveliness, QosReliability, QosTime

    zero = QosTime(sec=0, nsec=0)
    return Qos(history=QosHistory.KEEP_LAST, depth=1, reliability=QosReliability.RELIABLE,
               durability=QosDurability.TRANSIENT_LOCAL, deadline=zero, lifespan=zero,
               liveliness=QosLiveliness.AUTOMATIC, liveliness_lease_duration=zero,
               avoid_ros_namespace_conventions=False)


class _McapSink:
    """Standalone MCAP with the ros2 profile: ros2msg schemas, cdr messages."""

    def __init__(self, path: Path):
        from mcap.writer import CompressionType, Writer

        self.typestore = _ros2_typestore()
        self._file = open(path, "wb")
        try:
            self._writer = Writer(self._file, compression=CompressionType.ZSTD)
            self._writer.start(profile="ros2", library="carto")
        except BaseException:
            self._file.close()
            raise
        self._schemas: dict[str, int] = {}
        self._seq: dict[int, int] = {}

    def add(self, topic: str, msgtype: str):
        schema_id = self._schemas.get(msgtype)
        if schema_id is None:
            text, _ = self.typestore.generate_msgdef(msgtype, ros_version=2)
            schema_id = self._writer.register_schema(name=msgtype, encoding="ros2msg", data=text.encode())
            self._schemas[msgtype] = schema_id
        channel_id = self._writer.register_channel(topic=topic, message_encoding="cdr", schema_id=schema_id)
        return (channel_id, msgtype)

    def write(self, handle, ns: int, msg) -> None:
        channel_id, msgtype = handle
        seq = self._seq.get(channel_id, 0)
        self._seq[channel_id] = seq + 1
        self._writer.add_message(channel_id=channel_id, log_time=ns, publish_time=ns, sequence=seq & 0xFFFFFFFF,
                                 data=self.typestore.serialize_cdr(msg, msgtype))

    def close(self) -> None:
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def abort(self) -> None:
        self._file.close()
