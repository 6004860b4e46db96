"""A candidate link judged by free space (mapping.link_check): a session's returns placed where they were scanned
fall on the other session's walls; placed half a turn round in the ring corridor, some of them stand in its free
corridor. The kernel against a numpy reference on the same cells."""
import math

import numpy as np
import pytest

from carto_cli.core import transform
from carto_cli.grid.occupancy_image import AssembledImage
from carto_cli.mapping import link_check
from carto_cli.mapping.link_check import LINK_CONFLICT, free_space_conflict
from carto_cli.options import load_options
from carto_cli.pipeline import build
from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate


@pytest.fixture(scope="module")
def lap():
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), scan_rate=5.0, lidar=Lidar(beams=180))
    result = build(sim.recording(), load_options())
    assert result.graph is not None
    return result.graph


def _reference(grids, corrections, points, poses) -> tuple[float, int]:
    """The share by the definition, cell by cell in numpy."""
    image = AssembledImage(grids, corrections)
    prob = image.probability
    cloud = np.concatenate([transform.apply(pose, p[np.hypot(p[:, 0], p[:, 1]) <= link_check.LINK_RANGE])
                            for pose, p in zip(poses, points)])
    ix = np.floor((cloud[:, 0] - image.origin[0]) / image.resolution).astype(int)
    iy = np.floor((cloud[:, 1] - image.origin[1]) / image.resolution).astype(int)
    inside = (ix >= 0) & (iy >= 0) & (ix < prob.shape[1]) & (iy < prob.shape[0])
    ix, iy = ix[inside], iy[inside]
    value = prob[iy, ix]
    known = ~np.isnan(value)
    wall = np.nan_to_num(prob, nan=0.0) > 0.5
    m = link_check.WALL_MARGIN
    padded = np.pad(wall, m)
    near = np.zeros_like(wall)
    for dy in range(-m, m + 1):
        for dx in range(-m, m + 1):
            near |= padded[m + dy:m + dy + wall.shape[0], m + dx:m + dx + wall.shape[1]]
    conflicting = known & (value <= link_check.FREE) & ~near[iy, ix]
    return float(conflicting.sum() / known.sum()), int(known.sum())


def test_returns_where_they_were_scanned_fall_on_walls_and_half_a_turn_round_in_free_space(lap):
    grids = [e.submap.grid for e in lap.submaps]
    corrections = [e.local_to_global() for e in lap.submaps]
    nodes = list(range(0, lap.num_nodes // 3, 2))
    points = [lap.node_points[n] for n in nodes]
    poses = lap.global_poses[nodes]
    right, known = free_space_conflict(points, poses, grids, corrections)
    assert known > 1000 and right < 0.005
    # The same scans turned half round about the building's centre: the ring's corridors meet corridors again,
    # but its rooms and pillars do not
    turn = transform.compose((24.0, 16.0, math.pi), np.zeros(3))  # (x, y) -> (24 - x, 16 - y): the 24 x 16 m ring
    wrong, known_wrong = free_space_conflict(points, transform.compose(turn, poses), grids, corrections)
    assert known_wrong > 1000 and wrong > LINK_CONFLICT > right
    for share, placed in ((right, poses), (wrong, transform.compose(turn, poses))):
        expected, n = _reference(grids, corrections, points, placed)
        assert share == pytest.approx(expected, abs=1e-12) and n > 0


def test_nothing_known_nothing_conflicting(lap):
    far = transform.compose((1000.0, 1000.0, 0.0), lap.global_poses[:5])
    share, known = free_space_conflict([lap.node_points[n] for n in range(5)], far,
                                       [e.submap.grid for e in lap.submaps],
                                       [e.local_to_global() for e in lap.submaps])
    assert (share, known) == (0.0, 0)
