"""How well a scan fits a grid at a given pose: the scores that accept or reject a match after the search.

The loop-closure check (``mapping/constraint_builder``) and relocalization judge a refined pose with the
same plain score; relocalization also asks how much of the scan lands on cells the grid has seen.
"""
from __future__ import annotations

import numpy as np

from carto_cli.core import transform

__all__ = ["UNKNOWN_SCORE", "fit_scores", "inlier_fraction", "known_score", "score_at"]

UNKNOWN_SCORE = 0.1  # what a point on a never-observed cell adds to score_at's mean


def score_at(grid, points: np.ndarray, pose: np.ndarray) -> float:
    """Mean occupancy probability under ``points`` placed at ``pose`` (unknown cells count as ``UNKNOWN_SCORE``)."""
    if len(points) == 0:
        return 0.0
    cells = grid.cell_index(transform.apply(pose, points))
    p = grid.probability(cells, unknown=UNKNOWN_SCORE)
    return float(np.mean(np.where(np.isnan(p), UNKNOWN_SCORE, p)))


def known_score(grid, points: np.ndarray, pose: np.ndarray) -> tuple[float, float]:
    """(share of ``points`` at ``pose`` that fall in known cells, their mean occupancy probability)."""
    if len(points) == 0:
        return 0.0, 0.0
    p = np.asarray(grid.probability(grid.cell_index(transform.apply(pose, points)), unknown=np.nan), dtype=np.float64)
    known = ~np.isnan(p)
    n = int(known.sum())
    return n / len(p), (float(p[known].mean()) if n else 0.0)


def inlier_fraction(grid, points: np.ndarray, pose: np.ndarray, *, min_probability: float = 0.5) -> float:
    """Share of ``points`` at ``pose`` on a wall: a cell of the 3 x 3 around the point's reaches
    ``min_probability`` (a cell's slack, as a scan's own noise and the grid's quantisation put a good point
    beside the wall's cell as often as on it)."""
    if len(points) == 0:
        return 0.0
    p = np.nan_to_num(_nine_cells(grid, points, pose), nan=0.0)  # unknown reads 0, as before
    return float((p >= min_probability).any(axis=1).mean())


# Each point's 3 x 3 cells, the centre at index 4
_NEIGHBOURS = np.array([[dx, dy] for dx in (-1, 0, 1) for dy in (-1, 0, 1)], dtype=np.int64)


def _nine_cells(grid, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    """(n, 9) probabilities of every point's nine cells at ``pose`` (NaN where unknown), in one lookup: nine
    lookups were a fifth of a tracked scan's judging."""
    cells = grid.cell_index(transform.apply(pose, points))
    around = (cells[:, None, :] + _NEIGHBOURS[None, :, :]).reshape(-1, 2)
    return np.asarray(grid.probability(around), dtype=np.float64).reshape(len(cells), 9)


def fit_scores(grid, points: np.ndarray, pose: np.ndarray, *,
               min_probability: float = 0.5) -> tuple[float, float, float, float]:
    """(:func:`score_at`, :func:`known_score`'s share and mean, :func:`inlier_fraction`) of ``points`` at
    ``pose``, the same numbers from one placement and one lookup of every point's nine cells: what judging a
    tracked scan asks every scan. ``min_probability`` > 0 (an unknown cell never reaches it)."""
    if not min_probability > 0:
        raise ValueError(f"min_probability must be > 0, got {min_probability}")
    if len(points) == 0:
        return 0.0, 0.0, 0.0, 0.0
    p = _nine_cells(grid, points, pose)
    centre = p[:, 4]
    known = ~np.isnan(centre)
    n = int(known.sum())
    score = float(np.mean(np.where(known, centre, UNKNOWN_SCORE)))
    with np.errstate(invalid="ignore"):
        inliers = float((p >= min_probability).any(axis=1).mean())
    return score, n / len(centre), (float(centre[known].mean()) if n else 0.0), inliers
