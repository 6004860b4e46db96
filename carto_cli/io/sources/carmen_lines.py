"""A CARMEN log line by line: the file's lines (plain or gzipped), each line's message name and timestamp, and the
payload of the messages carto reads, parsed and checked (``carmen.py`` makes topics and time-ordered records of them).

Strictness: every line parsed is checked field by field (counts derived from the beam / remission counts, numeric
fields, finite timestamp). The fast path only says no (``LineError``); ``diagnose`` then says what is wrong, for a
``FormatError`` naming the file and line. A gzip stream that ends before its end marker is no error here:
``LogLines`` notes it (``truncated``), and the survey decides.

Beam angles follow CARMEN's own reader (``carmen_laser_guess_fov`` and
``carmen_laser_guess_angle_increment`` in ``readlog.c``): FLASER / RLASER
start at -pi/2 with an increment of 1 deg for 180 or 181 beams, 0.5 deg for
360 or 361, 0.25 deg for 400 or 401, and pi / (n - 1) otherwise. So 181 and
361 beams span exactly 180 deg, while 180 and 360 beams stop one increment
short of +pi/2 (CARMEN drops the last beam, it does not stretch the others).
ROBOTLASER / RAWLASER state their start angle and increment.
"""
from __future__ import annotations

import gzip
import math
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carto_cli.core.errors import FormatError
from carto_cli.io.sources.decimals import decimals

GZIP_MAGIC = b"\x1f\x8b"
FLASER_MAX_RANGE = 80.0  # what CARMEN's reader assumes for FLASER / RLASER

# Trailing tokens after the numeric payload: timestamp host logger_timestamp.
TRAILER = 3


# ---------------------------------------------------------------- reading lines

def is_gzip(path: Path) -> bool:
    with open(path, "rb") as f:
        return f.read(2) == GZIP_MAGIC


class LogLines:
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
        gz = is_gzip(path)
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


def first_token(line: str) -> str:
    parts = line.split(None, 1)
    return parts[0] if parts else ""


def line_time(kind: str, line: str, lineno: int, path: Path) -> float:
    """The timestamp of a line that is not otherwise parsed (the survey, unselected topics)."""
    parts = line.rsplit(None, TRAILER)
    try:
        t = float(parts[-TRAILER]) if len(parts) > TRAILER else math.nan
    except ValueError:
        t = math.nan
    if not math.isfinite(t):
        raise FormatError(diagnose(kind, line, lineno), path)
    return t


# ---------------------------------------------------------------- parsing

@dataclass
class LaserLine:
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
class OdomLine:
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


class LineError(Exception):
    """Raised by the fast path; ``diagnose`` turns it into a precise FormatError."""


def _floats(text: str) -> np.ndarray:
    # numpy >= 2 raises on a non-numeric token; older versions stop early with a
    # warning, which the callers' length checks catch.
    try:
        return decimals(text)
    except (ValueError, DeprecationWarning):
        raise LineError from None


def _f32(values: np.ndarray) -> np.ndarray:
    # A range beyond float32 is no real reading; it becomes inf, like any return out of range.
    with np.errstate(over="ignore"):
        return values.astype(np.float32)


def _count(value: float) -> int:
    if not (math.isfinite(value) and value >= 0 and value == int(value)):
        raise LineError
    return int(value)


def _split_payload(line: str) -> tuple[str, float]:
    """(numeric payload after the message name, timestamp)."""
    parts = line.split(None, 1)
    if len(parts) < 2:
        raise LineError
    body = parts[1].rsplit(None, TRAILER)
    if len(body) != TRAILER + 1:
        raise LineError
    try:
        t = float(body[1])
        float(body[3])
    except ValueError:
        raise LineError from None
    if not math.isfinite(t):
        raise LineError
    return body[0], t


def _parse_flaser(line: str) -> LaserLine:
    payload, t = _split_payload(line)
    v = _floats(payload)
    if len(v) < 1:
        raise LineError
    n = _count(v[0])
    if len(v) != 1 + n + 6:
        raise LineError
    start, inc = carmen_beam_geometry(n)
    return LaserLine(
        t, _f32(v[1:1 + n]), start, inc, FLASER_MAX_RANGE,
        laser_pose=tuple(v[1 + n:4 + n].tolist()), robot_pose=tuple(v[4 + n:7 + n].tolist()),
    )


def _parse_configured(line: str, posed: bool) -> LaserLine:
    """ROBOTLASERk (posed) and RAWLASERk: a laser config header, ranges and remissions."""
    payload, t = _split_payload(line)
    v = _floats(payload)
    if len(v) < 8:
        raise LineError
    n = _count(v[7])
    if len(v) < 9 + n:
        raise LineError
    m = _count(v[8 + n])
    tail = 11 if posed else 0  # two poses, tv rv forward_safety side_safety turn_axis
    if len(v) != 9 + n + m + tail:
        raise LineError
    rem = _f32(v[9 + n:9 + n + m]) if m == n and m > 0 else None
    laser = LaserLine(t, _f32(v[8:8 + n]), float(v[1]), float(v[3]), float(v[4]), remissions=rem)
    if posed:
        k = 9 + n + m
        laser.laser_pose = tuple(v[k:k + 3].tolist())
        laser.robot_pose = tuple(v[k + 3:k + 6].tolist())
        laser.tv, laser.rv = float(v[k + 6]), float(v[k + 7])
    return laser


def _parse_odom(line: str) -> OdomLine:
    # Six numbers: plain float() beats numpy's per-call overhead here, and
    # ODOM lines outnumber laser lines five to one in dense logs.
    tokens = line.split()
    if len(tokens) != 1 + 6 + TRAILER:
        raise LineError
    try:
        x, y, theta, tv, rv, _, t = map(float, tokens[1:8])
        float(tokens[9])
    except ValueError:
        raise LineError from None
    if not math.isfinite(t):
        raise LineError
    return OdomLine(t, x, y, theta, tv, rv)


def parse_line(kind: str, line: str):
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
        return "", 6 + TRAILER
    if kind in ("FLASER", "RLASER"):
        n = count_at(1)
        return (None if n is None else (f" with {n} beams", 1 + n + 6 + TRAILER))
    n = count_at(8)
    if n is None:
        return None
    m = count_at(9 + n)
    tail = 11 if kind.startswith("ROBOTLASER") else 0
    if m is None:
        return f" with {n} beams", 9 + n + 1 + tail + TRAILER  # assumes no remissions
    return f" with {n} beams and {m} remissions", 9 + n + m + tail + TRAILER


def diagnose(kind: str, line: str, lineno: int) -> str:
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
    if not math.isfinite(float(tokens[-TRAILER])):
        return f"line {lineno}: {kind} timestamp '{tokens[-TRAILER]}' is not a finite number"
    return f"line {lineno}: malformed {kind} line"
