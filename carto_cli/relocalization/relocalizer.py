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
   score against ``global_min_score``; they also keep every submap's best within ``stages.AMBIGUITY_MARGIN`` of
   the best overall as rivals.
5. The verdict (``Judge.verdict``): 'lost' when a check above fails, the laser would stand on a cell no submap knows
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

:class:`Relocalizer` is the face of objects with one job each: ``map_index.MapIndex`` (the map side: grids,
frames, boxes, covering set, distance filters, scan preprocessing; steps 1-2), ``search.Searches`` (step 3's
searches), ``judge.Judge`` (steps 4-5: refinement, fit, covariance, ambiguity, verdict), ``stages.Stages`` (the
policy: which search when, and step 6); ``batch.relocalize_many`` runs a batch of queries.

Precomputation stacks are built on first use and kept in an LRU cache under a
memory budget (:class:`~carto_cli.matching.stack_cache.StackCache`); queries and scan
selection live in ``queries.py``, results, timings and the batch CSV in ``result.py``.
"""
from __future__ import annotations

import numpy as np

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.core.records import Scan
from carto_cli.matching import least_squares
from carto_cli.matching.precomputation import stack_bytes
from carto_cli.matching.stack_cache import StackCache
from carto_cli.options import Options
from carto_cli.relocalization.judge import MIN_KNOWN_FRACTION, Candidate, Judge
from carto_cli.relocalization.map_index import MapIndex
from carto_cli.relocalization.queries import ScanContext
from carto_cli.relocalization.result import Fit, RelocalizationResult, Timings
from carto_cli.relocalization.search import Searches
from carto_cli.relocalization.stages import Carry, Stages

__all__ = ["MIN_KNOWN_FRACTION", "Candidate", "Fit", "Relocalizer"]


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
        self.index = MapIndex(loaded_map, self.options)
        budget = int(self.ro.cache_budget_mb * 1e6) if cache_budget_bytes is None else int(cache_budget_bytes)
        self.cache = StackCache(budget, self.ro.branch_and_bound_depth)
        self.judge = Judge(self.index, self.ro, self.ceres, self.cache)
        self.searches = Searches(self.index, self.ro, self.cache)
        self.stages = Stages(self.index, self.searches, self.judge)
        # What callers read of the map side.
        index = self.index
        self.laser_pose, self.grids, self.searchable, self.covering = (index.laser_pose, index.grids,
                                                                      index.searchable, index.covering)
        self.map_to_grid, self.grid_to_map, self.node_windows = index.map_to_grid, index.grid_to_map, index.node_windows
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

    def relocalize(self, scan: Scan, prior=None, *, sigma_xy: float | None = None, sigma_yaw: float | None = None,
                   corridor: bool = False, laser_pose=None, max_jump: float | None = None,
                   second_look: bool = True, context: ScanContext | None = None) -> RelocalizationResult:
        """Pose of ``scan`` in the map; ``prior`` (x, y, yaw) in the map frame or None for a global search.

        ``context``: the recording's records around ``scan``. An answer judged 'ok' that no window around the prior
        confirmed (a fallback's, a whole-map search's) is then 'lost' when more than ``context_max_through_walls``
        of up to ``context_scans`` neighbours each way, followed from it by odometry, see through walls of the map
        (``following.check_context``): a scan of another building can fit a corridor here, its path cannot.

        ``second_look``: a global answer in a map of a few grids (a map_server image) that fails its checks is
        searched for again with more coarse bets (``Stages.second_look``; a tracker, with the next scan to try, turns
        it off).

        ``max_jump`` (m): an answer farther than this from the prior is 'lost' (a confident jump to a similar
        place elsewhere is what a robot must not take).

        ``sigma_xy`` (m) / ``sigma_yaw`` (rad) default to ``relocalization.default_sigma_*``;
        ``laser_pose`` (laser in the tracking frame) defaults to the one stored in the map.
        Raises CartoError for a prior farther than ``max_prior_distance`` from every submap.
        """
        tm = Timings()
        mount = self.laser_pose if laser_pose is None else transform.as_pose(laser_pose).reshape(3)
        search_pts, fine_pts = self.index.preprocess(scan, mount)
        if len(search_pts) == 0:
            tb = self.options.trajectory_builder_2d
            raise CartoError(f"the scan at t={scan.time:.3f} has no returns within "
                             f"{tb.min_range:g}..{tb.max_range:g} m")
        carry = Carry(tm)
        q = self.stages.query(mount, search_pts, fine_pts, corridor=corridor, max_jump=max_jump,
                              second_look=second_look, jobs=self.jobs)
        if prior is not None:
            q = self.stages.with_prior(q, carry, prior, sigma_xy, sigma_yaw)
        return self.stages.run(q, carry, context)

    # What callers ask of the parts, by the names they always have.

    def preprocess(self, scan: Scan, laser_pose=None, *, search: bool = True) -> tuple[np.ndarray, np.ndarray]:
        return self.index.preprocess(scan, laser_pose, search=search)

    def box_distances(self, xy) -> np.ndarray:
        return self.index.box_distances(xy)

    def track_distances(self, xy) -> np.ndarray:
        return self.index.track_distances(xy)

    def filter_by_distance(self, prior, radius: float) -> list[int]:
        return self.index.filter_by_distance(prior, radius)

    def filter_corridor(self, prior, forward_range: float | None = None, side_range: float | None = None) -> list[int]:
        return self.index.filter_corridor(prior, forward_range, side_range)

    def radius_for(self, sigma_xy: float, reliable: bool) -> float:
        return self.index.radius_for(sigma_xy, reliable)

    def nearest_submap(self, xy) -> int:
        return self.index.nearest_submap(xy)

    def check_prior(self, prior) -> float:
        return self.index.check_prior(prior)

    def seen(self, submap: int, xy) -> bool:
        return self.index.seen(submap, xy)

    def windows(self, sigma_xy: float, sigma_yaw: float) -> tuple[float, float]:
        return self.searches.windows(sigma_xy, sigma_yaw)

    def wide_windows(self, lin: float, ang: float) -> tuple[float, float]:
        return self.searches.wide_windows(lin, ang)

    def refine(self, fine_points, cand: Candidate, threshold: float, tm: Timings, *, known_ok: bool = False,
               sensor=(0.0, 0.0)) -> tuple[np.ndarray, Fit]:
        return self.judge.refine(fine_points, cand, threshold, tm, known_ok=known_ok, sensor=sensor)

    def covariance(self, submap: int, points: np.ndarray, grid_pose: np.ndarray) -> np.ndarray:
        return self.judge.covariance(submap, points, grid_pose)

    def stats(self) -> dict:
        return {"submaps": self.map.num_submaps, "searchable": len(self.searchable), "cache": self.cache.stats()}
