"""Several 2D lasers on one robot as one scan, seen from the tracking frame.

Cartographer takes several range sensors natively: its collator waits until every sensor has sent data, then hands
local SLAM their points together, each with its own time and placed by its own sensor's mount. ``ScanMerger`` does
the same ahead of every mapping system, so that nothing downstream needs to know there were several lasers: each
laser's scan is placed by its mount, and the scans of one window (one scan of each laser at most) become one
:class:`Scan` in the tracking frame. Its bearings and ranges are seen from the tracking frame's origin, and
every beam keeps the time it was measured (``Scan.point_times``), so local SLAM de-skews the whole window by the
motion its extrapolator gives over it (odometry's, interpolated at both ends), as it does one laser's sweep.

Rays are then cast from the tracking frame's origin, as Cartographer's 2D inserter casts them from the tracking
frame's position; a laser a few decimetres off it clears nearly the same cells. Each laser's own limits
(``range_min``, ``range_max``, REP 117) are applied in its own frame first: a reading past its ``range_max`` stays
a miss along its own beam.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from carto_cli.core.records import Record, Scan
from carto_cli.sensor.range_filter import within_sensor_limits

__all__ = ["Laser", "ScanMerger", "merge", "merged_records", "merged_topic"]

# How far along its own beam a laser's miss (no echo) is placed before its bearing from the tracking frame is
# taken: far enough that a mount's offset turns the bearing by well under a beam (0.3 m at 1 km: 0.02 degrees).
_MISS_DISTANCE = 1000.0


@dataclass(frozen=True)
class Laser:
    """One laser of several: its scans' topic and frame, where it sits on the robot (x, y, yaw in the tracking
    frame) and where that came from, in words."""

    topic: str
    frame: str
    mount: tuple[float, float, float]
    source: str = ""

    def describe(self) -> str:
        x, y, yaw = self.mount
        return f"{self.topic} at ({x:.3f}, {y:.3f}, {math.degrees(yaw):.1f} deg) from {self.source or 'the caller'}"


def merged_topic(lasers: Sequence[Laser]) -> str:
    """The topic merged scans carry: the lasers' topics joined by '+'."""
    return "+".join(laser.topic for laser in lasers)


def merge(parts: Sequence[Scan], mounts: Sequence[tuple[float, float, float]], frame: str, topic: str) -> Scan:
    """``parts`` (scans in time order, ``mounts[i]`` placing ``parts[i]``) as one scan in the tracking frame
    ``frame``, at the newest part's time, every beam with its own time."""
    if len(parts) != len(mounts) or not parts:
        raise ValueError(f"{len(parts)} scans but {len(mounts)} mounts")
    reference = max(p.time for p in parts)
    ranges, angles, times, intensities = [], [], [], []
    for part, (mx, my, myaw) in zip(parts, mounts):
        r = np.asarray(within_sensor_limits(part.ranges, float(part.range_min), float(part.range_max)),
                       dtype=np.float64)
        bearing = np.asarray(part.angles, dtype=np.float64) + myaw
        hit = np.isfinite(r) & (r > 0.0)
        miss = np.isposinf(r)
        keep = hit | miss
        reach = np.where(hit, r, _MISS_DISTANCE)[keep]
        x = mx + reach * np.cos(bearing[keep])
        y = my + reach * np.sin(bearing[keep])
        ranges.append(np.where(hit[keep], np.hypot(x, y), np.inf))
        angles.append(np.arctan2(y, x))
        times.append((part.time - reference) + part.beam_times()[keep])
        if part.intensities is not None:
            intensities.append(np.asarray(part.intensities, dtype=np.float32)[keep])
    angle = np.concatenate(angles).astype(np.float32)
    return Scan(time=reference, ranges=np.concatenate(ranges).astype(np.float32), angles=angle, frame=frame,
                topic=topic, range_min=0.0, range_max=math.inf,
                angle_min=float(angle.min()) if angle.shape[0] else 0.0, angle_increment=None,
                intensities=np.concatenate(intensities) if len(intensities) == len(parts) else None,
                point_times=np.concatenate(times))


class ScanMerger:
    """Scans of ``lasers`` in, one scan a window out (:func:`merge`). A window never holds two scans of one laser:
    it closes at the first scan after it holds one of every laser, or at a laser's second (the others' scans may
    be late, or a laser may have stopped). Windows then come at the fastest laser's rate and every scan is used
    once: closing only once every laser had sent one (at the slowest laser's rate) left two lasers at 10 and 7 Hz
    10-25 % behind one 360 degree lidar at 10 Hz, and this at par (bench/multi_lidar.py). Scans stamped alike go
    into one window whatever order they came in, so that no two windows share a stamp (mapping would drop the
    second as a duplicate). A window is stamped with its newest scan: two lasers at 10 and 7 Hz give windows 14 to
    100 ms apart, which is why auto reads local SLAM's velocity off its poses over 0.2 s when lasers are merged
    (``regime.choose``)."""

    def __init__(self, lasers: Sequence[Laser], frame: str = "base_link") -> None:
        if len(lasers) < 2:
            raise ValueError("merging needs two lasers or more")
        self.lasers = {laser.topic: laser for laser in lasers}
        if len(self.lasers) != len(lasers):
            raise ValueError("every laser needs a topic of its own")
        self.frame = frame
        self.topic = merged_topic(lasers)
        self._window: dict[str, Scan] = {}

    def add(self, scan: Scan) -> Scan | None:
        """The merged scan of the window ``scan`` closed, else None."""
        if scan.topic not in self.lasers:
            raise ValueError(f"a scan on {scan.topic or 'no topic'}, not one of {', '.join(self.lasers)}")
        out = None
        if scan.topic in self._window or len(self._window) == len(self.lasers):
            # The parts stamped as this scan start the next window with it (unless one is its own laser's)
            older = {k: p for k, p in self._window.items() if p.time < scan.time}
            alike = {k: p for k, p in self._window.items() if p.time >= scan.time}
            if not older or scan.topic in alike:
                older, alike = self._window, {}
            out = self._merged(older)
            self._window = alike
        self._window[scan.topic] = scan
        return out

    def flush(self) -> Scan | None:
        """The window so far as one scan (None when empty): what is left when the recording ends."""
        out = self._merged(self._window) if self._window else None
        self._window = {}
        return out

    def _merged(self, window: dict[str, Scan]) -> Scan:
        parts = sorted(window.values(), key=lambda s: s.time)
        return merge(parts, [self.lasers[p.topic].mount for p in parts], self.frame, self.topic)


def merged_records(records: Iterable[Record], lasers: Sequence[Laser], frame: str = "base_link") -> Iterator[Record]:
    """``records`` with the scans of ``lasers`` merged (:class:`ScanMerger`), every other record as it came. A
    window goes out at the scan after it, so the records that came between (odometry over the whole window, which
    its de-skew needs) go before it: a merged scan may follow records up to a scan period newer than its stamp."""
    merger = ScanMerger(lasers, frame)
    for record in records:
        if isinstance(record, Scan) and record.topic in merger.lasers:
            out = merger.add(record)
            if out is not None:
                yield out
        else:
            yield record
    last = merger.flush()
    if last is not None:
        yield last
