"""Clean a finished map of what was only there for a while: people, carts, a door that was open.

An online mapper decides about a cell as scans come; a batch one can ask, once the final optimization has placed
every node, what the whole recording saw there and when. For every occupied cell of the finished image, in
``BINS`` bins of the recording's time:

* its **hits**: the returns that ended in it, and where in the cell they ended on average (what stood there);
* its **pass-throughs**: rays that crossed the cell within ``PASS_RADIUS`` of that point and went on at least
  ``MARGIN`` further (a ray that stops just behind a cell was stopped by what is in it, to within a pose's
  error). A ray beside the point only skirted a chair's leg filling a corner of the cell; a ray that meets a
  straight piece of wall at less than ``GRAZING`` skims it, as every map's rays skim the edge of its walls'
  bands, and neither counts.

Whatever stood in a cell **left** at a bin boundary before which it was hit, after which it was seen through at
least ``MIN_AFTER`` times and ``AFTER_RATIO`` times as often as hit (people walking through the place a cart
stood still hit it now and then), and while it was hit it was not seen through more than ``POROUS`` times per hit
(something that let rays through while there was never solid: legs, a railing). Such a cell is **transient**
unless one of its 8 neighbours is occupied and stays: the edge of a wall band seen through by a later pass a cell
off belongs to the wall. A transient cell is drawn free; the result keeps it with its time span and evidence, so
that the state (map.carto) says what was removed. A wall seen from one side only is never crossed; a cabinet put
down for good and seen to the end is never seen through after it came; both stay.

The evidence is every node's inserted returns (``compact_returns``, kept by the mapping system) or, for a node
without (a saved map's), its loop-closure points, at its optimized pose with its rays from the laser's mount.
``bench/clean.py`` measures it (docs/benchmarks.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from scipy import ndimage

from carto_cli.core.kernels import register_warm_up
from carto_cli.grid.occupancy_image import AssembledImage, OccupancyImage

__all__ = ["AFTER_RATIO", "GRAZING", "MARGIN", "MIN_AFTER", "PASS_RADIUS", "POROUS", "Evidence", "Transients",
           "cleaned_image", "cleaned_probability", "compact_returns", "find_transients", "flat_points",
           "gather_evidence"]

PASS_RADIUS = 0.015  # m: a ray passes through what a cell held if it comes this near where its returns ended
MARGIN = 0.25  # m: a ray crosses a cell only if it ends at least this far beyond it
GRAZING = math.radians(30.0)  # a ray meeting a straight wall at less than this does not count as crossing it
COHERENT = 0.5  # structure-tensor coherence above which a cell's structure counts as a straight wall
MIN_AFTER = 10  # rays through a cell after some time, at least, for what stood there to have gone
AFTER_RATIO = 3.0  # ... and this many times as many as still hit it after that time (people walking through)
POROUS = 1.0  # ... and before that time seen through while hit no more than this many times per hit
BINS = 64  # the recording's time in this many bins, where a departure is looked for, ...
EVIDENCE_BYTES = 64 << 20  # ... fewer when the counts of that many would take more (a campus: a million cells)
OCCUPIED = 0.5  # a cell is occupied above this probability (map.pgm's balance of evidence)
FREE = 0.3  # what a removed cell is drawn as: free by the same balance


@dataclass(frozen=True)
class Transients:
    """Cells of a finished map's image found transient: (ix, iy) on the image grid (``origin``, ``resolution``;
    iy grows with y), each with its time span (its first hit, and the time it left, to a bin), the returns that
    hit it before and the rays through it after."""

    resolution: float
    origin: tuple[float, float]
    cells: np.ndarray  # (n, 2) int64 ix iy
    spans: np.ndarray  # (n, 2) float64: first hit, and the time it left
    hits: np.ndarray  # (n,) int64
    after: np.ndarray  # (n,) int64
    candidates: int = 0  # occupied cells judged

    def __len__(self) -> int:
        return len(self.cells)

    def centres(self) -> np.ndarray:
        """(n, 2) the cells' centres in the map frame."""
        return (np.asarray(self.origin) + (self.cells + 0.5) * self.resolution).reshape(-1, 2)

    def cells_on(self, origin: tuple[float, float], resolution: float, shape: tuple[int, int]) -> np.ndarray:
        """(k, 2) ix iy of the cells of another grid (``origin``, ``resolution``, ``shape`` (H, W)) holding a
        transient cell's centre: the same cells on the grid they were found on."""
        at = np.floor((self.centres() - np.asarray(origin, np.float64)) / float(resolution)).astype(np.int64)
        inside = (at[:, 0] >= 0) & (at[:, 1] >= 0) & (at[:, 0] < shape[1]) & (at[:, 1] < shape[0])
        return at[inside]

    @classmethod
    def of_centres(cls, resolution: float, centres: np.ndarray, spans: np.ndarray, hits: np.ndarray,
                   after: np.ndarray, candidates: int = 0) -> Transients:
        """As saved (the cells' centres in the map frame), on a grid of ``resolution`` through (0, 0)."""
        cells = np.floor(np.asarray(centres, np.float64).reshape(-1, 2) / resolution).astype(np.int64)
        return cls(float(resolution), (0.0, 0.0), cells, np.asarray(spans, np.float64).reshape(-1, 2),
                   np.asarray(hits, np.int64).reshape(-1), np.asarray(after, np.int64).reshape(-1), candidates)

    @classmethod
    def none(cls, resolution: float = 0.05, origin: tuple[float, float] = (0.0, 0.0), candidates: int = 0
             ) -> Transients:
        return cls(resolution, origin, np.zeros((0, 2), np.int64), np.zeros((0, 2)), np.zeros(0, np.int64),
                   np.zeros(0, np.int64), candidates)


