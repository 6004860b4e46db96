"""`carto convert` as a library call: a recording in another format.

ROS1 <-> ROS2 with every topic goes through rosbags' converter, losing nothing (every topic, message and
stamp as recorded). A ROS1 bag read without its index (cut, or a recorder's .bag.active) is written again
whole from what its chunks held, with a new index, before any conversion. Anything else (MCAP, CARMEN,
chosen topics) goes through carto's writer, which carries scans, odometry, IMU and static TF and says which
topics it left out."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from carto_cli.io.recording import ReadOptions
from carto_cli.io.recording_writers import convert_bag, format_for_output, repair_bag, write_recording
from carto_cli.io.sources.open import open_recording
from carto_cli.io.sources.ros1_salvage import SalvagedBag
from carto_cli.io.sources.rosbag import RosbagRecording
from carto_cli.io.topics import choose_topic

__all__ = ["Converted", "run_convert"]


@dataclass(frozen=True)
class Converted:
    messages: int
    out: Path
    format: str
    lossless: bool = False  # every topic and stamp as recorded (rosbags' converter)
    left_out: tuple[str, ...] = ()  # topics of the source not written (carto's writer)
    warnings: tuple[str, ...] = ()  # what reading the source had to work around (a damaged bag)


def run_convert(
    source: str | Path,
    out: str | Path,
    *,
    fmt: str | None = None,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    imu_topic: str | None = None,
    overwrite: bool = False,
    read: ReadOptions | None = None,
    on_total: Callable[[int], None] | None = None,
    on_record: Callable[[], None] | None = None,
) -> Converted:
    """Write ``source`` to ``out`` in ``fmt`` (default: from ``out``'s suffix).

    With no topic given every scan, odometry and IMU topic is copied; with any given, only
    the given ones. ``on_total`` hears how many messages will be written.
    """
    out = Path(out)
    out_format = format_for_output(out, fmt)
    with open_recording(source, read) as rec:
        topics = rec.topics()
        ros2 = ("ros2-sqlite3", "ros2-mcap")
        whole = scan_topic is None and odom_topic is None and imu_topic is None
        warnings = tuple(rec.warnings)
        if whole and isinstance(rec, SalvagedBag) and out_format in ("ros1",) + ros2:
            if on_total is not None:
                on_total(sum(t.count for t in topics))
            n = repair_bag(rec, out, out_format, overwrite=overwrite, on_record=on_record)
            return Converted(n, out, out_format, lossless=True, warnings=warnings)
        if whole and ((rec.format == "ros1" and out_format in ros2) or (rec.format in ros2 and out_format == "ros1")):
            total = sum(t.count for t in topics)
            if on_total is not None:
                on_total(total)
            assert isinstance(rec, RosbagRecording)  # what opens ROS1 and ROS2 bags (SalvagedBag went above)
            convert_bag(rec.sources, out, out_format, overwrite=overwrite)
            return Converted(total, out, out_format, lossless=True, warnings=warnings)
        chosen: list[str] = []
        for kind, wanted in (("scan", scan_topic), ("odometry", odom_topic), ("imu", imu_topic)):
            if wanted is not None:
                name = choose_topic(rec, topics, kind, wanted, True)
                assert name is not None  # a named topic is found or refused
                chosen.append(name)
            elif not any(w is not None for w in (scan_topic, odom_topic, imu_topic)):
                chosen.extend(t.name for t in topics if t.kind == kind)
        types = {t.name: t.msgtype for t in topics}
        if on_total is not None:
            on_total(sum(t.count for t in topics if t.name in chosen))
        n = write_recording(
            rec.records(chosen), out, out_format,
            static_transforms=rec.static_transforms(), topics={t: types[t] for t in chosen},
            on_record=on_record, overwrite=overwrite,
        )
        left_out = tuple(t.name for t in topics if t.name not in chosen and t.kind != "tf_static")
    return Converted(n, out, out_format, left_out=left_out, warnings=warnings)
