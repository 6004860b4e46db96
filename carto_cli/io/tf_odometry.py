"""Odometry as most ROS robots record it: only in dynamic TF (/tf: odom -> base_link), with no Odometry topic.

``find_tf_odometry`` reads the start of the recording's /tf and picks the transform that is odometry: its parent
is the odometry frame (``--odom-frame``, else a frame named like ``odom``) and its child the robot's base
(``--base-frame``, else the root of the static tree the laser hangs from, else base_footprint / base_link, ...).
``tf_as_odometry`` then turns those transforms into Odometry records as the stream goes by; every other
transform is dropped. The transforms of /tf that never change (a laser mount broadcast on /tf instead of
/tf_static, as some drivers do) are kept as ``TfOdometry.fixed`` so the laser can be placed from them.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

from carto_cli.core.errors import TopicError
from carto_cli.core.records import Odometry, Record, Transform, strip_frame
from carto_cli.io.recording import Recording, head
from carto_cli.io.tf_tree import TRACKING_FRAMES, parent_map

__all__ = ["TfOdometry", "find_tf_odometry", "tf_as_odometry"]

SAMPLE = 500  # transforms read from the start of /tf to find the odometry edge
_FIXED_M = 1e-6  # a /tf transform that moves less than this (and turns less than _FIXED_RAD) is a fixed mount
_FIXED_RAD = 1e-6


@dataclass(frozen=True)
class TfOdometry:
    topic: str  # the TF topic
    odom_frame: str
    base_frame: str
    fixed: tuple[Transform, ...] = field(default=())  # /tf transforms that never moved in the sample

    def describe(self) -> str:
        return f"{self.topic} ({self.odom_frame} -> {self.base_frame})"


def _tf_topics(recording: Recording) -> list[str]:
    return [t.name for t in recording.topics() if t.kind == "tf" and t.count > 0]


def find_tf_odometry(recording: Recording, *, odom_frame: str | None = None, base_frame: str | None = None,
                     laser_frame: str | None = None) -> TfOdometry | None:
    """The odometry edge of the recording's dynamic TF (module doc), or None when there is none.

    With ``odom_frame`` / ``base_frame`` given, a TopicError says which edges exist when none matches.
    """
    topics = _tf_topics(recording)
    if not topics:
        if odom_frame or base_frame:
            raise TopicError("--odom-frame / --base-frame: the recording has no /tf topic", recording.path)
        return None
    topic = "/tf" if "/tf" in topics else topics[0]
    sample = [r for r in head(recording, [topic], SAMPLE) if isinstance(r, Transform)]
    edges: dict[tuple[str, str], list[Transform]] = {}
    for tf in sample:
        edges.setdefault((strip_frame(tf.parent), strip_frame(tf.child)), []).append(tf)
    fixed = tuple(v[-1] for v in edges.values() if _never_moved(v))
    want_odom = strip_frame(odom_frame) if odom_frame else None
    want_base = strip_frame(base_frame) if base_frame else None
    # Any edge may be odometry, even one that did not move in the sample (a robot standing still at the start).
    candidates = [(p, c) for p, c in edges
                  if (p == want_odom if want_odom else "odom" in p.lower())
                  and (c == want_base if want_base else True)]
    if not candidates:
        if odom_frame or base_frame:
            seen = ", ".join(f"{p} -> {c}" for p, c in edges) or "none"
            raise TopicError(f"no transform {want_odom or 'odom*'} -> {want_base or '*'} on {topic} "
                             f"(its transforms: {seen})", recording.path)
        return None
    # The base: the frame the laser's static chain ends in, else the usual tracking frames, else the first.
    root = _static_root(recording, laser_frame, fixed)
    candidates.sort(key=lambda e: (e[1] != root, _rank(e[1]), e))
    p, c = candidates[0]
    return TfOdometry(topic, p, c, tuple(tf for tf in fixed if (strip_frame(tf.parent), strip_frame(tf.child))
                                         != (p, c)))


def _rank(frame: str) -> int:
    return TRACKING_FRAMES.index(frame) if frame in TRACKING_FRAMES else len(TRACKING_FRAMES)


def _never_moved(tfs: list[Transform]) -> bool:
    if len(tfs) < 2:
        return False
    a = tfs[0].pose2d()
    return all(math.hypot(t.pose2d()[0] - a[0], t.pose2d()[1] - a[1]) < _FIXED_M
               and abs(t.pose2d()[2] - a[2]) < _FIXED_RAD for t in tfs[1:])


def _static_root(recording: Recording, laser_frame: str | None, fixed: tuple[Transform, ...]) -> str | None:
    if not laser_frame:
        return None
    parents = parent_map(list(recording.static_transforms()) + list(fixed))
    frame = strip_frame(laser_frame)
    seen = {frame}
    while frame in parents:
        frame = parents[frame][0]
        if frame in seen:
            return None
        seen.add(frame)
    return frame


def tf_as_odometry(records: Iterable[Record], tf_odometry: TfOdometry) -> Iterator[Record]:
    """``records`` with the odometry transforms of ``tf_odometry`` as Odometry records and every other transform
    of its topic dropped."""
    edge = (tf_odometry.odom_frame, tf_odometry.base_frame)
    for rec in records:
        if isinstance(rec, Transform):
            if rec.topic == tf_odometry.topic and (strip_frame(rec.parent), strip_frame(rec.child)) == edge:
                x, y, yaw = rec.pose2d()
                yield Odometry(rec.time, x, y, yaw, frame=edge[0], child_frame=edge[1], topic=rec.topic)
            continue
        yield rec
