"""The best particle's trajectory, each scan re-matched against the map all of its scans make together.

A particle's pose at a scan was chosen against the map as it stood then: a few scans of a corridor seen once,
before the loop that later confirmed it. At the end the best particle's whole map is known; matching every
processed scan against it once more (on one probability grid of all the scans, a correlative search within
0.4 m / 3 deg of its pose, then Cartographer's least-squares matcher nearly free to move: the map, not the
old pose, decides) and rebuilding the map from the moved scans
removes the jitter the filter leaves between neighbouring scans. The particle filter still decides the
topology (which lineage, which loop); this only moves scans by centimetres (docs/gmapping.md: 8-15 % lower
relation error on each of the four key-scan buildings GMapping maps under auto).
"""
from __future__ import annotations

import functools
import math

import numpy as np

from carto_cli.core.parallel import map_ordered
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.grid.range_inserter import ProbabilityGridRangeDataInserter
from carto_cli.matching import correlative, least_squares
from carto_cli.sensor.range_filter import RangeData

# The matcher's pull back to the pose it started from, against the grid's own cost (Cartographer's
# ceres_scan_matcher weights, with occupied_space_weight 1): weak, so the whole map decides where a scan sits.
TRANSLATION_WEIGHT = 1.0
ROTATION_WEIGHT = 1.0
# Least squares alone stays in the nearest minimum: a scan the filter left 0.3-0.4 m off (intel, seed 2: one
# scan after a 1.3 m step, 0.35-0.49 m off against a dozen others) scores 0.77 there and 0.84 at its place
SEARCH_WINDOW_M = 0.4
SEARCH_WINDOW_RAD = math.radians(3.0)
HIT_PROBABILITY = 0.55  # Cartographer's submap inserter defaults
MISS_PROBABILITY = 0.49


def map_of(poses: np.ndarray, scans: list[RangeData], resolution: float, *, hit_probability: float = HIT_PROBABILITY,
           miss_probability: float = MISS_PROBABILITY) -> ProbabilityGrid:
    """One probability grid of every scan inserted at its pose."""
    grid = ProbabilityGrid(resolution, (0.0, 0.0), (16, 16))
    inserter = ProbabilityGridRangeDataInserter(hit_probability=hit_probability, miss_probability=miss_probability)
    worlds = [scan.transformed(pose) for pose, scan in zip(poses, scans)]
    # Grown once to the bounds of every scan: growing scan by scan copied the grid again and again (one map of
    # intel's scans: 6.3 s, 0.5 s grown once)
    corners = [np.vstack([w.returns, w.misses, w.origin[None, :]]) for w in worlds]
    corners = [np.array([c.min(axis=0), c.max(axis=0)]) for c in corners]
    if corners:
        grid.grow_to_include(np.vstack(corners))
    for world in worlds:
        inserter.insert(world, grid)
    return grid


def refine_poses(poses: np.ndarray, scans: list[RangeData], *, resolution: float, iterations: int,
                 jobs: int | None = None) -> np.ndarray:
    """``poses`` (n, 3) moved so each scan matches the map of all of them; ``iterations`` rounds of
    (build the map, re-match every scan: a correlative search around its pose, then least squares from the
    best candidate) with the scans on ``jobs`` threads (None: every core). 0 returns a copy."""
    out = np.array(poses, dtype=np.float64, copy=True)
    for _ in range(iterations):
        grid = map_of(out, scans, resolution)
        coarse = correlative.coarse_grid(grid)
        moved = map_ordered(functools.partial(_rematch_scan, grid, coarse, scans, out), range(len(scans)), jobs)
        out = np.array(moved, dtype=np.float64).reshape(-1, 3)
    return out


def _rematch_scan(grid: ProbabilityGrid, coarse: correlative.CoarseGrid, scans: list[RangeData], poses: np.ndarray,
                  k: int) -> np.ndarray:
    return _rematch(grid, coarse, scans[k].returns, poses[k])


def _rematch(grid: ProbabilityGrid, coarse: correlative.CoarseGrid, points: np.ndarray, pose: np.ndarray) -> np.ndarray:
    if points.shape[0] == 0:
        return pose
    # the exhaustive search's answer (correlative.match), found scoring blocks of candidates first
    start = correlative.match_pruned(grid, coarse, points, pose, linear_search_window=SEARCH_WINDOW_M,
                                     angular_search_window=SEARCH_WINDOW_RAD).pose
    return least_squares.match(grid, points, start, target_translation=pose[:2],
                               translation_weight=TRANSLATION_WEIGHT, rotation_weight=ROTATION_WEIGHT).pose
