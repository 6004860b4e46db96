"""bench/run --peers lama without LaMa: bench/lama.sh against a stand-in build.sh, peer runs against a stand-in
driver (a script writing a trajectory of known error), and the side-by-side table of the document."""
import gzip
import importlib.util
import os
import subprocess
import sys
import textwrap
from pathlib import Path
from types import SimpleNamespace

import pytest

ROOT = Path(__file__).resolve().parents[2]
HARNESS = ROOT / "bench" / "harness.py"


@pytest.fixture(scope="module")
def harness():
    spec = importlib.util.spec_from_file_location("carto_bench_harness_peers", HARNESS)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]


# Writes a trajectory that moves 1.1 m per second where the relations say 1 m (error 0.1 m), with one repeated
# timestamp; burns 0.3 s of CPU and holds 64 MB so that wait4's figures have something to show. "pf" fails.
FAKE_DRIVER = """\
    import sys, time
    mode, log, prefix = sys.argv[1:4]
    if mode == "pf":
        print("pf: boom", file=sys.stderr)
        sys.exit(3)
    ballast = bytearray(64 * 2**20)
    ballast[::4096] = b"x" * len(ballast[::4096])
    while time.process_time() < 0.3:
        pass
    rows = [f"{t:.3f} {1.1 * t:.3f} 0 0" for t in range(11)]
    with open(prefix + ".scans.txt", "w") as f:
        f.write("\\n".join(rows[:5] + rows[4:]) + "\\n")
"""


def _case(harness, tmp_path: Path):
    log = tmp_path / "scans.clf.gz"
    with gzip.open(log, "wt") as f:
        f.write("".join(f"ODOM {t} 0 0\nFLASER 2 1 1 0 0 0 {t} 0 0 0 0 0 {t} host {t}\n" for t in range(4)))
    rel = tmp_path / "relations.txt"
    rel.write_text("".join(f"{t} {t + 1} 1 0 0 0 0 0\n" for t in range(10)))
    return harness.Case("hall", "bench", "hall", str(log), str(rel), None, 2)


def test_peer_runs_are_measured_and_scored(harness, tmp_path):
    driver = tmp_path / "lama_driver"
    driver.write_text(f"#!{sys.executable}\n" + textwrap.dedent(FAKE_DRIVER))
    driver.chmod(0o755)
    case = _case(harness, tmp_path)
    args = SimpleNamespace(quick=False, timeout=120)
    peers = harness.run_peers(case, {"lama": {"driver": str(driver), "source": "stand-in"}}, args, tmp_path)
    slam = peers["lama-slam2d"]
    assert slam["status"] == "ok", slam
    assert slam["accuracy"]["relations"]["trans_mean"] == pytest.approx(0.1, abs=2e-3)
    assert slam["accuracy"]["relations"]["used"] == 10
    assert slam["accuracy"]["dropped_poses"] == 1
    assert slam["cpu_s"] >= 0.3 and slam["peak_rss_mb"] >= 64
    pf = peers["lama-pf"]
    assert pf["status"] == "failed" and pf["error"] == "exit status 3: pf: boom"
    assert "threads=2 seed=1" in pf["command"]


def test_peer_memory_is_the_peers_own_not_the_harness_it_started_from(harness, tmp_path):
    """ru_maxrss counts what a process held before its exec: a peer forked straight from a harness that once held
    300 MB would show 300 MB."""
    driver = tmp_path / "lama_driver"
    driver.write_text('#!/bin/sh\nfor t in 0 1 2 3 4 5 6 7 8 9 10; do echo "$t $t 0 0"; done > "$3.scans.txt"\n')
    driver.chmod(0o755)
    ballast = bytearray(300 * 2**20)
    ballast[::4096] = b"x" * len(ballast[::4096])
    del ballast
    run = harness.LAMA_RUNS[0]
    res = harness.run_peer(_case(harness, tmp_path), run, str(driver), "log", tmp_path, timeout=60)
    assert res["status"] == "ok" and res["accuracy"]["relations"]["trans_mean"] == pytest.approx(0.0, abs=1e-6)
    assert 0 < res["peak_rss_mb"] < 50


