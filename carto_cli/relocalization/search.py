"""The searches of relocalization: branch and bound in windows around a prior, and over whole submaps.

:class:`Searches` runs them on the precomputation stacks of ``cache`` (built on first use, kept under a memory
budget) and hands back :class:`~carto_cli.relocalization.judge.Candidate` s, unrefined and unjudged: windowed,
coarse to fine within ±lin / ±ang of a prior in each submap, each looking only for something better than the best
so far (``windowed``); or coarse to fine at any heading over the box of each submap's nodes, or within a radius of
a prior, keeping every submap's best near the best overall as rivals (``whole``). Which search runs when is the
stages' policy (``stages.py``); the window sizes and lattice levels are here.
"""
from __future__ import annotations

import math
import time

import numpy as np

from carto_cli.core import transform
from carto_cli.matching import branch_and_bound
from carto_cli.matching.stack_cache import StackCache
from carto_cli.options.schema import Relocalization
from carto_cli.relocalization.judge import DISTINCT_XY, DISTINCT_YAW, Candidate
from carto_cli.relocalization.map_index import MapIndex
from carto_cli.relocalization.result import Timings

__all__ = ["GLOBAL_BETS", "Searches", "global_levels", "window_levels"]

# Search tuning (not options: the issue-6 benchmark, bench/relocalization.py, is what they are set on).
_WINDOW_MARGIN = 1.25  # first window = window_sigmas x sigma x this (a prior at 3 sigma is inside, not on the edge)
_WIDE_FACTOR = 2.0  # second windowed pass, before any whole-submap search
_EDGE_FRACTION = 0.8  # a windowed answer farther out than this fraction of a window is checked by the wide pass
# Coarse leaves a whole-map search follows down to full resolution, shared among the submaps it searches: a map of
# many submaps gets one per submap (each submap is a bet of its own), a map_server image of one grid six (on
# bench-dense/intel's image, global queries right: 1 bet 80 % and 3 bets 92 % of 60 before the range fix of
# relocalization/auto.py; after it, 4 bets 93 % and 6 bets 95 % of 100).
GLOBAL_BETS = 6


def _clamp(v: float, lo: float, hi: float) -> float:
    return min(max(v, lo), hi)


