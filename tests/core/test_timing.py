import json
import pickle
import re
import time

import pytest

from carto_cli.core.timing import NullTimer, StageTimer, report_json, report_tree_text

MS = 1_000_000


class FakeClock:
    """A clock that only moves when told to, so every figure is exact."""

    def __init__(self):
        self.now = 0

    def __call__(self) -> int:
        return self.now

    def advance(self, ms: float) -> None:
        self.now += int(ms * MS)


def run_pipeline(timer, clock, scans=4):
    """Shaped like seed 000 §7.1: 8 + 2 + 35 + 5 ms per frame, insertion every other scan."""
    clock.advance(3)                       # setup before the first scan: untimed
    for i in range(scans):
        with timer.scan():
            with timer.stage("preprocess"):
                with timer.stage("voxel"):
                    clock.advance(5)
                with timer.stage("range"):
                    clock.advance(3)
            with timer.stage("extrapolate"):
                clock.advance(2)
            with timer.stage("matching"):
                with timer.stage("csm"):
                    clock.advance(25)
                with timer.stage("ceres"):
                    clock.advance(9)
                clock.advance(1)           # matching's own work
            if i % 2 == 0:
                with timer.stage("insertion"):
                    clock.advance(10)
            clock.advance(0.5)             # between stages, inside the scan
    with timer.stage("final_optimization"):
        clock.advance(100)
    clock.advance(2)
    timer.stop()


@pytest.fixture
def timed():
    clock = FakeClock()
    timer = StageTimer(clock)
    run_pipeline(timer, clock)
    return timer


def test_nesting_totals_and_counts(timed):
    snap = timed.snapshot()
    assert snap.scans == 4
    assert snap.find("scan/preprocess/voxel").total_ns == 20 * MS
    assert snap.find("scan/matching").total_ns == 4 * 35 * MS
    assert snap.find("scan/matching").count == 4
    assert snap.find("scan/insertion").count == 2
    assert [c.name for c in snap.find("scan").children] == ["preprocess", "extrapolate", "matching", "insertion"]
    assert snap.find("scan/voxel") is None


def test_self_time_and_sums(timed):
    snap = timed.snapshot()
    assert snap.find("scan/matching").self_ns == 4 * MS
    assert snap.find("scan/preprocess").self_ns == 0
    assert snap.find("scan").self_ns == 4 * 0.5 * MS
    # 3 ms before the first scan + 2 ms after the optimization are not inside any stage.
    assert snap.root.self_ns == 5 * MS
    assert snap.wall_ns == snap.root.total_ns == (3 + 4 * 45.5 + 2 * 10 + 100 + 2) * MS
    for node in snap.root.walk():
        assert node.self_ns >= 0
        assert node.self_ns + sum(c.total_ns for c in node.children) == node.total_ns


def test_per_scan_samples(timed):
    snap = timed.snapshot()
    matching = snap.find("scan/matching")
    assert matching.samples_ns.tolist() == [35 * MS] * 4
    insertion = snap.find("scan/insertion")
    assert insertion.sample_scans.tolist() == [0, 2]
    assert insertion.percentile_ms(50) == 10.0
    scan = snap.find("scan")
    assert scan.samples_ns.tolist() == [55.5 * MS, 45.5 * MS, 55.5 * MS, 45.5 * MS]
    assert scan.percentile_ms(99) == pytest.approx(55.5)


def test_stage_entered_twice_in_a_scan_sums_into_one_sample():
    clock = FakeClock()
    timer = StageTimer(clock)
    with timer.scan():
        for _ in range(3):
            with timer.stage("ceres"):
                clock.advance(2)
    node = timer.snapshot().find("scan/ceres")
    assert node.count == 3 and node.samples_ns.tolist() == [6 * MS]


def test_outside_scan_stages(timed):
    snap = timed.snapshot()
    final = snap.find("final_optimization")
    assert final.total_ns == 100 * MS and not final.in_scan and final.samples_ns.size == 0
    j = report_json(timed)
    assert j["stages"]["final_optimization"]["ms_per_scan"] is None
    assert j["stages"]["scan/matching"]["ms_per_scan"] == 35.0


