"""Cartographer's 2D global SLAM: nodes and submaps, loop-closure search, periodic sparse optimization.

Frames: every trajectory has its own *local* frame (where local SLAM lives) and
all share the *global* (map) frame. A submap's grid is axis-aligned in its
trajectory's local frame; its ``local_pose`` is a translation there and its
``global_pose`` is where optimization puts that frame. A constraint is the
pose of a node in the frame of a submap (``inverse(submap.local_pose) ∘ node``
with both in the local frame of the submap's trajectory).

Nodes added after an optimization follow it: their global pose is their local
pose carried by the correction of the submap they were inserted into, so a
correction is never lost between optimizations.

The graph's data goes in and out as one value, :class:`PoseGraphState` (``to_state`` /
``from_state``). The graph holds the nodes, submaps and constraints and delegates the rest, each part seeing
only what it is handed: which pairs are searched and when their closures come back to ``closure_search``, the
searches themselves to ``constraint_builder`` (never the graph), the chain rule that confirms a closure to
``closure_confirmation``, and when the periodic optimization runs to ``optimization_scheduler``.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core import transform
from carto_cli.core.kernels import register_warm_up
from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.mapping.closure_confirmation import LINK_CHECKS, ClosureConfirmation, LinkConfirmation
from carto_cli.mapping.closure_search import ClosureSearches, node_data_of, submap_data_of
from carto_cli.mapping.constraint_builder import ConstraintBuilder, LoopClosure
from carto_cli.mapping.constraints import ConstraintKind, ConstraintSet
from carto_cli.mapping.link_check import LINK_CONFLICT, LINK_REACH, free_space_conflict
from carto_cli.mapping.odometry_log import GrowingArray, OdometryLog
from carto_cli.mapping.optimization import OptimizationResult, OptimizationSummary, residuals
from carto_cli.mapping.optimization_scheduler import OptimizationProblem, OptimizationScheduler
from carto_cli.mapping.pose_graph_state import PoseGraphState, SubmapEntry, odometry_at_nodes
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options

__all__ = ["PoseGraph", "PoseGraphStats"]

def _travel(local_poses: np.ndarray, trajectories: np.ndarray) -> np.ndarray:
    """(N,) local-SLAM path length of every node from its trajectory's first node."""
    out = np.zeros(len(local_poses))
    for t in np.unique(trajectories):
        idx = np.flatnonzero(trajectories == t)
        steps = np.hypot(*np.diff(local_poses[idx, :2], axis=0).T) if len(idx) > 1 else np.zeros(0)
        out[idx] = np.concatenate([[0.0], np.cumsum(steps)])
    return out


def _travel_to(local_pose: np.ndarray, trajectory: int, node_trajectory: list[int], node_travel: list[float],
               local_poses: np.ndarray) -> float:
    """The local-SLAM path length of a new node of ``trajectory`` at ``local_pose`` from the trajectory's start."""
    for previous in range(len(node_trajectory) - 1, -1, -1):  # the trajectory's last node: nearly always the last
        if node_trajectory[previous] == trajectory:
            step = local_poses[previous, :2] - local_pose[:2]
            return node_travel[previous] + math.hypot(step[0], step[1])
    return 0.0


