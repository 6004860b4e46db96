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


def test_record_gates_returns_the_failed_and_writes_junit_only_when_asked(tmp_path):
    gates = [GateResult("a", "m", 1.0, 0.5, 1.0, True), GateResult("b", "m", 1.0, 2.0, 1.0, False, "b: too far")]
    assert [g.name for g in record_gates(gates, None, "suite")] == ["b"]
    assert list(tmp_path.iterdir()) == []
    junit = tmp_path / "gates.xml"
    record_gates(gates, junit, "carto.eval")
    suite = ET.parse(junit).getroot().find("testsuite")
    assert suite.get("name") == "carto.eval" and suite.get("tests") == "2" and suite.get("failures") == "1"
