"""Following a scan from a predicted pose, and what the scans around an answer say of it.

:func:`follow` is one step of tracking: the scan's pose predicted from a pose the map already trusts (moved by
odometry, or by the previous motion and a small correlative search), refined by least squares against the map
grid nearest the prediction and judged like a relocalization (``Judge.fit``), with the slide from the
prediction bounded. The tracker (``tracking.py``) takes it for every scan of a recording.

:func:`check_context` takes it for the scans around a relocalization answer (``ScanContext``: the records of
the recording before and after the query). A single scan of another building can fit a corridor of this map
with every check passed: its points on walls, few rays through walls, no rival (docs/localization.md). The
robot that took it did not stand still, and a few metres on, or a few metres back, its scans' rays pass
through walls of this map. Clutter cannot do that: furniture and people shorten rays, they never lengthen one
through a wall. So the check counts the neighbours that see through walls, not those that fit badly: on carto's
maps of the benches' recordings (the six real Radish logs, three dense simulations) the right answers'
neighbours often fit badly (on walls 62-89 % where 90 % is asked, scores under min_score on faint walls), but of
689 right answers' 10,454 neighbours up to 4 m away, four answers had one neighbour seeing through walls (at
most 14.7 % of its rays, 13 % being the limit) and none had two; the scans of other buildings answered `ok` on
bench-dense's images had 4-9 (docs/localization.md, *The scans around an answer*).
"""
from __future__ import annotations

import math
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np

from carto_cli.core import transform
from carto_cli.core.records import Odometry, Record, Scan
from carto_cli.matching import correlative
from carto_cli.relocalization.judge import Judge
from carto_cli.relocalization.queries import ScanContext
from carto_cli.relocalization.result import Fit

__all__ = ["ContextCheck", "Followed", "check_context", "follow"]


# Without odometry the prediction is the previous motion repeated, and least squares from it alone is held back
# by its pull towards the prediction: along a corridor the track fell behind by 0.1 m a scan (3 m in 6 s, every
# scan still scoring 0.75) on the loop building. A small correlative search first (as local SLAM's online one).
CORRELATIVE_WINDOW_M = 0.2
CORRELATIVE_WINDOW_RAD = math.radians(5.0)

# A neighbour is taken each time odometry has moved this far (or turned this much) since the last one taken: scans
# 0.1 s apart say nearly what the query said. 8 each way at 0.5 m reach 4 m from the answer: an aces corridor scan
# on freiburg-079's image fitted a corridor for 3 m forward and 2 m back, and its path met walls beyond.
CONTEXT_STEP_M = 0.5
CONTEXT_STEP_RAD = math.radians(10.0)


@dataclass
class Followed:
    """A scan followed from a prediction: the refined pose, the submap it was refined in, and the judgement."""

    pose: np.ndarray  # (x, y, yaw) map frame
    submap: int
    grid_pose: np.ndarray  # ``pose`` in that submap's grid frame
    points: np.ndarray  # the refinement's points (tracking frame)
    fit: Fit
    ok: bool
    reason: str


def follow(judge: Judge, scan: Scan, predicted: np.ndarray, mount: np.ndarray, min_score: float, *,
           correlate: bool, max_slide: float, timings: dict[str, float] | None = None) -> Followed | None:
    """``scan`` refined from ``predicted`` (map frame) in the submap nearest it and judged: its fit (score or
    known-cell score against ``min_score``, see-through, on-wall share, laser on a known cell) and a slide of at
    most ``max_slide`` m from the prediction. ``correlate``: a small correlative search first (a prediction
    without odometry). None when the scan has no returns in range. ``timings``: ms added per stage
    ('preprocessing', 'refinement', 'judging')."""
    t = time.perf_counter()

    def lap(stage: str) -> None:
        nonlocal t
        now = time.perf_counter()
        if timings is not None:
            timings[stage] += (now - t) * 1e3
        t = now

    index = judge.index
    search, fine = index.preprocess(scan, mount, search=correlate)
    lap("preprocessing")
    if len(fine) == 0:
        return None
    submap = index.nearest_submap(predicted[:2])
    grid = index.grids[submap]
    start = transform.compose(index.map_to_grid[submap], predicted)
    if correlate and len(search):
        start = correlative.match(grid, search, start, linear_search_window=CORRELATIVE_WINDOW_M,
                                  angular_search_window=CORRELATIVE_WINDOW_RAD).pose
    grid_pose = judge.ceres.match(grid, fine, start, target_translation=start[:2]).pose
    found = transform.compose(index.grid_to_map[submap], grid_pose)
    lap("refinement")
    fit = judge.fit(submap, fine, grid_pose, min_score, known_ok=True, sensor=mount[:2])
    ok, reason = fit.ok, fit.reason
    slide = math.hypot(*(found[:2] - predicted[:2]))
    if ok and slide > max_slide:
        ok, reason = False, f"refinement slid {slide:.2f} m from the prediction"
    lap("judging")
    return Followed(found, submap, grid_pose, fine, fit, ok, reason)