def _offer_link(graph: PoseGraph, lc: LoopClosure, *, checking: bool = False) -> bool:
    """Hand ``lc`` to the link rule when it joins two trajectories not linked yet (True), inserting the closures
    that link them once they agree; False for any other closure. A closure that waits is checked at once
    (``_check_link``) unless it came from such a check."""
    submap_trajectory, node_trajectory = graph.submaps[lc.submap].trajectory, graph.node_trajectory[lc.node]
    pair = frozenset((submap_trajectory, node_trajectory))
    if submap_trajectory == node_trajectory:
        return False
    if pair in graph.builder.connected:
        # A whole-map search started before the link came back: the link is its prior now, and a match a windowed
        # search around the node's pose could not have found is a look-alike place (dropped)
        return lc.global_search and not _within_window(graph, lc)
    cb = graph.pg.constraint_builder
    linking, frame = graph.links.offer(lc, submap_trajectory, graph.submaps[lc.submap].local_pose, node_trajectory,
                                       graph.local_poses[lc.node])
    if frame is not None and _conflict(graph, lc, frame) > LINK_CONFLICT:
        graph.stats.refused_links += 1  # placed there, the session would stand in the other's free space
        return True
    for link in linking:
        graph.constraints.add(link.submap, link.node, link.relative_pose, cb.loop_closure_translation_weight,
                              cb.loop_closure_rotation_weight, ConstraintKind.INTER_SUBMAP)
    if frame is None:
        if not checking:
            _check_link(graph, lc)
        return True
    earlier, later = sorted(pair)
    group, other = _component(graph.builder.connected, later), _component(graph.builder.connected, earlier)
    if earlier not in group:
        # A session linked for the first time goes where the link puts it at once, and again once the running
        # optimization (which knew it elsewhere) lands: searches from now on look around its true place. The
        # trajectories already linked to it go with it (a merged map's own sessions share one frame,
        # mapping.merging), and the side that holds the lowest trajectory (the map frame's) stays
        if min(group) < min(other):
            earlier, later, frame, group = later, earlier, transform.inverse(frame), other
        _place(graph, earlier, later, frame, group)
        graph.placements.append((earlier, later, frame, group))
    # Every trajectory of the one side is now linked to every one of the other: a pair that meets after both were
    # placed is judged against where they are (a look-alike dropped), never linked afresh by two closures that
    # agree on a look-alike frame (a ring corridor turned half round) against the placement both already have
    joined = sorted(group | other)
    graph.builder.connected.update(frozenset((a, b)) for i, a in enumerate(joined) for b in joined[i + 1:])
    return True


