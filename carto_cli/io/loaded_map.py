"""What a saved map holds once read, whatever file it came from: :class:`LoadedMap` and its :class:`MapMetadata`.

``io/map_file.py`` reads map.carto into one, ``io/pbstream.py`` Cartographer's ``.pbstream``, ``io/map_server.py`` a
map_server image; relocalization, rendering and ``carto map --load-state`` take it from any of them. Its own module,
so that the readers depend on it and not on each other.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carto_cli.io.trajectory import Trajectory
from carto_cli.mapping.cleaning import Transients
from carto_cli.mapping.constraints import ConstraintSet
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.pose_graph_state import PoseGraphState, SubmapEntry
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options

__all__ = ["LoadedMap", "MapMetadata"]


@dataclass(frozen=True)
class MapMetadata:
    format_version: int
    carto_version: str
    created: str  # ISO 8601, UTC
    recordings: tuple[str, ...]
    laser_pose_source: str | None = None
    scan_topic: str | None = None
    stats: dict = field(default_factory=dict)  # the MapResult's stats, when saved from one


@dataclass(eq=False)
class LoadedMap:
    """A map file's contents. Arrays are indexed by node id / submap id of the saved graph."""

    path: Path
    options: Options
    metadata: MapMetadata
    submaps: list[Submap]
    submap_trajectories: np.ndarray  # (M,) int64
    submap_global_poses: np.ndarray  # (M, 3)
    submap_nodes: list[np.ndarray]  # node ids inserted into each submap
    node_times: np.ndarray  # (N,)
    node_trajectories: np.ndarray  # (N,) int64
    node_local_poses: np.ndarray  # (N, 3)
    node_global_poses: np.ndarray  # (N, 3)
    node_odometry: np.ndarray  # (N, 3), NaN rows where a node had no odometry
    node_points: list[np.ndarray]  # loop-closure points per node, (n_i, 2) tracking frame
    constraints: ConstraintSet
    trajectory: Trajectory | None  # every posed scan, in the map frame; None when not saved
    node_scans: np.ndarray | None  # (N,) index into ``trajectory`` of each node, when known
    laser_pose: np.ndarray | None  # (3,) laser in the tracking frame, when known
    ignored_options: tuple[str, ...] = ()  # option keys in the file this carto does not know
    transients: Transients | None = None  # what cleaning drew free in the map as written (mapping.cleaning)

    @property
    def num_nodes(self) -> int:
        return int(self.node_times.shape[0])

    @property
    def num_submaps(self) -> int:
        return len(self.submaps)

    @property
    def next_trajectory_id(self) -> int:
        """The id a trajectory added to this map should take."""
        ids = np.concatenate([self.node_trajectories, self.submap_trajectories])
        return int(ids.max()) + 1 if ids.size else 0

    def to_state(self) -> PoseGraphState:
        """The saved graph as a state, sharing this object's arrays (``PoseGraph.from_state`` copies them).

        What the file does not hold is set as it was when the map was finished: every node was a
        loop-closure source, every finished submap was searched against every node, and trajectory
        pairs joined by a loop closure are linked.
        """
        submaps = [SubmapEntry(submap, int(self.submap_trajectories[i]), self.submap_global_poses[i],
                               [int(v) for v in self.submap_nodes[i]], searched=bool(submap.finished))
                   for i, submap in enumerate(self.submaps)]
        return PoseGraphState(
            node_times=self.node_times, node_trajectories=self.node_trajectories,
            node_local_poses=self.node_local_poses, node_global_poses=self.node_global_poses,
            node_odometry=self.node_odometry, node_points=self.node_points,
            node_searches=np.ones(self.num_nodes, dtype=bool), submaps=submaps, constraints=self.constraints,
            connected=_linked_trajectories(self.constraints, self.node_trajectories, self.submap_trajectories))

    def to_pose_graph(self, options: Options | None = None, *, timer=None, loop_closure: bool = True,
                      seed: int = 0) -> PoseGraph:
        """A PoseGraph holding these nodes, submaps and constraints, ready for a new trajectory.

        The graph owns copies: building on it never changes this object, and two graphs made
        from one LoadedMap are independent. ``options`` defaults to the map's own.
        """
        return PoseGraph.from_state(self.options if options is None else options, self.to_state(), timer=timer,
                                    loop_closure=loop_closure, seed=seed)


def _linked_trajectories(cs: ConstraintSet, node_trajectories: np.ndarray,
                         submap_trajectories: np.ndarray) -> set[frozenset]:
    linked: set[frozenset] = set()
    if len(cs):
        loops = cs.is_loop_closure
        node_traj = np.asarray(node_trajectories, dtype=np.int64)[cs.node[loops]]
        sub_traj = np.asarray(submap_trajectories, dtype=np.int64)[cs.submap[loops]]
        for a, b in set(zip(node_traj.tolist(), sub_traj.tolist())):
            if a != b:
                linked.add(frozenset((a, b)))
    return linked