class Searches:
    """Windowed and whole-submap searches in ``index``'s submaps on ``cache``'s stacks (module doc); ``ro``: the
    windows' bounds and whether whole-submap searches go coarse to fine (``multilevel_global_search``)."""

    def __init__(self, index: MapIndex, ro: Relocalization, cache: StackCache):
        self.index = index
        self.ro = ro
        self.cache = cache

    def windows(self, sigma_xy: float, sigma_yaw: float) -> tuple[float, float]:
        """Half-widths (m, rad) of the first windowed search: ``window_sigmas`` sigma plus a margin, clamped.

        The margin (``_WINDOW_MARGIN``, 25 %) is there because a prior ``window_sigmas`` sigma off is
        still a prior the caller promised, and the map itself is off from any outside reference by a
        few decimetres (its drift): a window of exactly 3 sigma puts such a pose on its edge.
        """
        r = self.ro
        lin = _clamp(_WINDOW_MARGIN * r.window_sigmas * sigma_xy, r.min_linear_search_window,
                     r.max_linear_search_window)
        ang = _clamp(_WINDOW_MARGIN * r.window_sigmas * sigma_yaw, r.min_angular_search_window,
                     r.max_angular_search_window)
        return lin, ang

    def wide_windows(self, lin: float, ang: float) -> tuple[float, float]:
        """The second, wider windowed pass: twice the first, at least 1 m / 20 deg, within the max windows x 2."""
        r = self.ro
        return (min(max(_WIDE_FACTOR * lin, 1.0), max(2.0 * r.max_linear_search_window, lin)),
                min(max(_WIDE_FACTOR * ang, math.radians(20.0)), math.pi))

    def windowed(self, points, prior, submaps, lin, ang, min_score, tm: Timings) -> Candidate | None:
        """Coarse to fine (``window_levels``) within ±lin / ±ang of the prior in each submap, better only."""
        best: Candidate | None = None
        for i in submaps:
            t = time.perf_counter()
            stack = self.cache.get(i, self.index.grids[i])
            estimate = transform.compose(self.index.map_to_grid[i], prior)
            t = tm.add("submap preparation", t)
            floor = min_score if best is None else max(min_score, best.score)
            r = branch_and_bound.match_multilevel(
                stack, points, estimate, linear_search_window=lin, angular_search_window=ang,
                min_score=floor, coarse_min_score=min_score, levels=window_levels(stack.depth))
            tm.add("pose search", t)
            if r.found and (best is None or r.score > best.score):
                best = Candidate(i, r.pose, r.score, estimate, lin, ang, window_levels(stack.depth))
        return best

    def whole(self, points, submaps, min_score, tm: Timings, *, prior=None, window: float | None = None,
               margin: float = 0.0, bets: int = GLOBAL_BETS,
              jobs: int | None = None) -> list[Candidate]:
        """Coarse-to-fine searches of the submaps: whole, or within ±``window`` m (any heading) of ``prior``.

        Returns every submap's best that comes within ``margin`` of the best overall (best first): with a
        margin, later submaps are searched for anything that could rival the best, not only beat it,
        which is what the ambiguity check needs.
        """
        found: list[Candidate] = []
        top = 0.0
        for i in submaps:
            t = time.perf_counter()
            stack = self.cache.get(i, self.index.grids[i])
            t = tm.add("submap preparation", t)
            floor = max(min_score, top - margin) if found else min_score
            if prior is not None and window is not None:
                estimate = transform.compose(self.index.map_to_grid[i], prior)
                lin = window
            elif self.index.node_windows[i] is not None:
                cx, cy, lin = self.index.node_windows[i]
                estimate = np.array([cx, cy, 0.0])
            else:
                estimate = branch_and_bound.full_submap_center(stack)
                nx, ny = stack.num_cells
                lin = (nx + ny) * stack.resolution
            tries = max(1, bets // max(len(submaps), 1))
            if self.ro.multilevel_global_search and tries > 1:
                # Few grids to search (a map_server image is one): several coarse bets in each, not only the best
                # coarse leaf (match_multilevel), which missed right answers scoring 0.8 on bench-dense's images;
                # the second place found is the answer's rival.
                levels = global_levels(stack.depth)
                ps = branch_and_bound.peaks(stack, points, estimate, search=branch_and_bound.PeakSearch(
                    lin, math.pi, min_score, levels, count=2, distinct_xy=DISTINCT_XY, distinct_yaw=DISTINCT_YAW,
                    tries=tries, coarse_min_score=min_score), jobs=jobs)
                tm.add("pose search", t)
                if ps and ps[0].score > floor:
                    found.append(Candidate(i, ps[0].pose, ps[0].score, estimate, lin, math.pi, levels,
                                           ps[1] if len(ps) > 1 else None, True))
                    top = max(top, ps[0].score)
                continue
            if self.ro.multilevel_global_search:
                r = branch_and_bound.match_multilevel(
                    stack, points, estimate, linear_search_window=lin, angular_search_window=math.pi,
                    min_score=floor, coarse_min_score=min_score, levels=global_levels(stack.depth))
            else:
                r = branch_and_bound.match(stack, points, estimate, linear_search_window=lin,
                                           angular_search_window=math.pi, min_score=floor)
            tm.add("pose search", t)
            if r.found:
                found.append(Candidate(i, r.pose, r.score, estimate, lin, math.pi,
                                       global_levels(stack.depth) if self.ro.multilevel_global_search else ()))
                top = max(top, r.score)
        found.sort(key=lambda c: -c.score)
        return [c for c in found if c.score >= top - margin]

    def at_edge(self, cand: Candidate, lin: float, ang: float) -> bool:
        """Whether a windowed answer lies in the outer part of its window (the optimum may be beyond it)."""
        # The window is a square along the grid's axes around the estimate, and a range of headings.
        estimate = cand.estimate
        assert estimate is not None  # windowed searches always record their centre
        dx = cand.grid_pose[0] - estimate[0]
        dy = cand.grid_pose[1] - estimate[1]
        dyaw = transform.wrap_angle(cand.grid_pose[2] - estimate[2])
        return max(abs(dx), abs(dy)) > _EDGE_FRACTION * lin or (abs(dyaw) > _EDGE_FRACTION * ang and ang < math.pi)


def global_levels(depth: int) -> tuple[tuple[float, int], ...]:
    """Stages of a whole-submap search: 16-cell lattice (0.8 m at 0.05 m) over everything, then 4, then 1.

    Measured on the loop-building map (19 submaps, ~105 points a scan), per query over all
    submaps: (8, 1) 480 ms, (16, 1) 223 ms, (16, 4, 1) 174 ms, (32, 4, 1) 154 ms; over the
    covering submaps (10) with coarse stages rejecting at the plain threshold, (16, 4, 1) 127 ms
    against 2.2 s for the exact whole-submap search, with 5 against 4 wrong answers out of 32
    (the exact search's wrong answers are ambiguous places, not search misses). The fine stage
    only has to beat the best submap so far.
    """
    if depth >= 5:
        return ((1.0, 4), (0.0, 2), (0.0, 0))
    return branch_and_bound.default_levels(depth)


def window_levels(depth: int) -> tuple[tuple[float, int], ...]:
    """Stages of a windowed search: the window on an 8-cell lattice, then 2, then 1.

    Measured on bench-dense/intel (1500 mapped scans, 34 queries, windows ±1.9 m / ±19°, 3 submaps):
    the exact branch and bound 28 ms p50, (3, 0) 5.5 ms with 1 answer off, (3, 1, 0) 5.7 ms with none,
    (2, 0) 8.4 ms with none (shared machine, absolute times noisy).
    """
    if depth >= 4:
        return ((1.0, 3), (0.0, 1), (0.0, 0))
    return branch_and_bound.default_levels(depth)
