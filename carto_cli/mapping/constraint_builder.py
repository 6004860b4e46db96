"""Loop-closure search: which node–submap pairs to try, branch and bound, refinement, acceptance.

Cartographer's ConstraintBuilder2D: a pair is searched when the node is within
``max_constraint_distance`` of the submap and the submap's fixed-ratio sampler fires; nodes of a
trajectory not yet linked to the submap's one get a whole-submap search at ``global_sampling_ratio``. The fast
matcher's pose is dropped if it moves the node further from the graph's estimate than local SLAM can have
drifted over the travel between node and submap (``max_drift``) or lies on the search window's edge
(``window_edge_margin``: the window then did not hold the true pose); it is refined by least squares,
then kept only if the refined pose still scores (geometric check), stayed near the fast matcher's answer
(consistency check: a refinement that wanders has slid along a corridor) and sends few rays through the
submap's walls (``max_see_through``).

As Cartographer's ``MaybeAddConstraint``, it never sees the pose graph: the graph hands
it the node and the submap to try (:class:`NodeData`, :class:`SubmapData`).

Searches are independent, so ``submit`` starts them on a thread pool (the kernels release the GIL)
and ``record`` takes their outcomes back in the order they were submitted: the statistics, the
trajectory links and the closures handed back are the same for any number of workers. Choosing the
pairs (the samplers) and recording stay on the caller's thread.
"""
from __future__ import annotations

import math
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field

import numpy as np

from carto_cli.core import transform
from carto_cli.core.parallel import Done, available_cores
from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.matching import branch_and_bound, least_squares
from carto_cli.matching.precomputation import PrecomputationGridStack
from carto_cli.matching.ray_consistency import see_through_fraction
from carto_cli.matching.scoring import score_at
from carto_cli.matching.stack_cache import StackCache
from carto_cli.options import Options

# max_drift's allowance before any travel: what a right closure may correct of a node next to its submap.
DRIFT_BASE = 0.5  # m
# A refinement that moves the fast matcher's pose by more than this is not trusted.
MAX_REFINEMENT_TRANSLATION = 0.3  # m
MAX_REFINEMENT_ROTATION = math.radians(5.0)


class FixedRatioSampler:
    """Fires on a fixed share of pulses, spread evenly (Cartographer's FixedRatioSampler)."""

    def __init__(self, ratio: float):
        self.ratio = float(ratio)
        self.pulses = 0
        self.samples = 0

    def pulse(self) -> bool:
        self.pulses += 1
        if self.samples < self.ratio * self.pulses:
            self.samples += 1
            return True
        return False


@dataclass(frozen=True, slots=True)
class NodeData:
    """What a search needs of a node: its id, trajectory, pose in the map frame and loop-closure points."""

    index: int
    trajectory: int
    global_pose: np.ndarray  # (3,)
    points: np.ndarray  # (n, 2) in the tracking frame
    travel: float = math.nan  # local-SLAM path length from its trajectory's start (m)


@dataclass(frozen=True, slots=True)
class SubmapData:
    """What a search needs of a finished submap: its id in the pose graph, trajectory, grid, and its
    pose in its trajectory's local frame and in the map frame."""

    index: int
    trajectory: int
    grid: ProbabilityGrid
    local_pose: np.ndarray  # (3,)
    global_pose: np.ndarray  # (3,)
    travel: tuple[float, float] = (math.nan, math.nan)  # local-SLAM path length at its first and last node


@dataclass(frozen=True)
class LoopClosure:
    node: int
    submap: int
    relative_pose: np.ndarray  # node in the submap frame
    score: float
    global_search: bool


@dataclass(frozen=True)
class SearchOutcome:
    """One pair's search, before it is recorded: the closure (None if none passed) and why not, and how long
    each step took on whichever thread ran it."""

    node: NodeData
    submap: SubmapData
    global_search: bool
    closure: LoopClosure | None = None
    outcome: str = "empty"  # empty | not found | drift | window edge | refinement | see-through | accepted
    ns: dict = field(default_factory=dict)  # stage name -> ns


@dataclass
class ConstraintBuilderStats:
    candidates: int = 0
    searched: int = 0
    global_searches: int = 0
    found: int = 0
    rejected_refinement: int = 0
    rejected_see_through: int = 0
    rejected_drift: int = 0
    rejected_window_edge: int = 0
    accepted: int = 0


# The concurrent branch of the builder's timer that the steps of searches run on worker threads go to (thread
# time, summed over the workers: they run beside whatever stage is open when a search is recorded).
SEARCH_THREADS = "search threads"


class _OnThread:
    """A search submitted to a worker thread, and the branch its steps' time goes to when it is recorded."""

    __slots__ = ("future", "timer")

    def __init__(self, future, timer):
        self.future = future
        self.timer = timer

    def result(self) -> SearchOutcome:
        return self.future.result()


