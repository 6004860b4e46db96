"""`carto map` end to end through the CLI: outputs, their formats, --load-state, --no-state, --algorithm,
bad input."""
import json
from pathlib import Path

import numpy as np
import pytest
import yaml
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.core.errors import CartoError
from carto_cli.io.map_file import load_map
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.trajectory import read_trajectory
from carto_cli.pipeline import MapRequest
from carto_cli.sim.lidar import Lidar
from carto_cli.sim.recording import simulate
from carto_cli.sim.trajectory import loop_trajectory
from carto_cli.sim.world import loop_building

runner = CliRunner()
FAST = ["--set", "trajectory_builder_2d.submaps.num_range_data=20"]


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory):
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=20.0, lidar=Lidar(beams=270), laser_pose=(0.15, 0.0, 0.0))
    rec = sim.recording()
    path = tmp_path_factory.mktemp("sim") / "sim.bag"
    write_recording(rec.records(), path, "ros1", static_transforms=rec.static_transforms(),
                    topics={t.name: t.msgtype for t in rec.topics()})
    return path, sim


def test_map_writes_every_output(tmp_path, sim_bag):
    bag, sim = sim_bag
    out = tmp_path / "out"
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), *FAST])
    assert r.exit_code == 0, r.output
    assert "scans" in r.stdout and "submaps" in r.stdout
    meta = yaml.safe_load((out / "map.yaml").read_text())
    assert meta["image"] == "map.pgm" and meta["resolution"] == pytest.approx(0.05)
    assert meta["occupied_thresh"] == 0.65 and meta["free_thresh"] == 0.196 and meta["negate"] == 0
    pgm = (out / "map.pgm").read_bytes()
    assert pgm.startswith(b"P5")
    header = pgm.split(b"\n", 4)
    w, h = map(int, header[2].split())
    pixels = np.frombuffer(pgm[-w * h:], np.uint8)
    occupancy = (255 - pixels.astype(float)) / 255  # how map_server reads it (negate 0)
    assert (occupancy > 0.65).sum() > 100 and (occupancy < 0.196).sum() > 1000  # walls and free space
    assert (pixels == 205).sum() > 0  # unknown stays unknown
    assert (occupancy < 0.196).sum() > 5 * (occupancy > 0.65).sum()  # a building is mostly free space
    assert (out / "map.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    traj = read_trajectory(out / "trajectory.tum")
    assert len(traj) == sim.counts()["/scan"]  # a pose for every scan
    m = load_map(out / "map.carto")
    assert len(m.node_times) > 0 and len(m.submaps) > 0
    assert np.allclose(m.laser_pose, [0.15, 0.0, 0.0])  # the mount came from the bag's static TF


def test_load_state_continues_the_map(tmp_path, sim_bag):
    bag, _ = sim_bag
    first, second = tmp_path / "a", tmp_path / "b"
    assert runner.invoke(app, ["map", str(bag), "-o", str(first), *FAST]).exit_code == 0
    r = runner.invoke(app, ["map", str(bag), "-o", str(second), "--load-state", str(first / "map.carto"), *FAST])
    assert r.exit_code == 0, r.output
    m = load_map(second / "map.carto")
    assert set(np.unique(m.node_trajectories).tolist()) == {0, 1}
    lc = m.constraints.is_loop_closure
    cross = m.node_trajectories[m.constraints.node[lc]] != m.submap_trajectories[m.constraints.submap[lc]]
    assert cross.sum() > 0  # the new trajectory was linked to the old one
    # The same drive mapped twice: the second trajectory lands on the first.
    g, t = m.node_global_poses, m.node_trajectories
    assert np.linalg.norm(g[t == 1][0, :2] - g[t == 0][0, :2]) < 0.3
    # Every trajectory after the joint optimization, and how they are linked
    report = json.loads((second / "sessions.json").read_text())
    assert [s["linked"] for s in report["sessions"]] == [True, True] and report["links"][0]["trajectories"] == [0, 1]
    earlier, later = read_trajectory(second / "trajectory_0.tum"), read_trajectory(second / "trajectory_1.tum")
    assert len(earlier) == len(m.node_times[t == 0])  # a saved map knows its earlier sessions by their nodes
    assert len(later) == len(read_trajectory(second / "trajectory.tum"))
    assert "sessions: trajectories 0 and 1:" in r.stdout


def test_several_recordings_make_one_map(tmp_path, sim_bag):
    bag, sim = sim_bag
    out = tmp_path / "o"
    r = runner.invoke(app, ["map", str(bag), str(bag), "-o", str(out), *FAST])
    assert r.exit_code == 0, r.output
    report = json.loads((out / "sessions.json").read_text())
    assert [(s["trajectory"], s["recording"], s["linked"]) for s in report["sessions"]] == \
        [(0, bag.name, True), (1, bag.name, True)]
    first, second = read_trajectory(out / "trajectory_0.tum"), read_trajectory(out / "trajectory_1.tum")
    assert len(first) == len(second) == sim.counts()["/scan"]
    # The same drive twice: the two trajectories coincide in the map frame
    assert np.max(np.linalg.norm(first.xy - second.xy, axis=1)) < 0.3
    assert json.loads((out / "summary.json").read_text())["sessions"] == report
    assert load_map(out / "map.carto").metadata.recordings == (bag.name, bag.name)
    # A later recording that is not there is said at once, before the first is mapped, and nothing is written
    r = runner.invoke(app, ["map", str(bag), str(tmp_path / "no-such.bag"), "-o", str(tmp_path / "x"), *FAST])
    assert r.exit_code != 0 and "no-such.bag: no such file" in r.output and "mapping" not in r.stderr
    assert not (tmp_path / "x").exists()
    # One recording into the same directory: the earlier per-session files go with the earlier set
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--force", *FAST])
    assert r.exit_code == 0, r.output
    assert not list(out.glob("trajectory_*.tum")) and not (out / "sessions.json").exists()


def test_no_state_and_no_loop_closure(tmp_path, sim_bag):
    bag, _ = sim_bag
    out = tmp_path / "o"
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--no-state", "--no-loop-closure", *FAST])
    assert r.exit_code == 0, r.output
    assert "0 loop closures" in r.stdout
    assert not (out / "map.carto").exists() and (out / "map.pgm").exists()


def test_bad_input_leaves_no_outputs(tmp_path, sim_bag):
    bag, _ = sim_bag
    out = tmp_path / "o"
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--set", "trajectory_builder_2d.submaps.num_range_data=0"])
    assert r.exit_code == 2 and "num_range_data" in r.stderr
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--profile", "no-such-profile"])
    assert r.exit_code == 2 and "no-such-profile" in r.stderr
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--laser-pose", "1,2"])
    assert r.exit_code == 2 and "--laser-pose" in r.stderr
    bad_state = tmp_path / "bad.carto"
    bad_state.write_bytes(b"not a map")
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--load-state", str(bad_state)])
    assert r.exit_code == 2 and "bad.carto" in r.stderr
    assert not out.exists()


def test_run_map_as_a_library_call(sim_bag, tmp_path, monkeypatch):
    from carto_cli.commands.map import compile_note, default_outdir, run_map, summary_line
    from carto_cli.core.timing import StageTimer
    from carto_cli.options import load_options

    bag, sim = sim_bag
    copy = tmp_path / "drive.2024.bag"
    copy.write_bytes(bag.read_bytes())
    (tmp_path / "here").mkdir()
    monkeypatch.chdir(tmp_path / "here")
    assert default_outdir(copy) == Path("drive.2024_map")
    timer, totals = StageTimer(), []
    options = load_options(None, FAST[1:])
    result, outputs = run_map(MapRequest(copy, options), None, timer=timer, on_total=totals.append, state=False)
    assert outputs.yaml.resolve() == tmp_path / "here" / "drive.2024_map" / "map.yaml" and outputs.state is None
    assert totals == [sim.counts()["/scan"]]
    assert timer.snapshot().scans == result.stats["scans"]
    before = timer.snapshot().wall_ns
    assert timer.snapshot().wall_ns == before  # stopped once the outputs were written
    assert summary_line(result).startswith(f"{result.stats['scans']} scans, ")
    note = compile_note(timer)
    assert note == "" or note.startswith(" (incl. ")


def test_the_compile_note_speaks_only_of_compiling():
    """A warm-up stage over a second is named compiling only when kernels were compiled, not when a busy machine
    took that long to load them from the cache."""
    from carto_cli.commands.map import compile_note
    from carto_cli.core import kernels
    from carto_cli.core.timing import StageTimer

    ticks = iter(range(0, 10**12, 1_600_000_000))  # every clock read 1.6 s after the one before
    timer = StageTimer(clock=lambda: next(ticks))
    with timer.stage(kernels.STAGE):
        pass
    timer.stop()
    assert compile_note(timer, compiled=False) == ""
    assert compile_note(timer, compiled=True) == " (incl. 2 s compiling kernels: later runs load them from the cache)"
    quick = StageTimer(clock=lambda: 0)
    with quick.stage(kernels.STAGE):
        pass
    assert compile_note(quick, compiled=True) == ""


GMAPPING_FAST = ["--algorithm", "gmapping", "--set", "gmapping.particles=5"]


def test_gmapping_writes_every_output_and_names_itself(tmp_path, sim_bag):
    bag, sim = sim_bag
    out = tmp_path / "gm"
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), *GMAPPING_FAST])
    assert r.exit_code == 0, r.output
    assert {p.name for p in out.iterdir()} == {"map.pgm", "map.yaml", "map.png", "trajectory.tum", "map.carto",
                                               "summary.json"}
    summary = json.loads((out / "summary.json").read_text())
    assert summary["algorithm"] == "gmapping"
    # Its loop closures are the final refinement's, between passes of the best particle's trajectory.
    assert summary["stats"]["particles"] == 5
    assert 0 <= summary["stats"]["loop_closures"] <= summary["stats"]["loop_closure_candidates"]
    assert r.stdout.startswith(f"gmapping: {sim.counts()['/scan']} scans (")
    assert "5 particles" in r.stdout and "resamplings" in r.stdout
    # No profile: auto still chose Cartographer's options, and its line says which system mapped.
    # Auto would pick Cartographer for this dense recording; the line says which system maps.
    assert "auto: " in r.stderr and "algorithm gmapping" in r.stderr
    assert len(read_trajectory(out / "trajectory.tum")) == sim.counts()["/scan"]
    assert len(load_map(out / "map.carto").submaps) > 0


