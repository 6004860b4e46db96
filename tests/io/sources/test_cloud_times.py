"""A 3D lidar's clouds read as scans: the per-point time fields of each driver's convention into Scan.point_times, the
band chosen once per topic and reported, the cloud_band option, and the writer's clouds read back through a file."""
import math

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from carto_cli.core.errors import CartoError
from carto_cli.core.records import Cloud, Odometry
from carto_cli.io.recording import ReadOptions
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.sources import messages as M
from carto_cli.io.sources.open import open_recording

TS = get_typestore(Stores.ROS2_HUMBLE)
T = TS.types
STAMP = 1700000000.25


def cloud(xyz, time_field=None, times=None, datatype=None):
    """A packed PointCloud2 of float32 x y z and, optionally, one time column of ``datatype`` holding ``times``."""
    codes = {1: "i1", 2: "u1", 3: "i2", 4: "u2", 5: "i4", 6: "u4", 7: "f4", 8: "f8"}
    names, formats = ["x", "y", "z"], ["<f4"] * 3
    if time_field is not None:
        names.append(time_field)
        formats.append("<" + codes[datatype])
    dtype = np.dtype({"names": names, "formats": formats})
    rows = np.zeros(len(xyz), dtype=dtype)
    for k, n in enumerate("xyz"):
        rows[n] = np.asarray(xyz)[:, k]
    if time_field is not None:
        rows[time_field] = times
    pf = T["sensor_msgs/msg/PointField"]
    sec = int(STAMP)
    header = T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=int(round((STAMP - sec)
                                                                                                 * 1e9))),
                                      frame_id="lidar")
    msg = T["sensor_msgs/msg/PointCloud2"](
        header=header, height=1, width=len(xyz),
        fields=[pf(name=n, offset=dtype.fields[n][1], datatype=(7 if n in "xyz" else datatype), count=1)
                for n in names],
        is_bigendian=False, point_step=dtype.itemsize, row_step=dtype.itemsize * len(xyz),
        data=np.frombuffer(rows.tobytes(), dtype=np.uint8), is_dense=True)
    return TS.deserialize_cdr(TS.serialize_cdr(msg, msg.__msgtype__), msg.__msgtype__)


def ring(n=8, r=2.0, z=0.0):
    a = np.linspace(-math.pi, math.pi, n, endpoint=False) + 0.01
    return np.column_stack([r * np.cos(a), r * np.sin(a), np.full(n, z)])


OFFSETS = np.linspace(0.0, 0.0875, 8)  # seconds after the stamp, one per point in bearing order


@pytest.mark.parametrize("field,datatype,values", [
    ("t", 6, np.round(OFFSETS * 1e9)),  # Ouster: uint32 ns since the scan's start
    ("offset_time", 6, np.round(OFFSETS * 1e9)),  # Livox: uint32 ns after the stamp
    ("time", 7, OFFSETS),  # Velodyne: float32 s relative to the stamp
    ("t", 7, OFFSETS * 1e9),  # the old Ouster OS1 driver: float ns
    ("timestamp", 8, STAMP + OFFSETS),  # Hesai / Robosense: float64 absolute s
    ("time", 8, OFFSETS),  # any float width
])
def test_each_drivers_time_field_becomes_seconds_after_the_stamp(field, datatype, values):
    msg = cloud(ring(), field, values, datatype)
    scan = M.scan_from_pointcloud2(msg, "/points")
    assert scan.time == pytest.approx(STAMP)
    assert scan.point_times is not None and scan.timed
    assert np.allclose(scan.beam_times(), OFFSETS, atol=2e-6)


def test_velodyne_times_before_the_stamp_stay_negative():
    before = OFFSETS - 0.1  # the stamp is the sweep's end
    scan = M.scan_from_pointcloud2(cloud(ring(), "time", before, 7), "/points")
    assert np.allclose(scan.beam_times(), before, atol=1e-6)


def test_no_time_field_no_point_times():
    scan = M.scan_from_pointcloud2(cloud(ring()), "/points")
    assert scan.point_times is None and not scan.timed


def test_times_follow_their_points_through_the_slice_and_the_sort():
    xyz = ring()[::-1].copy()  # bearings descending: the sort reverses them
    xyz[2, 2] = 5.0  # above the slice
    times = np.arange(8) * 1000
    scan = M.scan_from_pointcloud2(cloud(xyz, "t", times, 6), "/points", ReadOptions(min_z=-1, max_z=1))
    assert scan.num_beams == 7
    assert np.all(np.diff(scan.angles) > 0)
    kept = np.delete(np.arange(8), 2)[::-1]
    assert np.allclose(scan.beam_times(), kept * 1e-6)