class ConstraintBuilder:
    def __init__(self, options: Options, timer: StageTimer | NullTimer | None = None, seed: int = 0,
                 jobs: int | None = 1) -> None:
        """``jobs``: threads for ``search_many`` (None: every available core; 1: the caller's thread)."""
        self.cb = options.pose_graph.constraint_builder
        self.ceres = least_squares.CeresScanMatcher.from_options(self.cb.ceres_scan_matcher)
        self.global_sampling_ratio = options.pose_graph.global_sampling_ratio
        self.timer = timer or NullTimer()
        self._samplers: dict[int, FixedRatioSampler] = {}
        self._global_samplers: dict[int, FixedRatioSampler] = {}
        # Held to cb.precomputation_memory, least recently searched dropped first. Evicting changes nothing but
        # time: a stack is a function of its finished (immutable) grid, rebuilt the same when searched again.
        # Its statistics: misses (stacks built, rebuilt ones included), evictions, peak_bytes.
        self.stacks = StackCache(int(self.cb.precomputation_memory * 2**20),
                                 self.cb.fast_correlative_scan_matcher.branch_and_bound_depth)
        self.stats = ConstraintBuilderStats()
        self.connected: set[frozenset] = set()  # trajectory pairs linked by a loop closure
        self.jobs = available_cores() if jobs is None else max(1, int(jobs))
        self._pool: ThreadPoolExecutor | None = None

    def export_data(self) -> dict:
        """What the builder learnt (samplers, trajectory links, statistics), for ``import_data`` in another
        process; not its threads or stacks."""
        return {"samplers": self._samplers, "global_samplers": self._global_samplers, "stats": self.stats,
                "connected": self.connected, "stacks": self.stacks.counters()}

    def import_data(self, data: dict) -> None:
        self._samplers, self._global_samplers = data["samplers"], data["global_samplers"]
        self.stats, self.connected = data["stats"], data["connected"]
        self.stacks.add_counters(data["stacks"])

    def close(self) -> None:
        """Stop the worker threads (a later search_many starts them again)."""
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def stack(self, index: int, grid: ProbabilityGrid) -> PrecomputationGridStack:
        """The precomputation grids of finished submap ``index``: built on first use, kept while the memory
        budget allows (least recently used dropped first), rebuilt when needed again."""
        if index in self.stacks:
            return self.stacks.get(index, grid)
        with self.timer.stage("precomputation"):
            return self.stacks.get(index, grid)

    def linked(self, node: NodeData, submap: SubmapData) -> bool:
        """Whether the node's trajectory is the submap's or linked to it (else only a whole-submap search)."""
        return node.trajectory == submap.trajectory or \
            frozenset((node.trajectory, submap.trajectory)) in self.connected

    def select(self, node: NodeData, submap: SubmapData) -> bool | None:
        """Whether the candidate rules pick the pair: None if not, else whether it is a whole-submap search."""
        linked = self.linked(node, submap)
        with self.timer.stage("candidate selection"):
            self.stats.candidates += 1
            if linked:
                distance = float(np.hypot(*(node.global_pose[:2] - submap.global_pose[:2])))
                if distance > self.cb.max_constraint_distance:
                    return None
                sampler = self._samplers.setdefault(submap.index, FixedRatioSampler(self.cb.sampling_ratio))
                if not sampler.pulse():
                    return None
            else:
                sampler = self._global_samplers.setdefault(submap.index,
                                                           FixedRatioSampler(self.global_sampling_ratio))
                if not sampler.pulse():
                    return None
        return not linked

    def maybe_add(self, node: NodeData, submap: SubmapData) -> LoopClosure | None:
        """Search ``node`` in ``submap`` if the candidate rules pick the pair; the loop closure found, or None."""
        global_search = self.select(node, submap)
        if global_search is None:
            return None
        return self.search(node, submap, global_search=global_search)

    def search(self, node: NodeData, submap: SubmapData, global_search: bool = False) -> LoopClosure | None:
        """Match ``node`` against ``submap`` (near its current pose, or the whole submap) and check the result."""
        return self.search_many([(node, submap, global_search)])[0]

    def search_many(self, pairs: list[tuple[NodeData, SubmapData, bool]]) -> list[LoopClosure | None]:
        """``search`` for every (node, submap, global_search) of ``pairs``, on the worker threads; recorded in
        order, so the result does not depend on their number."""
        return [self.record(p) for p in self.submit(pairs)]

    def submit(self, pairs: list[tuple[NodeData, SubmapData, bool]]) -> list:
        """Start the searches of ``pairs`` (on the worker threads, or now with one job); hand each of the returned
        handles to ``record``, in order. Precomputation grids are built here, in the caller's thread."""
        # Each search holds its stack: the cache may drop it before a worker gets to the search.
        work = [(node, submap, global_search, self.stack(submap.index, submap.grid))
                for node, submap, global_search in pairs]
        if self.jobs == 1:
            done = []
            for item in work:
                outcome = self._match(*item)
                # Searched now, within the caller's open stage: its steps are that stage's children.
                for name, ns in outcome.ns.items():
                    self.timer.add(name, ns)
                done.append(Done(outcome))
            return done
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=self.jobs, thread_name_prefix="carto-search")
        threads = self.timer.concurrent(SEARCH_THREADS)
        return [_OnThread(self._pool.submit(self._match, *item), threads) for item in work]

    def record(self, handle: Done[SearchOutcome] | _OnThread) -> LoopClosure | None:
        """A submitted search's closure (None if it found none), counted in the statistics; waits for it."""
        outcome = handle.result()
        if isinstance(handle, _OnThread):
            for name, ns in outcome.ns.items():
                handle.timer.add(name, ns)
        return self._record(outcome)

    def _match(self, node: NodeData, submap: SubmapData, global_search: bool,
               stack: PrecomputationGridStack) -> SearchOutcome:
        """The search itself: no shared state is written, so workers run it side by side."""
        grid = submap.grid
        points = node.points
        if len(points) == 0:
            return SearchOutcome(node, submap, global_search)
        fc = self.cb.fast_correlative_scan_matcher
        ns: dict[str, int] = {}
        t0 = time.perf_counter_ns()
        if global_search:
            result = branch_and_bound.match_full_submap(stack, points, min_score=self.cb.global_localization_min_score)
        else:
            # Where the graph currently believes the node is, in the submap's grid frame.
            estimate = transform.compose(
                submap.local_pose,
                transform.compose(transform.inverse(submap.global_pose), node.global_pose))
            matcher = branch_and_bound.match_multilevel if fc.multilevel else branch_and_bound.match
            result = matcher(stack, points, estimate,
                             linear_search_window=fc.linear_search_window,
                             angular_search_window=fc.angular_search_window,
                             min_score=self.cb.min_score)
        t1 = time.perf_counter_ns()
        ns["branch and bound"] = t1 - t0
        if not result.found:
            return SearchOutcome(node, submap, global_search, outcome="not found", ns=ns)
        if not global_search and self._drifted(node, submap, result.pose, estimate):
            return SearchOutcome(node, submap, global_search, outcome="drift", ns=ns)
        if not global_search and self._on_window_edge(result.pose, estimate):
            return SearchOutcome(node, submap, global_search, outcome="window edge", ns=ns)
        ls = self.ceres.match(grid, points, result.pose, target_translation=result.pose[:2])
        moved = transform.relative(result.pose, ls.pose)
        min_score = self.cb.global_localization_min_score if global_search else self.cb.min_score
        refined = not (np.hypot(moved[0], moved[1]) > MAX_REFINEMENT_TRANSLATION
                       or abs(moved[2]) > MAX_REFINEMENT_ROTATION
                       or score_at(grid, points, ls.pose) < min_score)
        t2 = time.perf_counter_ns()
        ns["refinement"] = t2 - t1
        if not refined:
            return SearchOutcome(node, submap, global_search, outcome="refinement", ns=ns)
        if self.cb.max_see_through < 1.0:
            # Endpoints on walls are all the score sees; at an aliased pose some rays also cross walls the
            # submap knows (matching/ray_consistency.py), which a right match's rays do not.
            see_through = see_through_fraction(grid, points, ls.pose) > self.cb.max_see_through
            ns["free-space check"] = time.perf_counter_ns() - t2
            if see_through:
                return SearchOutcome(node, submap, global_search, outcome="see-through", ns=ns)
        relative = transform.compose(transform.inverse(submap.local_pose), ls.pose)
        closure = LoopClosure(node.index, submap.index, relative, result.score, global_search)
        return SearchOutcome(node, submap, global_search, closure, "accepted", ns)

    def _on_window_edge(self, pose: np.ndarray, estimate: np.ndarray) -> bool:
        margin = self.cb.window_edge_margin
        if margin <= 0:
            return False
        limit = self.cb.fast_correlative_scan_matcher.linear_search_window - margin
        return abs(pose[0] - estimate[0]) > limit or abs(pose[1] - estimate[1]) > limit

    def _drifted(self, node: NodeData, submap: SubmapData, pose: np.ndarray, estimate: np.ndarray) -> bool:
        """Whether the match moves the node further from the graph's estimate than local SLAM can have drifted
        over the travel between node and submap (``max_drift``; only within one trajectory)."""
        if self.cb.max_drift <= 0 or node.trajectory != submap.trajectory:
            return False
        lo, hi = submap.travel
        if not (math.isfinite(node.travel) and math.isfinite(lo) and math.isfinite(hi)):
            return False
        travel = max(0.0, lo - node.travel, node.travel - hi)
        moved = math.hypot(pose[0] - estimate[0], pose[1] - estimate[1])
        return moved > DRIFT_BASE + self.cb.max_drift * travel

    def _record(self, o: SearchOutcome) -> LoopClosure | None:
        if o.outcome == "empty":
            return None
        stats = self.stats
        stats.searched += 1
        stats.global_searches += int(o.global_search)
        stats.found += int(o.outcome != "not found")
        stats.rejected_refinement += int(o.outcome == "refinement")
        stats.rejected_see_through += int(o.outcome == "see-through")
        stats.rejected_drift += int(o.outcome == "drift")
        stats.rejected_window_edge += int(o.outcome == "window edge")
        if o.closure is None:
            return None
        stats.accepted += 1
        # A whole-map search links two trajectories only once the pose graph has seen its closures agree
        # (closure_confirmation.LinkConfirmation), which then marks them connected
        return o.closure
