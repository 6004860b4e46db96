"""The map as one occupancy image, assembled from many submaps at their (optimized) poses.

Each output cell averages the log-odds of every submap that knows it. Averaging
rather than summing matters: every scan lives in two overlapping submaps, and a
sum would count it twice and let long stays at one place burn walls into free
space.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from carto_cli.core import transform
from carto_cli.core.kernels import register_warm_up
from carto_cli.grid.probability_grid import VALUE_TO_PROBABILITY


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

    def world_to_pixel(self, xy: np.ndarray) -> np.ndarray:
        """(n, 2) world points to (n, 2) float pixel coordinates of the output image (row 0 at the top)."""
        h = self.probability.shape[0]
        px = (xy[:, 0] - self.origin[0]) / self.resolution
        py = h - (xy[:, 1] - self.origin[1]) / self.resolution
        return np.stack([px, py], axis=1)


def _logodds_table() -> np.ndarray:
    p = np.clip(VALUE_TO_PROBABILITY.astype(np.float64), 1e-6, 1 - 1e-6)
    table = np.log(p / (1.0 - p))
    table[0] = 0.0  # unknown: never read, the kernel skips value 0
    return table


_LOGODDS = _logodds_table()


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


def _known_corners(grid) -> np.ndarray | None:
    b = grid.known_bounds
    if b is None:
        return None
    x0 = grid.origin[0] + b[0] * grid.resolution
    y0 = grid.origin[1] + b[1] * grid.resolution
    x1 = grid.origin[0] + (b[2] + 1) * grid.resolution
    y1 = grid.origin[1] + (b[3] + 1) * grid.resolution
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])


def assemble(grids: Sequence, corrections: Sequence, resolution: float | None = None,
             margin_cells: int = 10) -> OccupancyImage:
    """Merge grids; ``corrections[i]`` maps grid i's own frame into the map frame (x, y, theta)."""
    boxes = []
    for grid, corr in zip(grids, corrections):
        corners = _known_corners(grid)
        if corners is None:
            continue
        boxes.append(transform.apply(transform.as_pose(corr), corners))
    if not boxes:
        return OccupancyImage(np.zeros((0, 0), np.float32), resolution or 0.05, (0.0, 0.0))
    res = float(resolution or grids[0].resolution)
    pts = np.concatenate(boxes)
    lo = np.floor(pts.min(axis=0) / res) * res - margin_cells * res
    hi = np.ceil(pts.max(axis=0) / res) * res + margin_cells * res
    nx = int(round((hi[0] - lo[0]) / res))
    ny = int(round((hi[1] - lo[1]) / res))
    total = np.zeros((ny, nx), np.float64)
    count = np.zeros((ny, nx), np.int32)
    for grid, corr, box in zip(grids, corrections, boxes):
        corr = transform.as_pose(corr)
        bmin = np.floor((box.min(axis=0) - lo) / res).astype(int)
        bmax = np.ceil((box.max(axis=0) - lo) / res).astype(int)
        x0, y0 = max(bmin[0], 0), max(bmin[1], 0)
        x1, y1 = min(bmax[0] + 1, nx), min(bmax[1] + 1, ny)
        _accumulate(total, count, lo[0], lo[1], res, grid.cells, _LOGODDS, grid.origin[0], grid.origin[1],
                    grid.resolution, math.cos(corr[2]), math.sin(corr[2]), corr[0], corr[1], x0, y0, x1, y1)
    known = count > 0
    prob = np.full((ny, nx), np.nan, np.float32)
    prob[known] = (1.0 / (1.0 + np.exp(-total[known] / count[known]))).astype(np.float32)
    return OccupancyImage(prob, res, (float(lo[0]), float(lo[1])))


@register_warm_up
def warm_up() -> None:
    """Assembling the map image from a toy grid."""
    from carto_cli.grid.probability_grid import ProbabilityGrid

    grid = ProbabilityGrid(0.05, (0.0, 0.0), (8, 8))
    grid.set_probability(np.array([[2, 3], [4, 4]]), 0.8)
    assemble([grid], [np.array([0.1, 0.0, 0.2])])
