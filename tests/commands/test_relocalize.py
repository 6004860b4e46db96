"""`carto relocalize`: the library call (run_relocalize) and the command line over it, on the simulated
loop-building map (tests/reloc_map.py) and its second pass written as a ROS1 bag."""
import json
import math

import numpy as np
import pytest
from reloc_map import build_map, pose_error, second_pass, with_walls
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.commands.relocalize import RelocalizeRequest, RelocalizeScans, apply_map_auto, run_relocalize
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


def _scans(map_path, recording, *, at=None, scan_index=None, global_search=False, queries=None, csv_out=None,
           **request):
    return RelocalizeScans(RelocalizeRequest(map_path, recording, **request), at=at, scan_index=scan_index,
                           global_search=global_search, queries=queries, csv_out=csv_out)


# ------------------------------------------------------------------------------------------ library call


def test_run_relocalize_answers_one_scan(cli_files):
    map_path, bag, qs = cli_files
    scan, truth = qs[5]
    warned = []
    run = run_relocalize(_scans(map_path, bag, initial_pose=tuple(truth + [0.5, -0.4, 0.1]), at=scan.time,
                                sigma_yaw=math.radians(8)), on_warning=warned.append)
    assert not run.batch and run.result.success and run.result.path == "windowed"
    assert run.scan.time == pytest.approx(scan.time) and run.scan_index == round((scan.time - 1000.0) * 5)
    assert pose_error(run.result.pose, truth)[0] < 0.1
    d = run.to_dict()
    assert d["scan_index"] == run.scan_index and d["scan_time"] == scan.time and d["success"]
    assert warned == [] and run.warnings == []
    # The same prior as text, the way the command line gives it.
    text = run_relocalize(_scans(map_path, bag, initial_pose=",".join(str(v) for v in truth + [0.5, -0.4, 0.1]),
                                 scan_index=run.scan_index))
    assert text.scan_index == run.scan_index and pose_error(text.result.pose, run.result.pose)[0] < 1e-9


def test_run_relocalize_batch_writes_the_csv_next_to_the_queries(cli_files, tmp_path):
    map_path, bag, qs = cli_files
    (s0, t0), (s1, _) = qs[4], qs[12]
    q = tmp_path / "q.txt"
    q.write_text(f"{s0.time} {t0[0]} {t0[1]} {t0[2]}\n{s1.time} - - -\n")
    run = run_relocalize(_scans(map_path, bag, queries=q))
    assert run.batch and run.csv == tmp_path / "q.results.csv" and run.csv.is_file()
    assert [r.result.path for r in run.results] == ["windowed", "global"]
    assert run.summary.queries == 2 and run.to_dict() == run.summary.to_dict()
    assert run.csv.read_text().splitlines()[0].split(",") == list(CSV_COLUMNS)
    other = run_relocalize(_scans(map_path, bag, queries=q, csv_out=tmp_path / "sub" / "r.csv"))
    assert other.csv == tmp_path / "sub" / "r.csv" and other.csv.is_file()


def test_a_batch_on_threads_gives_the_answers_of_one_thread(cli_files, tmp_path):
    map_path, bag, qs = cli_files
    q = tmp_path / "q.txt"
    lines = [f"{s.time} {t[0] + 0.3} {t[1] - 0.2} {t[2] + 0.05}" for s, t in qs[:12:2]] + [f"{qs[3][0].time} - - -"]
    q.write_text("\n".join(lines) + "\n")
    one = run_relocalize(_scans(map_path, bag, queries=q, csv_out=tmp_path / "one.csv", jobs=1))
    three = run_relocalize(_scans(map_path, bag, queries=q, csv_out=tmp_path / "three.csv", jobs=3))
    assert len(one.results) == len(three.results) == len(lines)
    for a, b in zip(one.results, three.results):
        assert (a.scan_index, a.result.path, a.result.verdict) == (b.scan_index, b.result.path, b.result.verdict)
        assert (a.result.pose is None and b.result.pose is None) or (a.result.pose == b.result.pose).all()


def test_a_map_carto_without_a_profile_gets_thresholds_for_its_own_walls(cli_files):
    """No profile (or 'auto'): the score thresholds follow the map's own level (relocalization.auto); a profile's
    relocalization section replaces them untouched; a map at the reference level keeps its own."""
    from carto_cli.io.map_file import load_map

    map_path, _, _ = cli_files
    stock = load_map(map_path).options.relocalization
    for profile in (None, "auto"):
        faint = with_walls(load_map(map_path), lambda p: 0.5 + 0.3 * (p - 0.5))
        auto = apply_map_auto(faint, profile)
        assert auto is not None and "relocalization.global_min_score" in auto.describe()
        assert faint.options.relocalization.global_min_score < 0.9 * stock.global_min_score
        assert faint.options == auto.options
    faint = with_walls(load_map(map_path), lambda p: 0.5 + 0.3 * (p - 0.5))
    assert apply_map_auto(faint, "office") is None and faint.options.relocalization == stock
    sharp = with_walls(load_map(map_path), lambda p: np.full_like(p, 0.9))
    assert apply_map_auto(sharp, None) is None and sharp.options.relocalization == stock