@njit(cache=True, nogil=True)
def _bin(t, t0, width, bins):
    return min(max(int((t - t0) / width), 0), bins - 1)


@njit(cache=True, nogil=True)
def _hits(points, offsets, poses, times, index, gox, goy, res, t0, width, hits, first, centre):
    """Per occupied cell and time bin: the returns that ended in it; the first one's time, and the sum of where
    they ended (``centre``: x, y, count), whose mean is where in the cell the thing they hit stood."""
    ny, nx = index.shape
    bins = hits.shape[1]
    for i in range(offsets.shape[0] - 1):
        c, s = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        b = _bin(times[i], t0, width, bins)
        for k in range(offsets[i], offsets[i + 1]):
            x = c * points[k, 0] - s * points[k, 1] + poses[i, 0]
            y = s * points[k, 0] + c * points[k, 1] + poses[i, 1]
            ix = int(math.floor((x - gox) / res))
            iy = int(math.floor((y - goy) / res))
            if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
                continue
            j = index[iy, ix]
            if j < 0:
                continue
            if hits[j, b] < 65535:
                hits[j, b] += 1
            first[j] = min(first[j], times[i])
            centre[j, 0] += x
            centre[j, 1] += y
            centre[j, 2] += 1.0


@njit(cache=True, nogil=True)
def _crossings(points, offsets, poses, sensor, times, index, tangent, coherent, centre, gox, goy, res, margin,
               radius, grazing_cos, t0, width, passes):
    """Walk every ray from the sensor to ``margin`` short of its return, cell by cell (Amanatides and Woo), and
    count per occupied cell and time bin the rays that pass within ``radius`` of where its returns ended: through
    what was hit there, not beside a table leg that fills a corner of the cell."""
    ny, nx = index.shape
    bins = passes.shape[1]
    for i in range(offsets.shape[0] - 1):
        c, s = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        ox = c * sensor[0] - s * sensor[1] + poses[i, 0]
        oy = s * sensor[0] + c * sensor[1] + poses[i, 1]
        b = _bin(times[i], t0, width, bins)
        for k in range(offsets[i], offsets[i + 1]):
            ex = c * points[k, 0] - s * points[k, 1] + poses[i, 0]
            ey = s * points[k, 0] + c * points[k, 1] + poses[i, 1]
            dx, dy = ex - ox, ey - oy
            length = math.sqrt(dx * dx + dy * dy)
            if length <= margin:
                continue
            ux, uy = dx / length, dy / length
            reach = (length - margin) / res
            px, py = (ox - gox) / res, (oy - goy) / res
            cx, cy = int(math.floor(px)), int(math.floor(py))
            sx = 1 if ux > 0 else -1
            sy = 1 if uy > 0 else -1
            tdx = abs(1.0 / ux) if ux != 0 else np.inf
            tdy = abs(1.0 / uy) if uy != 0 else np.inf
            tx = ((cx + (1 if ux > 0 else 0)) - px) / ux if ux != 0 else np.inf
            ty = ((cy + (1 if uy > 0 else 0)) - py) / uy if uy != 0 else np.inf
            walked = 0.0
            while walked < reach:
                if 0 <= cx < nx and 0 <= cy < ny:
                    j = index[cy, cx]
                    if j >= 0 and centre[j, 2] > 0 and not (
                            coherent[j] and abs(ux * tangent[j, 0] + uy * tangent[j, 1]) > grazing_cos):
                        mx = centre[j, 0] / centre[j, 2] - ox
                        my = centre[j, 1] / centre[j, 2] - oy
                        if abs(ux * my - uy * mx) <= radius and passes[j, b] < 65535:
                            passes[j, b] += 1
                if tx < ty:
                    walked = tx
                    tx += tdx
                    cx += sx
                else:
                    walked = ty
                    ty += tdy
                    cy += sy


