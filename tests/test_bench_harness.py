"""bench/harness.py with --algorithm: the option reaches build and each case's result, and the document says
which system mapped (a Cartographer run's document is unchanged). No case of the real benchmark runs here."""
import importlib.util
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest

from carto_cli.io.recording_writers import write_recording
from carto_cli.sim.lidar import Lidar
from carto_cli.sim.recording import simulate
from carto_cli.sim.trajectory import loop_trajectory
from carto_cli.sim.world import loop_building

HARNESS = Path(__file__).resolve().parents[1] / "bench" / "harness.py"


@pytest.fixture(scope="module")
def harness():
    spec = importlib.util.spec_from_file_location("carto_bench_harness", HARNESS)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    yield module
    del sys.modules[spec.name]


def test_algorithm_option(harness, capsys):
    assert harness.parse_args([], "bench/run").algorithm is None  # auto's choice per case
    assert harness.parse_args(["--algorithm", "gmapping"], "bench/run").algorithm == "gmapping"
    with pytest.raises(SystemExit):
        harness.parse_args(["--algorithm", "bogus"], "bench/run")
    assert "invalid choice: 'bogus'" in capsys.readouterr().err


def test_run_case_maps_with_the_algorithm_and_records_it(harness, tmp_path):
    world = loop_building()
    rec = simulate(world, loop_trajectory(world), duration=6.0, lidar=Lidar(beams=180)).recording()
    bag = tmp_path / "drive.bag"
    write_recording(rec.records(), bag, "ros1", static_transforms=rec.static_transforms(),
                    topics={t.name: t.msgtype for t in rec.topics()})
    case = harness.Case("drive", "ccny", "drive", str(bag), quick_scans=40)
    res = harness.run_case(case, True, None, ["gmapping.particles=5"], tmp_path / "out", algorithm="gmapping")
    assert res["status"] == "ok" and res["algorithm"] == "gmapping"
    assert res["stats"]["algorithm"] == "gmapping" and res["stats"]["particles"] == 5 and res["stats"]["scans"] == 40
    detail = res["gmapping_detail"]
    assert set(detail) == set(harness.GMAPPING_DETAIL + harness.GMAPPING_FINAL)
    assert detail["scan matching"] > 0 and detail["refine"] > 0


def _result(harness, name: str, algorithm: str) -> dict:
    stats = {"scans": 100, "nodes": 40, "submaps": 2, "wall_time_s": 2.0, "scans_per_s": 50.0}
    if algorithm == "gmapping":
        stats.update(algorithm="gmapping", processed_scans=40, particles=30, resamplings=7, mean_neff=21.5,
                     map_memory_peak_bytes=64 * 2**20)
    stages = {"local_slam_s": 1.5, "constraint_search_s": 0.0, "optimization_s": 0.0, "jit_warmup_s": 0.2,
              "other_s": 0.3}
    res = {"status": "ok", "case": {"name": name, "family": "sim", "building": name}, "algorithm": algorithm,
           "stats": stats, "build_wall_s": 2.0, "scans_per_s": 50.0, "stages": stages,
           "stage_detail": {**{f"local/{n}": 0.3 for n in harness.LOCAL_DETAIL},
                            **{f"constraint/{n}": 0.0 for n in harness.CONSTRAINT_DETAIL}},
           "accuracy": {}, "loop_closures": {"total": 0},
           "process_wall_s": 4.0, "peak_rss_mb": 321.0}
    if algorithm == "gmapping":
        res["gmapping_detail"] = {"motion model": 0.01, "scan matching": 0.9, "weighting": 0.4, "resampling": 0.02,
                                  "map update": 0.2, "refine": 0.1}
    return res


def _doc(harness, algorithm: str | None, results: list[dict]) -> str:
    env = {"versions": dict.fromkeys(("python", "numpy", "numba", "scipy", "cv2"), "1"), "dirty": False,
           "modified": [], "untracked": [], "commit": "abc", "cpu": "cpu", "cores": 2, "memory_gb": 8.0,
           "kernel": "6", "loadavg_start": (0.0, 0.0, 0.0), "fingerprint": "f", "snapshot": None}
    args = SimpleNamespace(quick=True, profile="default", results="/tmp/r")
    if algorithm is not None:
        args.algorithm = algorithm
    return harness.render_doc(results, env, "bench/run", args, "start", "end", {}, {})


def test_document_names_gmapping_and_shows_the_filter(harness):
    failed = {"status": "failed", "case": {"name": "broken", "family": "sim", "building": "broken"},
              "algorithm": "gmapping", "error": "boom", "process_wall_s": 1.0, "peak_rss_mb": 99.0}
    text = _doc(harness, "gmapping", [_result(harness, "loop", "gmapping"), failed])
    assert "* algorithm: gmapping (every case mapped by `--algorithm gmapping`" in text
    (header,) = [line for line in text.splitlines() if line.startswith("| case | scans | processed |")]
    assert "particles" in header and "resamplings" in header and "peak RSS MB" in header
    (row,) = [line for line in text.splitlines() if line.startswith("| loop | 100 | 40 |")]
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[:8] == ["loop", "100", "40", "30", "7", "21.5", "2.0", "50"]
    assert cells[-3:] == ["4.0", "321", "64"]  # process wall s, peak RSS MB, map peak MB
    (broken,) = [line for line in text.splitlines() if line.startswith("| broken |") and "processed" not in line
                 and line.count("|") == header.count("|")]
    assert "failed: boom" in broken
    assert "**GMapping**" in text and "## Loop closures" not in text


def test_cartographer_document_is_unchanged(harness):
    results = [_result(harness, "loop", "cartographer")]
    text = _doc(harness, "cartographer", results)
    assert "algorithm" not in text and "**GMapping**" not in text and "| processed |" not in text
    assert text == _doc(harness, None, results)  # as before --algorithm existed
