"""Relocalization: a scan's pose in a saved map, from a prior pose or from nothing.

A :class:`Relocalizer` holds a loaded map's submaps at their global poses and
answers :meth:`Relocalizer.relocalize` queries, Cartographer-style:

1. The scan is preprocessed as local SLAM does it (crop to min/max range in the
   tracking frame through the laser mount, voxel filter, then the loop-closure
   adaptive voxel filter for the search and the finer matching one for the
   refinement).
2. Submap filtering. Around a prior, the submaps whose grid's known bounding
   box (not just its origin) lies within a radius of the prior, the radius
   growing as the prior gets less certain (high / medium / low confidence);
   with ``corridor=True``, the submaps whose box meets a rectangle along the
   prior's heading (± forward range ahead/behind, ± side range across).
3. Search. A reliable prior (sigma_xy <= 1.2 m and sigma_yaw <= 15° by
   default) gets a windowed search around it in the nearest filtered submaps
   (``max_windowed_submaps``, nearest track first), each only looking for
   something *better* than the best so far. Pass 1: windows of 3 sigma plus a
   25 % margin (so a prior off by its stated 3 sigma, plus the map's own local
   error, is inside the window, not on its edge), coarse to fine (8-, 2-,
   1-cell lattices). Pass 2, when pass 1 found nothing, failed the checks, or
   answered in the outer fifth of its window: twice the windows, coarse to
   fine, accepted at ``global_min_score``. Then fallbacks, at most ``fallback_max_submaps`` submaps for a
   reliable prior (nearest first: a count, not a time, so answers do not depend on the machine's speed):
   coarse-to-fine searches at any
   heading within the search radius of the prior (the low-confidence one)
   in the covering submaps near it ('fallback-filtered'; an unreliable prior
   starts here), then the other covering submaps whole ('fallback-all').
   No prior ('global'): the covering submaps, each searched coarse to fine
   (``match_multilevel``, unless ``multilevel_global_search`` is off) over the
   box of its own nodes plus 2 m (the robot can only be where it was while
   mapping, and the grid around that is mostly rays; a map_server image's tile,
   which has no nodes: the box of its free cells plus 2 m), then, unless that
   succeeded, the other submaps too.
4. The best candidate is refined by least squares, re-scored on the submap
   (``score_at``) and accepted (``success``) only when that score reaches the
   threshold, the refinement stayed near the search's answer (a wandering
   refinement has slid along a corridor) and at most ``max_see_through`` of the
   scan's rays pass through walls of the submap at the answer (free-space check,
   ``matching/ray_consistency.py``). Whole-submap searches (global and
   fallbacks) search down to ``global_search_min_score`` and judge the refined
   score against ``global_min_score``; they also keep every submap's best within ``_AMBIGUITY_MARGIN`` of
   the best overall as rivals.
5. The verdict (``_finish``): 'lost' when a check above fails, the laser would stand on a cell no submap knows
   (``seen``), fewer than ``min_inlier_fraction`` of the points on known cells fall on walls, or the answer is
   farther than ``max_jump`` from the prior;
   'ambiguous' when the best rival at a different place (> 1 m or > 10° away in the map frame; with a prior,
   not farther from it than the answer) -- another submap's best, or the best elsewhere in the answer's own
   search window (``branch_and_bound.peaks``) -- scores ``max_ambiguity`` of the answer or more: aliasing
   between similar rooms or corridors is reported, not guessed; else 'ok'. Every answer carries a covariance
   (``least_squares.covariance``), the ambiguity ratio and the inlier fraction (docs/localization.md).
6. Given the recording around the query (``context``), an 'ok' answer no window around the prior confirmed is
   'lost' when the robot's path there, followed by odometry, sees through walls of the map
   (``following.check_context``): one scan of another building can fit a corridor, its path cannot.

Poses are (x, y, yaw) of the tracking frame in the map frame. A submap's grid
lives in its trajectory's local frame; a map pose P is at
``local_pose ∘ inverse(global_pose) ∘ P`` in the grid (as in the constraint builder).

Each search of step 3 is one stage of :meth:`Relocalizer.relocalize`, tried in order until one
answers: with a prior 'windowed' (pass 1), 'windowed-wide' (pass 2), 'fallback-filtered',
'fallback-all'; without one 'global' over the covering submaps, then over the others.

Precomputation stacks are built on first use and kept in an LRU cache under a
memory budget (:class:`~carto_cli.matching.stack_cache.StackCache`); queries and scan
selection live in ``queries.py``, results, timings and the batch CSV in ``result.py``.
"""
from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field

import numpy as np

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.core.parallel import available_cores
from carto_cli.core.records import Scan
from carto_cli.grid.probability_grid import UNKNOWN_VALUE, VALUE_TO_PROBABILITY
from carto_cli.io.topics import TopicSelection
from carto_cli.matching import branch_and_bound, least_squares
from carto_cli.matching.precomputation import stack_bytes
from carto_cli.matching.ray_consistency import see_through_fraction
from carto_cli.matching.scoring import fit_scores
from carto_cli.matching.stack_cache import StackCache
from carto_cli.options import Options
from carto_cli.relocalization.following import check_context
from carto_cli.relocalization.queries import CONTEXT_SECONDS, Query, ScanContext, contexts_for, scans_for_queries
from carto_cli.relocalization.result import (
    BatchSummary,
    Fit,
    PoseVerdict,
    QueryResult,
    RelocalizationResult,
    SearchPath,
    Timings,
    summarize,
)
from carto_cli.sensor.range_filter import crop_scan
from carto_cli.sensor.voxel_filter import adaptive_voxel_filter, voxel_filter

__all__ = ["MIN_KNOWN_FRACTION", "Candidate", "Fit", "Relocalizer", "relocalize_many"]

# Search tuning (not options: the issue-6 benchmark, bench/relocalization.py, is what they are set on).
_WINDOW_MARGIN = 1.25  # first window = window_sigmas x sigma x this (a prior at 3 sigma is inside, not on the edge)
_WIDE_FACTOR = 2.0  # second windowed pass, before any whole-submap search
_EDGE_FRACTION = 0.8  # a windowed answer farther out than this fraction of a window is checked by the wide pass
_DISTINCT_XY = 1.0  # m: candidates farther apart than this (or _DISTINCT_YAW) are different places
_DISTINCT_YAW = math.radians(10.0)
_AMBIGUITY_MARGIN = 0.03  # a search without a (trusted) prior must beat every other place by this much score
_NODE_MARGIN = 2.0  # m: a whole-submap search covers the box of the submap's nodes plus this
# Coarse leaves a whole-map search follows down to full resolution, shared among the submaps it searches: a map of
# many submaps gets one per submap (each submap is a bet of its own), a map_server image of one grid six (on
# bench-dense/intel's image, global queries right: 1 bet 80 % and 3 bets 92 % of 60 before the range fix of
# relocalization/auto.py; after it, 4 bets 93 % and 6 bets 95 % of 100).
_GLOBAL_BETS = 6
# A whole-image answer that fails its checks is searched for again with this many (relocalizer._second_look): on
# bench-dense/intel's image 12 / 24 / 48 bets put 3 / 4 / 5 of its 6 lost right answers right, at about 7 ms a bet
_SECOND_LOOK_BETS = 24
# ... and its answer is `ambiguous` from this ratio (best distinct rival / answer) on, not max_ambiguity: searched
# four times as widely, a scan of another building found a place at 0.937 that passed every other check
# (freiburg-079 scan 414 on aces's image), where the right answers the second look found stood at 0.71-0.82
_SECOND_LOOK_MAX_AMBIGUITY = 0.9
# A scan taken where the map ends sees partly unmapped space: its points there read 0.1 whatever the pose, and
# drag the plain score of the right pose below min_score (on bench-dense, every failure with a prior was such a
# scan: docs/measurements.md).
# The windowed passes therefore search down to _KNOWN_SEARCH_FLOOR and accept a refined pose whose plain score
# misses the threshold when the points in known cells (at least MIN_KNOWN_FRACTION of them) reach it on their own.
# Only the first pass: in the wide one (4x the area) that let chance fits metres off through.
_KNOWN_SEARCH_FLOOR = 0.35
MIN_KNOWN_FRACTION = 0.5
# Not for whole-submap searches: there it turned more queries in places the map never saw into wrong answers than
# it recovered missed ones (docs/measurements.md).


