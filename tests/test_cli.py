import json
import signal
import subprocess
import sys

import pytest
from support import SAMPLE_BAG, shared_path
from typer.testing import CliRunner

from carto_cli.cli import app

runner = CliRunner()


def run(*args):
    return runner.invoke(app, [str(a) for a in args])


def test_info_on_the_real_ccny_bag():
    result = run("info", SAMPLE_BAG, "--json")
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert info["format"] == "ros1"
    (scan,) = [t for t in info["topics"] if t["kind"] == "scan"]
    assert scan["name"] == "/scan" and scan["count"] == 360
    assert scan["scan"]["beams_min"] == scan["scan"]["beams_max"] == 681
    assert 9.5 < scan["rate_hz"] < 10.5
    assert scan["scan"]["frames"] == ["/laser"]
    assert abs(info["duration"] - 35.8) < 0.2
    assert not info["has_odometry"] and not info["has_imu"]
    assert any("5.4% of ranges are out-of-limit" in w for w in info["warnings"])


def test_info_text():
    result = run("info", SAMPLE_BAG)
    assert result.exit_code == 0
    assert "681" in result.stdout and "360" in result.stdout and "Hz" in result.stdout


def test_info_warns_about_invalid_ranges(written_recordings):
    _, paths = written_recordings
    result = run("info", paths["ros1"], "--json")
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert any("NaN" in w for w in info["warnings"]) and any("Inf" in w for w in info["warnings"])
    assert info["has_odometry"] and info["has_imu"]
    assert info["static_transforms"][0]["child"] == "laser"


def test_missing_file_is_one_line_exit_2(tmp_path):
    result = run("info", tmp_path / "missing.bag")
    assert result.exit_code == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "missing.bag" in lines[0] and "no such file" in lines[0]
    assert "Traceback" not in result.output


def test_a_bag_with_a_damaged_index_is_read_with_a_warning():
    """The demo bag as recorded in 2010 (a writer bug in its index records): read from its chunks, said once."""
    orig = shared_path("bags", "ccny_laser_scan_matcher_demo.orig.bag")
    result = run("info", orig)
    assert result.exit_code == 0, result.output
    assert "360 msgs" in result.stdout
    assert "ccny_laser_scan_matcher_demo.orig.bag: damaged index" in result.stdout
    assert "360 messages recovered" in result.stdout


def test_a_bag_with_nothing_readable_is_a_clean_error(tmp_path):
    bad = tmp_path / "bad.bag"
    bad.write_bytes(b"#ROSBAG V2.0\n" + bytes(range(256)) * 4)
    result = run("info", bad)
    assert result.exit_code == 2
    (line,) = result.stderr.strip().splitlines()
    assert "bad.bag" in line and "no message could be recovered" in line


def test_convert_round_trip(tmp_path):
    out = tmp_path / "sample.mcap"
    result = run("convert", SAMPLE_BAG, out)
    assert result.exit_code == 0, result.output
    back = tmp_path / "back.bag"
    assert run("convert", out, back).exit_code == 0
    from carto_cli.io.sources.open import open_recording

    with open_recording(SAMPLE_BAG) as a, open_recording(back) as b:
        pairs = list(zip(a.records(), b.records(), strict=True))
    assert len(pairs) == 360 and all(x.same_as(y) for x, y in pairs)


def test_convert_refuses_to_overwrite_and_unknown_format(tmp_path):
    out = tmp_path / "exists.bag"
    out.write_bytes(b"keep me")
    result = run("convert", SAMPLE_BAG, out)
    assert result.exit_code == 2 and out.read_bytes() == b"keep me"
    result = run("convert", SAMPLE_BAG, tmp_path / "x.bag", "--format", "rosbag9")
    assert result.exit_code == 2 and not (tmp_path / "x.bag").exists()


def test_convert_of_corrupt_input_leaves_no_output(tmp_path):
    """The index is whole, so the bag opens; its 100th message record is broken, found while converting."""
    data = bytearray(SAMPLE_BAG.read_bytes())
    at = -1
    for _ in range(100):
        at = data.index(b"op=\x02", at + 1)
    data[at + 3] = 0x09
    bad = tmp_path / "bad.bag"
    bad.write_bytes(bytes(data))
    out = tmp_path / "out.mcap"
    result = run("convert", bad, out)
    assert result.exit_code == 2, result.output
    assert not out.exists() and list(tmp_path.iterdir()) == [bad]


