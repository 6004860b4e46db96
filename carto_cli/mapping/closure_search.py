"""Which node-submap pairs the pose graph's loop-closure search tries, and in what order what it finds comes back.

A node searches the finished submaps it is not in when it is a key node (``min_search_distance`` /
``min_search_angle`` since its trajectory's last key node); a newly finished submap is searched by every earlier
key node not in it. The constraint builder's candidate rules pick among those pairs and run the searches, on
threads; their closures are handed back (:meth:`ClosureSearches.flush`) only before each optimization (the only
reader of the constraints) and at the end. A search needs the node's and the submap's poses, which change only
when the graph is optimized, so it finds the same thing whenever it runs, and handing closures back at these
fixed points keeps the graph the same for any number of workers.

This object reads the nodes and submaps through :class:`GraphView` and never changes the graph; it holds only
the searches started and each trajectory's last key node, so it pickles with the graph's data (a graph run in
a process of its own hands it back).
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from typing import Any, Protocol

import numpy as np

from carto_cli.core import transform
from carto_cli.mapping.constraint_builder import ConstraintBuilder, LoopClosure, NodeData, SubmapData
from carto_cli.mapping.pose_graph_state import SubmapEntry
from carto_cli.options.schema import ConstraintBuilder as ConstraintBuilderOptions

__all__ = ["ClosureSearches", "GraphView", "node_data_of", "submap_data_of"]


class GraphView(Protocol):
    """What the searches read of the pose graph."""

    node_trajectory: list[int]
    node_points: list[np.ndarray]
    node_travel: list[float]  # local-SLAM path length from the node's trajectory's start (m)
    node_searches: list[bool]  # whether a node is a loop-closure source (key-node rule)
    submaps: list[SubmapEntry]

    @property
    def global_poses(self) -> np.ndarray: ...


class ClosureSearches:
    def __init__(self) -> None:
        self.in_flight: list[Any] = []  # searches started, in order, whose closures are not yet handed back
        self.last_search_pose: dict[int, np.ndarray] = {}  # trajectory → local pose of its last key node

    def is_key_node(self, options: ConstraintBuilderOptions, local_pose: np.ndarray, trajectory: int) -> bool:
        """Whether a node at ``local_pose`` searches (and becomes its trajectory's last key node)."""
        if options.min_search_distance <= 0 and options.min_search_angle <= 0:
            return True
        last = self.last_search_pose.get(trajectory)
        if last is not None:
            moved = transform.relative(last, local_pose)
            far = options.min_search_distance > 0 and math.hypot(moved[0], moved[1]) >= options.min_search_distance
            turned = options.min_search_angle > 0 and abs(moved[2]) >= options.min_search_angle
            if not (far or turned):
                return False
        self.last_search_pose[trajectory] = local_pose
        return True

    def search_node(self, builder: ConstraintBuilder, graph: GraphView, node: int, finished: set[int]) -> None:
        """Start the searches of ``node`` against the ``finished`` submaps it is not in."""
        node_data = node_data_of(graph, node)
        self._start(builder, ((node_data, submap_data_of(graph, index)) for index, entry in enumerate(graph.submaps)
                              if index in finished and node not in entry.nodes))

    def search_submap(self, builder: ConstraintBuilder, graph: GraphView, index: int,
                      max_constraint_distance: float, among: np.ndarray | None = None) -> None:
        """Start the searches of every earlier key node not in submap ``index`` (newly finished) against it;
        ``among``: (N,) bool, only these nodes (a merge searches another map's nodes, not the submap's own)."""
        entry = graph.submaps[index]
        # The distance rule that rejects most of them is applied to all at once here rather than per node in
        # Python. Links between trajectories only ever get added, so a node linked now is still linked when it is
        # chosen.
        searching = np.asarray(graph.node_searches, dtype=bool)
        if among is not None:
            searching &= among
        searching[entry.nodes] = False
        traj = np.asarray(graph.node_trajectory)
        linked = np.array([t == entry.trajectory or frozenset((t, entry.trajectory)) in builder.connected
                           for t in range(int(traj.max()) + 1)])[traj]
        offset = graph.global_poses[:, :2] - entry.global_pose[:2]
        far = np.hypot(offset[:, 0], offset[:, 1]) > max_constraint_distance
        submap_data = submap_data_of(graph, index)
        self._start(builder, ((node_data_of(graph, node), submap_data)
                              for node in np.flatnonzero(searching & ~(linked & far)).tolist()))

    def _start(self, builder: ConstraintBuilder, pairs: Iterable[tuple[NodeData, SubmapData]]) -> None:
        chosen = []
        for node_data, submap_data in pairs:
            global_search = builder.select(node_data, submap_data)
            if global_search is not None:
                chosen.append((node_data, submap_data, global_search))
        self.in_flight.extend(builder.submit(chosen))

    def flush(self, builder: ConstraintBuilder) -> Iterator[LoopClosure]:
        """The closures of every search started, in the order they were started, each recorded by the builder as
        it is taken (the caller may search more between two)."""
        in_flight, self.in_flight = self.in_flight, []
        for handle in in_flight:
            lc = builder.record(handle)
            if lc is not None:
                yield lc


def node_data_of(graph: GraphView, node: int) -> NodeData:
    """What a search needs of ``node``."""
    return NodeData(node, graph.node_trajectory[node], graph.global_poses[node], graph.node_points[node],
                    graph.node_travel[node])


def submap_data_of(graph: GraphView, index: int) -> SubmapData:
    """What a search needs of submap ``index``."""
    entry = graph.submaps[index]
    travel = (graph.node_travel[entry.nodes[0]], graph.node_travel[entry.nodes[-1]]) if entry.nodes else \
        (math.nan, math.nan)
    return SubmapData(index, entry.trajectory, entry.submap.grid, entry.local_pose, entry.global_pose, travel)
