"""What to relocalize: query files and ``--initial-pose`` text, the recording's scans they select, and the records
around each (``ScanContext``)."""
from __future__ import annotations

import re
from collections import deque
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from carto_cli.core import parse
from carto_cli.core.errors import CartoError
from carto_cli.core.records import Record, Scan
from carto_cli.io.topics import TopicSelection, select_topics, selected_records

__all__ = [
    "CONTEXT_SECONDS", "Query", "ScanContext", "context_at", "contexts_for", "iter_scans", "parse_pose", "read_queries",
    "scan_at", "scans_for_queries", "select_scan_topic",
]

# How far (s) around the query a caller gathers records for a ScanContext: 8 steps of 0.5 m at 0.13 m/s (following's
# neighbours are taken every 0.5 m, 8 each way).
CONTEXT_SECONDS = 30.0


@dataclass
class ScanContext:
    """The records of a recording around a query scan, in time order: ``before`` ends with the last record
    before the query scan, ``after`` starts with the first after it. Scans of the query's topic and odometry
    (other records are ignored); ``CONTEXT_SECONDS`` either way is enough."""

    before: Sequence[Record] = ()
    after: Sequence[Record] = ()


@dataclass(frozen=True)
class Query:
    """One line of a queries file: which scan (by time or index) and the prior (None: global)."""

    time: float | None
    index: int | None
    prior: tuple[float, float, float] | None
    sigma_xy: float | None = None
    sigma_yaw: float | None = None
    line: int = 0
    file: str | None = None  # the queries file of ``line``, which an error about the query then names


# ----------------------------------------------------------------------------------- parsing


_KEYS = {"t": "time", "time": "time", "stamp": "time", "index": "index", "scan": "index", "scan_index": "index",
         "i": "index"}
_NONE = {"-", "none", "null", "?"}


def parse_pose(text: str) -> tuple[float, float, float]:
    """'x,y,yaw' (yaw in radians, or degrees with a 'deg' suffix) -> (x, y, yaw), for ``--initial-pose``."""
    return parse.pose(text, "--initial-pose")


