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
``from_state``); the constraint builder is handed the node and submap data it searches,
never the graph.
"""
from __future__ import annotations

import math
import time
from collections.abc import Iterable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core import transform
from carto_cli.core.kernels import register_warm_up
from carto_cli.core.parallel import Done
from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.mapping.constraint_builder import ConstraintBuilder, LoopClosure, NodeData, SubmapData
from carto_cli.mapping.constraints import ConstraintKind, ConstraintSet
from carto_cli.mapping.optimization import NodePairs, OptimizationResult, OptimizationSummary, optimize, residuals
from carto_cli.mapping.pose_graph_state import PoseGraphState, SubmapEntry, odometry_at_nodes
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options

__all__ = ["PoseGraph", "PoseGraphStats"]

# confirm_loop_closures: two closures to one submap agree when they place their nodes, at most this many
# nodes apart, within this of local SLAM's relative pose (local SLAM is good to centimetres over a few nodes).
CONFIRM_MAX_NODES = 10
CONFIRM_MAX_TRANSLATION = 0.2  # m
CONFIRM_MAX_ROTATION = math.radians(2.0)
CONFIRM_NEIGHBOURS = 2  # nodes searched at once to confirm a new closure


def _travel(local_poses: np.ndarray, trajectories: np.ndarray) -> np.ndarray:
    """(N,) local-SLAM path length of every node from its trajectory's first node."""
    out = np.zeros(len(local_poses))
    for t in np.unique(trajectories):
        idx = np.flatnonzero(trajectories == t)
        steps = np.hypot(*np.diff(local_poses[idx, :2], axis=0).T) if len(idx) > 1 else np.zeros(0)
        out[idx] = np.concatenate([[0.0], np.cumsum(steps)])
    return out


class _Growing:
    """An (n, k) float array with amortised O(1) append."""

    def __init__(self, width: int, capacity: int = 256):
        self._data = np.empty((capacity, width))
        self.n = 0

    def append(self, row: ArrayLike) -> int:
        if self.n == len(self._data):
            self._data = np.concatenate([self._data, np.empty_like(self._data)])
        self._data[self.n] = row
        self.n += 1
        return self.n - 1

    @property
    def array(self) -> np.ndarray:
        return self._data[: self.n]


@dataclass
class PendingClosure:
    """A loop closure found while ``confirm_loop_closures`` is on, kept per submap: ``inserted`` once a closure of
    a neighbouring node agreed with it and both went into the graph."""

    node: int
    relative: np.ndarray  # the node's pose in the submap's frame
    inserted: bool


@dataclass(frozen=True)
class OptimizationProblem:
    """One optimization's inputs, copied when it starts: a solve beside the next nodes reads nothing live."""

    node_poses: np.ndarray
    submap_poses: np.ndarray
    constraints: ConstraintSet
    odometry: NodePairs | None
    local_slam: NodePairs
    huber_scale: float
    max_num_iterations: int
    fixed_submaps: tuple[int, ...] = (0,)

    def solve(self) -> tuple[OptimizationResult, int]:
        """The optimized poses and how long the solve took (ns), on whichever thread runs it."""
        start = time.perf_counter_ns()
        result = optimize(self.node_poses, self.submap_poses, self.constraints, self.odometry, self.local_slam,
                          huber_scale=self.huber_scale, max_num_iterations=self.max_num_iterations,
                          fixed_submaps=self.fixed_submaps)
        return result, time.perf_counter_ns() - start


@dataclass(frozen=True)
class RunningOptimization:
    """The periodic optimization running beside the next nodes: its result to come, and what it had."""

    task: Any  # a Future or core.parallel.Done of OptimizationProblem.solve's answer
    num_nodes: int
    num_submaps: int
    thread: Any  # its timer branch when it runs on the solver's thread; None when computed inline


@dataclass
class PoseGraphStats:
    optimizations: int = 0
    optimization_time_s: float = 0.0
    last_summary: OptimizationSummary | None = None


