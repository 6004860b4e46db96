import math

import numpy as np
import pytest
from reference.occupancy_image import accumulate as reference_accumulate

from carto_cli.core import transform
from carto_cli.grid.occupancy_image import OccupancyImage, assemble
from carto_cli.grid.probability_grid import ProbabilityGrid


def random_grid(rng, origin=(0.0, 0.0), cells=(30, 20), known=0.6):
    grid = ProbabilityGrid(0.05, origin, cells)
    iy, ix = np.nonzero(rng.random(grid.cells.shape) < known)
    grid.set_probability(np.stack([ix, iy], 1), rng.uniform(0.12, 0.88, len(ix)))
    return grid


def reference_assemble(grids, corrections, margin_cells=10):
    """The same output frame as assemble, every cell pulled by the numpy reference."""
    image = assemble(grids, corrections, margin_cells=margin_cells)
    ny, nx = image.probability.shape
    total, count = np.zeros((ny, nx)), np.zeros((ny, nx), np.int64)
    for grid, corr in zip(grids, corrections):
        reference_accumulate(total, count, image.origin[0], image.origin[1], image.resolution, grid,
                             transform.as_pose(corr), (0, 0, nx, ny))
    prob = np.full((ny, nx), np.nan)
    known = count > 0
    prob[known] = 1.0 / (1.0 + np.exp(-total[known] / count[known]))
    return image, prob


@pytest.mark.parametrize("seed", range(4))
def test_kernel_matches_the_numpy_reference_under_rotation(seed):
    rng = np.random.default_rng(seed)
    grids = [random_grid(rng, origin=rng.uniform(-1, 1, 2)) for _ in range(3)]
    corrections = [np.array([*rng.uniform(-0.5, 0.5, 2), rng.uniform(-math.pi, math.pi)]) for _ in grids]
    image, expected = reference_assemble(grids, corrections)
    np.testing.assert_array_equal(np.isnan(image.probability), np.isnan(expected))
    np.testing.assert_allclose(image.probability, expected, rtol=0, atol=1e-6, equal_nan=True)


def test_one_grid_at_identity_is_its_own_image():
    grid = random_grid(np.random.default_rng(7))
    image = assemble([grid], [np.zeros(3)], margin_cells=0)
    assert image.resolution == grid.resolution
    np.testing.assert_allclose(image.origin, grid.origin)
    iy, ix = np.indices(grid.cells.shape)
    own = grid.probability(np.stack([ix.ravel(), iy.ravel()], 1)).reshape(grid.cells.shape)
    np.testing.assert_allclose(image.probability, own, atol=1e-6, equal_nan=True)


def test_cells_are_averaged_not_summed():
    grid = random_grid(np.random.default_rng(3), known=1.0)
    once = assemble([grid], [np.zeros(3)])
    twice = assemble([grid, grid.copy()], [np.zeros(3), np.zeros(3)])
    np.testing.assert_allclose(twice.probability, once.probability, atol=1e-6, equal_nan=True)


def test_no_known_cell_gives_an_empty_image():
    image = assemble([ProbabilityGrid(0.05, (0.0, 0.0), (10, 10))], [np.zeros(3)])
    assert isinstance(image, OccupancyImage) and image.probability.shape == (0, 0)


def _random_grids(seed: int, n: int = 3):
    rng = np.random.default_rng(seed)
    grids, corrections = [], []
    for k in range(n):
        g = ProbabilityGrid(0.05, (k * 1.3, -0.7 * k), (320, 210))
        g.set_probability(rng.integers(0, 210, size=(600, 2)), 0.85)
        g.set_probability(rng.integers(0, 210, size=(600, 2)), 0.25)
        grids.append(g)
        corrections.append(np.array([0.4 * k, -0.3, 0.35 * k]))
    return grids, corrections


@pytest.mark.parametrize("strip", [1, 37, 256, 10_000])
def test_strips_hold_exactly_the_rows_of_the_whole_image(strip):
    from carto_cli.grid.occupancy_image import AssembledImage, image_rows

    grids, corrections = _random_grids(1)
    whole = assemble(grids, corrections)
    lazy = AssembledImage(grids, corrections)
    assert lazy.shape == whole.probability.shape and lazy.origin == whole.origin
    top_down = whole.probability[::-1]
    for rows in (list(lazy.rows(strip)), list(image_rows(whole, strip))):
        assert sum(len(r) for r in rows) == len(top_down)
        np.testing.assert_array_equal(np.concatenate(rows), top_down)


def test_coarsening_keeps_walls_and_unknown():
    from carto_cli.grid.occupancy_image import AssembledImage, coarsened

    grids, corrections = _random_grids(2)
    lazy = AssembledImage(grids, corrections)
    p = lazy.probability
    f = 6
    ny, nx = p.shape
    coarse = coarsened(lazy, f)
    assert coarse.probability.shape == (-(-ny // f), -(-nx // f)) and coarse.resolution == pytest.approx(0.05 * f)
    assert coarse.origin == lazy.origin
    for cy, cx in [(0, 0), (3, 7), (coarse.probability.shape[0] - 1, coarse.probability.shape[1] - 1)]:
        block = p[cy * f:(cy + 1) * f, cx * f:(cx + 1) * f]
        expected = np.nan if np.isnan(block).all() else np.nanmax(block)
        np.testing.assert_equal(coarse.probability[cy, cx], np.float32(expected))
