"""Decoded ROS messages -> records (carto_cli.io.sources.messages)."""
import math
from types import SimpleNamespace as NS

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from carto_cli.core.errors import TopicError
from carto_cli.core.records import Imu, Odometry, Scan, yaw_quaternion
from carto_cli.io.recording import ReadOptions
from carto_cli.io.sources import messages as M

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types


def header(sec=1282836370, nanosec=970876375, frame="/laser"):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec), frame_id=frame)


def laser_scan(ranges, intensities=(), angle_min=-2.0862138, inc=0.0061359233):
    ranges = np.asarray(ranges, dtype=np.float32)
    return wire(T["sensor_msgs/msg/LaserScan"](
        header=header(), angle_min=angle_min, angle_max=angle_min + inc * (len(ranges) - 1),
        angle_increment=inc, time_increment=1e-4, scan_time=0.1, range_min=0.02, range_max=5.6,
        ranges=ranges, intensities=np.asarray(intensities, dtype=np.float32)))


def wire(msg):
    """The message as a reader sees it: float32 fields hold float32 values, arrays view the raw buffer."""
    return TS.deserialize_cdr(TS.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)


def cloud(points, fields, point_step, *, height=1, row_step=None, bigendian=False, frame="velodyne"):
    """A PointCloud2 whose points are dicts name -> value, laid out by ``fields`` (name, offset, datatype)."""
    order = ">" if bigendian else "<"
    codes = {7: "f4", 8: "f8", 1: "i1", 4: "u2"}
    dtype = np.dtype({"names": [f[0] for f in fields], "formats": [order + codes[f[2]] for f in fields],
                      "offsets": [f[1] for f in fields], "itemsize": point_step})
    n = len(points)
    width = n // height
    row_step = row_step or width * point_step
    arr = np.zeros(n, dtype=dtype)
    for name, *_ in fields:
        arr[name] = [p.get(name, 0) for p in points]
    rows = arr.tobytes()
    data = b"".join(rows[r * width * point_step:(r + 1) * width * point_step].ljust(row_step, b"\xee")
                    for r in range(height))
    pf = T["sensor_msgs/msg/PointField"]
    return T["sensor_msgs/msg/PointCloud2"](
        header=header(frame=frame), height=height, width=width,
        fields=[pf(name=f[0], offset=f[1], datatype=f[2], count=1) for f in fields],
        is_bigendian=bigendian, point_step=point_step, row_step=row_step,
        data=np.frombuffer(data, dtype=np.uint8), is_dense=False)


# --- time ---------------------------------------------------------------------

def test_stamp_both_spellings_and_exact_seconds():
    ros2 = NS(sec=1282836370, nanosec=970876375)
    ros1 = NS(secs=1282836370, nsecs=970876375)
    assert M.stamp_seconds(ros2) == M.stamp_seconds(ros1) == 1282836370.970876375
    assert M.stamp_ns(ros1) == 1282836370970876375


@pytest.mark.parametrize("ns", [0, 1, 999_999_999, 1_000_000_000, 1000_100_000_000, 1282836370970876375,
                                1_700_000_000_123_456_789])
def test_seconds_survive_a_trip_through_nanoseconds(ns):
    t = M.ns_to_seconds(ns)
    assert M.ns_to_seconds(M.seconds_to_ns(t)) == t
    if ns < 2**53 // 1000:  # below ~104 days a float64 still resolves single nanoseconds
        assert M.seconds_to_ns(t) == ns


def test_seconds_to_ns_rejects_non_finite():
    with pytest.raises(ValueError):
        M.seconds_to_ns(math.nan)


# --- LaserScan ------------------------------------------------------------------

def test_laserscan():
    msg = laser_scan([1.0, np.nan, np.inf, 0.01, 3.5], intensities=[10, 20, 30, 40, 50])
    s = M.to_record(msg, "sensor_msgs/msg/LaserScan", "/scan")
    assert isinstance(s, Scan)
    assert s.time == 1282836370.970876375 and s.frame == "/laser" and s.topic == "/scan"
    assert s.ranges.dtype == np.float32 and s.angles.dtype == np.float32
    np.testing.assert_array_equal(s.ranges, msg.ranges)  # invalid returns kept as recorded
    expected = np.float32(msg.angle_min) + np.arange(5, dtype=np.float32) * np.float32(msg.angle_increment)
    np.testing.assert_array_equal(s.angles, expected)
    np.testing.assert_array_equal(s.intensities, np.float32([10, 20, 30, 40, 50]))
    assert s.angle_increment == float(np.float32(0.0061359233)) and s.angle_min == float(np.float32(-2.0862138))
    assert s.range_min == float(np.float32(0.02)) and s.range_max == float(np.float32(5.6))
    assert s.time_increment == float(np.float32(1e-4)) and s.scan_time == float(np.float32(0.1))
    assert s.source_type == "sensor_msgs/msg/LaserScan"
    # a copy, not a view of the decoder's buffer
    assert not np.shares_memory(s.ranges, msg.ranges)