def test_scan_to_map_writes_every_output_and_names_itself(tmp_path, sim_bag):
    bag, sim = sim_bag
    out = tmp_path / "s2m"
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--algorithm", "scan-to-map"])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["algorithm"] == "scan-to-map" and summary["stats"]["particles"] == 0
    assert r.stdout.startswith(f"scan-to-map: {sim.counts()['/scan']} scans (")
    assert "MB distance map" in r.stdout and "particles" not in r.stdout
    assert "auto: " in r.stderr and "algorithm scan-to-map" in r.stderr
    assert len(read_trajectory(out / "trajectory.tum")) == sim.counts()["/scan"]
    assert len(load_map(out / "map.carto").submaps) > 0


def test_cartographer_summary_names_its_algorithm(tmp_path, sim_bag):
    bag, _ = sim_bag
    out = tmp_path / "c"
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--no-state", *FAST])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "summary.json").read_text())["algorithm"] == "cartographer"
    assert "auto: " in r.stderr and "algorithm" not in r.stderr  # the auto line as before --algorithm


def test_unknown_algorithm_is_one_line(tmp_path, sim_bag):
    bag, _ = sim_bag
    out = tmp_path / "o"
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--algorithm", "bogus"])
    assert r.exit_code == 2
    (line,) = r.stderr.strip().splitlines()
    assert "--algorithm" in line and "'bogus'" in line and "cartographer, gmapping" in line
    assert "Traceback" not in r.output and not out.exists()


