"""Insert range data into a ``ProbabilityGrid``: odds tables, update marker, sub-pixel ray casting.

Why it is shaped like Cartographer's inserter:

* Bayesian odds updates on uint16 values become one table lookup per cell:
  ``table[value]`` is the new value for a cell whose old value is ``value``.
* Every table entry carries ``UPDATE_MARKER``; a cell that already has it is
  skipped, so a cell is updated at most once per insertion however many rays
  cross it. Hits go first, so a ray to a farther hit cannot erase the
  obstacle that a nearer return has just marked. The markers are removed at
  the end of the insertion.
* Rays are traversed on a grid subdivided ``SUBPIXEL_SCALE`` times, so the
  set of cells a ray crosses follows the true segment between the measured
  points rather than between cell centres.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from carto_cli.mapping.grid import (
    UNKNOWN_VALUE,
    UPDATE_MARKER,
    VALUE_TO_PROBABILITY,
    ProbabilityGrid,
    probability_to_value,
)
from carto_cli.sensor.range_filter import RangeData

SUBPIXEL_SCALE = 1000


def odds(p: float) -> float:
    return p / (1.0 - p)


def probability_from_odds(o):
    return o / (o + 1.0)


def compute_lookup_table_to_apply_odds(update_odds: float) -> np.ndarray:
    """uint16 table of 32768 entries: the marked new value for every old value.

    An unknown cell takes the update's own probability (a uniform prior);
    a known cell's odds are multiplied by ``update_odds``, then clamped.
    """
    p = VALUE_TO_PROBABILITY.copy()
    new_p = probability_from_odds(update_odds * odds(p))
    new_p[UNKNOWN_VALUE] = probability_from_odds(update_odds)
    table = probability_to_value(new_p) + np.uint16(UPDATE_MARKER)
    table.flags.writeable = False
    return table


@njit(cache=True)
def ray_cells(bx, by, ex, ey, subpixel_scale, include_end, out):
    """Write the cells crossed by the segment between two sub-pixel indices into ``out``.

    Sub-pixel index b stands for the point at b + 1/2 (in sub-pixel units);
    doubling every coordinate keeps the traversal in exact integer arithmetic.
    Cells are visited in order from the begin cell, each step moving to a
    4-neighbour at the next cell boundary the segment crosses (x first when
    it passes exactly through a corner). ``out`` needs room for
    |Δcx| + |Δcy| + 1 rows; returns the count written.
    """
    s = subpixel_scale
    p2 = 2 * s
    px = 2 * bx + 1
    py = 2 * by + 1
    dx = 2 * ex + 1 - px
    dy = 2 * ey + 1 - py
    cx = bx // s
    cy = by // s
    tx = ex // s
    ty = ey // s
    adx = abs(dx)
    ady = abs(dy)
    sx = 1 if dx > 0 else -1
    sy = 1 if dy > 0 else -1
    # Distances (doubled sub-pixel units) to the next x and y cell boundaries.
    nxd = (cx + 1) * p2 - px if dx > 0 else px - cx * p2
    nyd = (cy + 1) * p2 - py if dy > 0 else py - cy * p2
    k = 0
    nsteps = abs(tx - cx) + abs(ty - cy)
    for _ in range(nsteps):
        out[k, 0] = cx
        out[k, 1] = cy
        k += 1
        # The boundary reached first along the segment is the one with the smaller nd / |d|.
        if ady == 0 or (adx != 0 and nxd * ady <= nyd * adx):
            cx += sx
            nxd += p2
        else:
            cy += sy
            nyd += p2
    if include_end:
        out[k, 0] = tx
        out[k, 1] = ty
        k += 1
    return k


@njit(cache=True)
def _apply(cells, ix, iy, table, updated, nu):
    ny, nx = cells.shape
    if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
        return nu
    v = cells[iy, ix]
    if v >= UPDATE_MARKER:
        return nu
    cells[iy, ix] = table[v]
    updated[nu] = iy * nx + ix
    return nu + 1


@njit(cache=True)
def _subpixel(points, ox, oy, sub):
    n = points.shape[0]
    out = np.empty((n, 2), dtype=np.int64)
    for i in range(n):
        out[i, 0] = np.int64(np.floor((points[i, 0] - ox) / sub))
        out[i, 1] = np.int64(np.floor((points[i, 1] - oy) / sub))
    return out


@njit(cache=True)
def _insert(cells, known_box, ox, oy, resolution, sensor_x, sensor_y, returns, misses,
            hit_table, miss_table, insert_free_space):
    s = SUBPIXEL_SCALE
    sub = resolution / s
    bx = np.int64(np.floor((sensor_x - ox) / sub))
    by = np.int64(np.floor((sensor_y - oy) / sub))
    hit_ends = _subpixel(returns, ox, oy, sub)
    miss_ends = _subpixel(misses, ox, oy, sub)
    bcx = bx // s
    bcy = by // s
    capacity = hit_ends.shape[0] + 1
    longest = 1
    for i in range(hit_ends.shape[0]):
        length = abs(hit_ends[i, 0] // s - bcx) + abs(hit_ends[i, 1] // s - bcy) + 1
        capacity += length
        longest = max(longest, length)
    for i in range(miss_ends.shape[0]):
        length = abs(miss_ends[i, 0] // s - bcx) + abs(miss_ends[i, 1] // s - bcy) + 1
        capacity += length
        longest = max(longest, length)
    updated = np.empty(capacity, dtype=np.int64)
    ray = np.empty((longest, 2), dtype=np.int64)
    nu = 0
    for i in range(hit_ends.shape[0]):
        nu = _apply(cells, hit_ends[i, 0] // s, hit_ends[i, 1] // s, hit_table, updated, nu)
    if insert_free_space:
        for i in range(hit_ends.shape[0]):
            k = ray_cells(bx, by, hit_ends[i, 0], hit_ends[i, 1], s, False, ray)
            for j in range(k):
                nu = _apply(cells, ray[j, 0], ray[j, 1], miss_table, updated, nu)
        for i in range(miss_ends.shape[0]):
            k = ray_cells(bx, by, miss_ends[i, 0], miss_ends[i, 1], s, True, ray)
            for j in range(k):
                nu = _apply(cells, ray[j, 0], ray[j, 1], miss_table, updated, nu)
    nx = cells.shape[1]
    for k in range(nu):
        iy = updated[k] // nx
        ix = updated[k] - iy * nx
        cells[iy, ix] -= UPDATE_MARKER
        known_box[0] = min(known_box[0], ix)
        known_box[1] = min(known_box[1], iy)
        known_box[2] = max(known_box[2], ix)
        known_box[3] = max(known_box[3], iy)
    return nu


class ProbabilityGridRangeDataInserter:
    """Cartographer's ``probability_grid_range_data_inserter`` for 2D grids."""

    def __init__(self, *, hit_probability: float = 0.55, miss_probability: float = 0.49,
                 insert_free_space: bool = True):
        if not 0.5 < hit_probability < 1.0:
            raise ValueError(f"hit_probability must be in (0.5, 1), got {hit_probability}")
        if not 0.0 < miss_probability < 0.5:
            raise ValueError(f"miss_probability must be in (0, 0.5), got {miss_probability}")
        self.hit_probability = float(hit_probability)
        self.miss_probability = float(miss_probability)
        self.insert_free_space = bool(insert_free_space)
        self.hit_table = compute_lookup_table_to_apply_odds(odds(hit_probability))
        self.miss_table = compute_lookup_table_to_apply_odds(odds(miss_probability))

    def insert(self, range_data: RangeData, grid: ProbabilityGrid) -> int:
        """Insert range data given in the grid's frame; returns the number of cells updated."""
        origin = np.asarray(range_data.origin, dtype=np.float64).reshape(2)
        returns = np.ascontiguousarray(range_data.returns, dtype=np.float64).reshape(-1, 2)
        misses = np.ascontiguousarray(range_data.misses, dtype=np.float64).reshape(-1, 2)
        grid.grow_to_include(np.concatenate([origin[None, :], returns, misses]))
        n = _insert(grid.cells, grid.known_box, grid.origin[0], grid.origin[1], grid.resolution,
                    origin[0], origin[1], returns, misses, self.hit_table, self.miss_table,
                    self.insert_free_space)
        grid.version += 1
        return int(n)