def _conflict(graph: PoseGraph, lc: LoopClosure, frame: np.ndarray) -> float:
    """The share of the later trajectory's returns around ``lc`` that the link ``frame`` (the later trajectory's
    frame in the earlier's, by trajectory id) puts in the free space of the earlier one and those linked to it
    (``link_check``)."""
    entry = graph.submaps[lc.submap]
    earlier, later = sorted((entry.trajectory, graph.node_trajectory[lc.node]))
    # The earlier trajectory's local frame in the map where the closure is (its correction there)
    if entry.trajectory == earlier:
        correction, anchor = entry.local_to_global(), lc.node
    else:  # the node is the earlier trajectory's; the later one's scans around the closure are its submap's
        correction = transform.compose(graph.global_poses[lc.node], transform.inverse(graph.local_poses[lc.node]))
        anchor = entry.nodes[len(entry.nodes) // 2]
    place = transform.compose(correction, frame)
    travel = np.asarray(graph.node_travel)
    nodes = np.flatnonzero((np.asarray(graph.node_trajectory) == later)
                           & (np.abs(travel - travel[anchor]) <= LINK_REACH))
    points = [graph.node_points[n] for n in nodes.tolist()]
    poses = transform.compose(place, graph.local_poses[nodes])
    side = _component(graph.builder.connected, earlier)
    others = [e for e in graph.submaps if e.trajectory in side]
    share, _ = free_space_conflict(points, poses.reshape(-1, 3), [e.submap.grid for e in others],
                                   [e.local_to_global() for e in others])
    return share


def _component(connected: set[frozenset], trajectory: int) -> frozenset[int]:
    """``trajectory`` and every trajectory linked to it, directly or through others."""
    reached = {trajectory}
    grew = True
    while grew:
        grew = False
        for pair in connected:
            if len(pair & reached) == 1:
                reached |= pair
                grew = True
    return frozenset(reached)


def _place(graph: PoseGraph, earlier: int, later: int, frame: np.ndarray, group: frozenset[int]) -> None:
    """Move trajectory ``later``, and the trajectories ``group`` it is linked to, rigidly so that its frame lies at
    ``frame`` in trajectory ``earlier``'s."""
    move = transform.compose(transform.compose(_last_correction(graph.submaps, earlier), frame),
                             transform.inverse(_last_correction(graph.submaps, later)))
    mine = np.isin(np.asarray(graph.node_trajectory), list(group))
    graph._global.array[mine] = transform.compose(move, graph._global.array[mine])
    for entry in graph.submaps:
        if entry.trajectory in group:
            entry.global_pose = transform.compose(move, entry.global_pose)


def _within_window(graph: PoseGraph, lc: LoopClosure) -> bool:
    """Whether ``lc`` puts its node within the windowed search's reach of where the graph has it."""
    window = graph.pg.constraint_builder.fast_correlative_scan_matcher
    gap = transform.relative(graph.global_poses[lc.node],
                             transform.compose(graph.submaps[lc.submap].global_pose, lc.relative_pose))
    return (max(abs(gap[0]), abs(gap[1])) <= window.linear_search_window
            and abs(gap[2]) <= window.angular_search_window)


def _follow_links(graph: PoseGraph, node: int) -> None:
    """Check the placements still waiting for ``node``'s trajectory where each puts ``node``: as the session moves
    on, a right one is confirmed from a second place LINK_SEPARATION away, a look-alike refuted."""
    for lc in graph.links.waiting(graph.node_trajectory[node]):
        if graph.node_trajectory[lc.node] == graph.node_trajectory[node]:
            _check_link(graph, lc, [node])
        # (a placement offered from the other side, the session's own submap matched, waits for a search to come)


def _check_link(graph: PoseGraph, lc: LoopClosure, nodes: list[int] | None = None) -> None:
    """Search a few other nodes of ``lc``'s node's trajectory (``nodes``, default LINK_CHECKS spread over it)
    where ``lc`` says they are, each in the nearest finished submap of the other trajectory, with a windowed
    search: closures there that agree link the two at once. Whole-map searches are few
    (``global_sampling_ratio``), so without this a short session could wait for a second one that never comes, and
    a wrong candidate is refuted where it would put the session."""
    entry = graph.submaps[lc.submap]
    trajectory = graph.node_trajectory[lc.node]
    # Where the closure puts the node's trajectory, in the map frame of the submap's trajectory
    frame = transform.compose(transform.compose(entry.global_pose, lc.relative_pose),
                              transform.inverse(graph.local_poses[lc.node]))
    own = [n for n in (np.flatnonzero(np.asarray(graph.node_trajectory) == trajectory).tolist() if nodes is None
                       else nodes) if n != lc.node and len(graph.node_points[n])]
    targets = [i for i in sorted(graph._finished) if graph.submaps[i].trajectory == entry.trajectory]
    if not own or not targets:
        return
    centres = np.array([graph.submaps[i].global_pose[:2] for i in targets])
    pairs = []
    for k in np.unique(np.linspace(0, len(own) - 1, min(LINK_CHECKS, len(own))).round().astype(int)).tolist():
        node = own[k]
        pose = transform.compose(frame, graph.local_poses[node])
        # Another submap than the closure's where there is one: a second place is independent evidence
        gaps = np.hypot(*(centres - pose[:2]).T) + np.where(np.array(targets) == lc.submap, np.inf, 0.0)
        if not np.isfinite(gaps).any():
            gaps = np.hypot(*(centres - pose[:2]).T)
        nearest = int(np.argmin(gaps))
        if gaps[nearest] <= graph.pg.constraint_builder.max_constraint_distance:
            data = node_data_of(graph, node)
            pairs.append((dataclasses.replace(data, global_pose=pose), submap_data_of(graph, targets[nearest]),
                          False))
    for found in graph.builder.search_many(pairs):
        if found is not None:
            _offer_link(graph, found, checking=True)


def _last_correction(submaps: list[SubmapEntry], trajectory: int) -> np.ndarray:
    """Where the last submap of ``trajectory`` puts its local frame (none yet: the map frame itself)."""
    for entry in reversed(submaps):
        if entry.trajectory == trajectory:
            return entry.local_to_global()
    return np.zeros(3)


@dataclass
class PoseGraphStats:
    refused_links: int = 0  # placements of a session its returns said were wrong (link_check)
    optimizations: int = 0
    optimization_time_s: float = 0.0
    last_summary: OptimizationSummary | None = None


class PoseGraph:
    def __init__(self, options: Options, timer: StageTimer | NullTimer | None = None, loop_closure: bool = True,
                 seed: int = 0, jobs: int | None = 1) -> None:
        """``jobs``: threads for loop-closure searches (None: every core); the graph is the same for any number."""
        self.options = options
        self.pg = options.pose_graph
        self.timer = timer or NullTimer()
        self.loop_closure = loop_closure
        self.node_times: list[float] = []
        self.node_trajectory: list[int] = []
        self.node_points: list[np.ndarray] = []
        self.node_travel: list[float] = []  # local-SLAM path length from the node's trajectory's start (m)
        self._local = GrowingArray(3)
        self._global = GrowingArray(3)
        self._odometry = GrowingArray(3)  # explicit per-node odometry poses; NaN rows: interpolate
        self.odometry = OdometryLog()
        self.node_searches: list[bool] = []  # whether a node is a loop-closure source (key-frame rule)
        self.removed_loop_closures: list[tuple[int, int, float]] = []  # (node, submap, residual m)
        self.submaps: list[SubmapEntry] = []
        self._submap_index: dict[tuple[int, int], int] = {}  # (trajectory, local submap index) → graph index
        self.constraints = ConstraintSet()
        self.builder = ConstraintBuilder(options, timer=self.timer, seed=seed, jobs=jobs)
        # Submaps this graph has been told are finished. Local SLAM may run ahead of the graph (Slam's
        # background worker), so a submap's own flag can already be set for a node that came before it.
        self._finished: set[int] = set()
        self.stats = PoseGraphStats()
        self._nodes_since_optimization = 0
        self.searches = ClosureSearches()
        self.confirmation = ClosureConfirmation()  # with confirm_loop_closures
        self.links = LinkConfirmation()  # the first closures between two trajectories
        # sessions just linked (earlier, later, frame, the trajectories moved), moved into place again at settle
        self.placements: list[tuple[int, int, np.ndarray, frozenset[int]]] = []
        self.scheduler = OptimizationScheduler()

    # ------------------------------------------------------------------ state in and out

    def to_state(self) -> PoseGraphState:
        """The graph's data (with the closures of every search started). Arrays are copies; submaps (grids) and
        node points are shared, so an unfinished submap of a graph still mapping goes on changing in the state
        too."""
        self.settle()
        return PoseGraphState(
            node_times=np.asarray(self.node_times, dtype=np.float64).reshape(self.num_nodes),
            node_trajectories=np.asarray(self.node_trajectory, dtype=np.int64).reshape(self.num_nodes),
            node_local_poses=self._local.array.copy(),
            node_global_poses=self._global.array.copy(),
            node_odometry=self._odometry.array.copy(),
            node_points=list(self.node_points),
            node_searches=np.asarray(self.node_searches, dtype=bool).reshape(self.num_nodes),
            submaps=[SubmapEntry(e.submap, e.trajectory, e.global_pose.copy(), list(e.nodes), e.searched)
                     for e in self.submaps],
            constraints=self.constraints.copy(),
            odometry_samples={t: (times.copy(), poses.copy()) for t, (times, poses) in self.odometry.arrays().items()},
            last_search_poses={t: pose.copy() for t, pose in self.searches.last_search_pose.items()},
            connected=set(self.builder.connected),
            removed_loop_closures=list(self.removed_loop_closures),
            nodes_since_optimization=self._nodes_since_optimization,
        )

    @classmethod
    def from_state(cls, options: Options, state: PoseGraphState, *, timer: StageTimer | NullTimer | None = None,
                   loop_closure: bool = True, seed: int = 0, jobs: int | None = 1) -> PoseGraph:
        """A graph holding ``state``, ready to grow (e.g. by a new trajectory). It owns copies of
        everything in ``state``, so building on it never changes the state or whatever it came from."""
        graph = cls(options, timer=timer, loop_closure=loop_closure, seed=seed, jobs=jobs)
        state = state.copy()
        for i in range(state.num_nodes):
            graph._local.append(state.node_local_poses[i])
            graph._global.append(state.node_global_poses[i])
            graph._odometry.append(state.node_odometry[i])
        graph.node_times = [float(t) for t in state.node_times]
        graph.node_trajectory = [int(t) for t in state.node_trajectories]
        graph.node_points = list(state.node_points)
        graph.node_travel = _travel(state.node_local_poses, state.node_trajectories).tolist()
        graph.node_searches = [bool(v) for v in state.node_searches]
        graph.odometry = OdometryLog.of(state.odometry_samples)
        graph.searches.last_search_pose = dict(state.last_search_poses)
        graph.removed_loop_closures = list(state.removed_loop_closures)
        graph.submaps = list(state.submaps)
        graph._submap_index = {(e.trajectory, e.submap.index): i for i, e in enumerate(graph.submaps)}
        graph._finished = {i for i, e in enumerate(graph.submaps) if e.finished}
        graph.constraints = state.constraints
        graph.builder.connected = set(state.connected)
        graph._nodes_since_optimization = int(state.nodes_since_optimization)
        return graph

    # ------------------------------------------------------------------ a graph run in another process

    # What a graph run in a process of its own hands back (graph_runner's export_graph / import_graph), by name;
    # everything else it
    # holds is its configuration or its machinery (NOT_EXPORTED). tests/mapping/test_pose_graph.py checks that the
    # two lists name every attribute, so one added later is handed back or left out on purpose, never forgotten.
    EXPORTED = ("node_times", "node_trajectory", "node_points", "node_travel", "_local", "_global", "_odometry",
                "odometry", "node_searches", "removed_loop_closures", "constraints", "_submap_index",
                "_finished", "stats", "_nodes_since_optimization", "searches", "confirmation", "links",
                "placements")
    # scheduler: idle once settled (nothing runs at export), and its thread cannot cross processes
    NOT_EXPORTED = ("options", "pg", "timer", "loop_closure", "scheduler", "builder", "submaps")  # the last two: below

    # ------------------------------------------------------------------ state

    @property
    def num_nodes(self) -> int:
        return self._local.n

    @property
    def local_poses(self) -> np.ndarray:
        return self._local.array

    @property
    def global_poses(self) -> np.ndarray:
        return self._global.array

    @property
    def finished_submaps(self) -> frozenset[int]:
        """The submaps this graph has been told are finished (what a node's searches may try)."""
        return frozenset(self._finished)

    @property
    def submap_global_poses(self) -> np.ndarray:
        if not self.submaps:
            return np.zeros((0, 3))
        return np.array([s.global_pose for s in self.submaps])

    # ------------------------------------------------------------------ building

    def add_odometry(self, time: float, pose: ArrayLike, trajectory: int = 0) -> None:
        """An odometry sample (tracking frame in the odometry frame); nodes get it interpolated at their time."""
        self.odometry.add(time, pose, trajectory)

    def node_odometry(self) -> np.ndarray:
        """(N, 3) odometry at every node: the explicit pose if one was given, else odometry interpolated
        at the node's time (Cartographer's InterpolateOdometry), NaN outside the odometry's time range."""
        return odometry_at_nodes(self._odometry.array, self.node_times, self.node_trajectory, self.odometry.arrays())

    def close(self) -> None:
        """Stop the search and optimization threads, if any (an optimization running is finished first)."""
        self.builder.close()
        self.scheduler.close()

    def use_threads(self, jobs: int, timer: StageTimer | NullTimer | None = None) -> None:
        """Search on ``jobs`` threads and optimize beside the next nodes on one more (jobs > 1) from now on,
        and time the graph's work with ``timer`` (e.g. the timer of the thread it now runs on)."""
        self.close()
        self.builder.jobs = max(1, int(jobs))
        if timer is not None:
            self.timer = self.builder.timer = timer

    def add_node(self, time: float, local_pose: ArrayLike, points: np.ndarray, insertion_submaps: list[Submap],
                 odometry_pose: ArrayLike | None = None, trajectory: int = 0,
                 finished: list[bool] | None = None) -> int:
        """A node local SLAM inserted into ``insertion_submaps`` (oldest first); returns its id.
        ``finished``: which of them local SLAM had finished when it made the node (default: their flags now)."""
        local_pose = transform.as_pose(local_pose)
        if finished is None:
            finished = [s.finished for s in insertion_submaps]
        front_key = (trajectory, insertion_submaps[0].index)
        if front_key in self._submap_index:
            correction = self.submaps[self._submap_index[front_key]].local_to_global()
        else:
            correction = _last_correction(self.submaps, trajectory)
        indices = []
        for submap in insertion_submaps:
            key = (trajectory, submap.index)
            if key not in self._submap_index:
                self._submap_index[key] = len(self.submaps)
                self.submaps.append(SubmapEntry(submap, trajectory, transform.compose(correction, submap.local_pose)))
            indices.append(self._submap_index[key])
        self._finished.update(i for i, done in zip(indices, finished) if done)

        travel = _travel_to(local_pose, trajectory, self.node_trajectory, self.node_travel, self._local.array)
        node = self._local.append(local_pose)
        self.node_travel.append(travel)
        self._global.append(transform.compose(correction, local_pose))
        self._odometry.append(np.full(3, np.nan) if odometry_pose is None else transform.as_pose(odometry_pose))
        self.node_times.append(float(time))
        self.node_trajectory.append(trajectory)
        self.node_points.append(points)
        self.node_searches.append(self.searches.is_key_node(self.pg.constraint_builder, local_pose, trajectory))

        for index in indices:
            entry = self.submaps[index]
            entry.nodes.append(node)
            rel = transform.compose(transform.inverse(entry.local_pose), local_pose)
            self.constraints.add(index, node, rel, self.pg.matcher_translation_weight, self.pg.matcher_rotation_weight,
                                 ConstraintKind.INTRA_SUBMAP)

        if self.loop_closure:
            with self.timer.stage("loop closure"):
                front = self.submaps[indices[0]]
                if indices[0] in self._finished and not front.searched:
                    # A newly finished submap is searched by every earlier node not already in it.
                    front.searched = True
                    self.searches.search_submap(self.builder, self, indices[0],
                                                self.pg.constraint_builder.max_constraint_distance)
                if self.node_searches[node]:
                    self.searches.search_node(self.builder, self, node, self._finished)
                    _follow_links(self, node)

        self._nodes_since_optimization += 1
        n_every = self.pg.optimize_every_n_nodes
        # Without loop closure the graph holds only local-SLAM, intra-submap and odometry
        # constraints: optimizing it would only pull the trajectory towards the odometry,
        # so "local SLAM only" (--no-loop-closure) must not optimize at all.
        if self.loop_closure and n_every > 0 and self._nodes_since_optimization >= n_every:
            self._optimize_beside()
        return node

    # ------------------------------------------------------------------ loop closure

    def _add_loop_closure(self, lc: LoopClosure, confirming: bool = False) -> None:
        cb = self.pg.constraint_builder

        def insert(node: int, relative: np.ndarray) -> None:
            self.constraints.add(lc.submap, node, relative, cb.loop_closure_translation_weight,
                                 cb.loop_closure_rotation_weight, ConstraintKind.INTER_SUBMAP)

        if _offer_link(self, lc):
            return
        if not cb.confirm_loop_closures:
            insert(lc.node, lc.relative_pose)
            return
        confirmation = self.confirmation
        agreeing = confirmation.agreeing(lc, self.local_poses, self.node_trajectory)
        if not agreeing and not confirming:
            neighbours = confirmation.neighbours(lc.node, lc.submap, self.submaps[lc.submap].nodes,
                                                 self.node_trajectory, self.node_points)
            pairs = []
            if neighbours:
                submap = submap_data_of(self, lc.submap)
                pairs = [(node_data_of(self, other), submap, False) for other in neighbours]
            for found in self.builder.search_many(pairs):
                if found is not None:
                    self._add_loop_closure(found, confirming=True)
            agreeing = confirmation.agreeing(lc, self.local_poses, self.node_trajectory)
        if agreeing:
            insert(lc.node, lc.relative_pose)
        for entry in confirmation.keep(lc, agreeing):
            insert(entry.node, entry.relative)

    # ------------------------------------------------------------------ optimization

    def settle(self) -> None:
        """Take the closures of every search started, then the result of the optimization running beside the
        nodes: the graph as if everything begun were done. In that order: a search in flight reads its node's
        pose where the graph keeps it, which taking an optimization's result overwrites."""
        with self.timer.stage("loop closure"):
            for lc in self.searches.flush(self.builder):
                self._add_loop_closure(lc)
        taken = self.scheduler.take(self.timer)
        if taken is not None:
            self._apply(*taken)
        placements, self.placements = self.placements, []
        for earlier, later, frame, group in placements:
            _place(self, earlier, later, frame, group)  # again: the optimization just taken knew it elsewhere

    def _optimize_beside(self) -> None:
        """The periodic optimization, run while the next ``optimize_every_n_nodes`` nodes are added and searched
        (``optimization_scheduler``), its poses taken when the next one starts. The nodes added meanwhile, and their
        searches, use the poses of the optimization before; a search's closure is a pose in its submap's frame, so
        only its window's centre and the candidate distances see the older poses."""
        self.settle()
        self._nodes_since_optimization = 0
        problem = self._problem(final=False)
        if problem is not None:
            self.scheduler.start(problem, self.num_nodes, len(self.submaps), jobs=self.builder.jobs,
                                 timer=self.timer)

    def optimize(self, final: bool = False) -> OptimizationSummary | None:
        """Optimize now (after settling). The final optimization drops the loop closures it disagrees with by more
        than ``max_loop_closure_residual`` and optimizes once more without them."""
        self.settle()
        limit = self.pg.constraint_builder.max_loop_closure_residual
        for again in (False, True):
            self._nodes_since_optimization = 0
            with self.timer.stage("optimization"):
                problem = self._problem(final)
                if problem is None:
                    return None
                result, _ = problem.solve()
            summary = self._apply(result, self.num_nodes, len(self.submaps))
            if again or not final or limit <= 0 or not self.remove_bad_loop_closures(limit):
                break
        return summary

    def loop_closure_residuals(self) -> np.ndarray:
        """(K,) translation residual (m) of every loop closure at the current poses, in constraint order."""
        mask = self.constraints.is_loop_closure
        if not mask.any():
            return np.zeros(0)
        err = residuals(self.global_poses, self.submap_global_poses, self.constraints.select(mask))
        return np.hypot(err[:, 0], err[:, 1])

    def remove_bad_loop_closures(self, max_residual: float) -> int:
        """Drop loop closures the optimized graph disagrees with by more than ``max_residual`` metres."""
        mask = self.constraints.is_loop_closure
        if not mask.any():
            return 0
        res = self.loop_closure_residuals()
        bad_lc = res > max_residual
        if not bad_lc.any():
            return 0
        idx = np.flatnonzero(mask)[bad_lc]
        for i in idx:
            c = self.constraints[int(i)]
            self.removed_loop_closures.append((c.node, c.submap, float(res[np.searchsorted(np.flatnonzero(mask), i)])))
        drop = np.zeros(len(self.constraints), dtype=bool)
        drop[idx] = True
        return self.constraints.remove(drop)

    def _problem(self, final: bool) -> OptimizationProblem | None:
        """The optimization's inputs at this moment, copied: a solve beside the next nodes reads nothing live."""
        if self.num_nodes == 0 or not self.submaps:
            return None
        return OptimizationProblem.of(self.pg, local_poses=self.local_poses, global_poses=self.global_poses,
                                      trajectories=np.asarray(self.node_trajectory), odometry=self.node_odometry(),
                                      submap_poses=self.submap_global_poses, constraints=self.constraints,
                                      final=final)

    def _apply(self, result: OptimizationResult, num_nodes: int, num_submaps: int) -> OptimizationSummary:
        """Take an optimization's poses for the first ``num_nodes`` nodes and ``num_submaps`` submaps (those it
        had); nodes and submaps added since move rigidly with their trajectory's last submap it had."""
        before = {}
        for index in range(num_submaps - 1, -1, -1):
            trajectory = self.submaps[index].trajectory
            if trajectory not in before:
                before[trajectory] = (index, self.submaps[index].local_to_global())
        self._global.array[:num_nodes] = result.node_poses
        for entry, pose in zip(self.submaps[:num_submaps], result.submap_poses):
            entry.global_pose = pose
        if self.num_nodes > num_nodes or len(self.submaps) > num_submaps:
            moves = {t: transform.compose(self.submaps[index].local_to_global(), transform.inverse(old))
                     for t, (index, old) in before.items()}
            for node in range(num_nodes, self.num_nodes):
                move = moves.get(self.node_trajectory[node])
                if move is not None:
                    self._global.array[node] = transform.compose(move, self._global.array[node])
            for entry in self.submaps[num_submaps:]:
                move = moves.get(entry.trajectory)
                if move is not None:
                    entry.global_pose = transform.compose(move, entry.global_pose)
        self.stats.optimizations += 1
        self.stats.optimization_time_s += result.summary.time
        self.stats.last_summary = result.summary
        return result.summary


@register_warm_up(system="cartographer")
def warm_up() -> None:
    """The optimization's kernels on a toy graph: three nodes in one submap, with odometry."""
    from carto_cli.options import load_options

    graph = PoseGraph(load_options(None))
    submap = Submap((0.0, 0.0))
    for i in range(3):
        graph.add_odometry(float(i), (0.1 * i, 0.0, 0.0))
        graph.add_node(float(i), (0.1 * i, 0.01 * i, 0.0), np.zeros((0, 2)), [submap])
    graph.optimize(final=True)
