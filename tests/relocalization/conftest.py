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
def second_pass_records(mapped):
    """(records of a second pass: scans and odometry in time order, {scan time: reference pose in the map})."""
    from reloc_map import DURATION, SCAN_RATE, world

    from carto_cli.sim import simulate

    w, tr = world()
    sim = simulate(w, tr, duration=DURATION, scan_rate=SCAN_RATE, seed=7)
    ref = {round(t, 6): p for t, p in zip(mapped.trajectory.t, mapped.trajectory.poses)}
    return list(sim.records(["/scan", "/odom"])), ref


@pytest.fixture(scope="session")
def relocalizer(mapped):
    return Relocalizer(mapped)
