"""`carto relocalize`: the library call (run_relocalize) and the command line over it, on the simulated
loop-building map (tests/reloc_map.py) and its second pass written as a ROS1 bag."""
import json
import math

import pytest
from reloc_map import build_map, pose_error, second_pass
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.commands.relocalize import run_relocalize
from carto_cli.core.errors import CartoError
from carto_cli.io.recording_writers import write_recording
from carto_cli.relocalization import CSV_COLUMNS


@pytest.fixture(scope="module")
def cli_files(tmp_path_factory):
    """The map file and the second pass written as a ROS1 bag, as `carto relocalize` reads them."""
    base = tmp_path_factory.mktemp("cli")
    mapped = build_map(base)
    sim, qs = second_pass(mapped)
    bag = base / "second_pass.bag"
    write_recording(iter(list(sim.records(["/scan"]))), bag, "ros1",
                    topics={"/scan": "sensor_msgs/msg/LaserScan"})
    return mapped.path, bag, qs


def _cli(*args):
    return CliRunner().invoke(app, [str(a) for a in args])


# ------------------------------------------------------------------------------------------ library call


def test_run_relocalize_answers_one_scan(cli_files):
    map_path, bag, qs = cli_files
    scan, truth = qs[5]
    warned = []
    run = run_relocalize(map_path, bag, initial_pose=tuple(truth + [0.5, -0.4, 0.1]), at=scan.time,
                         sigma_yaw=math.radians(8), on_warning=warned.append)
    assert not run.batch and run.result.success and run.result.path == "windowed"
    assert run.scan.time == pytest.approx(scan.time) and run.scan_index == round((scan.time - 1000.0) * 5)
    assert pose_error(run.result.pose, truth)[0] < 0.1
    d = run.to_dict()
    assert d["scan_index"] == run.scan_index and d["scan_time"] == scan.time and d["success"]
    assert warned == [] and run.warnings == []
    # The same prior as text, the way the command line gives it.
    text = run_relocalize(map_path, bag, initial_pose=",".join(str(v) for v in truth + [0.5, -0.4, 0.1]),
                          scan_index=run.scan_index)
    assert text.scan_index == run.scan_index and pose_error(text.result.pose, run.result.pose)[0] < 1e-9


def test_run_relocalize_batch_writes_the_csv_next_to_the_queries(cli_files, tmp_path):
    map_path, bag, qs = cli_files
    (s0, t0), (s1, _) = qs[4], qs[12]
    q = tmp_path / "q.txt"
    q.write_text(f"{s0.time} {t0[0]} {t0[1]} {t0[2]}\n{s1.time} - - -\n")
    run = run_relocalize(map_path, bag, queries=q)
    assert run.batch and run.csv == tmp_path / "q.results.csv" and run.csv.is_file()
    assert [r.result.path for r in run.results] == ["windowed", "global"]
    assert run.summary.queries == 2 and run.to_dict() == run.summary.to_dict()
    assert run.csv.read_text().splitlines()[0].split(",") == list(CSV_COLUMNS)
    other = run_relocalize(map_path, bag, queries=q, csv_out=tmp_path / "sub" / "r.csv")
    assert other.csv == tmp_path / "sub" / "r.csv" and other.csv.is_file()


def test_run_relocalize_reports_warnings_before_reading_the_recording(cli_files, tmp_path):
    map_path, _, _ = cli_files
    warned = []
    with pytest.raises(CartoError):
        run_relocalize(map_path, tmp_path / "missing.bag", global_search=True,
                       overrides=["relocalization.cache_budget_mb=0.001"], on_warning=warned.append)
    assert len(warned) == 1 and "cache_budget_mb" in warned[0]


@pytest.mark.parametrize("kwargs, message", [
    ({}, "give --initial-pose x,y,yaw, or --global, or --queries FILE"),
    ({"global_search": True, "initial_pose": "1,2,3"}, "--global and --initial-pose exclude each other"),
    ({"global_search": True, "at": 1.0, "scan_index": 2}, "--at and --scan-index exclude each other"),
])
def test_run_relocalize_checks_its_arguments_first(tmp_path, kwargs, message):
    with pytest.raises(CartoError, match=message):
        run_relocalize(tmp_path / "no-map.carto", tmp_path / "no.bag", **kwargs)


