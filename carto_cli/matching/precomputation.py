"""Cartographer's PrecomputationGrid2D stack: per level, the max probability over a 2^d × 2^d block.

Branch and bound needs, for a whole block of translations at once, an upper
bound on the score of every translation in it. Level ``d`` stores, for cell
(ix, iy), the maximum over cells [ix, ix + 2^d) × [iy, iy + 2^d) of the
submap, so the sum of these maxima under a scan bounds the score of all 4^d
translations of that block. Level 0 is the submap itself.

Storage follows Cartographer:

* probabilities are mapped linearly from [MIN_PROBABILITY, MAX_PROBABILITY]
  to 0..255 and kept as uint8 (a 400 × 400 submap at depth 7 costs ~1.2 MB
  instead of ~9.8 MB as float64); unknown cells read MIN_PROBABILITY, i.e. 0,
  so unexplored space can never make a candidate look good;
* level ``d`` is padded by 2^d - 1 cells on the low side of each axis, so a
  block that starts left of (or below) the submap but reaches into it still
  has a value; a block starting at or beyond the high edge only covers
  unknown cells and so reads 0, which needs no storage;
* all levels live in one flat buffer so numba kernels take a single array
  plus per-level (start, width, height, pad) instead of a list of arrays.

Each level is built from the quantised submap with a separable sliding-window
maximum (along x, then along y) by van Herk / Gil-Werman: three passes of
max operations per axis whatever the window, so a level costs O(cells)
rather than O(cells × 4^d) (naive) or O(cells × 2^d) (naive separable).
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from carto_cli.grid.probability_grid import MAX_PROBABILITY, MIN_PROBABILITY, VALUE_TO_PROBABILITY, ProbabilityGrid
from carto_cli.options.schema import FastCorrelativeScanMatcher, Relocalization

# Refuse stacks bigger than this rather than exhaust memory.
MAX_STACK_BYTES = 1 << 30

# Bit 15 is the inserter's update marker; a finished submap never carries it,
# but masking keeps the lookup in bounds if one is matched mid-insertion.
_VALUE_MASK = 0x7FFF


def probability_to_cell_value(p: ArrayLike) -> np.ndarray:
    """Cartographer's ComputeCellValue: [MIN_PROBABILITY, MAX_PROBABILITY] -> 0..255 (rounded)."""
    scaled = (np.asarray(p, dtype=np.float64) - MIN_PROBABILITY) * (255.0 / (MAX_PROBABILITY - MIN_PROBABILITY))
    return np.clip(np.floor(scaled + 0.5), 0, 255).astype(np.uint8)


def cell_value_to_probability(v):
    """Inverse of :func:`probability_to_cell_value` (also for mean values, as scores are)."""
    return MIN_PROBABILITY + np.asarray(v, dtype=np.float64) * ((MAX_PROBABILITY - MIN_PROBABILITY) / 255.0)


def _value_to_cell_value_table() -> np.ndarray:
    table = probability_to_cell_value(VALUE_TO_PROBABILITY)
    table[0] = 0  # unknown: already 0.1 in VALUE_TO_PROBABILITY, made explicit against rounding drift
    table.flags.writeable = False
    return table


VALUE_TO_CELL_VALUE = _value_to_cell_value_table()


@njit(cache=True, nogil=True)
def _quantise(cells, table):
    ny, nx = cells.shape
    out = np.empty((ny, nx), dtype=np.uint8)
    for iy in range(ny):
        for ix in range(nx):
            out[iy, ix] = table[cells[iy, ix] & _VALUE_MASK]
    return out


