"""The map and second-pass queries every relocalization test module shares (built once per session)."""
import pytest
from reloc_map import build_map, second_pass

from carto_cli.relocalization import Relocalizer


@pytest.fixture(scope="session")
def mapped(tmp_path_factory):
    return build_map(tmp_path_factory.mktemp("map"))


@pytest.fixture(scope="session")
def queries(mapped):
    """(simulation, [(scan, reference pose in the map frame)]): every 7th scan of a second pass."""
    sim, out = second_pass(mapped)
    assert len(out) >= 30
    return sim, out


@pytest.fixture(scope="session")
def relocalizer(mapped):
    return Relocalizer(mapped)
