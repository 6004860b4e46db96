"""Maps made separately (other robots, other days) into one pose graph, without their recordings (``carto merge``).

Each map's graph state is appended to the ones before it with its trajectories, node ids and submap indices
renumbered after theirs (:func:`append_state`). An appended map keeps its own trajectories' local frames, and its
global poses lie in its own map frame, unrelated to the first's: its trajectories are linked to nothing. They are
placed as ``carto map A B`` places a later recording: whole-map searches between the appended map's key nodes and
the earlier maps' finished submaps, and the earlier maps' key nodes against the appended map's submaps, all through
the pose graph's link rule (closures from two places that agree, a first one checked at once where it puts the
session, the session moved there). Once every appended trajectory is linked, the pairs are searched again within
their windows (the closures that join the maps along their whole overlap), and one final optimization settles the
joint graph. Knows no file: ``pipeline.merge_maps`` hands it the states.

Cost: a whole-map search is one branch and bound over a whole submap. The appended nodes are taken in batches
along their trajectories, only key nodes (``min_search_distance`` / ``min_search_angle``, the rule mapping uses)
and only the pairs the constraint builder's whole-map sampler picks (``global_sampling_ratio``), and the searches
stop as soon as every appended trajectory is linked.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.mapping.closure_search import ClosureSearches
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.pose_graph_state import PoseGraphState, SubmapEntry
from carto_cli.options import Options

__all__ = ["MergedGraph", "append_state", "key_nodes", "merge_states"]

# Appended nodes searched between two looks at whether they are linked yet (the closures of a batch are taken
# together, as mapping takes them before each periodic optimization)
BATCH_NODES = 90


@dataclass(eq=False)
class MergedGraph:
    """The joint graph, and for each map merged the graph's trajectory id of each of its own (by its own id)."""

    graph: PoseGraph
    trajectories: list[dict[int, int]]


def _trajectory_ids(state: PoseGraphState) -> list[int]:
    return sorted({int(t) for t in state.node_trajectories} | {e.trajectory for e in state.submaps})


def append_state(base: PoseGraphState, other: PoseGraphState) -> tuple[PoseGraphState, dict[int, int]]:
    """``other`` after ``base`` in one state: its trajectories numbered after ``base``'s (in their order), its node
    ids and submap indices after ``base``'s; and the id each of ``other``'s trajectories got. The two share no
    constraint and no link. Grids and node points are shared with the inputs, as ``PoseGraph.to_state`` shares
    them (``PoseGraph.from_state`` copies)."""
    ids = _trajectory_ids(base)
    start = ids[-1] + 1 if ids else 0
    renumber = {t: start + k for k, t in enumerate(_trajectory_ids(other))}
    nodes, submaps = base.num_nodes, len(base.submaps)
    constraints = base.constraints.copy()
    oc = other.constraints
    if len(oc):
        constraints.extend(oc.submap + submaps, oc.node + nodes, oc.relative, oc.translation_weight,
                           oc.rotation_weight, oc.is_loop_closure)
    appended = [SubmapEntry(e.submap, renumber[e.trajectory], np.array(e.global_pose, dtype=np.float64),
                            [n + nodes for n in e.nodes], e.searched) for e in other.submaps]
    merged = PoseGraphState(
        node_times=np.concatenate([base.node_times, other.node_times]).astype(np.float64),
        node_trajectories=np.concatenate([
            base.node_trajectories,
            np.array([renumber[int(t)] for t in other.node_trajectories], dtype=np.int64)]).astype(np.int64),
        node_local_poses=np.concatenate([base.node_local_poses, other.node_local_poses]).reshape(-1, 3),
        node_global_poses=np.concatenate([base.node_global_poses, other.node_global_poses]).reshape(-1, 3),
        node_odometry=np.concatenate([base.node_odometry, other.node_odometry]).reshape(-1, 3),
        node_points=list(base.node_points) + list(other.node_points),
        node_searches=np.concatenate([base.node_searches, other.node_searches]).astype(bool),
        submaps=list(base.submaps) + appended,
        constraints=constraints,
        odometry_samples=dict(base.odometry_samples) | {renumber[t]: v for t, v in other.odometry_samples.items()},
        last_search_poses=dict(base.last_search_poses) | {renumber[t]: v for t, v in other.last_search_poses.items()},
        connected=set(base.connected) | {frozenset(renumber[t] for t in pair) for pair in other.connected},
        removed_loop_closures=list(base.removed_loop_closures) + [(n + nodes, s + submaps, r)
                                                                  for n, s, r in other.removed_loop_closures],
    )
    return merged, renumber


def key_nodes(options: Options, local_poses: np.ndarray, trajectories: np.ndarray) -> np.ndarray:
    """(N,) bool: the nodes that search for loop closures by mapping's key-node rule (``min_search_distance`` /
    ``min_search_angle`` since their trajectory's last key node), in node order. A saved map does not keep them
    (``LoadedMap.to_state`` takes every node): a merge searches what mapping would have."""
    rule = ClosureSearches()
    cb = options.pose_graph.constraint_builder
    return np.array([rule.is_key_node(cb, local_poses[i], int(trajectories[i])) for i in range(len(local_poses))],
                    dtype=bool).reshape(len(local_poses))


