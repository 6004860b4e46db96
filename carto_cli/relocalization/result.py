"""What a relocalization answers: one query's result and its timings, a batch's rows, summary and CSV."""
from __future__ import annotations

import csv
import io
import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carto_cli.core.enums import TextEnum
from carto_cli.io.atomic import atomic_output
from carto_cli.relocalization.queries import Query

__all__ = [
    "CSV_COLUMNS",
    "PATHS",
    "TIMING_BUCKETS",
    "VERDICTS",
    "BatchSummary",
    "Fit",
    "Latency",
    "PoseVerdict",
    "QueryResult",
    "RelocalizationResult",
    "SearchPath",
    "Timings",
    "summarize",
    "write_results_csv",
]

@dataclass(frozen=True)
class Fit:
    """How well a scan fits the map at a pose (``Judge.fit``), and whether that is good enough."""

    ok: bool
    reason: str  # '' when ok
    score: float  # mean probability under the points, unknown cells 0.1
    known_fraction: float  # share of the points on cells the map knows
    known_score: float  # their mean probability
    see_through: float  # share of the rays crossing a wall before their end
    inlier_fraction: float  # share of the points on a wall (within a cell)
    laser_seen: bool = True  # the laser stands on a cell the map knows (``MapIndex.seen``)


class SearchPath(TextEnum):
    """The search stage a result came from (RelocalizationResult.path), in the order a query tries them."""

    WINDOWED = "windowed"
    WINDOWED_WIDE = "windowed-wide"
    FALLBACK_FILTERED = "fallback-filtered"
    FALLBACK_ALL = "fallback-all"
    GLOBAL = "global"


class PoseVerdict(TextEnum):
    """What a relocalization (or a tracked scan) concludes of its pose."""

    OK = "ok"
    AMBIGUOUS = "ambiguous"  # it fits, and so does a distinct rival nearly as well
    LOST = "lost"  # nothing fits well enough, or the answer jumped farther than allowed


PATHS = tuple(SearchPath)
TIMING_BUCKETS = ("submap preparation", "pose search", "scan scoring", "other")
VERDICTS = tuple(PoseVerdict)
# The batch CSV: the scan, then the same fields as one answer's JSON (RelocalizationResult.to_dict), flattened.
CSV_COLUMNS = ("t", "scan_index", "x", "y", "yaw", "verdict", "score", "ambiguity", "inlier_fraction",
               "context_checked", "context_through_walls", "cov_xx",
               "cov_xy", "cov_xyaw", "cov_yy", "cov_yyaw", "cov_yawyaw", "path", "ms", "success", "submap", "reason")


class Timings:
    """One query's time in the TIMING_BUCKETS; 'other' is whatever the three named ones leave of the total."""

    def __init__(self):
        self.t0 = time.perf_counter()
        self.ms = dict.fromkeys(TIMING_BUCKETS[:3], 0.0)

    def add(self, bucket: str, t_start: float) -> float:
        now = time.perf_counter()
        self.ms[bucket] += (now - t_start) * 1e3
        return now

    def finish(self) -> tuple[dict[str, float], float]:
        total = (time.perf_counter() - self.t0) * 1e3
        out = dict(self.ms)
        out["other"] = max(0.0, total - sum(self.ms.values()))
        return out, total


@dataclass(frozen=True)
class Latency:
    """Mean, percentiles and maximum of query times (ms); None for no queries."""

    mean_ms: float | None
    p50_ms: float | None
    p95_ms: float | None
    p99_ms: float | None
    max_ms: float | None

    @classmethod
    def of(cls, values_ms) -> Latency:
        v = np.asarray(values_ms, dtype=np.float64)
        if v.size == 0:
            return cls(None, None, None, None, None)
        return cls(float(v.mean()), float(np.percentile(v, 50)), float(np.percentile(v, 95)),
                   float(np.percentile(v, 99)), float(v.max()))


