"""carto profile: the report, its schema, the speed gates, calibration and JUnit output."""
import copy
import json
from xml.etree import ElementTree as ET

import jsonschema
import pytest
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.core.timing import StageTimer
from carto_cli.evaluation.gates import accuracy_gates, calibration_scale, compare_profiles, write_junit
from carto_cli.evaluation.profiling import SCHEMA_PATH, build_report, calibrate
from carto_cli.options import load_options
from carto_cli.pipeline import build
from carto_cli.sim.lidar import Lidar
from carto_cli.sim.recording import simulate
from carto_cli.sim.trajectory import loop_trajectory
from carto_cli.sim.world import loop_building


@pytest.fixture(scope="module")
def report():
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=15.0, lidar=Lidar(beams=270))
    options = load_options(None, ["trajectory_builder_2d.submaps.num_range_data=20"])
    timer = StageTimer()
    result = build(sim.recording(), options, timer=timer, jobs=1)  # one thread: every level sums to its parent
    timer.stop()
    return build_report(result, timer, options, "simulated", calibration={"kernel": "k", "ms": 10.0})


def test_with_threads_the_graphs_thread_is_a_concurrent_branch_outside_the_sum():
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=15.0, lidar=Lidar(beams=270))
    options = load_options(None, ["trajectory_builder_2d.submaps.num_range_data=20"])
    timer = StageTimer()
    result = build(sim.recording(), options, timer=timer, jobs=2)
    timer.stop()
    tree = build_report(result, timer, options, "simulated")["timing"]["tree"]
    concurrent = [c for c in tree["children"] if c["concurrent"]]
    assert [c["name"] for c in concurrent] == ["global"]
    assert any(c["name"] == "node" for c in concurrent[0]["children"])
    inline = sum(c["total_ms"] for c in tree["children"] if not c["concurrent"])
    assert inline + tree["self_ms"] == pytest.approx(tree["total_ms"], abs=1e-6)


def test_report_validates_against_its_schema(report):
    schema = json.loads(SCHEMA_PATH.read_text())
    jsonschema.validate(json.loads(json.dumps(report)), schema)
    broken = copy.deepcopy(report)
    del broken["counts"]["nodes"]
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate(broken, schema)


def test_tree_sums_to_total(report):
    def check(node):
        if node["children"]:
            total = sum(c["total_ms"] for c in node["children"]) + node["self_ms"]
            assert total == pytest.approx(node["total_ms"], abs=1e-6)
            for c in node["children"]:
                check(c)

    tree = report["timing"]["tree"]
    check(tree)
    scan = report["timing"]["stages"]["scan"]
    assert scan["calls"] == report["counts"]["scans"] > 100
    assert report["counts"]["nodes"] > 0 and report["counts"]["submaps"] > 0
    for stage in ("scan/preprocess", "scan/match", "scan/insert", "scan/motion filter"):
        assert stage in report["timing"]["stages"], stage


def test_gate_passes_on_itself_and_fails_against_a_faster_baseline(report):
    assert all(g.passed for g in compare_profiles(report, report, 0.2))
    faster = copy.deepcopy(report)
    for stage in faster["timing"]["stages"].values():
        if stage["ms_per_scan"] is not None:
            stage["ms_per_scan"] /= 3.0
        stage["total_ms"] /= 3.0
    failed = [g for g in compare_profiles(report, faster, 0.2) if not g.passed]
    assert any(g.name == "scan" for g in failed)
    # The noise floor keeps tiny stages from flapping: a 3x slower motion filter at ~0.01 ms/scan passes.
    tiny = [g for g in compare_profiles(report, faster, 0.2) if g.name == "scan/motion filter"]
    assert tiny and (tiny[0].passed or tiny[0].current - tiny[0].baseline > 0.05)


def test_calibration_scales_times(report):
    slow_machine = copy.deepcopy(report)
    # The same work on a machine twice as slow: every time doubles, and so does its calibration kernel.
    for stage in slow_machine["timing"]["stages"].values():
        if stage["ms_per_scan"] is not None:
            stage["ms_per_scan"] *= 2.0
        stage["total_ms"] *= 2.0
    slow_machine["calibration"] = {"kernel": "k", "ms": 20.0}
    assert calibration_scale(slow_machine, report) == pytest.approx(0.5)
    assert all(g.passed for g in compare_profiles(slow_machine, report, 0.2))
    uncalibrated = copy.deepcopy(slow_machine)
    uncalibrated["calibration"] = None
    assert not all(g.passed for g in compare_profiles(uncalibrated, report, 0.2))


def _with_cpu(report, factor=1.0):
    """The report as if CPU time had been measured: each stage's CPU time its wall time times ``factor``."""
    out = copy.deepcopy(report)
    for path, stage in out["timing"]["stages"].items():
        if path != "total":
            stage["cpu_ms"] = stage["total_ms"] * factor
            stage["cpu_ms_per_scan"] = None if stage["ms_per_scan"] is None else stage["ms_per_scan"] * factor
    return out


def test_gates_compare_cpu_time_so_a_busy_neighbour_does_not_fail_them(report):
    base = _with_cpu(report)
    busy = copy.deepcopy(base)  # another job on the other core: wall times up by half, CPU times unchanged
    for stage in busy["timing"]["stages"].values():
        stage["total_ms"] *= 1.5
        if stage["ms_per_scan"] is not None:
            stage["ms_per_scan"] *= 1.5
    assert all(g.passed for g in compare_profiles(busy, base, 0.2))
    assert not all(g.passed for g in compare_profiles(busy, report, 0.2))  # on wall time it would fail
    slower = _with_cpu(report, 1.3)  # the code itself 30 % slower
    failed = [g for g in compare_profiles(slower, base, 0.2) if not g.passed]
    assert any(g.name == "scan" and g.unit == "CPU ms/scan" for g in failed)


