"""Probability grid stored as Cartographer stores it: uint16 "correspondence cost" values.

Each cell holds 1 - p quantised to 1..32767 (0 = unknown). Probabilities are
clamped to [0.1, 0.9] so a cell never becomes certain and can always be
revised; the narrow integer encoding lets insertion be a pure table lookup
(see ``range_inserter``). Bit 15 (``UPDATE_MARKER``) is reserved for the
inserter and is never set between insertions.

Cell (ix, iy) covers [origin + (ix, iy) * resolution, origin + (ix + 1, iy + 1) * resolution);
arrays are indexed ``cells[iy, ix]`` so row 0 is the lowest y.
"""
from __future__ import annotations

import threading
import weakref
import zlib
from collections import OrderedDict
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import ArrayLike

MIN_PROBABILITY = 0.1
MAX_PROBABILITY = 0.9
MIN_CORRESPONDENCE_COST = 1.0 - MAX_PROBABILITY
MAX_CORRESPONDENCE_COST = 1.0 - MIN_PROBABILITY
UNKNOWN_VALUE = 0
MAX_VALUE = 32767
UPDATE_MARKER = 1 << 15
_SCALE = (MAX_CORRESPONDENCE_COST - MIN_CORRESPONDENCE_COST) / (MAX_VALUE - 1)


def correspondence_cost_to_value(cost: ArrayLike) -> np.ndarray:
    """Clamp to [0.1, 0.9] and quantise to 1..32767 (rounding half away from zero, like lround)."""
    c = np.clip(np.asarray(cost, dtype=np.float64), MIN_CORRESPONDENCE_COST, MAX_CORRESPONDENCE_COST)
    return (np.floor((c - MIN_CORRESPONDENCE_COST) / _SCALE + 0.5) + 1).astype(np.uint16)


def probability_to_value(p: ArrayLike) -> np.ndarray:
    return correspondence_cost_to_value(1.0 - np.asarray(p, dtype=np.float64))


def _value_to_cost_table() -> np.ndarray:
    table = MIN_CORRESPONDENCE_COST + (np.arange(MAX_VALUE + 1, dtype=np.float64) - 1) * _SCALE
    # Unknown reads as the worst correspondence: matchers see unknown space as free-ish, never as a wall.
    table[UNKNOWN_VALUE] = MAX_CORRESPONDENCE_COST
    table.flags.writeable = False
    return table


VALUE_TO_CORRESPONDENCE_COST = _value_to_cost_table()
VALUE_TO_PROBABILITY = 1.0 - VALUE_TO_CORRESPONDENCE_COST
VALUE_TO_PROBABILITY.flags.writeable = False


# Packed grids (finished submaps) are unpacked on access and the unpacked cells kept, least recently used
# dropped first, up to this many bytes in all: the submaps searched around the robot stay unpacked. 16 MB (8 of
# dense aces's submaps): 64 MB held dense aces / intel at 456 / 455 MB peak RSS, 16 MB at 421 / 434, CPU within
# the noise (10.0-10.1 s against 10.1-10.5 s, 20.2-21.1 s against 18.5-21.4 s, runs interleaved), the same maps.
UNPACKED_BUDGET = 16 * 2**20


class UnpackedCells:
    """The LRU of unpacked cells of packed grids, shared by every grid and thread."""

    def __init__(self, budget: int):
        self.budget = int(budget)
        self.bytes = 0
        # Reentrant: a grid collected while the lock is held runs _forget in the same thread.
        self._lock = threading.RLock()
        self._grids: OrderedDict[int, tuple[weakref.ref, int]] = OrderedDict()  # id -> (grid, unpacked bytes)

    def get(self, grid: ProbabilityGrid) -> np.ndarray:
        with self._lock:
            cells = grid._unpacked
            if cells is not None:
                self._grids.move_to_end(id(grid))
                return cells
        assert grid._packed is not None
        packed, shape = grid._packed
        # A writable array (bytearray): numba compiles read-only arrays as another type.
        cells = np.frombuffer(bytearray(zlib.decompress(packed)), dtype=np.uint16).reshape(shape)
        with self._lock:
            if grid._unpacked is not None:  # another thread unpacked it meanwhile: one copy is kept
                return grid._unpacked
            grid._unpacked = cells
            key = id(grid)
            self._grids[key] = (weakref.ref(grid, self._forgetter(key)), cells.nbytes)
            self.bytes += cells.nbytes
            while self.bytes > self.budget and len(self._grids) > 1:
                _, (ref, nbytes) = self._grids.popitem(last=False)
                self.bytes -= nbytes
                dropped = ref()
                if dropped is not None:
                    dropped._unpacked = None  # a kernel still holding the array keeps it alive until done
        return cells

    def _forgetter(self, key: int) -> Callable[[weakref.ref], None]:
        def forget(_ref: weakref.ref) -> None:
            self._forget(key)
        return forget

    def _forget(self, key: int) -> None:
        """A grid was collected (its weakref's callback): its unpacked cells went with it."""
        with self._lock:
            entry = self._grids.pop(key, None)
            if entry is not None:
                self.bytes -= entry[1]


