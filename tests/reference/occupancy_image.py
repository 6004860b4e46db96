"""numpy reference for grid.occupancy_image's pull kernel: every output cell, all at once."""
import numpy as np

from carto_cli.grid.probability_grid import VALUE_TO_PROBABILITY


def logodds_of_values() -> np.ndarray:
    p = np.clip(VALUE_TO_PROBABILITY.astype(np.float64), 1e-6, 1 - 1e-6)
    return np.log(p / (1.0 - p))


def accumulate(total, count, gox, goy, res, grid, correction, box):
    """Add ``grid``'s log-odds to every output cell of ``box`` (x0, y0, x1, y1) whose centre it knows."""
    x0, y0, x1, y1 = box
    gx, gy = np.meshgrid(np.arange(x0, x1), np.arange(y0, y1))
    tx, ty, th = correction
    c, s = np.cos(th), np.sin(th)
    wx = gox + (gx + 0.5) * res - tx
    wy = goy + (gy + 0.5) * res - ty
    lx, ly = c * wx + s * wy, -s * wx + c * wy
    ix = np.floor((lx - grid.origin[0]) / grid.resolution).astype(int)
    iy = np.floor((ly - grid.origin[1]) / grid.resolution).astype(int)
    ny, nx = grid.cells.shape
    inside = (ix >= 0) & (iy >= 0) & (ix < nx) & (iy < ny)
    values = np.zeros(gx.shape, dtype=grid.cells.dtype)
    values[inside] = grid.cells[iy[inside], ix[inside]]
    known = values != 0
    np.add.at(total, (gy[known], gx[known]), logodds_of_values()[values[known]])
    np.add.at(count, (gy[known], gx[known]), 1)
