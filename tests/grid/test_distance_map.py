import math

import numpy as np
import pytest
from support import draws

from carto_cli.grid.distance_map import FAR, TILE, DistanceMap


def brute_force(obstacles: np.ndarray, cells: np.ndarray, window: int) -> np.ndarray:
    """Squared cell distance from every cell to the nearest obstacle, FAR beyond the window (numpy, no cleverness)."""
    if obstacles.shape[0] == 0:
        return np.full(cells.shape[0], FAR, np.int64)
    out = np.empty(cells.shape[0], np.int64)
    for start in range(0, cells.shape[0], 4096):
        c = cells[start:start + 4096]
        d = c[:, None, :] - obstacles[None, :, :]
        out[start:start + 4096] = (d * d).sum(-1).min(axis=1)
    out[out > window * window] = FAR
    return out


def edt_reference(obstacles: np.ndarray, cells: np.ndarray, window: int) -> np.ndarray:
    """The same from scipy's exact Euclidean distance transform, for large boxes (cells: a whole box, row-major)."""
    from scipy.ndimage import distance_transform_edt

    lo = cells.min(axis=0) - window - 1
    hi = cells.max(axis=0) + window + 1
    free = np.ones((hi[1] - lo[1] + 1, hi[0] - lo[0] + 1), bool)
    inside = np.all((obstacles >= lo) & (obstacles <= hi), axis=1)
    free[obstacles[inside, 1] - lo[1], obstacles[inside, 0] - lo[0]] = False
    d = distance_transform_edt(free)
    out = np.rint(d[cells[:, 1] - lo[1], cells[:, 0] - lo[0]] ** 2).astype(np.int64)
    out[out > window * window] = FAR
    return out


def box_cells(x0, y0, x1, y1) -> np.ndarray:
    xs, ys = np.meshgrid(np.arange(x0, x1 + 1), np.arange(y0, y1 + 1))
    return np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.int64)


def check_field(dm: DistanceMap, obstacles: np.ndarray, cells: np.ndarray, reference=brute_force) -> None:
    sq, nearest, is_obstacle = dm.cell_state(cells)
    expected = reference(obstacles, cells, dm.window)
    bad = np.flatnonzero(sq != expected)
    assert bad.size == 0, f"{bad.size} cells differ, e.g. {cells[bad[:5]]}: {sq[bad[:5]]} vs {expected[bad[:5]]}"
    # The stored nearest obstacle is an obstacle at exactly that distance.
    near = sq < FAR
    _, _, nobs = dm.cell_state(nearest[near])
    assert np.all(nobs)
    np.testing.assert_array_equal(((nearest[near] - cells[near]) ** 2).sum(1), sq[near])
    in_box = {tuple(c) for c in cells.tolist()}
    assert {tuple(c) for c in cells[is_obstacle].tolist()} == {tuple(c) for c in obstacles.tolist()} & in_box


@pytest.mark.parametrize("seed", range(2))
def test_field_matches_brute_force_after_random_insertions_and_removals(seed):
    rng = np.random.default_rng(seed)
    dm = DistanceMap(resolution=0.05, max_distance=0.4)  # window of 8 cells
    lo, hi = -45, 50  # straddles patch boundaries and negative cells
    occupied = set()
    cells = box_cells(lo - dm.window - 2, lo - dm.window - 2, hi + dm.window + 2, hi + dm.window + 2)
    for _ in range(draws(8, 2)):
        # Obstacles come in clumps and lines, as walls do, plus scattered single cells.
        add = rng.integers(lo, hi, (rng.integers(5, 60), 2))
        start = rng.integers(lo, hi - 20, 2)
        line = start + np.outer(np.arange(rng.integers(3, 20)), rng.integers(-1, 2, 2))
        add = np.concatenate([add, line])
        current = np.array(sorted(occupied), dtype=np.int64).reshape(-1, 2)
        remove = current[rng.random(current.shape[0]) < 0.3] if current.shape[0] else np.empty((0, 2), np.int64)
        dm.set_obstacles(add=add, remove=remove)
        occupied -= {tuple(c) for c in remove.tolist()}
        occupied |= {tuple(c) for c in add.tolist()}
        obstacles = np.array(sorted(occupied), dtype=np.int64).reshape(-1, 2)
        check_field(dm, obstacles, cells)


