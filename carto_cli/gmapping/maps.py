"""Every particle's occupancy map, shared copy-on-write in tiles.

A particle's map is a table of tile ids into one pool of 32 x 32-cell tiles. Resampling copies
tables, not cells: a child shares every tile with its parent until it writes one, and only then
gets its own copy (OpenSLAM GMapping shares reference-counted patches the same way). What the
particles hold apart is what they saw since they last had a common ancestor, so memory follows the
divergence of the filter, not particles x building.

A cell keeps GMapping's counts: rays that ended in it (hits), rays that reached it (visits) and the
mean of the endpoints that fell in it; its occupancy is hits / visits and its wall sits at the mean
endpoint, which is what the scan matcher measures distances to (sub-cell precision at any delta). Seven
bytes a cell, as the maps of 100 particles are most of a key-scan log's memory: the counts one byte each,
halved together before they overflow (the occupancy is their ratio), and the mean as its place inside the
cell in 1/65536ths of a cell on each axis (0.8 um at 0.05 m: the float32 world coordinates it replaced
were no finer 100 m from the origin). What
the matcher asks of a cell (never seen, seen, or a wall) is also kept as one byte, updated with the
counts: the matcher reads a 3 x 3 neighbourhood per endpoint some hundred times per particle and scan,
and one byte per cell and the means of the walls touch a fraction of the memory the counts would
(the climb about twice as fast on intel, docs/gmapping.md).

Writing happens in three steps so that particles update in parallel without locks: the tiles each
particle's rays cross are marked (in parallel), marked tiles that are missing or shared get a fresh
tile id from the pool (sequential, cheap) and their cells copied (in parallel), then the cells are updated
(in parallel; each particle writes only tiles it now owns).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from carto_cli.core.kernels import register_warm_up

TILE_BITS = 5
# 32 x 32 cells, 7 KB, 1.6 m at the default delta. 16 x 16 tiles copy less when a particle first writes a shared
# tile (orebro at 100 particles: peak RSS 865 -> 710 MB, the same poses) but cost 17 % more CPU (the per-scan
# passes over every particle's table of tile ids grow 4x; docs/gmapping.md).
TILE = 1 << TILE_BITS  # cells per tile side
TILE_MASK = TILE - 1  # cell >> TILE_BITS and cell & TILE_MASK: floor division and modulo, negatives too
_GROW_MARGIN = 8  # tiles added on each side when the table grows
# hits, visits (uint8, halved together before they overflow), mean endpoint (2 x uint16 in the cell), state
CELL_BYTES = 1 + 1 + 4 + 1
COUNT_MAX = 255
MEAN_SCALE = 65536.0  # a stored mean m lies at (cell + m / MEAN_SCALE) * resolution
FULLNESS = 0.1  # a cell hit on more than this share of the rays reaching it is a wall
UNKNOWN, SEEN, WALL = 0, 1, 2  # a cell's state


class TiledMaps:
    """The maps of ``particles`` particles at ``resolution`` (metres per cell), cells on the world lattice
    ``floor(x / resolution)``."""

    def __init__(self, particles: int, resolution: float, capacity: int = 64):
        self.resolution = float(resolution)
        self.hits = np.zeros((capacity, TILE, TILE), np.uint8)
        self.visits = np.zeros((capacity, TILE, TILE), np.uint8)
        self.mean = np.zeros((capacity, TILE, TILE, 2), np.uint16)
        self.state = np.zeros((capacity, TILE, TILE), np.uint8)
        self.refs = np.zeros(capacity, np.int32)
        self.table = np.full((particles, 0, 0), -1, np.int32)  # covers nothing until the first insert
        self.marks = np.zeros((particles, 0, 0), np.uint8)
        self.tile_origin = (0, 0)  # world tile index (tx, ty) of table[:, 0, 0]
        self._free = np.arange(capacity - 1, -1, -1, dtype=np.int32)
        self._nfree = capacity
        self.peak_tiles = 0

    # ------------------------------------------------------------------ geometry

    @property
    def particles(self) -> int:
        return self.table.shape[0]

    @property
    def capacity(self) -> int:
        return self.refs.shape[0]

    @property
    def tiles_in_use(self) -> int:
        return self.capacity - self._nfree

    @property
    def memory_bytes(self) -> int:
        """Bytes reserved by the pool (used and free tiles) and the tables; free tiles never written take no
        memory (peak_tiles is what the maps used)."""
        return (self.capacity * TILE * TILE * CELL_BYTES + self.refs.nbytes + self.table.nbytes
                + self.marks.nbytes + self._free.nbytes)

    def ensure_covers(self, xmin: float, ymin: float, xmax: float, ymax: float) -> None:
        """Grow every table to cover the box (world metres), keeping what is there."""
        span = self.resolution * TILE
        tx0, ty0 = math.floor(xmin / span), math.floor(ymin / span)
        tx1, ty1 = math.floor(xmax / span), math.floor(ymax / span)
        ox, oy = self.tile_origin
        h, w = self.table.shape[1:]
        if h and w:
            if tx0 >= ox and ty0 >= oy and tx1 < ox + w and ty1 < oy + h:
                return
            tx0, ty0 = min(tx0, ox), min(ty0, oy)
            tx1, ty1 = max(tx1, ox + w - 1), max(ty1, oy + h - 1)
        tx0 -= _GROW_MARGIN
        ty0 -= _GROW_MARGIN
        tx1 += _GROW_MARGIN
        ty1 += _GROW_MARGIN
        table = np.full((self.particles, ty1 - ty0 + 1, tx1 - tx0 + 1), -1, np.int32)
        table[:, oy - ty0:oy - ty0 + h, ox - tx0:ox - tx0 + w] = self.table
        self.table = table
        self.marks = np.zeros(table.shape, np.uint8)
        self.tile_origin = (tx0, ty0)

    # ------------------------------------------------------------------ particles

    def reindex(self, parents: np.ndarray) -> None:
        """After resampling: particle ``i`` takes the map of particle ``parents[i]`` (tiles shared)."""
        self.table = np.ascontiguousarray(self.table[parents])
        used = self.table[self.table >= 0]
        self.refs = np.bincount(used, minlength=self.capacity).astype(np.int32)
        free = np.flatnonzero(self.refs == 0).astype(np.int32)
        self._free = np.ascontiguousarray(free[::-1])
        self._nfree = free.shape[0]

    # ------------------------------------------------------------------ writing

    def insert(self, poses: np.ndarray, origin: np.ndarray, ends: np.ndarray, hit: np.ndarray) -> None:
        """Cast every ray into every particle's map: particle ``p`` at ``poses[p]``, rays from ``origin`` to
        ``ends`` (tracking frame); a ray with ``hit`` ends in a wall, the others only clear free space."""
        poses = np.ascontiguousarray(poses, dtype=np.float64)
        ends = np.ascontiguousarray(ends, dtype=np.float64)
        if ends.shape[0] == 0:
            return
        world_x, world_y = _world_extent(poses, origin, ends)
        self.ensure_covers(world_x[0], world_y[0], world_x[1], world_y[1])
        ox, oy = self.tile_origin
        span = self.resolution * TILE
        lx, ly = float(origin[0]), float(origin[1])
        _mark_tiles(self.marks, poses, lx, ly, ends, span, ox, oy)
        needed = _count_needed(self.table, self.marks, self.refs)
        if needed > self._nfree:
            self._grow_pool(needed - self._nfree)
        self._nfree, sources, targets = _claim_tiles(self.table, self.marks, self.refs, self._free, self._nfree,
                                                     needed)
        # The kernels get the pool's cells flat: reshaping or slicing them there compiled numba's shape checks and
        # their messages (13 s of a fresh install's compiling for the tile copy alone)
        flat = _flat(self.hits), _flat(self.visits), _flat(self.mean), _flat(self.state)
        _fill_tiles(sources, targets, *flat)
        _update_cells(self.table, self.marks, *flat, poses, lx, ly, ends, np.ascontiguousarray(hit, dtype=np.bool_),
                      self.resolution, ox, oy)
        self.peak_tiles = max(self.peak_tiles, self.tiles_in_use)

    def _grow_pool(self, at_least: int) -> None:
        # Four times, not twice: growing copies every tile in use (0.65 s of edmonton's 13 s at 30 particles
        # when doubling, 0.2-0.3 s so), while the free tail costs no memory until a tile there is first written
        # (np.zeros maps fresh pages lazily).
        old = self.capacity
        new = max(old * 4, old + at_least)
        self.hits = _grown(self.hits, new)
        self.visits = _grown(self.visits, new)
        self.mean = _grown(self.mean, new)
        self.state = _grown(self.state, new)
        self.refs = _grown(self.refs, new)
        free = np.concatenate([np.arange(new - 1, old - 1, -1, dtype=np.int32), self._free[:self._nfree]])
        self._free = np.ascontiguousarray(free)
        self._nfree = free.shape[0]

    # ------------------------------------------------------------------ reading

    def occupancy(self, particle: int) -> tuple[np.ndarray, tuple[float, float]]:
        """``particle``'s map as float32 probabilities hits / visits (NaN unknown), cropped to its known
        tiles, and the world position of cell [0, 0]'s lower-left corner."""
        own = self.table[particle]
        known = np.argwhere(own >= 0)
        if known.shape[0] == 0:
            return np.full((1, 1), np.nan, np.float32), (0.0, 0.0)
        (y0, x0), (y1, x1) = known.min(axis=0), known.max(axis=0)
        prob = _occupancy(own[y0:y1 + 1, x0:x1 + 1], self.hits, self.visits)
        ox, oy = self.tile_origin
        span = self.resolution * TILE
        return prob, ((ox + x0) * span, (oy + y0) * span)

    def entropy(self, particle: int) -> float:
        """Mean binary entropy (bits) of ``particle``'s known cells: 0 when every cell is certain, 1 when every
        known cell is as often hit as crossed."""
        return float(_entropy(self.table[particle], self.hits, self.visits))


