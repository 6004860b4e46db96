import gzip

import pytest
from support import SAMPLE_BAG, shared_path

from carto_cli.core.errors import CartoError, FormatError
from carto_cli.io.sources.open import detect_format, open_recording


def test_detects_every_real_format():
    assert detect_format(SAMPLE_BAG) == "ros1"
    assert detect_format(shared_path("bags", "ccny_laser_scan_matcher_demo_ros2_db3")) == "ros2-sqlite3"
    mcap_dir = shared_path("bags", "ccny_laser_scan_matcher_demo_ros2_mcap")
    assert detect_format(mcap_dir) == "ros2-mcap"
    assert detect_format(mcap_dir / "ccny_laser_scan_matcher_demo_ros2_mcap.mcap") == "mcap"
    assert detect_format(shared_path("bench", "intel", "scans.clf.gz")) == "carmen"


def test_db3_file_opens_its_bag_directory():
    db3 = shared_path("bags", "ccny_laser_scan_matcher_demo_ros2_db3", "ccny_laser_scan_matcher_demo_ros2_db3.db3")
    with open_recording(db3) as rec:
        assert rec.format == "ros2-sqlite3"


def test_missing_path(tmp_path):
    with pytest.raises(CartoError, match="no such file"):
        detect_format(tmp_path / "nope.bag")


def test_unknown_format_names_the_file(tmp_path):
    p = tmp_path / "notes.txt"
    p.write_text("hello")
    with pytest.raises(FormatError) as e:
        detect_format(p)
    assert str(p) in str(e.value)
    assert "unknown recording format" in str(e.value)


@pytest.mark.parametrize("name", ["fake.bag", "fake.mcap"])
def test_wrong_magic(tmp_path, name):
    p = tmp_path / name
    p.write_bytes(b"this is not a recording at all")
    with pytest.raises(FormatError):
        detect_format(p)


def test_directory_without_metadata(tmp_path):
    with pytest.raises(FormatError, match="metadata.yaml"):
        detect_format(tmp_path)


def test_gzip_detected_by_magic(tmp_path):
    p = tmp_path / "log.data"
    with gzip.open(p, "wt") as f:
        f.write("ODOM 0 0 0 0 0 0 1.0 host 1.0\n")
    assert detect_format(p) == "carmen"
