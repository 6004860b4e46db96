import numpy as np
import pytest

from carto_cli.grid.probability_grid import MAX_PROBABILITY, MIN_PROBABILITY, ProbabilityGrid, probability_to_value
from carto_cli.matching.precomputation import (
    VALUE_TO_CELL_VALUE,
    PrecomputationGridStack,
    block_max,
    cell_value_to_probability,
    probability_to_cell_value,
)


def brute_block_max(base, width):
    """Level values the slow way: max over the block starting at every (padded) cell."""
    ny, nx = base.shape
    out = np.zeros((ny + width - 1, nx + width - 1), dtype=np.uint8)
    for iy in range(-(width - 1), ny):
        for ix in range(-(width - 1), nx):
            block = base[max(iy, 0):iy + width, max(ix, 0):ix + width]
            out[iy + width - 1, ix + width - 1] = block.max() if block.size else 0
    return out


def random_grid(rng, nx, ny, known=0.7):
    grid = ProbabilityGrid(0.05, rng.uniform(-3, 3, 2), (nx, ny))
    mask = rng.random((ny, nx)) < known
    grid.cells[mask] = probability_to_value(rng.uniform(MIN_PROBABILITY, MAX_PROBABILITY, mask.sum()))
    return grid


@pytest.mark.parametrize("shape", [(1, 1), (1, 9), (7, 3), (13, 17), (32, 32), (33, 5)])
@pytest.mark.parametrize("width", [1, 2, 4, 8, 16, 64])
def test_block_max_matches_brute_force_including_padding(shape, width):
    rng = np.random.default_rng(shape[0] * 100 + shape[1] + width)
    base = rng.integers(0, 256, shape).astype(np.uint8)
    np.testing.assert_array_equal(block_max(base, width), brute_block_max(base, width))


@pytest.mark.parametrize("seed", range(6))
def test_every_level_is_the_block_max_of_the_quantised_grid(seed):
    rng = np.random.default_rng(seed)
    nx, ny = (int(v) for v in rng.integers(1, 40, 2))
    depth = int(rng.integers(1, 7))
    grid = random_grid(rng, nx, ny, known=rng.uniform(0.1, 0.9))
    stack = PrecomputationGridStack(grid, depth)
    base = VALUE_TO_CELL_VALUE[grid.cells]
    assert stack.depth == depth and stack.num_cells == (nx, ny)
    for d in range(depth):
        level = stack.level(d)
        assert level.dtype == np.uint8 and stack.pad(d) == 2 ** d - 1
        np.testing.assert_array_equal(level, brute_block_max(base, 2 ** d))
    np.testing.assert_array_equal(stack.level(0), base)


def test_values_reads_blocks_by_submap_cell_and_zero_beyond_storage():
    rng = np.random.default_rng(3)
    grid = random_grid(rng, 10, 6, known=1.0)
    stack = PrecomputationGridStack(grid, 3)
    base = VALUE_TO_CELL_VALUE[grid.cells]
    cells = np.array([[0, 0], [-3, -3], [-4, 0], [9, 5], [10, 0], [2, 6], [5, 2]])
    got = stack.values(2, cells)
    assert got[0] == base[0:4, 0:4].max()
    assert got[1] == base[0:1, 0:1].max()  # a block reaching in from the low-side padding
    assert got[2] == 0 and got[4] == 0 and got[5] == 0  # blocks that only cover unknown space
    assert got[3] == base[5, 9]
    assert got[6] == base[2:6, 5:9].max()


def test_quantisation_follows_cartographer():
    assert probability_to_cell_value(MIN_PROBABILITY) == 0
    assert probability_to_cell_value(MAX_PROBABILITY) == 255
    assert probability_to_cell_value(0.5) == 128  # 127.5 rounds up, as RoundToInt does
    assert VALUE_TO_CELL_VALUE[0] == 0  # unknown scores like the least likely cell
    assert np.all(np.diff(VALUE_TO_CELL_VALUE[1:].astype(int)) <= 0)  # value = 1 - p grows, p falls
    assert cell_value_to_probability(255) == pytest.approx(MAX_PROBABILITY)
    p = np.linspace(MIN_PROBABILITY, MAX_PROBABILITY, 101)
    assert np.abs(cell_value_to_probability(probability_to_cell_value(p)) - p).max() <= 0.8 / 255 / 2 + 1e-12


def test_unknown_cells_score_zero_at_every_level():
    grid = ProbabilityGrid(0.05, (0.0, 0.0), (20, 20))
    grid.set_probability([[5, 5]], 0.9)
    stack = PrecomputationGridStack(grid, 4)
    for d in range(4):
        level = stack.level(d)
        w = 2 ** d
        # Exactly the blocks containing (5, 5) are non-zero.
        nz = np.argwhere(level > 0) - stack.pad(d)
        assert len(nz) == w * w
        assert nz[:, 0].min() == 5 - (w - 1) and nz[:, 0].max() == 5


def test_memory_of_a_400_cell_submap_at_depth_7():
    rng = np.random.default_rng(0)
    grid = random_grid(rng, 400, 400)
    stack = PrecomputationGridStack(grid, 7)
    expected = sum((400 + 2 ** d - 1) ** 2 for d in range(7))
    assert stack.data.nbytes == expected  # one byte per cell per level, padding included
    assert expected <= stack.memory_bytes < expected + 1024
    assert stack.memory_bytes < 1.25e6
    assert stack.grid_version == grid.version


def test_levels_are_read_only_and_depth_is_checked():
    stack = PrecomputationGridStack(ProbabilityGrid(0.05, (0, 0), (4, 4)), 2)
    with pytest.raises(ValueError):
        stack.level(1)[0, 0] = 1
    with pytest.raises(IndexError):
        stack.level(2)
    with pytest.raises(ValueError):
        PrecomputationGridStack(ProbabilityGrid(0.05, (0, 0), (4, 4)), 0)
    with pytest.raises(ValueError, match="GiB"):  # options allow depth 24: 2^23 cells of padding
        PrecomputationGridStack(ProbabilityGrid(0.05, (0, 0), (4, 4)), 24)


@pytest.mark.parametrize("shape,depth", [((7, 5), 1), ((40, 33), 4), ((120, 90), 7)])
def test_stack_bytes_predicts_the_built_stack(shape, depth):
    from carto_cli.matching.precomputation import stack_bytes

    g = ProbabilityGrid(0.05, (0.0, 0.0), shape)
    assert stack_bytes(g.num_cells, depth) == PrecomputationGridStack(g, depth).data.nbytes
