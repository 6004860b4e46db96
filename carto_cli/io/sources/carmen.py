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

Beam angles follow CARMEN's own reader (``carmen_laser_guess_fov`` and
``carmen_laser_guess_angle_increment`` in ``readlog.c``): FLASER / RLASER
start at -pi/2 with an increment of 1 deg for 180 or 181 beams, 0.5 deg for
360 or 361, 0.25 deg for 400 or 401, and pi / (n - 1) otherwise. So 181 and
361 beams span exactly 180 deg, while 180 and 360 beams stop one increment
short of +pi/2 (CARMEN drops the last beam, it does not stretch the others).
ROBOTLASER / RAWLASER state their start angle and increment. The rear laser
gets the same angles in its own frame (``laser_rear``), which the static
transform turns by pi.

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

Strictness: every line read is checked field by field (counts derived from
the beam / remission counts, numeric fields, finite timestamp) and a failure
is a ``FormatError`` naming the file and line: bad content is an error wherever
it is. A file cut short is not bad content: as a bag or an MCAP file cut short,
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
from carto_cli.io.sources.decimals import decimals

GZIP_MAGIC = b"\x1f\x8b"
FLASER_MAX_RANGE = 80.0  # what CARMEN's reader assumes for FLASER / RLASER
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

# Trailing tokens after the numeric payload: timestamp host logger_timestamp.
_TRAILER = 3


# ---------------------------------------------------------------- reading lines

