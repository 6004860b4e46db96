"""The relocalization tests' map and queries (importable as `reloc_map`: pytest puts tests/ on sys.path).

The map is built from a simulated pass along the bottom and right stretches of the loop
building; queries are scans of a second pass (other noise seed) at the same times, so the
reference pose of each is the map's own pose of the first pass's scan at that time. (The
world frame is not a good reference: local SLAM's small rotation bias bends the map by up
to ~1 m over the loop, so a pose that fits the map perfectly is off from the world's.)
"""
import copy
import math
from pathlib import Path

import numpy as np

from carto_cli.core import transform

SCAN_RATE = 5.0
DURATION = 70.0  # bottom stretch, corner, right stretch
# The map's own poses of its first scans are matched against a submap still being started, and are
# off by up to 0.2 m from what the finished submaps say: they are no reference.
FIRST_QUERY = 1015.0
OVERRIDES = ["pose_graph.optimize_every_n_nodes=0", "trajectory_builder_2d.submaps.num_range_data=15"]


def world():
    from carto_cli.sim import loop_building, loop_trajectory

    w = loop_building()
    return w, loop_trajectory(w)


def build_map(directory: Path, duration: float = DURATION):
    """The map of the first pass, saved under ``directory`` and loaded back (what `carto relocalize` reads)."""
    from carto_cli.io.map_file import load_map, save_map
    from carto_cli.options import load_options
    from carto_cli.pipeline import build
    from carto_cli.sim import simulate

    w, tr = world()
    options = load_options(None, OVERRIDES)
    result = build(simulate(w, tr, duration=duration, scan_rate=SCAN_RATE).recording(), options)
    return load_map(save_map(Path(directory) / "map.carto", result, options))


def second_pass(mapped, duration: float = DURATION, every: int = 7):
    """(simulation, [(scan, reference pose in the map frame)]) of a second pass, every ``every``-th scan from
    FIRST_QUERY."""
    from carto_cli.sim import simulate

    w, tr = world()
    sim = simulate(w, tr, duration=duration, scan_rate=SCAN_RATE, seed=7)
    ref = {round(t, 6): p for t, p in zip(mapped.trajectory.t, mapped.trajectory.poses)}
    out = [(s, ref[round(s.time, 6)]) for k, s in enumerate(sim.records(["/scan"]))
           if k % every == 4 and round(s.time, 6) in ref and s.time >= FIRST_QUERY]
    return sim, out


def pose_error(a, b):
    """(m, degrees) between two poses."""
    d = np.asarray(a, float) - np.asarray(b, float)
    return math.hypot(d[0], d[1]), abs(math.degrees(transform.wrap_angle(d[2])))


def with_walls(loaded, probability):
    """A copy of ``loaded`` whose wall cells (p > 0.5) read ``probability(p)`` instead of p."""
    out = copy.deepcopy(loaded)
    for sub in out.submaps:
        grid = sub.grid
        grid.cells = grid.cells.copy()  # a loaded map's grids may be packed: writes go to cells of its own
        cells = np.argwhere(np.ones(grid.num_cells[::-1], dtype=bool))[:, ::-1]
        p = grid.probability(cells)
        walls = p > 0.5  # NaN (unknown) compares False
        grid.set_probability(cells[walls], probability(p[walls]))
    return out