def test_removing_every_obstacle_leaves_nothing_near():
    dm = DistanceMap(resolution=0.05, max_distance=0.3)
    cells = box_cells(-10, -10, 40, 40)
    wall = np.stack([np.arange(0, 30), np.full(30, 7)], axis=1)
    dm.set_obstacles(add=wall)
    check_field(dm, wall, cells)
    dm.set_obstacles(remove=wall[::2])
    check_field(dm, wall[1::2], cells)
    dm.set_obstacles(remove=wall[1::2])
    sq, _, _ = dm.cell_state(cells)
    assert np.all(sq == FAR)
    assert np.allclose(dm.distances(np.array([[0.5, 0.37]]))[:, 0], dm.max_distance)


@pytest.mark.slow_without_jit
def test_scan_insertion_keeps_field_exact_and_counts_decide_obstacles():
    from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate

    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=6.0, lidar=Lidar(beams=360, fov=2 * math.pi, dropout=0.0),
                   scan_rate=5.0, odom_rate=10.0, imu_rate=0.0)
    dm = DistanceMap(resolution=0.05, max_distance=0.5)
    angles = sim.lidar.angles()
    changes = []
    for pose, ranges in zip(sim.laser_poses(sim.scan_times), sim.scan_ranges()):
        ok = np.isfinite(ranges)
        a = angles[ok] + pose[2]
        pts = pose[:2] + ranges[ok, None] * np.stack([np.cos(a), np.sin(a)], axis=1)
        changes.append(dm.insert(pose[:2], pts))
    assert changes[0][0] > 100 and sum(c[1] for c in changes) > 0  # walls appeared, and some cells were cleared
    occ, _, origin = dm.images()
    ny, nx = occ.shape
    x0, y0 = round(origin[0] / dm.resolution), round(origin[1] / dm.resolution)
    cells = box_cells(x0, y0, x0 + nx - 1, y0 + ny - 1)
    _, _, is_obstacle = dm.cell_state(cells)
    # Obstacles are exactly the cells hit on more than a quarter of their visits.
    ratio = occ.ravel()
    np.testing.assert_array_equal(is_obstacle, np.nan_to_num(ratio, nan=0.0) > 0.25)
    check_field(dm, cells[is_obstacle], cells, edt_reference)
    # The walls are where the obstacles are: each obstacle cell's centre lies within a cell of a wall.
    centres = (cells[is_obstacle] + 0.5) * dm.resolution
    assert np.percentile(world.distance_to_walls(centres), 95) < dm.resolution
    assert dm.patches * TILE * TILE < 0.8 * nx * ny  # sparse: the closed core was never allocated


def test_interpolated_gradient_matches_finite_differences_and_far_reads_truncation():
    dm = DistanceMap(resolution=0.05, max_distance=0.5)
    angles = np.linspace(0, 2 * math.pi, 400, endpoint=False)
    ring = np.stack([2.0 * np.cos(angles), 1.3 * np.sin(angles)], axis=1)
    dm.insert((0.0, 0.0), ring)
    rng = np.random.default_rng(4)
    pts = rng.uniform(-2.3, 2.3, (200, 2))
    out = dm.distances(pts)
    h = 1e-6
    fx = (dm.distances(pts + [h, 0])[:, 0] - dm.distances(pts - [h, 0])[:, 0]) / (2 * h)
    fy = (dm.distances(pts + [0, h])[:, 0] - dm.distances(pts - [0, h])[:, 0]) / (2 * h)
    np.testing.assert_allclose(out[:, 1], fx, atol=1e-4)
    np.testing.assert_allclose(out[:, 2], fy, atol=1e-4)
    assert np.all((out[:, 0] >= 0) & (out[:, 0] <= dm.max_distance + 1e-12))
    # Far from any wall and outside every patch: the truncation distance, flat.
    np.testing.assert_allclose(dm.distances(np.array([[0.0, 0.0], [50.0, -40.0]])), [[0.5, 0, 0], [0.5, 0, 0]])
    # On the ellipse the distance is small (cell centres within a cell of the wall).
    assert np.all(dm.distances(ring)[:, 0] < 0.05)