def test_next_scan_matches_scan_context():
    a_clock, b_clock = FakeClock(), FakeClock()
    a, b = StageTimer(a_clock), StageTimer(b_clock)
    for i in range(3):
        with a.scan():
            with a.stage("work"):
                a_clock.advance(i + 1)
        b.next_scan()
        with b.stage("work"):
            b_clock.advance(i + 1)
    a.stop()
    b.stop()
    assert report_json(a) == report_json(b)


def test_open_scan_and_stage_are_counted_up_to_now():
    clock = FakeClock()
    timer = StageTimer(clock)
    timer.next_scan()
    with timer.stage("matching"):
        clock.advance(4)
        snap = timer.snapshot()
    assert snap.scans == 1
    for node in snap.root.walk():
        assert node.self_ns >= 0
    assert snap.find("scan").total_ns == 4 * MS


def test_misuse_is_reported():
    timer = StageTimer()
    with pytest.raises(RuntimeError, match="no scan is open"):
        timer.end_scan()
    with timer.scan():
        with pytest.raises(RuntimeError, match="already open"):
            timer.begin_scan()
    with timer.stage("outer"):
        with pytest.raises(RuntimeError, match="stage 'outer' is still open"):
            timer.next_scan()
        with pytest.raises(RuntimeError, match="still open"):
            timer.stop()
    with pytest.raises(ValueError):
        with timer.stage("a/b"):
            pass


def test_report_json(timed):
    j = report_json(timed)
    assert j["schema_version"] == 1 and j["enabled"] is True and j["scans"] == 4
    json.dumps(j)  # plain JSON types only
    tree = j["tree"]
    assert tree["share"] == 1.0
    assert sum(c["share"] for c in tree["children"]) + tree["self_share"] == pytest.approx(1.0)
    scan = next(c for c in tree["children"] if c["name"] == "scan")
    assert scan["share_of_scan"] == 1.0
    assert sum(c["share_of_scan"] for c in scan["children"]) + scan["self_ms"] / scan["total_ms"] == \
        pytest.approx(1.0)
    matching = j["stages"]["scan/matching"]
    assert (matching["p50_ms"], matching["p95_ms"], matching["max_ms"]) == (35.0, 35.0, 35.0)
    assert matching["share_of_scan"] == pytest.approx(140 / 202)


def test_report_tree_text(timed):
    text = report_tree_text(timed)
    lines = text.splitlines()
    assert lines[0] == "timing: 4 scans, wall 0.307 s"
    assert re.search(r"├─ scan \(4 scans\)\s+202\.0\s+50\.500\s+65\.8%\s+100\.0%\s+4", text)
    assert re.search(r"│  ├─ matching\s+140\.0\s+35\.000", text)
    assert re.search(r"│  │  └─ \(other\)\s+4\.0\s+1\.000", text)
    assert re.search(r"├─ final_optimization\s+100\.0\s+32\.6%\s+1$", text, re.M)
    assert re.search(r"└─ \(other: untimed\)\s+5\.0", text)
    # The root's direct children (and its other line) add up to 100%.
    top = [ln for ln in lines[3:] if re.match(r"^[├└]─ ", ln)]
    shares = [float(re.search(r"([\d.]+)%", ln.split("  ", 1)[1]).group(1)) for ln in top]
    assert sum(shares) == pytest.approx(100.0, abs=0.2)


def test_null_timer_has_the_same_interface_and_records_nothing():
    public = {n for n in dir(StageTimer) if not n.startswith("_")}
    assert public <= {n for n in dir(NullTimer) if not n.startswith("_")}
    timer = NullTimer()
    assert not timer.enabled
    run_pipeline(timer, FakeClock())
    timer.next_scan()
    assert report_tree_text(timer) == "timing: disabled\n"
    j = report_json(timer)
    assert j["enabled"] is False and j["schema_version"] == 1 and j["scans"] == 0


def test_real_clock_smoke():
    timer = StageTimer()
    for _ in range(3):
        with timer.scan():
            with timer.stage("sleep"):
                time.sleep(0.002)
    timer.stop()
    snap = timer.snapshot()
    assert snap.find("scan/sleep").total_ns >= 6_000_000
    assert snap.root.total_ns >= snap.find("scan").total_ns >= snap.find("scan/sleep").total_ns


