"""`carto tune` as a library call: the base profile's packaged space when none is given, and its summary."""
from pathlib import Path

import pytest

from carto_cli.commands.tune import StudyRequest, run_tune, summary_line
from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate
from carto_cli.tuning.study import TuneResult

pytest.importorskip("optuna")


def test_default_space_is_the_profiles(tmp_path):
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=8.0, scan_rate=5.0, lidar=Lidar(beams=180))
    result = run_tune(StudyRequest([sim.recording()], tmp_path / "t.yaml", trials=1, ground_truth=[sim.ground_truth],
                                   profile="sparse", seed=0, max_scans=20))
    assert result.n_trials == 1 and result.profile_path.is_file()
    from carto_cli.tuning.space import default_space_path, load_space

    tuned = {p.name for p in load_space(default_space_path("sparse"))}
    assert set(result.best_params) == tuned  # the baseline trial sets every parameter of the sparse space
    assert "# base profile: sparse" in result.profile_path.read_text()


def test_gmapping_tunes_the_gmapping_space_unless_given_one(monkeypatch, tmp_path):
    import carto_cli.commands.tune as command
    from carto_cli.tuning.space import default_space_path, spaces_dir

    calls = []
    monkeypatch.setattr(command, "tune", lambda request, **kw: calls.append((request.space, request.algorithm)))
    run_tune(StudyRequest(["r.bag"], tmp_path / "t.yaml", algorithm="gmapping"))
    run_tune(StudyRequest(["r.bag"], tmp_path / "t.yaml", algorithm="gmapping", space=tmp_path / "mine.yaml"))
    run_tune(StudyRequest(["r.bag"], tmp_path / "t.yaml", profile="sparse"))
    assert calls == [(spaces_dir() / "gmapping.yaml", "gmapping"), (tmp_path / "mine.yaml", "gmapping"),
                     (default_space_path("sparse"), "cartographer")]


def test_summary_line():
    result = TuneResult(best_value=0.01234, best_params={}, n_trials=5, profile_path=Path("out/t.yaml"),
                        csv_path=Path("out/t.trials.csv"), png_path=Path("out/t.report.png"),
                        objective="relations", baseline_value=0.05, n_complete=3, n_pruned=1, n_failed=1)
    assert summary_line(result) == ("5 trials (3 complete, 1 pruned, 1 failed); best relations 0.01234 "
                                    "(base profile 0.05) -> out/t.yaml, t.trials.csv, t.report.png")
    result.baseline_value = None
    assert "(base profile" not in summary_line(result)


@pytest.fixture(scope="module")
def small_sim():
    world = loop_building()
    return simulate(world, loop_trajectory(world), duration=4.0, scan_rate=5.0, lidar=Lidar(beams=90))


def _interrupting(monkeypatch, signals_at: dict[int, list]):
    """evaluate_options replaced by a quick score that sends ``signals_at[call]`` to this process."""
    import os

    import carto_cli.tuning.study as study

    calls = []

    def fake(options, cases, objective, **kwargs):
        calls.append(1)
        for sig in signals_at.get(len(calls), []):
            os.kill(os.getpid(), sig)
        return 0.1 + 0.01 * len(calls), {"relation_error_m": 0.1}

    monkeypatch.setattr(study, "evaluate_options", fake)
    return calls


@pytest.mark.parametrize("sig_name", ["SIGINT", "SIGTERM"])
def test_a_stop_signal_finishes_the_running_trial_and_writes_the_best_so_far(tmp_path, monkeypatch, small_sim,
                                                                            capfd, sig_name):
    import signal

    sig = getattr(signal, sig_name)
    before = signal.getsignal(sig)
    calls = _interrupting(monkeypatch, {2: [sig]})
    result = run_tune(StudyRequest([small_sim.recording()], tmp_path / "t.yaml", trials=6,
                                   ground_truth=[small_sim.ground_truth], profile="sparse", seed=0))
    assert result.interrupted and len(calls) == 2  # the trial under way finished; no third one started
    assert (result.n_trials, result.n_complete, result.n_failed) == (2, 2, 0)
    assert result.profile_path.is_file() and result.csv_path.is_file()
    assert "finishing the running trial" in capfd.readouterr().err
    assert signal.getsignal(sig) == before  # the handler is put back


def test_a_second_ctrl_c_stops_the_trial_at_once_and_records_no_failure(tmp_path, monkeypatch, small_sim):
    import signal

    import optuna

    calls = _interrupting(monkeypatch, {2: [signal.SIGINT, signal.SIGINT]})
    result = run_tune(StudyRequest([small_sim.recording()], tmp_path / "t.yaml", trials=6,
                                   ground_truth=[small_sim.ground_truth], profile="sparse", seed=0))
    assert result.interrupted and len(calls) == 2
    assert (result.n_complete, result.n_pruned, result.n_failed) == (1, 1, 0)
    study = optuna.load_study(study_name=result.study_name, storage=result.storage)
    stopped = study.trials[-1]
    assert stopped.state == optuna.trial.TrialState.PRUNED and stopped.user_attrs.get("interrupted") is True
    assert result.profile_path.is_file()


