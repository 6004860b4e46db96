"""`carto profile` as a library call: the report of a timed run, written when asked, gated against a baseline
of the same algorithm."""
import json

import jsonschema
import pytest
from support import SAMPLE_BAG

from carto_cli.commands.profile import ProfileRun, read_baseline, run_profile
from carto_cli.core.errors import CartoError
from carto_cli.evaluation.profiling import SCHEMA_PATH, format_report
from carto_cli.options import load_options
from carto_cli.pipeline import MapRequest


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    out = tmp_path_factory.mktemp("profile") / "base.json"
    totals, scans = [], []
    run = run_profile(MapRequest(SAMPLE_BAG, load_options(), max_scans=30), output=out, on_total=totals.append,
                      on_scan=scans.append)
    return run, out, totals, scans


def test_report_of_the_first_scans_is_written(first):
    run, out, totals, scans = first
    assert totals == [30] and sum(scans) == 30
    assert run.report["schema"] == "carto.profile" and run.report["counts"]["scans"] == 30
    assert run.report["recording"] == str(SAMPLE_BAG) and run.report["calibration"] is None
    assert json.loads(out.read_text()) == json.loads(json.dumps(run.report))
    assert run.baseline is None
    with pytest.raises(CartoError, match="no baseline"):
        run.gates()


def test_gates_against_a_baseline(first):
    _, out, _, _ = first
    base = read_baseline(out)
    run = ProfileRun(json.loads(out.read_text()), base)
    assert run.gates() and all(g.passed for g in run.gates())  # itself, within 20 %
    for stage in base["timing"]["stages"].values():
        if stage["ms_per_scan"] is not None:
            stage["ms_per_scan"] /= 20.0
        stage["total_ms"] /= 20.0
        for key in ("cpu_ms_per_scan", "cpu_ms"):  # what the gates compare
            if stage.get(key) is not None:
                stage[key] /= 20.0
    assert not all(g.passed for g in run.gates(max_regression=0.2))
    assert all(g.passed for g in run.gates(max_regression=1000.0))


def test_bad_baseline_fails_before_mapping(tmp_path):
    with pytest.raises(CartoError, match="cannot read baseline") as e:
        run_profile(MapRequest(tmp_path / "no-such-recording.bag", load_options()), baseline=tmp_path / "missing.json")
    assert e.value.path == str(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(CartoError, match="cannot read baseline"):
        read_baseline(bad)


def test_an_existing_output_is_kept_unless_force(first, tmp_path):
    _, out, _, _ = first
    before = out.read_bytes()
    # Refused before the recording is even opened (it does not exist).
    with pytest.raises(CartoError, match="--force") as e:
        run_profile(MapRequest(tmp_path / "no-such-recording.bag", load_options()), output=out)
    assert e.value.path == str(out) and out.read_bytes() == before
    replaced = tmp_path / "again.json"
    replaced.write_text("old")
    run_profile(MapRequest(SAMPLE_BAG, load_options(), max_scans=5), output=replaced, force=True)
    assert json.loads(replaced.read_text())["counts"]["scans"] == 5


@pytest.fixture(scope="module")
def gmapping_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("profile") / "gmapping.json"
    run = run_profile(MapRequest(SAMPLE_BAG, load_options(None, ["gmapping.particles=5"]), "gmapping", max_scans=20),
                      output=out)
    return run, out


def test_gmapping_report_has_the_filter_and_its_stages(gmapping_run):
    run, out = gmapping_run
    report = run.report
    assert report["algorithm"] == "gmapping" and report["counts"]["scans"] == 20
    # The CCNY bag has no odometry: the filter processes every scan.
    assert report["gmapping"]["particles"] == 5 and report["gmapping"]["processed_scans"] == 20
    for stage in ("motion model", "scan matching", "weighting", "resampling", "map update"):
        assert f"scan/{stage}" in report["timing"]["stages"], stage
    jsonschema.validate(json.loads(out.read_text()), json.loads(SCHEMA_PATH.read_text()))
    assert "algorithm   gmapping: 20 of 20 scans processed, 5 particles, " in format_report(report)


def test_a_baseline_of_the_other_algorithm_is_refused_before_mapping(first, gmapping_run, tmp_path):
    _, carto_out, _, _ = first
    _, gmapping_out = gmapping_run
    assert read_baseline(carto_out)["algorithm"] == "cartographer"
    with pytest.raises(CartoError, match="profiled with gmapping, this run maps with cartographer") as e:
        run_profile(MapRequest(tmp_path / "no-such-recording.bag", load_options()), baseline=gmapping_out)
    assert e.value.path == str(gmapping_out)
    with pytest.raises(CartoError, match="profiled with cartographer, this run maps with gmapping"):
        run_profile(MapRequest(tmp_path / "no-such-recording.bag", load_options(), "gmapping"), baseline=carto_out)
    # A report from before --algorithm names none: it was Cartographer's.
    old = read_baseline(carto_out)
    del old["algorithm"]
    (tmp_path / "old.json").write_text(json.dumps(old))
    with pytest.raises(CartoError, match="profiled with cartographer"):
        run_profile(MapRequest(tmp_path / "no-such-recording.bag", load_options(), "gmapping"),
                    baseline=tmp_path / "old.json")


def test_repeated_runs_record_cpu_time_and_its_spread(tmp_path):
    run = run_profile(MapRequest(SAMPLE_BAG, load_options(), max_scans=10), repeat=2)
    stages = run.report["timing"]["stages"]
    assert run.report["repeats"] == 2 and run.report["counts"]["scans"] == 10
    assert stages["scan"]["cpu_ms_per_scan"] > 0 and stages["scan"]["cpu_spread"] >= 0
    with pytest.raises(CartoError, match="--repeat"):
        run_profile(MapRequest(SAMPLE_BAG, load_options()), repeat=0)