@dataclass
class ContextCheck:
    """What the neighbours of an answer said: how many were judged where the map knows the place, how many of
    those saw through walls of the map (more than ``max_see_through`` of their rays), and how many were lost
    for any reason (reported, not a veto: clutter makes a right answer's neighbours fit badly)."""

    checked: int = 0
    through_walls: int = 0
    lost: int = 0

    def vetoes(self, max_through_walls: int) -> bool:
        return self.through_walls > max_through_walls


def _walk(records: Sequence[Record], odom_at_query: Odometry | None, backwards: bool
          ) -> Iterator[tuple[Scan, Odometry | None]]:
    """(scan, odometry at it) in walking order away from the query, lazily (a context holds 25 s of 50 Hz
    odometry; a check reads a few metres of it). The odometry at a scan is the latest message before it, as the
    tracker takes it."""
    if not backwards:
        last = odom_at_query
        for rec in records:
            if isinstance(rec, Odometry):
                last = rec
            elif isinstance(rec, Scan):
                yield rec, last
        return
    j = len(records) - 1  # the odometry search's position: only ever moves back, as the scans do
    for p in range(len(records) - 1, -1, -1):
        rec = records[p]
        if not isinstance(rec, Scan):
            continue
        j = min(j, p - 1)
        while j >= 0 and not isinstance(records[j], Odometry):
            j -= 1
        odom = records[j] if j >= 0 else None
        yield rec, odom if isinstance(odom, Odometry) else None


def _odometry_at_end(records: Sequence[Record]) -> Odometry | None:
    for rec in reversed(records):
        if isinstance(rec, Odometry):
            return rec
    return None


def _pose(odom: Odometry) -> np.ndarray:
    return np.array([odom.x, odom.y, odom.yaw])


def _moved(a: Odometry, b: Odometry) -> bool:
    """Whether odometry went at least one context step from ``a`` to ``b``."""
    turn = abs(transform.wrap_angle_scalar(b.yaw - a.yaw))
    return math.hypot(b.x - a.x, b.y - a.y) >= CONTEXT_STEP_M or turn >= CONTEXT_STEP_RAD


def check_context(judge: Judge, context: ScanContext, pose, mount: np.ndarray, min_score: float,
                  scans: int, max_through_walls: int, *, max_slide: float = 0.3) -> ContextCheck:
    """Follow up to ``scans`` neighbours each way from ``pose`` (the answer for the scan between ``context``'s
    ``before`` and ``after``), one each ``CONTEXT_STEP_M`` / ``CONTEXT_STEP_RAD`` of odometry (every scan without
    odometry, then by the previous motion and a correlative search), each from the last one that fitted, and
    count those whose rays pass through walls of the map, until the verdict is settled: it stops once more than
    ``max_through_walls`` did, or the neighbours left could not make that many. A neighbour whose laser would
    stand where the map never saw, or with no returns, says nothing and is not counted: the robot may have come
    from a part of the building the map leaves out."""
    out = ContextCheck()
    limit = judge.ro.max_see_through
    odom0 = _odometry_at_end(context.before)
    left = 2 * scans  # neighbours still to try, both ways

    def settled() -> bool:
        return out.through_walls > max_through_walls or out.through_walls + left <= max_through_walls

    for backwards, records in ((False, context.after), (True, context.before)):
        here = np.asarray(pose, dtype=np.float64).copy()
        here_odom = odom0
        taken_odom = odom0
        velocity = np.zeros(3)
        taken = 0
        for scan, odom in _walk(records, odom0, backwards):
            if taken >= scans or settled():
                break
            with_odometry = here_odom is not None and odom is not None
            if with_odometry:
                assert taken_odom is not None and here_odom is not None and odom is not None
                if not _moved(taken_odom, odom):
                    continue
                predicted = transform.compose(here, transform.relative(_pose(here_odom), _pose(odom)))
            else:
                predicted = transform.compose(here, velocity)
            taken += 1
            left -= 1
            taken_odom = odom
            f = follow(judge, scan, predicted, mount, min_score, correlate=not with_odometry, max_slide=max_slide)
            here_odom = odom
            if f is None or not f.fit.laser_seen:
                here = predicted
                continue
            out.checked += 1
            out.through_walls += f.fit.see_through > limit
            if f.ok:
                if not with_odometry:
                    velocity = transform.relative(here, f.pose)
                here = f.pose
            else:
                out.lost += 1
                here = predicted
        left -= scans - taken  # this way ran out of records: those neighbours will not come
    return out