def test_stopped_before_any_trial_completed_writes_nothing(tmp_path, monkeypatch, small_sim):
    import signal

    _interrupting(monkeypatch, {1: [signal.SIGINT, signal.SIGINT]})
    with pytest.raises(KeyboardInterrupt):
        run_tune(StudyRequest([small_sim.recording()], tmp_path / "t.yaml", trials=3,
                              ground_truth=[small_sim.ground_truth], profile="sparse", seed=0))
    assert not (tmp_path / "t.yaml").exists() and not (tmp_path / "t.trials.csv").exists()


def test_the_cli_exits_130_when_the_study_was_interrupted(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    import carto_cli.commands.tune as command
    from carto_cli.cli import app

    result = TuneResult(best_value=0.1, best_params={}, n_trials=2, profile_path=tmp_path / "t.yaml",
                        csv_path=tmp_path / "t.trials.csv", png_path=tmp_path / "t.report.png",
                        objective="relations", n_complete=2, interrupted=True)
    monkeypatch.setattr(command, "run_tune", lambda *a, **k: result)
    r = CliRunner().invoke(app, ["tune", str(tmp_path / "r.bag"), "-o", str(tmp_path / "t.yaml")])
    assert r.exit_code == 130, r.output
    assert "2 trials" in r.stdout and "best trial so far" in r.stderr


def test_an_existing_output_is_kept_unless_it_is_the_studys_own(tmp_path, monkeypatch, small_sim):
    from carto_cli.core.errors import CartoError

    _interrupting(monkeypatch, {})
    out = tmp_path / "t.yaml"
    out.write_text("# someone's hand-made profile\n")
    request = StudyRequest([small_sim.recording()], out, trials=2, ground_truth=[small_sim.ground_truth],
                           profile="sparse", seed=0)
    with pytest.raises(CartoError, match="not the output of study 't'.*--force"):
        run_tune(request)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t.yaml"]  # refused without touching anything
    assert out.read_text() == "# someone's hand-made profile\n"
    first = run_tune(request, force=True)
    resumed = run_tune(request)  # the same study: resuming rewrites its profile
    assert (first.n_trials, resumed.n_trials) == (2, 4)


def test_sigkill_during_tune_leaves_no_partial_output(tmp_path, small_sim):
    """`carto tune` killed with SIGKILL at five moments: the profile is absent or whole (it loads), no temporary
    file is left beside it, and the same command then resumes the study and finishes."""
    import random
    import signal
    import subprocess
    import sys
    import time

    from carto_cli.io.recording_writers import write_recording
    from carto_cli.io.trajectory import Trajectory, write_trajectory
    from carto_cli.options import load_options

    rec = small_sim.recording()
    bag = tmp_path / "drive.bag"
    write_recording(rec.records(), bag, "ros1", static_transforms=rec.static_transforms(),
                    topics={t.name: t.msgtype for t in rec.topics()})
    gt = small_sim.ground_truth
    truth = write_trajectory(tmp_path / "truth.tum", Trajectory.from_poses(gt[:, 0], gt[:, 1:4]))
    out = tmp_path / "tuned" / "t.yaml"
    command = [sys.executable, "-m", "carto_cli", "--quiet", "tune", str(bag), "--ground-truth", str(truth),
               "-o", str(out), "--trials", "2", "--max-scans", "15", "--profile", "sparse", "--seed", "0"]
    started = time.perf_counter()
    assert subprocess.run(command, capture_output=True, timeout=600).returncode == 0
    full = time.perf_counter() - started
    rng = random.Random(3)
    for k in range(5):
        proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        time.sleep(rng.uniform(0.1, 1.0) * full)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
        load_options(out)  # the profile of an earlier run stays whole
        assert [p.name for p in out.parent.iterdir() if p.name.startswith(".")] == [], k
    r = subprocess.run(command, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    load_options(out)


def test_the_profile_csv_and_report_are_written_together(tmp_path, monkeypatch, small_sim):
    """A failure while writing the outputs (here the report) leaves the earlier three as they were."""
    import carto_cli.tuning.study as study

    _interrupting(monkeypatch, {})
    out = tmp_path / "t.yaml"
    request = StudyRequest([small_sim.recording()], out, trials=2, ground_truth=[small_sim.ground_truth],
                           profile="sparse", seed=0)
    run_tune(request)
    names = ("t.yaml", "t.trials.csv", "t.report.png")
    before = {n: (tmp_path / n).read_bytes() for n in names}

    def broken(path, *args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(study, "draw_report", broken)
    from carto_cli.core.errors import CartoError

    with pytest.raises(CartoError, match="No space left on device"):
        run_tune(request)  # the same study, resumed
    assert {n: (tmp_path / n).read_bytes() for n in names} == before
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []
