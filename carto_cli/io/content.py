"""Bad content in a readable file: what carto drops before mapping, and the one warning line per kind.

A recording can be a valid bag and still hold messages nothing can use: a clock that jumps back, the same
stamp twice, an odometry pose of NaN, a scan without beams or with an angle increment of zero, scans of two
lasers published on one topic. ``ContentCheck.filter`` passes on what carto can use, in the reader's order,
and counts what it drops, so that ``carto map`` and ``carto info`` report the same thing once per kind
("/scan: 3 scans with no beams dropped") instead of a traceback, a hang or a silently wrong map.

What is dropped, per topic:

* a message whose time is not finite, or not later than the previous kept one on its topic (time going
  backwards, or the same stamp again: a duplicated message);
* odometry or IMU with a non-finite value;
* a scan with no beams, a laser scan with an angle increment of 0 (every beam on one bearing) or more than
  ``MAX_BEAMS`` beams (no 2D scanner has that many: a corrupt length);
* scans in a frame other than the topic's first scan's (two lasers on one topic: the first one is mapped).

Kept but reported: scans with no frame id (the laser mount then comes from --laser-pose or is identity) and
laser scans with a negative angle increment (beams clockwise: the bearings say so, nothing is wrong).
"""
from __future__ import annotations

import math
from collections import Counter
from collections.abc import Iterable, Iterator

import numpy as np

from carto_cli.core.records import Imu, Odometry, Record, Scan

__all__ = ["MAX_BEAMS", "ContentCheck"]

MAX_BEAMS = 100_000

_DROPPED = {
    "time": "{n} message(s) with a time that is not finite dropped",
    "backwards": "{n} message(s) older than the one before on the topic dropped (time goes backwards)",
    "duplicate": "{n} message(s) with the same stamp as the one before dropped (duplicated)",
    "odometry": "{n} odometry message(s) with a NaN or infinite value dropped",
    "imu": "{n} IMU message(s) with a NaN or infinite value dropped",
    "no_beams": "{n} scan(s) with no beams dropped",
    "zero_increment": "{n} scan(s) with angle_increment 0 dropped (every beam on one bearing)",
    "too_many_beams": "{n} scan(s) with over " + f"{MAX_BEAMS:,}" + " beams dropped (a corrupt length)",
    "other_frame": "{n} scan(s) from frame(s) {frames} dropped: two lasers on one topic, the first one "
                   "({first}) is mapped",
}
_KEPT = {
    "no_frame": "{n} scan(s) without a frame id (the laser mount comes from --laser-pose, or is identity)",
    "negative_increment": "{n} scan(s) with a negative angle_increment (beams clockwise), used as they are",
}


class ContentCheck:
    """Filter one pass over a recording's records; ``warnings()`` after it says what was dropped or odd."""

    def __init__(self) -> None:
        self.counts: Counter[tuple[str, str]] = Counter()  # (topic, kind) -> messages
        self._last: dict[str, float] = {}
        self._first_frame: dict[str, str] = {}
        self._other_frames: dict[str, set[str]] = {}

    def filter(self, records: Iterable[Record]) -> Iterator[Record]:
        """The records carto can use, in their order."""
        return (record for record in records if self.accept(record))

    def accept(self, record: Record) -> bool:
        """Whether carto uses ``record`` (counted when not); records are judged in their order."""
        kind = self._problem(record)
        if kind is not None:
            self.counts[(getattr(record, "topic", ""), kind)] += 1
        return kind is None

    def _problem(self, record) -> str | None:
        if not isinstance(record, (Scan, Odometry, Imu)):
            return None  # transforms and the like: not the stream's business
        topic = record.topic
        t = record.time
        if not math.isfinite(t):
            return "time"
        last = self._last.get(topic)
        if last is not None and t <= last:
            return "backwards" if t < last else "duplicate"
        if isinstance(record, Odometry):
            if not all(math.isfinite(v) for v in (record.x, record.y, record.yaw, record.vx, record.vy, record.wz)):
                return "odometry"
        elif isinstance(record, Imu):
            values = [record.angular_velocity, record.linear_acceleration]
            if record.orientation is not None:
                values.append(record.orientation)
            if not all(np.isfinite(v).all() for v in values):
                return "imu"
        else:
            problem = self._scan_problem(record)
            if problem is not None:
                return problem
        self._last[topic] = t
        return None

    def _scan_problem(self, scan: Scan) -> str | None:
        n = scan.num_beams
        if n == 0:
            return "no_beams"
        if scan.angle_increment is not None:
            if scan.angle_increment == 0.0 and n > 1:
                return "zero_increment"
            if n > MAX_BEAMS:
                return "too_many_beams"
        first = self._first_frame.setdefault(scan.topic, scan.frame)
        if scan.frame != first:
            self._other_frames.setdefault(scan.topic, set()).add(scan.frame)
            return "other_frame"
        if not scan.frame:
            self.counts[(scan.topic, "no_frame")] += 1
        if scan.angle_increment is not None and scan.angle_increment < 0.0:
            self.counts[(scan.topic, "negative_increment")] += 1
        return None

    def warnings(self) -> list[str]:
        """One line per topic and kind, in a fixed order: 'TOPIC: N ... dropped'."""
        out = []
        for (topic, kind), n in sorted(self.counts.items()):
            text = _DROPPED.get(kind) or _KEPT[kind]
            frames = ", ".join(sorted(f or "''" for f in self._other_frames.get(topic, ())))
            out.append(f"{topic or '(no topic)'}: " + text.format(n=n, frames=frames,
                                                                   first=self._first_frame.get(topic) or "''"))
        return out

    @property
    def dropped(self) -> int:
        return sum(n for (_, kind), n in self.counts.items() if kind in _DROPPED)
