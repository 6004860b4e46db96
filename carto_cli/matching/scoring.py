"""How well a scan fits a grid at a given pose: the scores that accept or reject a match after the search.

The loop-closure check (``mapping/constraint_builder``) and relocalization judge a refined pose with the
same plain score; relocalization also asks how much of the scan lands on cells the grid has seen.
"""
from __future__ import annotations

import numpy as np

from carto_cli.core import transform

__all__ = ["inlier_fraction", "known_score", "score_at"]


def score_at(grid, points: np.ndarray, pose: np.ndarray) -> float:
    """Mean occupancy probability under ``points`` placed at ``pose`` (unknown cells count as 0.1)."""
    if len(points) == 0:
        return 0.0
    cells = grid.cell_index(transform.apply(pose, points))
    p = grid.probability(cells, unknown=0.1)
    return float(np.mean(np.where(np.isnan(p), 0.1, p)))


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
    cells = grid.cell_index(transform.apply(pose, points))
    hit = np.zeros(len(cells), dtype=bool)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            p = grid.probability(cells + np.array([dx, dy]), unknown=0.0)
            hit |= p >= min_probability
    return float(hit.mean())
