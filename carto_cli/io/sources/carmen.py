"""CARMEN log files (``.clf`` / ``.log``, plain or gzipped) as a ``Recording``.

Message types read (everything else — PARAM, SYNC, TRUEPOS, NEFF, comments —
is skipped):

=============  ============  ==========================================
message        topic         notes
=============  ============  ==========================================
ROBOTLASER1    /scan         preferred source of /scan when present
FLASER         /scan         used when there is no ROBOTLASER1
RAWLASER1      /scan         used when there is neither of the above
ROBOTLASER2    /scan_rear    preferred source of /scan_rear
RLASER         /scan_rear
RAWLASER2..4   /scan2../scan4
ODOM           /odom
(laser poses)  /odom_laser   robot pose carried by the laser lines above
=============  ============  ==========================================

A topic takes its messages from one source only because newer CARMEN loggers
write the same laser as both ROBOTLASER1 and RAWLASER1, and converted logs
often carry FLASER and ROBOTLASER1 side by side: taking all would duplicate
every scan.

Beam angles: CARMEN's own reader's (``carmen_lines``). The rear laser gets the
same angles in its own frame (``laser_rear``), which the static transform
turns by pi.

Odometry inside laser lines: FLASER / RLASER carry the odometry pose of the
robot when the scan was taken and ROBOTLASER the robot pose plus tv / rv.
Each such line (front and rear laser alike) yields an ``Odometry`` on
``/odom_laser`` *before* its scan, with the scan's time (velocities from
ROBOTLASER's tv / rv; FLASER has none, so they are 0): the pose is then
exactly at the scan time, and an extrapolator fed in record order already has
it when the scan arrives. It is
a topic of its own rather than being mixed into ``/odom`` because the two
often disagree (the Radish "corrected" logs hold raw odometry in ODOM and the
corrected pose in FLASER), and a consumer must pick one stream, not a blend.

The laser's mount (``base_link -> laser``) comes from the difference between
the laser pose and the robot pose of the first laser lines, when it is the
same on all of them; otherwise (no difference, or one that varies because the
"laser pose" is really a corrected pose) it is the identity, and pi of yaw for
the rear laser.

Time order: a record's time is the message's own ``timestamp`` field (the
first one after the payload). Real logs are not always in that order, so
lines pass through a reordering window of ``REORDER_WINDOW`` seconds; a line
older than a record already delivered is dropped and counted in
``CarmenRecording.dropped`` (the Radish corrected logs hold one such ODOM per
scan, stamped 0). ``topics()`` counts what ``records()`` delivers.

Strictness: every line read is checked field by field (``carmen_lines``): bad
content is a ``FormatError`` naming the file and line wherever it is. A file
cut short is not bad content: as a bag or an MCAP file cut short,
it is read up to the cut with one warning in ``Recording.warnings`` (the
messages recovered). The cut is where the file ends: a last line without its
end of line that does not parse (a cut anywhere loses at least one field,
unless it falls inside the final ``logger_timestamp``, which carto does not
use, and the line then parses), or a gzip stream that ends before its end
marker (its partial last line is lost, the lines before it are whole). The
survey finds the cut, and every pass stops before it, so every command reads
the same messages whatever topics it asks for.
"""
from __future__ import annotations

import gzip
import heapq
import math
import zlib
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carto_cli.core.errors import CartoError, FormatError, TopicError
from carto_cli.core.records import Odometry, Record, Scan, Transform, yaw_quaternion
from carto_cli.core.transform import wrap_angle_scalar
from carto_cli.io.recording import SCAN_TIME_ODOMETRY, ReadOptions, Recording, TopicInfo
from carto_cli.io.sources.carmen_lines import (
    TRAILER,
    LineError,
    LogLines,
    OdomLine,
    diagnose,
    first_token,
    is_gzip,
    line_time,
    parse_line,
)
from carto_cli.io.sources.decimals import decimals

REORDER_WINDOW = 2.0  # s; the Radish logs step back by up to ~0.9 s
POSE_PROBE = 20  # laser lines inspected for the mount transform
MOUNT_TOLERANCE = 0.01  # m and rad; the Radish logs print poses with 6 digits