def test_gmapping_cannot_continue_a_saved_map(tmp_path, sim_bag):
    bag, _ = sim_bag
    out = tmp_path / "o"
    state = tmp_path / "earlier.carto"
    state.write_bytes(b"never read")  # refused before it is opened
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--load-state", str(state), *GMAPPING_FAST])
    assert r.exit_code == 2
    (line,) = r.stderr.strip().splitlines()
    assert "earlier.carto" in line and "gmapping" in line and "--load-state" in line
    assert "Traceback" not in r.output and not out.exists()


def test_run_map_refuses_gmapping_with_a_state_before_reading(tmp_path):
    from carto_cli.commands.map import run_map
    from carto_cli.options import load_options

    with pytest.raises(CartoError, match="gmapping starts every map afresh") as e:
        run_map(MapRequest(tmp_path / "no-such.bag", load_options(), "gmapping", load_state=tmp_path / "m.carto"),
                tmp_path / "o")
    assert e.value.path == str(tmp_path / "m.carto")
    with pytest.raises(CartoError, match="unknown algorithm 'ekf'"):
        run_map(MapRequest(tmp_path / "no-such.bag", load_options(), "ekf"), tmp_path / "o")


def test_summary_line_per_algorithm():
    from types import SimpleNamespace

    from carto_cli.commands.map import summary_line

    carto = {"scans": 200, "nodes": 40, "submaps": 3, "loop_closures": 2, "wall_time_s": 4.0, "scans_per_s": 50.0}
    assert summary_line(SimpleNamespace(stats=carto)) == (
        "200 scans, 40 nodes, 3 submaps, 2 loop closures, 4.0 s wall, 50 scans/s mapping")
    gm = dict(carto, algorithm="gmapping", processed_scans=83, particles=30, resamplings=7, loop_closures=0,
              map_memory_peak_bytes=12 * 2**20)
    assert summary_line(SimpleNamespace(stats=gm)) == (
        "gmapping: 200 scans (83 processed), 30 particles, 7 resamplings, 12 MB peak map, 4.0 s wall, 50 scans/s mapping")