def test_cpu_time_is_recorded_beside_wall_time():
    wall, cpu = FakeClock(), FakeClock()
    timer = StageTimer(wall, cpu_clock=cpu)
    for _ in range(2):
        with timer.scan():
            with timer.stage("matching"):
                wall.advance(10)
                cpu.advance(4)  # waiting for the other core's job: wall time that is not CPU time
            wall.advance(1)
            cpu.advance(1)
    timer.stop()
    stages = report_json(timer)["stages"]
    assert stages["scan/matching"]["ms_per_scan"] == pytest.approx(10.0)
    assert stages["scan/matching"]["cpu_ms_per_scan"] == pytest.approx(4.0)
    assert stages["scan"]["cpu_ms"] == pytest.approx(10.0) and stages["scan"]["total_ms"] == pytest.approx(22.0)
    assert "cpu_ms" not in report_json(StageTimer(FakeClock()))["stages"].get("scan", {})


def test_work_of_other_threads_is_added_and_shown_beside_the_wall_time():
    clock = iter(range(0, 10_000, 10)).__next__
    timer = StageTimer(clock=clock)
    background = timer.concurrent("global")
    with background.stage("search"):
        pass
    with timer.stage("loop closure"):
        # thread time, longer than the stage itself: a branch of its own, not the stage's child
        timer.concurrent("search threads").add("branch and bound", 50, count=2)
    timer.stop()
    snap = timer.snapshot()
    lc = snap.find("loop closure")
    bnb = snap.find("search threads/branch and bound")
    assert (bnb.total_ns, bnb.count) == (50, 2) and lc.children == [] and snap.find("search threads").concurrent
    g = snap.find("global")
    assert g.concurrent and g.total_ns == snap.find("global/search").total_ns == 10
    # The concurrent branch is not part of the wall-time sum: the root's untimed time ignores it.
    assert snap.root.self_ns == snap.wall_ns - lc.total_ns
    assert "concurrent" in report_tree_text(snap)


def test_profile_tree_charges_a_stalled_cpu_clock_to_the_stage_that_read_it():
    """Issue 42 item 8: on a busy machine, reading the process's CPU time after a long stretch of work is where
    the scheduler switches to other work (the read stalls). The read that ends a child is the child's: the stall
    is in its wall time, not in its parent's '(other)' (once most of `match`'s time, beside two children)."""
    wall = FakeClock()
    last = [0]

    def cpu_clock() -> int:
        if wall.now - last[0] >= 5 * MS:  # the time slice ran out during the work: switched out here
            wall.advance(3)
        last[0] = wall.now
        return 0

    timer = StageTimer(wall, cpu_clock=cpu_clock)
    with timer.scan():
        with timer.stage("match"):
            for name, ms in (("correlative", 10), ("least squares", 2)):
                with timer.stage(name):
                    wall.advance(ms)
    timer.stop()
    snap = timer.snapshot()
    assert snap.find("scan/match").self_ns == 0 and snap.find("scan/match").total_ns == 15 * MS
    assert snap.find("scan/match/correlative").total_ns == 13 * MS


def test_concurrent_branches_are_one_per_name_nest_and_cross_processes():
    clock = FakeClock()
    timer = StageTimer(clock)
    graph = timer.concurrent("global")
    assert timer.concurrent("global") is graph  # asked for again (a second pass): the same branch
    with graph.stage("node"):
        clock.advance(4)
    graph.concurrent("search threads").add("branch and bound", 9 * MS)
    # as the graph's process hands its timer back: its own branches come along
    again = StageTimer(clock)
    again.import_tree(pickle.loads(pickle.dumps(graph.export_tree())))
    timer._concurrent["global"] = again
    timer.stop()
    snap = timer.snapshot()
    g = snap.find("global")
    assert g.total_ns == 4 * MS  # the graph thread's busy time; its workers' is beside it
    assert snap.find("global/search threads").concurrent
    assert snap.find("global/search threads/branch and bound").total_ns == 9 * MS
    clash = StageTimer(clock)
    clash.concurrent("global")
    with clash.stage("global"):
        pass
    clash.stop()
    with pytest.raises(ValueError, match="named as a stage beside it"):
        clash.snapshot()