SCAN_MSGTYPE = "sensor_msgs/msg/LaserScan"
ODOM_MSGTYPE = "nav_msgs/msg/Odometry"
# The pose in each laser line was logged with that scan, so it needs no interpolation, and in corrected logs ODOM
# lines are often zeros while the laser lines carry the real pose: the topic chooser prefers it (io.topics).
ODOM_LASER_TOPIC = SCAN_TIME_ODOMETRY

# Candidate sources of each topic, best first.
TOPIC_SOURCES: dict[str, tuple[str, ...]] = {
    "/scan": ("ROBOTLASER1", "FLASER", "RAWLASER1"),
    "/scan_rear": ("ROBOTLASER2", "RLASER"),
    "/scan2": ("RAWLASER2",),
    "/scan3": ("RAWLASER3",),
    "/scan4": ("RAWLASER4",),
    "/odom": ("ODOM",),
}
SCAN_FRAMES = {
    "/scan": "laser", "/scan_rear": "laser_rear", "/scan2": "laser2", "/scan3": "laser3", "/scan4": "laser4",
}
SUPPORTED = frozenset(t for sources in TOPIC_SOURCES.values() for t in sources)
POSED = frozenset({"FLASER", "RLASER", "ROBOTLASER1", "ROBOTLASER2"})
# Known CARMEN messages that carto skips; they tell a CARMEN log from other text.
KNOWN_OTHER = frozenset({
    "PARAM", "SYNC", "TRUEPOS", "NEFF", "GPSNMEA", "SONAR", "BUMPER", "SCANMARK", "POSITIONLASER", "IMU",
    "VECTORMOVE", "ROBOTVELOCITY", "FOLLOWTRAJECTORY", "BASEVELOCITY", "LASER1", "LASER2", "LASER3", "LASER4",
    "REMISSIONLASER1", "REMISSIONLASER2",
})


# ---------------------------------------------------------------- time order

class _TimeOrder:
    """Releases pushed items in time order once ``window`` seconds of newer data have been seen.

    Items older than one already released cannot be placed and are dropped (counted per kind).
    """

    def __init__(self, window: float):
        self.window = window
        self.heap: list = []
        self.newest = -math.inf
        self.released = -math.inf
        self.dropped: Counter = Counter()

    def push(self, time: float, seq: int, kind: str, item) -> list:
        if time < self.released:
            self.dropped[kind] += 1
            return []
        heapq.heappush(self.heap, (time, seq, kind, item))
        self.newest = max(self.newest, time)
        out = []
        while self.heap and self.heap[0][0] < self.newest - self.window:
            out.append(self._pop())
        return out

    def flush(self) -> list:
        return [self._pop() for _ in range(len(self.heap))]

    def _pop(self):
        time, _, kind, item = heapq.heappop(self.heap)
        self.released = time
        return kind, item


# ---------------------------------------------------------------- survey (first pass)

@dataclass
class _Survey:
    counts: Counter = field(default_factory=Counter)  # delivered lines per message type
    dropped: Counter = field(default_factory=Counter)
    probes: dict = field(default_factory=dict)  # message type -> [(laser_pose, robot_pose)]
    recognised: bool = False
    cut_line: int | None = None  # the last line, left out: the file ends inside it
    truncated_after: int | None = None  # the last whole line of a gzip stream that ends early

    def source(self, topic: str) -> str | None:
        return next((k for k in TOPIC_SOURCES[topic] if self.counts[k] > 0), None)


def _probe_poses(kind: str, line: str):
    """Laser and robot pose of a posed laser line, from its tail; None if unreadable."""
    # FLASER: x y th ox oy oth | t host t; ROBOTLASER: lx ly lth rx ry rth tv rv fs ss ta | t host t
    skip = 0 if kind in ("FLASER", "RLASER") else 5
    parts = line.rsplit(None, 6 + skip + TRAILER)
    try:
        v = [float(p) for p in parts[1:7]]
    except ValueError:
        return None
    if len(v) != 6:
        return None
    return tuple(v[:3]), tuple(v[3:])


