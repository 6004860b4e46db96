"""carto_cli.io.sources.mcap: standalone MCAP, ROS2 (cdr) and ROS1 encodings."""

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType
from mcap.writer import Writer as McapWriter
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from support import SHARED, laser_scan_idl

from carto_cli.core.errors import CartoError, FormatError, TopicError
from carto_cli.core.records import Imu, Odometry, Scan, Transform, yaw_quaternion
from carto_cli.io.recording import ReadOptions
from carto_cli.io.sources import mcap as mcap_source
from carto_cli.io.sources.mcap import McapRecording

STANDALONE = (SHARED / "bags" / "ccny_laser_scan_matcher_demo_ros2_mcap"
              / "ccny_laser_scan_matcher_demo_ros2_mcap.mcap")
HUMBLE = get_typestore(Stores.ROS2_HUMBLE)
NOETIC = get_typestore(Stores.ROS1_NOETIC)
NOETIC.register(get_types_from_msg("geometry_msgs/TransformStamped[] transforms", "tf2_msgs/msg/TFMessage"))


# --- the real file ------------------------------------------------------------------------------

@pytest.mark.skipif(not STANDALONE.exists(), reason="shared data not available")
def test_mcap_of_a_ros2_bag_read_standalone():
    with McapRecording(STANDALONE) as rec:
        assert rec.format == "mcap"
        assert [(t.name, t.msgtype, t.count) for t in rec.topics()] == [("/scan", "sensor_msgs/msg/LaserScan", 360)]
        scans = list(rec.records())
    assert len(scans) == 360 and scans[0].time == 1282836370.970876375
    assert scans[0].num_beams == 681 and scans[0].frame == "/laser"


# --- ROS1-encoded MCAP ----------------------------------------------------------------------------

def write_ros1_mcap(path, messages):
    """messages: (topic, log_time_ns, msgtype, message object of NOETIC), as a ROS1 recorder writing MCAP does:
    ros1msg schemas named pkg/Name, ros1-encoded messages."""
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start(profile="ros1", library="test")
        schemas, channels = {}, {}
        for topic, ns, msgtype, msg in messages:
            if msgtype not in schemas:
                schemas[msgtype] = w.register_schema(msgtype.replace("/msg/", "/"), "ros1msg",
                                                     NOETIC.generate_msgdef(msgtype)[0].encode())
            if topic not in channels:
                channels[topic] = w.register_channel(topic, "ros1", schemas[msgtype])
            w.add_message(channels[topic], log_time=ns, publish_time=ns,
                          data=bytes(NOETIC.serialize_ros1(msg, msgtype)))
        w.finish()
    return path


def noetic_header(ns, frame):
    T = NOETIC.types
    return T["std_msgs/msg/Header"](seq=0, stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                    frame_id=frame)


