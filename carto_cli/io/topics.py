"""Choosing which topics feed SLAM: automatic when unambiguous, explicit otherwise."""
from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from carto_cli.core.errors import TopicError
from carto_cli.core.records import Record
from carto_cli.io.recording import SCAN_TIME_ODOMETRY, Recording, TopicInfo, first_scan_frame
from carto_cli.io.tf_odometry import TfOdometry, find_tf_odometry, tf_as_odometry


@dataclass(frozen=True)
class TopicSelection:
    scan: str
    odometry: str | None = None  # an Odometry topic, or the TF topic when ``tf_odometry`` is set
    imu: str | None = None
    tf_odometry: TfOdometry | None = None  # odometry read from dynamic TF (io.tf_odometry)

    def describe_odometry(self) -> str:
        if self.tf_odometry is not None:
            return f"from TF {self.tf_odometry.describe()}"
        return self.odometry or "none"

    @property
    def topics(self) -> list[str]:
        return [t for t in (self.scan, self.odometry, self.imu) if t]


_FLAGS = {"scan": "--scan-topic", "odometry": "--odom-topic", "imu": "--imu-topic"}


def choose_topic(recording: Recording, topics: list[TopicInfo], kind: str, wanted: str | None,
                 required: bool) -> str | None:
    candidates = [t for t in topics if t.kind == kind and t.count > 0]
    if wanted is not None:
        by_name = {t.name: t for t in topics}
        # ROS1 users often type topics without the leading slash.
        match = by_name.get(wanted) or by_name.get("/" + wanted.lstrip("/"))
        if match is None:
            names = ", ".join(t.name for t in candidates) or "none"
            raise TopicError(f"no topic '{wanted}' ({kind} topics: {names})", recording.path)
        if match.kind != kind:
            raise TopicError(
                f"topic '{match.name}' is {match.msgtype}, not a supported {kind} type", recording.path
            )
        return match.name
    if not candidates:
        if required:
            others = ", ".join(f"{t.name} ({t.msgtype})" for t in topics) or "no topics at all"
            raise TopicError(f"no laser scan topic (LaserScan, MultiEchoLaserScan or PointCloud2); found {others}",
                             recording.path)
        return None
    if len(candidates) > 1:
        for preferred in (recording.preferred_topic(kind), SCAN_TIME_ODOMETRY if kind == "odometry" else None):
            if preferred is not None and any(t.name == preferred for t in candidates):
                return preferred
        names = ", ".join(f"{t.name} ({t.count} msgs)" for t in candidates)
        raise TopicError(f"several {kind} topics, choose one with {_FLAGS[kind]}: {names}", recording.path)
    return candidates[0].name


def select_topics(
    recording: Recording,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    imu_topic: str | None = None,
    *,
    odom_frame: str | None = None,
    base_frame: str | None = None,
) -> TopicSelection:
    """The scan, odometry and IMU topics. Without an Odometry topic (or with ``odom_frame`` / ``base_frame``
    given), odometry comes from dynamic TF when /tf carries an odom -> base transform (``io.tf_odometry``)."""
    topics = recording.topics()
    scan = choose_topic(recording, topics, "scan", scan_topic, True)
    assert scan is not None  # a required topic that is missing raised TopicError
    imu = choose_topic(recording, topics, "imu", imu_topic, False)
    if odom_topic is not None and (odom_frame or base_frame):
        raise TopicError("--odom-topic and --odom-frame / --base-frame exclude each other", recording.path)
    odom = None if (odom_frame or base_frame) else choose_topic(recording, topics, "odometry", odom_topic, False)
    if odom is None and odom_topic is None and (odom_frame or base_frame or any(t.kind == "tf" for t in topics)):
        laser = first_scan_frame(recording, scan)
        tf = find_tf_odometry(recording, odom_frame=odom_frame, base_frame=base_frame, laser_frame=laser)
        if tf is not None:
            return TopicSelection(scan=scan, odometry=tf.topic, imu=imu, tf_odometry=tf)
    return TopicSelection(scan=scan, odometry=odom, imu=imu)


def selected_records(recording: Recording, selection: TopicSelection,
                     topics: Sequence[str] | None = None) -> Iterator[Record]:
    """``recording.records(topics)`` (default: the selection's), with odometry from TF turned into Odometry."""
    topics = list(selection.topics if topics is None else topics)
    records = recording.records(topics)
    if selection.tf_odometry is not None and selection.odometry in topics:
        return tf_as_odometry(records, selection.tf_odometry)
    return records
