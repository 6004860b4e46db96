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

Insertion runs as two numba passes, timed separately (``insert/ray casting``,
``insert/update``): ray casting lists the cells of the hits and of every
free-space ray as index arrays; the update pass applies the odds tables to
them through the update marker. The split costs nothing measurable against a
fused kernel (the index arrays stay in cache) and lets one ray casting serve
every grid on the same cell lattice: both active submaps.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.grid.probability_grid import (
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


@njit(cache=True, nogil=True)
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


@njit(cache=True, nogil=True)
def _subpixel(points, ox, oy, sub):
    n = points.shape[0]
    out = np.empty((n, 2), dtype=np.int64)
    for i in range(n):
        out[i, 0] = np.int64(np.floor((points[i, 0] - ox) / sub))
        out[i, 1] = np.int64(np.floor((points[i, 1] - oy) / sub))
    return out


@njit(cache=True, nogil=True)
def cast_rays(ox, oy, resolution, sensor_x, sensor_y, returns, misses, insert_free_space):
    """Ray-casting pass: the cells to update, on the lattice of cells ``resolution`` wide from (ox, oy).

    Returns ``(hits, free, box)``: (n, 2) int32 cell indices of the returns; (m, 2)
    int32 cells crossed by the free-space rays (to every return, its own cell
    excluded, and to every miss, its end cell included), ray after ray, each from
    the sensor's cell outwards; and the (min_ix, min_iy, max_ix, max_iy) box of
    every cell listed (min > max when there is none). A cell may be listed many
    times: the update marker makes the update pass apply it once.
    """
    s = SUBPIXEL_SCALE
    sub = resolution / s
    bx = np.int64(np.floor((sensor_x - ox) / sub))
    by = np.int64(np.floor((sensor_y - oy) / sub))
    bcx = bx // s
    bcy = by // s
    hit_ends = _subpixel(returns, ox, oy, sub)
    miss_ends = _subpixel(misses, ox, oy, sub)
    n_hits = hit_ends.shape[0]
    n_misses = miss_ends.shape[0]
    box = np.empty(4, dtype=np.int64)
    box[0] = box[1] = np.iinfo(np.int64).max
    box[2] = box[3] = np.iinfo(np.int64).min
    hits = np.empty((n_hits, 2), dtype=np.int32)
    capacity = 0
    for i in range(n_hits):
        cx = hit_ends[i, 0] // s
        cy = hit_ends[i, 1] // s
        hits[i, 0] = cx
        hits[i, 1] = cy
        box[0] = min(box[0], cx)
        box[1] = min(box[1], cy)
        box[2] = max(box[2], cx)
        box[3] = max(box[3], cy)
        capacity += abs(cx - bcx) + abs(cy - bcy)
    if not insert_free_space:
        return hits, np.empty((0, 2), dtype=np.int32), box
    for i in range(n_misses):
        cx = miss_ends[i, 0] // s
        cy = miss_ends[i, 1] // s
        box[0] = min(box[0], cx)
        box[1] = min(box[1], cy)
        box[2] = max(box[2], cx)
        box[3] = max(box[3], cy)
        capacity += abs(cx - bcx) + abs(cy - bcy) + 1
    if n_hits + n_misses > 0:
        # Every ray starts in the sensor's cell (a zero-length hit ray is its own hit cell).
        box[0] = min(box[0], bcx)
        box[1] = min(box[1], bcy)
        box[2] = max(box[2], bcx)
        box[3] = max(box[3], bcy)
    free = np.empty((capacity, 2), dtype=np.int32)
    nf = 0
    for i in range(n_hits):
        nf += ray_cells(bx, by, hit_ends[i, 0], hit_ends[i, 1], s, False, free[nf:])
    for i in range(n_misses):
        nf += ray_cells(bx, by, miss_ends[i, 0], miss_ends[i, 1], s, True, free[nf:])
    return hits, free, box


@njit(cache=True, nogil=True)
def _apply_updates(cells, known_box, off_x, off_y, hits, free, box, hit_table, miss_table):
    """Update pass: hits, then free cells, each cell at most once (update marker); then unmark.

    Lattice cell (ix, iy) is grid cell (ix + off_x, iy + off_y); the grid must
    already contain ``box`` (see ``ProbabilityGrid.grow_to_include``).
    """
    _, nx = cells.shape
    flat = cells.reshape(-1)
    updated = np.empty(hits.shape[0] + free.shape[0], dtype=np.int64)
    nu = 0
    for i in range(hits.shape[0]):
        k = (hits[i, 1] + off_y) * nx + hits[i, 0] + off_x
        v = flat[k]
        if v < UPDATE_MARKER:
            flat[k] = hit_table[v]
            updated[nu] = k
            nu += 1
    for i in range(free.shape[0]):
        k = (free[i, 1] + off_y) * nx + free[i, 0] + off_x
        v = flat[k]
        if v < UPDATE_MARKER:
            flat[k] = miss_table[v]
            updated[nu] = k
            nu += 1
    for j in range(nu):
        flat[updated[j]] -= UPDATE_MARKER
    if nu > 0:
        known_box[0] = min(known_box[0], box[0] + off_x)
        known_box[1] = min(known_box[1], box[1] + off_y)
        known_box[2] = max(known_box[2], box[2] + off_x)
        known_box[3] = max(known_box[3], box[3] + off_y)
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

    def insert(self, range_data: RangeData, grid: ProbabilityGrid,
               timer: StageTimer | NullTimer | None = None) -> int:
        """Insert range data given in the grid's frame; returns the number of cells updated."""
        return self.insert_many(range_data, [grid], timer)[0]

    def insert_many(self, range_data: RangeData, grids: Sequence[ProbabilityGrid],
                    timer: StageTimer | NullTimer | None = None) -> list[int]:
        """Insert the same range data into several grids; returns the cells updated in each.

        Rays are cast once for all grids whose cells lie on a common lattice
        (origins a whole number of cells apart, as submaps' are): the update
        pass then only shifts the indices. Times the two passes as
        ``ray casting`` and ``update`` when given a ``StageTimer``.
        """
        timer = timer or NullTimer()
        origin = np.asarray(range_data.origin, dtype=np.float64).reshape(2)
        returns = np.ascontiguousarray(range_data.returns, dtype=np.float64).reshape(-1, 2)
        misses = np.ascontiguousarray(range_data.misses, dtype=np.float64).reshape(-1, 2)
        counts = []
        # lattice origin x, y, resolution, hits, free, box (array, list) of the last ray casting
        cast: tuple | None = None
        for grid in grids:
            res = grid.resolution
            gx, gy = float(grid.origin[0]), float(grid.origin[1])
            off = None
            if cast is not None and cast[2] == res:
                sx, sy = (cast[0] - gx) / res, (cast[1] - gy) / res
                if abs(sx - round(sx)) < 1e-6 and abs(sy - round(sy)) < 1e-6:
                    off = (round(sx), round(sy))
            if off is None:
                with timer.stage("ray casting"):
                    hits, free, box = cast_rays(gx, gy, res, origin[0], origin[1], returns, misses,
                                                 self.insert_free_space)
                    cast = (gx, gy, res, hits, free, box, box.tolist())
                off = (0, 0)
            assert cast is not None
            lx, ly, _, hits, free, box, (b0, b1, b2, b3) = cast
            with timer.stage("update"):
                ny, nx = grid.cells.shape
                if b0 <= b2 and (b0 + off[0] < 0 or b1 + off[1] < 0 or b2 + off[0] >= nx or b3 + off[1] >= ny):
                    # Grow so the box's corner cells exist; growing moves the origin by whole cells.
                    corners = np.array([[lx + (b0 + 0.5) * res, ly + (b1 + 0.5) * res],
                                        [lx + (b2 + 0.5) * res, ly + (b3 + 0.5) * res]])
                    grid.grow_to_include(corners)
                    off = (round((lx - grid.origin[0]) / res), round((ly - grid.origin[1]) / res))
                n = _apply_updates(grid.cells, grid.known_box, off[0], off[1], hits, free, box,
                                   self.hit_table, self.miss_table)
                grid.version += 1
            counts.append(int(n))
        return counts
