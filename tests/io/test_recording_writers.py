"""carto_cli.io.recording_writers: the four output formats, round trips, atomic output."""
import dataclasses
import math
import os
import sqlite3

import numpy as np
import pytest

from carto_cli.core.errors import CartoError, FormatError
from carto_cli.core.records import Imu, Odometry, Scan, Transform
from carto_cli.io.recording_writers import format_for_output, write_recording
from carto_cli.io.sources.mcap import McapRecording
from carto_cli.io.sources.rosbag import RosbagRecording

FORMATS = {"ros1": "out.bag", "ros2-sqlite3": "out_db3", "ros2-mcap": "out_mcap", "mcap": "out.mcap"}
TOPIC_TYPES = {"/scan": "sensor_msgs/msg/LaserScan", "/front/scan": "sensor_msgs/msg/LaserScan",
               "/odom": "nav_msgs/msg/Odometry", "/imu": "sensor_msgs/msg/Imu"}
STATIC = [
    Transform("base_link", "laser", (0.2, 0.0, 0.3), (0.0, 0.0, math.sin(0.05), math.cos(0.05))),
    Transform("base_link", "front_laser", (0.4, 0.1, 0.2), (0.0, 0.0, 0.0, 1.0), time=1_700_000_000.0),
]


def t_of(ns: int) -> float:
    """Record times on the nanosecond grid, as every ROS format stores them."""
    return ns / 1_000_000_000


