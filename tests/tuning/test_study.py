"""carto tune's study: it improves on a poor profile, writes a profile that reproduces its best score,
resumes, records failing trials, refuses bad inputs, and shares its storage between processes."""
from __future__ import annotations

import csv

import cv2
import pytest

from carto_cli.core.errors import CartoError
from carto_cli.options import apply_overrides, load_options
from carto_cli.tuning.objectives import evaluate_options, make_cases
from carto_cli.tuning.study import StudyRequest, tune

optuna = pytest.importorskip("optuna")

SPACE = {
    "trajectory_builder_2d.ceres_scan_matcher.translation_weight": {"low": 0.1, "high": 1.0e4, "log": True},
    "trajectory_builder_2d.ceres_scan_matcher.rotation_weight": {"low": 1.0, "high": 1.0e4, "log": True},
    "pose_graph.optimization_problem.odometry_translation_weight": {"low": 10.0, "high": 1.0e5, "log": True},
    "trajectory_builder_2d.submaps.num_range_data": {"low": 20, "high": 90, "int": True},
}


@pytest.fixture(scope="module")
def poor_study(sim, tmp_path_factory, poor):
    out = tmp_path_factory.mktemp("tune") / "tuned.yaml"
    seen = []
    request = StudyRequest([sim.recording()], out, space=SPACE, trials=6, ground_truth=[sim.ground_truth],
                           overrides=poor, seed=1)
    result = tune(request, on_trial=lambda n, v, b: seen.append((n, v, b)))
    return result, seen


def test_study_improves_on_a_poor_profile(sim, poor_study, poor):
    result, seen = poor_study
    assert result.objective == "ground-truth"
    cases = make_cases([sim.recording()], ground_truth=[sim.ground_truth])
    poor_value, _ = evaluate_options(apply_overrides(load_options(), poor), cases, "ground-truth")
    # The first trial measures the base options (enqueued), so the baseline is in the study.
    assert result.baseline_value == pytest.approx(poor_value, rel=1e-9)
    assert result.best_value < 0.8 * poor_value
    assert result.n_trials == 6 and len(seen) == 6
    assert [n for n, _, _ in seen] == list(range(6))
    assert seen[-1][2] == pytest.approx(result.best_value)


def test_written_profile_loads_and_reproduces_the_best_score(sim, poor_study, poor):
    result, _ = poor_study
    text = result.profile_path.read_text()
    assert text.startswith("# carto tune result")
    assert "# objective: ground-truth" in text and "best value" in text
    options = load_options(result.profile_path)
    expected = apply_overrides(apply_overrides(load_options(), poor), result.best_params)
    assert options == expected
    value, _ = evaluate_options(options, make_cases([sim.recording()], ground_truth=[sim.ground_truth]),
                                "ground-truth")
    assert value == pytest.approx(result.best_value, rel=1e-9, abs=1e-12)


