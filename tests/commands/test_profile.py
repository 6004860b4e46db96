"""`carto profile` as a library call: the report of a timed run, written when asked, gated against a baseline."""
import json

import pytest
from support import SAMPLE_BAG

from carto_cli.commands.profile import ProfileRun, read_baseline, run_profile
from carto_cli.core.errors import CartoError
from carto_cli.options import load_options


@pytest.fixture(scope="module")
def first(tmp_path_factory):
    out = tmp_path_factory.mktemp("profile") / "base.json"
    totals, scans = [], []
    run = run_profile(SAMPLE_BAG, load_options(), output=out, max_scans=30, on_total=totals.append,
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
    assert not all(g.passed for g in run.gates(max_regression=0.2))
    assert all(g.passed for g in run.gates(max_regression=1000.0))


def test_bad_baseline_fails_before_mapping(tmp_path):
    with pytest.raises(CartoError, match="cannot read baseline") as e:
        run_profile(tmp_path / "no-such-recording.bag", load_options(), baseline=tmp_path / "missing.json")
    assert e.value.path == str(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(CartoError, match="cannot read baseline"):
        read_baseline(bad)