@register_warm_up(system="gmapping")
def warm_up() -> None:
    """The map update's kernels, and reading a map, on a toy scan into two particles' maps."""
    maps = TiledMaps(2, 0.05, capacity=4)
    angles = np.linspace(-1.5, 1.5, 32)
    ends = np.stack([2.0 * np.cos(angles), 2.0 * np.sin(angles)], axis=1)
    maps.insert(np.zeros((2, 3)), np.zeros(2), ends, np.ones(32, bool))
    maps.occupancy(0)
    maps.entropy(0)


def _flat(a: np.ndarray) -> np.ndarray:
    """``a`` as one axis, the same memory: the kernels write through it (reshape would copy an array that is not
    contiguous; setting the shape raises instead)."""
    v = a.view()
    v.shape = (a.size,)
    return v


def _grown(a: np.ndarray, capacity: int) -> np.ndarray:
    out = np.zeros((capacity,) + a.shape[1:], a.dtype)
    out[:a.shape[0]] = a
    return out


def _world_extent(poses, origin, ends):
    """Bounding box of every particle's rays (world metres)."""
    pts = np.vstack([ends, np.asarray(origin, dtype=np.float64)[None, :]])
    # Whatever a particle's heading, its rays stay within their farthest reach of its position.
    reach = float(np.sqrt(np.max(np.sum(pts * pts, axis=1))))
    xs, ys = poses[:, 0], poses[:, 1]
    return (xs.min() - reach, xs.max() + reach), (ys.min() - reach, ys.max() + reach)


