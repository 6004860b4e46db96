"""Tracking a whole recording in a fixed map: a pose and a verdict for every scan (pure localization, offline).

Cartographer localizes only in its own .pbstream and AMCL only online; this follows a recording through any map
the :class:`~carto_cli.relocalization.Relocalizer` reads (map.carto or a map_server image):

1. **First fix.** From ``initial_pose`` (a windowed search around it), else a global search; scans before the
   first fix are reported 'lost' with no pose, and the time to the first fix is measured.
2. **Each following scan** is predicted from the previous pose moved by the odometry between the two scans (or,
   without odometry, by the previous scan-to-scan motion: constant velocity, then a small correlative search),
   then refined by least squares against the map grid nearest the prediction (the map's own refinement weights,
   pulled towards the prediction). With odometry that is the whole cost of a tracked scan: no search.
3. **Judged like a relocalization:** the refined pose's score on the map, or the score of its points on known
   cells when part of the scan sees what the map never did, must reach ``min_score``; of the points on known
   cells ``min_inlier_fraction`` must fall on walls; at most ``max_see_through`` of the rays may cross a wall;
   the refinement must not slide farther than ``max_slide`` from the prediction. A scan that fails is 'lost';
   after ``lost_after`` such scans in a row the tracker re-localizes: a windowed search around the prediction,
   then a global one (and again every ``lost_after`` scans while it stays lost). A kidnapped robot is so found
   again within a few scans.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.core.records import Odometry, Record, Scan
from carto_cli.relocalization.following import follow
from carto_cli.relocalization.relocalizer import Relocalizer
from carto_cli.relocalization.result import PoseVerdict

__all__ = ["TRACK_COLUMNS", "TrackSummary", "TrackedScan", "Tracker", "summarize_track"]

TRACK_COLUMNS = ("t", "scan_index", "x", "y", "yaw", "verdict", "source", "score", "inlier_fraction", "sigma_x",
                 "sigma_y", "sigma_yaw", "ms", "reason")


@dataclass
class TrackedScan:
    index: int  # the scan's index in the recording (from 0)
    time: float
    pose: np.ndarray | None  # (x, y, yaw) in the map frame; None before the first fix
    verdict: str  # ok | ambiguous | lost
    source: str  # 'track' (predicted and refined), 'relocalize:PATH' (a search), 'none'
    score: float = 0.0
    inlier_fraction: float = 0.0
    sigmas: tuple[float, float, float] | None = None
    ms: float = 0.0
    reason: str = ""

    def row(self) -> dict:
        p = self.pose
        s = self.sigmas
        return {"t": f"{self.time:.6f}", "scan_index": self.index,
                "x": "" if p is None else f"{p[0]:.4f}", "y": "" if p is None else f"{p[1]:.4f}",
                "yaw": "" if p is None else f"{p[2]:.5f}", "verdict": self.verdict, "source": self.source,
                "score": f"{self.score:.4f}", "inlier_fraction": f"{self.inlier_fraction:.4f}",
                "sigma_x": "" if s is None else f"{s[0]:.4f}", "sigma_y": "" if s is None else f"{s[1]:.4f}",
                "sigma_yaw": "" if s is None else f"{s[2]:.5f}", "ms": f"{self.ms:.3f}", "reason": self.reason}


@dataclass
class TrackSummary:
    scans: int
    verdicts: dict[str, int]
    relocalizations: int  # searches run (first fix included)
    first_fix_index: int | None  # the first scan with an 'ok' pose
    first_fix_s: float | None  # processing time from the start until that pose (s)
    seconds: float  # processing time of the whole recording, reading included
    scans_per_second: float
    timings_ms: dict[str, float] = field(default_factory=dict)  # per stage, totals

    def to_dict(self) -> dict:
        return {k: (round(v, 4) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


class Tracker:
    """Follows scans through ``relocalizer``'s map (module doc). ``lost_after``: failed scans in a row before a
    search; ``max_slide``: m a refinement may move from the prediction before it is not trusted."""

    def __init__(self, relocalizer: Relocalizer, *, lost_after: int = 3, max_slide: float = 0.3,
                 laser_pose=None, max_jump: float | None = None):
        self.reloc = relocalizer
        self.lost_after = int(lost_after)
        self.max_slide = float(max_slide)
        self.max_jump = max_jump
        self.mount = relocalizer.laser_pose if laser_pose is None else transform.as_pose(laser_pose).reshape(3)
        self.min_score = relocalizer.ro.min_score
        self.timings = {"preprocessing": 0.0, "refinement": 0.0, "judging": 0.0, "relocalization": 0.0}
        self.relocalizations = 0  # searches run by the last track() (its first fix included)

    def track(self, records: Iterable[Record], *, initial_pose=None, sigma_xy: float | None = None,
              sigma_yaw: float | None = None,
              on_scan: Callable[[TrackedScan], None] | None = None) -> Iterator[TrackedScan]:
        """A :class:`TrackedScan` per scan of ``records`` (scans and odometry in time order), as they come."""
        pose: np.ndarray | None = None
        prev_odom: np.ndarray | None = None  # odometry at the previous scan
        last_odom: np.ndarray | None = None  # latest odometry message
        velocity = np.zeros(3)  # previous scan-to-scan motion, for constant velocity without odometry
        failures = 0
        index = -1
        self.relocalizations = 0
        for rec in records:
            if isinstance(rec, Odometry):
                last_odom = np.array([rec.x, rec.y, rec.yaw])
                continue
            if not isinstance(rec, Scan):
                continue
            index += 1
            t0 = time.perf_counter()
            scan_odom = None if last_odom is None else last_odom.copy()
            out = self._step(rec, index, pose, prev_odom, scan_odom, velocity, failures, initial_pose, sigma_xy,
                             sigma_yaw)
            out.ms = (time.perf_counter() - t0) * 1e3
            if out.pose is not None and out.verdict == PoseVerdict.OK:
                if pose is not None:
                    velocity = transform.relative(pose, out.pose)
                pose = out.pose
                failures = 0
            elif pose is not None:
                failures += 1
                # Keep dead reckoning so the next prediction still follows the robot.
                pose = self._predict(pose, prev_odom, scan_odom, velocity)
            prev_odom = scan_odom
            if on_scan is not None:
                on_scan(out)
            yield out

    @staticmethod
    def _predict(pose, prev_odom, odom, velocity) -> np.ndarray:
        if prev_odom is not None and odom is not None:
            return transform.compose(pose, transform.relative(prev_odom, odom))
        return transform.compose(pose, velocity)

    def _step(self, scan: Scan, index: int, pose, prev_odom, odom, velocity, failures, initial_pose, sigma_xy,
              sigma_yaw) -> TrackedScan:
        t = time.perf_counter()
        if pose is None:
            prior = initial_pose if (initial_pose is not None and self.relocalizations == 0) else None
            return self._search(scan, index, prior, sigma_xy, sigma_yaw, "no fix yet")
        predicted = self._predict(pose, prev_odom, odom, velocity)
        # Searches only every ``lost_after`` failed scans: a robot lost for a while is not searched for at 10 Hz.
        if failures >= self.lost_after and (failures - self.lost_after) % self.lost_after == 0:
            res = self._search(scan, index, predicted, 0.5, math.radians(10.0), f"{failures} scans lost")
            if res.verdict == PoseVerdict.OK:
                return res
            return self._search(scan, index, None, None, None, f"{failures} scans lost; windowed search failed")
        with_odometry = prev_odom is not None and odom is not None
        self._add("preprocessing", t)  # the prediction's share
        f = follow(self.reloc.judge, scan, predicted, self.mount, self.min_score, correlate=not with_odometry,
                   max_slide=self.max_slide, timings=self.timings)
        if f is None:
            return TrackedScan(index, scan.time, predicted, PoseVerdict.LOST, "none", reason="no returns in range")
        t = time.perf_counter()
        cov = self.reloc.covariance(f.submap, f.points, f.grid_pose)
        sig = tuple(float(v) for v in np.sqrt(np.maximum(np.diag(cov), 0.0)))
        self._add("judging", t)
        return TrackedScan(index, scan.time, f.pose, PoseVerdict.OK if f.ok else PoseVerdict.LOST, "track", f.fit.score,
                           f.fit.inlier_fraction, (sig[0], sig[1], sig[2]), reason=f.reason)

    def _search(self, scan: Scan, index: int, prior, sigma_xy, sigma_yaw, why: str) -> TrackedScan:
        t = time.perf_counter()
        self.relocalizations += 1
        try:
            try:
                # No second look: the next scan is the tracker's (a robot not in the map would cost it ~0.5 s a scan)
                r = self.reloc.relocalize(scan, prior, sigma_xy=sigma_xy, sigma_yaw=sigma_yaw, laser_pose=self.mount,
                                          max_jump=self.max_jump if prior is not None else None, second_look=False)
            except CartoError:
                if prior is None:
                    raise
                # Dead reckoning has carried the prediction off the map: only a global search can help.
                r = self.reloc.relocalize(scan, None, laser_pose=self.mount, second_look=False)
        finally:
            self._add("relocalization", t)
        return TrackedScan(index, scan.time, r.pose if r.verdict != PoseVerdict.LOST else None, r.verdict,
                           f"relocalize:{r.path}", r.score, r.inlier_fraction, r.sigmas,
                           reason=f"{why}: {r.reason}" if r.reason else why)

    def _add(self, stage: str, t: float) -> float:
        now = time.perf_counter()
        self.timings[stage] += (now - t) * 1e3
        return now


def summarize_track(scans: list[TrackedScan], seconds: float, relocalizations: int,
                    timings: dict[str, float]) -> TrackSummary:
    """Counts, first fix and rate of a tracked recording (``seconds``: its whole processing time)."""
    verdicts = {v.value: sum(s.verdict == v for s in scans) for v in PoseVerdict}
    first = next((k for k, s in enumerate(scans) if s.verdict == PoseVerdict.OK), None)
    first_s = None if first is None else float(sum(s.ms for s in scans[:first + 1])) / 1e3
    return TrackSummary(len(scans), verdicts, relocalizations, None if first is None else scans[first].index,
                        first_s, seconds, len(scans) / seconds if seconds > 0 else 0.0,
                        {k: round(v, 1) for k, v in timings.items()})
