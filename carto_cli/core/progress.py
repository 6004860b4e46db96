"""Progress of long work on stderr: a bar on a terminal; elsewhere (CI logs, nohup, a pipe) a plain line now and
then; nothing with --quiet."""
from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from enum import Enum
from typing import TextIO

__all__ = ["LINE_EVERY_S", "LINE_MIN_GAP_S", "LINE_STEP", "LineProgress", "Progress", "ProgressMode", "TerminalBar",
           "progress", "progress_mode"]

# A line at every tenth of the work, or after LINE_EVERY_S without one, whichever comes first: a short run says at
# least once how fast it goes, a 7-minute one speaks every half minute. Lines are never closer than LINE_MIN_GAP_S
# (the first excepted), so a run of seconds does not fill a CI log with ten lines.
LINE_STEP = 0.1
LINE_EVERY_S = 30.0
LINE_MIN_GAP_S = 5.0


class Progress:
    """A counter long work advances; this base shows nothing (--quiet)."""

    def advance(self, n: int = 1) -> None:
        pass

    def set_total(self, total: int | None) -> None:
        pass

    def set_description(self, text: str) -> None:
        pass

    def close(self) -> None:
        pass


class TerminalBar(Progress):
    """rich's bar, redrawn in place: only for a terminal. Redrawn as work advances (at most every REDRAW_S), not
    by rich's refresh thread: a second thread makes forking unsafe (core.parallel.fork_safe), which put the pose
    graph on a thread beside local SLAM, twice as slow as in its own process, whenever the bar was shown."""

    REDRAW_S = 0.1

    def __init__(self, description: str, total: int | None, stream: TextIO):
        from rich.console import Console
        from rich.progress import BarColumn, MofNCompleteColumn, TextColumn, TimeElapsedColumn, TimeRemainingColumn
        from rich.progress import Progress as RichProgress

        self._bar: RichProgress | None = RichProgress(
            TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
            TimeElapsedColumn(), TimeRemainingColumn(),
            console=Console(file=stream), transient=True, auto_refresh=False,
        )
        self._bar.start()
        self._task = self._bar.add_task(description, total=total)
        self._drawn = -math.inf
        self._redraw(force=True)

    def _redraw(self, force: bool = False) -> None:
        now = time.monotonic()
        if self._bar is not None and (force or now - self._drawn >= self.REDRAW_S):
            self._bar.refresh()
            self._drawn = now

    def advance(self, n: int = 1) -> None:
        if self._bar is not None:
            self._bar.advance(self._task, n)
            self._redraw()

    def set_total(self, total: int | None) -> None:
        if self._bar is not None:
            self._bar.update(self._task, total=total)
            self._redraw(force=True)

    def set_description(self, text: str) -> None:
        if self._bar is not None:
            self._bar.update(self._task, description=text)
            self._redraw(force=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.stop()
            self._bar = None


class LineProgress(Progress):
    """Plain lines for a log that is not a terminal (``carto: mapping x.bag 40% 200/499 scans, 35.2 scans/s, ETA
    8 s``), each written whole and flushed. Lines come only as work advances: no thread of their own."""

    def __init__(self, description: str, total: int | None, unit: str = "scans", *, stream: TextIO | None = None,
                 clock: Callable[[], float] = time.monotonic, step: float = LINE_STEP,
                 every_s: float = LINE_EVERY_S, min_gap_s: float = LINE_MIN_GAP_S):
        self.description, self.total, self.unit = description, total, unit
        self._stream: TextIO | None = stream if stream is not None else sys.stderr
        self._clock = clock
        self._step, self._every_s, self._min_gap_s = step, every_s, min_gap_s
        self._count = 0
        # Rate and time are measured from the first unit done: what came before it (reading, surveying, loading
        # or compiling kernels) says nothing of how fast the rest will go.
        self._first: tuple[float, int] | None = None
        self._last_line: float | None = None
        self._last_steps = 0  # whole steps done at the last line

    def advance(self, n: int = 1) -> None:
        self._count += n
        now = self._clock()
        if self._first is None:
            self._first = (now, self._count)
            return
        if self._due(now):
            self._line(now)

    def set_total(self, total: int | None) -> None:
        self.total = total

    def set_description(self, text: str) -> None:
        self.description = text

    def _steps(self) -> int:
        if not self.total or self.total <= 0:
            return 0
        return math.floor(min(self._count, self.total) / self.total / self._step + 1e-9)

    def _due(self, now: float) -> bool:
        assert self._first is not None
        since = now - (self._first[0] if self._last_line is None else self._last_line)
        if since >= self._every_s:
            return True
        if self._steps() <= self._last_steps:
            return False
        return self._last_line is None or since >= self._min_gap_s

    def rate(self, now: float) -> float | None:
        """Units per second since the first one was done (None before a second one)."""
        if self._first is None:
            return None
        t0, n0 = self._first
        return (self._count - n0) / (now - t0) if now > t0 and self._count > n0 else None

    def _line(self, now: float) -> None:
        self._last_line, self._last_steps = now, self._steps()
        if self._stream is None:
            return
        try:
            self._stream.write(self.text(now) + "\n")
            self._stream.flush()
        except (OSError, ValueError):
            # The log's reader went away (`2>&1 | head`) or closed it: the work goes on without its progress.
            self._stream = None

    def text(self, now: float) -> str:
        parts = [f"carto: {self.description}"]
        if self.total:
            parts.append(f"{100 * min(self._count, self.total) // self.total}% {self._count}/{self.total} {self.unit}")
        else:
            parts.append(f"{self._count} {self.unit}")
        rate = self.rate(now)
        text = " ".join(parts)
        if rate is not None:
            text += f", {_number(rate)} {self.unit}/s"
            if self.total and self._count < self.total:
                text += f", ETA {_duration((self.total - self._count) / rate)}"
        return text


def _number(rate: float) -> str:
    return f"{rate:.1f}" if rate >= 1 else f"{rate:.2g}"


def _duration(seconds: float) -> str:
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60} s"
    return f"{s // 3600} h {s % 3600 // 60} min"


class ProgressMode(Enum):
    BAR = "bar"  # a terminal: redrawn in place
    LINES = "lines"  # a log, a pipe, nohup: a plain line now and then


def progress_mode(quiet: bool, stream: TextIO | None = None) -> ProgressMode | None:
    """How progress shows on ``stream`` (stderr by default); None with ``quiet``."""
    if quiet:
        return None
    stream = stream if stream is not None else sys.stderr
    try:
        tty = stream.isatty()
    except (AttributeError, ValueError):  # a closed or odd stream: plain lines cannot hurt it more
        tty = False
    return ProgressMode.BAR if tty else ProgressMode.LINES


@contextmanager
def progress(description: str, total: int | None, quiet: bool = False, unit: str = "scans") -> Iterator[Progress]:
    """Progress of ``total`` ``unit`` (None: not known yet, ``set_total`` may say later) on stderr."""
    mode = progress_mode(quiet)
    shown: Progress
    if mode is ProgressMode.BAR:
        shown = TerminalBar(description, total, sys.stderr)
    elif mode is ProgressMode.LINES:
        shown = LineProgress(description, total, unit)
    else:
        shown = Progress()
    try:
        yield shown
    finally:
        shown.close()