def read_queries(path: str | Path) -> list[Query]:
    """Queries from a text file, one per line::

        # comments and blank lines are ignored; fields split on whitespace and/or commas
        t x y yaw [sigma_xy sigma_yaw]      <- optional header; 'index x y yaw ...' selects scans by index
        1012.5  3.2  1.0  1.57
        1013.0  3.2  1.0  90deg  0.3  5deg  <- per-query sigmas (m, rad or 'deg')
        1020.0  -    -    -                 <- no prior: global search

    The first column is a time (s, the recording's clock: the scan nearest it, within 1 s) unless a header
    line 'index x y yaw' makes it a scan index (the recording's scans counted from 0); a headerless file is
    read as times, whatever its numbers look like. Angles are radians unless suffixed 'deg'. Errors name
    the file and the line, also those found when the scans are looked up (``scans_for_queries``).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CartoError("no such queries file", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise CartoError(f"cannot read queries: {e}", path) from None
    key = "time"
    out: list[Query] = []
    seen_data = False
    for n, raw in enumerate(text.splitlines(), start=1):
        line = raw.split("#", 1)[0].strip()
        if not line:
            continue

        def fail(msg, n=n):
            return CartoError(f"line {n}: {msg}", path)
        fields = [f for f in re.split(r"[,\s]+", line) if f]
        head = fields[0].lower()
        if head in _KEYS or not re.match(rf"^{parse.NUMBER}$", head):
            if seen_data:
                raise fail(f"expected a query (time or index, x, y, yaw), got {raw.strip()!r}")
            if head not in _KEYS:
                raise fail(f"the first column must be a time or a scan index; a header names it 't' or 'index', "
                           f"got {fields[0]!r}")
            key = _KEYS[head]
            names = [f.lower() for f in fields[1:]]
            if names[:3] != ["x", "y", "yaw"] or any(f not in ("sigma_xy", "sigma_yaw") for f in names[3:]):
                raise fail("header must be 't x y yaw [sigma_xy sigma_yaw]' or 'index x y yaw [sigma_xy sigma_yaw]'")
            seen_data = True  # one header at most, and before the data
            continue
        seen_data = True
        if len(fields) not in (4, 6):
            raise fail(f"expected 4 fields (time or index, x, y, yaw) or 6 (+ sigma_xy sigma_yaw), got {len(fields)}")
        if key == "time":
            t, idx = parse.number(fields[0], "time", fail), None
        else:
            try:
                idx, t = int(fields[0]), None
            except ValueError:
                raise fail(f"scan index must be a whole number, got {fields[0]!r}") from None
            if idx < 0:
                raise fail(f"scan index must be >= 0, got {idx}")
        pose_fields = [f.lower() for f in fields[1:4]]
        if all(f in _NONE for f in pose_fields):
            prior = None
        elif any(f in _NONE for f in pose_fields):
            raise fail("give all of x, y, yaw or none of them ('-' for a global search)")
        else:
            prior = (parse.number(fields[1], "x", fail), parse.number(fields[2], "y", fail),
                     parse.angle(fields[3], "yaw", fail))
        sxy = syaw = None
        if len(fields) == 6:
            sxy = parse.number(fields[4], "sigma_xy", fail)
            syaw = parse.angle(fields[5], "sigma_yaw", fail)
            if sxy <= 0 or syaw <= 0:
                raise fail("sigmas must be positive")
        out.append(Query(t, idx, prior, sxy, syaw, n, str(path)))
    if not out:
        raise CartoError("no queries in the file", path)
    return out


# ----------------------------------------------------------------------------------- scans


def select_scan_topic(recording, wanted: str | None = None) -> str:
    """The scan topic relocalization reads (``wanted``, or the recording's only one), as every command chooses it."""
    return select_topics(recording, scan_topic=wanted).scan


def iter_scans(recording, topic: str) -> Iterator[tuple[int, Scan]]:
    """(index, scan) of every scan on ``topic`` in recording order; the index counts scans from 0."""
    count = 0
    for record in recording.records([topic]):
        if not isinstance(record, Scan):
            continue
        yield count, record
        count += 1


def scans_for_queries(recording, queries: Sequence[Query], scan_topic: str | None = None,
                      max_time_offset: float = 1.0, *, selection: TopicSelection | None = None
                      ) -> dict[int, tuple[int, Scan]]:
    """{query position: (scan index, Scan)} in one pass over the recording's scans (``selection``'s when given:
    several lasers' merged, as mapping read them).

    A timed query gets the scan nearest its time (the earlier one on a tie), an error beyond ``max_time_offset``.
    """
    return _scan_pass(recording, queries, scan_topic, max_time_offset, 0.0, selection)[0]


def contexts_for(recording, queries: Sequence[Query], scan_topic: str | None = None, max_time_offset: float = 1.0,
                 *, context_seconds: float, selection: TopicSelection | None = None
                 ) -> tuple[dict[int, tuple[int, Scan]], dict[int, ScanContext]]:
    """``scans_for_queries`` and each query's records around its scan (``ScanContext``: the scans and the
    odometry of ``selection``, default the recording's own, ``context_seconds`` either side), in one pass."""
    return _scan_pass(recording, queries, scan_topic, max_time_offset, context_seconds, selection)


class _Gatherer:
    """The records within ``seconds`` before the newest (``recent``) and, for each query whose scan has been
    found, those after its scan until ``seconds`` have passed."""

    def __init__(self, seconds: float):
        self.seconds = seconds
        self.recent: deque[Record] = deque()
        self.open: list[tuple[float, list[Record]]] = []
        self.contexts: dict[int, ScanContext] = {}

    def take(self, record: Record, oldest: float) -> None:
        """Keep ``record``; ``oldest``: the time of the earliest scan a query may still be given (the previous
        scan, for a timed query between two), whose context reaches ``seconds`` before it."""
        if self.seconds <= 0:
            return
        t = record.time
        if self.open:
            self.open = [(until, after) for until, after in self.open if t <= until]
            for _, after in self.open:
                after.append(record)
        self.recent.append(record)
        while self.recent and self.recent[0].time < min(t, oldest) - self.seconds:
            self.recent.popleft()

    def found(self, k: int, scan: Scan) -> None:
        """Query ``k``'s scan is ``scan``, already taken (the newest record, or the previous scan)."""
        if self.seconds <= 0:
            return
        recent = list(self.recent)
        at = next((n for n in range(len(recent) - 1, -1, -1) if recent[n] is scan), None)
        before, after = (recent, []) if at is None else (recent[:at], recent[at + 1:])
        before = [r for r in before if r.time >= scan.time - self.seconds]
        after = [r for r in after if r.time <= scan.time + self.seconds]
        self.contexts[k] = ScanContext(before, after)
        self.open.append((scan.time + self.seconds, after))


def _scan_pass(recording, queries: Sequence[Query], scan_topic: str | None, max_time_offset: float,
               context_seconds: float, selection: TopicSelection | None
               ) -> tuple[dict[int, tuple[int, Scan]], dict[int, ScanContext]]:
    if context_seconds > 0 or selection is not None:
        selection = selection or select_topics(recording, scan_topic)
        topic = "+".join(selection.scan_topics)
        wanted = list(selection.scan_topics) + ([selection.odometry] if selection.odometry and context_seconds > 0
                                                else [])
        stream: Iterator[Record] = selected_records(recording, selection, wanted)
    else:
        topic = select_scan_topic(recording, scan_topic)
        stream = recording.records([topic])
    gather = _Gatherer(context_seconds)
    by_index: dict[int, list[int]] = {}
    timed = sorted(((q.time, k) for k, q in enumerate(queries) if q.time is not None))
    for k, q in enumerate(queries):
        if q.index is not None:
            by_index.setdefault(q.index, []).append(k)
    found: dict[int, tuple[int, Scan]] = {}
    j = 0
    prev: tuple[int, Scan] | None = None
    count = 0
    last = None
    first_time = 0.0
    for record in stream:
        gather.take(record, record.time if prev is None else prev[1].time)
        if not isinstance(record, Scan):  # only the scan topic's are read
            continue
        i = count
        count = i + 1
        if i == 0:
            first_time = record.time
        for k in by_index.get(i, ()):
            found[k] = (i, record)
            gather.found(k, record)
        while j < len(timed) and record.time >= timed[j][0]:
            t, k = timed[j]
            if prev is not None and abs(prev[1].time - t) <= abs(record.time - t):
                found[k] = prev
            else:
                found[k] = (i, record)
            gather.found(k, found[k][1])
            j += 1
        prev = (i, record)
        last = prev
    if count == 0 or last is None:
        raise CartoError(f"the recording has no scans on {topic}", getattr(recording, "path", None))
    while j < len(timed):
        found[timed[j][1]] = last
        gather.found(timed[j][1], last[1])
        j += 1
    rec_path = getattr(recording, "path", None)
    for k, q in enumerate(queries):
        where = f"line {q.line}: " if q.line else ""
        # A query file's line is the user's to fix: the error names that file, and the recording in its text.
        rec_name = Path(rec_path).name if q.file and rec_path else None
        if q.index is not None and k not in found:
            whose = f"{rec_name}'s" if rec_name else "the recording's"
            raise CartoError(f"{where}scan index {q.index} is beyond {whose} {count} scans (0-{count - 1})",
                             q.file or rec_path)
        if q.time is not None:
            dt = abs(found[k][1].time - q.time)
            if dt > max_time_offset:
                of = f" of {rec_name}" if rec_name else ""
                hint = ("; the first column is a time (s) unless the file's first line 'index x y yaw' makes it "
                        "scan indices" if q.file else "")
                raise CartoError(f"{where}no scan{of} within {max_time_offset:g} s of t={q.time:.3f} (its scans run "
                                 f"from t={first_time:.3f} to {last[1].time:.3f}){hint}", q.file or rec_path)
    return found, gather.contexts


def scan_at(recording, *, time: float | None = None, index: int | None = None, scan_topic: str | None = None,
            max_time_offset: float = 1.0, selection: TopicSelection | None = None) -> tuple[int, Scan]:
    """(index, scan) of the scan nearest ``time`` or at ``index`` (default: the first scan)."""
    return scans_for_queries(recording, [_query_at(time, index)], scan_topic, max_time_offset,
                             selection=selection)[0]


def context_at(recording, *, time: float | None = None, index: int | None = None, scan_topic: str | None = None,
               max_time_offset: float = 1.0, context_seconds: float, selection: TopicSelection | None = None
               ) -> tuple[int, Scan, ScanContext]:
    """``scan_at`` and the records around that scan (``contexts_for``)."""
    found, contexts = contexts_for(recording, [_query_at(time, index)], scan_topic, max_time_offset,
                                   context_seconds=context_seconds, selection=selection)
    return found[0][0], found[0][1], contexts.get(0, ScanContext())


def _query_at(time: float | None, index: int | None) -> Query:
    if time is not None and index is not None:
        raise CartoError("give a time or a scan index, not both")
    if index is not None and index < 0:
        raise CartoError(f"scan index must be >= 0, got {index}")
    return Query(time, index if index is not None or time is not None else 0, None)
