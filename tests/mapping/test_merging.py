"""mapping.merging: saved graphs appended with their ids renumbered, placed by the link rule; a map of several
trajectories moves as one."""
import math

import numpy as np

from carto_cli.core import transform
from carto_cli.io.map_file import load_map
from carto_cli.mapping.merging import append_state, key_nodes, merge_states
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.sessions import linked_to, session_links
from carto_cli.mapping.submaps import Submap
from carto_cli.options import load_options


def _toy(trajectories: list[int], nodes: int = 3) -> PoseGraph:
    graph = PoseGraph(load_options(None))
    for t in trajectories:
        submap = Submap((0.0, 0.0), index=0)
        for i in range(nodes):
            graph.add_node(10.0 * t + i, (0.1 * i, 0.0, 0.0), np.zeros((0, 2)), [submap], trajectory=t)
    return graph


def test_append_renumbers_trajectories_nodes_and_submaps():
    base, other = _toy([0]).to_state(), _toy([0, 2]).to_state()
    other.connected = {frozenset((0, 2))}
    merged, renumber = append_state(base, other)
    assert renumber == {0: 1, 2: 2}
    assert merged.node_trajectories.tolist() == [0] * 3 + [1] * 3 + [2] * 3
    assert [e.trajectory for e in merged.submaps] == [0, 1, 2]
    assert merged.submaps[2].nodes == [6, 7, 8]
    # Each constraint keeps its node in its submap: the appended ones moved by the base's counts
    assert merged.constraints.node.tolist()[len(base.constraints):] == (other.constraints.node + 3).tolist()
    assert merged.constraints.submap.tolist()[len(base.constraints):] == (other.constraints.submap + 1).tolist()
    assert merged.connected == {frozenset((1, 2))}  # the appended map's own link, and none to the base
    assert merged.constraints.num_loop_closures == 0


def test_key_nodes_follow_the_mapping_rule():
    options = load_options(None, ["pose_graph.constraint_builder.min_search_distance=1.0"])
    poses = np.array([[0.0, 0, 0], [0.5, 0, 0], [1.2, 0, 0], [1.5, 0, 0], [0.0, 0, 0]])
    assert key_nodes(options, poses, np.array([0, 0, 0, 0, 1])).tolist() == [True, False, True, False, True]


def test_a_map_of_two_trajectories_is_placed_as_one(merge_parts):
    """Part 0, then part 0 and part 1 already merged: the appended pair (linked to each other) lands together,
    part 1 where it lies against the first part 0."""
    (a, b), _ = merge_parts
    states = [load_map(d / "map.carto").to_state() for d in (a, a, b)]
    options = load_map(a / "map.carto").options
    pair = merge_states(options, states[1:], jobs=1).graph.to_state()
    merged = merge_states(options, [states[0], pair], jobs=1)
    assert merged.trajectories == [{0: 0}, {0: 1, 1: 2}]
    graph = merged.graph
    assert linked_to(0, session_links(graph)) == {0, 1, 2}
    # The copy of part 0 lies on part 0, node for node
    own = np.asarray(graph.node_trajectory)
    gap = graph.global_poses[own == 1] - graph.global_poses[own == 0]
    assert np.max(np.hypot(gap[:, 0], gap[:, 1])) < 0.05
    # and part 1 where merging it alone to part 0 puts it
    alone = merge_states(options, [load_map(d / "map.carto").to_state() for d in (a, b)], jobs=1).graph
    first = np.flatnonzero(own == 2)[0]
    shift = transform.relative(alone.global_poses[np.flatnonzero(np.asarray(alone.node_trajectory) == 1)[0]],
                               graph.global_poses[first])
    assert math.hypot(shift[0], shift[1]) < 0.05 and abs(shift[2]) < math.radians(0.5)
