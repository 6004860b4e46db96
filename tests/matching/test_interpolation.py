import numpy as np
import pytest

from carto_cli.grid.probability_grid import VALUE_TO_CORRESPONDENCE_COST, ProbabilityGrid
from carto_cli.matching.interpolation import interpolate_correspondence_cost


def catmull_rom(p, x):
    p0, p1, p2, p3 = p
    return p1 + 0.5 * x * (p2 - p0 + x * (2 * p0 - 5 * p1 + 4 * p2 - p3 + x * (3 * (p1 - p2) + p3 - p0)))


def reference_cost(grid, x, y):
    """Plain-Python bicubic Catmull-Rom through cell centres; unknown/outside cells cost 0.9."""
    c = (x - grid.origin[0]) / grid.resolution - 0.5
    r = (y - grid.origin[1]) / grid.resolution - 0.5
    col, row = int(np.floor(c)), int(np.floor(r))
    nx, ny = grid.num_cells

    def cost(i, j):
        if 0 <= i < nx and 0 <= j < ny:
            return VALUE_TO_CORRESPONDENCE_COST[grid.cells[j, i]]
        return 0.9

    rows = [catmull_rom([cost(col + k, row + m) for k in (-1, 0, 1, 2)], c - col) for m in (-1, 0, 1, 2)]
    return catmull_rom(rows, r - row)


@pytest.fixture(scope="module")
def grid():
    rng = np.random.default_rng(5)
    g = ProbabilityGrid(0.05, (-0.3, 0.2), (16, 12))
    cells = np.array([[i, j] for i in range(16) for j in range(12) if rng.random() < 0.8])
    g.set_probability(cells, rng.uniform(0.1, 0.9, len(cells)))
    return g


def test_interpolates_cell_values_at_centres(grid):
    cells = np.array([[i, j] for i in range(16) for j in range(12)])
    values, _ = interpolate_correspondence_cost(grid, grid.cell_center(cells))
    np.testing.assert_allclose(values, VALUE_TO_CORRESPONDENCE_COST[grid.cells[cells[:, 1], cells[:, 0]]], atol=1e-12)


def test_matches_plain_python_reference(grid):
    rng = np.random.default_rng(6)
    pts = rng.uniform(grid.origin - 0.2, grid.max_corner + 0.2, size=(300, 2))
    values, _ = interpolate_correspondence_cost(grid, pts)
    np.testing.assert_allclose(values, [reference_cost(grid, x, y) for x, y in pts], atol=1e-12)


def test_gradient_matches_finite_differences(grid):
    rng = np.random.default_rng(7)
    pts = rng.uniform(grid.origin - 0.1, grid.max_corner + 0.1, size=(300, 2))
    _, grad = interpolate_correspondence_cost(grid, pts)
    h = 1e-6
    for axis in (0, 1):
        d = np.zeros(2)
        d[axis] = h
        fd = (interpolate_correspondence_cost(grid, pts + d)[0] - interpolate_correspondence_cost(grid, pts - d)[0]) / (2 * h)
        np.testing.assert_allclose(grad[:, axis], fd, atol=1e-5)


def test_far_outside_is_max_cost_and_flat(grid):
    values, grad = interpolate_correspondence_cost(grid, np.array([[-50.0, 3.0], [10.0, 100.0]]))
    np.testing.assert_allclose(values, 0.9)
    np.testing.assert_allclose(grad, 0.0, atol=1e-12)