@dataclass
class Candidate:
    """A search's best pose in one submap, before refinement."""

    submap: int
    grid_pose: np.ndarray  # B&B pose in the submap's grid frame
    score: float
    estimate: np.ndarray | None = None  # the search's centre in the grid frame
    lin: float = 0.0  # the search's half-windows (m, rad) around ``estimate``: where a rival is looked for
    ang: float = 0.0
    levels: tuple[tuple[float, int], ...] = ()  # the search's stages (match_multilevel), for the rival search
    rival: branch_and_bound.MatchResult | None = None  # the search's best at another place, when it looked
    rival_searched: bool = False


@dataclass
class _Search:
    """One query on its way through the stages: its points, what it has searched, and what a stage hands on."""

    mount: np.ndarray
    search_pts: np.ndarray
    fine_pts: np.ndarray
    corridor: bool
    tm: Timings
    search_floor: float  # what whole-submap searches look down to
    prior: np.ndarray | None = None
    second_look: bool = True  # a failed whole-image answer is searched for again with more bets
    max_ambiguity: float | None = None  # the rival ratio from which an answer is ambiguous (None: the option's)
    considered: list[int] = field(default_factory=list)
    reasons: list[str] = field(default_factory=list)
    # With a prior (see Relocalizer._read_prior).
    sxy: float = 0.0
    syaw: float = 0.0
    reliable: bool = False
    filtered: list[int] = field(default_factory=list)
    # Pass 1 -> pass 2: the windows, the submaps searched, the floor and pass 1's best.
    lin: float = 0.0
    ang: float = 0.0
    nearest: list[int] = field(default_factory=list)
    floor: float = 0.0
    windowed_best: Candidate | None = None
    # Fallback-filtered -> fallback-all, global covering -> global rest: the submaps left, the candidates so far.
    rest: list[int] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)
    max_jump: float | None = None  # m: an answer farther from the prior is 'lost'
    failed: RelocalizationResult | None = None  # the best answer a stage judged not ok, should no stage find one


# ----------------------------------------------------------------------------------- relocalizer


def _clamp(v: float, lo: float, hi: float) -> float:
    return min(max(v, lo), hi)


