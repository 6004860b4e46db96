"""An occupancy map and its dynamic distance field, over sparse 32 x 32-cell patches allocated on demand.

The map LaMa-style online SLAM matches against (IRIS LaMa's ``Slam2D``: scan-to-map matching on a distance map
kept up to date as scans are inserted, no submaps). Cells lie on the world lattice ``floor(x / resolution)``; a
table of patch ids (grown as the map grows, like ``gmapping/maps.py``'s tiles) points into one pool of patches,
so memory follows the area seen, not its bounding box.

Each cell keeps:

* occupancy as frequency counts, GMapping's and LaMa's ``FrequencyOccupancyMap``: rays that ended in it (hits) and
  rays that reached it (visits); it is an obstacle while ``hits > occupied_fraction * visits``. A cell is
  counted at most once per inserted scan (an update mark, as Cartographer's inserter does), hits first, so a ray
  to a farther return cannot clear the obstacle a nearer one has just marked;
* the squared distance (in cells, exact integer Euclidean) to the nearest obstacle cell and that obstacle's
  offset, both only while the distance is within ``max_distance`` (W = ceil(max_distance / resolution) cells);
  farther cells (and cells of patches never allocated) read W cells: the field is truncated.

The field is updated incrementally from the cells a scan turned into obstacles (``added``) or out of them
(``removed``), exactly (not the 4-neighbour wavefront of dynamic brushfire, which is only nearly Euclidean):

1. every removed cell is marked "no obstacle", every added one "obstacle at distance 0";
2. raising: a removed cell, and every cell within W of it whose stored nearest obstacle is no longer one, is
   recomputed from scratch by scanning the disk of radius W around it in order of increasing distance (first
   obstacle found is the nearest; the disk's offsets are precomputed and sorted);
3. lowering: every cell within W of an added cell takes it when it is nearer than what the cell holds.

After step 2 every cell is exact for the obstacles that remain (a cell whose nearest obstacle survived cannot have
got farther from the rest), step 3 adds the new ones. A cell costs at most the disk's (2W+1)^2 reads, usually a
few, since the nearest obstacle is close; the patches within W of every cell a scan hits are allocated before the
update, so the field never needs a patch that is not there.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from carto_cli.core.kernels import register_warm_up
from carto_cli.grid.range_inserter import cast_rays

TILE_BITS = 5
TILE = 1 << TILE_BITS  # cells per patch side: 32 x 32 cells, 1.6 m at 0.05 m
TILE_MASK = TILE - 1
TILE_CELLS = TILE * TILE
FAR = 32767  # stored squared distance of a cell farther than the truncation (int16 max)
_GROW_MARGIN = 4  # patches added on each side when the table grows
CELL_BYTES = 2 + 2 + 2 + 2 + 1  # hits, visits (uint16), squared distance (int16), nearest offset (2 x int8), mark


# ---------------------------------------------------------------------------------------------------- cell access

@njit(cache=True, nogil=True)
def cell_index(table, tx0, ty0, cx, cy):
    """Flat index into the pool of cell (cx, cy) (world lattice), or -1 when its patch is not allocated."""
    tx = (cx >> TILE_BITS) - tx0
    ty = (cy >> TILE_BITS) - ty0
    if tx < 0 or ty < 0 or ty >= table.shape[0] or tx >= table.shape[1]:
        return -1
    p = table[ty, tx]
    if p < 0:
        return -1
    return (np.int64(p) << (2 * TILE_BITS)) + ((cy & TILE_MASK) << TILE_BITS) + (cx & TILE_MASK)


@njit(cache=True, nogil=True)
def _cell_distance(table, tx0, ty0, sqdist, lut, cx, cy):
    k = cell_index(table, tx0, ty0, cx, cy)
    if k < 0:
        return lut[lut.shape[0] - 1]
    s = sqdist[k]
    last = lut.shape[0] - 1
    return lut[s] if s < last else lut[last]


@njit(cache=True, nogil=True)
def distance_and_gradient(table, tx0, ty0, sqdist, lut, inv_resolution, x, y):
    """Bilinear interpolation of the distance field at world (x, y) between cell centres: (d, dd/dx, dd/dy).

    ``lut[s]`` is the distance (m) of squared cell distance s; its last entry the truncation distance, which cells
    farther away and cells outside the allocated patches read."""
    u = x * inv_resolution - 0.5
    v = y * inv_resolution - 0.5
    fu = math.floor(u)
    fv = math.floor(v)
    i = np.int64(fu)
    j = np.int64(fv)
    ax = u - fu
    ay = v - fv
    d00 = _cell_distance(table, tx0, ty0, sqdist, lut, i, j)
    d10 = _cell_distance(table, tx0, ty0, sqdist, lut, i + 1, j)
    d01 = _cell_distance(table, tx0, ty0, sqdist, lut, i, j + 1)
    d11 = _cell_distance(table, tx0, ty0, sqdist, lut, i + 1, j + 1)
    bx = 1.0 - ax
    by = 1.0 - ay
    d = (d00 * bx + d10 * ax) * by + (d01 * bx + d11 * ax) * ay
    gx = ((d10 - d00) * by + (d11 - d01) * ay) * inv_resolution
    gy = ((d01 - d00) * bx + (d11 - d10) * ax) * inv_resolution
    return d, gx, gy


@njit(cache=True, nogil=True)
def _distances(table, tx0, ty0, sqdist, lut, inv_resolution, points):
    n = points.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        d, gx, gy = distance_and_gradient(table, tx0, ty0, sqdist, lut, inv_resolution, points[i, 0], points[i, 1])
        out[i, 0] = d
        out[i, 1] = gx
        out[i, 2] = gy
    return out


# ---------------------------------------------------------------------------------------------------- allocation

@njit(cache=True, nogil=True)
def _mark_missing(table, tx0, ty0, hits, free, w):
    """Mark (-2) every unallocated patch a free cell lies in or a hit cell's (2w+1)^2 neighbourhood touches;
    returns their table positions (k, 2) as (row, column)."""
    h, wd = table.shape
    out = np.empty((h * wd, 2), dtype=np.int64)
    n = 0
    for i in range(hits.shape[0]):
        x0 = ((np.int64(hits[i, 0]) - w) >> TILE_BITS) - tx0
        x1 = ((np.int64(hits[i, 0]) + w) >> TILE_BITS) - tx0
        y0 = ((np.int64(hits[i, 1]) - w) >> TILE_BITS) - ty0
        y1 = ((np.int64(hits[i, 1]) + w) >> TILE_BITS) - ty0
        for ty in range(y0, y1 + 1):
            for tx in range(x0, x1 + 1):
                if table[ty, tx] == -1:
                    table[ty, tx] = -2
                    out[n, 0] = ty
                    out[n, 1] = tx
                    n += 1
    for i in range(free.shape[0]):
        tx = (np.int64(free[i, 0]) >> TILE_BITS) - tx0
        ty = (np.int64(free[i, 1]) >> TILE_BITS) - ty0
        if table[ty, tx] == -1:
            table[ty, tx] = -2
            out[n, 0] = ty
            out[n, 1] = tx
            n += 1
    return out[:n].copy()


@njit(cache=True, nogil=True)
def _assign(table, marked, first, sqdist):
    """Give the marked patches the pool ids first, first + 1, ...; their cells start far from every obstacle
    (the counts start at zero: the pool grows with zeros)."""
    for j in range(marked.shape[0]):
        p = first + j
        table[marked[j, 0], marked[j, 1]] = p
        base = np.int64(p) * TILE_CELLS
        for k in range(TILE_CELLS):
            sqdist[base + k] = FAR


# ---------------------------------------------------------------------------------------------------- updates

@njit(cache=True, nogil=True)
def _update_counts(table, tx0, ty0, hit_count, visit_count, mark, sqdist, hits, free, occupied_fraction):
    """Count the scan's hits and free cells (each cell once, hits first); returns the cells (k, 2) that became
    obstacles and those that stopped being one."""
    touched = np.empty(hits.shape[0] + free.shape[0], dtype=np.int64)
    cells = np.empty((hits.shape[0] + free.shape[0], 2), dtype=np.int64)
    nt = 0
    for i in range(hits.shape[0] + free.shape[0]):
        is_hit = i < hits.shape[0]
        if is_hit:
            cx = np.int64(hits[i, 0])
            cy = np.int64(hits[i, 1])
        else:
            cx = np.int64(free[i - hits.shape[0], 0])
            cy = np.int64(free[i - hits.shape[0], 1])
        k = cell_index(table, tx0, ty0, cx, cy)
        if k < 0 or mark[k] != 0:
            continue
        mark[k] = 1
        if visit_count[k] == 65535:  # saturated: halve both, the ratio stays
            visit_count[k] = visit_count[k] // 2
            hit_count[k] = hit_count[k] // 2
        visit_count[k] += 1
        if is_hit:
            hit_count[k] += 1
        touched[nt] = k
        cells[nt, 0] = cx
        cells[nt, 1] = cy
        nt += 1
    added = np.empty((nt, 2), dtype=np.int64)
    removed = np.empty((nt, 2), dtype=np.int64)
    na = 0
    nr = 0
    for j in range(nt):
        k = touched[j]
        mark[k] = 0
        occupied = hit_count[k] > occupied_fraction * visit_count[k]
        was = sqdist[k] == 0
        if occupied and not was:
            added[na, 0] = cells[j, 0]
            added[na, 1] = cells[j, 1]
            na += 1
        elif was and not occupied:
            removed[nr, 0] = cells[j, 0]
            removed[nr, 1] = cells[j, 1]
            nr += 1
    return added[:na].copy(), removed[:nr].copy()


@njit(cache=True, nogil=True)
def _recompute(table, tx0, ty0, sqdist, offset, disk, cx, cy, k):
    """Cell (cx, cy) (flat index k) from scratch: the first obstacle along the disk's offsets (sorted by distance)."""
    for m in range(disk.shape[0]):
        n = cell_index(table, tx0, ty0, cx + disk[m, 0], cy + disk[m, 1])
        if n >= 0 and sqdist[n] == 0:
            sqdist[k] = disk[m, 2]
            offset[2 * k] = disk[m, 0]
            offset[2 * k + 1] = disk[m, 1]
            return
    sqdist[k] = FAR