def test_an_output_path_that_is_a_file_is_refused_before_mapping(tmp_path, sim_bag):
    bag, _ = sim_bag
    taken = tmp_path / "notes.txt"
    taken.write_text("keep me\n")
    r = runner.invoke(app, ["map", str(bag), "-o", str(taken)])
    assert r.exit_code == 2
    assert f"{taken}: exists and is not a directory" in r.output and "Traceback" not in r.output
    assert taken.read_text() == "keep me\n"
    assert "scans" not in r.output  # refused before the recording was mapped


def _snapshot(out):
    return {p.name: p.read_bytes() for p in sorted(out.iterdir())}


def test_an_earlier_map_is_kept_unless_force(tmp_path, sim_bag):
    bag, _ = sim_bag
    out = tmp_path / "o"
    assert runner.invoke(app, ["map", str(bag), "-o", str(out), *FAST]).exit_code == 0
    before = _snapshot(out)
    assert set(before) == {"map.pgm", "map.yaml", "map.png", "trajectory.tum", "map.carto", "summary.json"}

    r = runner.invoke(app, ["map", str(bag), "-o", str(out), *FAST])
    assert r.exit_code == 2 and "Traceback" not in r.output
    assert f"{out}: already holds a map (map.pgm, " in r.output and "--force" in r.output
    assert "scans" not in r.stdout  # refused before mapping
    assert _snapshot(out) == before

    # --force replaces the whole set: an output this run does not write does not survive from the last one.
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--no-state", "--force", *FAST])
    assert r.exit_code == 0, r.output
    assert not (out / "map.carto").exists() and (out / "map.pgm").exists()
    assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []


def test_an_interrupted_write_leaves_the_earlier_set(tmp_path, sim_bag, monkeypatch):
    from carto_cli.io import map_file

    bag, _ = sim_bag
    out = tmp_path / "o"
    assert runner.invoke(app, ["map", str(bag), "-o", str(out), *FAST]).exit_code == 0
    before = _snapshot(out)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt  # Ctrl-C after the map, the image and the trajectory were staged

    monkeypatch.setattr(map_file, "save_map", interrupted)
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--force", *FAST])
    assert r.exit_code == 130
    assert _snapshot(out) == before  # nothing of the half-written set moved in, nothing left behind


def test_a_staging_directory_of_a_killed_run_is_cleared(tmp_path):
    from carto_cli.io.atomic import STAGING_PREFIX, output_set

    out = tmp_path / "o"
    dead = out / f"{STAGING_PREFIX}999999999-abc"  # no such pid
    dead.mkdir(parents=True)
    (dead / "map.pgm").write_bytes(b"half")
    with output_set(out, ["a.txt"]) as staging:
        (staging / "a.txt").write_text("x")
    assert sorted(p.name for p in out.iterdir()) == ["a.txt"]


def test_a_failed_first_write_leaves_no_directory(tmp_path):
    from carto_cli.io.atomic import output_set

    out = tmp_path / "new"
    with pytest.raises(RuntimeError), output_set(out, ["a.txt"]) as staging:
        (staging / "a.txt").write_text("x")
        raise RuntimeError("disk full")
    assert not out.exists()


@pytest.mark.parametrize("name, want", [
    ("robot.2024.05.01.bag", "robot.2024.05.01_map"),
    ("scans.clf.gz", "scans_map"),
    ("run.MCAP", "run_map"),
    ("rosbag2_2024_05_01-10_00_00", "rosbag2_2024_05_01-10_00_00_map"),
    ("intel.log", "intel_map"),
    (".bag", ".bag_map"),
])
def test_default_output_names_keep_the_whole_name(tmp_path, name, want):
    from carto_cli.commands.map import default_outdir

    assert default_outdir(tmp_path / name) == Path(want)