def test_repeats_keep_each_stages_lowest_cpu_time_and_their_spread_widens_the_gate(report):
    from carto_cli.evaluation.profiling import merge_repeats

    runs = [_with_cpu(report, f) for f in (1.1, 1.0, 1.25)]
    merged = merge_repeats(runs)
    scan = merged["timing"]["stages"]["scan"]
    assert merged["repeats"] == 3
    assert scan["cpu_ms_per_scan"] == pytest.approx(report["timing"]["stages"]["scan"]["ms_per_scan"])
    assert scan["cpu_spread"] == pytest.approx(0.25)
    # 30 % slower fails a baseline without spread at +20 %, and passes one whose repeats varied by 25 %
    slower = _with_cpu(report, 1.3)
    assert not all(g.passed for g in compare_profiles(slower, _with_cpu(report), 0.2))
    assert all(g.passed for g in compare_profiles(slower, merged, 0.2) if g.name == "scan")


def test_reference_kernel_is_positive_and_stable():
    a = calibrate(repeats=3)
    assert a["ms"] > 0 and a["kernel"]


def test_junit_parses(tmp_path, report):
    faster = copy.deepcopy(report)
    faster["timing"]["stages"]["scan"]["ms_per_scan"] /= 10
    gates = compare_profiles(report, faster, 0.2)
    out = write_junit(tmp_path / "gates.xml", "carto.profile", gates)
    root = ET.parse(out).getroot()
    suite = root.find("testsuite")
    assert int(suite.get("tests")) == len(gates)
    assert int(suite.get("failures")) == sum(not g.passed for g in gates) >= 1
    assert suite.find("testcase/failure") is not None


def test_accuracy_gates():
    data = {"relations": {"translation_m": {"mean": 0.12}, "rotation_deg": {"mean": 0.8}}, "ate": None}
    assert all(g.passed for g in accuracy_gates(data, 0.2, 1.0))
    failed = [g for g in accuracy_gates(data, 0.1, 1.0) if not g.passed]
    assert len(failed) == 1 and "translation" in failed[0].name


def test_cli_profile_gate_exit_codes(tmp_path):
    from support import SAMPLE_BAG

    runner = CliRunner()
    base = tmp_path / "base.json"
    args = ["profile", str(SAMPLE_BAG), "--max-scans", "60", "--set",
            "trajectory_builder_2d.use_online_correlative_scan_matching=true"]
    r = runner.invoke(app, args + ["--output", str(base)])
    assert r.exit_code == 0, r.output
    data = json.loads(base.read_text())
    assert data["counts"]["scans"] == 60
    for stage in data["timing"]["stages"].values():
        if stage["ms_per_scan"] is not None:
            stage["ms_per_scan"] /= 20.0
        stage["total_ms"] /= 20.0
        for key in ("cpu_ms_per_scan", "cpu_ms"):  # what the gates compare
            if stage.get(key) is not None:
                stage[key] /= 20.0
    base.write_text(json.dumps(data))
    junit = tmp_path / "j.xml"
    r = runner.invoke(app, args + ["--baseline", str(base), "--junit", str(junit)])
    assert r.exit_code == 3
    assert "slower than baseline" in r.stderr
    ET.parse(junit)


def test_cli_eval_gates(tmp_path):
    traj = tmp_path / "t.txt"
    traj.write_text("0 0 0 0\n1 1 0 0\n2 2 0 0\n")
    rel = tmp_path / "r.txt"
    rel.write_text("0 1 1.0 0 0 0 0 0\n1 2 1.3 0 0 0 0 0\n")
    runner = CliRunner()
    ok = runner.invoke(app, ["eval", str(traj), "--relations", str(rel), "--max-trans-error", "0.5"])
    assert ok.exit_code == 0, ok.output
    bad = runner.invoke(app, ["eval", str(traj), "--relations", str(rel), "--max-trans-error", "0.1",
                              "--junit", str(tmp_path / "e.xml")])
    assert bad.exit_code == 3 and "gate failed" in bad.stderr
    ET.parse(tmp_path / "e.xml")


def test_relocalization_profile(tmp_path, report):
    from support import SAMPLE_BAG

    from carto_cli.evaluation.profiling import profile_relocalization
    from carto_cli.io.map_file import load_map, save_map
    from carto_cli.io.sources.open import open_recording

    options = load_options("office")
    with open_recording(SAMPLE_BAG) as rec:
        result = build(rec, options, max_scans=120)
    path = save_map(tmp_path / "m.carto", result, options)
    with open_recording(SAMPLE_BAG) as rec:
        rel = profile_relocalization(load_map(path), rec, every=15, max_queries=8)
    assert rel["queries"] == 8
    assert set(rel["stages"]) == {"submap preparation", "pose search", "scan scoring", "other"}
    shares = sum(s["share"] for s in rel["stages"].values())
    assert shares == pytest.approx(1.0, abs=0.02)
    assert rel["success_rate"] >= 0.75  # the first 120 scans are in the map; later ones mostly overlap it
    full = dict(report, relocalization=rel)
    jsonschema.validate(json.loads(json.dumps(full)), json.loads(SCHEMA_PATH.read_text()))
