"""carto_cli.io.sources.rosbag: ROS1 bags and ROS2 bag directories."""
import math
import sqlite3

import numpy as np
import pytest
from rosbags.rosbag1 import Reader as Reader1
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin
from rosbags.rosbag2 import Writer as Writer2
from rosbags.typesys import Stores, get_typestore
from support import SHARED

from carto_cli.core.errors import CartoError, FormatError, TopicError
from carto_cli.core.records import Odometry, Scan, Transform
from carto_cli.io.recording import ReadOptions
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.sources.mcap import McapRecording
from carto_cli.io.sources.rosbag import RosbagRecording

BAGS = SHARED / "bags"
ROS1 = BAGS / "ccny_laser_scan_matcher_demo.bag"
ORIG = BAGS / "ccny_laser_scan_matcher_demo.orig.bag"
DB3 = BAGS / "ccny_laser_scan_matcher_demo_ros2_db3"
MCAPDIR = BAGS / "ccny_laser_scan_matcher_demo_ros2_mcap"
STANDALONE = MCAPDIR / "ccny_laser_scan_matcher_demo_ros2_mcap.mcap"
FIRST_STAMP = 1282836370.970876375

needs_data = pytest.mark.skipif(not ROS1.exists(), reason=f"shared data not available: {BAGS}")
HUMBLE = get_typestore(Stores.ROS2_HUMBLE)


def t_of(ns):
    return ns / 1_000_000_000


# --- the real recording in every format ---------------------------------------------------------

@pytest.fixture(scope="module")
def real():
    """Records of the real recording as read from each of its four forms."""
    out = {}
    for name, path, cls in (("ros1", ROS1, RosbagRecording), ("ros2-sqlite3", DB3, RosbagRecording),
                            ("ros2-mcap", MCAPDIR, RosbagRecording), ("mcap", STANDALONE, McapRecording)):
        with cls(path) as rec:
            out[name] = (rec.format, rec.topics(), rec.static_transforms(), list(rec.records()))
    return out


@needs_data
@pytest.mark.parametrize("name", ["ros1", "ros2-sqlite3", "ros2-mcap", "mcap"])
def test_real_recording(real, name):
    fmt, topics, static, records = real[name]
    assert fmt == name
    assert [(t.name, t.msgtype, t.count, t.kind) for t in topics] == [("/scan", "sensor_msgs/msg/LaserScan", 360, "scan")]
    assert static == []
    assert len(records) == 360 and all(isinstance(r, Scan) for r in records)
    first = records[0]
    assert first.time == FIRST_STAMP
    assert first.num_beams == 681 and first.frame == "/laser" and first.topic == "/scan"
    assert first.angles[0] == np.float32(first.angle_min)
    assert math.degrees(first.angles[-1] - first.angles[0]) == pytest.approx(239.0, abs=0.1)
    assert first.range_min == pytest.approx(0.02) and first.range_max == pytest.approx(5.6)
    assert first.intensities is None
    times = [r.time for r in records]
    assert times == sorted(times) and times[-1] - times[0] == pytest.approx(35.8, abs=0.1)


@needs_data
def test_real_recording_identical_in_every_format(real):
    base = real["ros1"][3]
    for name in ("ros2-sqlite3", "ros2-mcap", "mcap"):
        other = real[name][3]
        assert len(other) == len(base)
        assert all(a.same_as(b) and a.topic == b.topic and a.angle_increment == b.angle_increment
                   and a.scan_time == b.scan_time and a.time_increment == b.time_increment
                   for a, b in zip(base, other)), name


@needs_data
def test_orig_bag_is_a_format_error_naming_the_file():
    with pytest.raises(FormatError) as info:
        with RosbagRecording(ORIG) as rec:
            list(rec.records())
    err = info.value
    assert err.path == str(ORIG)
    assert str(ORIG) in str(err) and "corrupt or truncated ROS1 bag" in str(err)
    assert isinstance(err.__cause__, AssertionError)