def test_a_peer_past_the_timeout_is_stopped(harness, tmp_path):
    driver = tmp_path / "lama_driver"
    driver.write_text("#!/bin/sh\nsleep 30\n")
    driver.chmod(0o755)
    res = harness.run_peer(_case(harness, tmp_path), harness.LAMA_RUNS[0], str(driver), "log", tmp_path, timeout=0.5)
    assert (res["status"], res["error"]) == ("failed", "timeout after 0.5 s")
    assert res["command"].endswith("hall.lama-slam2d")


def test_peers_read_carmen_logs_only_and_skip_an_unbuilt_peer(harness, tmp_path):
    args = SimpleNamespace(quick=False, timeout=0)
    bag = harness.Case("bag", "ccny", "bag", str(tmp_path / "x.bag"))
    peers = harness.run_peers(bag, {"lama": {"driver": "/nonexistent", "source": "-"}}, args, tmp_path)
    assert {r["status"] for r in peers.values()} == {"skipped"}
    peers = harness.run_peers(_case(harness, tmp_path), {"lama": {"error": "no eigen"}}, args, tmp_path)
    assert [r["error"] for r in peers.values()] == ["not built", "not built"]


def test_quick_cuts_the_log_after_the_scans_carto_mapped(harness, tmp_path):
    case = _case(harness, tmp_path)
    cut = harness.first_scans(case.path, 2, tmp_path / "cut.clf.gz")
    with gzip.open(cut, "rt") as f:
        assert [line.split()[0] for line in f] == ["ODOM", "FLASER", "ODOM", "FLASER"]


def test_peers_option(harness, capsys):
    assert harness.parse_args([], "bench/run").peers == []
    assert harness.parse_args(["--peers", "lama"], "bench/run").peers == ["lama"]
    with pytest.raises(SystemExit):
        harness.parse_args(["--peers", "lama,slam_toolbox"], "bench/run")
    assert "unknown peer slam_toolbox" in capsys.readouterr().err


def _doc(harness, results: list[dict], builds: dict | None) -> str:
    env = {"versions": dict.fromkeys(("python", "numpy", "numba", "scipy", "cv2"), "1"), "dirty": False,
           "modified": [], "untracked": [], "commit": "abc", "cpu": "cpu", "cores": 2, "memory_gb": 8.0,
           "kernel": "6", "loadavg_start": (0.0, 0.0, 0.0), "fingerprint": "f", "snapshot": None}
    if builds is not None:
        env["peer_builds"] = builds
    args = SimpleNamespace(quick=False, profile="default", results="/tmp/r")
    return harness.render_doc(results, env, "bench/run", args, "start", "end", {}, {})


def _carto(harness, name: str, error: float) -> dict:
    return {"status": "ok", "case": {"name": name, "family": "bench", "building": name}, "algorithm": "cartographer",
            "stats": {"scans": 100, "nodes": 40, "submaps": 2}, "build_wall_s": 2.0, "scans_per_s": 50.0,
            "stages": dict.fromkeys(("local_slam_s", "constraint_search_s", "optimization_s", "jit_warmup_s",
                                     "other_s"), 0.1),
            "stage_detail": dict.fromkeys([f"local/{n}" for n in harness.LOCAL_DETAIL]
                                          + [f"constraint/{n}" for n in harness.CONSTRAINT_DETAIL], 0.0),
            "accuracy": {"relations": {"trans_mean": error, "trans_std": 0.01, "rot_mean": 0.5,
                                                           "rot_std": 0.1}},
            "loop_closures": {"total": 0}, "process_wall_s": 14.0, "cpu_s": 12.04, "peak_rss_mb": 321.4}


def test_document_sets_carto_beside_the_peers(harness):
    hall = _carto(harness, "hall", 0.05)
    hall["peers"] = {"lama-slam2d": {"status": "ok", "accuracy": {"relations": {"trans_mean": 0.04}}, "cpu_s": 0.26,
                                     "peak_rss_mb": 15.2},
                     "lama-pf": {"status": "failed", "error": "exit status 3: boom", "cpu_s": 0.1, "peak_rss_mb": 9}}
    text = _doc(harness, [hall], {"lama": {"driver": "/x", "source": "iris_lama fd60e55"}})
    assert "## Peers run beside carto" in text and "IRIS LaMa (iris_lama fd60e55)" in text
    lines = text.splitlines()
    (header,) = [line for line in lines if line.startswith("| case | carto: error m · CPU s · peak MB |")]
    assert "LaMa Slam2D: error · CPU · MB" in header and "LaMa PF-SLAM: error · CPU · MB" in header
    (row,) = [line for line in lines if line.startswith("| hall | 0.050 · ")]
    assert [c.strip() for c in row.strip("|").split("|")] == [
        "hall", "0.050 · 12.0 · 321", "**0.040** · 0.3 · 15", "failed: exit status 3: boom"]