@njit(cache=True, inline="always")
def _walk_start(x0, y0, x1, y1, size):
    """Amanatides-Woo's start: the first and last cells, the steps, and the ray parameters of the first x and y
    cell borders and between borders."""
    ix = int(math.floor(x0 / size))
    iy = int(math.floor(y0 / size))
    ex = int(math.floor(x1 / size))
    ey = int(math.floor(y1 / size))
    dx = x1 - x0
    dy = y1 - y0
    step_x = 1 if dx > 0 else -1
    step_y = 1 if dy > 0 else -1
    inf = 1e300
    if dx != 0.0:
        t_max_x = ((ix + (1 if dx > 0 else 0)) * size - x0) / dx
        t_delta_x = size / abs(dx)
    else:
        t_max_x = inf
        t_delta_x = inf
    if dy != 0.0:
        t_max_y = ((iy + (1 if dy > 0 else 0)) * size - y0) / dy
        t_delta_y = size / abs(dy)
    else:
        t_max_y = inf
        t_delta_y = inf
    return ix, iy, ex, ey, step_x, step_y, t_max_x, t_delta_x, t_max_y, t_delta_y


@njit(cache=True)
def traverse(x0, y0, x1, y1, size, out):
    """Every cell of side ``size`` the segment (x0, y0)-(x1, y1) passes through, in order (Amanatides-Woo),
    written as integer (ix, iy) rows into ``out``; returns how many. The last one holds (x1, y1)."""
    ix, iy, ex, ey, step_x, step_y, t_max_x, t_delta_x, t_max_y, t_delta_y = _walk_start(x0, y0, x1, y1, size)
    n = 0
    limit = min(out.shape[0], abs(ex - ix) + abs(ey - iy) + 1)
    out[0, 0] = ix
    out[0, 1] = iy
    n = 1
    while n < limit and (ix != ex or iy != ey):
        if t_max_x < t_max_y:
            t_max_x += t_delta_x
            ix += step_x
        else:
            t_max_y += t_delta_y
            iy += step_y
        out[n, 0] = ix
        out[n, 1] = iy
        n += 1
    # Rounding can leave the walk one step short of the end cell: the end cell is always last.
    out[n - 1, 0] = ex
    out[n - 1, 1] = ey
    return n