def test_laserscan_without_intensities_and_ros1_type_name():
    s = M.to_record(laser_scan([1.0, 2.0]), "sensor_msgs/LaserScan", "/scan")
    assert s.intensities is None and s.num_beams == 2


def test_laserscan_from_plain_python_objects():
    """Objects as ROS1's Python classes hold a message: tuples, secs/nsecs."""
    msg = NS(header=NS(stamp=NS(secs=5, nsecs=500_000_000), frame_id="laser", seq=3), angle_min=-1.0,
             angle_max=1.0, angle_increment=0.5, time_increment=0.0, scan_time=0.0, range_min=0.0,
             range_max=10.0, ranges=(1.0, 2.0, 3.0, 4.0, 5.0), intensities=())
    s = M.scan_from_laserscan(msg, "/scan")
    assert s.time == 5.5 and s.frame == "laser"
    np.testing.assert_array_equal(s.angles, np.float32([-1.0, -0.5, 0.0, 0.5, 1.0]))


# --- MultiEchoLaserScan ---------------------------------------------------------------

def test_multiecho_first_echo():
    echo = T["sensor_msgs/msg/LaserEcho"]
    msg = T["sensor_msgs/msg/MultiEchoLaserScan"](
        header=header(frame="laser"), angle_min=-0.5, angle_max=0.5, angle_increment=0.5, time_increment=0.0,
        scan_time=0.1, range_min=0.1, range_max=30.0,
        ranges=[echo(echoes=np.float32([1.5, 2.5])), echo(echoes=np.float32([])), echo(echoes=np.float32([3.0]))],
        intensities=[echo(echoes=np.float32([7, 8])), echo(echoes=np.float32([])), echo(echoes=np.float32([9]))])
    s = M.to_record(msg, "sensor_msgs/msg/MultiEchoLaserScan", "/echoes")
    np.testing.assert_array_equal(s.ranges, np.float32([1.5, np.nan, 3.0]))
    np.testing.assert_array_equal(s.intensities, np.float32([7, np.nan, 9]))
    np.testing.assert_array_equal(s.angles, np.float32([-0.5, 0.0, 0.5]))
    assert s.source_type == "sensor_msgs/msg/MultiEchoLaserScan" and s.angle_increment == 0.5


def test_multiecho_without_intensities():
    echo = T["sensor_msgs/msg/LaserEcho"]
    msg = T["sensor_msgs/msg/MultiEchoLaserScan"](
        header=header(), angle_min=0.0, angle_max=0.1, angle_increment=0.1, time_increment=0.0,
        scan_time=0.0, range_min=0.0, range_max=1.0,
        ranges=[echo(echoes=np.float32([0.5])), echo(echoes=np.float32([0.7]))], intensities=[])
    s = M.scan_from_multiecho(msg)
    assert s.intensities is None and s.num_beams == 2


# --- PointCloud2 ---------------------------------------------------------------

POINTS = [
    {"x": 1.0, "y": 0.0, "z": 0.0, "intensity": 1},     # bearing 0
    {"x": 0.0, "y": 2.0, "z": 0.05, "intensity": 2},    # +pi/2
    {"x": -3.0, "y": 0.0, "z": -0.05, "intensity": 3},  # pi
    {"x": 0.0, "y": -4.0, "z": 0.0, "intensity": 4},    # -pi/2
    {"x": 1.0, "y": 1.0, "z": 0.5, "intensity": 5},     # too high
    {"x": 1.0, "y": -1.0, "z": -0.3, "intensity": 6},   # too low
    {"x": np.nan, "y": 1.0, "z": 0.0, "intensity": 7},  # invalid
    {"x": 2.0, "y": np.inf, "z": 0.0, "intensity": 8},  # invalid
    {"x": 3.0, "y": 3.0, "z": np.nan, "intensity": 9},  # no height: not in the slice
    {"x": 1.0, "y": -1.0, "z": 0.0625, "intensity": 10},  # -pi/4
]
EXPECTED_ANGLES = [-math.pi / 2, -math.pi / 4, 0.0, math.pi / 2, math.pi]
EXPECTED_RANGES = [4.0, math.sqrt(2), 1.0, 2.0, 3.0]


