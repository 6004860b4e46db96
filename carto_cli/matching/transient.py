"""Which scan points are likely transient (a person, a passing cart): they land where the grid has seen through
many times and no wall is near.

A point counts as transient when its cell at the given pose is known, its probability is at most
``max_free_probability`` (with Cartographer's miss probability 0.49 that takes about 15 rays through the cell)
and no cell within ``clearance`` of it (a square of cells) reaches ``OCCUPIED_PROBABILITY``. The clearance is what
keeps a wall point of a slightly wrong pose: its cell may read free, but the wall it belongs to is next to it,
and that pull is exactly what a matcher needs. Unknown cells never make a point transient, so the points of a
place seen for the first time all stay.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from carto_cli.core import transform
from carto_cli.core.kernels import register_warm_up
from carto_cli.grid.probability_grid import UNKNOWN_VALUE, VALUE_TO_PROBABILITY, ProbabilityGrid

__all__ = ["OCCUPIED_PROBABILITY", "transient_mask"]

# A cell with more hits than misses behind it: a wall within the clearance keeps a point.
OCCUPIED_PROBABILITY = 0.5


def transient_mask(grid: ProbabilityGrid, points: np.ndarray, pose: np.ndarray, *, max_free_probability: float,
                   clearance: float) -> np.ndarray:
    """(n,) bool: ``points`` (tracking frame) at ``pose`` that fall in known, confidently free cells of ``grid``
    with no occupied cell within ``clearance`` (m)."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(0, dtype=np.bool_)
    x, y, th = (float(v) for v in transform.as_pose(pose).reshape(3))
    reach = int(math.ceil(clearance / grid.resolution - 1e-9))
    return _mask(grid.cells, VALUE_TO_PROBABILITY, float(grid.origin[0]), float(grid.origin[1]),
                 1.0 / grid.resolution, math.cos(th), math.sin(th), x, y, pts, float(max_free_probability),
                 OCCUPIED_PROBABILITY, reach, UNKNOWN_VALUE)


@njit(cache=True, nogil=True)
def _mask(cells, table, ox, oy, inv_res, c, s, tx, ty, points, max_free, occupied, reach, unknown_value):
    ny, nx = cells.shape
    out = np.zeros(points.shape[0], dtype=np.bool_)
    for k in range(points.shape[0]):
        x = c * points[k, 0] - s * points[k, 1] + tx
        y = s * points[k, 0] + c * points[k, 1] + ty
        ix = int(np.floor((x - ox) * inv_res))
        iy = int(np.floor((y - oy) * inv_res))
        if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
            continue
        v = cells[iy, ix]
        if v == unknown_value or table[v] > max_free:
            continue
        out[k] = not _occupied_near(cells, table, ix, iy, reach, occupied, unknown_value)
    return out


@njit(cache=True, nogil=True)
def _occupied_near(cells, table, ix, iy, reach, occupied, unknown_value):
    ny, nx = cells.shape
    for jy in range(max(iy - reach, 0), min(iy + reach + 1, ny)):
        for jx in range(max(ix - reach, 0), min(ix + reach + 1, nx)):
            v = cells[jy, jx]
            if v != unknown_value and table[v] >= occupied:
                return True
    return False


@register_warm_up(system="cartographer")
def warm_up() -> None:
    """The mask kernel on a toy grid."""
    grid = ProbabilityGrid(0.05, (0.0, 0.0), (8, 8))
    grid.set_probability(np.array([[3, 3], [5, 5]]), np.array([0.9, 0.1]))
    transient_mask(grid, np.array([[0.16, 0.17], [0.27, 0.27]]), np.zeros(3), max_free_probability=0.3,
                   clearance=0.05)
