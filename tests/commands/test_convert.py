"""`carto convert` as a library call: every supported topic by default, only the named ones otherwise."""
import pytest
from support import STATIC_TF

from carto_cli.commands.convert import run_convert
from carto_cli.core.errors import CartoError
from carto_cli.io.sources.open import open_recording


def test_everything_by_default_and_the_total_announced(tmp_path, written_recordings):
    records, paths = written_recordings
    totals, seen = [], []
    done = run_convert(paths["ros1"], tmp_path / "all.mcap", on_total=totals.append, on_record=lambda: seen.append(1))
    assert (done.format, done.out) == ("mcap", tmp_path / "all.mcap")
    assert totals == [len(records)] and len(seen) == len(records)
    assert done.messages == len(records) + 1  # and one /tf_static message with the static transforms
    with open_recording(done.out) as rec:
        assert sorted(t.name for t in rec.topics()) == ["/imu", "/odom", "/scan", "/tf_static"]
        assert len(rec.static_transforms()) == len(STATIC_TF)


def test_only_the_named_topics(tmp_path, written_recordings):
    records, paths = written_recordings
    done = run_convert(paths["mcap"], tmp_path / "scans.bag", scan_topic="scan")  # the leading slash may be left out
    assert done.messages == sum(r.topic == "/scan" for r in records) + 1 and done.format == "ros1"
    with open_recording(done.out) as rec:
        assert sorted(t.name for t in rec.topics()) == ["/scan", "/tf_static"]


def test_refusals(tmp_path, written_recordings):
    _, paths = written_recordings
    with pytest.raises(CartoError, match="unknown output format 'rosbag9'"):
        run_convert(tmp_path / "not-even-there.bag", tmp_path / "x.bag", fmt="rosbag9")  # checked before opening
    with pytest.raises(CartoError, match="no topic '/nope'"):
        run_convert(paths["ros1"], tmp_path / "y.bag", odom_topic="/nope")
    existing = tmp_path / "exists.bag"
    existing.write_bytes(b"keep me")
    with pytest.raises(CartoError):
        run_convert(paths["ros1"], existing)
    assert existing.read_bytes() == b"keep me"
    assert run_convert(paths["ros1"], existing, overwrite=True).messages > 0


def _messages(path):
    """{topic: [(bag time ns, header stamp ns or None, message type)]} read with rosbags itself."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    out = {}
    with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            header = getattr(msg, "header", None)
            if header is None and hasattr(msg, "transforms"):
                header = msg.transforms[0].header if len(msg.transforms) else None
            stamp = None if header is None else header.stamp.sec * 10**9 + header.stamp.nanosec
            out.setdefault(conn.topic, []).append((t, stamp, conn.msgtype.split("/")[-1]))
    return out


def test_ros1_to_ros2_and_back_loses_nothing(tmp_path, written_recordings):
    """Through rosbags' converter: every topic (also /tf, which carto itself does not map from), every stamp."""
    from carto_cli.core.records import Transform, yaw_quaternion
    from carto_cli.io.recording_writers import write_recording

    records, _ = written_recordings
    tf = [Transform("odom", "base_link", (0.1 * k, 0.0, 0.0), yaw_quaternion(0.01 * k), r.time, topic="/tf")
          for k, r in enumerate(records) if r.topic == "/odom"]
    source = tmp_path / "with_tf.bag"
    write_recording(iter(sorted([*records, *tf], key=lambda r: r.time)), source, "ros1", static_transforms=STATIC_TF)
    there = run_convert(source, tmp_path / "ros2")
    back = run_convert(there.out, tmp_path / "back.bag")
    assert there.lossless and back.lossless and there.format == "ros2-sqlite3" and back.format == "ros1"
    original, round_trip = _messages(source), _messages(back.out)
    assert sorted(original) == sorted(round_trip) == ["/imu", "/odom", "/scan", "/tf", "/tf_static"]
    assert original == round_trip
    assert there.messages == sum(len(v) for v in original.values())


def test_the_writer_says_which_topics_it_left_out(tmp_path, written_recordings):
    from carto_cli.core.records import Transform, yaw_quaternion
    from carto_cli.io.recording_writers import write_recording

    records, _ = written_recordings
    tf = [Transform("odom", "base_link", (0.0, 0.0, 0.0), yaw_quaternion(0.0), records[0].time, topic="/tf")]
    source = tmp_path / "with_tf.bag"
    write_recording(iter([*tf, *records]), source, "ros1", static_transforms=STATIC_TF)
    done = run_convert(source, tmp_path / "out.mcap")  # MCAP: carto's writer
    assert not done.lossless and done.left_out == ("/tf",)


@pytest.fixture(scope="module")
def carmen(tmp_path_factory):
    from support import sim_carmen_log

    return sim_carmen_log(tmp_path_factory.mktemp("carmen") / "loop.clf")


def test_carmen_converted_to_bag_maps_with_no_flags(tmp_path, carmen):
    from typer.testing import CliRunner

    from carto_cli.cli import app

    bag = run_convert(carmen, tmp_path / "loop.bag").out
    with open_recording(bag) as rec:
        assert {"/odom", "/odom_laser"} <= {t.name for t in rec.topics()}  # both kept: nothing is lost
    r = CliRunner().invoke(app, ["map", str(bag), "-o", str(tmp_path / "map")])
    assert r.exit_code == 0, r.output
    assert (tmp_path / "map" / "map.carto").is_file()


@pytest.mark.parametrize("fmt, name", [("ros1", "loop.bag"), ("ros2-sqlite3", "db3"), ("ros2-mcap", "ros2mcap"),
                                       ("mcap", "loop.mcap")])
def test_carmen_converted_to_every_format_is_read_as_the_log_is(tmp_path, carmen, fmt, name):
    from carto_cli.commands.info import run_info
    from carto_cli.io.topics import select_topics

    def order(rec, topics):
        return [(r.topic, round(r.time, 6)) for r in rec.records(topics)]

    out = run_convert(carmen, tmp_path / name, fmt=fmt).out
    with open_recording(carmen) as log, open_recording(out) as converted:
        selection = select_topics(log)
        assert select_topics(converted) == selection
        # Each scan's odometry, stamped as the scan, still comes first (what the extrapolator is fed).
        assert order(converted, selection.topics) == order(log, selection.topics)
    info = run_info(out)
    assert info.auto is not None and info.odometry_source == "/odom_laser"
