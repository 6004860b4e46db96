"""The pose graph's data as one value (Cartographer's PoseGraphData): what a map file holds, what a graph restarts from.

``PoseGraph.to_state()`` and ``PoseGraph.from_state()`` are the only ways into and out of a
graph's internals; ``io/map_file.py`` turns a state into arrays and back. What is not here is
rebuilt, not restored: the constraint builder's samplers and precomputation grids, timers and
statistics.
"""
from __future__ import annotations

import copy
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core import transform
from carto_cli.core.transform import wrap_angle
from carto_cli.mapping.constraints import ConstraintSet
from carto_cli.mapping.submaps import Submap

__all__ = ["PoseGraphState", "SubmapEntry", "odometry_at_nodes"]


@dataclass
class SubmapEntry:
    """A submap in the pose graph: its grid (axis-aligned in its trajectory's local frame), where the
    optimization puts it, and the nodes inserted into it."""

    submap: Submap
    trajectory: int
    global_pose: np.ndarray
    nodes: list[int] = field(default_factory=list)
    # Finished and already searched against every earlier node: a finished submap is searched once.
    searched: bool = False

    @property
    def local_pose(self) -> np.ndarray:
        return self.submap.local_pose

    @property
    def finished(self) -> bool:
        return self.submap.finished

    def local_to_global(self) -> np.ndarray:
        """The correction carrying the submap's trajectory-local frame into the map frame, via this submap."""
        return transform.compose(self.global_pose, transform.inverse(self.local_pose))


@dataclass
class PoseGraphState:
    """Nodes, submaps and constraints of a pose graph, indexed by node id and submap id (graph order)."""

    node_times: np.ndarray  # (N,)
    node_trajectories: np.ndarray  # (N,) int64
    node_local_poses: np.ndarray  # (N, 3) in the node's trajectory's local frame
    node_global_poses: np.ndarray  # (N, 3) in the map frame
    node_odometry: np.ndarray  # (N, 3) odometry given with each node; NaN rows: interpolated from odometry_samples
    node_points: list[np.ndarray]  # loop-closure points per node, (n_i, 2) in the tracking frame
    node_searches: np.ndarray  # (N,) bool: the node is a loop-closure source (key-frame rule)
    submaps: list[SubmapEntry]
    constraints: ConstraintSet
    # trajectory → (times (T,), poses (T, 3) with the yaw unwrapped): the odometry stream nodes interpolate
    odometry_samples: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    last_search_poses: dict[int, np.ndarray] = field(default_factory=dict)  # trajectory → last key node's local pose
    connected: set[frozenset] = field(default_factory=set)  # trajectory pairs linked by a whole-submap search
    removed_loop_closures: list[tuple[int, int, float]] = field(default_factory=list)  # (node, submap, residual m)
    nodes_since_optimization: int = 0

    @classmethod
    def empty(cls) -> PoseGraphState:
        return cls(node_times=np.zeros(0), node_trajectories=np.zeros(0, np.int64),
                   node_local_poses=np.zeros((0, 3)), node_global_poses=np.zeros((0, 3)),
                   node_odometry=np.zeros((0, 3)), node_points=[], node_searches=np.zeros(0, bool),
                   submaps=[], constraints=ConstraintSet())

    @property
    def num_nodes(self) -> int:
        return int(self.node_times.shape[0])

    def odometry_at_nodes(self) -> np.ndarray:
        """(N, 3) odometry at every node, as ``PoseGraph.node_odometry`` gives it."""
        return odometry_at_nodes(self.node_odometry, self.node_times, self.node_trajectories, self.odometry_samples)

    def without_submaps(self, drop: np.ndarray) -> PoseGraphState:
        """This state without the submaps ``drop`` marks (a bool per submap), their constraints, and the nodes left
        in no submap; nodes and submaps renumbered in their order (the first submap kept is the one the optimizer
        holds). Grids and node points are shared with this state."""
        drop = np.asarray(drop, dtype=bool).reshape(len(self.submaps))
        kept = np.zeros(self.num_nodes, bool)
        for entry, gone in zip(self.submaps, drop):
            if not gone:
                kept[np.asarray(entry.nodes, dtype=np.int64)] = True
        node_id = np.cumsum(kept) - 1  # new id of a kept node
        submap_id = np.cumsum(~drop) - 1
        cs = self.constraints
        live = kept[cs.node] & ~drop[cs.submap]
        constraints = ConstraintSet.from_arrays(submap_id[cs.submap[live]], node_id[cs.node[live]],
                                                cs.relative[live], cs.translation_weight[live],
                                                cs.rotation_weight[live], cs.is_loop_closure[live])
        submaps = [SubmapEntry(e.submap, e.trajectory, e.global_pose.copy(), node_id[np.asarray(e.nodes, dtype=np.int64)
                                                                                     ].tolist(), e.searched)
                   for e, gone in zip(self.submaps, drop) if not gone]
        trajectories = {int(t) for t in self.node_trajectories[kept]}
        index = np.flatnonzero(kept)
        return PoseGraphState(
            node_times=self.node_times[kept], node_trajectories=self.node_trajectories[kept],
            node_local_poses=self.node_local_poses[kept], node_global_poses=self.node_global_poses[kept],
            node_odometry=self.node_odometry[kept], node_points=[self.node_points[i] for i in index.tolist()],
            node_searches=self.node_searches[kept], submaps=submaps, constraints=constraints,
            odometry_samples=_renumbered_samples(self, kept),
            last_search_poses={t: p for t, p in self.last_search_poses.items() if t in trajectories},
            connected={pair for pair in self.connected if set(pair) <= trajectories},
            removed_loop_closures=[(int(node_id[n]), int(submap_id[s]), r) for n, s, r in self.removed_loop_closures
                                   if kept[n] and not drop[s]],
            nodes_since_optimization=self.nodes_since_optimization)

    def copy(self) -> PoseGraphState:
        """A state sharing nothing mutable with this one (grids included)."""
        submaps = []
        for entry in self.submaps:
            submap = copy.copy(entry.submap)
            submap.local_pose = entry.submap.local_pose.copy()
            submap.grid = entry.submap.grid.copy()
            submaps.append(SubmapEntry(submap, int(entry.trajectory), np.array(entry.global_pose, dtype=np.float64),
                                       [int(v) for v in entry.nodes], bool(entry.searched)))
        return PoseGraphState(
            node_times=np.array(self.node_times, dtype=np.float64),
            node_trajectories=np.array(self.node_trajectories, dtype=np.int64),
            node_local_poses=np.array(self.node_local_poses, dtype=np.float64),
            node_global_poses=np.array(self.node_global_poses, dtype=np.float64),
            node_odometry=np.array(self.node_odometry, dtype=np.float64),
            node_points=[p.copy() for p in self.node_points],
            node_searches=np.array(self.node_searches, dtype=bool),
            submaps=submaps,
            constraints=self.constraints.copy(),
            odometry_samples={t: (times.copy(), poses.copy()) for t, (times, poses) in self.odometry_samples.items()},
            last_search_poses={t: pose.copy() for t, pose in self.last_search_poses.items()},
            connected=set(self.connected),
            removed_loop_closures=list(self.removed_loop_closures),
            nodes_since_optimization=self.nodes_since_optimization,
        )