def _structure(occupied: np.ndarray, cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per cell of ``cells`` (n, 2 ix iy): the unit direction along its structure, and whether that structure is
    straight (the occupied mask's structure tensor over 5 x 5 cells: coherent where one direction dominates)."""
    mask = ndimage.gaussian_filter(occupied.astype(np.float32), 1.0)
    gy, gx = np.gradient(mask)
    jxx = ndimage.uniform_filter(gx * gx, 5)[cells[:, 1], cells[:, 0]]
    jxy = ndimage.uniform_filter(gx * gy, 5)[cells[:, 1], cells[:, 0]]
    jyy = ndimage.uniform_filter(gy * gy, 5)[cells[:, 1], cells[:, 0]]
    trace = jxx + jyy
    coherence = np.sqrt((jxx - jyy) ** 2 + 4 * jxy ** 2) / np.maximum(trace, 1e-12)
    normal = 0.5 * np.arctan2(2 * jxy, jxx - jyy)  # the gradient's direction: across the wall
    tangent = np.column_stack([-np.sin(normal), np.cos(normal)]).astype(np.float64)
    return tangent, (coherence > COHERENT) & (trace > 1e-9)


RETURN_UNIT = 0.01  # m: returns kept for cleaning as int16 multiples of this (up to 327 m), 4 bytes a point


def compact_returns(returns: np.ndarray, pose: np.ndarray | None = None) -> np.ndarray:
    """``returns`` (n, 2) in a frame where the node is at ``pose`` (None: in the node's frame), as int16 cm in
    the node's frame: what cleaning keeps of every node while mapping."""
    pts = np.asarray(returns, np.float64).reshape(-1, 2)
    if pose is not None:
        c, s = math.cos(pose[2]), math.sin(pose[2])
        d = pts - np.asarray(pose[:2], np.float64)
        pts = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]])
    limit = np.iinfo(np.int16).max
    return np.clip(np.rint(pts / RETURN_UNIT), -limit, limit).astype(np.int16)