def test_ros1_encoded_mcap(tmp_path):
    T = NOETIC.types
    vec = T["geometry_msgs/msg/Vector3"]
    quat = T["geometry_msgs/msg/Quaternion"]
    cov = np.zeros(36)
    messages = [("/tf_static", 10**9, "tf2_msgs/msg/TFMessage", T["tf2_msgs/msg/TFMessage"](transforms=[
        T["geometry_msgs/msg/TransformStamped"](header=noetic_header(0, "base_link"), child_frame_id="laser",
                                                transform=T["geometry_msgs/msg/Transform"](
                                                    translation=vec(x=0.25, y=0.0, z=0.0),
                                                    rotation=quat(x=0.0, y=0.0, z=0.0, w=1.0)))]))]
    for i in range(4):
        ns = 10**9 + i * 10**8
        scan = T["sensor_msgs/msg/LaserScan"](
            header=noetic_header(ns, "/laser"), angle_min=-1.0, angle_max=1.0, angle_increment=0.5, time_increment=0.0,
            scan_time=0.0, range_min=0.0, range_max=30.0,
            ranges=np.float32([1.0 + i, 2.0, np.nan, 4.0, 5.0]), intensities=np.float32([7.0] * 5))
        q = yaw_quaternion(0.3 * i)
        odom = T["nav_msgs/msg/Odometry"](
            header=noetic_header(ns + 5 * 10**7, "odom"), child_frame_id="base_link",
            pose=T["geometry_msgs/msg/PoseWithCovariance"](
                pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=float(i), y=0.0, z=0.0),
                                                 orientation=quat(x=q[0], y=q[1], z=q[2], w=q[3])), covariance=cov),
            twist=T["geometry_msgs/msg/TwistWithCovariance"](
                twist=T["geometry_msgs/msg/Twist"](linear=vec(x=0.5, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.1)),
                covariance=cov))
        imu = T["sensor_msgs/msg/Imu"](
            header=noetic_header(ns + 2 * 10**7, "imu"), orientation=quat(x=0.0, y=0.0, z=0.0, w=1.0),
            orientation_covariance=np.array([-1.0] + [0.0] * 8), angular_velocity=vec(x=0.0, y=0.0, z=0.1),
            angular_velocity_covariance=np.zeros(9), linear_acceleration=vec(x=0.0, y=0.0, z=9.81),
            linear_acceleration_covariance=np.zeros(9))
        messages += [("/scan", ns, "sensor_msgs/msg/LaserScan", scan),
                     ("/odom", ns + 5 * 10**7, "nav_msgs/msg/Odometry", odom),
                     ("/imu", ns + 2 * 10**7, "sensor_msgs/msg/Imu", imu)]
    path = write_ros1_mcap(tmp_path / "ros1.mcap", messages)
    with McapRecording(path) as rec:
        assert {(t.name, t.msgtype, t.count) for t in rec.topics()} == {
            ("/scan", "sensor_msgs/msg/LaserScan", 4), ("/odom", "nav_msgs/msg/Odometry", 4),
            ("/imu", "sensor_msgs/msg/Imu", 4), ("/tf_static", "tf2_msgs/msg/TFMessage", 1)}
        assert rec.static_transforms() == [Transform("base_link", "laser", (0.25, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0), 0.0)]
        recs = list(rec.records())
    assert [type(r) for r in recs[:3]] == [Scan, Imu, Odometry]
    assert [r.time for r in recs] == sorted(r.time for r in recs)
    s, m, o = recs[3:6]
    assert s.time == 1.1 and s.frame == "/laser" and s.topic == "/scan"
    np.testing.assert_array_equal(s.ranges, np.float32([2.0, 2.0, np.nan, 4.0, 5.0]))
    np.testing.assert_array_equal(s.angles, np.float32([-1.0, -0.5, 0.0, 0.5, 1.0]))
    np.testing.assert_array_equal(s.intensities, np.float32([7.0] * 5))
    assert m.orientation is None and m.angular_velocity[2] == 0.1 and m.time == 1.12
    assert (o.x, o.vx, o.wz, o.frame, o.child_frame) == (1.0, 0.5, 0.1, "odom", "base_link")
    assert o.yaw == pytest.approx(0.3, abs=1e-12)


# --- files built with the mcap library directly -----------------------------------------------------

def laser(ns, value, beams=20):
    T = HUMBLE.types
    return T["sensor_msgs/msg/LaserScan"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9),
                                        frame_id="laser"),
        angle_min=-1.0, angle_max=1.0, angle_increment=0.1, time_increment=0.0, scan_time=0.1, range_min=0.0,
        range_max=10.0, ranges=np.full(beams, value, dtype=np.float32), intensities=np.empty(0, dtype=np.float32))


def write_mcap(path, messages, **writer_options):
    """messages: (topic, log_time_ns, msgtype, message object) in the order to write them."""
    with open(path, "wb") as f:
        w = McapWriter(f, **writer_options)
        w.start(profile="ros2", library="test")
        schemas, channels = {}, {}
        for topic, ns, msgtype, msg in messages:
            if msgtype not in schemas:
                schemas[msgtype] = w.register_schema(msgtype, "ros2msg",
                                                     HUMBLE.generate_msgdef(msgtype, ros_version=2)[0].encode())
            if topic not in channels:
                channels[topic] = w.register_channel(topic, "cdr", schemas[msgtype])
            w.add_message(channels[topic], log_time=ns, publish_time=ns, data=HUMBLE.serialize_cdr(msg, msgtype))
        w.finish()
    return path


def scans_out_of_order():
    order = [0, 2, 1, 3, 5, 4, 6, 7]
    return [("/scan", 10**9 + k * 10**7, "sensor_msgs/msg/LaserScan", laser(10**9 + k * 10**7, float(k))) for k in order]


