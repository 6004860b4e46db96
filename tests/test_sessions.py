"""Several recordings of one building into one map (pipeline.map_sessions): each later session, started anywhere
with its odometry at zero, is placed by whole-map search, its closures confirmed before it is linked; a recording
of another building is linked to nothing, reported, and kept out of the map."""
import math

import numpy as np
import pytest

from carto_cli.core import transform
from carto_cli.evaluation.metrics import align_se2
from carto_cli.pipeline import Auto, MapRequest, map_sessions
from carto_cli.sim.sessions import cut_sessions, route_sessions
from carto_cli.sim.world import loop_building, room

OPTIONS = Auto()  # what `carto map A B` does


@pytest.fixture(scope="module")
def two():
    """The loop building driven twice: the second session from the opposite corner, the other way round."""
    recordings, references = route_sessions(loop_building(), 2)
    return recordings, references, map_sessions(MapRequest(recordings[0], OPTIONS, later=(recordings[1],)))


def test_a_later_session_is_linked_and_placed_where_it_was(two):
    _, references, result = two
    assert result.quality is not None and result.quality.ok, result.quality.line()
    assert [s.linked for s in result.sessions] == [True, True]
    assert [s.trajectory for s in result.sessions] == [0, 1] and result.sessions[1].name.endswith(".part0")
    (link,) = result.links
    assert (link.a, link.b) == (0, 1) and link.closures >= 5
    # The truth: where session 1's first pose lies seen from session 0's first pose (each frame starts there)
    g0, g1 = references[0][0, 1:], references[1][0, 1:]
    truth = transform.compose(transform.inverse(g0), g1)
    e0, e1 = result.sessions[0].poses[0], result.sessions[1].poses[0]
    got = transform.compose(transform.inverse(e0), e1)
    gap = transform.relative(truth, got)
    assert math.hypot(gap[0], gap[1]) < 0.1 and abs(math.degrees(gap[2])) < 1.0
    # Both sessions in one frame: one alignment for both puts every scan near its reference
    est = np.concatenate([s.poses for s in result.sessions])
    ref = np.concatenate([np.column_stack([np.interp(s.times, r[:, 0], r[:, 1]), np.interp(s.times, r[:, 0], r[:, 2])])
                          for s, r in zip(result.sessions, references)])
    fit = align_se2(est[:, :2], ref)
    moved = transform.apply(fit, est[:, :2])
    assert float(np.sqrt(np.mean(np.sum((moved - ref) ** 2, axis=1)))) < 0.1


def test_another_building_is_linked_to_nothing_and_kept_out_of_the_map(two):
    recordings, _, _ = two
    (other,), _ = route_sessions(room(), 1)
    result = map_sessions(MapRequest(recordings[0], OPTIONS, later=(other,)))
    assert [s.linked for s in result.sessions] == [True, False] and result.links == ()
    assert result.quality is not None and result.quality.verdict == "failed"
    assert any("linked by no loop closure" in r for r in result.quality.reasons)
    # The map is the first session's alone (to the joint optimization's micrometres): the room's walls, in a frame
    # of their own, are not drawn over it
    alone = map_sessions(MapRequest(recordings[0], OPTIONS))
    assert result.image.shape == alone.image.shape
    known = ~np.isnan(alone.image.probability)
    assert np.count_nonzero(known != ~np.isnan(result.image.probability)) <= 1e-3 * np.count_nonzero(known)


def test_cut_sessions_restart_odometry_and_keep_every_record(two):
    recordings, _, _ = two
    topics = [t.name for t in recordings[0].topics()]
    records = list(recordings[0].records(topics))
    cut = records[len(records) // 2].time
    a, b = cut_sessions(recordings[0], [cut])
    odometry = list(b.records(["/odom"]))
    np.testing.assert_allclose((odometry[0].x, odometry[0].y, odometry[0].yaw), 0.0, atol=1e-12)
    assert len(list(a.records(topics))) + len(list(b.records(topics))) == len(records)


def test_a_placement_that_puts_a_session_in_free_space_is_refused(two, monkeypatch):
    """The link rule's last word is free space (mapping.link_check): here every placement is made to look wrong, so
    the second session is never linked, and the refusals are counted and said."""
    from carto_cli.commands.map import sessions_lines
    from carto_cli.mapping import pose_graph

    recordings, _, _ = two
    monkeypatch.setattr(pose_graph, "_conflict", lambda graph, lc, frame: 1.0)
    result = map_sessions(MapRequest(recordings[0], OPTIONS, later=(recordings[1],)))
    assert [s.linked for s in result.sessions] == [True, False] and result.links == ()
    assert result.quality is not None and result.quality.verdict == "failed"
    refused = result.sessions_report()["refused_placements"]
    assert refused >= 1 and any(f"{refused} placement(s) refused" in line for line in sessions_lines(result))