@dataclass
class RelocalizationResult:
    pose: np.ndarray  # (x, y, yaw) tracking frame in the map frame (refined when the refinement was trusted)
    score: float  # score_at of ``pose`` on ``submap`` (mean probability, 0.1..0.9); 0 when nothing was found
    path: str  # a SearchPath
    success: bool  # found, score >= the path's threshold, refinement consistent
    submaps_considered: list[int]  # every submap searched, in search order
    timings: dict[str, float]  # ms per TIMING_BUCKETS
    total_ms: float
    submap: int | None = None  # the submap the pose was found in
    search_score: float = 0.0  # branch-and-bound score before refinement
    reason: str = ""  # why it fell back / failed, '' on a clean windowed success
    threshold: float = 0.0  # the score ``success`` was judged against
    known_fraction: float = 1.0  # share of the refinement points in known cells at ``pose``
    known_score: float = 0.0  # score_at over those points only
    see_through: float = 0.0  # share of the scan's rays crossing a wall of the submap at ``pose`` (ray_consistency)
    # How far to trust ``pose``: ``verdict`` 'ok' (success), 'ambiguous' (a different place fits about as well:
    # ``ambiguity`` = the best distinct rival's search score / the answer's, ``rival`` its map pose) or 'lost'
    # (nothing fits well enough, or the answer jumped farther than allowed); ``reason`` says why.
    verdict: str = ""  # a PoseVerdict; '' -> from ``success``: OK or LOST
    covariance: np.ndarray | None = None  # (3, 3) of (x, y, yaw) in the map frame (m^2, rad^2)
    ambiguity: float = 0.0
    rival: np.ndarray | None = None
    inlier_fraction: float = 0.0  # share of the refinement points on a wall of the map at ``pose``
    # The scans around the query that checked the answer (``Relocalizer.relocalize``'s context): how many were
    # judged where the map knows the place, and how many of those saw through walls of the map (0 / 0: not checked)
    context_checked: int = 0
    context_through_walls: int = 0

    def __post_init__(self):
        if not self.verdict:
            self.verdict = PoseVerdict.OK if self.success else PoseVerdict.LOST
        if self.verdict not in VERDICTS:
            raise ValueError(f"verdict must be one of {', '.join(VERDICTS)}, got {self.verdict!r}")
        self.verdict = PoseVerdict(self.verdict)

    @property
    def sigmas(self) -> tuple[float, float, float] | None:
        """Standard deviations of x, y (m) and yaw (rad) from the covariance's diagonal."""
        if self.covariance is None:
            return None
        d = np.sqrt(np.maximum(np.diag(self.covariance), 0.0))
        return float(d[0]), float(d[1]), float(d[2])

    def to_dict(self) -> dict:
        """JSON-ready (``carto relocalize --json``)."""
        cov = None if self.covariance is None else [[float(f"{v:.6g}") for v in row] for row in self.covariance]
        return {
            "pose": {"x": float(self.pose[0]), "y": float(self.pose[1]), "yaw": float(self.pose[2])},
            "verdict": self.verdict,
            "covariance": cov,
            "ambiguity": round(float(self.ambiguity), 4),
            "rival": None if self.rival is None else {"x": float(self.rival[0]), "y": float(self.rival[1]),
                                                      "yaw": float(self.rival[2])},
            "inlier_fraction": round(float(self.inlier_fraction), 4),
            "context_checked": int(self.context_checked),
            "context_through_walls": int(self.context_through_walls),
            "score": round(float(self.score), 6),
            "search_score": round(float(self.search_score), 6),
            "threshold": float(self.threshold),
            "known_fraction": round(float(self.known_fraction), 4),
            "known_score": round(float(self.known_score), 6),
            "see_through": round(float(self.see_through), 4),
            "path": self.path,
            "success": bool(self.success),
            "submap": self.submap,
            "submaps_considered": [int(i) for i in self.submaps_considered],
            "reason": self.reason,
            "timings_ms": {k: round(float(v), 3) for k, v in self.timings.items()},
            "total_ms": round(float(self.total_ms), 3),
        }


@dataclass
class QueryResult:
    query: Query
    scan_index: int
    scan_time: float
    result: RelocalizationResult

    def row(self) -> dict:
        r = self.result
        c = np.full((3, 3), np.nan) if r.covariance is None else r.covariance
        cov = {name: ("" if np.isnan(c[i, j]) else f"{c[i, j]:.6g}") for name, (i, j) in zip(
            ("cov_xx", "cov_xy", "cov_xyaw", "cov_yy", "cov_yyaw", "cov_yawyaw"),
            ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)))}
        return {"t": f"{self.scan_time:.6f}", "scan_index": self.scan_index,
                "x": f"{r.pose[0]:.4f}", "y": f"{r.pose[1]:.4f}", "yaw": f"{r.pose[2]:.5f}", "verdict": r.verdict,
                "score": f"{r.score:.4f}", "ambiguity": f"{r.ambiguity:.4f}",
                "inlier_fraction": f"{r.inlier_fraction:.4f}", "context_checked": r.context_checked,
                "context_through_walls": r.context_through_walls, **cov, "path": r.path, "ms": f"{r.total_ms:.2f}",
                "success": int(bool(r.success)), "submap": "" if r.submap is None else r.submap,
                "reason": r.reason}


@dataclass
class BatchSummary:
    queries: int
    successes: int
    success_rate: float
    p50_ms: float
    p95_ms: float
    p99_ms: float
    max_ms: float
    paths: dict[str, int] = field(default_factory=dict)
    verdicts: dict[str, int] = field(default_factory=dict)
    timings_ms: dict[str, float] = field(default_factory=dict)  # mean per bucket

    def to_dict(self) -> dict:
        return {k: (round(v, 3) if isinstance(v, float) else v) for k, v in self.__dict__.items()}


def summarize(results: Sequence[QueryResult]) -> BatchSummary:
    ok = sum(bool(q.result.success) for q in results)
    paths = {p.value: sum(q.result.path == p for q in results) for p in SearchPath}
    verdicts = {v.value: sum(q.result.verdict == v for q in results) for v in PoseVerdict}
    buckets = {b: float(np.mean([q.result.timings[b] for q in results])) if results else 0.0 for b in TIMING_BUCKETS}
    lat = Latency.of([q.result.total_ms for q in results])
    return BatchSummary(len(results), ok, ok / len(results) if results else 0.0, lat.p50_ms or 0.0,
                        lat.p95_ms or 0.0, lat.p99_ms or 0.0, lat.max_ms or 0.0, paths, verdicts, buckets)


def write_results_csv(path: str | Path, results: Iterable[QueryResult]) -> Path:
    """The rows as CSV (CSV_COLUMNS), written atomically."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(CSV_COLUMNS), lineterminator="\n")
    w.writeheader()
    for q in results:
        w.writerow(q.row())
    path = Path(path)
    with atomic_output(path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")
    return path