def test_run_relocalize_reports_warnings_before_reading_the_recording(cli_files, tmp_path):
    map_path, _, _ = cli_files
    warned = []
    with pytest.raises(CartoError):
        run_relocalize(_scans(map_path, tmp_path / "missing.bag", global_search=True,
                              overrides=["relocalization.cache_budget_mb=0.001"]), on_warning=warned.append)
    assert len(warned) == 1 and "cache_budget_mb" in warned[0]


@pytest.mark.parametrize("kwargs, message", [
    ({}, "give --initial-pose x,y,yaw, or --global, or --queries FILE"),
    ({"global_search": True, "initial_pose": "1,2,3"}, "--global and --initial-pose exclude each other"),
    ({"global_search": True, "at": 1.0, "scan_index": 2}, "--at and --scan-index exclude each other"),
    ({"global_search": True, "max_jump": 0.0}, "--max-jump must be > 0 m, got 0"),
    # Both wrong: reported in the order the command always has.
    ({"at": 1.0, "scan_index": 2}, "give --initial-pose x,y,yaw, or --global, or --queries FILE"),
    ({"max_jump": -1.0}, "--max-jump must be > 0 m, got -1"),
])
def test_run_relocalize_checks_its_arguments_first(tmp_path, kwargs, message):
    """The request refuses them as it is built, before any map or recording is looked at."""
    with pytest.raises(CartoError, match=message):
        _scans(tmp_path / "no-map.carto", tmp_path / "no.bag", **kwargs)


def test_a_bad_initial_pose_is_reported_after_the_scan_is_read(cli_files, tmp_path):
    map_path, bag, _ = cli_files
    with pytest.raises(CartoError, match="--initial-pose: expected x,y,yaw"):
        run_relocalize(_scans(map_path, bag, initial_pose="1,2"))
    with pytest.raises(CartoError, match="beyond the recording's"):
        run_relocalize(_scans(map_path, bag, initial_pose="1,2", scan_index=10_000))


# ------------------------------------------------------------------------------------------ command line


def test_cli_relocalizes_one_scan_as_text_and_json(cli_files):
    map_path, bag, qs = cli_files
    scan, truth = qs[5]
    prior = truth + [0.8, -0.6, math.radians(8)]
    pose = f"{prior[0]},{prior[1]},{math.degrees(prior[2])}deg"
    r = _cli("relocalize", map_path, bag, "--initial-pose", pose, "--at", scan.time)
    assert r.exit_code == 0, r.output
    assert "verdict ok, score" in r.output and "via windowed" in r.output and "timing submap preparation" in r.output
    assert "sigma " in r.output and "ambiguity" in r.output
    assert r.output.startswith(f"scan {round((scan.time - 1000.0) * 5)} at {scan.time:.3f}: pose ")
    r = _cli("relocalize", map_path, bag, "--initial-pose", pose, "--at", scan.time, "--json")
    assert r.exit_code == 0, r.output
    d = json.loads(r.output)
    assert d["success"] and d["path"] == "windowed" and d["verdict"] == "ok" and len(d["covariance"]) == 3
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
    assert "verdict lost" in r.output and "why: " in r.output and "below 0.95" in r.output


def test_cli_batch_prints_the_summary_line(cli_files, tmp_path):
    map_path, bag, qs = cli_files
    (s0, t0) = qs[4]
    q = tmp_path / "q.txt"
    q.write_text(f"{s0.time} {t0[0]} {t0[1]} {t0[2]}\n")
    r = _cli("relocalize", map_path, bag, "--queries", q, "--csv", tmp_path / "out.csv")
    assert r.exit_code == 0, r.output
    assert r.output.startswith("1/1 relocalized (100.0%; ok 1, ambiguous 0, lost 0), p50 ") and r.output.rstrip().endswith(
        f"-> {tmp_path / 'out.csv'}")
    r = _cli("relocalize", map_path, bag, "--queries", q, "--json")
    assert r.exit_code == 0 and json.loads(r.output)["successes"] == 1
    # The results CSV is an output like any other: kept unless --force
    before = (tmp_path / "out.csv").read_bytes()
    r = _cli("relocalize", map_path, bag, "--queries", q, "--csv", tmp_path / "out.csv")
    assert r.exit_code == 2 and "out.csv: exists; --force replaces it" in r.stderr
    assert (tmp_path / "out.csv").read_bytes() == before
    assert _cli("relocalize", map_path, bag, "--queries", q, "--csv", tmp_path / "out.csv", "--force").exit_code == 0