def _renumbered_samples(state: PoseGraphState, kept: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """The odometry streams of the trajectories that keep nodes, cut to the span of those nodes (one sample either
    side, for interpolation)."""
    out = {}
    for trajectory, (times, poses) in state.odometry_samples.items():
        mine = state.node_times[kept & (state.node_trajectories == trajectory)]
        if not len(mine) or not len(times):
            continue
        lo = max(int(np.searchsorted(times, mine.min(), side="right")) - 1, 0)
        hi = min(int(np.searchsorted(times, mine.max(), side="left")) + 1, len(times))
        out[trajectory] = (times[lo:hi], poses[lo:hi])
    return out


def odometry_at_nodes(node_odometry: np.ndarray, node_times: ArrayLike, node_trajectories: ArrayLike,
                      samples: dict[int, tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """(N, 3) odometry at every node: the node's own pose if it was given one, else the trajectory's odometry
    ``samples`` interpolated at the node's time (Cartographer's InterpolateOdometry), NaN outside their range."""
    odom = node_odometry.copy()
    if not samples:
        return odom
    node_times = np.asarray(node_times)
    node_traj = np.asarray(node_trajectories)
    for trajectory, (t, p) in samples.items():
        if len(t) < 1:
            continue
        want = np.flatnonzero((node_traj == trajectory) & np.isnan(odom[:, 0]))
        if not len(want):
            continue
        nt = node_times[want]
        inside = (nt >= t[0]) & (nt <= t[-1])
        want, nt = want[inside], nt[inside]
        if not len(want):
            continue
        if len(t) == 1:
            odom[want] = p[0]
            continue
        hi = np.clip(np.searchsorted(t, nt, side="left"), 1, len(t) - 1)
        lo = hi - 1
        f = ((nt - t[lo]) / (t[hi] - t[lo]))[:, None]
        out = p[lo] + f * (p[hi] - p[lo])
        out[:, 2] = wrap_angle(out[:, 2])
        odom[want] = out
    return odom