@njit(cache=True)
def _rays_in_world(pose, lx, ly, ends):
    """The sensor (sx, sy) and the rays' ends (n, 2) of a particle at ``pose``, in the world."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    world = np.empty_like(ends)
    for i in range(ends.shape[0]):
        world[i, 0] = pose[0] + c * ends[i, 0] - s * ends[i, 1]
        world[i, 1] = pose[1] + s * ends[i, 0] + c * ends[i, 1]
    return pose[0] + c * lx - s * ly, pose[1] + s * lx + c * ly, world


@njit(cache=True, parallel=True)
def _mark_tiles(marks, poses, lx, ly, ends, span, ox, oy):
    n_particles = poses.shape[0]
    h, w = marks.shape[1], marks.shape[2]
    for p in prange(n_particles):
        sx, sy, world = _rays_in_world(poses[p], lx, ly, ends)
        buf = np.empty((4 * (h + w) + 8, 2), np.int64)
        for i in range(ends.shape[0]):
            k = traverse(sx, sy, world[i, 0], world[i, 1], span, buf)
            for j in range(k):
                tx = buf[j, 0] - ox
                ty = buf[j, 1] - oy
                if 0 <= tx < w and 0 <= ty < h:
                    marks[p, ty, tx] = 1


@njit(cache=True)
def _count_needed(table, marks, refs):
    needed = 0
    for p in range(table.shape[0]):
        for ty in range(table.shape[1]):
            for tx in range(table.shape[2]):
                if marks[p, ty, tx]:
                    t = table[p, ty, tx]
                    if t < 0 or refs[t] > 1:
                        needed += 1
    return needed


@njit(cache=True)
def _claim_tiles(table, marks, refs, free, nfree, needed):
    """Give each particle its own tile id for every tile it is about to write (a fresh one where it has none);
    returns the free count left and the (source, target) pairs to copy (source -1: an empty tile). ``needed``:
    ``_count_needed``'s bound on how many. The ids are handed out in order here, sequentially; ``_fill_tiles``
    copies the cells in parallel."""
    sources = np.empty(needed, np.int32)
    targets = np.empty(needed, np.int32)
    k = 0
    for p in range(table.shape[0]):
        for ty in range(table.shape[1]):
            for tx in range(table.shape[2]):
                if not marks[p, ty, tx]:
                    continue
                t = table[p, ty, tx]
                if t >= 0 and refs[t] == 1:
                    continue
                nfree -= 1
                fresh = free[nfree]
                if t >= 0:
                    refs[t] -= 1
                refs[fresh] = 1
                table[p, ty, tx] = fresh
                sources[k] = t
                targets[k] = fresh
                k += 1
    # Fewer than counted when particles shared a tile: the last one to claim it keeps the original.
    return nfree, sources[:k], targets[:k]


@njit(cache=True, parallel=True)
def _fill_tiles(sources, targets, hits, visits, mean, state):
    """Tile targets[i] becomes a copy of sources[i] (an empty tile where the source is -1), the pool's arrays flat.
    No target is anyone's source: a target was free, a source is still held."""
    cells = TILE * TILE
    for i in prange(targets.shape[0]):
        t, fresh = sources[i], targets[i]
        to = fresh * cells
        if t < 0:
            for c in range(cells):
                hits[to + c] = 0
                visits[to + c] = 0
                mean[2 * (to + c)] = 0
                mean[2 * (to + c) + 1] = 0
                state[to + c] = UNKNOWN
        else:
            fr = t * cells
            for c in range(cells):
                hits[to + c] = hits[fr + c]
                visits[to + c] = visits[fr + c]
                mean[2 * (to + c)] = mean[2 * (fr + c)]
                mean[2 * (to + c) + 1] = mean[2 * (fr + c) + 1]
                state[to + c] = state[fr + c]