def flat_points(points: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The nodes' points as one (P, 2) float64 array in metres (int16 ones are ``compact_returns``') and P + 1
    offsets."""
    counts = np.array([len(p) for p in points], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    metres = [np.asarray(p, np.float64).reshape(-1, 2) * (RETURN_UNIT if np.asarray(p).dtype == np.int16 else 1.0)
              for p in points]
    flat = np.concatenate(metres) if points else np.zeros((0, 2))
    return np.ascontiguousarray(flat), offsets


@dataclass(frozen=True)
class Evidence:
    """What the recording saw of every occupied cell of an image: ``cells`` (n, 2) ix iy; per cell and time bin
    (up to ``BINS`` bins of ``width`` s from ``t0``) the returns that ended in it (``hits``) and the rays through it
    near where they ended (``passes``); each cell's first hit time and ``centre`` (sum of x, sum of y, count of its
    returns)."""

    cells: np.ndarray
    hits: np.ndarray  # (n, bins) uint16
    passes: np.ndarray  # (n, bins) uint16
    first: np.ndarray  # (n,)
    centre: np.ndarray  # (n, 3)
    t0: float
    width: float


def gather_evidence(probability: np.ndarray, origin: tuple[float, float], resolution: float,
                    points: list[np.ndarray], poses: np.ndarray, times: np.ndarray,
                    sensor: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0), *,
                    grazing: float = GRAZING) -> Evidence:
    """The evidence on every occupied cell of ``probability`` (H, W; row 0 at the lowest y, NaN unknown) from
    every node's returns ``points[i]`` (its own frame; int16 ones are ``compact_returns``') at ``poses[i]`` (map
    frame), taken at ``times[i]``, the laser at ``sensor`` in the node's frame. ``grazing``: rays meeting a
    straight wall at less than this angle are not counted as crossing it (0: every ray counts)."""
    prob = np.asarray(probability)
    occupied = np.nan_to_num(prob, nan=0.0) > OCCUPIED
    iy, ix = np.nonzero(occupied)
    n = len(ix)
    cells = np.column_stack([ix, iy]).astype(np.int64)
    times = np.ascontiguousarray(times, np.float64).reshape(-1)
    bins = int(np.clip(EVIDENCE_BYTES // max(4 * n, 1), 8, BINS))
    t0 = float(times.min()) if len(times) else 0.0
    width = max((float(times.max()) - t0) / bins, 1e-3) if len(times) else 1.0
    evidence = Evidence(cells, np.zeros((n, bins), np.uint16), np.zeros((n, bins), np.uint16), np.full(n, np.inf),
                        np.zeros((n, 3)), t0, width)
    if n == 0 or len(points) == 0:
        return evidence
    index = np.full(prob.shape, -1, np.int32)
    index[iy, ix] = np.arange(n, dtype=np.int32)
    flat, offsets = flat_points(points)
    poses = np.ascontiguousarray(poses, np.float64).reshape(-1, 3)
    gox, goy, res = float(origin[0]), float(origin[1]), float(resolution)
    _hits(flat, offsets, poses, times, index, gox, goy, res, t0, width, evidence.hits, evidence.first,
          evidence.centre)
    tangent, coherent = _structure(occupied, cells)
    _crossings(flat, offsets, poses, np.asarray(sensor, np.float64), times, index, tangent, coherent, evidence.centre,
               gox, goy, res, MARGIN, PASS_RADIUS, math.cos(grazing), t0, width, evidence.passes)
    return evidence


def find_transients(probability: np.ndarray, origin: tuple[float, float], resolution: float,
                    points: list[np.ndarray], poses: np.ndarray, times: np.ndarray,
                    sensor: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Transients:
    """The transient cells of a finished image, judged by the evidence of :func:`gather_evidence` (the same
    arguments)."""
    e = gather_evidence(probability, origin, resolution, points, poses, times, sensor)
    if len(e.cells) == 0:
        return Transients.none(resolution, origin, 0)
    gone, left, hits_before, passes_after = _departures(e.hits, e.passes)
    gone &= ~_beside(e.cells, gone, np.shape(probability))
    spans = np.column_stack([e.first[gone], e.t0 + left[gone] * e.width])
    return Transients(float(resolution), (float(origin[0]), float(origin[1])), e.cells[gone], spans,
                      hits_before[gone], passes_after[gone], len(e.cells))


def _beside(cells: np.ndarray, gone: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Per cell: whether an occupied cell that stays is among its 8 neighbours. The edge of a wall band, seen
    through by a later pass whose pose differs by a cell, belongs to the wall; whatever stood free of the walls,
    or reached them by one cell, goes all but that cell."""
    stays = np.zeros(shape, bool)
    stays[cells[~gone, 1], cells[~gone, 0]] = True
    near = ndimage.binary_dilation(stays, structure=np.ones((3, 3), bool))
    return near[cells[:, 1], cells[:, 0]]


