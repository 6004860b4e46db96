"""How well a scan fits a grid at a given pose: the scores that accept or reject a match after the search.

The loop-closure check (``mapping/constraint_builder``) and relocalization judge a refined pose with the
same plain score; relocalization also asks how much of the scan lands on cells the grid has seen.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from carto_cli.core import transform
from carto_cli.core.kernels import register_warm_up
from carto_cli.grid.probability_grid import UNKNOWN_VALUE, VALUE_TO_PROBABILITY, ProbabilityGrid

__all__ = ["UNKNOWN_SCORE", "fit_scores", "inlier_fraction", "known_score", "score_at"]

UNKNOWN_SCORE = 0.1  # what a point on a never-observed cell adds to score_at's mean


def score_at(grid: ProbabilityGrid, points: np.ndarray, pose: np.ndarray) -> float:
    """Mean occupancy probability under ``points`` placed at ``pose`` (unknown cells count as ``UNKNOWN_SCORE``)."""
    if len(points) == 0:
        return 0.0
    cells = grid.cell_index(transform.apply(pose, points))
    p = grid.probability(cells, unknown=UNKNOWN_SCORE)
    return float(np.mean(np.where(np.isnan(p), UNKNOWN_SCORE, p)))


def known_score(grid: ProbabilityGrid, points: np.ndarray, pose: np.ndarray) -> tuple[float, float]:
    """(share of ``points`` at ``pose`` that fall in known cells, their mean occupancy probability)."""
    if len(points) == 0:
        return 0.0, 0.0
    p = np.asarray(grid.probability(grid.cell_index(transform.apply(pose, points)), unknown=np.nan), dtype=np.float64)
    known = ~np.isnan(p)
    n = int(known.sum())
    return n / len(p), (float(p[known].mean()) if n else 0.0)


def inlier_fraction(grid: ProbabilityGrid, points: np.ndarray, pose: np.ndarray, *,
                    min_probability: float = 0.5) -> float:
    """Share of ``points`` at ``pose`` on a wall: a cell of the 3 x 3 around the point's reaches
    ``min_probability`` (a cell's slack, as a scan's own noise and the grid's quantisation put a good point
    beside the wall's cell as often as on it)."""
    if len(points) == 0:
        return 0.0
    p = np.nan_to_num(_nine_cells(grid, points, pose), nan=0.0)  # unknown reads 0, as before
    return float((p >= min_probability).any(axis=1).mean())


# Each point's 3 x 3 cells, the centre at index 4
_NEIGHBOURS = np.array([[dx, dy] for dx in (-1, 0, 1) for dy in (-1, 0, 1)], dtype=np.int64)


def _nine_cells(grid: ProbabilityGrid, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(n, 9) probabilities of every point's nine cells at ``pose`` (NaN where unknown), in one lookup: nine
    lookups were a fifth of a tracked scan's judging."""
    cells = grid.cell_index(transform.apply(pose, points))
    around = (cells[:, None, :] + _NEIGHBOURS[None, :, :]).reshape(-1, 2)
    return np.asarray(grid.probability(around), dtype=np.float64).reshape(len(cells), 9)


def fit_scores(grid: ProbabilityGrid, points: np.ndarray, pose: np.ndarray, *,
               min_probability: float = 0.5) -> tuple[float, float, float, float]:
    """(:func:`score_at`, :func:`known_score`'s share and mean, :func:`inlier_fraction`) of ``points`` at
    ``pose``, the same numbers from one placement and one look at every point's nine cells, in one kernel: what
    judging a tracked scan (and each neighbour of a relocalization answer) asks every scan; the three numpy
    passes were a quarter of a tracked scan's cost. ``min_probability`` > 0 (an unknown cell never reaches it)."""
    if not min_probability > 0:
        raise ValueError(f"min_probability must be > 0, got {min_probability}")
    if len(points) == 0:
        return 0.0, 0.0, 0.0, 0.0
    pose = transform.as_pose(pose).reshape(3)
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    total, known, known_sum, inliers = _fit(grid.cells, VALUE_TO_PROBABILITY, float(grid.origin[0]),
                                            float(grid.origin[1]), float(grid.resolution), math.cos(pose[2]),
                                            math.sin(pose[2]), float(pose[0]), float(pose[1]), pts,
                                            float(min_probability), UNKNOWN_VALUE, UNKNOWN_SCORE)
    n = len(pts)
    return total / n, known / n, (known_sum / known if known else 0.0), inliers / n


@njit(cache=True, nogil=True)
def _fit(cells, table, ox, oy, resolution, c, s, tx, ty, points, min_probability, unknown_value, unknown_score):
    """(sum of the centre cells' probabilities with unknown ones at ``unknown_score``, known centres, their sum,
    points with a cell of their 3 x 3 at ``min_probability`` or more); placement and cell index as
    ``transform.apply`` and ``ProbabilityGrid.cell_index`` compute them."""
    ny, nx = cells.shape
    total = 0.0
    known = 0
    known_sum = 0.0
    inliers = 0
    for k in range(points.shape[0]):
        x = c * points[k, 0] - s * points[k, 1] + tx
        y = s * points[k, 0] + c * points[k, 1] + ty
        ix = int(np.floor((x - ox) / resolution))
        iy = int(np.floor((y - oy) / resolution))
        p = unknown_score
        if 0 <= ix < nx and 0 <= iy < ny and cells[iy, ix] != unknown_value:
            p = table[cells[iy, ix]]
            known += 1
            known_sum += p
        total += p
        hit = False
        for dx in range(-1, 2):
            for dy in range(-1, 2):
                jx = ix + dx
                jy = iy + dy
                if 0 <= jx < nx and 0 <= jy < ny:
                    v = cells[jy, jx]
                    if v != unknown_value and table[v] >= min_probability:
                        hit = True
        inliers += hit
    return total, known, known_sum, inliers


@register_warm_up
def warm_up() -> None:
    """The fit kernel on a toy grid."""
    from carto_cli.grid.probability_grid import ProbabilityGrid

    grid = ProbabilityGrid(0.05, (0.0, 0.0), (8, 8))
    grid.set_probability(np.array([[3, 3]]), 0.9)
    fit_scores(grid, np.array([[0.16, 0.17], [0.5, 0.1]]), np.zeros(3))