def test_csv_and_report(poor_study):
    result, _ = poor_study
    with open(result.csv_path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == 6
    assert {"number", "state", "value", "duration_s", *SPACE} <= set(rows[0])
    assert min(float(r["value"]) for r in rows if r["state"] == "COMPLETE") == pytest.approx(result.best_value)
    img = cv2.imread(str(result.png_path))
    assert img is not None and img.shape[0] > 300 and img.shape[1] > 600


def test_rerunning_resumes_the_study(sim, tmp_path, poor):
    out = tmp_path / "resume.yaml"
    request = StudyRequest([sim.recording()], out, space=SPACE, trials=3, objective="map-quality", overrides=poor,
                           seed=3, max_scans=60)
    first = tune(request)
    assert first.n_trials == 3
    assert (tmp_path / "resume.optuna.db").is_file()
    second = tune(request)
    assert second.n_trials == 6
    assert second.best_value <= first.best_value
    with open(second.csv_path, newline="") as f:
        assert [int(r["number"]) for r in csv.DictReader(f)] == list(range(6))


def test_failing_trials_are_recorded_not_raised(sim, tmp_path):
    # min_range above max_range for some draws: the options check rejects them inside the trial.
    space = {"trajectory_builder_2d.min_range": {"low": 0.0, "high": 60.0},
             "trajectory_builder_2d.max_range": {"low": 20.0, "high": 30.0}}
    result = tune(StudyRequest([sim.recording()], tmp_path / "f.yaml", space=space, trials=4, objective="map-quality",
                               seed=0, max_scans=30))
    assert result.n_trials == 4
    assert result.n_failed + result.n_complete == 4
    assert result.n_failed >= 1


def test_tune_rejects_bad_inputs(sim, tmp_path):
    rec = sim.recording()
    with pytest.raises(CartoError, match="no such search-space file"):
        tune(StudyRequest([rec], tmp_path / "x.yaml", space=tmp_path / "missing.yaml", trials=1))
    with pytest.raises(CartoError, match="one --relations file per recording"):
        tune(StudyRequest([rec, rec], tmp_path / "x.yaml", space=SPACE, trials=1, relations=[tmp_path / "r.txt"]))
    with pytest.raises(CartoError, match="unknown objective"):
        tune(StudyRequest([rec], tmp_path / "x.yaml", space=SPACE, trials=1, objective="speed"))
    grid_space = {"trajectory_builder_2d.submaps.grid_options_2d.resolution": {"low": 0.03, "high": 0.1}}
    with pytest.raises(CartoError, match="map-quality"):
        tune(StudyRequest([rec], tmp_path / "x.yaml", space=grid_space, trials=1))


def test_a_sessions_study_maps_the_recordings_into_one_map(tmp_path):
    from carto_cli.sim import Lidar, loop_building
    from carto_cli.sim.sessions import route_sessions

    recordings, _ = route_sessions(loop_building(), 2, scan_rate=5.0, lidar=Lidar(beams=180))
    with pytest.raises(CartoError, match="--sessions maps the recordings into one Cartographer pose graph"):
        StudyRequest(recordings, tmp_path / "x.yaml", space=SPACE, trials=1, sessions=True, algorithm="gmapping")
    space = {"pose_graph.constraint_builder.min_score": {"low": 0.5, "high": 0.7}}
    result = tune(StudyRequest(recordings, tmp_path / "s.yaml", space=space, trials=2, sessions=True, seed=0))
    assert result.objective == "map-quality" and result.n_complete == 2
    # Scored as one map of both: the metrics of the sessions' form
    assert result.best_metrics["unlinked_sessions"] == 0
    assert result.best_value == pytest.approx(result.best_metrics["map_quality"])


PARALLEL_SCRIPT = """
import sys
from pathlib import Path
from carto_cli.sim.lidar import Lidar
from carto_cli.sim.recording import simulate
from carto_cli.sim.trajectory import loop_trajectory
from carto_cli.sim.world import loop_building
from carto_cli.tuning.study import StudyRequest, tune

world = loop_building()
sim = simulate(world, loop_trajectory(world), duration=20.0, scan_rate=5.0, lidar=Lidar(beams=180))
space = {"trajectory_builder_2d.ceres_scan_matcher.translation_weight": {"low": 0.1, "high": 1.0e4, "log": True}}
seen = []
request = StudyRequest([sim.recording()], Path(sys.argv[1]), space=space, trials=4, n_jobs=2,
                       ground_truth=[sim.ground_truth], seed=0, max_scans=40)
result = tune(request, on_trial=lambda n, v, b: seen.append(n))
print(result.n_trials, result.n_complete, len(seen))
"""


def test_a_gmapping_study_maps_every_trial_with_gmapping_and_keeps_to_it(sim, tmp_path, monkeypatch):
    import carto_cli.pipeline

    seen = []
    real = carto_cli.pipeline.build

    def spy(*args, **kwargs):
        seen.append(kwargs.get("algorithm", "cartographer"))
        return real(*args, **kwargs)

    monkeypatch.setattr(carto_cli.pipeline, "build", spy)
    space = {"gmapping.srr": {"low": 0.01, "high": 0.4, "log": True}, "gmapping.sigma": {"low": 0.02, "high": 0.1}}
    out = tmp_path / "gm.yaml"
    result = tune(StudyRequest([sim.recording()], out, space=space, trials=2, objective="map-quality",
                               overrides=["gmapping.particles=5"], seed=0, max_scans=30, algorithm="gmapping"))
    assert result.n_complete == 2 and seen == ["gmapping", "gmapping"]
    assert "# algorithm: gmapping (map with --algorithm gmapping --profile gm.yaml)" in out.read_text()
    carto_space = {"pose_graph.constraint_builder.min_score": {"low": 0.5, "high": 0.7}}
    with pytest.raises(CartoError, match="maps with gmapping, not cartographer"):
        tune(StudyRequest([sim.recording()], out, space=carto_space, trials=1, objective="map-quality",
                          max_scans=30))
    with pytest.raises(CartoError, match="unknown algorithm 'ekf'"):
        StudyRequest([sim.recording()], tmp_path / "x.yaml", space=carto_space, trials=1, algorithm="ekf")
    assert seen == ["gmapping", "gmapping"]


def test_parallel_processes_share_the_study(tmp_path):
    # In a fresh interpreter, as `carto tune --n-jobs 2` runs: forking pytest's own process is not what users do.
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", PARALLEL_SCRIPT, str(tmp_path / "p.yaml")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    n_trials, n_complete, seen = map(int, done.stdout.split()[-3:])
    assert n_trials == 4 and n_complete == 4
    assert 1 <= seen < 4  # this process ran its share; the worker process ran the rest
