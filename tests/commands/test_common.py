"""What commands share: the --min-z/--max-z slice and the gates' JUnit file."""
from xml.etree import ElementTree as ET

import pytest

from carto_cli.commands.common import record_gates, z_slice
from carto_cli.core.errors import CartoError
from carto_cli.evaluation.gates import GateResult


def test_z_slice():
    read = z_slice(-0.2, 0.3)
    assert (read.min_z, read.max_z) == (-0.2, 0.3)
    assert z_slice(0.1, 0.1).min_z == 0.1  # a single height is a valid slice
    with pytest.raises(CartoError, match=r"--min-z \(1.0\) is above --max-z \(0.0\)"):
        z_slice(1.0, 0.0)


def test_z_slice_given_is_the_sensor_frame_and_none_is_the_band_above_the_floor():
    assert z_slice(-0.2, 0.3).cloud_band == "sensor"
    read = z_slice(-0.5, None)  # the other bound keeps its default
    assert (read.min_z, read.max_z, read.cloud_band) == (-0.5, 2.0, "sensor")
    assert z_slice(None, None).cloud_band == "auto"


def test_cloud_band_option_reaches_the_readers():
    from carto_cli.options import load_options
    from carto_cli.pipeline import read_options

    assert read_options(load_options("default")).cloud_band == "auto"
    given = read_options(load_options("default", ["trajectory_builder_2d.cloud_band=0.2..1.1"]))
    assert given.cloud_band == "0.2..1.1"
    with pytest.raises(CartoError, match="cloud_band"):
        load_options("default", ["trajectory_builder_2d.cloud_band=1.1..0.2"])


def test_record_gates_returns_the_failed_and_writes_junit_only_when_asked(tmp_path):
    gates = [GateResult("a", "m", 1.0, 0.5, 1.0, True), GateResult("b", "m", 1.0, 2.0, 1.0, False, "b: too far")]
    assert [g.name for g in record_gates(gates, None, "suite")] == ["b"]
    assert list(tmp_path.iterdir()) == []
    junit = tmp_path / "gates.xml"
    record_gates(gates, junit, "carto.eval")
    suite = ET.parse(junit).getroot().find("testsuite")
    assert suite.get("name") == "carto.eval" and suite.get("tests") == "2" and suite.get("failures") == "1"