def make_records(n_scans: int = 6, beams: int = 40, seed: int = 3) -> list:
    """Two scan topics, odometry and IMU interleaved in time; NaN/Inf ranges, intensities on one topic."""
    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000_123_456_789
    inc = np.float32(2 * math.pi / beams)
    out = []
    for i in range(n_scans):
        ranges = rng.uniform(0.2, 12.0, beams).astype(np.float32)
        ranges[rng.integers(0, beams, 2)] = np.nan
        ranges[rng.integers(0, beams, 2)] = np.inf
        angle_min = float(np.float32(-math.pi))
        angles = np.float32(angle_min) + np.arange(beams, dtype=np.float32) * inc
        out.append(Scan(time=t_of(t0 + i * 100_000_000), ranges=ranges, angles=angles, frame="laser", topic="/scan",
                        range_min=0.1, range_max=30.0, angle_min=angle_min, angle_increment=float(inc),
                        time_increment=1e-5, scan_time=0.1))
        front = rng.uniform(0.5, 4.0, beams // 2).astype(np.float32)
        out.append(Scan(time=t_of(t0 + i * 100_000_000 + 33_333_333), ranges=front,
                        angles=np.float32(-1.0) + np.arange(beams // 2, dtype=np.float32) * np.float32(0.05),
                        frame="front_laser", topic="/front/scan", range_min=0.05, range_max=math.inf,
                        angle_min=-1.0, angle_increment=float(np.float32(0.05)),
                        intensities=rng.uniform(0, 1000, beams // 2).astype(np.float32)))
        for k in range(4):
            tk = t0 + i * 100_000_000 + k * 25_000_000 + 1_000_001
            out.append(Odometry(time=t_of(tk), x=0.1 * i + 0.01 * k, y=-0.02 * i, yaw=math.remainder(0.7 * i + k, 2 * math.pi),
                                frame="odom", child_frame="base_link", topic="/odom", vx=0.4, vy=-0.01, wz=0.25))
        for k in range(5):
            tk = t0 + i * 100_000_000 + k * 20_000_000 + 500_003
            q = None if k == 3 else np.array([0.0, 0.0, math.sin(0.1 * i), math.cos(0.1 * i)])
            out.append(Imu(time=t_of(tk), angular_velocity=np.array([0.01, -0.02, 0.25]),
                           linear_acceleration=np.array([0.3, 0.0, 9.81]), orientation=q, frame="imu_link",
                           topic="/imu"))
    out.sort(key=lambda r: r.time)
    return out


def open_any(path, fmt, **kw):
    return McapRecording(path, **kw) if fmt == "mcap" else RosbagRecording(path, **kw)


def same_record(a, b) -> bool:
    if type(a) is not type(b) or a.topic != b.topic:
        return False
    if isinstance(a, Odometry):
        return abs(a.yaw - b.yaw) < 1e-12 and dataclasses.replace(a, yaw=0.0) == dataclasses.replace(b, yaw=0.0)
    if isinstance(a, Scan):
        return (a.same_as(b) and a.angle_increment == b.angle_increment and a.angle_min == b.angle_min
                and np.float32(a.scan_time) == np.float32(b.scan_time)
                and np.float32(a.time_increment) == np.float32(b.time_increment))
    return a.same_as(b)


def assert_same_records(expected, got):
    assert len(got) == len(expected)
    for i, (a, b) in enumerate(zip(expected, got)):
        assert same_record(a, b), f"record {i} differs:\n{a}\n{b}"


@pytest.fixture(scope="module")
def records():
    return make_records()


@pytest.fixture(scope="module")
def written(tmp_path_factory, records):
    """The records written once to every format: {fmt: (path, messages written)}."""
    base = tmp_path_factory.mktemp("written")
    out = {}
    for fmt, name in FORMATS.items():
        path = base / name
        n = write_recording(iter(records), path, fmt, static_transforms=STATIC, topics=TOPIC_TYPES)
        out[fmt] = (path, n)
    return out


# --- format_for_output ------------------------------------------------------------

@pytest.mark.parametrize("name, explicit, fmt", [
    ("out.bag", None, "ros1"), ("OUT.BAG", None, "ros1"), ("x/out.mcap", None, "mcap"), ("out", None, "ros2-sqlite3"),
    ("out.bag", "mcap", "mcap"), ("out", "ros2-mcap", "ros2-mcap"), ("out.mcap", "ROS1", "ros1"),
    ("weird.db", "ros2-sqlite3", "ros2-sqlite3"),
])
def test_format_for_output(tmp_path, name, explicit, fmt):
    assert format_for_output(tmp_path / name, explicit) == fmt


@pytest.mark.parametrize("name, explicit", [("out.txt", None), ("out.db3", None), ("out.bag", "ros3"), ("out", "")])
def test_format_for_output_unknown(tmp_path, name, explicit):
    with pytest.raises(CartoError):
        format_for_output(tmp_path / name, explicit)


# --- round trips ------------------------------------------------------------------

@pytest.mark.parametrize("fmt", list(FORMATS))
def test_round_trip(written, records, fmt):
    path, n = written[fmt]
    assert n == len(records) + 1  # and one /tf_static message
    with open_any(path, fmt) as rec:
        assert rec.format == fmt
        topics = {t.name: (t.msgtype, t.count) for t in rec.topics()}
        assert topics == {
            "/scan": ("sensor_msgs/msg/LaserScan", 6), "/front/scan": ("sensor_msgs/msg/LaserScan", 6),
            "/odom": ("nav_msgs/msg/Odometry", 24), "/imu": ("sensor_msgs/msg/Imu", 30),
            "/tf_static": ("tf2_msgs/msg/TFMessage", 1)}
        assert rec.static_transforms() == STATIC
        got = list(rec.records())
        assert_same_records(records, got)
        times = [r.time for r in got]
        assert times == sorted(times)
        # a subset of topics, still in time order
        sub = list(rec.records(["/imu", "/front/scan"]))
        assert_same_records([r for r in records if r.topic in ("/imu", "/front/scan")], sub)


def test_formats_agree_bit_for_bit(written):
    """The same records, read from each format, are identical (same floats, same frames, same order)."""
    reads = {}
    for fmt, (path, _) in written.items():
        with open_any(path, fmt) as rec:
            reads[fmt] = list(rec.records())
    base = reads.pop("ros1")
    for fmt, got in reads.items():
        assert all(type(a) is type(b) and (a == b if isinstance(a, Odometry) else a.same_as(b))
                   for a, b in zip(base, got)), fmt


def test_ros2_bag_layout(written):
    path, _ = written["ros2-sqlite3"]
    assert sorted(p.name for p in path.iterdir()) == ["metadata.yaml", "out_db3.db3"]
    with sqlite3.connect(path / "out_db3.db3") as db:
        assert db.execute("select count(*) from messages").fetchone()[0] == written["ros2-sqlite3"][1]
    path, _ = written["ros2-mcap"]
    assert sorted(p.name for p in path.iterdir()) == ["metadata.yaml", "out_mcap.mcap"]
    # the storage file of a ROS2 mcap bag is itself a standalone MCAP
    with McapRecording(path / "out_mcap.mcap") as rec:
        assert len(list(rec.records())) == written["ros2-mcap"][1] - 1


def test_ros1_bag_uses_ros1_type_names_and_latches_tf_static(written):
    data = written["ros1"][0].read_bytes()
    assert b"type=sensor_msgs/LaserScan" in data and b"type=tf2_msgs/TFMessage" in data
    assert b"md5sum=90c7ef2dc6895d81024acba2ac42f369" in data  # noetic LaserScan
    assert b"latching=1" in data


@pytest.mark.parametrize("fmt", ["ros1", "mcap", "ros2-sqlite3"])
def test_point_cloud_scans(tmp_path, fmt):
    """Scans without even spacing become PointCloud2 and come back as the same points (float32 x, y)."""
    rng = np.random.default_rng(0)
    angles = np.sort(rng.uniform(-3.0, 3.0, 50)).astype(np.float32)
    ranges = rng.uniform(0.5, 20.0, 50).astype(np.float32)
    scans = [Scan(time=t_of(5_000_000_000 + i * 100_000_000), ranges=ranges, angles=angles, frame="lidar",
                  topic="/points", source_type="sensor_msgs/msg/PointCloud2") for i in range(3)]
    out = tmp_path / FORMATS[fmt]
    write_recording(iter(scans), out, fmt)
    with open_any(out, fmt) as rec:
        assert [(t.name, t.msgtype) for t in rec.topics()] == [("/points", "sensor_msgs/msg/PointCloud2")]
        got = list(rec.records())
    assert len(got) == 3
    for a, b in zip(scans, got):
        assert b.angle_increment is None and b.frame == "lidar" and b.time == a.time
        np.testing.assert_allclose(b.ranges, a.ranges, rtol=1e-6)
        np.testing.assert_allclose(b.angles, a.angles, atol=1e-6)


def test_declared_topic_types(tmp_path):
    """Declared topics exist even without messages; a PointCloud2 source stays a PointCloud2."""
    scan = make_records(n_scans=1)[0]
    out = tmp_path / "d.mcap"
    n = write_recording(iter([dataclasses.replace(scan, topic="/cloud")]), out, "mcap",
                        topics={"/cloud": "sensor_msgs/PointCloud2", "/odom": "nav_msgs/msg/Odometry",
                                "/echo": "sensor_msgs/msg/MultiEchoLaserScan", "/chatter": "std_msgs/msg/String"})
    assert n == 1
    with McapRecording(out) as rec:
        assert {(t.name, t.msgtype, t.count) for t in rec.topics()} == {
            ("/cloud", "sensor_msgs/msg/PointCloud2", 1), ("/odom", "nav_msgs/msg/Odometry", 0),
            ("/echo", "sensor_msgs/msg/LaserScan", 0)}
        assert next(iter(rec.records())).angle_increment is None


def test_default_topics_and_transform_records(tmp_path):
    recs = [r for r in make_records(n_scans=1) if r.topic != "/front/scan"]
    recs = [dataclasses.replace(r, topic="") for r in recs]
    tf = Transform("map", "odom", (1.0, 2.0, 0.0), (0.0, 0.0, 0.0, 1.0), time=recs[-1].time)
    out = tmp_path / "t.bag"
    write_recording(iter(recs + [tf]), out, "ros1")
    with RosbagRecording(out) as rec:
        assert sorted(t.name for t in rec.topics()) == ["/imu", "/odom", "/scan", "/tf_static"]
        assert rec.static_transforms() == [tf]
        assert_same_records([dataclasses.replace(r, topic={Scan: "/scan", Odometry: "/odom", Imu: "/imu"}[type(r)])
                             for r in recs], list(rec.records()))


def test_on_record_and_no_static_transforms(tmp_path, records):
    calls = []
    n = write_recording(iter(records), tmp_path / "p.bag", "ros1", on_record=lambda: calls.append(1))
    assert n == len(calls) == len(records)
    with RosbagRecording(tmp_path / "p.bag") as rec:
        assert rec.static_transforms() == []
        assert "/tf_static" not in {t.name for t in rec.topics()}


def test_empty_recording(tmp_path):
    assert write_recording(iter([]), tmp_path / "e.mcap", "mcap", static_transforms=STATIC[:1]) == 1
    with McapRecording(tmp_path / "e.mcap") as rec:
        assert rec.static_transforms() == STATIC[:1] and list(rec.records()) == []


def test_a_topic_cannot_change_type(tmp_path, records):
    scan = records[0]
    cloud = dataclasses.replace(scan, angle_increment=None, time=scan.time + 1)
    with pytest.raises(CartoError, match="/scan"):
        write_recording(iter([scan, cloud]), tmp_path / "x.bag", "ros1")
    assert list(tmp_path.iterdir()) == []
    odom_on_scan = dataclasses.replace(records[1 if isinstance(records[1], Odometry) else 2], topic="/scan")
    with pytest.raises(CartoError, match="/scan"):
        write_recording(iter([scan, odom_on_scan]), tmp_path / "x.mcap", "mcap")
    assert list(tmp_path.iterdir()) == []


def test_times_that_cannot_be_stored(tmp_path, records):
    for bad in (-1.0, math.nan):
        with pytest.raises(CartoError, match="time"):
            write_recording(iter([dataclasses.replace(records[0], time=bad)]), tmp_path / "x.bag", "ros1")
    assert list(tmp_path.iterdir()) == []


# --- atomic output ----------------------------------------------------------------------

class Boom(RuntimeError):
    pass


def failing(records, after):
    for i, r in enumerate(records):
        if i == after:
            raise Boom("source broke")
        yield r


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_failure_midway_leaves_nothing(tmp_path, records, fmt):
    out = tmp_path / FORMATS[fmt]
    with pytest.raises(Boom):
        write_recording(failing(records, 25), out, fmt, static_transforms=STATIC, topics=TOPIC_TYPES)
    assert list(tmp_path.iterdir()) == []


def test_failure_in_callback_leaves_nothing(tmp_path, records):
    def callback():
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        write_recording(iter(records), tmp_path / "k_db3", "ros2-sqlite3", on_record=callback)
    assert list(tmp_path.iterdir()) == []


def test_reader_errors_pass_through(tmp_path, records):
    def source():
        yield records[0]
        raise FormatError("corrupt or truncated ROS1 bag: x", "in.bag")

    with pytest.raises(FormatError, match="in.bag"):
        write_recording(source(), tmp_path / "o.mcap", "mcap")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("fmt", ["ros1", "ros2-mcap"])
def test_refuses_to_overwrite(tmp_path, records, fmt):
    out = tmp_path / FORMATS[fmt]
    write_recording(iter(records[:3]), out, fmt)
    before = sorted(os.listdir(out)) if out.is_dir() else out.read_bytes()
    with pytest.raises(CartoError, match="exists"):
        write_recording(iter(records), out, fmt)
    assert (sorted(os.listdir(out)) if out.is_dir() else out.read_bytes()) == before
    # replacing it, and a failed replacement keeping the old one
    with pytest.raises(Boom):
        write_recording(failing(records, 5), out, fmt, overwrite=True)
    with open_any(out, fmt) as rec:
        assert len(list(rec.records())) == 3
    write_recording(iter(records), out, fmt, overwrite=True)
    with open_any(out, fmt) as rec:
        assert len(list(rec.records())) == len(records)
    assert sorted(p.name for p in tmp_path.iterdir()) == [out.name]


def test_overwrite_a_file_with_a_directory(tmp_path, records):
    out = tmp_path / "out"
    out.write_text("old")
    write_recording(iter(records[:2]), out, "ros2-sqlite3", overwrite=True)
    assert out.is_dir() and sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_missing_output_directory(tmp_path, records):
    with pytest.raises(CartoError, match="does not exist"):
        write_recording(iter(records), tmp_path / "no" / "out.bag", "ros1")


# --- truncated and corrupt output is a FormatError -------------------------------------------

def cuts(size):
    return sorted({0, 1, 7, 13, 64, size // 5, size // 3, size // 2, 2 * size // 3, size - 200, size - 30, size - 9,
                   size - 1})


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_truncated_files(tmp_path, written, fmt):
    """A cut file is refused by the indexed ROS1 reader (open_recording then reads its chunks: test_ros1_salvage)
    and read up to the cut by the MCAP reader: a prefix of what was written, with a warning, or a FormatError
    naming the file when no whole message precedes the cut."""
    data = written[fmt][0].read_bytes()
    with open_any(written[fmt][0], fmt) as rec:
        whole = {(r.topic, r.time) for r in rec.records()}
    for cut in cuts(len(data)):
        p = tmp_path / f"cut{cut}{written[fmt][0].suffix}"
        p.write_bytes(data[:cut])
        try:
            with open_any(p, fmt) as rec:
                rec.topics()
                rec.static_transforms()
                got = {(r.topic, r.time) for r in rec.records()}
                warned = list(rec.warnings)
        except FormatError as e:
            assert str(p) in str(e)
            continue
        assert fmt == "mcap", cut
        assert len(warned) == 1 and p.name in warned[0] and "recovered" in warned[0]
        assert got and got <= whole


@pytest.mark.parametrize("fmt", ["ros2-sqlite3", "ros2-mcap"])
def test_truncated_ros2_storage(tmp_path, written, records, fmt):
    """A cut ROS2 storage file is a FormatError, unless the cut only removed unused sqlite pages."""
    src, _ = written[fmt]
    storage = next(p for p in src.iterdir() if p.name != "metadata.yaml")
    data = storage.read_bytes()
    errors = 0
    for cut in cuts(len(data)):
        bag = tmp_path / f"cut{cut}"
        bag.mkdir()
        (bag / "metadata.yaml").write_bytes((src / "metadata.yaml").read_bytes())
        (bag / storage.name).write_bytes(data[:cut])
        try:
            with RosbagRecording(bag) as rec:
                got = list(rec.records())
        except FormatError as e:
            assert str(bag) in str(e)
            errors += 1
        else:
            assert_same_records(records, got)
    assert errors >= len(cuts(len(data))) - 3


@pytest.mark.parametrize("fmt", list(FORMATS))
def test_flipped_bytes_never_escape_as_other_errors(tmp_path, written, fmt):
    src, _ = written[fmt]
    storage = src if src.is_file() else next(p for p in src.iterdir() if p.name != "metadata.yaml")
    data = storage.read_bytes()
    rng = np.random.default_rng(7)
    for trial in range(8):
        b = bytearray(data)
        for i in rng.integers(0, len(b), 3):
            b[i] ^= 0xA5
        if src.is_file():
            p = tmp_path / f"c{trial}{src.suffix}"
            p.write_bytes(bytes(b))
        else:
            p = tmp_path / f"c{trial}"
            p.mkdir()
            (p / "metadata.yaml").write_bytes((src / "metadata.yaml").read_bytes())
            (p / storage.name).write_bytes(bytes(b))
        try:
            with open_any(p, fmt) as rec:
                rec.topics()
                rec.static_transforms()
                list(rec.records())
        except FormatError:
            pass