def test_document_says_why_lama_did_not_run_and_is_unchanged_without_peers(harness):
    text = _doc(harness, [_carto(harness, "hall", 0.05)], {"lama": {"error": "bench/lama.sh failed (install libeigen3-dev)"}})
    assert "IRIS LaMa was not run: bench/lama.sh failed (install libeigen3-dev)." in text
    assert "| case | carto: error m · CPU s · peak MB |\n|---|---|\n| hall | 0.050 · 12.0 · 321 |\n" in text
    assert "## Peers run beside carto" not in _doc(harness, [_carto(harness, "hall", 0.05)], None)


def _lama_sh(tmp_path: Path, *args: str, **env: str) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(ROOT / "bench" / "lama.sh"), *args], capture_output=True, text=True,
                          env={**os.environ, "LAMA_CACHE": str(tmp_path / "cache"),
                               "LAMA_PEER_DIR": str(tmp_path / "peer"), "LAMA_SRC": "", **env})


def test_lama_sh_unpacks_a_bare_git_dir_builds_once_and_says_why_not(harness, tmp_path, monkeypatch):
    peer = tmp_path / "peer"
    peer.mkdir()
    (peer / "driver.cpp").write_text("// stand-in\n")
    # A stand-in for ../shared/peers/lama/build.sh: records the tree it was given and writes the driver.
    (peer / "build.sh").write_text('echo built >> "$(dirname "$LAMA_DRIVER")/builds"\n'
                                   'ls "$LAMA_SRC" > "$(dirname "$LAMA_DRIVER")/tree"\n'
                                   'printf "#!/bin/sh\\n" > "$LAMA_DRIVER"; chmod +x "$LAMA_DRIVER"; echo "built"\n')
    work = tmp_path / "lama"
    work.mkdir()
    (work / "CMakeLists.txt").write_text("project(iris_lama)\n")
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "init.defaultBranch=main"]
    subprocess.run([*git, "init", "-q", str(work)], check=True)
    subprocess.run([*git, "-C", str(work), "add", "."], check=True)
    subprocess.run([*git, "-C", str(work), "commit", "-qm", "x"], check=True)
    subprocess.run([*git, "clone", "-q", "--bare", str(work), str(tmp_path / "bare")], check=True)

    assert "no LaMa source" in _lama_sh(tmp_path).stderr
    assert "neither an iris_lama tree" in _lama_sh(tmp_path, str(tmp_path)).stderr
    first = _lama_sh(tmp_path, str(tmp_path / "bare"))
    cache = tmp_path / "cache"
    assert first.returncode == 0, first.stderr
    assert first.stdout == f"{cache / 'lama_driver'}\n"  # build.sh's own "built" went to stderr
    assert (cache / "tree").read_text() == "CMakeLists.txt\n"
    assert (cache / "source.txt").read_text().startswith("iris_lama ")
    again = _lama_sh(tmp_path)  # cached: no source needed, nothing rebuilt
    assert again.stdout == first.stdout and (cache / "builds").read_text() == "built\n"

    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "CMakeLists.txt").write_text("\n")
    (peer / "build.sh").write_text('echo "install libeigen3-dev" >&2; exit 1\n')
    os.utime(peer / "driver.cpp", (4e9, 4e9))  # newer than the cached driver: rebuild
    monkeypatch.setenv("LAMA_CACHE", str(cache))
    monkeypatch.setenv("LAMA_PEER_DIR", str(peer))
    monkeypatch.setenv("LAMA_SRC", str(broken))
    assert harness.build_lama(tmp_path / "build.log") == {"error": "bench/lama.sh failed (install libeigen3-dev)"}
