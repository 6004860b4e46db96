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