def test_ambiguous_topic_through_the_cli(tmp_path, written_recordings):
    _, paths = written_recordings
    result = run("convert", paths["mcap"], tmp_path / "o.bag", "--scan-topic", "/nope")
    assert result.exit_code == 2
    assert "/nope" in result.stderr and "/scan" in result.stderr


def test_real_subprocess_entry_point(tmp_path):
    ok = subprocess.run([sys.executable, "-m", "carto_cli", "info", str(SAMPLE_BAG), "--json"],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert json.loads(ok.stdout)["topics"][0]["count"] == 360
    bad = subprocess.run([sys.executable, "-m", "carto_cli", "info", str(tmp_path / "nope.mcap")],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2
    assert bad.stderr.count("\n") == 1 and "Traceback" not in bad.stderr


LEAVING = """
import atexit, sys, threading, time
from carto_cli.cli import main
atexit.register(lambda: print("exit handler ran"))
if {thread}:
    threading.Thread(target=lambda: (time.sleep(3.0), print("thread finished"))).start()  # outlasts the command
sys.argv = ["carto", "info", {path!r}]
main()
"""


@pytest.mark.parametrize("thread", [False, True], ids=["alone", "a-thread-still-working"])
def test_the_entry_point_exits_with_the_commands_status_after_the_exit_handlers_and_waits_for_a_working_thread(
        tmp_path, thread):
    """main() skips the interpreter's teardown (os._exit) but not what an exit must do: the status, the exit
    handlers, flushed output, and a thread still working is waited for."""
    ok = subprocess.run([sys.executable, "-c", LEAVING.format(thread=thread, path=str(SAMPLE_BAG))],
                        capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert "ccny_laser_scan_matcher_demo.bag" in ok.stdout and ok.stdout.rstrip().endswith("exit handler ran")
    assert ("thread finished" in ok.stdout) == thread
    bad = subprocess.run([sys.executable, "-c", LEAVING.format(thread=thread, path=str(tmp_path / "nope.bag"))],
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "nope.bag" in bad.stderr and "exit handler ran" in bad.stdout


def test_map_with_no_profile_says_what_auto_chose_and_judges_the_map(tmp_path):
    out = tmp_path / "m"
    result = run("map", SAMPLE_BAG, "-o", out)
    assert result.exit_code == 0, result.output
    assert "auto: dense scans" in result.stderr and "no odometry -> profile office" in result.stderr
    assert "map quality: ok" in result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["quality"]["verdict"] == "ok"
    assert summary["auto"]["profile"] == "office" and summary["auto"]["detected"]["motion_source"] == "scan matching"
    assert summary["stats"]["scans"] == 360


def _judged(monkeypatch, verdict):
    from carto_cli import pipeline
    from carto_cli.mapping.quality import MapQuality, MapVerdict, QualityCheck

    limit = {"ok": 0.0, "suspect": 20.0, "failed": 60.0}[verdict]
    check = QualityCheck("see_through", limit, 10.0, 50.0, "%", "of scans cross walls")
    monkeypatch.setattr(pipeline, "assess", lambda result, odometry=None: MapQuality(
        MapVerdict(verdict), [] if verdict == "ok" else [check.reason()], [check]))


def test_a_failed_map_exits_3_with_its_outputs_written(tmp_path, monkeypatch):
    _judged(monkeypatch, "failed")
    result = run("map", SAMPLE_BAG, "-o", tmp_path / "m", "--profile", "office")
    assert result.exit_code == 3
    assert "map quality: failed" in result.stderr and "of scans cross walls" in result.stderr
    assert (tmp_path / "m" / "map.pgm").is_file()
    assert json.loads((tmp_path / "m" / "summary.json").read_text())["quality"]["verdict"] == "failed"


def test_strict_turns_a_suspect_map_into_a_failure(tmp_path, monkeypatch):
    _judged(monkeypatch, "suspect")
    assert run("map", SAMPLE_BAG, "-o", tmp_path / "a", "--profile", "office").exit_code == 0
    assert run("map", SAMPLE_BAG, "-o", tmp_path / "b", "--profile", "office", "--strict").exit_code == 3


def test_profile_with_gmapping_prints_the_filter_stages():
    result = run("profile", SAMPLE_BAG, "--algorithm", "gmapping", "--profile", "default", "--max-scans", 15,
                 "--set", "gmapping.particles=5")
    assert result.exit_code == 0, result.output
    assert "algorithm   gmapping: 15 of 15 scans processed, 5 particles" in result.stdout
    for stage in ("motion model", "scan matching", "weighting", "resampling", "map update"):
        assert stage in result.stdout, stage


@pytest.mark.parametrize("command", ["map", "profile", "tune"])
def test_unknown_algorithm_is_a_one_line_error(tmp_path, command):
    extra = ["-o", tmp_path / "out.yaml"] if command == "tune" else []
    result = run(command, SAMPLE_BAG, "--algorithm", "bogus", *extra)
    assert result.exit_code == 2
    (line,) = result.stderr.strip().splitlines()
    assert line == "carto: error: --algorithm: unknown algorithm 'bogus' (choose from cartographer, gmapping, scan-to-map)"
    assert "Traceback" not in result.output and list(tmp_path.iterdir()) == []


def test_algorithm_help_names_the_gmapping_options():
    result = run("map", "--help")
    assert result.exit_code == 0
    assert "--algorithm" in result.stdout and "gmapping.particles=30" in result.stdout


def test_help_states_the_exit_status_contract():
    r = run("--help")
    assert r.exit_code == 0
    text = " ".join(r.output.split())
    for part in ("0 success", "1 internal error", "2 bad input or usage", "3 a check you asked for failed",
                 "130 interrupted (Ctrl-C or SIGTERM)"):
        assert part in text, part


SIGNALLED = """
import os, signal, sys, time
from carto_cli import cli
cli.stop_on_signals()

@cli.handle_errors
def long_work():
    os.kill(os.getpid(), signal.{sig})
    time.sleep(30)  # the signal arrives long before this ends
    print("not interrupted")

try:
    long_work()
except cli.typer.Exit as e:  # what the app would turn into the process's status
    sys.exit(e.exit_code)
"""


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_sigterm_stops_a_command_as_ctrl_c_does(sig):
    # A shell without job control starts background jobs with SIGINT ignored, and Python then keeps it
    # ignored (as nohup intends); a user at a terminal has the default, which the child gets here.
    r = subprocess.run([sys.executable, "-c", SIGNALLED.format(sig=sig)], capture_output=True, text=True,
                       timeout=60, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert r.returncode == 130, (r.returncode, r.stderr)
    assert r.stderr.strip() == "carto: interrupted" and "not interrupted" not in r.stdout


def test_an_internal_error_is_one_line_and_exit_1(capsys):
    import typer

    from carto_cli import cli

    @cli.handle_errors
    def broken():
        raise RuntimeError("boom")

    with pytest.raises(typer.Exit) as e:
        broken()
    assert e.value.exit_code == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "internal error: RuntimeError: boom" in err


def test_global_flags_work_after_the_subcommand(tmp_path):
    from carto_cli.cli import hoist_global_flags

    assert hoist_global_flags(["map", "r.bag", "--debug", "-o", "x"]) == ["--debug", "map", "r.bag", "-o", "x"]
    assert hoist_global_flags(["-q", "info", "r.bag"]) == ["-q", "info", "r.bag"]
    assert hoist_global_flags(["info", "--", "--quiet"]) == ["info", "--", "--quiet"]
    missing = str(tmp_path / "nope.mcap")
    quiet = subprocess.run([sys.executable, "-m", "carto_cli", "info", missing, "--quiet"], capture_output=True,
                           text=True, timeout=120)
    assert quiet.returncode == 2 and "No such option" not in quiet.stderr and "nope.mcap" in quiet.stderr
    debug = subprocess.run([sys.executable, "-m", "carto_cli", "info", missing, "--debug"], capture_output=True,
                           text=True, timeout=120)
    assert "Traceback" in debug.stderr and "nope.mcap" in debug.stderr


def test_map_slices_clouds_as_info_and_convert_do_by_default():
    from carto_cli.io.recording import ReadOptions
    from carto_cli.options import load_options

    tb = load_options().trajectory_builder_2d
    assert (ReadOptions().min_z, ReadOptions().max_z) == (tb.min_z, tb.max_z)


def test_min_z_and_max_z_on_map_become_the_options(tmp_path, monkeypatch):
    import carto_cli.commands.map as map_command

    seen = {}

    def fake_run_map(request, outdir, **kwargs):
        seen["options"] = request.options
        raise KeyboardInterrupt  # stop before mapping

    monkeypatch.setattr(map_command, "run_map", fake_run_map)
    r = run("map", SAMPLE_BAG, "-o", tmp_path / "m", "--profile", "office", "--min-z", "-0.25", "--max-z", "0.5",
            "--set", "trajectory_builder_2d.min_z=-3")
    assert r.exit_code == 130
    tb = seen["options"].trajectory_builder_2d
    assert (tb.min_z, tb.max_z) == (-0.25, 0.5)  # --min-z wins over --set
    r = run("map", SAMPLE_BAG, "-o", tmp_path / "m", "--min-z", "1", "--max-z", "0")
    assert r.exit_code == 2 and "min_z" in r.stderr


@pytest.mark.parametrize("extra", [[], ["--algorithm", "gmapping", "--set", "gmapping.particles=5"]])
def test_two_processes_write_byte_identical_maps(tmp_path, extra):
    """Same input, same options: the same bytes, whatever the threads did (GMapping's particles, loop step and
    re-matching run on threads: one process gets one thread, the other two; GMapping draws from its seeded
    generator)."""
    outs = []
    for name, jobs in (("a", "1"), ("b", "2")):
        out = tmp_path / name
        r = subprocess.run([sys.executable, "-m", "carto_cli", "--quiet", "map", str(SAMPLE_BAG), "-o", str(out),
                            "--jobs", jobs, *extra], capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr
        outs.append(out)
    for f in ("map.pgm", "map.yaml", "map.png", "trajectory.tum", "map.carto"):
        assert (outs[0] / f).read_bytes() == (outs[1] / f).read_bytes(), f


@pytest.mark.parametrize("command", ["info", "convert", "relocalize", "map", "profile", "tune"])
def test_every_command_that_reads_clouds_takes_the_z_slice(command):
    r = run(command, "--help")
    assert r.exit_code == 0 and "--min-z" in r.output and "--max-z" in r.output



def test_cut_short_carmen_log_is_read_up_to_the_cut_by_every_command(tmp_path):
    from support import sim_carmen_log

    text = sim_carmen_log(tmp_path / "whole.clf").read_text()
    last = text.rindex("\n", 0, len(text) - 1) + 1
    cut = tmp_path / "cut.clf"
    cut.write_text(text[:last + 20])  # the case: the last line is an ODOM, which mapping does not read
    assert text[last:].startswith("ODOM")
    n = text.count("\n")
    warning = f"cut.clf: cut short (line {n} ends mid-message): read up to the cut, {n - 1} messages recovered"
    r = run("info", cut)
    assert r.exit_code == 0, r.output
    assert [line.strip() for line in r.stdout.splitlines() if "cut short" in line] == [warning]
    commands = [("convert", cut, tmp_path / "cut.mcap"), ("map", cut, "-o", tmp_path / "m"),
                ("relocalize", tmp_path / "m" / "map.carto", cut, "--scan-index", 3, "--initial-pose", "0,0,0"),
                ("profile", cut)]
    for args in commands:
        r = run(*args)
        assert r.exit_code == 0, (args[0], r.output)
        assert [line for line in r.stderr.splitlines() if "cut short" in line] == [f"carto: warning: {warning}"], \
            args[0]


KERNEL_INTERRUPTED = """
import ctypes, signal, sys
import numba, numpy as np
from carto_cli import cli

c_raise = getattr(ctypes.CDLL(None), "raise")
c_raise.argtypes, c_raise.restype = [ctypes.c_int], ctypes.c_int

@numba.njit(parallel=True)
def kernel(n, sig):
    out = np.zeros(n)
    if sig:
        c_raise(sig)  # the signal arrives while compiled code runs: Python's handler waits for Python code
    for i in numba.prange(n):
        out[i] = i
    return out, out.copy()  # handing the arrays back runs Python code (numba's unpickling), which raises

@cli.app.command("spin")
@cli.handle_errors
def spin():
    kernel(1, 0)
    kernel(10, int(signal.{sig}))
    print("not interrupted")

sys.argv = ["carto", "spin"]
cli.main()
"""


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_interrupt_in_compiled_code_exits_130(sig):
    """Issue 42, item 2: a signal handled inside a numba kernel comes out of it as a SystemError ("returned a
    result with an exception set"), which was reported as an internal error, exit 1."""
    r = subprocess.run([sys.executable, "-c", KERNEL_INTERRUPTED.format(sig=sig)], capture_output=True, text=True,
                       timeout=120, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert (r.returncode, r.stderr.strip()) == (130, "carto: interrupted"), r.stderr
    assert "not interrupted" not in r.stdout


def _interrupt_log(path, *, dense: bool):
    """The simulated loop as a CARMEN log: key scans 0.5 m apart (1 Hz, FLASER; GMapping under auto), or dense
    scans (10 Hz, ROBOTLASER1 as in bench-dense, two laps; Cartographer)."""
    import math

    from support import write_carmen_log

    from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate

    world = loop_building()
    sim = simulate(world, loop_trajectory(world, laps=2 if dense else 1), duration=None if dense else 40.0,
                   lidar=Lidar(beams=360 if dense else 181, fov=1.5 * math.pi if dense else math.pi, dropout=0.0),
                   scan_rate=10.0 if dense else 1.0, odom_rate=10.0, imu_rate=0.0)
    return write_carmen_log(sim, path, robotlaser=dense, no_return=30.0)


def _interrupted_map(recording, outdir, sig, to_group: bool, delay: float):
    """`carto map` signalled ``delay`` s after its 'auto:' line (the survey done, the kernels loaded: mapping):
    (exit status, stderr), or None if the map was done first."""
    import os
    import threading
    import time

    # SIGINT as at a terminal (see test_sigterm_stops_a_command_as_ctrl_c_does), in a group of its own.
    p = subprocess.Popen([sys.executable, "-m", "carto_cli", "map", str(recording), "-o", str(outdir)],
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    lines: list[str] = []
    mapping = threading.Event()

    def read():
        for line in p.stderr:
            lines.append(line)
            if line.startswith("auto:"):
                mapping.set()
        mapping.set()

    reader = threading.Thread(target=read)
    reader.start()
    try:
        mapping.wait(timeout=300)
        time.sleep(delay)
        if p.poll() is not None:
            return None
        (os.killpg if to_group else os.kill)(p.pid, getattr(signal, sig))  # the group: Ctrl-C at a terminal, timeout
        p.wait(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
        p.wait()
        reader.join()
    # Its children (the graph's process, the reader, kernel helpers) go with it: its group empties (one that only
    # dies with its parent, by PR_SET_PDEATHSIG, takes a moment).
    for _ in range(100):
        try:
            os.killpg(p.pid, 0)
        except ProcessLookupError:
            break
        time.sleep(0.1)
    else:
        pytest.fail(f"a process of carto map's group outlived it ({sig})")
    if p.returncode == 0:
        return None  # the signal came once the map was written, as the process left: it only finished
    return p.returncode, "".join(lines)


def test_interrupts_at_random_moments_of_map_exit_130(tmp_path):
    """Issue 42, item 2, in small: SIGINT and SIGTERM (to the process, or to its group as a terminal's Ctrl-C and
    `timeout` send them) at random moments of mapping a key-scan log (GMapping) and a dense one (Cartographer):
    exit 130, one line 'interrupted', nothing half-written. bench/interrupts.py runs 20 moments on the real logs."""
    import random
    from concurrent.futures import ThreadPoolExecutor

    key = _interrupt_log(tmp_path / "key.clf", dense=False)
    dense = _interrupt_log(tmp_path / "dense.clf", dense=True)
    # The longest delay stays within the mapping pass (4 s of GMapping, 1 s of Cartographer, on an idle machine).
    runs = [(key, "SIGINT", False, 2.0), (key, "SIGTERM", True, 2.0), (dense, "SIGINT", True, 0.6),
            (dense, "SIGTERM", False, 0.6), (dense, "SIGINT", False, 0.6), (dense, "SIGTERM", True, 0.6)]
    rng = random.Random()

    def one(k: int):
        recording, sig, to_group, longest = runs[k]
        for attempt in range(4):
            delay = rng.uniform(0.0, longest / 2 ** attempt)
            outdir = tmp_path / f"out{k}-{attempt}"
            outcome = _interrupted_map(recording, outdir, sig, to_group, delay)
            if outcome is not None:
                return recording.name, sig, to_group, delay, outdir, *outcome
        pytest.fail(f"{recording.name} was mapped before every moment chosen to interrupt it")

    with ThreadPoolExecutor(2) as pool:
        outcomes = list(pool.map(one, range(len(runs))))
    for name, sig, to_group, delay, outdir, status, stderr in outcomes:
        what = f"{sig} to the {'group' if to_group else 'process'} {delay:.2f} s into mapping {name}: {stderr}"
        assert status == 130, what
        assert stderr.splitlines()[-1] == "carto: interrupted", what
        assert "Traceback" not in stderr and "internal error" not in stderr and stderr.count("interrupted") == 1, what
        # Nothing half-written: no output directory, or (interrupted once the set was in place) the whole set.
        left = sorted(p.name for p in outdir.iterdir()) if outdir.exists() else []
        assert left in ([], ["map.carto", "map.pgm", "map.png", "map.yaml", "summary.json", "trajectory.tum"]), what