class Relocalizer:
    """Answers relocalization queries against one loaded map (see the module docstring).

    ``options`` defaults to the map's own; its ``relocalization`` section drives the search,
    ``trajectory_builder_2d`` the scan preprocessing and ``pose_graph.constraint_builder.
    ceres_scan_matcher`` the refinement. ``cache_budget_bytes`` defaults to
    ``relocalization.cache_budget_mb``. ``jobs``: threads for each coarse stage of a whole-map search
    (None: every core; ``branch_and_bound.peaks``), the same answers for any number.
    """

    def __init__(self, loaded_map, options: Options | None = None, *, cache_budget_bytes: int | None = None,
                 jobs: int | None = None):
        self.jobs = jobs
        self.map = loaded_map
        self.options = loaded_map.options if options is None else options
        self.ro = self.options.relocalization
        # the refinement is the loop-closure search's (the constraint builder's section)
        self.ceres = least_squares.CeresScanMatcher.from_options(
            self.options.pose_graph.constraint_builder.ceres_scan_matcher)
        if loaded_map.num_submaps == 0:
            raise CartoError("the map has no submaps to relocalize in", getattr(loaded_map, "path", None))
        budget = int(self.ro.cache_budget_mb * 1e6) if cache_budget_bytes is None else int(cache_budget_bytes)
        self.cache = StackCache(budget, self.ro.branch_and_bound_depth)
        self.laser_pose = (np.zeros(3) if loaded_map.laser_pose is None
                           else np.asarray(loaded_map.laser_pose, dtype=np.float64).reshape(3))

        m = loaded_map.num_submaps
        # A map saved mid-trajectory holds its newest submaps as allocated while growing (several times their
        # known area: docs/measurements.md); their precomputation stacks would be as big, and evict each other
        # from the cache on every whole-map search.
        self.grids = [_tight(s.grid) for s in loaded_map.submaps]
        # map -> grid frame of each submap: local_pose ∘ inverse(global_pose)
        self.map_to_grid = np.array([
            transform.compose(s.local_pose, transform.inverse(loaded_map.submap_global_poses[i]))
            for i, s in enumerate(loaded_map.submaps)]).reshape(m, 3)
        self.grid_to_map = transform.inverse(self.map_to_grid).reshape(m, 3)
        # Known bounding box of each grid, in its grid frame: (x0, y0, x1, y1); NaN when empty.
        self.boxes = np.full((m, 4), np.nan)
        for i, g in enumerate(self.grids):
            kb = g.known_bounds
            if kb is not None:
                lo = g.origin + np.array(kb[:2], dtype=np.float64) * g.resolution
                hi = g.origin + (np.array(kb[2:], dtype=np.float64) + 1.0) * g.resolution
                self.boxes[i] = [lo[0], lo[1], hi[0], hi[1]]
        self.searchable = [i for i in range(m) if not np.isnan(self.boxes[i, 0])]
        self._searchable_set = set(self.searchable)
        if not self.searchable:
            raise CartoError("every submap of the map is empty", getattr(loaded_map, "path", None))
        # Where the robot was while building each submap (its nodes), to order the search.
        self.node_xy = [np.asarray(loaded_map.node_global_poses, dtype=np.float64)[
            np.asarray(nodes, dtype=np.int64), :2] if len(nodes) else
            transform.apply(self.grid_to_map[i], self.map.submaps[i].local_pose[None, :2])
            for i, nodes in enumerate(loaded_map.submap_nodes)]
        self.covering = self._covering_submaps()
        # A whole-map search visits every covering submap: with stacks beyond the cache budget each such query
        # rebuilds the evicted ones (LRU order is the worst case for a cyclic scan): warn when they do not fit.
        self.stack_bytes_needed = sum(stack_bytes(self.grids[i].num_cells, self.ro.branch_and_bound_depth)
                                      for i in self.searchable)
        self.warnings: list[str] = []
        if self.stack_bytes_needed > budget:
            self.warnings.append(
                f"the map's precomputation grids need {self.stack_bytes_needed / 1e6:.0f} MB, more than "
                f"relocalization.cache_budget_mb = {budget / 1e6:g}: searches over many submaps will rebuild them "
                f"(--set relocalization.cache_budget_mb={int(self.stack_bytes_needed / 1e6) + 1} keeps them all)")
        # Where a whole-submap search looks: the box of the submap's nodes plus a margin (the robot can only be
        # where it was while mapping), as (centre x, centre y, half-width) in the grid frame; for a grid without
        # nodes (a map_server image's tiles) the box of its free cells plus the margin (the laser stands in free
        # space); None: the whole grid.
        self.node_windows: list[tuple[float, float, float] | None] = []
        for i, nodes in enumerate(loaded_map.submap_nodes):
            if len(nodes) == 0:
                self.node_windows.append(_free_window(self.grids[i]) if i in self._searchable_set else None)
                continue
            xy = transform.apply(self.map_to_grid[i], self.node_xy[i]).reshape(-1, 2)
            lo, hi = xy.min(axis=0) - _NODE_MARGIN, xy.max(axis=0) + _NODE_MARGIN
            self.node_windows.append((float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2, float(max(hi - lo)) / 2))
        self._track_xy = np.concatenate(self.node_xy).reshape(-1, 2)
        self._track_submap = np.concatenate([np.full(len(p), i) for i, p in enumerate(self.node_xy)]).astype(np.int64)

    def _covering_submaps(self) -> list[int]:
        """A small set of submaps holding every node (greedy set cover, biggest first).

        Consecutive submaps overlap by half (every scan goes into two), so about half of them
        already hold every place the robot was: whole-map searches visit only those.
        """
        sets = {i: {int(n) for n in self.map.submap_nodes[i]} for i in self.searchable}
        uncovered = set().union(*sets.values()) if sets else set()
        chosen: list[int] = []
        while uncovered:
            i = max(sets, key=lambda j: (len(sets[j] & uncovered), -j))
            gain = sets[i] & uncovered
            if not gain:
                break
            chosen.append(i)
            uncovered -= gain
        # Submaps without nodes (hand-made maps) are searched too.
        chosen += [i for i in self.searchable if not sets[i]]
        return sorted(chosen)

    # ------------------------------------------------------------------ scan preprocessing

    def preprocess(self, scan: Scan, laser_pose=None, *, search: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(search points, refinement points), both (n, 2) in the tracking frame; without ``search`` the search
        points are not filtered (an empty array: a step that only refines)."""
        tb = self.options.trajectory_builder_2d
        mount = self.laser_pose if laser_pose is None else transform.as_pose(laser_pose).reshape(3)
        data = crop_scan(scan, mount=mount, min_range=tb.min_range, max_range=tb.max_range,
                         missing_data_ray_length=tb.missing_data_ray_length)
        returns = voxel_filter(data.returns, tb.voxel_filter_size) if len(data.returns) else data.returns
        f = tb.loop_closure_adaptive_voxel_filter
        coarse = (adaptive_voxel_filter(returns, max_length=f.max_length, min_num_points=f.min_num_points,
                                        max_range=f.max_range) if search else np.zeros((0, 2)))
        f = tb.adaptive_voxel_filter
        fine = adaptive_voxel_filter(returns, max_length=f.max_length, min_num_points=f.min_num_points,
                                     max_range=f.max_range)
        return np.ascontiguousarray(coarse, dtype=np.float64), np.ascontiguousarray(fine, dtype=np.float64)

    # ------------------------------------------------------------------ submap filtering

    def box_distances(self, xy) -> np.ndarray:
        """Distance (m) from map point ``xy`` to every submap's known box; inf for empty submaps."""
        xy = np.asarray(xy, dtype=np.float64).reshape(2)
        g = self.map_to_grid
        c, s = np.cos(g[:, 2]), np.sin(g[:, 2])
        px = c * xy[0] - s * xy[1] + g[:, 0]
        py = s * xy[0] + c * xy[1] + g[:, 1]
        b = self.boxes
        with np.errstate(invalid="ignore"):
            dx = np.maximum(np.maximum(b[:, 0] - px, px - b[:, 2]), 0.0)
            dy = np.maximum(np.maximum(b[:, 1] - py, py - b[:, 3]), 0.0)
        out = np.hypot(dx, dy)
        out[np.isnan(out)] = np.inf
        return out

    def radius_for(self, sigma_xy: float, reliable: bool) -> float:
        """Search radius from the prior's confidence: high (sigma small), medium (reliable), low."""
        if not reliable:
            return self.ro.low_confidence_radius
        if sigma_xy <= self.ro.high_confidence_sigma_xy:
            return self.ro.high_confidence_radius
        return self.ro.medium_confidence_radius

    def filter_by_distance(self, prior, radius: float) -> list[int]:
        """Submaps whose known box is within ``radius`` of the prior, nearest track first."""
        d = self.box_distances(np.asarray(prior, dtype=np.float64)[:2])
        return self._order([i for i in self.searchable if d[i] <= radius], prior)

    def filter_corridor(self, prior, forward_range: float | None = None, side_range: float | None = None) -> list[int]:
        """Submaps whose known box meets the rectangle ±forward_range along the prior's heading, ±side_range across.

        Separating-axis test of two oriented rectangles (the submap box is axis-aligned in its grid frame).
        """
        fr = self.ro.corridor_forward_range if forward_range is None else float(forward_range)
        sr = self.ro.corridor_side_range if side_range is None else float(side_range)
        prior = transform.as_pose(prior).reshape(3)
        keep = []
        for i in self.searchable:
            # The corridor rectangle in the submap's grid frame.
            centre = transform.compose(self.map_to_grid[i], prior)
            c, s = math.cos(centre[2]), math.sin(centre[2])
            axes_r = np.array([[c, s], [-s, c]])  # rectangle's axes (rows)
            half_r = np.array([fr, sr])
            x0, y0, x1, y1 = self.boxes[i]
            box_c = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
            half_b = np.array([(x1 - x0) / 2, (y1 - y0) / 2])
            d = box_c - centre[:2]
            separated = False
            # Box axes (x, y).
            for k in range(2):
                proj_r = abs(axes_r[0, k]) * half_r[0] + abs(axes_r[1, k]) * half_r[1]
                if abs(d[k]) > half_b[k] + proj_r:
                    separated = True
                    break
            if not separated:
                for k in range(2):
                    a = axes_r[k]
                    proj_b = abs(a[0]) * half_b[0] + abs(a[1]) * half_b[1]
                    if abs(d @ a) > half_r[k] + proj_b:
                        separated = True
                        break
            if not separated:
                keep.append(i)
        return self._order(keep, prior)

    def track_distances(self, xy) -> np.ndarray:
        """Distance (m) from map point ``xy`` to the nearest node of every submap (where its scans were taken)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(2)
        d = np.hypot(self._track_xy[:, 0] - xy[0], self._track_xy[:, 1] - xy[1])
        out = np.full(self.map.num_submaps, np.inf)
        np.minimum.at(out, self._track_submap, d)
        return out

    def nearest_submap(self, xy) -> int:
        """The searchable submap to match a pose at ``xy`` against: the one whose scans were taken nearest it; in
        a map without nodes (a map_server image's tiles) the one whose known box holds it most centrally."""
        xy = np.asarray(xy, dtype=np.float64).reshape(2)
        if len(self._track_xy):
            d = self.track_distances(xy)
            return min(self.searchable, key=lambda i: (d[i], i))
        box = self.box_distances(xy)
        centre = np.array([transform.apply(self.grid_to_map[i], np.array([[(b[0] + b[2]) / 2, (b[1] + b[3]) / 2]]))[0]
                           if not np.isnan(b[0]) else (np.inf, np.inf) for i, b in enumerate(self.boxes)])
        off = np.hypot(centre[:, 0] - xy[0], centre[:, 1] - xy[1])
        return min(self.searchable, key=lambda i: (box[i], off[i], i))

    def _order(self, indices: Sequence[int], prior) -> list[int]:
        """Nearest first, by the distance from the prior to the submap's nodes."""
        key = self.track_distances(np.asarray(prior, dtype=np.float64)[:2])
        return sorted(indices, key=lambda i: (key[i], i))

    def check_prior(self, prior) -> float:
        """Distance to the nearest submap; CartoError beyond ``max_prior_distance``."""
        prior = transform.as_pose(prior).reshape(3)
        if not np.all(np.isfinite(prior)):
            raise CartoError(f"initial pose must be finite numbers, got {prior[0]:g},{prior[1]:g},{prior[2]:g}")
        d = float(np.min(self.box_distances(prior[:2])))
        if d > self.ro.max_prior_distance:
            raise CartoError(f"initial pose {prior[0]:g},{prior[1]:g} is {d:.1f} m from the nearest submap "
                             f"(more than relocalization.max_prior_distance = {self.ro.max_prior_distance:g} m)",
                             getattr(self.map, "path", None))
        return d

    # ------------------------------------------------------------------ searches

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

    def _windowed(self, points, prior, submaps, lin, ang, min_score, tm: Timings) -> Candidate | None:
        """Coarse to fine (``_window_levels``) within ±lin / ±ang of the prior in each submap, better only."""
        best: Candidate | None = None
        for i in submaps:
            t = time.perf_counter()
            stack = self.cache.get(i, self.grids[i])
            estimate = transform.compose(self.map_to_grid[i], prior)
            t = tm.add("submap preparation", t)
            floor = min_score if best is None else max(min_score, best.score)
            r = branch_and_bound.match_multilevel(
                stack, points, estimate, linear_search_window=lin, angular_search_window=ang,
                min_score=floor, coarse_min_score=min_score, levels=_window_levels(stack.depth))
            tm.add("pose search", t)
            if r.found and (best is None or r.score > best.score):
                best = Candidate(i, r.pose, r.score, estimate, lin, ang, _window_levels(stack.depth))
        return best

    def _whole(self, points, submaps, min_score, tm: Timings, *, prior=None, window: float | None = None,
               margin: float = 0.0, bets: int = _GLOBAL_BETS) -> list[Candidate]:
        """Coarse-to-fine searches of the submaps: whole, or within ±``window`` m (any heading) of ``prior``.

        Returns every submap's best that comes within ``margin`` of the best overall (best first): with a
        margin, later submaps are searched for anything that could rival the best, not only beat it,
        which is what the ambiguity check needs.
        """
        found: list[Candidate] = []
        top = 0.0
        for i in submaps:
            t = time.perf_counter()
            stack = self.cache.get(i, self.grids[i])
            t = tm.add("submap preparation", t)
            floor = max(min_score, top - margin) if found else min_score
            if prior is not None and window is not None:
                estimate = transform.compose(self.map_to_grid[i], prior)
                lin = window
            elif self.node_windows[i] is not None:
                cx, cy, lin = self.node_windows[i]
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
                levels = _global_levels(stack.depth)
                ps = branch_and_bound.peaks(stack, points, estimate, linear_search_window=lin,
                                            angular_search_window=math.pi, min_score=min_score, levels=levels,
                                            count=2, distinct_xy=_DISTINCT_XY, distinct_yaw=_DISTINCT_YAW,
                                            tries=tries, coarse_min_score=min_score, jobs=self.jobs)
                tm.add("pose search", t)
                if ps and ps[0].score > floor:
                    found.append(Candidate(i, ps[0].pose, ps[0].score, estimate, lin, math.pi, levels,
                                           ps[1] if len(ps) > 1 else None, True))
                    top = max(top, ps[0].score)
                continue
            if self.ro.multilevel_global_search:
                r = branch_and_bound.match_multilevel(
                    stack, points, estimate, linear_search_window=lin, angular_search_window=math.pi,
                    min_score=floor, coarse_min_score=min_score, levels=_global_levels(stack.depth))
            else:
                r = branch_and_bound.match(stack, points, estimate, linear_search_window=lin,
                                           angular_search_window=math.pi, min_score=floor)
            tm.add("pose search", t)
            if r.found:
                found.append(Candidate(i, r.pose, r.score, estimate, lin, math.pi,
                                       _global_levels(stack.depth) if self.ro.multilevel_global_search else ()))
                top = max(top, r.score)
        found.sort(key=lambda c: -c.score)
        return [c for c in found if c.score >= top - margin]

    def _rival(self, best: Candidate, best_pose: np.ndarray, others: Sequence[Candidate],
               prior=None) -> tuple[Candidate, np.ndarray] | None:
        """The best of ``others`` at a different place than ``best_pose`` (> 1 m or > 10 deg away in the map).

        With a prior, a rival farther from it than the best (by more than _DISTINCT_XY) is no rival:
        the prior tells them apart.
        """
        for c in others:
            if c is best:
                continue
            pose = transform.compose(self.grid_to_map[c.submap], c.grid_pose)
            d = transform.relative(best_pose, pose)
            if math.hypot(d[0], d[1]) > _DISTINCT_XY or abs(d[2]) > _DISTINCT_YAW:
                if prior is not None and (math.hypot(*(pose[:2] - prior[:2]))
                                          > math.hypot(*(best_pose[:2] - prior[:2])) + _DISTINCT_XY):
                    continue
                return c, pose
        return None

    def judge(self, submap: int, points: np.ndarray, grid_pose: np.ndarray, threshold: float, *,
              known_ok: bool = False, sensor=(0.0, 0.0)) -> Fit:
        """How well ``points`` (tracking frame) fit submap ``submap`` at ``grid_pose`` (its grid frame), and
        whether that is good enough: the score reaches ``threshold`` (with ``known_ok``, or the points on known
        cells do, when at least ``MIN_KNOWN_FRACTION`` of them are); at most ``max_see_through`` of the rays from
        ``sensor`` (the laser in the tracking frame) cross walls; at least ``min_inlier_fraction`` of the points
        on known cells fall on walls; the laser stands where the map has seen (:meth:`seen`). The one judgement of
        a match, for a search's answer and a tracked scan."""
        grid = self.grids[submap]
        laser = transform.apply(grid_pose, np.asarray(sensor, dtype=np.float64).reshape(1, 2))[0]
        score, known, kscore, inliers = fit_scores(grid, points, grid_pose)
        see = see_through_fraction(grid, points, grid_pose, sensor)
        # Points on cells the map never saw say nothing; of the others, a right answer puts >= 0.92 on walls
        # (bench-dense's map images, every right answer), a scan of another building 0.5-0.87.
        on_walls = inliers / known if known > 0 else 0.0
        ro, reason = self.ro, ""
        laser_seen = self.seen(submap, laser)
        if not laser_seen:
            at = transform.apply(self.grid_to_map[submap], laser[None])[0]
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

    def seen(self, submap: int, xy) -> bool:
        """Whether a cell of the map knows grid point ``xy`` of submap ``submap`` (that submap's, else any other's).

        A scan's rays all start at the laser, so the map knows every place the robot stood while mapping, and a
        map_server image marks where a robot can stand as free. A match that puts the laser on an unknown cell has
        fitted the scan's walls to walls of the map from a place outside it: on bench-dense's map images, a scan of
        another building fitted to the lip of the map's outline (docs/localization.md); no right answer of the
        building's own scans stood on an unknown cell."""
        xy = np.asarray(xy, dtype=np.float64).reshape(1, 2)
        if self.grids[submap].is_known(self.grids[submap].cell_index(xy))[0]:
            return True
        # The point in every submap's grid frame at once; only those whose known box holds it are looked up (a
        # tracked robot at the map's edge asks this every scan, of maps with hundreds of submaps).
        x, y = transform.apply(self.grid_to_map[submap], xy)[0]
        m = self.map_to_grid
        c, s = np.cos(m[:, 2]), np.sin(m[:, 2])
        gx, gy = c * x - s * y + m[:, 0], s * x + c * y + m[:, 1]
        b = self.boxes  # NaN for empty submaps: every comparison false
        inside = (b[:, 0] <= gx) & (gx <= b[:, 2]) & (b[:, 1] <= gy) & (gy <= b[:, 3])
        inside[submap] = False
        for i in np.flatnonzero(inside):
            g = self.grids[i]
            if g.is_known(g.cell_index(np.array([[gx[i], gy[i]]])))[0]:
                return True
        return False

    def covariance(self, submap: int, points: np.ndarray, grid_pose: np.ndarray) -> np.ndarray:
        """3x3 covariance (map frame) of a match of ``points`` in submap ``submap`` (``least_squares.covariance``,
        plus half a cell and half an angular step for the grid's quantisation)."""
        grid = self.grids[submap]
        cov = least_squares.covariance(grid, points, grid_pose, min_sigma_xy=0.5 * grid.resolution,
                                       min_sigma_yaw=0.5 * branch_and_bound.angular_step(points, grid.resolution))
        rot = np.eye(3)
        c, si = math.cos(self.grid_to_map[submap, 2]), math.sin(self.grid_to_map[submap, 2])
        rot[:2, :2] = [[c, -si], [si, c]]
        return rot @ cov @ rot.T

    def refine(self, fine_points, cand: Candidate, threshold: float, tm: Timings, *, known_ok: bool = False,
               sensor=(0.0, 0.0)) -> tuple[np.ndarray, Fit]:
        """(map pose, its :meth:`judge`-ment) of ``cand`` refined by least squares; a refinement that wanders
        from the search's pose (it has slid along a corridor) is not taken, and the search's pose is judged
        'not ok' with that reason. ``sensor``: the laser's position in the tracking frame."""
        t = time.perf_counter()
        grid = self.grids[cand.submap]
        ls = self.ceres.match(grid, fine_points, cand.grid_pose, target_translation=cand.grid_pose[:2])
        moved = transform.relative(cand.grid_pose, ls.pose)
        consistent = (math.hypot(moved[0], moved[1]) <= self.ro.max_refinement_translation
                      and abs(moved[2]) <= self.ro.max_refinement_rotation)
        grid_pose = ls.pose if consistent else cand.grid_pose
        fit = self.judge(cand.submap, fine_points, grid_pose, threshold, known_ok=known_ok, sensor=sensor)
        if not consistent:
            fit = dataclasses.replace(fit, ok=False, reason=(
                f"refinement moved {math.hypot(moved[0], moved[1]):.2f} m / {math.degrees(abs(moved[2])):.1f} deg "
                "from the search's pose"))
        tm.add("scan scoring", t)
        return transform.compose(self.grid_to_map[cand.submap], grid_pose), fit

    # ------------------------------------------------------------------ the query

    def relocalize(self, scan: Scan, prior=None, *, sigma_xy: float | None = None, sigma_yaw: float | None = None,
                   corridor: bool = False, laser_pose=None, max_jump: float | None = None,
                   second_look: bool = True, context: ScanContext | None = None) -> RelocalizationResult:
        """Pose of ``scan`` in the map; ``prior`` (x, y, yaw) in the map frame or None for a global search.

        ``context``: the recording's records around ``scan``. An answer judged 'ok' that no window around the prior
        confirmed (a fallback's, a whole-map search's) is then 'lost' when more than ``context_max_through_walls``
        of up to ``context_scans`` neighbours each way, followed from it by odometry, see through walls of the map
        (``following.check_context``): a scan of another building can fit a corridor here, its path cannot.

        ``second_look``: a global answer in a map of a few grids (a map_server image) that fails its checks is
        searched for again with _SECOND_LOOK_BETS coarse bets (a tracker, with the next scan to try, turns it off).

        ``max_jump`` (m): an answer farther than this from the prior is 'lost' (a confident jump to a similar
        place elsewhere is what a robot must not take).

        ``sigma_xy`` (m) / ``sigma_yaw`` (rad) default to ``relocalization.default_sigma_*``;
        ``laser_pose`` (laser in the tracking frame) defaults to the one stored in the map.
        Raises CartoError for a prior farther than ``max_prior_distance`` from every submap.
        """
        tm = Timings()
        ro = self.ro
        mount = self.laser_pose if laser_pose is None else transform.as_pose(laser_pose).reshape(3)
        search_pts, fine_pts = self.preprocess(scan, mount)
        if len(search_pts) == 0:
            tb = self.options.trajectory_builder_2d
            raise CartoError(f"the scan at t={scan.time:.3f} has no returns within "
                             f"{tb.min_range:g}..{tb.max_range:g} m")
        # Whole-submap searches look for anything above global_search_min_score and judge the *refined* score
        # against global_min_score: the search's score, on the coarser loop-closure points, runs ~0.07 below it
        # (bench-dense/aces: right answers at 0.57-0.59 searched, 0.65-0.74 refined; with the floor at 0.55, 13 of
        # 100 global queries on the mapped route found nothing, 6 of which a floor of 0.5 finds).
        s = _Search(mount, search_pts, fine_pts, corridor, tm,
                    search_floor=min(ro.global_search_min_score, ro.global_min_score), max_jump=max_jump,
                    second_look=second_look)
        stages: tuple[Callable[[_Search], RelocalizationResult | None], ...]
        if prior is None:
            stages = (self._global_covering, self._global_rest)
        else:
            self._read_prior(s, prior, sigma_xy, sigma_yaw)
            stages = (self._windowed_pass, self._wide_pass, self._fallback_filtered, self._fallback_all)
        for stage in stages:
            result = stage(s)
            if result is not None:
                if result.verdict == PoseVerdict.LOST and result.submap is None and s.failed is not None:
                    # Nothing at all in the last stage: what an earlier one found and doubted says more.
                    failed = s.failed
                    failed.reason = "; ".join(s.reasons)
                    failed.timings, failed.total_ms = s.tm.finish()
                    failed.submaps_considered = s.considered
                    return failed
                if context is not None and result.verdict == PoseVerdict.OK and result.path != SearchPath.WINDOWED:
                    self._check_context(result, context, mount)
                return result
        raise AssertionError("the last stage always answers")

    def _check_context(self, result: RelocalizationResult, context: ScanContext, mount: np.ndarray) -> None:
        """Judge ``result`` (ok) by the scans around it (``relocalize``'s ``context``); 'lost' on a veto."""
        ro = self.ro
        if ro.context_scans <= 0:
            return
        t = time.perf_counter()
        check = check_context(self, context, result.pose, mount, ro.min_score, ro.context_scans,
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

    def _read_prior(self, s: _Search, prior, sigma_xy: float | None, sigma_yaw: float | None) -> None:
        """Check the prior and its sigmas, judge it reliable or not, and choose the submaps near it."""
        ro = self.ro
        t = time.perf_counter()
        s.prior = transform.as_pose(prior).astype(np.float64).reshape(3).copy()
        self.check_prior(s.prior)
        sxy = ro.default_sigma_xy if sigma_xy is None else float(sigma_xy)
        syaw = ro.default_sigma_yaw if sigma_yaw is None else float(sigma_yaw)
        if not (sxy > 0 and syaw > 0 and math.isfinite(sxy) and math.isfinite(syaw)):
            raise CartoError(f"sigmas must be positive, got sigma_xy={sxy:g} m, sigma_yaw={syaw:g} rad")
        s.sxy, s.syaw = sxy, syaw
        s.reliable = sxy <= ro.max_reliable_sigma_xy and syaw <= ro.max_reliable_sigma_yaw
        if s.corridor:
            s.filtered = self.filter_corridor(s.prior)
        else:
            s.filtered = self.filter_by_distance(s.prior, self.radius_for(sxy, s.reliable))
        s.tm.add("submap preparation", t)

    # Each stage returns the query's answer, or None to hand on to the next one.

    def _windowed_pass(self, s: _Search) -> RelocalizationResult | None:
        """'windowed' (pass 1): coarse-to-fine branch and bound in windows covering the prior's uncertainty with a
        margin, in the nearest filtered submaps; only for a reliable prior with submaps near it."""
        ro = self.ro
        if not (s.reliable and s.filtered):
            if not s.reliable:
                s.reasons.append(f"prior unreliable (sigma_xy {s.sxy:g} m, sigma_yaw {math.degrees(s.syaw):.1f} deg)")
            else:
                s.reasons.append("no submap near the prior")
            return None
        s.lin, s.ang = self.windows(s.sxy, s.syaw)
        s.nearest = s.filtered[:ro.max_windowed_submaps]
        s.considered.extend(s.nearest)
        s.floor = min(ro.min_score, _KNOWN_SEARCH_FLOOR)
        cand = s.windowed_best = self._windowed(s.search_pts, s.prior, s.nearest, s.lin, s.ang, s.floor, s.tm)
        edge = cand is not None and self._at_edge(cand, s.lin, s.ang)
        if cand is not None and not edge:
            res = self._finish(s, cand, SearchPath.WINDOWED, ro.min_score, s.prior, label="windowed search",
                               known_ok=True)
            # Two places fit inside the prior's own window: no wider search can tell them apart.
            if res.success or res.verdict == PoseVerdict.AMBIGUOUS:
                return res
        elif cand is not None:
            s.reasons.append(f"windowed search's best ({cand.score:.3f}) is at the edge of its window")
        else:
            s.reasons.append(f"windowed search found nothing above {s.floor:g}")
        return None

    def _wide_pass(self, s: _Search) -> RelocalizationResult | None:
        """'windowed-wide' (pass 2): twice the windows, coarse to fine; only something better than pass 1 replaces
        it, and the answer is judged against the stricter whole-submap threshold."""
        ro = self.ro
        if not (s.reliable and s.filtered):
            return None
        wlin, wang = self.wide_windows(s.lin, s.ang)
        wide = self._windowed(s.search_pts, s.prior, s.nearest, wlin, wang, s.floor, s.tm)
        cand = s.windowed_best
        if wide is not None and (cand is None or wide.score > cand.score):
            cand = wide
        if cand is None:
            s.reasons.append(f"wide windowed search found nothing above {s.floor:g}")
            return None
        # Four times the area and twice the headings: more room for a chance fit, so the stricter
        # score of the whole-submap searches (on bench/intel, sparse, the wide pass at min_score
        # added 5 answers 0.6-1 m off, all scoring below global_min_score).
        res = self._finish(s, cand, SearchPath.WINDOWED_WIDE, max(ro.min_score, ro.global_min_score), s.prior,
                           label=f"wide windowed search (±{wlin:.1f} m / ±{math.degrees(wang):.0f} deg)")
        return res if res.success else None

    def _fallback_filtered(self, s: _Search) -> RelocalizationResult | None:
        """'fallback-filtered': coarse-to-fine searches, any heading, within the search radius of the prior (the
        low-confidence one when the prior was reliable but wrong), in the covering submaps near it (they hold every
        scan taken there) -- bounded by that radius, not by the submaps' size."""
        ro = self.ro
        t = time.perf_counter()
        radius = (max(self.radius_for(s.sxy, s.reliable), ro.low_confidence_radius) if s.reliable
                  else self.radius_for(s.sxy, False))
        if s.corridor:
            near = s.filtered
            radius = max(ro.corridor_forward_range, ro.corridor_side_range)
        else:
            near = self.filter_by_distance(s.prior, radius)
        cover = set(self.covering)
        near = [i for i in near if i in cover] or near
        rest = [i for i in self._order(self.covering, s.prior) if i not in near]
        # Only a reliable prior's fallbacks are bounded (an unreliable one starts here: this is its search). A count
        # of submaps, not a time, so that a query gives the same answer on any machine.
        limit = ro.fallback_max_submaps if s.reliable and s.filtered and ro.fallback_max_submaps > 0 else None
        if limit is not None and len(near) + len(rest) > limit:
            s.reasons.append(f"fallback limited to the nearest {limit} submaps (relocalization.fallback_max_submaps)")
            near = near[:limit]
            rest = rest[:limit - len(near)]
        s.tm.add("submap preparation", t)
        s.rest = rest
        if not near:
            return None
        s.considered.extend(i for i in near if i not in s.considered)
        cands = self._whole(s.search_pts, near, s.search_floor, s.tm, prior=s.prior, window=radius,
                            margin=_AMBIGUITY_MARGIN)
        if not cands:
            s.reasons.append(f"fallback over {len(near)} nearby submaps found nothing above {s.search_floor:g}")
            return None
        res = self._decide(s, cands, SearchPath.FALLBACK_FILTERED, ro.global_min_score, s.prior,
                           label=f"fallback over {len(near)} nearby submaps")
        return res if res.success else None

    def _fallback_all(self, s: _Search) -> RelocalizationResult:
        """'fallback-all': every (covering) submap not searched yet, whole. Always answers."""
        if not s.rest:
            return self._finish(s, None, SearchPath.FALLBACK_ALL, self.ro.global_min_score, s.prior)
        s.considered.extend(i for i in s.rest if i not in s.considered)
        cands = self._whole(s.search_pts, s.rest, s.search_floor, s.tm, margin=_AMBIGUITY_MARGIN)
        return self._decide(s, cands, SearchPath.FALLBACK_ALL, self.ro.global_min_score, s.prior)

    def _global_covering(self, s: _Search) -> RelocalizationResult | None:
        """'global', first the covering submaps, each over the box of its nodes; the answer when no other submap
        is left, else only a success."""
        t = time.perf_counter()
        submaps = list(self.covering)
        s.considered.extend(submaps)
        s.tm.add("submap preparation", t)
        s.candidates = self._whole(s.search_pts, submaps, s.search_floor, s.tm, margin=_AMBIGUITY_MARGIN)
        s.rest = [i for i in self.searchable if i not in set(submaps)]
        if not s.rest:
            res = self._decide(s, s.candidates, SearchPath.GLOBAL, self.ro.global_min_score, np.zeros(3))
            return self._second_look(s, submaps, res)
        res = self._decide(s, s.candidates, SearchPath.GLOBAL, self.ro.global_min_score, np.zeros(3),
                           label="covering submaps")
        return res if res.success else None

    def _second_look(self, s: _Search, submaps: Sequence[int], res: RelocalizationResult) -> RelocalizationResult:
        """A whole-map answer that failed its checks, where the search bet on a few coarse leaves in each grid (a
        map_server image): the search again with _SECOND_LOOK_BETS bets, decided anew when it finds a place scoring
        above the first answer. Costs only queries that failed (bench-dense/intel's image: 6 of 100 global queries
        right there lost with 6 bets, scoring 0.50-0.71 against 0.82-0.85 at the right place)."""
        if (res.verdict == PoseVerdict.OK or not s.second_look or not self.ro.multilevel_global_search
                or max(len(submaps), 1) >= _GLOBAL_BETS):
            return res
        first = max(c.score for c in s.candidates) if s.candidates else 0.0
        more = self._whole(s.search_pts, submaps, s.search_floor, s.tm, margin=_AMBIGUITY_MARGIN,
                           bets=_SECOND_LOOK_BETS)
        if not more or more[0].score <= first:
            return res
        s.reasons.append(f"second look with {_SECOND_LOOK_BETS} bets")
        # Four times the places tried raise the best wrong place's score: the answer must stand further out
        s.max_ambiguity = min(self.ro.max_ambiguity, _SECOND_LOOK_MAX_AMBIGUITY)
        return self._decide(s, sorted(more + s.candidates, key=lambda c: -c.score), SearchPath.GLOBAL,
                            self.ro.global_min_score, np.zeros(3))

    def _global_rest(self, s: _Search) -> RelocalizationResult:
        """'global', then the other submaps: the covering ones hold every place, not always its best version (a
        place seen again after the map drifted); their candidates are pooled with the covering ones'."""
        s.considered.extend(s.rest)
        more = self._whole(s.search_pts, s.rest, s.search_floor, s.tm, margin=_AMBIGUITY_MARGIN)
        top = max([c.score for c in s.candidates + more], default=0.0)
        cands = sorted((c for c in s.candidates + more if c.score >= top - _AMBIGUITY_MARGIN), key=lambda c: -c.score)
        return self._decide(s, cands, SearchPath.GLOBAL, self.ro.global_min_score, np.zeros(3))

    def _finish(self, s: _Search, cand: Candidate | None, path: str, threshold: float, fallback_pose, *,
                label: str = "", rivals: Sequence[Candidate] = (), known_ok: bool = False) -> RelocalizationResult:
        """The result of ``path``: ``cand`` refined and judged (not found without one).

        The verdict: 'lost' when nothing was found, the refined pose fails the score, consistency or free-space
        checks, or it lies more than ``max_jump`` from the prior; 'ambiguous' when a different place (in another
        submap, or elsewhere in this search's window) scores ``max_ambiguity`` of the answer or more; else 'ok'.
        """
        if cand is None:
            timings, total = s.tm.finish()
            return RelocalizationResult(np.asarray(fallback_pose, dtype=np.float64), 0.0, path, False,
                                        s.considered, timings, total, None, 0.0,
                                        "; ".join(s.reasons + ["no match above the threshold"]), threshold)
        pose, fit = self.refine(s.fine_pts, cand, threshold, s.tm, known_ok=known_ok, sensor=s.mount[:2])
        ok, reason = fit.ok, fit.reason
        t = time.perf_counter()
        cov = self.covariance(cand.submap, s.fine_pts, transform.compose(self.map_to_grid[cand.submap], pose))
        verdict = PoseVerdict.OK if ok else PoseVerdict.LOST
        ambiguity, rival_pose, rival_note = self._ambiguity(s, cand, pose, rivals, path)
        s.tm.add("scan scoring", t)
        limit = self.ro.max_ambiguity if s.max_ambiguity is None else s.max_ambiguity
        if ok and ambiguity >= limit:
            verdict = PoseVerdict.AMBIGUOUS
            reason = f"ambiguous: {rival_note} (ratio {ambiguity:.3f}, at least {limit:g})"
        if ok and s.max_jump is not None and s.prior is not None and path != SearchPath.GLOBAL:
            jump = math.hypot(*(pose[:2] - s.prior[:2]))
            if jump > s.max_jump:
                verdict = PoseVerdict.LOST
                reason = f"the answer is {jump:.2f} m from the prior (more than --max-jump {s.max_jump:g} m)"
        if reason:
            s.reasons.append(f"{label}: {reason}" if label else reason)
        timings, total = s.tm.finish()
        result = RelocalizationResult(pose, fit.score, path, verdict == PoseVerdict.OK, s.considered, timings, total,
                                      cand.submap, cand.score, "; ".join(s.reasons), threshold, fit.known_fraction,
                                      fit.known_score, fit.see_through, verdict, cov, ambiguity, rival_pose,
                                      fit.inlier_fraction)
        rank: dict[str, int] = {PoseVerdict.LOST: 0, PoseVerdict.AMBIGUOUS: 1}
        if verdict != PoseVerdict.OK and (s.failed is None or (rank[verdict], fit.score) > (rank[s.failed.verdict],
                                                                                  s.failed.score)):
            s.failed = result  # an ambiguous answer says more than a lost one, a better score more than a worse
        return result

    def _ambiguity(self, s: _Search, cand: Candidate, pose: np.ndarray, rivals: Sequence[Candidate],
                   path: str) -> tuple[float, np.ndarray | None, str]:
        """(best distinct rival's search score / the answer's, its map pose, a note): the other submaps' bests,
        and the best pose of the answer's own search window away from the answer (``branch_and_bound.best_rival``).
        With a prior, a rival farther from it than the answer (by more than _DISTINCT_XY) does not count."""
        prior = None if path == SearchPath.GLOBAL else s.prior
        best: tuple[float, np.ndarray | None, str] = (0.0, None, "")
        rival = self._rival(cand, pose, rivals, prior)
        if rival is not None and cand.score > 0:
            c, p = rival
            best = (c.score / cand.score, p, f"submap {c.submap} scores {c.score:.3f} against {cand.score:.3f} at "
                                             f"{p[0]:.2f},{p[1]:.2f},{math.degrees(p[2]):.0f}deg")
        if cand.estimate is None or cand.lin <= 0 or not (cand.levels or cand.rival_searched):
            return best
        r = cand.rival
        if not cand.rival_searched:
            stack = self.cache.get(cand.submap, self.grids[cand.submap])
            grid_pose = transform.compose(self.map_to_grid[cand.submap], pose)
            ps = branch_and_bound.peaks(
                stack, s.search_pts, cand.estimate, linear_search_window=cand.lin, angular_search_window=cand.ang,
                min_score=max(s.search_floor * 0.8, 0.1), levels=cand.levels, count=1, distinct_xy=_DISTINCT_XY,
                distinct_yaw=_DISTINCT_YAW, exclude=[grid_pose, cand.grid_pose], jobs=self.jobs)
            r = ps[0] if ps else None
        if r is not None and cand.score > 0 and r.score / cand.score > best[0]:
            p = transform.compose(self.grid_to_map[cand.submap], r.pose)
            if prior is None or (math.hypot(*(p[:2] - prior[:2]))
                                 <= math.hypot(*(pose[:2] - prior[:2])) + _DISTINCT_XY):
                best = (r.score / cand.score, p, f"{p[0]:.2f},{p[1]:.2f},{math.degrees(p[2]):.0f}deg in submap "
                                                 f"{cand.submap} scores {r.score:.3f} against {cand.score:.3f}")
        return best

    def _decide(self, s: _Search, cands: list[Candidate], path: str, threshold: float, fallback_pose,
                label: str = "") -> RelocalizationResult:
        """The best of whole-submap candidates, unless a different place scores within _AMBIGUITY_MARGIN of it."""
        if not cands:
            return self._finish(s, None, path, threshold, fallback_pose)
        return self._finish(s, cands[0], path, threshold, fallback_pose, label=label, rivals=cands)

    def _at_edge(self, cand: Candidate, lin: float, ang: float) -> bool:
        """Whether a windowed answer lies in the outer part of its window (the optimum may be beyond it)."""
        # The window is a square along the grid's axes around the estimate, and a range of headings.
        estimate = cand.estimate
        assert estimate is not None  # windowed searches always record their centre
        dx = cand.grid_pose[0] - estimate[0]
        dy = cand.grid_pose[1] - estimate[1]
        dyaw = transform.wrap_angle(cand.grid_pose[2] - estimate[2])
        return max(abs(dx), abs(dy)) > _EDGE_FRACTION * lin or (abs(dyaw) > _EDGE_FRACTION * ang and ang < math.pi)

    # ------------------------------------------------------------------ batch

    def relocalize_many(self, recording, queries: Sequence[Query], *, scan_topic: str | None = None,
                        laser_pose=None, corridor: bool = False, max_time_offset: float = 1.0,
                        on_query=None, max_jump: float | None = None) -> tuple[list[QueryResult], BatchSummary]:
        return relocalize_many(self, recording, queries, scan_topic=scan_topic, laser_pose=laser_pose,
                               corridor=corridor, max_time_offset=max_time_offset, on_query=on_query,
                               max_jump=max_jump)

    def stats(self) -> dict:
        return {"submaps": self.map.num_submaps, "searchable": len(self.searchable), "cache": self.cache.stats()}


def _tight(grid):
    """The grid cropped to its known cells, unless it already is (no copy then)."""
    b = grid.known_bounds
    if b is None or (b[0] == 0 and b[1] == 0 and b[2] == grid.num_cells[0] - 1 and b[3] == grid.num_cells[1] - 1):
        return grid
    return grid.cropped()


def _free_window(grid) -> tuple[float, float, float] | None:
    """(centre x, centre y, half-width) of the box of ``grid``'s free cells (probability below 0.5) plus
    ``_NODE_MARGIN``, in the grid frame; None without a free cell.

    Without it a whole-grid search tries every offset at which the scan still overlaps the grid, the laser up to
    the scan's reach outside it, where no answer may stand (``Relocalizer.seen``): on bench-dense/aces's image
    (60 m) that is four times the positions, and global queries took 288 ms (p50 of 40) against 188 ms with the
    free box, the same 40 right (intel's image 96 -> 76 ms, freiburg-079's 54 -> 48 ms, all right both ways).
    """
    cells = grid.cells
    free = (cells != UNKNOWN_VALUE) & (VALUE_TO_PROBABILITY[cells] < 0.5)
    cols, rows = np.flatnonzero(free.any(axis=0)), np.flatnonzero(free.any(axis=1))
    if cols.size == 0:
        return None
    lo = grid.origin + np.array([cols[0], rows[0]], dtype=np.float64) * grid.resolution - _NODE_MARGIN
    hi = grid.origin + np.array([cols[-1] + 1, rows[-1] + 1], dtype=np.float64) * grid.resolution + _NODE_MARGIN
    return float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2, float(max(hi - lo)) / 2


def _global_levels(depth: int) -> tuple[tuple[float, int], ...]:
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


def _window_levels(depth: int) -> tuple[tuple[float, int], ...]:
    """Stages of a windowed search: the window on an 8-cell lattice, then 2, then 1.

    Measured on bench-dense/intel (1500 mapped scans, 34 queries, windows ±1.9 m / ±19°, 3 submaps):
    the exact branch and bound 28 ms p50, (3, 0) 5.5 ms with 1 answer off, (3, 1, 0) 5.7 ms with none,
    (2, 0) 8.4 ms with none (shared machine, absolute times noisy).
    """
    if depth >= 4:
        return ((1.0, 3), (0.0, 1), (0.0, 0))
    return branch_and_bound.default_levels(depth)


def relocalize_many(relocalizer: Relocalizer, recording, queries: Sequence[Query], *, scan_topic: str | None = None,
                    laser_pose=None, corridor: bool = False, max_time_offset: float = 1.0,
                    on_query=None, max_jump: float | None = None,
                    jobs: int | None = 1, selection: TopicSelection | None = None
                    ) -> tuple[list[QueryResult], BatchSummary]:
    """Run every query against its scan (nearest to its time, or at its index), in file order, on ``jobs``
    threads (None: every core). Queries are independent and the stack cache is shared and thread-safe, so the
    answers are the same for any number; each query's own timings then include waiting for a core. Each query
    gets the records around its scan as its context (``relocalize``), the odometry from ``selection`` (default:
    the recording's own)."""
    if not queries:
        raise CartoError("no queries")
    if relocalizer.ro.context_scans > 0:
        scans, contexts = contexts_for(recording, queries, scan_topic, max_time_offset,
                                       context_seconds=CONTEXT_SECONDS, selection=selection)
    else:
        scans, contexts = scans_for_queries(recording, queries, scan_topic, max_time_offset), {}

    def run(k: int) -> QueryResult:
        q = queries[k]
        i, scan = scans[k]
        r = relocalizer.relocalize(scan, q.prior, sigma_xy=q.sigma_xy, sigma_yaw=q.sigma_yaw, corridor=corridor,
                                   laser_pose=laser_pose, max_jump=max_jump, context=contexts.get(k))
        return QueryResult(q, i, scan.time, r)

    jobs = available_cores() if jobs is None else max(1, int(jobs))
    results = []
    inner = relocalizer.jobs
    if jobs > 1:
        relocalizer.jobs = 1  # the queries share the cores; a query's own searches then take one each
    try:
        with ThreadPoolExecutor(max_workers=jobs) if jobs > 1 else nullcontext() as pool:
            answers = pool.map(run, range(len(queries))) if pool is not None else map(run, range(len(queries)))
            for result in answers:  # in file order, as each is done
                results.append(result)
                if on_query is not None:
                    on_query(1)
    finally:
        relocalizer.jobs = inner
    return results, summarize(results)