def test_a_time_field_of_no_pointfield_type_is_a_topic_error():
    msg = cloud(ring(), "t", np.zeros(8), 6)
    msg.fields[3].datatype = 9
    with pytest.raises(CartoError, match="field t has datatype 9"):
        M.scan_from_pointcloud2(msg, "/points")


def test_cloud_band_option_is_checked_when_a_cloud_is_read():
    decoder = M.Decoder(ReadOptions(cloud_band="1.5..0.5"))
    with pytest.raises(CartoError, match="cloud_band"):
        decoder.cloud(cloud(ring()), "/points")


def test_a_planar_cloud_keeps_the_sensor_slice():
    """carto's own PointCloud2 of a 2D scan (z = 0): no floor in sight, so min_z..max_z as always."""
    decoder = M.Decoder(ReadOptions())
    scan = decoder.cloud(cloud(ring()), "/points")
    assert scan.num_beams == 8
    band = decoder.bands["/points"]
    assert band.floor is None and band.how == "no floor" and (band.low, band.high) == (-0.8, 2.0)


def _written(tmp_path, fmt, name, field):
    rng = np.random.default_rng(0)
    n = 3000
    a = rng.uniform(-math.pi, math.pi, n)
    floor = np.column_stack([3 * np.cos(a[:1500]), 3 * np.sin(a[:1500]), np.full(1500, -0.7)])
    wall = np.column_stack([4 * np.cos(a[1500:]), 4 * np.sin(a[1500:]), rng.uniform(-0.6, 1.5, 1500)])
    points = np.vstack([floor, wall]).astype(np.float32)
    offsets = (a + math.pi) / (2 * math.pi) * 0.1
    records = [Odometry(10.0, 0.0, 0.0, 0.0, topic="/odom"),
               Cloud(10.0, points, "lidar", "/points", offsets, field),
               Odometry(10.2, 0.1, 0.0, 0.0, topic="/odom")]
    out = tmp_path / name
    write_recording(records, out, fmt)
    return out, offsets


@pytest.mark.parametrize("fmt,name", [("ros1", "c.bag"), ("mcap", "c.mcap"), ("ros2-sqlite3", "c_db3")])
@pytest.mark.parametrize("field", ["t", "time", "offset_time"])
def test_written_clouds_read_back_with_their_times_and_band(tmp_path, fmt, name, field):
    out, _offsets = _written(tmp_path, fmt, name, field)
    with open_recording(out) as rec:
        scans = list(rec.records(["/points"]))
        band = rec.cloud_bands["/points"]
    assert len(scans) == 1
    scan = scans[0]
    assert band.floor == pytest.approx(-0.7, abs=0.01) and band.how == "auto"
    assert band.low - band.floor == pytest.approx(0.6) and band.high - band.floor == pytest.approx(1.9)
    # The floor points are gone, the wall's in the band are kept: one per bearing step at most.
    assert np.allclose(np.hypot(*scan.points().T), 4.0, atol=1e-4)
    assert 0 < scan.num_beams <= 1500
    assert scan.point_times is not None
    assert float(scan.point_times.min()) >= 0.0 and float(scan.point_times.max()) <= 0.1 + 1e-6
    # Each kept point's time is its own: the sweep turns from -pi, so time grows with bearing.
    expected = (scan.angles.astype(np.float64) + math.pi) / (2 * math.pi) * 0.1
    assert np.allclose(scan.point_times, expected, atol=2e-5)


def test_sensor_band_keeps_every_point_of_the_slice(tmp_path):
    out, _ = _written(tmp_path, "mcap", "c.mcap", "t")
    with open_recording(out, ReadOptions(min_z=-0.8, max_z=2.0, cloud_band="sensor")) as rec:
        scan = next(iter(rec.records(["/points"])))
    assert scan.num_beams == 3000  # floor and wall alike, as Cartographer slices


def test_a_flattened_sweep_converted_keeps_its_point_times(tmp_path):
    out, _ = _written(tmp_path, "mcap", "c.mcap", "t")
    with open_recording(out) as rec:
        scan = next(iter(rec.records(["/points"])))
    again = tmp_path / "again.bag"
    write_recording([scan], again, "ros1")
    with open_recording(again) as rec:
        back = next(iter(rec.records(["/points"])))
        assert rec.cloud_bands["/points"].how == "no floor"  # flat now: every point kept
    assert back.num_beams == scan.num_beams
    assert np.allclose(back.ranges, scan.ranges, atol=1e-5)
    assert np.allclose(back.point_times, scan.point_times, atol=1e-7)