@njit(cache=True, nogil=True)
def _update_distances(table, tx0, ty0, sqdist, offset, disk, added, removed):
    """Bring the field up to date after ``added`` cells became obstacles and ``removed`` ones stopped being one
    (see the module docstring); returns the number of cells whose distance was written."""
    written = 0
    for i in range(removed.shape[0]):
        k = cell_index(table, tx0, ty0, removed[i, 0], removed[i, 1])
        if k >= 0:
            sqdist[k] = FAR
    for i in range(added.shape[0]):
        k = cell_index(table, tx0, ty0, added[i, 0], added[i, 1])
        if k >= 0:
            sqdist[k] = 0
            offset[2 * k] = 0
            offset[2 * k + 1] = 0
            written += 1
    # Raise: cells whose nearest obstacle is gone, all within W of a removed cell.
    for i in range(removed.shape[0]):
        cx = removed[i, 0]
        cy = removed[i, 1]
        k = cell_index(table, tx0, ty0, cx, cy)
        if k < 0:
            continue
        if sqdist[k] == FAR:
            _recompute(table, tx0, ty0, sqdist, offset, disk, cx, cy, k)
            written += 1
        for m in range(1, disk.shape[0]):
            qx = cx + disk[m, 0]
            qy = cy + disk[m, 1]
            q = cell_index(table, tx0, ty0, qx, qy)
            if q < 0:
                continue
            s = sqdist[q]
            if s == 0 or s == FAR:
                continue
            n = cell_index(table, tx0, ty0, qx + offset[2 * q], qy + offset[2 * q + 1])
            if n < 0 or sqdist[n] != 0:
                _recompute(table, tx0, ty0, sqdist, offset, disk, qx, qy, q)
                written += 1
    # Lower: the new obstacles' disks.
    for i in range(added.shape[0]):
        cx = added[i, 0]
        cy = added[i, 1]
        for m in range(1, disk.shape[0]):
            d2 = disk[m, 2]
            q = cell_index(table, tx0, ty0, cx + disk[m, 0], cy + disk[m, 1])
            if q >= 0 and d2 < sqdist[q]:
                sqdist[q] = d2
                offset[2 * q] = -disk[m, 0]
                offset[2 * q + 1] = -disk[m, 1]
                written += 1
    return written