def test_default_output_folders_are_made_in_the_current_directory(tmp_path, monkeypatch):
    """Issue 42, item 11: `carto map REC` / `relocalize --track` with no -o wrote next to the recording (often a
    read-only share or a robot's disk); like rosbag's tools, carto writes where it is run."""
    from carto_cli.commands.map import default_outdir
    from carto_cli.commands.relocalize import default_track_dir

    monkeypatch.chdir(tmp_path)
    recording = Path("/data/robots/run.bag")
    assert default_outdir(recording).resolve() == tmp_path / "run_map"
    assert default_track_dir(recording).resolve() == tmp_path / "run_track"


def left_running(out, wait_s: float = 10.0) -> list[int]:
    """Processes still running whose command line names ``out`` (forked children share their parent's), after
    up to ``wait_s`` for them to go."""
    import os
    import time

    deadline = time.monotonic() + wait_s
    while True:
        pids = []
        for entry in os.listdir("/proc"):
            try:
                with open(f"/proc/{entry}/cmdline", "rb") as f:
                    line = f.read()
                with open(f"/proc/{entry}/stat") as f:
                    zombie = f.read().rsplit(")", 1)[1].split()[0] == "Z"
            except OSError:  # not a process, or gone
                continue
            if str(out).encode() in line.split(b"\0") and not zombie:
                pids.append(int(entry))
        if not pids or time.monotonic() > deadline:
            return pids
        time.sleep(0.1)


def test_sigkill_at_any_moment_leaves_no_partial_output(tmp_path):
    """`carto map` killed with SIGKILL at ten moments from start-up to the writing of the outputs: the output
    directory holds either nothing or a whole set identical to an uninterrupted run's, and where the kill left
    anything (a staging directory, a whole set), the next run (with --force) finishes and leaves no temporary
    directory behind. (Where it left no directory, the next run is a first run; the reference is one.) No process
    of the killed run stays behind (its forked children once waited for ever on a pipe)."""
    import random
    import signal
    import subprocess
    import sys
    import time

    from support import SAMPLE_BAG

    def command(out, *extra):
        return [sys.executable, "-m", "carto_cli", "--quiet", "map", str(SAMPLE_BAG), "-o", str(out), *extra]

    reference = tmp_path / "reference"
    started = time.perf_counter()
    assert subprocess.run(command(reference), capture_output=True, timeout=600).returncode == 0
    full = time.perf_counter() - started
    names = ["map.pgm", "map.yaml", "map.png", "trajectory.tum", "map.carto", "summary.json"]
    want = {n: (reference / n).read_bytes() for n in names if n != "summary.json"}  # summary has timings
    rng = random.Random(7)
    for k in range(10):
        out = tmp_path / f"run{k}"
        proc = subprocess.Popen(command(out, "--force"), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(0.05, 1.1) * full)  # from start-up to after the end
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
        assert left_running(out) == [], k  # the forked reader and pose graph die with it
        visible = sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) if out.exists() else []
        assert visible in ([], sorted(names)), (k, visible)
        for n in want if visible else ():
            assert (out / n).read_bytes() == want[n], (k, n)
        if not out.exists():
            continue
        r = subprocess.run(command(out, "--force"), capture_output=True, timeout=600)
        assert r.returncode == 0, r.stderr
        assert [p.name for p in out.iterdir() if p.name.startswith(".")] == []
        assert all((out / n).read_bytes() == want[n] for n in want)


def test_a_full_disk_is_one_line_and_keeps_the_earlier_map(tmp_path, sim_bag, monkeypatch):
    import errno

    from carto_cli.io import map_image

    bag, _ = sim_bag
    out = tmp_path / "o"
    assert runner.invoke(app, ["map", str(bag), "-o", str(out), *FAST]).exit_code == 0
    before = _snapshot(out)
    real = map_image.write_png

    def full(path, bgr):
        real(path, bgr)  # the image lands in the staging directory, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(map_image, "write_png", full)
    monkeypatch.setattr("carto_cli.commands.map.write_png", full)
    r = runner.invoke(app, ["map", str(bag), "-o", str(out), "--force", *FAST])
    assert r.exit_code == 2 and "Traceback" not in r.output
    assert f"{out}: cannot write the outputs: No space left on device; the earlier outputs are kept" in r.stderr
    assert [line for line in r.stderr.splitlines() if "error" in line] == [
        f"carto: error: {out}: cannot write the outputs: No space left on device; the earlier outputs are kept"]
    assert _snapshot(out) == before


