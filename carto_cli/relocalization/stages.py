"""The staged policy of a relocalization query: which search runs when, and what one stage hands the next.

A query (:class:`Query`, frozen: its points, its prior read and checked, its limits) goes through stages in order
until one answers: with a prior 'windowed' (pass 1), 'windowed-wide' (pass 2), 'fallback-filtered',
'fallback-all'; without one 'global' over the covering submaps (with a second look in a map of a few grids), then
over the others. A stage returns the query's answer, or None to hand on; what the next one needs (the windows,
the submaps searched, the candidates so far) and what every verdict records (the :class:`~carto_cli.relocalization.
judge.Ledger`) travel in the :class:`Carry`. An 'ok' answer no window around the prior confirmed is then checked by
the scans around the query (``following.check_context``). The searches are ``search.py``'s, the verdicts
``judge.py``'s.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.relocalization.following import check_context
from carto_cli.relocalization.judge import Candidate, Judge, Ledger
from carto_cli.relocalization.map_index import MapIndex
from carto_cli.relocalization.queries import ScanContext
from carto_cli.relocalization.result import PoseVerdict, RelocalizationResult, SearchPath
from carto_cli.relocalization.search import GLOBAL_BETS, Searches

__all__ = ["AMBIGUITY_MARGIN", "Carry", "Query", "Stages"]

AMBIGUITY_MARGIN = 0.03  # a search without a (trusted) prior must beat every other place by this much score
# A whole-image answer that fails its checks is searched for again with this many (Stages.second_look): on
# bench-dense/intel's image 12 / 24 / 48 bets put 3 / 4 / 5 of its 6 lost right answers right, at about 7 ms a bet
_SECOND_LOOK_BETS = 24
# ... and its answer is `ambiguous` from this ratio (best distinct rival / answer) on, not max_ambiguity: searched
# four times as widely, a scan of another building found a place at 0.937 that passed every other check
# (freiburg-079 scan 414 on aces's image), where the right answers the second look found stood at 0.71-0.82
_SECOND_LOOK_MAX_AMBIGUITY = 0.9
# The windowed passes search down to _KNOWN_SEARCH_FLOOR and accept a refined pose whose plain score misses the
# threshold when the points in known cells reach it on their own (``judge.MIN_KNOWN_FRACTION``).
# Only the first pass: in the wide one (4x the area) that let chance fits metres off through.
_KNOWN_SEARCH_FLOOR = 0.35
# Not for whole-submap searches: there it turned more queries in places the map never saw into wrong answers than
# it recovered missed ones (docs/measurements.md).


@dataclass(frozen=True, slots=True, eq=False)
class Query:
    """One query as the stages take it: its points (tracking frame), what it asks, and its prior once read."""

    mount: np.ndarray  # the laser in the tracking frame
    search_pts: np.ndarray
    fine_pts: np.ndarray
    corridor: bool
    search_floor: float  # what whole-submap searches look down to
    max_jump: float | None = None  # m: an answer farther from the prior is 'lost'
    second_look: bool = True  # a failed whole-image answer is searched for again with more bets
    jobs: int | None = None  # threads for a whole-map search's coarse stages (None: every core)
    # With a prior (see Stages.with_prior).
    prior: np.ndarray | None = None
    sxy: float = 0.0
    syaw: float = 0.0
    reliable: bool = False
    filtered: tuple[int, ...] = ()


@dataclass
class Carry(Ledger):
    """A query's ledger, and what one stage hands the next."""

    # Pass 1 -> pass 2: the windows, the submaps searched, the floor and pass 1's best.
    lin: float = 0.0
    ang: float = 0.0
    nearest: Sequence[int] = ()
    floor: float = 0.0
    windowed_best: Candidate | None = None
    # Fallback-filtered -> fallback-all, global covering -> global rest: the submaps left, the candidates so far.
    rest: list[int] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)