UNPACKED_CELLS = UnpackedCells(UNPACKED_BUDGET)


class ProbabilityGrid:
    """A growable occupancy grid of one submap (or of a whole map)."""

    _cells: np.ndarray | None = None
    _packed: tuple[bytes, tuple[int, int]] | None = None
    _unpacked: np.ndarray | None = None

    @property
    def cells(self) -> np.ndarray:
        """(ny, nx) uint16 values (unpacked on access if the grid is packed)."""
        cells = self._cells
        return cells if cells is not None else UNPACKED_CELLS.get(self)

    @cells.setter
    def cells(self, value: np.ndarray) -> None:
        self._cells = value
        self._packed = self._unpacked = None

    def __getstate__(self) -> dict:
        # The unpacked cells of a packed grid are a cache: a copy sent to another process unpacks its own.
        state = self.__dict__.copy()
        state.pop("_unpacked", None)
        return state

    def pack(self) -> None:
        """Keep the cells zlib-compressed from now on (a finished submap, mostly unknown cells: several times
        smaller); reads unpack them through a shared LRU. The grid must not be written after this."""
        cells = self.cells
        self._packed = (zlib.compress(np.ascontiguousarray(cells).tobytes(), 1), (int(cells.shape[0]),
                                                                                  int(cells.shape[1])))
        self._cells = None

    @property
    def is_packed(self) -> bool:
        return self._packed is not None

    def __init__(self, resolution: float = 0.05, origin: ArrayLike = (0.0, 0.0),
                 num_cells: Sequence[int] = (100, 100)) -> None:
        nx, ny = int(num_cells[0]), int(num_cells[1])
        if resolution <= 0 or nx <= 0 or ny <= 0:
            raise ValueError("resolution and cell counts must be positive")
        self.resolution = float(resolution)
        self.origin = np.array(origin, dtype=np.float64).reshape(2)
        self.cells = np.zeros((ny, nx), dtype=np.uint16)
        # (min_ix, min_iy, max_ix, max_iy) of cells ever updated; min > max while empty.
        self.known_box = np.array([nx, ny, -1, -1], dtype=np.int64)
        # Bumped on every change so callers can cache derived data (e.g. precomputation grids).
        self.version = 0

    @classmethod
    def centered(cls, center: ArrayLike, resolution: float = 0.05, num_cells: int = 100) -> ProbabilityGrid:
        """A ``num_cells`` square grid centred on ``center`` (Cartographer's initial submap size)."""
        center = np.asarray(center, dtype=np.float64)[:2]
        return cls(resolution, center - 0.5 * num_cells * resolution, (num_cells, num_cells))

    # --- geometry -------------------------------------------------------------------------

    @property
    def num_cells(self) -> tuple[int, int]:
        """(nx, ny)."""
        return int(self.cells.shape[1]), int(self.cells.shape[0])

    @property
    def max_corner(self) -> np.ndarray:
        return self.origin + self.resolution * np.array(self.num_cells, dtype=np.float64)

    def cell_index(self, points: ArrayLike) -> np.ndarray:
        """(n, 2) int64 (ix, iy) of the cells containing world points."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return np.floor((p - self.origin) / self.resolution).astype(np.int64)

    def cell_center(self, cells: ArrayLike) -> np.ndarray:
        c = np.asarray(cells, dtype=np.float64).reshape(-1, 2)
        return self.origin + (c + 0.5) * self.resolution

    def contains(self, cells: ArrayLike) -> np.ndarray:
        c = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        nx, ny = self.num_cells
        return (c[:, 0] >= 0) & (c[:, 0] < nx) & (c[:, 1] >= 0) & (c[:, 1] < ny)

    @property
    def known_bounds(self):
        """(min_ix, min_iy, max_ix, max_iy) inclusive, or None when nothing is known."""
        b = self.known_box
        if b[0] > b[2] or b[1] > b[3]:
            return None
        return tuple(int(v) for v in b)

    def grow_to_include(self, points: ArrayLike, margin: int = 4) -> bool:
        """Re-allocate so every point lies inside; returns whether the grid grew.

        A side that must grow grows by at least the current size along that
        axis, so a robot driving off the edge costs O(log) re-allocations and
        the copies amortise to O(1) per cell.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        if p.shape[0] == 0:
            return False
        idx = self.cell_index(np.array([p.min(axis=0), p.max(axis=0)]))
        nx, ny = self.num_cells
        lo = np.minimum(idx[0], 0)
        hi = np.maximum(idx[1] - np.array([nx - 1, ny - 1]), 0)
        if not (lo.any() or hi.any()):
            return False
        size = np.array([nx, ny])
        pad_lo = np.where(lo < 0, np.maximum(-lo + margin, size), 0)
        pad_hi = np.where(hi > 0, np.maximum(hi + margin, size), 0)
        new_nx, new_ny = (size + pad_lo + pad_hi).tolist()
        cells = np.zeros((new_ny, new_nx), dtype=np.uint16)
        cells[pad_lo[1]:pad_lo[1] + ny, pad_lo[0]:pad_lo[0] + nx] = self.cells
        self.cells = cells
        self.origin = self.origin - pad_lo * self.resolution
        if self.known_bounds is None:
            self.known_box = np.array([new_nx, new_ny, -1, -1], dtype=np.int64)
        else:
            self.known_box = self.known_box + np.concatenate([pad_lo, pad_lo])
        self.version += 1
        return True

    # --- values ---------------------------------------------------------------------------

    def _values(self, cells: ArrayLike) -> np.ndarray:
        c = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        inside = self.contains(c)
        values = np.zeros(c.shape[0], dtype=np.uint16)
        values[inside] = self.cells[c[inside, 1], c[inside, 0]]
        return values

    def is_known(self, cells: ArrayLike) -> np.ndarray:
        return self._values(cells) != UNKNOWN_VALUE

    def probability(self, cells: ArrayLike, unknown: float = np.nan) -> np.ndarray:
        """p per cell; ``unknown`` for cells never observed or outside the grid.

        (Cartographer's GetProbability returns 0.1 there: pass ``unknown=0.1``.)
        """
        v = self._values(cells)
        return np.where(v == UNKNOWN_VALUE, unknown, VALUE_TO_PROBABILITY[v])

    def set_probability(self, cells: ArrayLike, probability: ArrayLike) -> None:
        """Overwrite cells (growing as needed), e.g. to build a known map in a test."""
        c = np.asarray(cells, dtype=np.int64).reshape(-1, 2)
        if c.shape[0] == 0:
            return
        if not self.contains(c).all():
            self.grow_to_include(self.cell_center(c))
            c = self.cell_index(self.cell_center(c))  # indices shift with the origin
        self.cells[c[:, 1], c[:, 0]] = probability_to_value(np.broadcast_to(probability, c.shape[0]))
        self.known_box[:2] = np.minimum(self.known_box[:2], c.min(axis=0))
        self.known_box[2:] = np.maximum(self.known_box[2:], c.max(axis=0))
        self.version += 1

    def copy(self) -> ProbabilityGrid:
        g = ProbabilityGrid.__new__(ProbabilityGrid)
        g.resolution = self.resolution
        g.origin = self.origin.copy()
        g.cells = self.cells.copy()
        g.known_box = self.known_box.copy()
        g.version = self.version
        return g

    def cropped(self) -> ProbabilityGrid:
        """A copy reduced to the known cells (what a finished submap keeps)."""
        b = self.known_bounds
        if b is None:
            return ProbabilityGrid(self.resolution, self.origin, (1, 1))
        x0, y0, x1, y1 = b
        g = ProbabilityGrid.__new__(ProbabilityGrid)
        g.resolution = self.resolution
        g.origin = self.origin + np.array([x0, y0], dtype=np.float64) * self.resolution
        g.cells = self.cells[y0:y1 + 1, x0:x1 + 1].copy()
        g.known_box = np.array([0, 0, x1 - x0, y1 - y0], dtype=np.int64)
        g.version = self.version + 1
        return g