@needs_data
def test_bag_with_pre_groovy_definitions(tmp_path):
    """Old bags embed 'MSG: roslib/Header'; the messages are read with the bag's own definitions."""
    data = ORIG.read_bytes()
    start = data.index(b"message_definition=") + len(b"message_definition=")
    end = data.index(b"string frame_id\n", data.index(b"MSG: roslib/Header", start)) + len(b"string frame_id\n")
    old_definition = data[start:end].decode()
    with Reader1(ROS1) as reader:
        raw = [(ts, bytes(d)) for _, ts, d in reader.messages()][:5]
    bag = tmp_path / "old.bag"
    with Writer1(bag) as writer:
        conn = writer.add_connection("/scan", "sensor_msgs/msg/LaserScan", msgdef=old_definition,
                                     md5sum="90c7ef2dc6895d81024acba2ac42f369")
        for ts, d in raw:
            writer.write(conn, ts, d)
    with RosbagRecording(bag) as rec:
        scans = list(rec.records())
    assert len(scans) == 5 and scans[0].time == FIRST_STAMP and scans[0].num_beams == 681


@needs_data
def test_records_can_interleave_with_other_reads():
    with RosbagRecording(ROS1) as rec:
        a, b = rec.records(), rec.records(["/scan"])
        pairs = [(next(a), next(b), rec.static_transforms()) for _ in range(3)]
    assert all(x.same_as(y) for x, y, _ in pairs)


# --- synthetic bags -------------------------------------------------------------------------------

def scan(i, topic="/scan", beams=30):
    ranges = (np.arange(beams, dtype=np.float32) * np.float32(0.1) + np.float32(i))
    return Scan(time=t_of(2_000_000_000 + i * 50_000_000), ranges=ranges,
                angles=np.float32(-1.5) + np.arange(beams, dtype=np.float32) * np.float32(0.1), frame="laser",
                topic=topic, range_min=0.0, range_max=40.0, angle_min=-1.5, angle_increment=float(np.float32(0.1)))


def odom(i):
    return Odometry(time=t_of(2_000_000_000 + i * 50_000_000 + 25_000_000), x=float(i), y=0.5, yaw=0.1 * i,
                    topic="/odom", vx=1.0)


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    base = tmp_path_factory.mktemp("bags")
    recs = sorted([scan(i) for i in range(10)] + [scan(i, "/scan2") for i in range(0, 10, 3)]
                  + [odom(i) for i in range(10)], key=lambda r: r.time)
    tf = [Transform("base_link", "laser", (0.1, 0.0, 0.2), (0.0, 0.0, 0.0, 1.0))]
    paths = {"ros1": base / "s.bag", "ros2-sqlite3": base / "s_db3", "ros2-mcap": base / "s_mcap"}
    for fmt, p in paths.items():
        write_recording(iter(recs), p, fmt, static_transforms=tf)
    return recs, tf, paths


@pytest.mark.parametrize("fmt", ["ros1", "ros2-sqlite3", "ros2-mcap"])
def test_topics_selection_and_order(bags, fmt):
    recs, tf, paths = bags
    with RosbagRecording(paths[fmt]) as rec:
        assert rec.format == fmt
        assert {t.name: t.count for t in rec.topics()} == {"/scan": 10, "/scan2": 4, "/odom": 10, "/tf_static": 1}
        assert {t.name: t.kind for t in rec.topics()}["/tf_static"] == "tf_static"
        assert rec.static_transforms() == tf
        everything = list(rec.records())
        assert [r.time for r in everything] == [r.time for r in recs]
        assert [r.topic for r in everything] == [r.topic for r in recs]
        only = list(rec.records(["/scan2", "/odom"]))
        assert [r.time for r in only] == [r.time for r in recs if r.topic in ("/scan2", "/odom")]
        assert list(rec.records([])) == []
        with pytest.raises(TopicError, match="/nope"):
            rec.records(["/scan", "/nope"])
        with pytest.raises(TopicError, match="/tf_static"):
            rec.records(["/tf_static"])


def test_closed_recording(bags):
    rec = RosbagRecording(bags[2]["ros1"])
    rec.close()
    rec.close()
    with pytest.raises(CartoError, match="closed"):
        rec.records()


def test_not_a_bag(tmp_path):
    with pytest.raises(CartoError, match="no such"):
        RosbagRecording(tmp_path / "missing.bag")
    (tmp_path / "empty.bag").write_bytes(b"")
    with pytest.raises(FormatError, match="ROS1 bag"):
        RosbagRecording(tmp_path / "empty.bag")
    (tmp_path / "text.bag").write_text("hello world\n" * 100)
    with pytest.raises(FormatError, match="text.bag"):
        RosbagRecording(tmp_path / "text.bag")
    (tmp_path / "dir").mkdir()
    with pytest.raises(FormatError, match="ROS2 bag"):
        RosbagRecording(tmp_path / "dir")
    (tmp_path / "dir" / "metadata.yaml").write_text("rosbag2_bagfile_information: [\n")
    with pytest.raises(FormatError, match="ROS2 bag"):
        RosbagRecording(tmp_path / "dir")