def check_slice(s: Scan):
    assert s.angle_increment is None and s.source_type == "sensor_msgs/msg/PointCloud2"
    assert s.ranges.dtype == np.float32 and s.angles.dtype == np.float32
    np.testing.assert_allclose(s.angles, EXPECTED_ANGLES, rtol=1e-6)
    np.testing.assert_allclose(s.ranges, EXPECTED_RANGES, rtol=1e-6)
    assert np.all(np.diff(s.angles) >= 0)
    assert s.angle_min == float(s.angles[0])


def test_pointcloud_float32_packed():
    msg = cloud(POINTS, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12)
    s = M.to_record(msg, "sensor_msgs/msg/PointCloud2", "/points", ReadOptions(min_z=-0.1, max_z=0.1))
    check_slice(s)
    assert s.frame == "velodyne" and s.topic == "/points" and s.time == 1282836370.970876375


def test_pointcloud_float64_padded_point_step_and_rows():
    # z before x, an intensity field between, 40-byte points, rows padded to 8 bytes more than needed
    fields = [("z", 0, 8), ("intensity", 8, 4), ("x", 16, 8), ("y", 24, 8)]
    msg = cloud(POINTS, fields, 40, height=2, row_step=5 * 40 + 8)
    check_slice(M.scan_from_pointcloud2(msg, "/points", ReadOptions(min_z=-0.1, max_z=0.1)))


def test_pointcloud_big_endian_mixed_widths():
    msg = cloud(POINTS, [("x", 0, 8), ("y", 8, 7), ("z", 12, 7)], 16, bigendian=True)
    check_slice(M.scan_from_pointcloud2(msg, "/points", ReadOptions(min_z=-0.1, max_z=0.1)))


def test_pointcloud_slice_bounds_follow_options():
    msg = cloud(POINTS, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12)
    s = M.scan_from_pointcloud2(msg, "/points", ReadOptions(min_z=0.2, max_z=1.0))
    np.testing.assert_allclose(s.angles, [math.pi / 4], rtol=1e-6)
    s = M.scan_from_pointcloud2(msg, "/points", ReadOptions(min_z=-1.0, max_z=1.0))
    assert s.num_beams == 7
    s = M.scan_from_pointcloud2(msg, "/points", ReadOptions(min_z=0.5, max_z=0.5))  # bounds are inclusive
    np.testing.assert_allclose(s.angles, [math.pi / 4], rtol=1e-6)