def _cut_mid_message(kind: str, line: str) -> bool:
    """Whether the file's last line, which has no end of line, is a message the file ends inside: one carto reads
    that does not parse, or a cut-off name of one. (A cut inside the final logger timestamp loses nothing carto
    reads and parses.)"""
    if kind in SUPPORTED:
        try:
            parse_line(kind, line)
        except LineError:
            return True
        return False
    return bool(kind) and any(name.startswith(kind) for name in SUPPORTED)


def _survey(path: Path) -> _Survey:
    s = _Survey()
    order = _TimeOrder(REORDER_WINDOW)
    lines = LogLines(path)
    for lineno, line in lines:
        kind = first_token(line)
        if not line.endswith("\n") and _cut_mid_message(kind, line):
            s.cut_line = lineno
            continue
        if kind not in SUPPORTED:
            if kind in KNOWN_OTHER or kind.startswith("#"):
                s.recognised = True
            continue
        s.recognised = True
        t = line_time(kind, line, lineno, path)
        if kind in POSED:
            probes = s.probes.setdefault(kind, [])
            if len(probes) < POSE_PROBE:
                p = _probe_poses(kind, line)
                if p is not None:
                    probes.append(p)
        for k, _ in order.push(t, lineno, kind, None):
            s.counts[k] += 1
    for k, _ in order.flush():
        s.counts[k] += 1
    s.dropped = order.dropped
    if lines.truncated:
        s.truncated_after = lines.count
    return s


def _mount(probes, default_yaw: float) -> tuple[float, float, float]:
    """Laser pose in the robot frame when the laser lines agree on one, else (0, 0, default_yaw)."""
    offsets = []
    for (lx, ly, lth), (rx, ry, rth) in probes:
        c, s = math.cos(rth), math.sin(rth)
        dx, dy = lx - rx, ly - ry
        offsets.append((c * dx + s * dy, -s * dx + c * dy, wrap_angle_scalar(lth - rth)))
    if not offsets or not all(math.isfinite(v) for o in offsets for v in o):
        return 0.0, 0.0, default_yaw
    x0, y0, a0 = offsets[0]
    if math.hypot(x0, y0) < 1e-3 and abs(a0) < 1e-3:
        return 0.0, 0.0, default_yaw
    for x, y, a in offsets[1:]:
        if math.hypot(x - x0, y - y0) > MOUNT_TOLERANCE or abs(wrap_angle_scalar(a - a0)) > MOUNT_TOLERANCE:
            return 0.0, 0.0, default_yaw
    return x0, y0, a0


# ---------------------------------------------------------------- the recording

