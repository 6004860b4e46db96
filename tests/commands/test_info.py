"""carto info's summary: rates, scan geometry, and the warnings it must raise."""
import math

import numpy as np
import pytest

from carto_cli.commands.info import format_info, inspect_recording, run_info
from carto_cli.core.errors import CartoError
from carto_cli.core.records import Odometry, Scan, Transform
from carto_cli.io.recording import Recording, TopicInfo


class ListRecording(Recording):
    format = "test"

    def __init__(self, records, transforms=()):
        super().__init__("list.bag")
        self._records = records
        self._transforms = list(transforms)

    def topics(self):
        counts = {}
        for r in self._records:
            kind = "sensor_msgs/msg/LaserScan" if isinstance(r, Scan) else "nav_msgs/msg/Odometry"
            counts.setdefault(r.topic, [kind, 0])[1] += 1
        return [TopicInfo(n, t, c) for n, (t, c) in counts.items()]

    def static_transforms(self):
        return self._transforms

    def records(self, topics=None):
        return iter(r for r in self._records if topics is None or r.topic in topics)


def scan(t, ranges):
    r = np.asarray(ranges, np.float32)
    return Scan(time=t, ranges=r, angles=np.linspace(-1, 1, len(r)).astype(np.float32), frame="laser",
                topic="/scan", range_min=0.1, range_max=10.0)


def test_rates_geometry_and_warnings():
    times = [0.0, 0.1, 0.2, 0.3, 1.5, 1.6, 1.55, 1.7]  # a 1.2 s gap, and one step backwards
    records = [scan(t, [1.0, np.nan, np.inf, 20.0, 2.0]) for t in times]
    records += [Odometry(time=0.01 * k, x=0, y=0, yaw=0, topic="/odom") for k in range(50)]
    tf = [Transform("base_link", "laser", (0.2, 0.0, 0.1), (0.0, 0.0, math.sin(0.1), math.cos(0.1)))]
    info = inspect_recording(ListRecording(records, tf))
    (s,) = [t for t in info.topics if t.kind == "scan"]
    assert s.count == 8 and s.scan.beams_min == s.scan.beams_max == 5
    assert s.backwards == 1 and s.gaps == 1 and 1.1 < s.max_gap < 1.3
    warnings = " | ".join(info.warnings)
    assert "time goes backwards" in warnings and "gap" in warnings
    assert "20.0% of ranges are NaN" in warnings and "20.0% of ranges are Inf" in warnings
    assert "20.0% of ranges are out-of-limit" in warnings
    assert info.has_odometry and not info.has_imu
    (o,) = [t for t in info.topics if t.kind == "odometry"]
    assert abs(o.rate_hz - 100.0) < 1e-6
    text = format_info(info)
    assert "base_link" in text and "laser" in text and "yaw 11.46°" in text


def test_no_scans_is_a_warning():
    info = inspect_recording(ListRecording([Odometry(time=0.0, x=0, y=0, yaw=0, topic="/odom")]))
    assert any("no laser scans" in w for w in info.warnings)


def test_run_info_opens_the_file_and_announces_what_it_will_read(written_recordings):
    records, paths = written_recordings
    totals, seen = [], []
    info = run_info(paths["mcap"], on_total=totals.append, on_record=lambda: seen.append(1))
    assert totals == [len(records)] and len(seen) == len(records)
    assert info.format == "mcap" and info.has_odometry and info.has_imu
    assert {t.name: t.count for t in info.topics} == {"/scan": 20, "/odom": 100, "/imu": 200, "/tf_static": 1}


def test_run_info_on_a_missing_file(tmp_path):
    with pytest.raises(CartoError, match="no such file"):
        run_info(tmp_path / "missing.bag")


def test_info_says_why_auto_cannot_choose(tmp_path):
    from dataclasses import replace

    from support import STATIC_TF, synthetic_records

    from carto_cli.io.recording_writers import write_recording

    records = synthetic_records(n_scans=5)
    records += [replace(r, topic="/odometry/filtered") for r in records if isinstance(r, Odometry)]
    records.sort(key=lambda r: r.time)
    path = tmp_path / "two_odometries.mcap"
    write_recording(iter(records), path, "mcap", static_transforms=STATIC_TF,
                    topics={"/scan": "sensor_msgs/msg/LaserScan", "/odom": "nav_msgs/msg/Odometry",
                            "/imu": "sensor_msgs/msg/Imu", "/odometry/filtered": "nav_msgs/msg/Odometry"})
    info = run_info(path)
    assert info.auto is None
    assert info.auto_unavailable == ("several odometry topics, choose one with --odom-topic: /odom (25 msgs), "
                                     "/odometry/filtered (25 msgs)")
    assert f"auto       none: {info.auto_unavailable}" in format_info(info).splitlines()


def test_info_shows_every_lasers_mount(tmp_path):
    """Two lasers on two topics (front and back, each with its static TF): info places each as `carto map` would
    place it, and says that mapping merges both."""
    from dataclasses import replace

    from support import synthetic_records

    from carto_cli.core.records import yaw_quaternion
    from carto_cli.io.recording_writers import write_recording

    records = synthetic_records(n_scans=5)
    records += [replace(r, topic="/scan_back", frame="laser_back", time=r.time + 0.05) for r in records
                if isinstance(r, Scan)]
    records = [replace(r, topic="/scan_front", frame="laser_front") if isinstance(r, Scan) and r.topic == "/scan"
               else r for r in records]
    records.sort(key=lambda r: r.time)
    mounts = [Transform("base_link", "laser_front", (0.3, 0.05, 0.2), yaw_quaternion(0.0)),
              Transform("base_link", "laser_back", (-0.3, -0.05, 0.2), yaw_quaternion(math.pi))]
    path = tmp_path / "two_lasers.mcap"
    write_recording(iter(records), path, "mcap", static_transforms=mounts,
                    topics={"/scan_front": "sensor_msgs/msg/LaserScan", "/scan_back": "sensor_msgs/msg/LaserScan",
                            "/odom": "nav_msgs/msg/Odometry", "/imu": "sensor_msgs/msg/Imu"})
    info = run_info(path)
    placed = {t.name: t.scan.mounts for t in info.topics if t.scan is not None}
    (front,), (back,) = placed["/scan_front"], placed["/scan_back"]
    assert (front["frame"], front["x"], front["y"], front["yaw_deg"]) == ("laser_front", 0.3, 0.05, 0.0)
    assert back["frame"] == "laser_back" and (back["x"], back["y"]) == (-0.3, -0.05)
    assert abs(abs(back["yaw_deg"]) - 180.0) < 1e-6
    assert front["source"] == "static TF base_link -> laser_front"
    text = format_info(info)
    assert "mount laser_back: x -0.300 m, y -0.050 m, yaw" in text
    assert info.auto is not None and "2 lasers merged (/scan_back, /scan_front)" in info.auto["detected"]
    assert info.auto["regime"]["lasers"] == ["/scan_back", "/scan_front"]
