"""Query files, --initial-pose text, and which scans of a recording they select."""
import math

import pytest

from carto_cli.core.errors import CartoError
from carto_cli.relocalization import (
    Query,
    context_at,
    contexts_for,
    iter_scans,
    parse_pose,
    read_queries,
    relocalize_many,
    scan_at,
    scans_for_queries,
    select_scan_topic,
)


def test_parse_pose():
    assert parse_pose("1.5,-2,90deg") == pytest.approx((1.5, -2.0, math.pi / 2))
    assert parse_pose("1 2 0.5") == (1.0, 2.0, 0.5)
    for bad in ("1,2", "a,2,3", "1,2,3rad", "1,2,inf"):
        with pytest.raises(CartoError, match="--initial-pose"):
            parse_pose(bad)


def test_read_queries_formats_and_errors(tmp_path):
    p = tmp_path / "q.txt"
    p.write_text("# header comment\n\n1000.5 1 2 0.5\n1001.0, 3, 4, 90deg, 0.3, 5deg  # sigmas\n1002 - - -\n")
    q = read_queries(p)
    assert [x.time for x in q] == [1000.5, 1001.0, 1002.0] and all(x.index is None for x in q)
    assert q[1].prior == pytest.approx((3, 4, math.pi / 2)) and q[1].sigma_xy == 0.3
    assert q[1].sigma_yaw == pytest.approx(math.radians(5)) and q[2].prior is None and q[2].line == 5
    p.write_text("index x y yaw\n7 1 2 0.5\n")
    q = read_queries(p)
    assert q[0].index == 7 and q[0].time is None
    cases = {
        "": "no queries",
        "1 2 3\n": "line 1: expected 4 fields",
        "1 2 3 4 5\n": "line 1: expected 4 fields",
        "1 a 3 4\n": "line 1: x must be a number",
        "1 2 - 4\n": "line 1: give all of x, y, yaw",
        "1 2 3 4\nt x y yaw\n": "line 2: expected a query",
        "foo x y yaw\n": "line 1: the first column",
        "t a b c\n": "line 1: header must be",
        "index x y yaw\n1.5 1 2 3\n": "line 2: scan index must be a whole number",
        "1 2 3 4 -1 5\n": "line 1: sigmas must be positive",
        "1 2 3 4deg2\n": "line 1: yaw must be",
    }
    for text, message in cases.items():
        p.write_text(text)
        with pytest.raises(CartoError, match=message):
            read_queries(p)
    with pytest.raises(CartoError, match="no such queries file"):
        read_queries(tmp_path / "missing.txt")


# ------------------------------------------------------------------------------------------ scans


def test_scan_at(queries):
    sim, _ = queries
    rec = sim.recording()
    i, scan = scan_at(rec, time=1010.07)
    assert i == 50 and scan.time == pytest.approx(1010.0)
    i, scan = scan_at(rec, index=3)
    assert i == 3 and scan.time == pytest.approx(1000.6)
    with pytest.raises(CartoError, match="beyond the recording's 350 scans"):
        scan_at(rec, index=10_000)
    with pytest.raises(CartoError, match="no scan within"):
        scan_at(rec, time=5000.0)


def test_scans_for_queries_picks_the_nearest_scan_in_one_pass(queries):
    sim, _ = queries
    rec = sim.recording()
    # Scans every 0.2 s from t=1000: 1000.09 is nearer 1000.0, 1000.11 nearer 1000.2, a tie goes to the earlier.
    qs = [Query(1000.11, None, None), Query(None, 7, None), Query(1000.09, None, None), Query(1000.1, None, None),
          Query(None, 7, (1.0, 2.0, 0.0), line=9)]
    found = scans_for_queries(rec, qs)
    assert sorted(found) == [0, 1, 2, 3, 4]
    assert [found[k][0] for k in range(5)] == [1, 7, 0, 0, 7]
    assert found[1][1] is found[4][1]  # one pass: the same scan object for both queries of index 7
    assert found[0][1].time == pytest.approx(1000.2)
    with pytest.raises(CartoError, match="line 3: scan index 999 is beyond"):
        scans_for_queries(rec, [Query(None, 999, None, line=3)])


def test_contexts_are_gathered_in_the_same_pass(queries):
    """Each query's scan with the scans and odometry within the span before and after it, nothing else."""
    from carto_cli.core.records import Odometry, Scan

    sim, _ = queries
    rec = sim.recording()
    qs = [Query(None, 0, None), Query(1010.09, None, None), Query(1010.11, None, None), Query(None, 349, None)]
    found, contexts = contexts_for(rec, qs, context_seconds=2.0)
    assert [found[k][0] for k in range(4)] == [0, 50, 51, 349]
    every = [(type(r), r.time) for r in sim.records(["/scan", "/odom"])]
    for k in range(4):
        scan = found[k][1]
        ctx = contexts[k]
        at = every.index((Scan, scan.time))
        assert [(type(r), r.time) for r in ctx.before] == [e for e in every[:at] if e[1] >= scan.time - 2.0]
        assert [(type(r), r.time) for r in ctx.after] == [e for e in every[at + 1:] if e[1] <= scan.time + 2.0]
        assert all(isinstance(r, (Scan, Odometry)) for r in list(ctx.before) + list(ctx.after))
    assert not any(isinstance(r, Scan) for r in list(contexts[0].before) + list(contexts[3].after))
    assert sum(isinstance(r, Scan) for r in contexts[1].after) == 10  # 2 s of scans at 5 Hz
    # The query between two scans that went to the earlier one has the later one after it
    assert contexts[1].after[[isinstance(r, Scan) for r in contexts[1].after].index(True)] is found[2][1]
    i, scan, ctx = context_at(rec, index=50, context_seconds=2.0)
    assert i == 50 and [r.time for r in ctx.before] == [r.time for r in contexts[1].before]


def test_iter_scans_counts_scans_on_the_selected_topic(queries):
    sim, _ = queries
    rec = sim.recording()
    topic = select_scan_topic(rec)
    assert topic == "/scan"
    scans = list(iter_scans(rec, topic))
    assert [i for i, _ in scans] == list(range(350))
    assert scans[3][1].time == pytest.approx(1000.6)


class _NoScans:
    path = "empty.bag"

    def topics(self):
        from carto_cli.io.recording import TopicInfo

        return [TopicInfo("/scan", "sensor_msgs/msg/LaserScan", 0)]

    def preferred_topic(self, kind):
        return None

    def records(self, topics=None):
        return iter(())


def test_recording_without_scans_is_an_error(relocalizer):
    with pytest.raises(CartoError, match="no scans|no laser scan topic"):
        scan_at(_NoScans(), time=1.0)
    with pytest.raises(CartoError, match="no scans|no laser scan topic"):
        relocalize_many(relocalizer, _NoScans(), [Query(1.0, None, None)])