def test_two_jobs_decode_the_recording_in_a_process_of_their_own(sim_bag, tmp_path):
    """With two jobs the records come from a reading process (its time shows as the concurrent stage ``read
    ahead``) and the map is the one a single job makes."""
    from carto_cli.commands.map import run_map
    from carto_cli.core.timing import StageTimer
    from carto_cli.io.read_ahead import STAGE
    from carto_cli.options import load_options

    bag, sim = sim_bag
    options = load_options(None, FAST[1:])
    runs = {}
    for jobs in (1, 2):
        timer = StageTimer()
        _, outputs = run_map(MapRequest(bag, options, jobs=jobs), tmp_path / str(jobs), timer=timer, state=False)
        runs[jobs] = (timer.snapshot().find(f"{STAGE}/read recording"), outputs.trajectory.read_bytes(),
                      outputs.pgm.read_bytes())
    assert runs[1][0] is None and runs[2][0] is not None
    assert runs[2][0].count >= sim.counts()["/scan"]  # every record the pass read, decoded over there
    assert runs[1][1:] == runs[2][1:]


def test_summary_line_wall_includes_compile():
    """Issue 42, item 10: a first run said "0.6 s wall ... (incl. 36 s compiling kernels)": the wall was the
    mapping's alone while the kernels compiled before it (here inside the survey, another phase). The line's wall
    is now the run's, which holds the compiling it claims to include; scans/s stays the mapping's."""
    from types import SimpleNamespace

    from carto_cli.commands.map import summary_line
    from carto_cli.core import kernels
    from carto_cli.core.timing import StageTimer

    now = [0]
    timer = StageTimer(clock=lambda: now[0])
    now[0] += 500_000_000  # opening the recording
    with timer.stage("survey"), timer.stage(kernels.STAGE):
        now[0] += 36_000_000_000
    now[0] += 600_000_000  # mapping
    timer.stop()
    stats = {"scans": 30, "nodes": 6, "submaps": 1, "loop_closures": 0, "wall_time_s": 0.6, "scans_per_s": 50.0}
    assert summary_line(SimpleNamespace(stats=stats), timer, compiled=True) == (
        "30 scans, 6 nodes, 1 submaps, 0 loop closures, 37.1 s wall (incl. 36 s compiling kernels: later runs load "
        "them from the cache), 50 scans/s mapping")
    # A warm run: the run's wall, no note.
    assert summary_line(SimpleNamespace(stats=stats), timer, compiled=False) == (
        "30 scans, 6 nodes, 1 submaps, 0 loop closures, 37.1 s wall, 50 scans/s mapping")


def test_lifelong_sessions_say_what_is_trimmed_and_continue(tmp_path):
    """Two sessions of a building that changed between them: with --lifelong the earlier one's superseded submaps
    are trimmed from map.carto and said (stdout, sessions.json); the trimmed map loads and is continued by a third;
    by default (last seen) nothing is trimmed."""
    from carto_cli.commands.map import run_map, sessions_lines
    from carto_cli.mapping.lifelong import SessionPolicy
    from carto_cli.pipeline import Auto
    from carto_cli.sim.sessions import route_sessions
    from carto_cli.sim.world import rearranged_loop_building

    recordings, _ = route_sessions(list(rearranged_loop_building()), 2)
    kept, kept_out = run_map(MapRequest(recordings[0], Auto(), later=(recordings[1],)), tmp_path / "kept")
    whole = load_map(kept_out.state)
    assert kept.trimmed == () and "trimmed" not in (tmp_path / "kept" / "sessions.json").read_text()
    result, outputs = run_map(MapRequest(recordings[0], Auto(), later=(recordings[1],),
                                         sessions=SessionPolicy.LIFELONG), tmp_path / "ab")
    assert result.trimmed and any(line.startswith("trimmed: ") for line in sessions_lines(result))
    report = json.loads((tmp_path / "ab" / "sessions.json").read_text())
    gone = report["sessions"][0]["trimmed"]
    saved = load_map(outputs.state)
    assert len(saved.submaps) == whole.num_submaps - gone["submaps"]
    assert saved.num_nodes == whole.num_nodes - gone["nodes"]
    # Every session's trajectory file stays whole: it was written from the poses before trimming
    assert len(read_trajectory(tmp_path / "ab" / "trajectory_0.tum")) == len(result.sessions[0].times)
    again, _ = run_map(MapRequest(recordings[1], Auto(), load_state=outputs.state), tmp_path / "abb")
    assert again.quality is not None and again.quality.ok, again.quality.line()
    assert all(s.linked for s in again.sessions)