def test_pointcloud_last_point_without_trailing_padding():
    msg = cloud(POINTS[:4], [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 16)
    msg = T["sensor_msgs/msg/PointCloud2"](**{**msg.__dict__, "data": msg.data[:-4]})
    assert M.scan_from_pointcloud2(msg, "/points").num_beams == 4


def test_pointcloud_data_as_bytes_or_list():
    """uint8[] held as bytes (or lists), as other decoders hand it over."""
    msg = cloud(POINTS, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12)
    for data in (bytes(msg.data), list(bytes(msg.data))):
        plain = NS(**{k: v for k, v in msg.__dict__.items() if k != "data"}, data=data)
        check_slice(M.scan_from_pointcloud2(plain, "/points", ReadOptions(min_z=-0.1, max_z=0.1)))


def test_empty_pointcloud():
    msg = cloud([], [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12)
    s = M.scan_from_pointcloud2(msg, "/points")
    assert s.num_beams == 0 and s.angle_min == 0.0


@pytest.mark.parametrize("fields, point_step, match", [
    ([("x", 0, 7), ("y", 4, 7)], 8, "no z field"),
    ([("a", 0, 7), ("b", 4, 7), ("c", 8, 7)], 12, "no x/y/z"),
    ([("x", 0, 7), ("y", 4, 7), ("z", 8, 4)], 12, "datatype 4"),
    ([("x", 0, 1), ("y", 1, 1), ("z", 2, 1)], 3, "datatype 1"),
])
def test_unsupported_pointcloud_is_a_topic_error(fields, point_step, match):
    msg = cloud(POINTS[:3], fields, point_step)
    with pytest.raises(TopicError, match=match) as info:
        M.to_record(msg, "sensor_msgs/msg/PointCloud2", "/bad_cloud")
    assert "/bad_cloud" in str(info.value)


def test_pointcloud_field_past_point_step_is_a_topic_error():
    msg = cloud(POINTS, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12)
    pf = T["sensor_msgs/msg/PointField"]
    fields = msg.fields[:2] + [pf(name="z", offset=8, datatype=8, count=1)]  # 8 bytes at 8 in a 12-byte point
    msg = T["sensor_msgs/msg/PointCloud2"](**{**msg.__dict__, "fields": fields})
    with pytest.raises(TopicError, match="/points.*malformed"):
        M.scan_from_pointcloud2(msg, "/points")


def test_pointcloud_with_too_little_data_is_a_topic_error():
    msg = cloud(POINTS, [("x", 0, 7), ("y", 4, 7), ("z", 8, 7)], 12)
    msg = T["sensor_msgs/msg/PointCloud2"](**{**msg.__dict__, "data": msg.data[:50]})
    with pytest.raises(TopicError, match="/points.*malformed"):
        M.scan_from_pointcloud2(msg, "/points")


# --- Imu, Odometry, TF -------------------------------------------------------------

def imu_msg(orientation_covariance0):
    v3, q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]
    cov = np.zeros(9)
    cov[0] = orientation_covariance0
    return T["sensor_msgs/msg/Imu"](
        header=header(frame="imu_link"), orientation=q(x=0.0, y=0.0, z=0.6, w=0.8), orientation_covariance=cov,
        angular_velocity=v3(x=0.1, y=0.2, z=0.3), angular_velocity_covariance=np.zeros(9),
        linear_acceleration=v3(x=1.0, y=2.0, z=9.8), linear_acceleration_covariance=np.zeros(9))


def test_imu():
    m = M.to_record(imu_msg(0.01), "sensor_msgs/Imu", "/imu")
    assert isinstance(m, Imu) and m.frame == "imu_link" and m.topic == "/imu"
    np.testing.assert_array_equal(m.orientation, [0.0, 0.0, 0.6, 0.8])
    np.testing.assert_array_equal(m.angular_velocity, [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(m.linear_acceleration, [1.0, 2.0, 9.8])
    assert m.angular_velocity.dtype == np.float64


def test_imu_without_orientation():
    assert M.imu_from_msg(imu_msg(-1.0)).orientation is None


def test_odometry():
    q = yaw_quaternion(2.5)
    pose = T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=1.5, y=-2.0, z=0.0),
                                       orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]))
    twist = T["geometry_msgs/msg/Twist"](linear=T["geometry_msgs/msg/Vector3"](x=0.5, y=0.1, z=0.0),
                                         angular=T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=-0.2))
    msg = T["nav_msgs/msg/Odometry"](
        header=header(frame="odom"), child_frame_id="base_footprint",
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=twist, covariance=np.zeros(36)))
    o = M.to_record(msg, "nav_msgs/msg/Odometry", "/odom")
    assert isinstance(o, Odometry)
    assert (o.x, o.y, o.vx, o.vy, o.wz) == (1.5, -2.0, 0.5, 0.1, -0.2)
    assert o.yaw == pytest.approx(2.5, abs=1e-12)
    assert (o.frame, o.child_frame, o.topic) == ("odom", "base_footprint", "/odom")


def test_tf_message_and_merge():
    v3, q = T["geometry_msgs/msg/Vector3"], T["geometry_msgs/msg/Quaternion"]

    def stamped(parent, child, x):
        return T["geometry_msgs/msg/TransformStamped"](
            header=header(sec=10, nanosec=0, frame=parent), child_frame_id=child,
            transform=T["geometry_msgs/msg/Transform"](translation=v3(x=x, y=0.0, z=0.3),
                                                       rotation=q(x=0.0, y=0.0, z=0.0, w=1.0)))

    msg = T["tf2_msgs/msg/TFMessage"](transforms=[stamped("base_link", "laser", 0.2), stamped("base_link", "imu", 0.0)])
    tfs = M.transforms_from_tf(msg)
    assert [(t.parent, t.child, t.translation, t.rotation, t.time) for t in tfs] == [
        ("base_link", "laser", (0.2, 0.0, 0.3), (0.0, 0.0, 0.0, 1.0), 10.0),
        ("base_link", "imu", (0.0, 0.0, 0.3), (0.0, 0.0, 0.0, 1.0), 10.0)]
    again = M.transforms_from_tf(T["tf2_msgs/msg/TFMessage"](transforms=[stamped("base_link", "laser", 0.25)]))
    merged = M.merge_static_transforms(tfs + again)
    assert [(t.child, t.translation[0]) for t in merged] == [("laser", 0.25), ("imu", 0.0)]


def test_unsupported_type_is_a_topic_error():
    assert not M.is_supported("/chatter", "std_msgs/String")
    assert M.is_supported("/scan", "sensor_msgs/LaserScan")
    with pytest.raises(TopicError, match="/chatter"):
        M.to_record(NS(data="hi"), "std_msgs/msg/String", "/chatter")