@njit(cache=True, inline="always")
def _touch(hits, visits, mean, state, q, last_hit, fx, fy):
    """One cell of a ray (flat index ``q`` into the pool): crossed, or (``last_hit``) the wall the ray ended in at
    (fx, fy), its place in the cell in cells (0..1 on each axis)."""
    if visits[q] == COUNT_MAX:
        # One byte a count: a cell crossed 255 times (a few minutes beside the robot's path) has both counts
        # halved, which keeps its occupancy; the mean endpoint then weighs the next hits a little more.
        visits[q] >>= 1
        hits[q] >>= 1
    visits[q] += 1
    if last_hit:
        m = hits[q] + 1
        hits[q] = m
        mx = mean[2 * q] + (min(max(fx, 0.0), 1.0) * MEAN_SCALE - mean[2 * q]) / m
        my = mean[2 * q + 1] + (min(max(fy, 0.0), 1.0) * MEAN_SCALE - mean[2 * q + 1]) / m
        mean[2 * q] = min(round(mx), 65535)
        mean[2 * q + 1] = min(round(my), 65535)
        state[q] = WALL if m > FULLNESS * visits[q] else SEEN
    else:
        s = state[q]
        if s == WALL:
            state[q] = WALL if hits[q] > FULLNESS * visits[q] else SEEN
        elif s == UNKNOWN:
            state[q] = SEEN  # a ray through a cell that was no wall leaves it none


@njit(cache=True, inline="always")
def _own_tile(table, marks, p, h, w, tx, ty):
    """The first flat index of tile (tx, ty) of particle p, if it is one p may write (-1: not marked, outside):
    outside its marked tiles only on a ray grazing a tile corner the tile walk rounded the other way."""
    if 0 <= tx < w and 0 <= ty < h and marks[p, ty, tx]:
        t = table[p, ty, tx]
        if t >= 0:
            return t << (2 * TILE_BITS)
    return -1


