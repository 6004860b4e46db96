"""Judging a pose: how well a scan fits the map there, how sure that is, and the verdict of a query's answer.

A search's best pose (:class:`Candidate`) is refined by least squares (``refine``: a refinement that wanders from
the search's pose has slid along a corridor, and the search's pose is judged instead), fitted (``fit``: the score,
or that of the points on known cells when part of the scan sees what the map never did; the rays through walls,
``matching/ray_consistency.py``; the share of points on walls; whether the laser stands where the map has seen),
given a covariance (``least_squares.covariance``) and weighed against its rivals (``ambiguity``: other submaps'
bests, and the best elsewhere in its own search window, ``branch_and_bound.peaks``). ``verdict`` turns that into
the query's answer, 'ok', 'ambiguous' or 'lost', and records it in the query's :class:`Ledger`.

The one judgement of a match: relocalization's answers and a tracked scan (``following.follow``) are judged alike.
The judge searches nothing but an answer's rival; it knows neither the searches nor the stages that call it.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from carto_cli.core import transform
from carto_cli.matching import branch_and_bound, least_squares
from carto_cli.matching.ray_consistency import see_through_fraction
from carto_cli.matching.scoring import fit_scores
from carto_cli.matching.stack_cache import StackCache
from carto_cli.options.schema import Relocalization
from carto_cli.relocalization.map_index import MapIndex
from carto_cli.relocalization.result import Fit, PoseVerdict, RelocalizationResult, SearchPath, Timings

__all__ = ["DISTINCT_XY", "DISTINCT_YAW", "MIN_KNOWN_FRACTION", "Asked", "Candidate", "Judge", "Ledger"]

DISTINCT_XY = 1.0  # m: candidates farther apart than this (or DISTINCT_YAW) are different places
DISTINCT_YAW = math.radians(10.0)
# A scan taken where the map ends sees partly unmapped space: its points there read 0.1 whatever the pose, and
# drag the plain score of the right pose below min_score (on bench-dense, every failure with a prior was such a
# scan: docs/measurements.md). A windowed answer (``known_ok``) whose plain score misses the threshold is accepted
# when the points in known cells (at least MIN_KNOWN_FRACTION of them) reach it on their own.
MIN_KNOWN_FRACTION = 0.5


@dataclass(frozen=True, slots=True, eq=False)
class Candidate:
    """A search's best pose in one submap, before refinement (told from the others by identity, not value)."""

    submap: int
    grid_pose: np.ndarray  # B&B pose in the submap's grid frame
    score: float
    estimate: np.ndarray | None = None  # the search's centre in the grid frame
    lin: float = 0.0  # the search's half-windows (m, rad) around ``estimate``: where a rival is looked for
    ang: float = 0.0
    levels: tuple[tuple[float, int], ...] = ()  # the search's stages (match_multilevel), for the rival search
    rival: branch_and_bound.MatchResult | None = None  # the search's best at another place, when it looked
    rival_searched: bool = False

class Asked(Protocol):
    """What a verdict reads of the query it answers (``stages.Query`` is one)."""

    @property
    def mount(self) -> np.ndarray: ...  # the laser in the tracking frame

    @property
    def search_pts(self) -> np.ndarray: ...

    @property
    def fine_pts(self) -> np.ndarray: ...

    @property
    def search_floor(self) -> float: ...  # what whole-submap searches look down to

    @property
    def prior(self) -> np.ndarray | None: ...

    @property
    def max_jump(self) -> float | None: ...  # m: an answer farther from the prior is 'lost'

    @property
    def jobs(self) -> int | None: ...  # threads for the rival search (None: every core)


@dataclass
class Ledger:
    """What a query's verdicts record as its stages go: its timings, the submaps it searched, why each stage did
    not answer, and its best answer judged not ok (should no stage find one)."""

    tm: Timings
    considered: list[int] = field(default_factory=list)
    reasons: list[str] = field(default_factory=list)
    max_ambiguity: float | None = None  # the rival ratio from which an answer is ambiguous (None: the option's)
    failed: RelocalizationResult | None = None


