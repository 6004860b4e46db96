"""carto_cli.io.sources.ros1_salvage: ROS1 bags read without their index (cut, .bag.active, damaged index)."""
import hashlib
import struct
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag1 import Writer as Writer1
from support import SAMPLE_BAG, SHARED, synthetic_records

from carto_cli.commands.convert import run_convert
from carto_cli.commands.info import run_info
from carto_cli.core.errors import FormatError
from carto_cli.core.records import Scan
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.sources.open import open_recording
from carto_cli.io.sources.ros1_salvage import SalvagedBag
from carto_cli.io.sources.rosbag import RosbagRecording

ORIG = SHARED / "bags" / "ccny_laser_scan_matcher_demo.orig.bag"
TOPICS = {"/scan": "sensor_msgs/msg/LaserScan", "/odom": "nav_msgs/msg/Odometry", "/imu": "sensor_msgs/msg/Imu"}


def records_of(path):
    with open_recording(path) as rec:
        return list(rec.records()), list(rec.warnings)


def same_records(a, b):
    assert len(a) == len(b)
    for x, y in zip(a, b):
        assert type(x) is type(y) and x.topic == y.topic and x.time == y.time
        if isinstance(x, Scan):
            np.testing.assert_array_equal(x.ranges, y.ranges)


def message_digest(path) -> tuple[int, str]:
    """How many messages a bag holds and a digest of their topics, stamps and bytes (read with rosbags)."""
    h = hashlib.sha256()
    n = 0
    with AnyReader([Path(path)]) as reader:
        for conn, t, raw in reader.messages():
            h.update(f"{conn.topic} {conn.msgtype} {t}".encode())
            h.update(bytes(raw))
            n += 1
    return n, h.hexdigest()


def rewrite_index_pos(data: bytes, value: int) -> bytes:
    """The bag with its header's index position replaced (a recorder that never closed the file leaves 0)."""
    out = bytearray(data)
    start = out.index(b"index_pos=") + len("index_pos=")
    out[start:start + 8] = struct.pack("<Q", value)
    return bytes(out)


def index_pos(data: bytes) -> int:
    start = data.index(b"index_pos=") + len("index_pos=")
    return struct.unpack("<Q", data[start:start + 8])[0]


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A bag written by carto's writer (scans, odometry, IMU, static TF) and what it holds."""
    path = tmp_path_factory.mktemp("salvage") / "whole.bag"
    write_recording(iter(synthetic_records(n_scans=30)), path, "ros1", topics=TOPICS)
    return path, records_of(path)[0]


def test_a_recorders_active_file_gives_every_message(tmp_path, synthetic):
    """rosbag record killed: the header says no index (0) and the file ends after the last chunk."""
    path, whole = synthetic
    data = path.read_bytes()
    active = tmp_path / "run.bag.active"
    active.write_bytes(rewrite_index_pos(data, 0)[:index_pos(data)])
    got, warnings = records_of(active)
    same_records(got, whole)
    assert len(warnings) == 1 and "run.bag.active" in warnings[0] and "no index" in warnings[0]
    assert f"{len(got)} messages recovered" in warnings[0]


def test_an_intact_bag_is_still_read_by_rosbags(synthetic):
    path, _ = synthetic
    with open_recording(path) as rec:
        assert isinstance(rec, RosbagRecording) and rec.warnings == []


@pytest.mark.parametrize("compression", [None, Writer1.CompressionFormat.BZ2, Writer1.CompressionFormat.LZ4],
                         ids=["none", "bz2", "lz4"])
def test_a_cut_bag_gives_a_prefix_of_its_messages(tmp_path, compression):
    """Cut anywhere: the messages read are the first ones written, in order, and more the later the cut."""
    plain = tmp_path / "plain.bag"
    write_recording(iter(r for r in synthetic_records(n_scans=40) if isinstance(r, Scan)), plain, "ros1",
                    topics={"/scan": TOPICS["/scan"]})
    src = tmp_path / "src.bag"
    writer = Writer1(src)
    if compression is not None:
        writer.set_compression(compression)
    writer.chunk_threshold = 3000  # many chunks, so cuts fall inside and between them
    writer.open()
    with AnyReader([plain]) as reader:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest)
                 for c in reader.connections}
        for c, t, raw in reader.messages():
            writer.write(conns[c.id], t, raw)
    writer.close()
    records = records_of(plain)[0]
    whole, _ = records_of(src)
    assert len(whole) == len(records)
    data = src.read_bytes()
    counts = []
    for cut in range(200, len(data), max(1, len(data) // 23)):
        p = tmp_path / f"cut{cut}.bag"
        p.write_bytes(data[:cut])
        try:
            got, warnings = records_of(p)
        except FormatError as e:
            assert str(p) in str(e) and "no message could be recovered" in str(e)
            counts.append(0)
            continue
        same_records(got, whole[:len(got)])
        assert len(warnings) == 1 and p.name in warnings[0] and "cut short" in warnings[0]
        counts.append(len(got))
    assert counts == sorted(counts) and counts[-1] > 0.8 * len(records) and 0 in counts


@pytest.mark.skipif(not ORIG.exists(), reason="shared data not available")
def test_a_bag_with_a_damaged_index_reads_whole():
    """The CCNY demo bag as recorded in 2010 (index records with a wrong length) reads as its repaired copy."""
    with pytest.raises(FormatError):
        RosbagRecording(ORIG)
    got, warnings = records_of(ORIG)
    same_records(got, records_of(SAMPLE_BAG)[0])
    assert len(warnings) == 1 and "damaged index" in warnings[0] and "360 messages recovered" in warnings[0]


@pytest.mark.skipif(not ORIG.exists(), reason="shared data not available")
@pytest.mark.parametrize("out_name", ["repaired.bag", "repaired_ros2"])
def test_convert_repairs_a_damaged_bag_losslessly(tmp_path, out_name):
    """`carto convert damaged.bag repaired.bag` writes every recovered message's bytes and stamp again, with an
    index: the same messages as the hand-repaired sample."""
    out = tmp_path / out_name
    done = run_convert(ORIG, out)
    assert done.lossless and done.messages == 360 and done.warnings and "damaged index" in done.warnings[0]
    if out.suffix == ".bag":
        assert message_digest(out) == message_digest(SAMPLE_BAG)
        with open_recording(out) as rec:
            assert isinstance(rec, RosbagRecording)
    same_records(records_of(out)[0], records_of(SAMPLE_BAG)[0])


def test_info_reports_the_recovery(tmp_path, synthetic):
    path, _ = synthetic
    data = path.read_bytes()
    cut = tmp_path / "cut.bag"
    cut.write_bytes(data[: len(data) * 2 // 3])
    info = run_info(cut)
    assert any("cut.bag" in w and "messages recovered" in w for w in info.warnings)


def test_nothing_recoverable_is_a_format_error_naming_the_file(tmp_path):
    p = tmp_path / "empty.bag.active"
    p.write_bytes(b"#ROSBAG V2.0\n" + b"\xff" * 64)
    with pytest.raises(FormatError) as info:
        SalvagedBag(p)
    assert str(p) in str(info.value) and "no message could be recovered" in str(info.value)