def test_a_bad_initial_pose_is_reported_after_the_scan_is_read(cli_files, tmp_path):
    map_path, bag, _ = cli_files
    with pytest.raises(CartoError, match="--initial-pose: expected x,y,yaw"):
        run_relocalize(map_path, bag, initial_pose="1,2")
    with pytest.raises(CartoError, match="beyond the recording's"):
        run_relocalize(map_path, bag, initial_pose="1,2", scan_index=10_000)


# ------------------------------------------------------------------------------------------ command line


def test_cli_relocalizes_one_scan_as_text_and_json(cli_files):
    map_path, bag, qs = cli_files
    scan, truth = qs[5]
    prior = truth + [0.8, -0.6, math.radians(8)]
    pose = f"{prior[0]},{prior[1]},{math.degrees(prior[2])}deg"
    r = _cli("relocalize", map_path, bag, "--initial-pose", pose, "--at", scan.time)
    assert r.exit_code == 0, r.output
    assert "(ok) via windowed" in r.output and "timing submap preparation" in r.output
    assert r.output.startswith(f"scan {round((scan.time - 1000.0) * 5)} at {scan.time:.3f}: pose ")
    r = _cli("relocalize", map_path, bag, "--initial-pose", pose, "--at", scan.time, "--json")
    assert r.exit_code == 0, r.output
    d = json.loads(r.output)
    assert d["success"] and d["path"] == "windowed"
    assert pose_error([d["pose"]["x"], d["pose"]["y"], d["pose"]["yaw"]], truth)[0] < 0.1
    assert set(d["timings_ms"]) == {"submap preparation", "pose search", "scan scoring", "other"}
    assert d["scan_time"] == pytest.approx(scan.time)


def test_cli_says_why_a_scan_was_not_relocalized(cli_files):
    map_path, bag, qs = cli_files
    scan, truth = qs[5]
    pose = f"{truth[0]},{truth[1]},{truth[2]}"
    # A threshold no scan reaches: not found, the reason printed, exit 3 (a check failed).
    r = _cli("relocalize", map_path, bag, "--initial-pose", pose, "--at", scan.time,
             "--set", "relocalization.min_score=0.95", "--set", "relocalization.global_min_score=0.95")
    assert r.exit_code == 3, r.output
    assert "UNRELIABLE" in r.output and "why: " in r.output and "below 0.95" in r.output


def test_cli_batch_prints_the_summary_line(cli_files, tmp_path):
    map_path, bag, qs = cli_files
    (s0, t0) = qs[4]
    q = tmp_path / "q.txt"
    q.write_text(f"{s0.time} {t0[0]} {t0[1]} {t0[2]}\n")
    r = _cli("relocalize", map_path, bag, "--queries", q, "--csv", tmp_path / "out.csv")
    assert r.exit_code == 0, r.output
    assert r.output.startswith("1/1 relocalized (100.0%), p50 ") and r.output.rstrip().endswith(
        f"-> {tmp_path / 'out.csv'}")
    r = _cli("relocalize", map_path, bag, "--queries", q, "--json")
    assert r.exit_code == 0 and json.loads(r.output)["successes"] == 1
    # The results CSV is an output like any other: kept unless --force
    before = (tmp_path / "out.csv").read_bytes()
    r = _cli("relocalize", map_path, bag, "--queries", q, "--csv", tmp_path / "out.csv")
    assert r.exit_code == 2 and "out.csv: exists; --force replaces it" in r.stderr
    assert (tmp_path / "out.csv").read_bytes() == before
    assert _cli("relocalize", map_path, bag, "--queries", q, "--csv", tmp_path / "out.csv", "--force").exit_code == 0


def test_cli_warns_on_stderr_and_fails_with_exit_2_on_user_errors(cli_files, tmp_path):
    map_path, bag, _ = cli_files
    r = _cli("relocalize", map_path, tmp_path / "missing.bag", "--global",
             "--set", "relocalization.cache_budget_mb=0.001")
    assert r.exit_code == 2
    assert r.stderr.startswith("carto: warning: the map's precomputation grids need ")
    assert r.stderr.splitlines()[-1].startswith("carto: error: ")
    r = _cli("relocalize", map_path, bag)
    assert r.exit_code == 2
    assert r.stderr == "carto: error: give --initial-pose x,y,yaw, or --global, or --queries FILE\n"


def test_cli_rejects_an_unknown_override_by_name(cli_files):
    map_path, bag, _ = cli_files
    r = _cli("relocalize", map_path, bag, "--global", "--set", "relocalization.min_scroe=0.7")
    assert r.exit_code == 2 and "min_scroe" in r.output