def test_a_sparse_first_cloud_leaves_the_choice_to_the_next():
    decoder = M.Decoder(ReadOptions())
    decoder.cloud(cloud(ring(8)), "/points")
    assert decoder.bands["/points"].how == "no floor"
    rng = np.random.default_rng(1)
    a = rng.uniform(-math.pi, math.pi, 2000)
    floor = np.column_stack([3 * np.cos(a[:1000]), 3 * np.sin(a[:1000]), np.full(1000, -0.5)])
    wall = np.column_stack([4 * np.cos(a[1000:]), 4 * np.sin(a[1000:]), rng.uniform(-0.4, 1.5, 1000)])
    decoder.cloud(cloud(np.vstack([floor, wall])), "/points")
    band = decoder.bands["/points"]
    assert band.how == "auto" and band.floor == pytest.approx(-0.5, abs=0.01)
    decoder.cloud(cloud(ring(8)), "/points")
    assert decoder.bands["/points"] is band  # chosen once, kept


LIVOX_POINT = "uint32 offset_time\nfloat32 x\nfloat32 y\nfloat32 z\nuint8 reflectivity\nuint8 tag\nuint8 line\n"
LIVOX_MSG = ("std_msgs/Header header\nuint64 timebase\nuint32 point_num\nuint8 lidar_id\nuint8[3] rsvd\n"
             "livox_ros_driver/CustomPoint[] points\n")


def test_livox_custom_msg_read_from_the_bags_own_definition(tmp_path):
    """A ROS1 bag of livox_ros_driver/CustomMsg: rosbags reads it by the definition the bag carries, and its points
    become a scan in the band above the floor, timed by offset_time after timebase."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import get_types_from_msg

    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register({**get_types_from_msg(LIVOX_POINT, "livox_ros_driver/msg/CustomPoint"),
                 **get_types_from_msg(LIVOX_MSG, "livox_ros_driver/msg/CustomMsg")})
    L = ts.types
    rng = np.random.default_rng(2)
    a = rng.uniform(-math.pi, math.pi, 2000)
    floor = np.column_stack([3 * np.cos(a[:1000]), 3 * np.sin(a[:1000]), np.full(1000, -0.6)])
    wall = np.column_stack([4 * np.cos(a[1000:]), 4 * np.sin(a[1000:]), rng.uniform(-0.5, 1.5, 1000)])
    xyz = np.vstack([floor, wall])
    offsets = np.round((a + math.pi) / (2 * math.pi) * 0.1e9).astype(np.int64)
    stamp_ns = 20_000_000_000
    timebase = stamp_ns + 5_000_000  # 5 ms after the header's stamp
    points = [L["livox_ros_driver/msg/CustomPoint"](offset_time=int(o), x=float(p[0]), y=float(p[1]), z=float(p[2]),
                                                    reflectivity=10, tag=0, line=0) for p, o in zip(xyz, offsets)]
    header = L["std_msgs/msg/Header"](seq=0, stamp=L["builtin_interfaces/msg/Time"](sec=20, nanosec=0),
                                      frame_id="livox_frame")
    msg = L["livox_ros_driver/msg/CustomMsg"](header=header, timebase=timebase, point_num=len(points), lidar_id=0,
                                              rsvd=np.zeros(3, np.uint8), points=points)
    path = tmp_path / "livox.bag"
    with Writer(path) as writer:
        conn = writer.add_connection("/livox/lidar", "livox_ros_driver/msg/CustomMsg", typestore=ts)
        writer.write(conn, stamp_ns, ts.serialize_ros1(msg, "livox_ros_driver/msg/CustomMsg"))
    with open_recording(path) as rec:
        assert [t.kind for t in rec.topics()] == ["scan"]
        scan = next(iter(rec.records(["/livox/lidar"])))
        band = rec.cloud_bands["/livox/lidar"]
    assert scan.time == 20.0 and scan.frame == "livox_frame"
    assert band.how == "auto" and band.floor == pytest.approx(-0.6, abs=0.01)
    assert np.allclose(np.hypot(*scan.points().T), 4.0, atol=1e-4)
    expected = 0.005 + (scan.angles.astype(np.float64) + math.pi) / (2 * math.pi) * 0.1
    assert np.allclose(scan.point_times, expected, atol=2e-5)