class CarmenRecording(Recording):
    """A CARMEN log; see the module docstring for topics, angles and time order."""

    format = "carmen"
    read_ahead = True

    def __init__(self, path: Path, options: ReadOptions | None = None):
        super().__init__(path, options)
        if not self.path.is_file():
            raise CartoError("no such file", self.path)
        self._survey_cache: _Survey | None = None
        # Surveyed at once (every command lists the topics first anyway) so that a log cut short is known, and
        # warned about, before anything is read, as a bag cut short is.
        self._survey()

    @staticmethod
    def sniff(path: Path, max_bytes: int = 65536) -> bool:
        """True when the start of ``path`` (plain or gzipped) holds a CARMEN message name.

        Reads a fixed number of bytes, so a large binary file without line breaks costs nothing.
        """
        path = Path(path)
        try:
            opener = gzip.open if is_gzip(path) else open
            with opener(path, "rb") as f:
                head = f.read(max_bytes)
        except (OSError, EOFError, zlib.error):
            return False
        for line in head.decode("latin-1").splitlines():
            kind = first_token(line)
            if kind in SUPPORTED or kind in KNOWN_OTHER:
                return True
        return False

    # -- survey-derived facts

    def _survey(self) -> _Survey:
        if self._survey_cache is None:
            s = _survey(self.path)
            if s.cut_line is not None or s.truncated_after is not None:
                n = sum(s.counts.values())
                if s.truncated_after is not None:
                    where = "the compressed stream ends early" + (f", after line {s.truncated_after}"
                                                                   if s.truncated_after else "")
                else:
                    where = f"line {s.cut_line} ends mid-message"
                if not n:
                    raise FormatError(f"cut short ({where}) before its first whole message", self.path)
                self.warnings.append(f"{self.path.name}: cut short ({where}): read up to the cut, {n} "
                                     f"message{'s' if n != 1 else ''} recovered")
            if not s.recognised:
                raise FormatError("not a CARMEN log: no known message type in the file", self.path)
            self._survey_cache = s
        return self._survey_cache

    @property
    def dropped(self) -> dict[str, int]:
        """Lines per message type dropped because they came too late for time order."""
        return dict(self._survey().dropped)

    def _sources(self) -> dict[str, str]:
        s = self._survey()
        return {topic: src for topic in TOPIC_SOURCES if (src := s.source(topic)) is not None}

    def before_fork(self) -> None:
        decimals("0")  # the numbers' kernel: a child inherits it instead of paying numba's start-up again

    def independent(self) -> CarmenRecording:
        return self  # every pass opens the file anew: nothing is shared (and the survey of the file is kept)

    def topics(self) -> list[TopicInfo]:
        s = self._survey()
        out = []
        odom_laser = 0
        for topic, src in self._sources().items():
            msgtype = ODOM_MSGTYPE if topic == "/odom" else SCAN_MSGTYPE
            out.append(TopicInfo(topic, msgtype, s.counts[src]))
            if src in POSED:
                odom_laser += s.counts[src]
        if odom_laser:
            out.append(TopicInfo(ODOM_LASER_TOPIC, ODOM_MSGTYPE, odom_laser))
        return out

    def static_transforms(self) -> list[Transform]:
        s = self._survey()
        out = []
        for topic, src in self._sources().items():
            if topic == "/odom":
                continue
            default_yaw = math.pi if topic == "/scan_rear" else 0.0
            x, y, yaw = _mount(s.probes.get(src, []), default_yaw)
            out.append(Transform("base_link", SCAN_FRAMES[topic], (x, y, 0.0), yaw_quaternion(yaw)))
        return out

    # -- records

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        sources = self._sources()
        available = {t.name for t in self.topics()}
        wanted = set(available) if topics is None else set(topics)
        unknown = wanted - available
        if unknown:
            raise TopicError(
                f"no topic {', '.join(sorted(unknown))} (available: {', '.join(sorted(available)) or 'none'})",
                self.path,
            )
        topic_of = {src: topic for topic, src in sources.items()}
        return self._records(topic_of, wanted)

    def _records(self, topic_of: dict[str, str], wanted: set[str]) -> Iterator[Record]:
        order = _TimeOrder(REORDER_WINDOW)
        want_pose = ODOM_LASER_TOPIC in wanted
        cut = self._survey().cut_line
        for lineno, line in LogLines(self.path):
            if lineno == cut:
                break
            kind = first_token(line)
            if kind not in SUPPORTED:
                continue
            topic = topic_of.get(kind)
            if topic is not None and (topic in wanted or (want_pose and kind in POSED)):
                try:
                    msg = parse_line(kind, line)
                except LineError:
                    raise FormatError(diagnose(kind, line, lineno), self.path) from None
                t, item = msg.time, self._to_records(topic, msg, wanted)
            else:
                t, item = line_time(kind, line, lineno, self.path), None
            for _, released in order.push(t, lineno, kind, item):
                if released:
                    yield from released
        for _, released in order.flush():
            if released:
                yield from released

    @staticmethod
    def _to_records(topic: str, msg, wanted: set[str]) -> tuple[Record, ...]:
        if isinstance(msg, OdomLine):
            return (Odometry(msg.time, msg.x, msg.y, msg.theta, topic=topic, vx=msg.tv, wz=msg.rv),)
        out: list[Record] = []
        if msg.robot_pose is not None and ODOM_LASER_TOPIC in wanted:
            x, y, th = msg.robot_pose
            out.append(Odometry(msg.time, x, y, th, topic=ODOM_LASER_TOPIC, vx=msg.tv, wz=msg.rv))
        if topic in wanted:
            n = msg.ranges.shape[0]
            angles = (msg.start + msg.increment * np.arange(n)).astype(np.float32)
            out.append(Scan(
                time=msg.time, ranges=msg.ranges, angles=angles, frame=SCAN_FRAMES[topic], topic=topic,
                range_min=0.0, range_max=msg.max_range, angle_min=msg.start, angle_increment=msg.increment,
                intensities=msg.remissions,
            ))
        return tuple(out)