def _is_gzip(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.read(2) == GZIP_MAGIC


class _Lines:
    """(line number, text) of every line, decompressing on the fly; ``truncated`` once they are over if a gzip
    stream ended before its end marker (the lines before the cut are whole: only the partial one is lost).

    latin-1 decodes any byte, so a stray host name never stops the reader;
    only the numeric fields matter and they are ASCII.
    """

    def __init__(self, path: Path):
        self.path = path
        self.truncated = False
        self.count = 0

    def __iter__(self) -> Iterator[tuple[int, str]]:
        path = self.path
        gz = _is_gzip(path)
        f = gzip.open(path, "rt", encoding="latin-1") if gz else open(path, encoding="latin-1")
        lineno = 0
        try:
            with f:
                for lineno, line in enumerate(f, 1):
                    yield lineno, line
        except EOFError:
            # A copy or a logger cut short, as a plain file ending mid-line: the survey warns, nothing is wrong
            # with what came before.
            self.truncated = True
        except (zlib.error, gzip.BadGzipFile) as e:
            raise FormatError(f"compressed data corrupt after line {lineno} ({e})", path) from None
        except OSError as e:
            raise FormatError(f"cannot read after line {lineno} ({e})", path) from None
        self.count = lineno


def _first_token(line: str) -> str:
    parts = line.split(None, 1)
    return parts[0] if parts else ""


def _cut_mid_message(kind: str, line: str) -> bool:
    """Whether the file's last line, which has no end of line, is a message the file ends inside: one carto reads
    that does not parse, or a cut-off name of one. (A cut inside the final logger timestamp loses nothing carto
    reads and parses.)"""
    if kind in SUPPORTED:
        try:
            _parse(kind, line)
        except _LineError:
            return True
        return False
    return bool(kind) and any(name.startswith(kind) for name in SUPPORTED)


def _line_time(kind: str, line: str, lineno: int, path: Path) -> float:
    """The timestamp of a line that is not otherwise parsed (the survey, unselected topics)."""
    parts = line.rsplit(None, _TRAILER)
    try:
        t = float(parts[-_TRAILER]) if len(parts) > _TRAILER else math.nan
    except ValueError:
        t = math.nan
    if not math.isfinite(t):
        raise FormatError(_diagnose(kind, line, lineno), path)
    return t


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


# ---------------------------------------------------------------- parsing

@dataclass
class _Laser:
    time: float
    ranges: np.ndarray
    start: float
    increment: float
    max_range: float
    remissions: np.ndarray | None = None
    laser_pose: tuple[float, float, float] | None = None
    robot_pose: tuple[float, float, float] | None = None
    tv: float = 0.0
    rv: float = 0.0


@dataclass
class _Odom:
    time: float
    x: float
    y: float
    theta: float
    tv: float
    rv: float


def carmen_beam_geometry(n: int) -> tuple[float, float]:
    """(start angle, increment) CARMEN assumes for a FLASER / RLASER of ``n`` beams."""
    if n in (180, 181):
        inc = math.pi / 180.0
    elif n in (360, 361):
        inc = math.pi / 360.0
    elif n in (400, 401):
        inc = math.pi / 720.0
    else:
        inc = math.pi / max(n - 1, 1)
    return -math.pi / 2.0, inc


class _LineError(Exception):
    """Raised by the fast path; ``_diagnose`` turns it into a precise FormatError."""


def _floats(text: str) -> np.ndarray:
    # numpy >= 2 raises on a non-numeric token; older versions stop early with a
    # warning, which the callers' length checks catch.
    try:
        return decimals(text)
    except (ValueError, DeprecationWarning):
        raise _LineError from None


def _f32(values: np.ndarray) -> np.ndarray:
    # A range beyond float32 is no real reading; it becomes inf, like any return out of range.
    with np.errstate(over="ignore"):
        return values.astype(np.float32)


def _count(value: float) -> int:
    if not (math.isfinite(value) and value >= 0 and value == int(value)):
        raise _LineError
    return int(value)


def _split_payload(line: str) -> tuple[str, float]:
    """(numeric payload after the message name, timestamp)."""
    parts = line.split(None, 1)
    if len(parts) < 2:
        raise _LineError
    body = parts[1].rsplit(None, _TRAILER)
    if len(body) != _TRAILER + 1:
        raise _LineError
    try:
        t = float(body[1])
        float(body[3])
    except ValueError:
        raise _LineError from None
    if not math.isfinite(t):
        raise _LineError
    return body[0], t


def _parse_flaser(line: str) -> _Laser:
    payload, t = _split_payload(line)
    v = _floats(payload)
    if len(v) < 1:
        raise _LineError
    n = _count(v[0])
    if len(v) != 1 + n + 6:
        raise _LineError
    start, inc = carmen_beam_geometry(n)
    return _Laser(
        t, _f32(v[1:1 + n]), start, inc, FLASER_MAX_RANGE,
        laser_pose=tuple(v[1 + n:4 + n].tolist()), robot_pose=tuple(v[4 + n:7 + n].tolist()),
    )


def _parse_configured(line: str, posed: bool) -> _Laser:
    """ROBOTLASERk (posed) and RAWLASERk: a laser config header, ranges and remissions."""
    payload, t = _split_payload(line)
    v = _floats(payload)
    if len(v) < 8:
        raise _LineError
    n = _count(v[7])
    if len(v) < 9 + n:
        raise _LineError
    m = _count(v[8 + n])
    tail = 11 if posed else 0  # two poses, tv rv forward_safety side_safety turn_axis
    if len(v) != 9 + n + m + tail:
        raise _LineError
    rem = _f32(v[9 + n:9 + n + m]) if m == n and m > 0 else None
    laser = _Laser(t, _f32(v[8:8 + n]), float(v[1]), float(v[3]), float(v[4]), remissions=rem)
    if posed:
        k = 9 + n + m
        laser.laser_pose = tuple(v[k:k + 3].tolist())
        laser.robot_pose = tuple(v[k + 3:k + 6].tolist())
        laser.tv, laser.rv = float(v[k + 6]), float(v[k + 7])
    return laser


def _parse_odom(line: str) -> _Odom:
    # Six numbers: plain float() beats numpy's per-call overhead here, and
    # ODOM lines outnumber laser lines five to one in dense logs.
    tokens = line.split()
    if len(tokens) != 1 + 6 + _TRAILER:
        raise _LineError
    try:
        x, y, theta, tv, rv, _, t = map(float, tokens[1:8])
        float(tokens[9])
    except ValueError:
        raise _LineError from None
    if not math.isfinite(t):
        raise _LineError
    return _Odom(t, x, y, theta, tv, rv)


def _parse(kind: str, line: str):
    if kind == "ODOM":
        return _parse_odom(line)
    if kind in ("FLASER", "RLASER"):
        return _parse_flaser(line)
    return _parse_configured(line, posed=kind.startswith("ROBOTLASER"))


def _expected_fields(kind: str, tokens: list[str]) -> tuple[str, int] | None:
    """(what the count depends on, expected number of fields after the name), or None if unknowable."""
    def count_at(i):
        try:
            c = float(tokens[i])
        except (IndexError, ValueError):
            return None
        return int(c) if math.isfinite(c) and c >= 0 and c == int(c) else None

    if kind == "ODOM":
        return "", 6 + _TRAILER
    if kind in ("FLASER", "RLASER"):
        n = count_at(1)
        return (None if n is None else (f" with {n} beams", 1 + n + 6 + _TRAILER))
    n = count_at(8)
    if n is None:
        return None
    m = count_at(9 + n)
    tail = 11 if kind.startswith("ROBOTLASER") else 0
    if m is None:
        return f" with {n} beams", 9 + n + 1 + tail + _TRAILER  # assumes no remissions
    return f" with {n} beams and {m} remissions", 9 + n + m + tail + _TRAILER


def _diagnose(kind: str, line: str, lineno: int) -> str:
    """The most precise thing to say about a line the fast path rejected."""
    tokens = line.split()
    expected = _expected_fields(kind, tokens)
    if expected is None:
        return f"line {lineno}: {kind} has no valid beam or remission count"
    what, want = expected
    got = len(tokens) - 1
    if got != want:
        return f"line {lineno}: {kind}{what} has {got} fields after its name, expected {want}"
    host = len(tokens) - 2
    for i, tok in enumerate(tokens[1:], 1):
        if i == host:
            continue
        try:
            float(tok)
        except ValueError:
            return f"line {lineno}: {kind} field {i} is not a number ('{tok[:20]}')"
    if not math.isfinite(float(tokens[-_TRAILER])):
        return f"line {lineno}: {kind} timestamp '{tokens[-_TRAILER]}' is not a finite number"
    return f"line {lineno}: malformed {kind} line"


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
    parts = line.rsplit(None, 6 + skip + _TRAILER)
    try:
        v = [float(p) for p in parts[1:7]]
    except ValueError:
        return None
    if len(v) != 6:
        return None
    return tuple(v[:3]), tuple(v[3:])


def _survey(path: Path) -> _Survey:
    s = _Survey()
    order = _TimeOrder(REORDER_WINDOW)
    lines = _Lines(path)
    for lineno, line in lines:
        kind = _first_token(line)
        if not line.endswith("\n") and _cut_mid_message(kind, line):
            s.cut_line = lineno
            continue
        if kind not in SUPPORTED:
            if kind in KNOWN_OTHER or kind.startswith("#"):
                s.recognised = True
            continue
        s.recognised = True
        t = _line_time(kind, line, lineno, path)
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
            opener = gzip.open if _is_gzip(path) else open
            with opener(path, "rb") as f:
                head = f.read(max_bytes)
        except (OSError, EOFError, zlib.error):
            return False
        for line in head.decode("latin-1").splitlines():
            kind = _first_token(line)
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
        for lineno, line in _Lines(self.path):
            if lineno == cut:
                break
            kind = _first_token(line)
            if kind not in SUPPORTED:
                continue
            topic = topic_of.get(kind)
            if topic is not None and (topic in wanted or (want_pose and kind in POSED)):
                try:
                    msg = _parse(kind, line)
                except _LineError:
                    raise FormatError(_diagnose(kind, line, lineno), self.path) from None
                t, item = msg.time, self._to_records(topic, msg, wanted)
            else:
                t, item = _line_time(kind, line, lineno, self.path), None
            for _, released in order.push(t, lineno, kind, item):
                if released:
                    yield from released
        for _, released in order.flush():
            if released:
                yield from released

    @staticmethod
    def _to_records(topic: str, msg, wanted: set[str]) -> tuple[Record, ...]:
        if isinstance(msg, _Odom):
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