class Stages:
    """The staged policy over ``index``'s submaps (module doc): ``searches`` look, ``judge`` decides."""

    def __init__(self, index: MapIndex, searches: Searches, judge: Judge):
        self.index = index
        self.searches = searches
        self.judge = judge
        self.ro = judge.ro

    def query(self, mount: np.ndarray, search_pts: np.ndarray, fine_pts: np.ndarray, *, corridor: bool,
              max_jump: float | None, second_look: bool, jobs: int | None) -> Query:
        """A query without a prior (``with_prior`` adds one)."""
        ro = self.ro
        # Whole-submap searches look for anything above global_search_min_score and judge the *refined* score
        # against global_min_score: the search's score, on the coarser loop-closure points, runs ~0.07 below it
        # (bench-dense/aces: right answers at 0.57-0.59 searched, 0.65-0.74 refined; with the floor at 0.55, 13 of
        # 100 global queries on the mapped route found nothing, 6 of which a floor of 0.5 finds).
        return Query(mount, search_pts, fine_pts, corridor, min(ro.global_search_min_score, ro.global_min_score),
                     max_jump, second_look, jobs)

    def with_prior(self, q: Query, carry: Carry, prior, sigma_xy: float | None, sigma_yaw: float | None) -> Query:
        """``q`` with its prior checked, its sigmas, whether it is reliable, and the submaps near it."""
        ro = self.ro
        t = time.perf_counter()
        pose = transform.as_pose(prior).astype(np.float64).reshape(3).copy()
        self.index.check_prior(pose)
        sxy = ro.default_sigma_xy if sigma_xy is None else float(sigma_xy)
        syaw = ro.default_sigma_yaw if sigma_yaw is None else float(sigma_yaw)
        if not (sxy > 0 and syaw > 0 and math.isfinite(sxy) and math.isfinite(syaw)):
            raise CartoError(f"sigmas must be positive, got sigma_xy={sxy:g} m, sigma_yaw={syaw:g} rad")
        reliable = sxy <= ro.max_reliable_sigma_xy and syaw <= ro.max_reliable_sigma_yaw
        if q.corridor:
            filtered = self.index.filter_corridor(pose)
        else:
            filtered = self.index.filter_by_distance(pose, self.index.radius_for(sxy, reliable))
        carry.tm.add("submap preparation", t)
        return dataclasses.replace(q, prior=pose, sxy=sxy, syaw=syaw, reliable=reliable, filtered=tuple(filtered))

    def run(self, q: Query, carry: Carry, context: ScanContext | None = None) -> RelocalizationResult:
        """The answer of the first stage that gives one; ``context``: the records around the query's scan."""
        stages: tuple[Callable[[Query, Carry], RelocalizationResult | None], ...]
        if q.prior is None:
            stages = (self.global_covering, self.global_rest)
        else:
            stages = (self.windowed_pass, self.wide_pass, self.fallback_filtered, self.fallback_all)
        for stage in stages:
            result = stage(q, carry)
            if result is not None:
                if result.verdict == PoseVerdict.LOST and result.submap is None and carry.failed is not None:
                    # Nothing at all in the last stage: what an earlier one found and doubted says more.
                    failed = carry.failed
                    failed.reason = "; ".join(carry.reasons)
                    failed.timings, failed.total_ms = carry.tm.finish()
                    failed.submaps_considered = carry.considered
                    return failed
                if context is not None and result.verdict == PoseVerdict.OK and result.path != SearchPath.WINDOWED:
                    self.confirm_by_context(result, context, q.mount)
                return result
        raise AssertionError("the last stage always answers")

    def confirm_by_context(self, result: RelocalizationResult, context: ScanContext, mount: np.ndarray) -> None:
        """Judge ``result`` (ok) by the scans around it (``relocalize``'s ``context``); 'lost' on a veto."""
        ro = self.ro
        if ro.context_scans <= 0:
            return
        t = time.perf_counter()
        check = check_context(self.judge, context, result.pose, mount, ro.min_score, ro.context_scans,
                              ro.context_max_through_walls)
        result.context_checked, result.context_through_walls = check.checked, check.through_walls
        if check.vetoes(ro.context_max_through_walls):
            result.verdict, result.success = PoseVerdict.LOST, False
            why = (f"{check.through_walls} of {check.checked} scans around it, followed by odometry, see through walls "
                   f"of the map (more than relocalization.context_max_through_walls = "
                   f"{ro.context_max_through_walls}): the robot's path does not fit here")
            result.reason = f"{result.reason}; {why}" if result.reason else why
        ms = (time.perf_counter() - t) * 1e3
        result.timings["scan scoring"] = result.timings.get("scan scoring", 0.0) + ms
        result.total_ms += ms

    def _whole(self, q: Query, carry: Carry, submaps: Sequence[int], **kw) -> list[Candidate]:
        """Whole-submap searches of ``submaps`` for ``q`` that keep every place within AMBIGUITY_MARGIN of the best."""
        return self.searches.whole(q.search_pts, submaps, q.search_floor, carry.tm, jobs=q.jobs,
                                   margin=AMBIGUITY_MARGIN, **kw)

    def windowed_pass(self, q: Query, carry: Carry) -> RelocalizationResult | None:
        """'windowed' (pass 1): coarse-to-fine branch and bound in windows covering the prior's uncertainty with a
        margin, in the nearest filtered submaps; only for a reliable prior with submaps near it."""
        ro = self.ro
        if not (q.reliable and q.filtered):
            if not q.reliable:
                carry.reasons.append(f"prior unreliable (sigma_xy {q.sxy:g} m, "
                                     f"sigma_yaw {math.degrees(q.syaw):.1f} deg)")
            else:
                carry.reasons.append("no submap near the prior")
            return None
        carry.lin, carry.ang = self.searches.windows(q.sxy, q.syaw)
        carry.nearest = q.filtered[:ro.max_windowed_submaps]
        carry.considered.extend(carry.nearest)
        carry.floor = min(ro.min_score, _KNOWN_SEARCH_FLOOR)
        cand = carry.windowed_best = self.searches.windowed(q.search_pts, q.prior, carry.nearest, carry.lin,
                                                            carry.ang, carry.floor, carry.tm)
        edge = cand is not None and self.searches.at_edge(cand, carry.lin, carry.ang)
        if cand is not None and not edge:
            res = self.judge.verdict(q, carry, cand, SearchPath.WINDOWED, ro.min_score, q.prior,
                                     label="windowed search", known_ok=True)
            # Two places fit inside the prior's own window: no wider search can tell them apart.
            if res.success or res.verdict == PoseVerdict.AMBIGUOUS:
                return res
        elif cand is not None:
            carry.reasons.append(f"windowed search's best ({cand.score:.3f}) is at the edge of its window")
        else:
            carry.reasons.append(f"windowed search found nothing above {carry.floor:g}")
        return None

    def wide_pass(self, q: Query, carry: Carry) -> RelocalizationResult | None:
        """'windowed-wide' (pass 2): twice the windows, coarse to fine; only something better than pass 1 replaces
        it, and the answer is judged against the stricter whole-submap threshold."""
        ro = self.ro
        if not (q.reliable and q.filtered):
            return None
        wlin, wang = self.searches.wide_windows(carry.lin, carry.ang)
        wide = self.searches.windowed(q.search_pts, q.prior, carry.nearest, wlin, wang, carry.floor, carry.tm)
        cand = carry.windowed_best
        if wide is not None and (cand is None or wide.score > cand.score):
            cand = wide
        if cand is None:
            carry.reasons.append(f"wide windowed search found nothing above {carry.floor:g}")
            return None
        # Four times the area and twice the headings: more room for a chance fit, so the stricter
        # score of the whole-submap searches (on bench/intel, sparse, the wide pass at min_score
        # added 5 answers 0.6-1 m off, all scoring below global_min_score).
        res = self.judge.verdict(q, carry, cand, SearchPath.WINDOWED_WIDE, max(ro.min_score, ro.global_min_score),
                                 q.prior, label=f"wide windowed search (±{wlin:.1f} m / ±{math.degrees(wang):.0f} deg)")
        return res if res.success else None

    def fallback_filtered(self, q: Query, carry: Carry) -> RelocalizationResult | None:
        """'fallback-filtered': coarse-to-fine searches, any heading, within the search radius of the prior (the
        low-confidence one when the prior was reliable but wrong), in the covering submaps near it (they hold every
        scan taken there) -- bounded by that radius, not by the submaps' size."""
        ro = self.ro
        t = time.perf_counter()
        radius = (max(self.index.radius_for(q.sxy, q.reliable), ro.low_confidence_radius) if q.reliable
                  else self.index.radius_for(q.sxy, False))
        if q.corridor:
            near = list(q.filtered)
            radius = max(ro.corridor_forward_range, ro.corridor_side_range)
        else:
            near = self.index.filter_by_distance(q.prior, radius)
        cover = set(self.index.covering)
        near = [i for i in near if i in cover] or near
        rest = [i for i in self.index.order(self.index.covering, q.prior) if i not in near]
        # Only a reliable prior's fallbacks are bounded (an unreliable one starts here: this is its search). A count
        # of submaps, not a time, so that a query gives the same answer on any machine.
        limit = ro.fallback_max_submaps if q.reliable and q.filtered and ro.fallback_max_submaps > 0 else None
        if limit is not None and len(near) + len(rest) > limit:
            carry.reasons.append(f"fallback limited to the nearest {limit} submaps "
                                 "(relocalization.fallback_max_submaps)")
            near = near[:limit]
            rest = rest[:limit - len(near)]
        carry.tm.add("submap preparation", t)
        carry.rest = rest
        if not near:
            return None
        carry.considered.extend(i for i in near if i not in carry.considered)
        cands = self._whole(q, carry, near, prior=q.prior, window=radius)
        if not cands:
            carry.reasons.append(f"fallback over {len(near)} nearby submaps found nothing above {q.search_floor:g}")
            return None
        res = self.judge.decide(q, carry, cands, SearchPath.FALLBACK_FILTERED, ro.global_min_score, q.prior,
                           label=f"fallback over {len(near)} nearby submaps")
        return res if res.success else None

    def fallback_all(self, q: Query, carry: Carry) -> RelocalizationResult:
        """'fallback-all': every (covering) submap not searched yet, whole. Always answers."""
        if not carry.rest:
            return self.judge.verdict(q, carry, None, SearchPath.FALLBACK_ALL, self.ro.global_min_score, q.prior)
        carry.considered.extend(i for i in carry.rest if i not in carry.considered)
        cands = self._whole(q, carry, carry.rest)
        return self.judge.decide(q, carry, cands, SearchPath.FALLBACK_ALL, self.ro.global_min_score, q.prior)

    def global_covering(self, q: Query, carry: Carry) -> RelocalizationResult | None:
        """'global', first the covering submaps, each over the box of its nodes; the answer when no other submap
        is left, else only a success."""
        t = time.perf_counter()
        submaps = list(self.index.covering)
        carry.considered.extend(submaps)
        carry.tm.add("submap preparation", t)
        carry.candidates = self._whole(q, carry, submaps)
        carry.rest = [i for i in self.index.searchable if i not in set(submaps)]
        if not carry.rest:
            res = self.judge.decide(q, carry, carry.candidates, SearchPath.GLOBAL, self.ro.global_min_score,
                                    np.zeros(3))
            return self.second_look(q, carry, submaps, res)
        res = self.judge.decide(q, carry, carry.candidates, SearchPath.GLOBAL, self.ro.global_min_score, np.zeros(3),
                           label="covering submaps")
        return res if res.success else None

    def second_look(self, q: Query, carry: Carry, submaps: Sequence[int],
                    res: RelocalizationResult) -> RelocalizationResult:
        """A whole-map answer that failed its checks, where the search bet on a few coarse leaves in each grid (a
        map_server image): the search again with _SECOND_LOOK_BETS bets, decided anew when it finds a place scoring
        above the first answer. Costs only queries that failed (bench-dense/intel's image: 6 of 100 global queries
        right there lost with 6 bets, scoring 0.50-0.71 against 0.82-0.85 at the right place)."""
        if (res.verdict == PoseVerdict.OK or not q.second_look or not self.ro.multilevel_global_search
                or max(len(submaps), 1) >= GLOBAL_BETS):
            return res
        first = max(c.score for c in carry.candidates) if carry.candidates else 0.0
        more = self._whole(q, carry, submaps, bets=_SECOND_LOOK_BETS)
        if not more or more[0].score <= first:
            return res
        carry.reasons.append(f"second look with {_SECOND_LOOK_BETS} bets")
        # Four times the places tried raise the best wrong place's score: the answer must stand further out
        carry.max_ambiguity = min(self.ro.max_ambiguity, _SECOND_LOOK_MAX_AMBIGUITY)
        return self.judge.decide(q, carry, sorted(more + carry.candidates, key=lambda c: -c.score), SearchPath.GLOBAL,
                            self.ro.global_min_score, np.zeros(3))

    def global_rest(self, q: Query, carry: Carry) -> RelocalizationResult:
        """'global', then the other submaps: the covering ones hold every place, not always its best version (a
        place seen again after the map drifted); their candidates are pooled with the covering ones'."""
        carry.considered.extend(carry.rest)
        more = self._whole(q, carry, carry.rest)
        top = max([c.score for c in carry.candidates + more], default=0.0)
        cands = sorted((c for c in carry.candidates + more if c.score >= top - AMBIGUITY_MARGIN),
                       key=lambda c: -c.score)
        return self.judge.decide(q, carry, cands, SearchPath.GLOBAL, self.ro.global_min_score, np.zeros(3))