def test_relocalize_prints_the_compile_note_on_a_cold_cache(cli_files, tmp_path, monkeypatch):
    """Issue 42, item 10: the first relocalize after installing spent about 7 s compiling kernels without a word,
    where map says it; now relocalize says it the same way (and nothing once they load from the cache)."""
    from contextlib import contextmanager

    from carto_cli.core import kernels

    compiled = [7.2]

    @contextmanager
    def compile_time():  # numba's own count of compiling, as on a first run (the kernels here are cached)
        yield lambda: compiled[0]

    monkeypatch.setattr(kernels, "compile_time", compile_time, raising=False)
    map_path, bag, qs = cli_files
    scan, truth = qs[4]
    note = "(incl. 7 s compiling kernels: later runs load them from the cache)"
    one = _cli("relocalize", map_path, bag, "--initial-pose", ",".join(map(str, truth)), "--at", scan.time)
    assert one.exit_code == 0, one.output
    (timing,) = [line for line in one.stdout.splitlines() if line.startswith("timing ")]
    assert timing.endswith(f" ms {note}")
    q = tmp_path / "q.txt"
    q.write_text(f"{scan.time} {truth[0]} {truth[1]} {truth[2]}\n")
    batch = _cli("relocalize", map_path, bag, "--queries", q, "--csv", tmp_path / "out.csv")
    assert batch.exit_code == 0, batch.output
    assert batch.stdout.startswith("1/1 relocalized") and note in batch.stdout
    compiled[0] = 0.0
    warm = _cli("relocalize", map_path, bag, "--initial-pose", ",".join(map(str, truth)), "--at", scan.time)
    assert warm.exit_code == 0 and "compiling" not in warm.output


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


def test_headerless_query_file_errors_name_the_query_file(cli_files, tmp_path):
    """Issue 42 item 7: a query line no scan answers is the query file's error, at its line; a headerless
    number is a time, and the message and --queries' help say how to give a scan index instead."""
    map_path, bag, _ = cli_files
    q = tmp_path / "q.txt"
    q.write_text("# x y in the map\n100 -0.5 0.3 0.62\n")
    r = _cli("relocalize", map_path, bag, "--queries", q)
    assert r.exit_code == 2 and len(r.stderr.splitlines()) == 1, r.output
    assert r.stderr.startswith(f"carto: error: {q}: line 2: no scan of {bag.name} within 1 s of t=100.000 ")
    assert "'index x y yaw'" in r.stderr
    q.write_text("index x y yaw\n3 - - -\n100000 - - -\n")
    with pytest.raises(CartoError, match=f"line 3: scan index 100000 is beyond {bag.name}'s 350 scans") as e:
        run_relocalize(_scans(map_path, bag, queries=q))
    assert e.value.path == str(q)
    assert not q.with_suffix(".results.csv").exists()
    help_text = " ".join(_cli("relocalize", "--help").output.replace("│", " ").split())
    assert "a scan index (from 0)" in help_text and "time" in help_text


def test_cli_rejects_an_unknown_override_by_name(cli_files):
    map_path, bag, _ = cli_files
    r = _cli("relocalize", map_path, bag, "--global", "--set", "relocalization.min_scroe=0.7")
    assert r.exit_code == 2 and "min_scroe" in r.output


# ------------------------------------------------------------------------------------------ map_server maps, tracking


@pytest.fixture(scope="module")
def track_files(cli_files, tmp_path_factory):
    """The second pass with its odometry as a ROS1 bag, and the map as map_server PGM + YAML."""
    from reloc_map import DURATION, SCAN_RATE, world

    from carto_cli.core import transform
    from carto_cli.grid.occupancy_image import assemble
    from carto_cli.io.map_file import load_map
    from carto_cli.io.map_image import write_map
    from carto_cli.sim import simulate

    map_path, _, qs = cli_files
    base = tmp_path_factory.mktemp("track")
    w, tr = world()
    sim = simulate(w, tr, duration=DURATION, scan_rate=SCAN_RATE, seed=7)
    bag = base / "with_odom.bag"
    write_recording(iter(list(sim.records(["/scan", "/odom"]))), bag, "ros1",
                    topics={"/scan": "sensor_msgs/msg/LaserScan", "/odom": "nav_msgs/msg/Odometry"})
    m = load_map(map_path)
    image = assemble([s.grid for s in m.submaps], [transform.compose(g, transform.inverse(s.local_pose))
                                                   for s, g in zip(m.submaps, m.submap_global_poses)])
    _, yaml_path = write_map(base / "ms", image)
    return bag, yaml_path, qs