@njit(cache=True, nogil=True)
def _force(table, tx0, ty0, hit_count, visit_count, sqdist, cells, occupied):
    """Set cells' counts to one hit of one visit (``occupied``) or none of one; returns those whose state
    changes (the obstacle list to add or remove)."""
    out = np.empty((cells.shape[0], 2), dtype=np.int64)
    n = 0
    for i in range(cells.shape[0]):
        k = cell_index(table, tx0, ty0, cells[i, 0], cells[i, 1])
        if k < 0:
            continue
        was = sqdist[k] == 0
        hit_count[k] = 1 if occupied else 0
        visit_count[k] = 1
        if was != occupied:
            out[n, 0] = cells[i, 0]
            out[n, 1] = cells[i, 1]
            n += 1
    return out[:n].copy()


@njit(cache=True, nogil=True)
def _cell_state(table, tx0, ty0, sqdist, offset, cells):
    n = cells.shape[0]
    sq = np.full(n, FAR, dtype=np.int64)
    nearest = cells.copy()
    for i in range(n):
        k = cell_index(table, tx0, ty0, cells[i, 0], cells[i, 1])
        if k >= 0:
            sq[i] = sqdist[k]
            nearest[i, 0] += offset[2 * k]
            nearest[i, 1] += offset[2 * k + 1]
    return sq, nearest


