"""A map of several sessions shown as last seen, with what later sessions superseded trimmed (mapping.lifelong):
the loop building mapped once, then again after a door was closed, a room's back wall moved and a cabinet taken
away (sim.world.rearranged_loop_building)."""
import numpy as np
import pytest

from carto_cli.evaluation.changes import score_changes
from carto_cli.grid.occupancy_image import AssembledImage
from carto_cli.mapping.alignment import Align
from carto_cli.mapping.lifelong import SURE, SessionPolicy, last_seen
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.options import load_options
from carto_cli.pipeline import Auto, MapRequest, map_sessions
from carto_cli.sim.sessions import route_sessions
from carto_cli.sim.world import rearranged_loop_building


@pytest.fixture(scope="module")
def rearranged():
    """The two sessions mapped keeping both (the old fusion), and the same graph as last seen."""
    before, after = rearranged_loop_building()
    recordings, references = route_sessions([before, after], 2)
    # Uncleaned: what fusing alone draws (cleaning, on by default, also wipes the walls a later session saw through)
    fused = map_sessions(MapRequest(recordings[0], Auto(), later=(recordings[1],), sessions=SessionPolicy.FUSE,
                                    clean=False, align=Align.NONE))
    assert fused.graph is not None and [s.linked for s in fused.sessions] == [True, True]
    state = fused.graph.to_state()
    last = [e for e in state.submaps if e.trajectory == 1]
    seen_last = AssembledImage([e.submap.grid for e in last], [e.local_to_global() for e in last])
    return before, after, references[0][0, 1:], fused, state, last_seen(state, [0, 1]), seen_last


def test_changed_cells_show_the_last_session(rearranged):
    before, after, start, fused, _, seen, seen_last = rearranged
    old = score_changes(fused.image, before, after, alignment=start, observed=seen_last, sure=SURE)
    new = score_changes(seen.image, before, after, alignment=start, observed=seen_last, sure=SURE)
    assert new.appeared >= 40 and new.vanished >= 20  # the door and the moved wall appeared, the cabinet vanished
    assert new.changed_shown >= 0.95, new
    assert old.changed_shown < 0.9, old  # fusing both sessions shows the old walls where they were (0.83)


def test_walls_that_stayed_are_still_drawn(rearranged):
    before, after, start, fused, _, seen, _ = rearranged
    old = score_changes(fused.image, before, after, alignment=start)
    new = score_changes(seen.image, before, after, alignment=start)
    assert new.unchanged_shown >= 0.93 * old.unchanged_shown, (old, new)


def test_superseded_submaps_are_trimmed_and_the_rest_renumbered(rearranged):
    _, _, _, _, state, seen, _ = rearranged
    trimmed = seen.state
    assert [x.trajectory for x in seen.trimmed] == [0] and seen.trimmed[0].superseded_by == (1,)
    gone = seen.trimmed[0]
    assert len(trimmed.submaps) == len(state.submaps) - gone.submaps
    assert trimmed.num_nodes == state.num_nodes - gone.nodes
    # The newest session loses nothing; every kept node is in a kept submap and keeps its pose
    newest = state.node_trajectories == 1
    assert np.count_nonzero(trimmed.node_trajectories == 1) == np.count_nonzero(newest)
    members = np.concatenate([np.asarray(e.nodes) for e in trimmed.submaps])
    assert set(members.tolist()) == set(range(trimmed.num_nodes))
    by_time = {float(t): i for i, t in enumerate(state.node_times)}
    old = np.array([by_time[float(t)] for t in trimmed.node_times])
    np.testing.assert_array_equal(trimmed.node_global_poses, state.node_global_poses[old])
    cs = trimmed.constraints
    assert len(cs) and cs.node.max() < trimmed.num_nodes and cs.submap.max() < len(trimmed.submaps)
    # Each constraint still joins the same node and submap (the submap known by its trajectory and index)
    key = [(e.trajectory, e.submap.index) for e in trimmed.submaps]
    was = {(int(state.node_times[n]), (state.submaps[s].trajectory, state.submaps[s].submap.index))
           for n, s in zip(state.constraints.node.tolist(), state.constraints.submap.tolist())}
    assert all((int(trimmed.node_times[n]), key[s]) in was for n, s in zip(cs.node.tolist(), cs.submap.tolist()))
    # The trimmed state makes a graph again, every pose where it was
    graph = PoseGraph.from_state(load_options(), trimmed)
    np.testing.assert_array_equal(graph.global_poses, trimmed.node_global_poses)


def test_nothing_is_trimmed_when_the_later_session_saw_little(rearranged):
    _, _, _, _, state, _, _ = rearranged
    # The newest session's first submap alone covers too little of the first session's to supersede any of it
    keep = [e for e in state.submaps if e.trajectory == 0 or e.submap.index == 0]
    partial = state.without_submaps(np.array([e not in keep for e in state.submaps]))
    seen = last_seen(partial, [0, 1])
    covered = [x.submaps for x in seen.trimmed]
    assert sum(covered) < sum(1 for e in partial.submaps if e.trajectory == 0)


def test_last_seen_without_trimming_keeps_every_wall_and_shows_the_changes(rearranged):
    """The default for several sessions: the newest sure evidence draws, nothing is removed."""
    before, after, start, fused, state, _, seen_last = rearranged
    seen = last_seen(state, [0, 1], trim=False)
    assert seen.trimmed == () and len(seen.state.submaps) == len(state.submaps)
    known = np.isfinite(fused.image.probability)
    assert np.count_nonzero(np.isfinite(seen.image.probability)) == np.count_nonzero(known)
    old = score_changes(fused.image, before, after, alignment=start, observed=seen_last, sure=SURE)
    new = score_changes(seen.image, before, after, alignment=start, observed=seen_last, sure=SURE)
    assert new.changed_shown >= 0.95 > old.changed_shown, (old, new)  # 1.0 against 0.83
    assert new.unchanged_shown >= old.unchanged_shown - 0.005, (old, new)  # the same 99.4 %
