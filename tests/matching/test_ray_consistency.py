"""see_through_fraction against a grid with one wall, and against a plain-Python ray walk."""
import math

import numpy as np
import pytest

from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.matching.ray_consistency import see_through_fraction


def _wall_grid():
    """10 x 10 m, free everywhere, a wall (p = 0.9) along x = 5 m."""
    g = ProbabilityGrid(0.05, (0.0, 0.0), (200, 200))
    xs = np.arange(200)
    cells = np.stack(np.meshgrid(xs, xs), axis=-1).reshape(-1, 2)
    g.set_probability(cells, np.full(len(cells), 0.2))
    wall = np.column_stack([np.full(200, 100), xs])
    g.set_probability(wall, np.full(200, 0.9))
    return g


def test_rays_ending_on_the_wall_do_not_see_through():
    g = _wall_grid()
    pts = np.column_stack([np.full(20, 5.02), np.linspace(1, 9, 20)])
    assert see_through_fraction(g, pts, (0.0, 0.0, 0.0), sensor=(2.0, 5.0), occupied=0.8, margin=0.3) == 0.0


def test_rays_ending_behind_the_wall_see_through():
    g = _wall_grid()
    pts = np.column_stack([np.full(20, 8.0), np.linspace(1, 9, 20)])
    assert see_through_fraction(g, pts, (0.0, 0.0, 0.0), sensor=(2.0, 5.0), occupied=0.8, margin=0.3) == 1.0
    # Within the margin (along the ray) of the endpoint the wall does not count: endpoints ~0.2 m behind it.
    pts = np.column_stack([np.full(20, 5.25), np.linspace(4, 6, 20)])
    assert see_through_fraction(g, pts, (0.0, 0.0, 0.0), sensor=(2.0, 5.0), occupied=0.8, margin=0.3) == 0.0


def test_the_pose_moves_sensor_and_points_together():
    g = _wall_grid()
    # In the scan's frame the sensor is at the origin and the points 6 m ahead; the pose puts it at x = 1 facing +x.
    pts = np.column_stack([np.full(10, 6.0), np.linspace(-1, 1, 10)])
    assert see_through_fraction(g, pts, (1.0, 5.0, 0.0), occupied=0.8, margin=0.3) == 1.0
    # Facing -x from x = 4: the points land at x = -2, outside the grid, and the rays never meet the wall.
    assert see_through_fraction(g, pts, (4.0, 5.0, math.pi), occupied=0.8, margin=0.3) == 0.0


def test_unknown_cells_never_count():
    g = ProbabilityGrid(0.05, (0.0, 0.0), (200, 200))
    pts = np.column_stack([np.full(10, 8.0), np.linspace(1, 9, 10)])
    assert see_through_fraction(g, pts, (0.0, 0.0, 0.0), sensor=(2.0, 5.0)) == 0.0


@pytest.mark.parametrize("seed", range(5))
def test_matches_a_plain_python_walk(seed):
    rng = np.random.default_rng(seed)
    g = ProbabilityGrid(0.1, (-5.0, -5.0), (100, 100))
    xs = np.arange(100)
    cells = np.stack(np.meshgrid(xs, xs), axis=-1).reshape(-1, 2)
    g.set_probability(cells, rng.uniform(0.1, 0.9, len(cells)))
    pts = rng.uniform(-4.5, 4.5, (50, 2))
    pose = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-math.pi, math.pi)])
    got = see_through_fraction(g, pts, pose, occupied=0.8, margin=0.3)

    c, s = math.cos(pose[2]), math.sin(pose[2])
    world = pts @ np.array([[c, s], [-s, c]]) + pose[:2]
    prob = g.probability(np.stack(np.meshgrid(xs, xs), axis=-1).reshape(-1, 2)).reshape(100, 100)  # [iy, ix]
    hits = checked = 0
    step = 0.05
    for p in world:
        d = p - pose[:2]
        length = math.hypot(*d)
        if length - 0.3 <= step:
            continue
        checked += 1
        u = d / length
        for k in range(1, int((length - 0.3) / step) + 1):
            q = pose[:2] + k * step * u
            ix, iy = (np.floor((q - g.origin) / g.resolution)).astype(int)
            if 0 <= ix < 100 and 0 <= iy < 100 and prob[iy, ix] >= 0.8:
                hits += 1
                break
    assert got == pytest.approx(hits / checked)
