"""The map as one occupancy image, assembled from many submaps at their (optimized) poses.

Each output cell averages the log-odds of every submap that knows it. Averaging
rather than summing matters: every scan lives in two overlapping submaps, and a
sum would count it twice and let long stays at one place burn walls into free
space. Submaps may come in layers (a map of several sessions: one layer each, the
newest last); then a cell takes the newest layer that knows it with confidence,
and only a cell no layer is sure of averages them all (``mapping/lifelong.py``).
"""
from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from carto_cli.core import transform
from carto_cli.core.kernels import register_warm_up
from carto_cli.grid.probability_grid import VALUE_TO_PROBABILITY, ProbabilityGrid


@dataclass(frozen=True)
class OccupancyImage:
    """Occupancy probabilities on a regular grid.

    ``probability[iy, ix]`` covers the cell whose lower-left corner is
    ``origin + (ix, iy) * resolution`` (y grows with the row index, as in the world;
    images are flipped on output). NaN marks unknown cells.
    """

    probability: np.ndarray  # float32 (H, W)
    resolution: float
    origin: tuple[float, float]

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.probability.shape[0]), int(self.probability.shape[1]))

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) world points to (n, 2) float pixel coordinates of the output image (row 0 at the top)."""
        return _world_to_pixel(xy, self.origin, self.resolution, self.probability.shape[0])


def _logodds_table() -> np.ndarray:
    p = np.clip(VALUE_TO_PROBABILITY.astype(np.float64), 1e-6, 1 - 1e-6)
    table = np.log(p / (1.0 - p))
    table[0] = 0.0  # unknown: never read, the kernel skips value 0
    return table


_LOGODDS = _logodds_table()


def logodds(cells: np.ndarray) -> np.ndarray:
    """The log-odds of grid values ``cells`` (0, unknown, gives 0)."""
    return _LOGODDS[cells]


@njit(cache=True, nogil=True)
def _accumulate(total, count, gox, goy, res, cells, logodds, sox, soy, sres, c, s, tx, ty, x0, y0, x1, y1):
    """Pull every output cell in [x0, x1) × [y0, y1) from the submap by inverse transform (no holes under rotation)."""
    ny, nx = cells.shape
    for gy in range(y0, y1):
        wy = goy + (gy + 0.5) * res - ty
        for gx in range(x0, x1):
            wx = gox + (gx + 0.5) * res - tx
            # inverse rotation: submap-local coordinates of this output cell's centre
            lx = c * wx + s * wy
            ly = -s * wx + c * wy
            ix = int(math.floor((lx - sox) / sres))
            iy = int(math.floor((ly - soy) / sres))
            if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
                continue
            v = cells[iy, ix]
            if v == 0:
                continue
            total[gy, gx] += logodds[v]
            count[gy, gx] += 1


def _known_corners(grid: ProbabilityGrid) -> np.ndarray | None:
    b = grid.known_bounds
    if b is None:
        return None
    x0 = grid.origin[0] + b[0] * grid.resolution
    y0 = grid.origin[1] + b[1] * grid.resolution
    x1 = grid.origin[0] + (b[2] + 1) * grid.resolution
    y1 = grid.origin[1] + (b[3] + 1) * grid.resolution
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


def _known_outline(grid: ProbabilityGrid) -> np.ndarray | None:
    """The corners of every row's first and last known cell: placed at any rotation, their bounding box is that of
    the known cells (the box's four corners turned would enclose the empty corners of a turned submap too)."""
    b = grid.known_bounds
    if b is None:
        return None
    known = grid.cells[b[1]:b[3] + 1, b[0]:b[2] + 1] != 0
    rows = np.flatnonzero(known.any(axis=1))
    first = np.argmax(known[rows], axis=1)
    last = known.shape[1] - np.argmax(known[rows, ::-1], axis=1)  # one past the last known cell
    res = grid.resolution
    x0 = grid.origin[0] + (b[0] + first) * res
    x1 = grid.origin[0] + (b[0] + last) * res
    y0 = grid.origin[1] + (b[1] + rows) * res
    y1 = y0 + res
    return np.concatenate([np.column_stack([x, y]) for x in (x0, x1) for y in (y0, y1)])


def known_box(grid: ProbabilityGrid, correction: np.ndarray) -> np.ndarray | None:
    """The bounding box (xmin, ymin, xmax, ymax) of ``grid``'s known cells placed at ``correction``; None when it
    knows none."""
    corners = _known_corners(grid)
    if corners is None:
        return None
    placed = transform.apply(transform.as_pose(correction), corners)
    return np.concatenate([placed.min(axis=0), placed.max(axis=0)])


# Rows of the map assembled at a time: the accumulators (12 bytes a cell) exist for one strip only.
STRIP_ROWS = 256
# Maps up to this many cells are assembled whole when mapping ends (4 bytes a cell: 200 MB); larger ones are
# assembled strip by strip as they are written, so a campus-sized map never sits in memory at full resolution.
EAGER_CELLS = 50_000_000


class AssembledImage:
    """The occupancy image of submaps at their corrected poses, assembled on demand: ``probability`` (the whole
    float32 image, made once and kept), or ``rows()`` strip by strip from the top, which is how the PGM writer
    reads a large map. Interchangeable with :class:`OccupancyImage` for the readers of ``probability``,
    ``resolution``, ``origin``, ``shape`` and ``world_to_pixel``; a strip holds the same values as the rows of the
    whole image."""

    def __init__(self, grids: Sequence, corrections: Sequence, resolution: float | None = None,
                 margin_cells: int = 10, *, layers: Sequence[int] | None = None, sure: float = 0.0):
        """``layers``: one int per grid, higher newer; a cell takes the newest layer whose mean log-odds there is
        at least ``sure`` in magnitude, else the mean of all. None: every grid averaged alike."""
        self._parts = []
        self._margin = int(margin_cells)
        self._layered = layers is not None
        self._sure = float(sure)
        ranks = list(layers) if layers is not None else [0] * len(grids)
        for grid, corr, rank in zip(grids, corrections, ranks):
            outline = _known_outline(grid)
            if outline is not None:
                corr = transform.as_pose(corr)
                placed = transform.apply(corr, outline)
                box = np.array([placed.min(axis=0), placed.max(axis=0)])  # what the part covers, turned or not
                self._parts.append((grid, corr, box, int(rank)))
        self.resolution = float(resolution or (grids[0].resolution if len(grids) else 0.05))
        self._probability: np.ndarray | None = None
        if not self._parts:
            self.origin, self.shape = (0.0, 0.0), (0, 0)
            return
        res = self.resolution
        pts = np.concatenate([box for _, _, box, _ in self._parts])
        lo = np.floor(pts.min(axis=0) / res) * res - margin_cells * res
        hi = np.ceil(pts.max(axis=0) / res) * res + margin_cells * res
        self.origin = (float(lo[0]), float(lo[1]))
        self.shape = (int(round((hi[1] - lo[1]) / res)), int(round((hi[0] - lo[0]) / res)))

    @property
    def probability(self) -> np.ndarray:
        if self._probability is None:
            ny, nx = self.shape
            prob = np.empty((ny, nx), np.float32)
            for y0 in range(0, ny, STRIP_ROWS):
                prob[y0:y0 + STRIP_ROWS] = self._strip(y0, min(y0 + STRIP_ROWS, ny))
            self._probability = prob
        return self._probability

    def rows(self, strip: int = STRIP_ROWS) -> Iterator[np.ndarray]:
        """The image in strips of up to ``strip`` rows, top first and each with row 0 at the top (as written)."""
        ny = self.shape[0]
        for y1 in range(ny, 0, -strip):
            y0 = max(0, y1 - strip)
            rows = self._probability[y0:y1] if self._probability is not None else self._strip(y0, y1)
            yield rows[::-1]

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        return _world_to_pixel(xy, self.origin, self.resolution, self.shape[0])

    def moved(self, frame: np.ndarray) -> AssembledImage:
        """The same submaps, layers and margin with the map frame moved by ``frame`` (x, y, yaw: every correction
        composed after it): the image a map whose poses were all moved so would assemble, not a resampled one."""
        corrections = [transform.compose(frame, corr) for _, corr, _, _ in self._parts]
        return AssembledImage([grid for grid, _, _, _ in self._parts], corrections, self.resolution, self._margin,
                              layers=[rank for *_, rank in self._parts] if self._layered else None, sure=self._sure)

    def _strip(self, y0: int, y1: int) -> np.ndarray:
        """float32 probabilities of rows [y0, y1) (row 0 at the bottom), NaN where unknown."""
        res, nx = self.resolution, self.shape[1]
        gox, goy = self.origin[0], self.origin[1] + y0 * res
        total = np.zeros((y1 - y0, nx), np.float64)
        count = np.zeros((y1 - y0, nx), np.int32)
        lo = np.array([self.origin[0], goy])
        # Layer by layer, oldest first, so that a newer layer's sure cells overwrite an older one's
        chosen = np.full(total.shape, np.nan) if self._layered else None
        for rank in sorted({part[3] for part in self._parts}):
            part_total = np.zeros_like(total) if self._layered else total
            part_count = np.zeros_like(count) if self._layered else count
            for grid, corr, box, r in self._parts:
                if r != rank:
                    continue
                bmin = np.floor((box.min(axis=0) - lo) / res).astype(int)
                bmax = np.ceil((box.max(axis=0) - lo) / res).astype(int)
                x0, ya = max(bmin[0], 0), max(bmin[1], 0)
                x1, yb = min(bmax[0] + 1, nx), min(bmax[1] + 1, y1 - y0)
                if ya >= yb or x0 >= x1:
                    continue
                _accumulate(part_total, part_count, gox, goy, res, grid.cells, _LOGODDS, grid.origin[0],
                            grid.origin[1], grid.resolution, math.cos(corr[2]), math.sin(corr[2]), corr[0], corr[1],
                            x0, ya, x1, yb)
            if chosen is not None:
                total += part_total
                count += part_count
                mean = np.divide(part_total, part_count, out=np.zeros_like(part_total), where=part_count > 0)
                sure = (part_count > 0) & (np.abs(mean) >= self._sure)
                chosen[sure] = mean[sure]
        known = count > 0
        mean = np.divide(total, count, out=np.zeros_like(total), where=known)
        if chosen is not None:
            mean = np.where(np.isnan(chosen), mean, chosen)
        prob = np.full(total.shape, np.nan, np.float32)
        prob[known] = (1.0 / (1.0 + np.exp(-mean[known]))).astype(np.float32)
        return prob


def _world_to_pixel(xy: np.ndarray, origin: tuple[float, float], resolution: float, height: int) -> np.ndarray:
    px = (xy[:, 0] - origin[0]) / resolution
    py = height - (xy[:, 1] - origin[1]) / resolution
    return np.stack([px, py], axis=1)


def image_rows(image: OccupancyImage | AssembledImage, strip: int = STRIP_ROWS) -> Iterator[np.ndarray]:
    """Strips of ``image`` (an OccupancyImage or an AssembledImage), top first, row 0 at the top."""
    if isinstance(image, AssembledImage):
        yield from image.rows(strip)
        return
    p = image.probability
    for y1 in range(p.shape[0], 0, -strip):
        yield p[max(0, y1 - strip):y1][::-1]


def coarsened(image: OccupancyImage | AssembledImage, factor: int) -> OccupancyImage:
    """``image`` with ``factor`` x ``factor`` cells made one, built strip by strip: a block is unknown when all of
    its cells are, else it takes its most occupied known cell (walls stay walls when the map shrinks)."""
    factor = int(factor)
    if factor <= 1:
        return image if isinstance(image, OccupancyImage) else OccupancyImage(image.probability, image.resolution,
                                                                               image.origin)
    ny, nx = image.shape
    cy, cx = -(-ny // factor), -(-nx // factor)
    out = np.full((cy, cx), np.nan, np.float32)
    filled = 0  # coarse rows done, from the top
    top_pad = cy * factor - ny  # the coarse grid's top row may cover fewer fine rows: pad them unknown
    pending = np.full((top_pad, nx), np.nan, np.float32)
    for rows in image_rows(image, STRIP_ROWS):
        pending = np.concatenate([pending, rows])
        whole = pending.shape[0] // factor * factor
        if whole:
            block = pending[:whole]
            padded = np.full((whole, cx * factor), np.nan, np.float32)
            padded[:, :nx] = block
            # fmax ignores NaN (unknown) unless every cell of the block is
            blocks = padded.reshape(whole // factor, factor, cx, factor)
            reduced = np.fmax.reduce(np.fmax.reduce(blocks, axis=3), axis=1)
            out[filled:filled + whole // factor] = reduced
            filled += whole // factor
            pending = pending[whole:]
    # out is top-down here; OccupancyImage keeps row 0 at the bottom. The coarse grid keeps the lower-left corner.
    return OccupancyImage(np.ascontiguousarray(out[::-1]), image.resolution * factor, image.origin)


def assemble(grids: Sequence, corrections: Sequence, resolution: float | None = None,
             margin_cells: int = 10) -> OccupancyImage:
    """Merge grids; ``corrections[i]`` maps grid i's own frame into the map frame (x, y, theta)."""
    image = AssembledImage(grids, corrections, resolution, margin_cells)
    if 0 in image.shape:
        return OccupancyImage(np.zeros((0, 0), np.float32), resolution or 0.05, (0.0, 0.0))
    return OccupancyImage(image.probability, image.resolution, image.origin)


@register_warm_up
def warm_up() -> None:
    """Assembling the map image from a toy grid."""
    grid = ProbabilityGrid(0.05, (0.0, 0.0), (8, 8))
    grid.set_probability(np.array([[2, 3], [4, 4]]), 0.8)
    assemble([grid], [np.array([0.1, 0.0, 0.2])])
