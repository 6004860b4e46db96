"""Choosing which topics feed SLAM: automatic when unambiguous, explicit otherwise."""
from __future__ import annotations

from dataclasses import dataclass

from carto_cli.core.errors import TopicError
from carto_cli.io.recording import Recording, TopicInfo


@dataclass(frozen=True)
class TopicSelection:
    scan: str
    odometry: str | None = None
    imu: str | None = None

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
        preferred = recording.preferred_topic(kind)
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
) -> TopicSelection:
    topics = recording.topics()
    scan = choose_topic(recording, topics, "scan", scan_topic, True)
    assert scan is not None  # a required topic that is missing raised TopicError
    odom = choose_topic(recording, topics, "odometry", odom_topic, False)
    imu = choose_topic(recording, topics, "imu", imu_topic, False)
    return TopicSelection(scan=scan, odometry=odom, imu=imu)
