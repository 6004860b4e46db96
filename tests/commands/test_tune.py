"""`carto tune` as a library call: the base profile's packaged space when none is given, and its summary."""
from pathlib import Path

import pytest

from carto_cli.commands.tune import run_tune, summary_line
from carto_cli.sim import loop_building, loop_trajectory, simulate
from carto_cli.tuning.study import TuneResult

pytest.importorskip("optuna")


def test_default_space_is_the_profiles(tmp_path):
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=8.0, scan_rate=5.0, beams=180)
    result = run_tune([sim.recording()], tmp_path / "t.yaml", trials=1, ground_truth=[sim.ground_truth],
                      profile="sparse", seed=0, max_scans=20)
    assert result.n_trials == 1 and result.profile_path.is_file()
    from carto_cli.tuning.space import default_space_path, load_space

    tuned = {p.name for p in load_space(default_space_path("sparse"))}
    assert set(result.best_params) == tuned  # the baseline trial sets every parameter of the sparse space
    assert "# base profile: sparse" in result.profile_path.read_text()


def test_gmapping_tunes_the_gmapping_space_unless_given_one(monkeypatch, tmp_path):
    import carto_cli.commands.tune as command
    from carto_cli.tuning.space import default_space_path, spaces_dir

    calls = []
    monkeypatch.setattr(command, "tune", lambda recordings, space, **kw: calls.append((space, kw["algorithm"])))
    run_tune(["r.bag"], tmp_path / "t.yaml", algorithm="gmapping")
    run_tune(["r.bag"], tmp_path / "t.yaml", algorithm="gmapping", space=tmp_path / "mine.yaml")
    run_tune(["r.bag"], tmp_path / "t.yaml", profile="sparse")
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