def test_cli_relocalizes_in_a_map_server_map(track_files, cli_files):
    bag, yaml_path, qs = track_files
    scan, truth = qs[5]
    prior = truth + [0.4, -0.3, math.radians(5)]
    r = _cli("relocalize", yaml_path, bag, "--initial-pose", f"{prior[0]},{prior[1]},{prior[2]}", "--at", scan.time,
             "--json")
    assert r.exit_code == 0, r.output
    d = json.loads(r.output)
    assert d["verdict"] == "ok" and pose_error([d["pose"]["x"], d["pose"]["y"], d["pose"]["yaw"]], truth)[0] < 0.1


def test_cli_tracks_a_recording(track_files, cli_files, tmp_path):
    bag, _, _qs = track_files
    map_path = cli_files[0]
    out = tmp_path / "trk"
    r = _cli("relocalize", map_path, bag, "--track", "-o", out)  # no prior: a global first fix
    assert r.exit_code == 0, r.output
    assert "first fix at scan 0" in r.output and r.output.rstrip().endswith(f"-> {out}")
    rows = (out / "track.csv").read_text().splitlines()
    assert rows[0].startswith("t,scan_index,x,y,yaw,verdict,source") and len(rows) == 1 + 350
    summary = json.loads((out / "track.json").read_text())
    assert summary["scans"] == 350 and summary["first_fix_index"] == 0
    tum = (out / "trajectory.tum").read_text().splitlines()
    assert len(tum) - 1 == summary["verdicts"]["ok"] >= 340  # a header line, then one pose per ok scan
    # an earlier track is kept unless --force
    r = _cli("relocalize", map_path, bag, "--track", "-o", out)
    assert r.exit_code == 2 and "--force" in r.output
    r = _cli("relocalize", map_path, bag, "--track", "-o", out, "--force", "--json")
    assert r.exit_code == 0 and json.loads(r.stdout)["scans"] == 350  # progress lines, if any, are on stderr
    r = _cli("relocalize", map_path, bag, "--output", out, "--initial-pose", "0,0,0")
    assert r.exit_code == 2 and "--track" in r.output


def test_cli_exit_status_4_for_an_ambiguous_answer(tmp_path):
    import cv2

    from carto_cli.core.records import Scan

    # Two identical rooms 12 m apart; the scan sees only one of them.
    n = 480
    px = np.full((n, n), 254, np.uint8)
    rooms = []
    for ox in (2.0, 14.0):
        rooms += [(ox, 2.0, ox + 6.0, 2.0), (ox + 6.0, 2.0, ox + 6.0, 7.0), (ox + 6.0, 7.0, ox, 7.0),
                  (ox, 7.0, ox, 2.0), (ox + 1.0, 5.0, ox + 2.5, 5.0), (ox + 2.5, 5.0, ox + 2.5, 6.0)]
    for x0, y0, x1, y1 in rooms:
        cv2.line(px, (int(x0 / 0.05), n - 1 - int(y0 / 0.05)), (int(x1 / 0.05), n - 1 - int(y1 / 0.05)), 0, 1)
    cv2.imwrite(str(tmp_path / "twins.pgm"), px)
    (tmp_path / "twins.yaml").write_text("image: twins.pgm\nresolution: 0.05\norigin: [0.0, 0.0, 0.0]\n")
    angles = -math.pi + np.arange(360) * (2 * math.pi / 360)
    ranges = np.full(360, 9.0)
    for k, a in enumerate(angles + 0.2):
        d = np.array([math.cos(a), math.sin(a)])
        for x0, y0, x1, y1 in rooms[:6]:
            e = np.array([x1 - x0, y1 - y0])
            m = np.array([[d[0], -e[0]], [d[1], -e[1]]])
            if abs(np.linalg.det(m)) > 1e-12:
                t, u = np.linalg.solve(m, np.array([x0 - 4.0, y0 - 4.0]))
                if t > 0 and 0 <= u <= 1:
                    ranges[k] = min(ranges[k], t)
    scan = Scan(1000.0, ranges.astype(np.float32), angles.astype(np.float32), "laser", "/scan", 0.05, 8.0,
                float(angles[0]), float(angles[1] - angles[0]))
    bag = tmp_path / "one.bag"
    write_recording(iter([scan]), bag, "ros1", topics={"/scan": "sensor_msgs/msg/LaserScan"})
    r = _cli("relocalize", tmp_path / "twins.yaml", bag, "--global")
    assert r.exit_code == 4, r.output
    assert "verdict ambiguous" in r.output