# The concurrent branch of the graph's timer that periodic optimizations solved on the optimizer's own thread go to
# (they run beside the next nodes; the graph's own stage for them is "optimization wait").
OPTIMIZER_THREAD = "optimizer thread"


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
        self._local = _Growing(3)
        self._global = _Growing(3)
        self._odometry = _Growing(3)  # explicit per-node odometry poses; NaN rows: interpolate
        self._odometry_samples: dict[int, tuple[_Growing, _Growing]] = {}  # trajectory → (times, unwrapped poses)
        self.node_searches: list[bool] = []  # whether a node is a loop-closure source (key-frame rule)
        self._last_search_pose: dict[int, np.ndarray] = {}  # trajectory → local pose of its last key node
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
        # confirm_loop_closures: per submap, every closure found there
        self._pending_closures: dict[int, list[PendingClosure]] = {}
        self.unconfirmed_loop_closures = 0
        self._in_flight: list = []  # searches started, in order, whose closures are not yet added
        self._running: RunningOptimization | None = None  # the periodic optimization beside the next nodes
        self._solver: ThreadPoolExecutor | None = None  # its thread, with more than one job

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
            odometry_samples={t: (times.array[:, 0].copy(), poses.array.copy())
                              for t, (times, poses) in self._odometry_samples.items()},
            last_search_poses={t: pose.copy() for t, pose in self._last_search_pose.items()},
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
        graph._adopt(state.copy())
        return graph

    def _adopt(self, state: PoseGraphState) -> None:
        for i in range(state.num_nodes):
            self._local.append(state.node_local_poses[i])
            self._global.append(state.node_global_poses[i])
            self._odometry.append(state.node_odometry[i])
        self.node_times = [float(t) for t in state.node_times]
        self.node_trajectory = [int(t) for t in state.node_trajectories]
        self.node_points = list(state.node_points)
        self.node_travel = _travel(state.node_local_poses, state.node_trajectories).tolist()
        self.node_searches = [bool(v) for v in state.node_searches]
        for trajectory, (times, poses) in state.odometry_samples.items():
            grown = self._odometry_samples[int(trajectory)] = (_Growing(1), _Growing(3))
            for t, pose in zip(times, poses):
                grown[0].append((float(t),))
                grown[1].append(pose)
        self._last_search_pose = dict(state.last_search_poses)
        self.removed_loop_closures = list(state.removed_loop_closures)
        self.submaps = list(state.submaps)
        self._submap_index = {(e.trajectory, e.submap.index): i for i, e in enumerate(self.submaps)}
        self._finished = {i for i, e in enumerate(self.submaps) if e.finished}
        self.constraints = state.constraints
        self.builder.connected = set(state.connected)
        self._nodes_since_optimization = int(state.nodes_since_optimization)

    # ------------------------------------------------------------------ a graph run in another process

    # What a graph run in a process of its own hands back (export_data / import_data), by name; everything else it
    # holds is its configuration or its machinery (NOT_EXPORTED). tests/mapping/test_pose_graph.py checks that the
    # two lists name every attribute, so one added later is handed back or left out on purpose, never forgotten.
    EXPORTED = ("node_times", "node_trajectory", "node_points", "node_travel", "_local", "_global", "_odometry",
                "_odometry_samples", "node_searches", "_last_search_pose", "removed_loop_closures", "constraints",
                "_submap_index", "_finished", "stats", "_nodes_since_optimization", "_pending_closures",
                "unconfirmed_loop_closures", "_in_flight", "_running")
    NOT_EXPORTED = ("options", "pg", "timer", "loop_closure", "_solver", "builder", "submaps")  # the last two: below

    def export_data(self) -> dict:
        """Everything this graph holds but its options, timer, threads and stacks, as one picklable value: the
        graph of a process of its own handing its work back (``import_data``). Submaps go by key, not grid; the
        constraint builder as what it learnt."""
        self.settle()
        self.close()
        data = {name: getattr(self, name) for name in self.EXPORTED}
        data["submaps"] = [(e.trajectory, e.submap.index, e.global_pose, e.nodes, e.searched) for e in self.submaps]
        data["builder"] = self.builder.export_data()
        return data

    def import_data(self, data: dict, submaps: dict[int, Submap], trajectory: int) -> None:
        """Become the graph ``export_data`` gave, whose submaps of ``trajectory`` are ``submaps`` (by index) and
        whose other submaps are this graph's own."""
        data = dict(data)
        own = {(e.trajectory, e.submap.index): e.submap for e in self.submaps}
        entries = [SubmapEntry(submaps[index] if t == trajectory and index in submaps else own[(t, index)], t, pose,
                               nodes, searched) for t, index, pose, nodes, searched in data.pop("submaps")]
        self.builder.import_data(data.pop("builder"))
        for name in self.EXPORTED:
            setattr(self, name, data[name])
        self.submaps = entries

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
    def submap_global_poses(self) -> np.ndarray:
        if not self.submaps:
            return np.zeros((0, 3))
        return np.array([s.global_pose for s in self.submaps])

    def local_to_global(self, submap_index: int) -> np.ndarray:
        """The correction carrying the submap's trajectory-local frame into the map frame, via this submap."""
        entry = self.submaps[submap_index]
        return transform.compose(entry.global_pose, transform.inverse(entry.local_pose))

    # ------------------------------------------------------------------ building

    def add_odometry(self, time: float, pose: ArrayLike, trajectory: int = 0) -> None:
        """An odometry sample (tracking frame in the odometry frame); nodes get it interpolated at their time."""
        times, poses = self._odometry_samples.setdefault(trajectory, (_Growing(1), _Growing(3)))
        sample = np.asarray(pose, dtype=np.float64).reshape(3).copy()
        if times.n:
            if time <= times.array[-1, 0]:
                return  # out of order or duplicate: Cartographer drops these too
            prev = poses.array[-1, 2]
            sample[2] = transform.unwrap_angle(sample[2], prev)  # for interpolation
        times.append((float(time),))
        poses.append(sample)

    def odometry_samples(self, trajectory: int = 0) -> np.ndarray | None:
        """(n, 4) t, x, y, yaw (unwrapped) of the odometry given for ``trajectory``; None with fewer than two."""
        samples = self._odometry_samples.get(trajectory)
        if samples is None or samples[0].n < 2:
            return None
        return np.column_stack([samples[0].array[:, 0], samples[1].array])

    def node_odometry(self) -> np.ndarray:
        """(N, 3) odometry at every node: the explicit pose if one was given, else odometry interpolated
        at the node's time (Cartographer's InterpolateOdometry), NaN outside the odometry's time range."""
        samples = {t: (times.array[:, 0], poses.array) for t, (times, poses) in self._odometry_samples.items()}
        return odometry_at_nodes(self._odometry.array, self.node_times, self.node_trajectory, samples)

    def _is_key_node(self, local_pose: np.ndarray, trajectory: int) -> bool:
        cb = self.pg.constraint_builder
        if cb.min_search_distance <= 0 and cb.min_search_angle <= 0:
            return True
        last = self._last_search_pose.get(trajectory)
        if last is not None:
            moved = transform.relative(last, local_pose)
            far = cb.min_search_distance > 0 and math.hypot(moved[0], moved[1]) >= cb.min_search_distance
            turned = cb.min_search_angle > 0 and abs(moved[2]) >= cb.min_search_angle
            if not (far or turned):
                return False
        self._last_search_pose[trajectory] = local_pose
        return True

    def _register_submap(self, submap: Submap, trajectory: int, correction: np.ndarray) -> int:
        key = (trajectory, submap.index)
        index = self._submap_index.get(key)
        if index is None:
            index = len(self.submaps)
            self._submap_index[key] = index
            self.submaps.append(SubmapEntry(submap, trajectory, transform.compose(correction, submap.local_pose)))
        return index

    def close(self) -> None:
        """Stop the search and optimization threads, if any (an optimization running is finished first)."""
        self.builder.close()
        if self._solver is not None:
            self._solver.shutdown()
            self._solver = None

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
            correction = self.local_to_global(self._submap_index[front_key])
        else:
            correction = self._trajectory_correction(trajectory)
        indices = [self._register_submap(s, trajectory, correction) for s in insertion_submaps]
        self._finished.update(i for i, done in zip(indices, finished) if done)

        travel = 0.0
        for previous in range(self.num_nodes - 1, -1, -1):  # the trajectory's last node: nearly always the last
            if self.node_trajectory[previous] == trajectory:
                step = self._local.array[previous, :2] - local_pose[:2]
                travel = self.node_travel[previous] + math.hypot(step[0], step[1])
                break
        node = self._local.append(local_pose)
        self.node_travel.append(travel)
        self._global.append(transform.compose(correction, local_pose))
        self._odometry.append(np.full(3, np.nan) if odometry_pose is None else transform.as_pose(odometry_pose))
        self.node_times.append(float(time))
        self.node_trajectory.append(trajectory)
        self.node_points.append(points)
        self.node_searches.append(self._is_key_node(local_pose, trajectory))

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
                    self._search_submap_against_nodes(indices[0])
                if self.node_searches[node]:
                    self._search_node_against_submaps(node)

        self._nodes_since_optimization += 1
        n_every = self.pg.optimize_every_n_nodes
        # Without loop closure the graph holds only local-SLAM, intra-submap and odometry
        # constraints: optimizing it would only pull the trajectory towards the odometry,
        # so "local SLAM only" (--no-loop-closure) must not optimize at all.
        if self.loop_closure and n_every > 0 and self._nodes_since_optimization >= n_every:
            self._optimize_beside()
        return node

    def _trajectory_correction(self, trajectory: int) -> np.ndarray:
        for entry in reversed(self.submaps):
            if entry.trajectory == trajectory:
                return transform.compose(entry.global_pose, transform.inverse(entry.local_pose))
        return np.zeros(3)

    # ------------------------------------------------------------------ loop closure

    def _confirming_neighbours(self, node: int, submap: int) -> list[int]:
        """Up to CONFIRM_NEIGHBOURS nodes nearest to ``node`` along its trajectory, not in ``submap`` and without
        a closure to it already (a second search would only add the same constraint twice)."""
        members = set(self.submaps[submap].nodes)
        members.update(entry.node for entry in self._pending_closures.get(submap, ()))
        trajectory = self.node_trajectory[node]
        out = []
        for step in range(1, CONFIRM_MAX_NODES + 1):
            for other in (node - step, node + step):
                if (0 <= other < self.num_nodes and other not in members and self.node_trajectory[other] == trajectory
                        and len(self.node_points[other])):
                    out.append(other)
            if len(out) >= CONFIRM_NEIGHBOURS:
                break
        return out[:CONFIRM_NEIGHBOURS]

    def _add_loop_closure(self, lc: LoopClosure, confirming: bool = False) -> None:
        cb = self.pg.constraint_builder
        if not cb.confirm_loop_closures:
            self._insert_loop_closure(lc.node, lc.submap, lc.relative_pose)
            return
        # Karto's chain rule: a false match rarely repeats consistently for a neighbouring node, a true revisit
        # does. A closure waits until a closure of another node of the same trajectory, near it along the
        # trajectory, places both nodes in the submap as local SLAM places them relative to each other.
        pending = self._pending_closures.setdefault(lc.submap, [])
        agreeing = [entry for entry in pending
                    if self._closures_agree(entry.node, entry.relative, lc.node, lc.relative_pose)]
        if not agreeing and not confirming:
            # The samplers search only a share of the pairs, so the neighbours that could confirm this closure
            # may never be tried: search the nearest ones against this submap now.
            neighbours = self._confirming_neighbours(lc.node, lc.submap)
            pairs = []
            if neighbours:
                submap = self._submap_data(lc.submap)
                pairs = [(self._node_data(other), submap, False) for other in neighbours]
            for found in self.builder.search_many(pairs):
                if found is not None:
                    self._add_loop_closure(found, confirming=True)
            agreeing = [entry for entry in pending
                        if self._closures_agree(entry.node, entry.relative, lc.node, lc.relative_pose)]
        if agreeing:
            self._insert_loop_closure(lc.node, lc.submap, lc.relative_pose)
            for entry in agreeing:
                if not entry.inserted:
                    self._insert_loop_closure(entry.node, lc.submap, entry.relative)
                    entry.inserted = True
                    self.unconfirmed_loop_closures -= 1
        pending.append(PendingClosure(lc.node, lc.relative_pose, bool(agreeing)))
        self.unconfirmed_loop_closures += 0 if agreeing else 1

    def _closures_agree(self, m: int, rel_m: np.ndarray, n: int, rel_n: np.ndarray) -> bool:
        if m == n or self.node_trajectory[m] != self.node_trajectory[n] or abs(m - n) > CONFIRM_MAX_NODES:
            return False
        by_local_slam = transform.relative(self.local_poses[m], self.local_poses[n])
        by_closures = transform.relative(rel_m, rel_n)
        gap = transform.relative(by_local_slam, by_closures)
        return (math.hypot(gap[0], gap[1]) <= CONFIRM_MAX_TRANSLATION
                and abs(gap[2]) <= CONFIRM_MAX_ROTATION)

    def _insert_loop_closure(self, node: int, submap: int, relative: np.ndarray) -> None:
        cb = self.pg.constraint_builder
        self.constraints.add(submap, node, relative, cb.loop_closure_translation_weight,
                             cb.loop_closure_rotation_weight, ConstraintKind.INTER_SUBMAP)

    def _node_data(self, node: int) -> NodeData:
        return NodeData(node, self.node_trajectory[node], self.global_poses[node], self.node_points[node],
                        self.node_travel[node])

    def _submap_data(self, index: int) -> SubmapData:
        entry = self.submaps[index]
        travel = (self.node_travel[entry.nodes[0]], self.node_travel[entry.nodes[-1]]) if entry.nodes else \
            (math.nan, math.nan)
        return SubmapData(index, entry.trajectory, entry.submap.grid, entry.local_pose, entry.global_pose, travel)

    def _search_pairs(self, pairs: Iterable[tuple[NodeData, SubmapData]]) -> None:
        """Start the searches of the (NodeData, SubmapData) pairs the candidate rules pick; ``flush_searches``
        adds what they find."""
        chosen = []
        for node_data, submap_data in pairs:
            global_search = self.builder.select(node_data, submap_data)
            if global_search is not None:
                chosen.append((node_data, submap_data, global_search))
        self._in_flight.extend(self.builder.submit(chosen))

    def flush_searches(self) -> None:
        """Add the closures of every search started, in the order they were started.

        Searches run while the graph goes on taking nodes, and their closures are added only here, before each
        optimization (the only reader of the constraints) and at the end: a search needs the node's and the
        submap's poses, which change only when the graph is optimized, so it finds the same thing whenever it
        runs, and adding closures at these fixed points keeps the graph the same for any number of workers.
        """
        in_flight, self._in_flight = self._in_flight, []
        for handle in in_flight:
            lc = self.builder.record(handle)
            if lc is not None:
                self._add_loop_closure(lc)

    def _search_node_against_submaps(self, node: int) -> None:
        node_data = self._node_data(node)
        self._search_pairs((node_data, self._submap_data(index)) for index, entry in enumerate(self.submaps)
                           if index in self._finished and node not in entry.nodes)

    def _search_submap_against_nodes(self, index: int) -> None:
        entry = self.submaps[index]
        # Every earlier node is a candidate for a newly finished submap; the distance rule that rejects
        # most of them is applied to all at once here rather than per node in Python. Links between
        # trajectories only ever get added, so a node linked now is still linked when it is chosen.
        searching = np.asarray(self.node_searches, dtype=bool)
        searching[entry.nodes] = False
        traj = np.asarray(self.node_trajectory)
        linked = np.array([t == entry.trajectory or frozenset((t, entry.trajectory)) in self.builder.connected
                           for t in range(int(traj.max()) + 1)])[traj]
        offset = self.global_poses[:, :2] - entry.global_pose[:2]
        far = np.hypot(offset[:, 0], offset[:, 1]) > self.pg.constraint_builder.max_constraint_distance
        submap_data = self._submap_data(index)
        self._search_pairs((self._node_data(node), submap_data)
                           for node in np.flatnonzero(searching & ~(linked & far)).tolist())

    # ------------------------------------------------------------------ optimization

    def settle(self) -> None:
        """Take the closures of every search started, then the result of the optimization running beside the
        nodes: the graph as if everything begun were done. In that order: a search in flight reads its node's
        pose where the graph keeps it, which taking an optimization's result overwrites."""
        with self.timer.stage("loop closure"):
            self.flush_searches()
        self._land()

    def _optimize_beside(self) -> None:
        """The periodic optimization, run while the next ``optimize_every_n_nodes`` nodes are added and searched
        (as Cartographer's runs beside its constraint searches), its poses taken when the next one starts.

        Waiting for each optimization before the next node left the search threads idle for about a third of the
        graph's work (docs/scaling.md). The nodes added meanwhile, and their searches,
        use the poses of the optimization before; a search's closure is a pose in its submap's frame, so only its
        window's centre and the candidate distances see the older poses. The optimization gets a copy of the graph
        as it is when it starts and its result is taken at a fixed point, one period later, on every job count
        (one job: computed at once, taken at the same point), so the graph is the same for any number of jobs.
        """
        self.settle()
        self._nodes_since_optimization = 0
        problem = self._problem(final=False)
        if problem is None:
            return
        if self._solver is None and self.builder.jobs > 1:
            self._solver = ThreadPoolExecutor(max_workers=1, thread_name_prefix="carto-optimize")
        if self._solver is None:
            with self.timer.stage("optimization"):
                task: Any = Done(problem.solve())
            thread = None
        else:
            task = self._solver.submit(problem.solve)
            thread = self.timer.concurrent(OPTIMIZER_THREAD)
        self._running = RunningOptimization(task, self.num_nodes, len(self.submaps), thread)

    def _land(self) -> None:
        """Apply the optimization running beside the nodes, if any (waiting for it)."""
        running, self._running = self._running, None
        if running is None:
            return
        with self.timer.stage("optimization wait"):
            result, ns = running.task.result()
        if running.thread is not None:  # computed inline, it was timed where it ran
            running.thread.add("optimization", ns)
        self._apply(result, running.num_nodes, running.num_submaps)

    def optimize(self, final: bool = False) -> OptimizationSummary | None:
        self.settle()
        summary = self._optimize(final)
        limit = self.pg.constraint_builder.max_loop_closure_residual
        if final and summary is not None and limit > 0 and self.remove_bad_loop_closures(limit):
            summary = self._optimize(final)
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
        op = self.pg.optimization_problem
        traj = np.asarray(self.node_trajectory)
        local = NodePairs.consecutive(self.local_poses, traj,
                                      translation_weight=op.local_slam_pose_translation_weight,
                                      rotation_weight=op.local_slam_pose_rotation_weight)
        odom = self.node_odometry()
        odometry = None
        if np.isfinite(odom).any():
            odometry = NodePairs.consecutive(odom, traj, translation_weight=op.odometry_translation_weight,
                                             rotation_weight=op.odometry_rotation_weight)
        iterations = self.pg.max_num_final_iterations if final else op.ceres_solver_options.max_num_iterations
        return OptimizationProblem(self.global_poses.copy(), self.submap_global_poses, self.constraints.copy(),
                                   odometry, local, op.huber_scale, iterations)

    def _optimize(self, final: bool = False) -> OptimizationSummary | None:
        self._nodes_since_optimization = 0
        with self.timer.stage("optimization"):
            problem = self._problem(final)
            if problem is None:
                return None
            result, _ = problem.solve()
        return self._apply(result, self.num_nodes, len(self.submaps))

    def _apply(self, result: OptimizationResult, num_nodes: int, num_submaps: int) -> OptimizationSummary:
        """Take an optimization's poses for the first ``num_nodes`` nodes and ``num_submaps`` submaps (those it
        had); nodes and submaps added since move rigidly with their trajectory's last submap it had."""
        before = {}
        for index in range(num_submaps - 1, -1, -1):
            trajectory = self.submaps[index].trajectory
            if trajectory not in before:
                before[trajectory] = (index, self.local_to_global(index))
        self._global.array[:num_nodes] = result.node_poses
        for entry, pose in zip(self.submaps[:num_submaps], result.submap_poses):
            entry.global_pose = pose
        if self.num_nodes > num_nodes or len(self.submaps) > num_submaps:
            moves = {t: transform.compose(self.local_to_global(index), transform.inverse(old))
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

    def loop_closure_segments(self) -> np.ndarray:
        """(K, 4) node xy → submap origin xy in the map frame, for drawing."""
        mask = self.constraints.is_loop_closure
        if not mask.any():
            return np.zeros((0, 4))
        nodes = self.constraints.node[mask]
        subs = self.constraints.submap[mask]
        g = self.global_poses
        sp = self.submap_global_poses
        return np.concatenate([g[nodes, :2], sp[subs, :2]], axis=1)

    def scan_poses(self, scan_local: np.ndarray, scan_node: np.ndarray) -> np.ndarray:
        """Global poses of scans given their local poses and the latest node at or before each.

        A scan between nodes takes the correction of the node before it, which is what
        the robot would have reported at that moment had it known the optimized graph.
        """
        g = self.global_poses[scan_node]
        l = self.local_poses[scan_node]
        correction = transform.compose(g, transform.inverse(l))
        return transform.compose(correction, scan_local)

    @property
    def num_loop_closures(self) -> int:
        return int(self.constraints.num_loop_closures)


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