def test_ros1_message_corrupt_mid_iteration(tmp_path, bags):
    """The index is fine, so the bag opens; the 8th message record is broken, found while streaming."""
    data = bytearray(bags[2]["ros1"].read_bytes())
    at = -1
    for _ in range(8):
        at = data.index(b"op=\x02", at + 1)
    data[at + 3] = 0x09
    bad = tmp_path / "bad.bag"
    bad.write_bytes(bytes(data))
    got = []
    with RosbagRecording(bad) as rec:
        with pytest.raises(FormatError, match="corrupt or truncated ROS1 bag") as info:
            for r in rec.records():
                got.append(r)
    assert 0 < len(got) < 24 and str(bad) in str(info.value)


def test_ros2_message_corrupt_mid_iteration(tmp_path, bags):
    src = bags[2]["ros2-sqlite3"]
    bag = tmp_path / src.name
    bag.mkdir()
    for p in src.iterdir():
        (bag / p.name).write_bytes(p.read_bytes())
    with sqlite3.connect(bag / f"{src.name}.db3") as db:
        db.execute("update messages set data = x'0001000001' where id = 6")
    got = []
    with RosbagRecording(bag) as rec:
        with pytest.raises(FormatError, match="ROS2 bag"):
            for r in rec.records():
                got.append(r)
    assert 0 < len(got) < 24


@pytest.mark.parametrize("fmt", ["ros1", "ros2-sqlite3"])
def test_truncated_bags(tmp_path, bags, fmt):
    src = bags[2][fmt]
    storage = src if src.is_file() else src / f"{src.name}.db3"
    data = storage.read_bytes()
    for cut in (0, 10, 100, len(data) // 4, len(data) // 2, len(data) - 500, len(data) - 1):
        if src.is_file():
            p = tmp_path / f"t{cut}.bag"
            p.write_bytes(data[:cut])
        else:
            p = tmp_path / f"t{cut}"
            p.mkdir()
            (p / "metadata.yaml").write_bytes((src / "metadata.yaml").read_bytes())
            (p / storage.name).write_bytes(data[:cut])
        with pytest.raises(FormatError) as info:
            with RosbagRecording(p) as rec:
                list(rec.records())
        assert str(p) in str(info.value), cut


# --- message types written by other tools -------------------------------------------------------

def write_ros2(path, topic, msgtype, msgs, storage=StoragePlugin.SQLITE3):
    with Writer2(path, version=9, storage_plugin=storage) as w:
        conn = w.add_connection(topic, msgtype, typestore=HUMBLE)
        for ns, msg in msgs:
            w.write(conn, ns, HUMBLE.serialize_cdr(msg, msgtype))


def header(ns, frame):
    T = HUMBLE.types
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                    frame_id=frame)


def test_multiecho_bag(tmp_path):
    T = HUMBLE.types
    echo = T["sensor_msgs/msg/LaserEcho"]
    msgs = []
    for i in range(3):
        ns = 3_000_000_000 + i * 10**8
        msgs.append((ns, T["sensor_msgs/msg/MultiEchoLaserScan"](
            header=header(ns, "laser"), angle_min=-0.1, angle_max=0.1, angle_increment=0.1, time_increment=0.0,
            scan_time=0.1, range_min=0.1, range_max=10.0,
            ranges=[echo(echoes=np.float32([1.0 + i, 9.0])), echo(echoes=np.float32([])), echo(echoes=np.float32([2.0]))],
            intensities=[])))
    write_ros2(tmp_path / "echo", "/echoes", "sensor_msgs/msg/MultiEchoLaserScan", msgs, StoragePlugin.MCAP)
    with RosbagRecording(tmp_path / "echo") as rec:
        assert rec.topics()[0].kind == "scan"
        scans = list(rec.records())
    assert [s.time for s in scans] == [3.0, 3.1, 3.2]
    np.testing.assert_array_equal(scans[2].ranges, np.float32([3.0, np.nan, 2.0]))
    assert scans[0].source_type == "sensor_msgs/msg/MultiEchoLaserScan" and scans[0].intensities is None