@njit(cache=True, nogil=True)
def _block_max_along_rows(src, w):
    """out[j] = max(src[j - w + 1 .. j]) (rows, element-wise) for j in [0, ny + w - 1), zero outside src.

    That is the max over the w rows *starting* at row j - (w - 1), which is how
    the low-side padding of a level is laid out. Whole rows are processed at a
    time so every inner loop runs over contiguous memory.
    """
    ny, nx = src.shape
    n_out = ny + w - 1
    # Zero-padded p[t] = src[t - (w - 1)], cut into blocks of w rows. van Herk / Gil-Werman:
    # out[j] = max(suffix max of p from j to the end of its block,
    #              prefix max of p from the start of the block holding j + w - 1 up to it).
    length = ((n_out + 2 * w - 2) // w) * w
    p = np.zeros((length, nx), dtype=np.uint8)
    for t in range(ny):
        for ix in range(nx):
            p[t + w - 1, ix] = src[t, ix]
    g = p.copy()
    h = p.copy()
    for b in range(0, length, w):
        for t in range(b + 1, b + w):
            for ix in range(nx):
                if g[t - 1, ix] > g[t, ix]:
                    g[t, ix] = g[t - 1, ix]
        for t in range(b + w - 2, b - 1, -1):
            for ix in range(nx):
                if h[t + 1, ix] > h[t, ix]:
                    h[t, ix] = h[t + 1, ix]
    out = np.empty((n_out, nx), dtype=np.uint8)
    for j in range(n_out):
        for ix in range(nx):
            a = h[j, ix]
            c = g[j + w - 1, ix]
            out[j, ix] = a if a > c else c
    return out


def block_max(base: np.ndarray, width: int) -> np.ndarray:
    """Padded block maximum of a uint8 (ny, nx) array for a square window of ``width`` cells.

    Returns (ny + width - 1, nx + width - 1); entry [iy + width - 1, ix + width - 1]
    is the max over base[iy:iy + width, ix:ix + width] (clipped to base), for
    ix, iy from -(width - 1).
    """
    base = np.ascontiguousarray(base, dtype=np.uint8)
    width = int(width)
    if width == 1:
        return base.copy()
    # Along x by transposing around the row kernel: two O(cells) copies buy one kernel
    # (and one compilation) instead of two.
    along_x = _block_max_along_rows(np.ascontiguousarray(base.T), width).T
    return _block_max_along_rows(np.ascontiguousarray(along_x), width)


def _level_shapes(nx: int, ny: int, depth: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pads, widths, heights) of each level: level d is padded by 2^d - 1 cells on the low side of each axis."""
    pads = (1 << np.arange(int(depth), dtype=np.int64)) - 1
    return pads, int(nx) + pads, int(ny) + pads


def stack_bytes(num_cells: Sequence[int], depth: int) -> int:
    """Bytes of the levels of a depth-``depth`` stack over a grid of ``num_cells`` (nx, ny), without building it."""
    _, widths, heights = _level_shapes(num_cells[0], num_cells[1], depth)
    return int((widths * heights).sum())


class PrecomputationGridStack:
    """Levels 0..depth-1 of block-max grids of one (finished) submap; build once, match many scans.

    ``level(d)[iy + pad(d), ix + pad(d)]`` is the max cell value over the
    2^d × 2^d block starting at submap cell (ix, iy), ``pad(d) = 2^d - 1``.
    Cell (ix, iy) covers ``origin + (ix, iy) * resolution`` as in the grid.
    """

    def __init__(self, grid: ProbabilityGrid, depth: int = 7) -> None:
        depth = int(depth)
        if depth < 1:
            raise ValueError(f"branch_and_bound_depth must be >= 1, got {depth}")
        self.depth = depth
        self.resolution = float(grid.resolution)
        self.origin = np.array(grid.origin, dtype=np.float64).reshape(2).copy()
        ny, nx = grid.cells.shape
        self.num_cells = (int(nx), int(ny))
        # Lets a caller holding the grid tell whether this stack is stale.
        self.grid_version = int(getattr(grid, "version", 0))

        base = _quantise(np.ascontiguousarray(grid.cells), VALUE_TO_CELL_VALUE)
        widths = 1 << np.arange(depth, dtype=np.int64)
        # columns (x) and rows (y) of each padded level
        self.pads, self.level_widths, self.level_heights = _level_shapes(nx, ny, depth)
        sizes = self.level_widths * self.level_heights
        if int(sizes.sum()) > MAX_STACK_BYTES:
            # Padding grows as 2^depth: the "depth 15-25" of some tuning guides would ask for
            # terabytes. Levels coarser than the search window prune nothing anyway.
            raise ValueError(f"a depth-{depth} stack of a {nx}x{ny} grid needs {int(sizes.sum()) / 2 ** 30:.1f} GiB; "
                             f"branch_and_bound_depth beyond log2(window in cells) + 1 gains nothing")
        self.starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
        self.data = np.empty(int(sizes.sum()), dtype=np.uint8)
        for d in range(depth):
            level = block_max(base, int(widths[d]))
            self.data[self.starts[d]:self.starts[d] + sizes[d]] = level.ravel()

    @classmethod
    def from_options(cls, grid: ProbabilityGrid,
                     options: FastCorrelativeScanMatcher | Relocalization) -> PrecomputationGridStack:
        """``options``: a ``FastCorrelativeScanMatcher`` options section (or anything with
        ``branch_and_bound_depth``)."""
        return cls(grid, options.branch_and_bound_depth)

    def level(self, d: int) -> np.ndarray:
        """Read-only (ny + 2^d - 1, nx + 2^d - 1) view of level ``d``."""
        if not 0 <= d < self.depth:
            raise IndexError(f"level {d} not in 0..{self.depth - 1}")
        h, w = int(self.level_heights[d]), int(self.level_widths[d])
        view = self.data[self.starts[d]:self.starts[d] + h * w].reshape(h, w)
        view.flags.writeable = False
        return view

    def pad(self, d: int) -> int:
        return int(self.pads[d])

    def values(self, d: int, cells: ArrayLike) -> np.ndarray:
        """uint8 level-``d`` values of the blocks starting at submap cells (n, 2) (ix, iy); 0 beyond storage."""
        c = np.asarray(cells, dtype=np.int64).reshape(-1, 2) + self.pad(d)
        lv = self.level(d)
        inside = (c[:, 0] >= 0) & (c[:, 1] >= 0) & (c[:, 0] < lv.shape[1]) & (c[:, 1] < lv.shape[0])
        out = np.zeros(c.shape[0], dtype=np.uint8)
        out[inside] = lv[c[inside, 1], c[inside, 0]]
        return out

    @property
    def memory_bytes(self) -> int:
        return int(self.data.nbytes + self.starts.nbytes + self.pads.nbytes
                   + self.level_widths.nbytes + self.level_heights.nbytes + self.origin.nbytes)

    def __repr__(self) -> str:
        nx, ny = self.num_cells
        return (f"PrecomputationGridStack({nx}x{ny} cells @ {self.resolution} m, depth {self.depth}, "
                f"{self.memory_bytes / 1e6:.2f} MB)")