@njit(cache=True, parallel=True)
def _update_cells(table, marks, fh, fv, fm, fs, poses, lx, ly, ends, hit, res, ox, oy):
    """Every particle's rays into its own tiles (the pool's arrays flat). The cells are those
    ``traverse`` gives (the last one always the ray's end cell), walked here without a buffer, the tile looked up
    only when the walk leaves one: the map update is a fifth to a third of the filter's time (edmonton's 51 m beams
    cross ~1,000 cells each)."""
    n_particles = poses.shape[0]
    h, w = table.shape[1], table.shape[2]
    for p in prange(n_particles):
        sx, sy, world = _rays_in_world(poses[p], lx, ly, ends)
        for i in range(ends.shape[0]):
            x1, y1 = world[i, 0], world[i, 1]
            # the walk traverse makes
            ix, iy, ex, ey, step_x, step_y, t_max_x, t_delta_x, t_max_y, t_delta_y = _walk_start(sx, sy, x1, y1, res)
            limit = abs(ex - ix) + abs(ey - iy) + 1
            n = 1
            u = ix & TILE_MASK
            v = iy & TILE_MASK
            base = _own_tile(table, marks, p, h, w, (ix >> TILE_BITS) - ox, (iy >> TILE_BITS) - oy)
            while n < limit and (ix != ex or iy != ey):
                if base >= 0:
                    _touch(fh, fv, fm, fs, base + (v << TILE_BITS) + u, False, 0.0, 0.0)
                if t_max_x < t_max_y:
                    t_max_x += t_delta_x
                    ix += step_x
                    u += step_x
                    if u < 0 or u >= TILE:
                        u = ix & TILE_MASK
                        base = _own_tile(table, marks, p, h, w, (ix >> TILE_BITS) - ox, (iy >> TILE_BITS) - oy)
                else:
                    t_max_y += t_delta_y
                    iy += step_y
                    v += step_y
                    if v < 0 or v >= TILE:
                        v = iy & TILE_MASK
                        base = _own_tile(table, marks, p, h, w, (ix >> TILE_BITS) - ox, (iy >> TILE_BITS) - oy)
                n += 1
            # the walk's last cell is the end cell, whatever rounding left it at
            last = _own_tile(table, marks, p, h, w, (ex >> TILE_BITS) - ox, (ey >> TILE_BITS) - oy)
            if last >= 0:
                _touch(fh, fv, fm, fs, last + ((ey & TILE_MASK) << TILE_BITS) + (ex & TILE_MASK), hit[i],
                       x1 / res - ex, y1 / res - ey)
        for ty in range(h):
            for tx in range(w):
                marks[p, ty, tx] = 0


@njit(cache=True)
def _occupancy(own, hits, visits):
    th, tw = own.shape
    out = np.full((th * TILE, tw * TILE), np.nan, np.float32)
    for ty in range(th):
        for tx in range(tw):
            t = own[ty, tx]
            if t < 0:
                continue
            for v in range(TILE):
                for u in range(TILE):
                    n = visits[t, v, u]
                    if n > 0:
                        out[ty * TILE + v, tx * TILE + u] = hits[t, v, u] / n
    return out


@njit(cache=True)
def _entropy(own, hits, visits):
    total = 0.0
    known = 0
    for ty in range(own.shape[0]):
        for tx in range(own.shape[1]):
            t = own[ty, tx]
            if t < 0:
                continue
            for v in range(TILE):
                for u in range(TILE):
                    n = visits[t, v, u]
                    if n > 0:
                        q = hits[t, v, u] / n
                        known += 1
                        if 0.0 < q < 1.0:
                            total -= q * math.log2(q) + (1.0 - q) * math.log2(1.0 - q)
    return total / known if known > 0 else 0.0