@njit(cache=True, nogil=True)
def _dense(table, hit_count, visit_count, sqdist, lut, r0, c0, rows, cols):
    """Occupancy (hits / visits, NaN unknown) and distance (m) of the table's rows r0.. and columns c0.. as dense
    images, row 0 at the lowest y."""
    occ = np.full((rows * TILE, cols * TILE), np.nan, dtype=np.float32)
    dist = np.full((rows * TILE, cols * TILE), lut[lut.shape[0] - 1], dtype=np.float32)
    last = lut.shape[0] - 1
    for r in range(rows):
        for c in range(cols):
            p = table[r0 + r, c0 + c]
            if p < 0:
                continue
            base = np.int64(p) * TILE_CELLS
            for iy in range(TILE):
                for ix in range(TILE):
                    k = base + iy * TILE + ix
                    if visit_count[k] > 0:
                        occ[r * TILE + iy, c * TILE + ix] = hit_count[k] / visit_count[k]
                    s = sqdist[k]
                    dist[r * TILE + iy, c * TILE + ix] = lut[s] if s < last else lut[last]
    return occ, dist


def _disk(w: int) -> np.ndarray:
    """Offsets (dx, dy, dx^2 + dy^2) within radius w, nearest first (ties in a fixed order)."""
    r = np.arange(-w, w + 1)
    dx, dy = np.meshgrid(r, r, indexing="xy")
    d2 = dx * dx + dy * dy
    keep = d2 <= w * w
    rows = np.stack([dx[keep], dy[keep], d2[keep]], axis=1).astype(np.int64)
    order = np.lexsort((rows[:, 0], rows[:, 1], rows[:, 2]))
    return np.ascontiguousarray(rows[order])


def _flat(a: np.ndarray) -> np.ndarray:
    v = a.view()
    v.shape = (a.size,)
    return v