@pytest.mark.parametrize("options", [
    {},
    {"use_statistics": False},
    {"use_chunking": False},
    {"use_chunking": False, "use_statistics": False, "index_types": IndexType.NONE, "repeat_channels": False,
     "repeat_schemas": False, "use_summary_offsets": False},
    {"chunk_size": 200, "compression": CompressionType.LZ4},
], ids=["indexed", "no-statistics", "unchunked", "no-summary", "many-lz4-chunks"])
def test_counts_and_log_time_order_with_or_without_index(tmp_path, options):
    path = write_mcap(tmp_path / "s.mcap", scans_out_of_order(), **options)
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    indexed = summary is not None and bool(summary.chunk_indexes)
    assert indexed == options.get("use_chunking", True)
    if "index_types" in options:
        assert summary is None
    with McapRecording(path) as rec:
        assert [(t.name, t.count) for t in rec.topics()] == [("/scan", 8)]
        got = list(rec.records())
    assert [s.ranges[0] for s in got] == list(range(8))


def test_pointcloud_in_mcap_uses_read_options(tmp_path):
    T = HUMBLE.types
    pts = np.zeros(4, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("i", "<f4")])
    pts["x"], pts["y"], pts["z"] = [1, 2, 3, 4], [0, 0, 0, 0], [0.0, 0.5, -0.5, 2.0]
    pf = T["sensor_msgs/msg/PointField"]
    msg = T["sensor_msgs/msg/PointCloud2"](
        header=T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=3, nanosec=0), frame_id="lidar"),
        height=1, width=4, fields=[pf(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyzi")],
        is_bigendian=False, point_step=16, row_step=64, data=np.frombuffer(pts.tobytes(), dtype=np.uint8),
        is_dense=True)
    path = write_mcap(tmp_path / "pc.mcap", [("/points", 3 * 10**9, "sensor_msgs/msg/PointCloud2", msg)])
    with McapRecording(path, ReadOptions(min_z=-1.0, max_z=1.0)) as rec:
        (s,) = list(rec.records())
    np.testing.assert_array_equal(s.ranges, np.float32([1, 2, 3]))
    assert s.angle_increment is None and s.time == 3.0


def test_topic_errors(tmp_path):
    T = HUMBLE.types
    msgs = scans_out_of_order()[:2] + [("/chatter", 10**9, "std_msgs/msg/String", T["std_msgs/msg/String"](data="hi"))]
    path = write_mcap(tmp_path / "t.mcap", msgs)
    with McapRecording(path) as rec:
        assert len(list(rec.records())) == 2  # other types are skipped, not decoded
        with pytest.raises(TopicError, match="/nope"):
            rec.records(["/nope"])
        with pytest.raises(TopicError, match="std_msgs/msg/String"):
            rec.records(["/chatter"])
        assert len(list(rec.records(["/scan"]))) == 2


def test_unknown_encoding_is_a_format_error(tmp_path):
    path = tmp_path / "j.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start()
        sid = w.register_schema("sensor_msgs/msg/LaserScan", "jsonschema", b"{}")
        cid = w.register_channel("/scan", "json", sid)
        w.add_message(cid, log_time=1, publish_time=1, data=b"{}")
        w.finish()
    with McapRecording(path) as rec:
        with pytest.raises(FormatError, match="no decoder for topic /scan"):
            list(rec.records())


def test_bad_schema_is_refused_when_opened_without_noise(tmp_path, capfd):
    path = tmp_path / "b.mcap"
    with open(path, "wb") as f:
        w = McapWriter(f)
        w.start()
        sid = w.register_schema("sensor_msgs/msg/LaserScan", "ros2msg", b"float32 ranges broken line here\n")
        cid = w.register_channel("/scan", "cdr", sid)
        w.add_message(cid, log_time=1, publish_time=1, data=b"\x00\x01\x00\x00")
        w.finish()
    with pytest.raises(FormatError, match=r"b.mcap: topic /scan: .* line 1: 'float32 ranges broken line here'"):
        McapRecording(path)
    assert capfd.readouterr().err == ""


def test_ros2idl_schemas_are_read(tmp_path):
    """rosbag2 writes a ros2idl schema for a type defined in .idl alone: the type's IDL, then each it uses."""
    text = laser_scan_idl()

    def write(path, text):
        with open(path, "wb") as f:
            w = McapWriter(f)
            w.start(profile="ros2", library="test")
            cid = w.register_channel("/scan", "cdr", w.register_schema("sensor_msgs/msg/LaserScan", "ros2idl",
                                                                       text.encode()))
            for _, ns, msgtype, msg in scans_out_of_order():
                w.add_message(cid, log_time=ns, publish_time=ns, data=HUMBLE.serialize_cdr(msg, msgtype))
            w.finish()
        return path

    with McapRecording(write(tmp_path / "idl.mcap", text)) as rec:
        assert [s.ranges[0] for s in rec.records()] == list(range(8))
    broken = write(tmp_path / "broken.mcap", text.replace("float scan_time;", "float scan-time;"))
    with pytest.raises(FormatError, match=r"broken.mcap: topic /scan: .*, line 5: the declaration beginning on this line does not parse"):
        McapRecording(broken)


def test_not_mcap(tmp_path):
    with pytest.raises(CartoError, match="no such file"):
        McapRecording(tmp_path / "missing.mcap")
    (tmp_path / "x.mcap").write_bytes(b"#ROSBAG V2.0\n" + bytes(100))
    with pytest.raises(FormatError, match="not an MCAP"):
        McapRecording(tmp_path / "x.mcap")


@pytest.mark.parametrize("options", [
    {"chunk_size": 300},
    {"chunk_size": 10**6, "compression": CompressionType.NONE},
    {"chunk_size": 10**6, "compression": CompressionType.LZ4},
    {"chunk_size": 10**6, "compression": CompressionType.ZSTD},
    {"use_chunking": False},
], ids=["small-chunks", "one-chunk", "one-lz4-chunk", "one-zstd-chunk", "unchunked"])
def test_a_cut_mcap_gives_the_messages_before_the_cut(tmp_path, options):
    """A writer killed mid-file: every message whole before the cut is read (in log-time order), with a warning;
    a cut before any whole message is a FormatError naming the file."""
    written = scans_out_of_order()
    data = write_mcap(tmp_path / "s.mcap", written, **options).read_bytes()
    recovered = []
    for cut in sorted({0, 5, 8, 9, 40, len(data) // 3, len(data) // 2, len(data) * 3 // 4, len(data) - 100,
                       len(data) - 8, len(data) - 1}):
        p = tmp_path / f"cut{cut}.mcap"
        p.write_bytes(data[:cut])
        try:
            with McapRecording(p) as rec:
                got = [s.ranges[0] for s in rec.records()]
                assert rec.topics()[0].count == len(got)
                warnings = list(rec.warnings)
        except FormatError as e:
            assert str(p) in str(e) and ("truncated MCAP" in str(e) or cut < 8), str(e)
            recovered.append(0)
            continue
        assert got, cut
        # What was written first, whole: a prefix of the writing order, read back in log-time order.
        prefix = [msg.ranges[0] for _, _, _, msg in written[:len(got)]]
        assert got == sorted(prefix), (cut, got)
        assert len(warnings) == 1 and p.name in warnings[0] and f"{len(got)} messages recovered" in warnings[0]
        recovered.append(len(got))
    assert recovered == sorted(recovered) and recovered[0] == 0
    assert recovered[-1] == len(written)  # only the closing magic bytes missing: nothing lost
    if options.get("compression") in (None, CompressionType.NONE):  # lz4 and zstd decode a block at a time: a
        assert any(0 < n < len(written) for n in recovered)  # chunk this small is one; a plain one gives a part


def test_corrupt_chunk_found_mid_iteration(tmp_path):
    path = write_mcap(tmp_path / "s.mcap", scans_out_of_order(), chunk_size=300, compression=CompressionType.NONE)
    with open(path, "rb") as f:
        chunks = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.message_start_time)
    assert len(chunks) >= 4
    target = chunks[len(chunks) // 2]
    data = bytearray(path.read_bytes())
    data[target.chunk_start_offset + target.chunk_length - 20] ^= 0xFF
    path.write_bytes(bytes(data))
    got = []
    with McapRecording(path) as rec:
        with pytest.raises(FormatError, match="corrupt or truncated MCAP"):
            for s in rec.records():
                got.append(s)
    assert 0 < len(got) < 8


def test_reorder_window_is_bounded(monkeypatch, tmp_path):
    """An unindexed file is streamed through a bounded heap, never loaded whole."""
    monkeypatch.setattr(mcap_source, "REORDER_WINDOW", 2)
    msgs = scans_out_of_order()
    path = write_mcap(tmp_path / "u.mcap", msgs, use_chunking=False, index_types=IndexType.NONE,
                      use_statistics=False, repeat_channels=False, repeat_schemas=False, use_summary_offsets=False)
    with McapRecording(path) as rec:
        assert [s.ranges[0] for s in rec.records()] == list(range(8))
