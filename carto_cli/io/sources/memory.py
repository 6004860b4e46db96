"""A recording held in memory: records a program made (``carto_cli.api.map_records``), behind ``Recording``."""
from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path

from carto_cli.core.errors import CartoError, TopicError
from carto_cli.core.records import Imu, Odometry, Record, Scan, Transform
from carto_cli.io.recording import ReadOptions, Recording, TopicInfo

__all__ = ["MemoryRecording"]

_TYPES = {Scan: "sensor_msgs/msg/LaserScan", Odometry: "nav_msgs/msg/Odometry", Imu: "sensor_msgs/msg/Imu"}
_DEFAULT_TOPICS = {Scan: "/scan", Odometry: "/odom", Imu: "/imu"}


class MemoryRecording(Recording):
    """``records`` (Scan / Odometry / Imu, sorted here by time, stably) and the laser mount as static transforms.

    A record without a topic goes to /scan, /odom or /imu by its kind.
    """

    format = "memory"

    def __init__(self, records: Iterable[Record], static_transforms: Sequence[Transform] = (), *,
                 name: str = "memory", options: ReadOptions | None = None):
        super().__init__(Path(name), options)
        kept: list[tuple[str, Record]] = []
        for r in records:
            kind = type(r)
            if kind not in _TYPES:
                raise CartoError(f"a recording in memory holds scans, odometry and IMU, not {kind.__name__}")
            topic = r.topic or _DEFAULT_TOPICS[kind]
            # Every reader names a record's topic; what reads records (io.content) tells streams apart by it.
            kept.append((topic, r if r.topic else dataclasses.replace(r, topic=topic)))
        kept.sort(key=lambda tr: tr[1].time)
        self._records = kept
        self._static = list(static_transforms)

    def topics(self) -> list[TopicInfo]:
        counts: dict[str, tuple[str, int]] = {}
        for topic, r in self._records:
            msgtype, n = counts.get(topic, (_TYPES[type(r)], 0))
            counts[topic] = (msgtype, n + 1)
        return [TopicInfo(t, msgtype, n) for t, (msgtype, n) in sorted(counts.items())]

    def static_transforms(self) -> list[Transform]:
        return list(self._static)

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        available = {t for t, _ in self._records}
        wanted = available if topics is None else set(topics)
        unknown = wanted - available
        if unknown:
            raise TopicError(f"no topic {', '.join(sorted(unknown))} in the recording", self.path)
        return (r for t, r in self._records if t in wanted)