class DistanceMap:
    """Occupancy counts and a truncated Euclidean distance field on sparse patches; see the module docstring.

    ``resolution`` m per cell; ``max_distance`` m, the truncation (rounded up to whole cells);
    ``occupied_fraction`` the share of a cell's visits that must be hits for it to be an obstacle (LaMa: 0.25).
    """

    def __init__(self, resolution: float = 0.05, max_distance: float = 0.5, occupied_fraction: float = 0.25,
                 capacity: int = 64):
        if resolution <= 0 or max_distance <= 0:
            raise ValueError("resolution and max_distance must be positive")
        self.resolution = float(resolution)
        self.window = max(1, math.ceil(max_distance / resolution - 1e-9))
        if self.window > 127:
            raise ValueError("max_distance / resolution must be at most 127 cells (offsets are int8)")
        self.max_distance = self.window * self.resolution
        self.occupied_fraction = float(occupied_fraction)
        self.disk = _disk(self.window)
        r2 = self.window * self.window
        lut = np.sqrt(np.arange(r2 + 2, dtype=np.float64)) * self.resolution
        lut[r2 + 1] = self.max_distance
        self.lut = lut
        self.hit_count = np.zeros(capacity * TILE_CELLS, np.uint16)
        self.visit_count = np.zeros(capacity * TILE_CELLS, np.uint16)
        self.sqdist = np.empty(capacity * TILE_CELLS, np.int16)
        self.offset = np.empty(capacity * TILE_CELLS * 2, np.int8)
        self.mark = np.zeros(capacity * TILE_CELLS, np.uint8)
        self.patches = 0  # pool ids 0 .. patches - 1 are in use
        self.table = np.full((0, 0), -1, np.int32)
        self.tile_origin = (0, 0)  # world patch index (tx, ty) of table[0, 0]
        self.version = 0

    # ------------------------------------------------------------------ geometry

    @property
    def capacity(self) -> int:
        return self.sqdist.shape[0] // TILE_CELLS

    @property
    def memory_bytes(self) -> int:
        """Bytes of the patches in use and the table (the pool's free tail is reserved, never touched)."""
        return self.patches * TILE_CELLS * CELL_BYTES + self.table.nbytes

    def ensure_covers(self, cx0: int, cy0: int, cx1: int, cy1: int) -> None:
        """Grow the table to cover cells [cx0, cx1] x [cy0, cy1] (world lattice), keeping what is there."""
        tx0, ty0, tx1, ty1 = cx0 >> TILE_BITS, cy0 >> TILE_BITS, cx1 >> TILE_BITS, cy1 >> TILE_BITS
        ox, oy = self.tile_origin
        h, w = self.table.shape
        if h and w:
            if tx0 >= ox and ty0 >= oy and tx1 < ox + w and ty1 < oy + h:
                return
            tx0, ty0 = min(tx0, ox), min(ty0, oy)
            tx1, ty1 = max(tx1, ox + w - 1), max(ty1, oy + h - 1)
        tx0, ty0, tx1, ty1 = tx0 - _GROW_MARGIN, ty0 - _GROW_MARGIN, tx1 + _GROW_MARGIN, ty1 + _GROW_MARGIN
        table = np.full((ty1 - ty0 + 1, tx1 - tx0 + 1), -1, np.int32)
        table[oy - ty0:oy - ty0 + h, ox - tx0:ox - tx0 + w] = self.table
        self.table = table
        self.tile_origin = (tx0, ty0)

    def _allocate(self, hits: np.ndarray, free: np.ndarray, box: np.ndarray | Sequence[int] | None = None) -> None:
        """Patches for the free cells and for every cell within the window of a hit; ``box`` (min x, min y,
        max x, max y) of all those cells when the caller knows it (the ray casting does)."""
        if hits.shape[0] == 0 and free.shape[0] == 0:
            return
        w = self.window
        if box is None:
            both = np.concatenate([hits, free]).astype(np.int64)
            box = (*both.min(axis=0), *both.max(axis=0))
        self.ensure_covers(int(box[0]) - w, int(box[1]) - w, int(box[2]) + w, int(box[3]) + w)
        ox, oy = self.tile_origin
        marked = _mark_missing(self.table, ox, oy, hits, free, w)
        if marked.shape[0] == 0:
            return
        need = self.patches + marked.shape[0]
        if need > self.capacity:
            self._grow_pool(max(2 * self.capacity, need))
        _assign(self.table, marked, self.patches, self.sqdist)
        self.patches = need

    def _grow_pool(self, capacity: int) -> None:
        n = capacity * TILE_CELLS

        def grown(a, size, zero=True):
            out = np.zeros(size, a.dtype) if zero else np.empty(size, a.dtype)
            out[:a.shape[0]] = a
            return out

        self.hit_count = grown(self.hit_count, n)
        self.visit_count = grown(self.visit_count, n)
        self.sqdist = grown(self.sqdist, n, zero=False)
        self.offset = grown(self.offset, 2 * n, zero=False)
        self.mark = grown(self.mark, n)

    # ------------------------------------------------------------------ writing

    def insert(self, origin: ArrayLike, returns: ArrayLike, misses: ArrayLike | None = None) -> tuple[int, int]:
        """Insert a scan given in the map frame: rays from ``origin`` (2,) to ``returns`` (n, 2) end in
        obstacles, rays to ``misses`` (m, 2) only clear free space. Returns (cells that became obstacles, cells
        that stopped being one)."""
        origin = np.asarray(origin, dtype=np.float64).reshape(2)
        returns = np.ascontiguousarray(returns, dtype=np.float64).reshape(-1, 2)
        misses = np.ascontiguousarray(misses if misses is not None else np.empty((0, 2)),
                                      dtype=np.float64).reshape(-1, 2)
        hits, free, box = cast_rays(0.0, 0.0, self.resolution, origin[0], origin[1], returns, misses, True)
        self._allocate(hits, free, box)
        ox, oy = self.tile_origin
        added, removed = _update_counts(self.table, ox, oy, self.hit_count, self.visit_count, self.mark,
                                        self.sqdist, hits, free, self.occupied_fraction)
        if added.shape[0] or removed.shape[0]:
            _update_distances(self.table, ox, oy, self.sqdist, self.offset, self.disk, added, removed)
        self.version += 1
        return int(added.shape[0]), int(removed.shape[0])

    def set_obstacles(self, add: ArrayLike | None = None, remove: ArrayLike | None = None) -> None:
        """Make cells (k, 2) (world lattice) obstacles or not directly (their counts set to one hit or one miss),
        then update the field: for tests and for maps loaded from elsewhere."""
        add = np.ascontiguousarray(add if add is not None else np.empty((0, 2)), dtype=np.int64).reshape(-1, 2)
        remove = np.ascontiguousarray(remove if remove is not None else np.empty((0, 2)),
                                      dtype=np.int64).reshape(-1, 2)
        self._allocate(add.astype(np.int32), remove.astype(np.int32))
        ox, oy = self.tile_origin
        # Removals first, then additions: a cell in both ends an obstacle.
        none = np.empty((0, 2), np.int64)
        removed = _force(self.table, ox, oy, self.hit_count, self.visit_count, self.sqdist, remove, False)
        _update_distances(self.table, ox, oy, self.sqdist, self.offset, self.disk, none, removed)
        added = _force(self.table, ox, oy, self.hit_count, self.visit_count, self.sqdist, add, True)
        _update_distances(self.table, ox, oy, self.sqdist, self.offset, self.disk, added, none)
        self.version += 1

    # ------------------------------------------------------------------ reading

    def distances(self, points: ArrayLike) -> np.ndarray:
        """(n, 3): interpolated distance (m) and its gradient (per m) at world ``points`` (n, 2)."""
        pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        ox, oy = self.tile_origin
        return _distances(self.table, ox, oy, self.sqdist, self.lut, 1.0 / self.resolution, pts)

    def cell_state(self, cells: ArrayLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """For cells (k, 2) of the world lattice: squared distance in cells (FAR beyond the truncation or
        unallocated), the nearest obstacle cell (k, 2; meaningless where FAR), and whether each is an obstacle."""
        cells = np.ascontiguousarray(cells, dtype=np.int64).reshape(-1, 2)
        ox, oy = self.tile_origin
        sq, nearest = _cell_state(self.table, ox, oy, self.sqdist, self.offset, cells)
        return sq, nearest, sq == 0

    def images(self):
        """(occupancy, distance, origin): dense float32 images of the allocated area (occupancy hits / visits,
        NaN unknown; distance in m), row 0 at the lowest y, and the world position of their [0, 0] corner."""
        known = np.argwhere(self.table >= 0)
        if known.shape[0] == 0:
            return np.full((1, 1), np.nan, np.float32), np.full((1, 1), self.max_distance, np.float32), (0.0, 0.0)
        (r0, c0), (r1, c1) = known.min(axis=0), known.max(axis=0)
        occ, dist = _dense(self.table, self.hit_count, self.visit_count, self.sqdist, self.lut, int(r0), int(c0),
                           int(r1 - r0 + 1), int(c1 - c0 + 1))
        ox, oy = self.tile_origin
        span = self.resolution * TILE
        return occ, dist, ((ox + c0) * span, (oy + r0) * span)


@register_warm_up(system="scan-to-map")
def warm_up() -> None:
    """Insertion (ray casting, counts, field) and reading, on a toy scan."""
    dm = DistanceMap(0.05, 0.3, capacity=4)
    angles = np.linspace(-1.5, 1.5, 32)
    ends = np.stack([2.0 * np.cos(angles), 2.0 * np.sin(angles)], axis=1)
    dm.insert((0.0, 0.0), ends)
    dm.insert((0.0, 0.0), 1.5 * ends)  # clears the first returns: raising too
    dm.set_obstacles(np.array([[3, 3]]), np.array([[3, 3]]))
    dm.distances(ends)
    dm.images()
