"""What carto tune writes: a profile that stands alone, one CSV row per trial, a report image."""
import csv
import math

import cv2
import numpy as np
import pytest

from carto_cli.options import apply_overrides, changed_options, load_options
from carto_cli.tuning.report import draw_report, write_profile, write_trials_csv

optuna = pytest.importorskip("optuna")

KEY = "pose_graph.constraint_builder.min_score"


def _trials():
    dist = {KEY: optuna.distributions.FloatDistribution(0.4, 0.8)}
    state = optuna.trial.TrialState
    return [
        optuna.trial.create_trial(params={KEY: 0.55}, distributions=dist, value=0.3,
                                  user_attrs={"baseline": True, "ate_rmse_m": 0.3}),
        optuna.trial.create_trial(params={KEY: 0.7}, distributions=dist, value=0.125, user_attrs={"ate_rmse_m": 0.125}),
        optuna.trial.create_trial(params={KEY: 0.45}, distributions=dist, state=state.FAIL,
                                  user_attrs={"error": "CartoError: no"}),
    ]


def _numbered(trials):
    # create_trial leaves the number to the study; a study's trials are numbered in order.
    for i, t in enumerate(trials):
        t.number = i
    return trials


def test_trials_csv_has_a_row_per_trial_with_params_and_metrics(tmp_path):
    path = write_trials_csv(tmp_path / "t.csv", _numbered(_trials()))
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["number", "state", "value", "duration_s", KEY, "baseline", "ate_rmse_m", "error"]
    assert [r["state"] for r in rows] == ["COMPLETE", "COMPLETE", "FAIL"]
    assert [r["value"] for r in rows] == ["0.3", "0.125", ""]  # repr: the exact float, read back as it was
    assert rows[1][KEY] == "0.7" and rows[2]["error"] == "CartoError: no" and rows[0]["error"] == ""


def test_profile_holds_every_change_from_the_defaults_and_loads_back(tmp_path):
    base = load_options("office")
    tuned = apply_overrides(base, {KEY: 0.7})
    best = _numbered(_trials())[1]
    path = write_profile(tmp_path / "tuned.yaml", tuned, best=best, objective="ground-truth", n_trials=3,
                         base_profile="office", overrides=["trajectory_builder_2d.max_range=20"], tuned=[KEY],
                         baseline=0.3, time_weight=10.0, max_scans=50)
    text = path.read_text()
    header = [line for line in text.splitlines() if line.startswith("#")]
    assert header[0] == "# carto tune result: load with --profile tuned.yaml"
    assert "# base profile: office (--set trajectory_builder_2d.max_range=20)" in header
    assert any(h.startswith("# objective: ground-truth = ATE RMSE") and h.endswith("+ 10 x s/scan") for h in header)
    assert "# best value: 0.125 (trial 1 of 3); base options scored 0.3" in header
    assert "# scored on the first 50 scans of each recording" in header and f"# tuned options: {KEY}" in header
    # The file stands alone: loaded over the defaults, it gives the tuned options back, base profile included.
    assert load_options(path) == tuned
    assert set(changed_options(load_options(path))) == set(changed_options(tuned))


def test_profile_of_the_defaults_is_an_empty_mapping(tmp_path):
    path = write_profile(tmp_path / "same.yaml", load_options())
    assert path.read_text().rstrip().endswith("{}")
    assert load_options(path) == load_options()


def test_report_image(tmp_path):
    trials = _numbered(_trials())
    path = draw_report(tmp_path / "r.png", trials, {KEY: 1.0}, title="t")
    img = cv2.imread(str(path))
    assert img.shape == (520, 1280, 3)
    assert (img < 255).any() and np.mean(img) > 200  # drawn on, mostly white
    empty = cv2.imread(str(draw_report(tmp_path / "e.png", trials[2:], {}, title="t")))
    assert empty.shape == img.shape
    assert not math.isclose(float(np.mean(empty)), float(np.mean(img)))  # nothing to plot, and it shows


def test_tune_report_option_names_are_distinct(tmp_path, monkeypatch):
    """Issue 42, item 10: the importance bars of four real-time correlative matcher options all read
    "real_time_correlative_scan_matcher" (the last two parts of each name, cut to the column's width)."""
    matcher = "trajectory_builder_2d.real_time_correlative_scan_matcher"
    names = [f"{matcher}.linear_search_window", f"{matcher}.angular_search_window",
             f"{matcher}.translation_delta_cost_weight", f"{matcher}.rotation_delta_cost_weight",
             "trajectory_builder_2d.ceres_scan_matcher.translation_weight",
             "pose_graph.constraint_builder.ceres_scan_matcher.translation_weight",
             "trajectory_builder_2d.submaps.num_range_data", KEY]
    drawn: list[str] = []
    put_text = cv2.putText
    monkeypatch.setattr(cv2, "putText", lambda img, text, *a, **k: drawn.append(text) or put_text(img, text, *a, **k))
    draw_report(tmp_path / "r.png", _numbered(_trials()), {n: 1.0 - 0.1 * i for i, n in enumerate(names)})
    labels = drawn[drawn.index("parameter importance (fANOVA)") + 1::2]  # each bar: its label, then its value
    assert len(labels) == len(names) and len(set(labels)) == len(names), labels
    assert all(len(label) <= 34 for label in labels), labels
    # Each label ends with the option's own name when that fits, so the bars still say which option they are.
    assert [label.rsplit(".", 1)[-1] for label in labels[:4]] == [n.rsplit(".", 1)[-1] for n in names[:4]]
