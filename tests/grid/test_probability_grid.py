import pickle

import numpy as np
import pytest

from carto_cli.grid.probability_grid import (
    MAX_VALUE,
    VALUE_TO_CORRESPONDENCE_COST,
    VALUE_TO_PROBABILITY,
    ProbabilityGrid,
    correspondence_cost_to_value,
    probability_to_value,
)


def test_value_encoding_round_trips_and_clamps():
    p = np.linspace(0.1, 0.9, 101)
    np.testing.assert_allclose(VALUE_TO_PROBABILITY[probability_to_value(p)], p, atol=2e-5)
    assert probability_to_value(0.0) == probability_to_value(0.1) == MAX_VALUE
    assert probability_to_value(1.0) == probability_to_value(0.9) == 1
    assert correspondence_cost_to_value(0.1) == 1
    assert VALUE_TO_CORRESPONDENCE_COST[0] == pytest.approx(0.9)  # unknown reads as the worst cost
    assert VALUE_TO_PROBABILITY[1] == pytest.approx(0.9) and VALUE_TO_PROBABILITY[MAX_VALUE] == pytest.approx(0.1)


def test_cell_geometry():
    g = ProbabilityGrid(0.1, (-1.0, 2.0), (20, 10))
    assert g.num_cells == (20, 10) and g.cells.shape == (10, 20)
    np.testing.assert_array_equal(g.cell_index([[-1.0, 2.0], [-0.95, 2.99], [0.99, 2.0]]), [[0, 0], [0, 9], [19, 0]])
    np.testing.assert_allclose(g.cell_center([[0, 0]]), [[-0.95, 2.05]])
    np.testing.assert_array_equal(g.contains([[0, 0], [19, 9], [20, 0], [-1, 3]]), [True, True, False, False])


def test_probability_unknown_and_cells():
    from carto_cli.grid import probability_grid as pg

    g = ProbabilityGrid.centered((0.0, 0.0), 0.05, 40)
    g.set_probability([[3, 4], [5, 6]], [0.7, 0.2])
    np.testing.assert_allclose(g.probability([[3, 4], [5, 6]]), [0.7, 0.2], atol=1e-4)
    assert np.isnan(g.probability([[0, 0], [-5, 2]])).all()
    assert g.probability([[0, 0]], unknown=0.1)[0] == pytest.approx(0.1)
    np.testing.assert_array_equal(g.is_known([[3, 4], [0, 0]]), [True, False])
    assert g.cells.shape == (40, 40) and (g.cells != pg.UNKNOWN_VALUE).sum() == 2  # row 0 is the lowest y
    assert pg.VALUE_TO_PROBABILITY[g.cells[4, 3]] == pytest.approx(0.7, abs=1e-4)
    assert g.known_bounds == (3, 4, 5, 6)


def test_grow_keeps_contents_in_world_coordinates():
    g = ProbabilityGrid.centered((0.0, 0.0), 0.1, 10)
    rng = np.random.default_rng(0)
    cells = np.array([[i, j] for i in range(10) for j in range(10)])
    probs = rng.uniform(0.1, 0.9, len(cells))
    g.set_probability(cells, probs)
    centres = g.cell_center(cells)
    before = g.probability(g.cell_index(centres))
    for far in ([5.0, 0.2], [-3.0, -7.0], [0.0, 12.0]):
        nx, ny = g.num_cells
        assert g.grow_to_include(np.array([far]))
        assert g.contains(g.cell_index([far]))[0]
        np.testing.assert_array_equal(g.probability(g.cell_index(centres)), before)
        # Amortised: an axis that grows at least doubles.
        assert g.num_cells[0] in (nx,) or g.num_cells[0] >= 2 * nx
        assert g.num_cells[1] in (ny,) or g.num_cells[1] >= 2 * ny
    assert not g.grow_to_include(np.array([[0.0, 0.0]]))
    x0, y0, x1, y1 = g.known_bounds
    np.testing.assert_allclose(g.cell_center([[x0, y0], [x1, y1]]), [centres.min(axis=0), centres.max(axis=0)])


def test_cropped_keeps_known_cells_only():
    g = ProbabilityGrid.centered((1.0, 1.0), 0.05, 100)
    g.set_probability([[10, 20], [30, 25]], 0.8)
    c = g.cropped()
    assert c.num_cells == (21, 6)
    np.testing.assert_allclose(c.probability(c.cell_index(g.cell_center([[10, 20], [30, 25]]))), 0.8, atol=1e-4)
    assert c.known_bounds == (0, 0, 20, 5)


def test_a_packed_grid_reads_the_same_cells_and_takes_less_memory():
    import gc

    from carto_cli.grid import probability_grid as pg

    grid = ProbabilityGrid(0.05, (0.0, 0.0), (400, 300))
    grid.set_probability(np.array([[3, 4], [100, 150], [399, 299]]), 0.8)
    cells = grid.cells.copy()
    grid.pack()
    # Mostly unknown, as a corridor's submap: what is kept (and what a copy sent to another process carries) is small.
    assert len(pickle.dumps(grid)) < cells.nbytes / 20
    read = grid.cells
    assert np.array_equal(read, cells) and read.flags.writeable and read.dtype == np.uint16
    assert grid.cells is read  # kept unpacked while the budget allows
    before = pg.UNPACKED_CELLS.bytes
    del grid, read
    gc.collect()
    assert pg.UNPACKED_CELLS.bytes == before - cells.nbytes  # a collected grid's cells leave the count


def test_unpacked_cells_stay_within_their_budget(monkeypatch):
    from carto_cli.grid import probability_grid as pg

    lru = pg.UnpackedCells(3 * 400 * 300 * 2)
    monkeypatch.setattr(pg, "UNPACKED_CELLS", lru)
    grids = []
    for k in range(6):
        g = ProbabilityGrid(0.05, (0.0, 0.0), (400, 300))
        g.set_probability(np.array([[k, k]]), 0.8)
        g.pack()
        grids.append(g)
    for g in grids:
        assert g.cells[g.cells > 0].size == 1
    assert lru.bytes <= lru.budget and sum(g._unpacked is not None for g in grids) == 3
    for k, g in enumerate(grids):  # evicted ones unpack again, the same
        assert g.cells[k, k] == grids[k].cells[k, k] > 0