def cloud_msg(ns, zs):
    T = HUMBLE.types
    pts = np.zeros(len(zs), dtype=[("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("pad", "<f8")])
    pts["x"] = np.arange(1, len(zs) + 1)
    pts["y"] = 1.0
    pts["z"] = zs
    pf = T["sensor_msgs/msg/PointField"]
    return T["sensor_msgs/msg/PointCloud2"](
        header=header(ns, "lidar"), height=1, width=len(zs),
        fields=[pf(name=n, offset=8 * i, datatype=8, count=1) for i, n in enumerate("xyz")], is_bigendian=False,
        point_step=32, row_step=32 * len(zs), data=np.frombuffer(pts.tobytes(), dtype=np.uint8), is_dense=True)


def test_pointcloud_bag_uses_read_options(tmp_path):
    write_ros2(tmp_path / "pc", "/points", "sensor_msgs/msg/PointCloud2",
               [(5 * 10**9, cloud_msg(5 * 10**9, [0.0, 0.3, -0.3, 0.05, 1.0, -1.0, 2.5]))])
    with RosbagRecording(tmp_path / "pc") as rec:  # the default slice: -0.8 .. 2.0 m
        assert len(next(iter(rec.records())).ranges) == 5
    with RosbagRecording(tmp_path / "pc", ReadOptions(min_z=-0.5, max_z=0.5)) as rec:
        s = next(iter(rec.records()))
    assert s.num_beams == 4 and s.angle_increment is None and s.frame == "lidar"
    np.testing.assert_allclose(s.ranges, np.hypot([4, 3, 2, 1], 1.0), rtol=1e-6)  # sorted by bearing


def test_bad_pointcloud_in_a_bag_is_a_topic_error(tmp_path):
    msg = cloud_msg(10**9, [0.0])
    msg.fields[2].datatype = 5  # INT32 z
    write_ros2(tmp_path / "pc", "/points", "sensor_msgs/msg/PointCloud2", [(10**9, msg)])
    with RosbagRecording(tmp_path / "pc") as rec:
        with pytest.raises(TopicError) as info:
            list(rec.records())
    assert "/points" in str(info.value) and str(tmp_path / "pc") in str(info.value)


# --- a ROS2 bag without its metadata.yaml ---------------------------------------------------------

@pytest.mark.parametrize("storage", ["ros2-sqlite3", "ros2-mcap"])
def test_a_ros2_bag_without_metadata_reads_from_its_storage_file(tmp_path, written_recordings, storage):
    """metadata.yaml lost (or never written): the storage file names its topics and types itself."""
    from carto_cli.commands.convert import run_convert
    from carto_cli.io.sources.open import detect_format, open_recording

    _, paths = written_recordings
    src = paths[storage]
    bare = tmp_path / "bare"
    bare.mkdir()
    (storage_file,) = [f for f in src.iterdir() if f.suffix in (".db3", ".mcap")]
    (bare / storage_file.name).write_bytes(storage_file.read_bytes())
    with open_recording(src) as rec:
        want = [(r.topic, r.time) for r in rec.records()]
        topics = rec.topics()
    assert detect_format(bare) == storage
    with open_recording(bare) as rec:
        assert rec.format == storage and rec.topics() == topics
        assert [(r.topic, r.time) for r in rec.records()] == want
        assert len(rec.warnings) == 1 and "no metadata.yaml" in rec.warnings[0] and storage_file.name in rec.warnings[0]
    if storage == "ros2-sqlite3":  # the .db3 file itself, named on the command line
        with open_recording(bare / storage_file.name) as rec:
            assert [(r.topic, r.time) for r in rec.records()] == want
    done = run_convert(bare, tmp_path / "back.bag")
    assert done.lossless and done.messages == sum(t.count for t in topics)
    with open_recording(tmp_path / "back.bag") as rec:
        assert [(r.topic, r.time) for r in rec.records()] == want


def test_a_directory_with_no_bag_in_it_is_refused(tmp_path):
    from carto_cli.io.sources.open import open_recording

    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(FormatError, match="no metadata.yaml, no .db3 or .mcap file") as info:
        open_recording(tmp_path)
    assert str(tmp_path) in str(info.value)