def merge_states(options: Options, states: Sequence[PoseGraphState], *, timer: StageTimer | NullTimer | None = None,
                 jobs: int | None = 1, on_total: Callable[[int], None] | None = None,
                 on_nodes: Callable[[int], None] | None = None) -> MergedGraph:
    """``states`` (each a map's graph) into one graph, in order: the first fixes the map frame, each later one is
    appended and placed by loop-closure search against the ones before it (module doc), then the final
    optimization. Every submap is finished first (a saved map's last ones may not be: its recording is over, and a
    whole-map search matches only finished submaps), in ``states`` themselves. ``on_total`` hears how many
    appended key nodes there are to search (each twice: whole-map until linked, then windowed), ``on_nodes`` each
    batch done (the whole-map pass's rest at once when it stops early)."""
    if not states:
        raise ValueError("no map to merge")
    for state in states:
        for entry in state.submaps:
            if not entry.finished:
                entry.submap.finish()
    merged, renumbers = states[0], [{t: t for t in _trajectory_ids(states[0])}]
    for state in states[1:]:
        merged, renumber = append_state(merged, state)
        renumbers.append(renumber)
    merged.node_searches = key_nodes(options, merged.node_local_poses, merged.node_trajectories)
    graph = PoseGraph.from_state(options, merged, timer=timer, jobs=jobs)
    appended = np.isin(merged.node_trajectories, [t for r in renumbers[1:] for t in r.values()])
    if on_total is not None:
        on_total(2 * int(np.count_nonzero(appended & merged.node_searches)))
    try:
        earlier: set[int] = set(renumbers[0].values())
        for renumber in renumbers[1:]:
            own = set(renumber.values())
            _join(graph, own, earlier, on_nodes or (lambda n: None))
            earlier |= own
        graph.optimize(final=True)
    finally:
        graph.close()
    return MergedGraph(graph, renumbers)


def _linked(graph: PoseGraph, own: set[int], earlier: set[int]) -> bool:
    """Whether every trajectory of ``own`` is linked, directly or through others, to one of ``earlier``."""
    reached = set(earlier)
    grew = True
    while grew:
        grew = False
        for pair in graph.builder.connected:
            if len(pair & reached) == 1:
                reached |= pair
                grew = True
    return own <= reached


def _join(graph: PoseGraph, own: set[int], earlier: set[int], on_nodes: Callable[[int], None]) -> None:
    """Place the appended trajectories ``own`` against ``earlier``'s (module doc)."""
    traj = np.asarray(graph.node_trajectory)
    searching = np.asarray(graph.node_searches, dtype=bool)
    mine = np.isin(traj, sorted(own))
    theirs = np.isin(traj, sorted(earlier)) & searching
    own_nodes = np.flatnonzero(mine & searching).tolist()
    own_submaps = [i for i, e in enumerate(graph.submaps) if e.trajectory in own]
    earlier_submaps = {i for i in graph.finished_submaps if graph.submaps[i].trajectory in earlier}
    # A submap of the appended map is "finished" for the other way round once the batch holding its last node is
    # searched, as mapping finishes it while its trajectory goes on
    last_node = {i: max(graph.submaps[i].nodes, default=-1) for i in own_submaps}
    reach = graph.pg.constraint_builder.max_constraint_distance
    cb, searches = graph.builder, graph.searches

    def search(nodes: list[int], submaps: list[int]) -> None:
        with graph.timer.stage("loop closure"):
            for node in nodes:
                searches.search_node(cb, graph, node, earlier_submaps)
            for index in submaps:
                searches.search_submap(cb, graph, index, reach, among=theirs)
        graph.settle()

    done: set[int] = set()
    for start in range(0, len(own_nodes), BATCH_NODES):
        if _linked(graph, own, earlier):
            break
        batch = own_nodes[start:start + BATCH_NODES]
        ready = [i for i in own_submaps if i not in done and last_node[i] <= batch[-1]]
        done.update(ready)
        search(batch, ready)
        on_nodes(len(batch))
    else:
        start = len(own_nodes)
    on_nodes(len(own_nodes) - min(start, len(own_nodes)))  # the whole-map pass stopped early: its rest is skipped
    if not _linked(graph, own, earlier):
        search([], [i for i in own_submaps if i not in done])
    # Linked: the whole overlap again, within the windows around where the link put the appended map (the whole-map
    # searches before sampled a few pairs); a trajectory still unlinked is left alone (its pairs would be whole-map
    # searches once more)
    still = {t for t in own if not _linked(graph, {t}, earlier)}
    again_nodes = [n for n in own_nodes if graph.node_trajectory[n] not in still]
    again_submaps = [i for i in own_submaps if graph.submaps[i].trajectory not in still]
    search(again_nodes, again_submaps)
    on_nodes(len(own_nodes))