DEPARTURE_ROWS = 1 << 16  # cells judged at a time: the running sums (int32, a few per bin) for these only


def _departures(hits: np.ndarray, passes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per cell (rows of per-bin counts): whether something there left (a bin boundary before which it was hit
    and after which it was seen through ``MIN_AFTER`` times, ``AFTER_RATIO`` times as often as hit, and not
    porous before); the first such boundary with the most hits before it (in bins), those hits and the pass-throughs
    after it."""
    parts = [_departures_of(hits[a:a + DEPARTURE_ROWS], passes[a:a + DEPARTURE_ROWS])
             for a in range(0, len(hits), DEPARTURE_ROWS)]
    if not parts:
        return np.zeros(0, bool), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64)
    gone, k, h, p = (np.concatenate(x) for x in zip(*parts))
    return gone, k, h, p


def _departures_of(hits: np.ndarray, passes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    h_after = np.cumsum(hits[:, ::-1], axis=1, dtype=np.int32)[:, ::-1]  # [:, k]: hits in bins k and later
    p_after = np.cumsum(passes[:, ::-1], axis=1, dtype=np.int32)[:, ::-1]
    h_before = h_after[:, :1] - h_after
    # Seen through while it was being hit: a chair's leg filling a corner of the cell, not something that left
    through = np.cumsum(np.where(hits > 0, passes, 0), axis=1, dtype=np.int32)
    through = np.concatenate([np.zeros((len(hits), 1), np.int32), through], axis=1)[:, :-1]  # [:, k]: bins < k
    left = ((h_before[:, 1:] > 0) & (p_after[:, 1:] >= MIN_AFTER) & (p_after[:, 1:] >= AFTER_RATIO * h_after[:, 1:])
            & (through[:, 1:] <= POROUS * h_before[:, 1:]))
    gone = np.asarray(left.any(axis=1))
    # The boundary with the most hits before it, the first of them: right after what left was last hit
    k = np.argmax(np.where(left, h_before[:, 1:], -1), axis=1) + 1
    rows = np.arange(len(k))
    return gone, k.astype(np.int64), h_before[rows, k].astype(np.int64), p_after[rows, k].astype(np.int64)


def cleaned_image(image: OccupancyImage | AssembledImage, transients: Transients) -> OccupancyImage:
    """``image`` (held whole) with the transient cells drawn free."""
    return OccupancyImage(cleaned_probability(image.probability, image.origin, image.resolution, transients),
                          image.resolution, image.origin)


def cleaned_probability(probability: np.ndarray, origin: tuple[float, float], resolution: float,
                        transients: Transients) -> np.ndarray:
    """A copy of ``probability`` (a grid at ``origin``, ``resolution``) with the transient cells drawn free (no
    more than ``FREE``)."""
    out = np.array(probability, dtype=np.float32, copy=True)
    cells = transients.cells_on(origin, resolution, out.shape)
    if len(cells):
        ix, iy = cells[:, 0], cells[:, 1]
        out[iy, ix] = np.fmin(out[iy, ix], np.float32(FREE))
    return out


@register_warm_up
def warm_up() -> None:
    prob = np.full((12, 12), 0.2, np.float32)
    prob[6, 6] = 0.9
    find_transients(prob, (0.0, 0.0), 0.05, [np.array([[0.33, 0.33]]), np.array([[0.5, 0.5]])],
                    np.zeros((2, 3)), np.array([0.0, 1.0]))