class Judge:
    """Refines, fits and judges poses in ``index``'s submaps (module doc): ``ro`` the thresholds, ``ceres`` the
    refinement (the loop-closure search's), ``cache`` the precomputation stacks an answer's rival is searched on."""

    def __init__(self, index: MapIndex, ro: Relocalization, ceres: least_squares.CeresScanMatcher, cache: StackCache):
        self.index = index
        self.ro = ro
        self.ceres = ceres
        self.cache = cache

    def fit(self, submap: int, points: np.ndarray, grid_pose: np.ndarray, threshold: float, *,
              known_ok: bool = False, sensor=(0.0, 0.0)) -> Fit:
        """How well ``points`` (tracking frame) fit submap ``submap`` at ``grid_pose`` (its grid frame), and
        whether that is good enough: the score reaches ``threshold`` (with ``known_ok``, or the points on known
        cells do, when at least ``MIN_KNOWN_FRACTION`` of them are); at most ``max_see_through`` of the rays from
        ``sensor`` (the laser in the tracking frame) cross walls; at least ``min_inlier_fraction`` of the points
        on known cells fall on walls; the laser stands where the map has seen (``MapIndex.seen``). The one judgement of
        a match, for a search's answer and a tracked scan."""
        grid = self.index.grids[submap]
        laser = transform.apply(grid_pose, np.asarray(sensor, dtype=np.float64).reshape(1, 2))[0]
        score, known, kscore, inliers = fit_scores(grid, points, grid_pose)
        see = see_through_fraction(grid, points, grid_pose, sensor)
        # Points on cells the map never saw say nothing; of the others, a right answer puts >= 0.92 on walls
        # (bench-dense's map images, every right answer), a scan of another building 0.5-0.87.
        on_walls = inliers / known if known > 0 else 0.0
        ro, reason = self.ro, ""
        laser_seen = self.index.seen(submap, laser)
        if not laser_seen:
            at = transform.apply(self.index.grid_to_map[submap], laser[None])[0]
            reason = (f"the laser would stand at {at[0]:.2f},{at[1]:.2f}, where the map has never seen: the robot "
                      "cannot have been there while it was mapped")
        elif score < threshold and not (known_ok and known >= MIN_KNOWN_FRACTION and kscore >= threshold):
            reason = f"refined score {score:.3f} below {threshold:g}" + (
                f" (known cells: {100 * known:.0f} % of the points, scoring {kscore:.3f})" if known_ok else "")
        elif see > ro.max_see_through:
            reason = (f"{100 * see:.0f} % of the scan's rays pass through walls of the map at the match "
                      f"(more than relocalization.max_see_through = {ro.max_see_through:g})")
        elif on_walls < ro.min_inlier_fraction:
            reason = (f"only {100 * on_walls:.0f} % of the points on known cells fall on walls (less than "
                      f"relocalization.min_inlier_fraction = {ro.min_inlier_fraction:g})")
        return Fit(not reason, reason, score, known, kscore, see, inliers, laser_seen)

    def covariance(self, submap: int, points: np.ndarray, grid_pose: np.ndarray) -> np.ndarray:
        """3x3 covariance (map frame) of a match of ``points`` in submap ``submap`` (``least_squares.covariance``,
        plus half a cell and half an angular step for the grid's quantisation)."""
        grid = self.index.grids[submap]
        cov = least_squares.covariance(grid, points, grid_pose, min_sigma_xy=0.5 * grid.resolution,
                                       min_sigma_yaw=0.5 * branch_and_bound.angular_step(points, grid.resolution))
        rot = np.eye(3)
        c, si = math.cos(self.index.grid_to_map[submap, 2]), math.sin(self.index.grid_to_map[submap, 2])
        rot[:2, :2] = [[c, -si], [si, c]]
        return rot @ cov @ rot.T

    def refine(self, fine_points, cand: Candidate, threshold: float, tm: Timings, *, known_ok: bool = False,
               sensor=(0.0, 0.0)) -> tuple[np.ndarray, Fit]:
        """(map pose, its :meth:`fit`) of ``cand`` refined by least squares; a refinement that wanders
        from the search's pose (it has slid along a corridor) is not taken, and the search's pose is judged
        'not ok' with that reason. ``sensor``: the laser's position in the tracking frame."""
        t = time.perf_counter()
        grid = self.index.grids[cand.submap]
        ls = self.ceres.match(grid, fine_points, cand.grid_pose, target_translation=cand.grid_pose[:2])
        moved = transform.relative(cand.grid_pose, ls.pose)
        consistent = (math.hypot(moved[0], moved[1]) <= self.ro.max_refinement_translation
                      and abs(moved[2]) <= self.ro.max_refinement_rotation)
        grid_pose = ls.pose if consistent else cand.grid_pose
        fit = self.fit(cand.submap, fine_points, grid_pose, threshold, known_ok=known_ok, sensor=sensor)
        if not consistent:
            fit = dataclasses.replace(fit, ok=False, reason=(
                f"refinement moved {math.hypot(moved[0], moved[1]):.2f} m / {math.degrees(abs(moved[2])):.1f} deg "
                "from the search's pose"))
        tm.add("scan scoring", t)
        return transform.compose(self.index.grid_to_map[cand.submap], grid_pose), fit

    def rival(self, best: Candidate, best_pose: np.ndarray, others: Sequence[Candidate],
               prior=None) -> tuple[Candidate, np.ndarray] | None:
        """The best of ``others`` at a different place than ``best_pose`` (> 1 m or > 10 deg away in the map).

        With a prior, a rival farther from it than the best (by more than DISTINCT_XY) is no rival:
        the prior tells them apart.
        """
        for c in others:
            if c is best:
                continue
            pose = transform.compose(self.index.grid_to_map[c.submap], c.grid_pose)
            d = transform.relative(best_pose, pose)
            if math.hypot(d[0], d[1]) > DISTINCT_XY or abs(d[2]) > DISTINCT_YAW:
                if prior is not None and (math.hypot(*(pose[:2] - prior[:2]))
                                          > math.hypot(*(best_pose[:2] - prior[:2])) + DISTINCT_XY):
                    continue
                return c, pose
        return None

    def ambiguity(self, q: Asked, cand: Candidate, pose: np.ndarray, rivals: Sequence[Candidate],
                   path: str) -> tuple[float, np.ndarray | None, str]:
        """(best distinct rival's search score / the answer's, its map pose, a note): the other submaps' bests,
        and the best pose of the answer's own search window away from the answer (``branch_and_bound.best_rival``).
        With a prior, a rival farther from it than the answer (by more than DISTINCT_XY) does not count."""
        prior = None if path == SearchPath.GLOBAL else q.prior
        best: tuple[float, np.ndarray | None, str] = (0.0, None, "")
        rival = self.rival(cand, pose, rivals, prior)
        if rival is not None and cand.score > 0:
            c, p = rival
            best = (c.score / cand.score, p, f"submap {c.submap} scores {c.score:.3f} against {cand.score:.3f} at "
                                             f"{p[0]:.2f},{p[1]:.2f},{math.degrees(p[2]):.0f}deg")
        if cand.estimate is None or cand.lin <= 0 or not (cand.levels or cand.rival_searched):
            return best
        r = cand.rival
        if not cand.rival_searched:
            stack = self.cache.get(cand.submap, self.index.grids[cand.submap])
            grid_pose = transform.compose(self.index.map_to_grid[cand.submap], pose)
            ps = branch_and_bound.peaks(
                stack, q.search_pts, cand.estimate,
                search=branch_and_bound.PeakSearch(cand.lin, cand.ang, max(q.search_floor * 0.8, 0.1), cand.levels,
                                                   count=1, distinct_xy=DISTINCT_XY, distinct_yaw=DISTINCT_YAW),
                exclude=[grid_pose, cand.grid_pose], jobs=q.jobs)
            r = ps[0] if ps else None
        if r is not None and cand.score > 0 and r.score / cand.score > best[0]:
            p = transform.compose(self.index.grid_to_map[cand.submap], r.pose)
            if prior is None or (math.hypot(*(p[:2] - prior[:2]))
                                 <= math.hypot(*(pose[:2] - prior[:2])) + DISTINCT_XY):
                best = (r.score / cand.score, p, f"{p[0]:.2f},{p[1]:.2f},{math.degrees(p[2]):.0f}deg in submap "
                                                 f"{cand.submap} scores {r.score:.3f} against {cand.score:.3f}")
        return best

    def verdict(self, q: Asked, ledger: Ledger, cand: Candidate | None, path: str, threshold: float, fallback_pose, *,
                label: str = "", rivals: Sequence[Candidate] = (), known_ok: bool = False) -> RelocalizationResult:
        """The result of ``path``: ``cand`` refined and judged (not found without one).

        The verdict: 'lost' when nothing was found, the refined pose fails the score, consistency or free-space
        checks, or it lies more than ``max_jump`` from the prior; 'ambiguous' when a different place (in another
        submap, or elsewhere in this search's window) scores ``max_ambiguity`` of the answer or more; else 'ok'.
        """
        if cand is None:
            timings, total = ledger.tm.finish()
            return RelocalizationResult(np.asarray(fallback_pose, dtype=np.float64), 0.0, path, False,
                                        ledger.considered, timings, total, None, 0.0,
                                        "; ".join(ledger.reasons + ["no match above the threshold"]), threshold)
        pose, fit = self.refine(q.fine_pts, cand, threshold, ledger.tm, known_ok=known_ok, sensor=q.mount[:2])
        ok, reason = fit.ok, fit.reason
        t = time.perf_counter()
        cov = self.covariance(cand.submap, q.fine_pts, transform.compose(self.index.map_to_grid[cand.submap], pose))
        verdict = PoseVerdict.OK if ok else PoseVerdict.LOST
        ambiguity, rival_pose, rival_note = self.ambiguity(q, cand, pose, rivals, path)
        ledger.tm.add("scan scoring", t)
        limit = self.ro.max_ambiguity if ledger.max_ambiguity is None else ledger.max_ambiguity
        if ok and ambiguity >= limit:
            verdict = PoseVerdict.AMBIGUOUS
            reason = f"ambiguous: {rival_note} (ratio {ambiguity:.3f}, at least {limit:g})"
        if ok and q.max_jump is not None and q.prior is not None and path != SearchPath.GLOBAL:
            jump = math.hypot(*(pose[:2] - q.prior[:2]))
            if jump > q.max_jump:
                verdict = PoseVerdict.LOST
                reason = f"the answer is {jump:.2f} m from the prior (more than --max-jump {q.max_jump:g} m)"
        if reason:
            ledger.reasons.append(f"{label}: {reason}" if label else reason)
        timings, total = ledger.tm.finish()
        result = RelocalizationResult(pose, fit.score, path, verdict == PoseVerdict.OK, ledger.considered, timings,
                                      total, cand.submap, cand.score, "; ".join(ledger.reasons), threshold,
                                      fit.known_fraction, fit.known_score, fit.see_through, verdict, cov, ambiguity,
                                      rival_pose, fit.inlier_fraction)
        rank: dict[str, int] = {PoseVerdict.LOST: 0, PoseVerdict.AMBIGUOUS: 1}
        failed = ledger.failed
        if verdict != PoseVerdict.OK and (failed is None or (rank[verdict], fit.score) > (rank[failed.verdict],
                                                                                          failed.score)):
            ledger.failed = result  # an ambiguous answer says more than a lost one, a better score more than a worse
        return result

    def decide(self, q: Asked, ledger: Ledger, cands: list[Candidate], path: str, threshold: float, fallback_pose,
                label: str = "") -> RelocalizationResult:
        """The best of whole-submap candidates, unless a different place scores within _AMBIGUITY_MARGIN of it."""
        if not cands:
            return self.verdict(q, ledger, None, path, threshold, fallback_pose)
        return self.verdict(q, ledger, cands[0], path, threshold, fallback_pose, label=label, rivals=cands)
