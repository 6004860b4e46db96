"""The best particle's trajectory made consistent where it revisits a place: a small pose graph at the end.

The particle filter closes a loop by keeping the lineage whose map agrees best with the revisit, but it
never moves the earlier pass: where the robot came back 0.2-0.4 m off, the map keeps two versions of the
walls, and matching each scan against the whole map (``refine.refine_poses``) leaves each pass on its own
version (intel, seed 0: 12 % of the relations more than 0.1 m off, nearly all of them between passes). Here
every scan is matched against the scans of *other* times near it, and the disagreements become the loop
closures of a pose graph (Cartographer's optimizer, ``mapping.optimization``):

* the processed scans are cut into chunks of ``CHUNK`` consecutive scans, each a small probability grid at
  the particle's poses and a submap of the graph, anchored at its first scan;
* every scan is matched (a correlative search of +-``WINDOW_M`` / +-``WINDOW_RAD``, then least squares)
  against each chunk of another pass whose scans come within ``NEAR_M`` of it: another pass is at least
  ``MIN_TRAVEL_M`` of travel away, so that a dense recording's next metres are not taken for a revisit;
* a search whose best pose lies on its window's edge has not found a peak but a slope (most often a scan
  sliding towards the few walls a chunk knows): it is searched again from there, and the match is dropped
  when the slope leads further than ``MAX_MOVE_M``;
* a match counts when most of its points fall on cells the chunk knows and their mean occupancy reaches
  ``MIN_PROBABILITY``, and when a scan within two of it found the same correction in the same chunk (one
  scan's match alone is often a corridor's slide or a door's edge);
* the graph holds every scan in its own chunk and its step from the previous scan as the particle left
  them, and the accepted matches, all with one weight; the Huber loss bounds what a wrong match can pull.

Where nothing is revisited no match is accepted and the poses come back unchanged. The particle filter still
decides the topology; this moves whole passes by centimetres to decimetres.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from carto_cli.core import transform
from carto_cli.core.parallel import map_ordered
from carto_cli.gmapping.refine import map_of
from carto_cli.mapping.constraints import ConstraintSet
from carto_cli.mapping.optimization import NodePairs, optimize
from carto_cli.matching import correlative, least_squares
from carto_cli.matching.scoring import known_score
from carto_cli.sensor.range_filter import RangeData

CHUNK = 10  # processed scans per chunk: 5-20 measured alike on intel (docs/gmapping.md)
NEAR_M = 2.0  # a chunk whose scans' bounding circle comes this close to the scan is a candidate
# The correlative search's reach (revisits sit 0.2-0.7 m off; fhw, seed 3: one 0.63-0.67 m) and the largest
# correction: a search on its window's edge is followed (EDGE_SEARCHES), so a wider reach does not turn a
# slope into a match. 0.4 / 0.6 m before that rule; 0.5 / 0.8 had then let a false closure in (docs/gmapping.md)
WINDOW_M = 0.5
WINDOW_RAD = math.radians(3.0)
# A chunk's grid from a handful of scans: stronger updates than a submap's (0.55 / 0.49) so that walls seen
# two or three times already stand out from free space
HIT_PROBABILITY = 0.7
MISS_PROBABILITY = 0.4
PREFILTER_KNOWN = 0.3  # below this share of points on known cells at the start, no search
MIN_KNOWN = 0.5  # share of the scan's points on cells the chunk knows, after the match
# their mean occupancy: a chunk of a few scans knows the free side of a wall as well as the wall, so even a
# right match lands many points on cells below 0.5 (orebro, 30 particles: the first scans against the last,
# 0.45 m off, match at 0.42-0.51; 0.65 missed that loop and left it 0.5 m open)
MIN_PROBABILITY = 0.45
MAX_MOVE_M = 0.8  # a larger correction is not a revisit a few decimetres off but another place
# Travel between a scan and a chunk below which they are one pass, not a revisit. The chunk index alone (two
# chunks apart) meant 7-10 m on key scans but 1-2 m on a dense recording (a chunk of processed scans 0.1 m
# apart), where scans matched against the corridor just behind them slid to the search window's edge and 73-75
# such "loop closures" made the simulated loop's map five times worse (0.02 -> 0.10 m, docs/gmapping.md)
MIN_TRAVEL_M = 5.0
EDGE_SEARCHES = 3  # correlative searches from one start, each from the last one's edge (the reach's bound)
MIN_POINTS = 20
CONFIRM_SPAN = 2  # a neighbour within this many processed scans must agree ...
CONFIRM_M = 0.1  # ... on the correction within this translation ...
CONFIRM_RAD = 0.02  # ... and rotation
WEIGHT = (1e3, 1e4)  # translation, rotation: every constraint alike
HUBER = 10.0


@dataclass(frozen=True)
class LoopRefinement:
    poses: np.ndarray  # (n, 3)
    candidates: int  # scan-chunk pairs searched
    accepted: int  # loop closures in the graph


def close_loops(poses: np.ndarray, scans: list[RangeData], *, resolution: float,
                jobs: int | None = None) -> LoopRefinement:
    """``poses`` (n, 3) of ``scans`` optimized with the loop closures found between passes (module doc); a
    chunk's candidates are matched on ``jobs`` threads (None: every core), applied in scan order."""
    poses = np.array(poses, dtype=np.float64, copy=True).reshape(-1, 3)
    n = len(poses)
    chunk_of = np.arange(n) // CHUNK
    m = int(chunk_of[-1]) + 1 if n else 0
    if m < 3:
        return LoopRefinement(poses, 0, 0)
    anchors = poses[::CHUNK].copy()
    centres = np.empty((m, 2))
    radii = np.empty(m)
    for j in range(m):
        xy = poses[j * CHUNK:(j + 1) * CHUNK, :2]
        centres[j] = xy.mean(axis=0)
        radii[j] = np.max(np.linalg.norm(xy - centres[j], axis=1))
    enough = np.array([len(scan.returns) >= MIN_POINTS for scan in scans])
    travel = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poses[:, :2], axis=0), axis=1))])

    candidates = 0
    corrections: dict[tuple[int, int], np.ndarray] = {}
    matched: dict[tuple[int, int], np.ndarray] = {}
    # Chunk by chunk, so one chunk's grid is in memory at a time (they reach as far as the rays: a few MB each)
    for j in range(m):
        near = (np.linalg.norm(poses[:, :2] - centres[j], axis=1) - radii[j] < NEAR_M) & enough
        near &= np.abs(chunk_of - j) >= 2
        first_travel, last_travel = travel[j * CHUNK], travel[min((j + 1) * CHUNK, n) - 1]
        near &= np.maximum(first_travel - travel, travel - last_travel) >= MIN_TRAVEL_M
        if not near.any():
            continue
        first, last = j * CHUNK, (j + 1) * CHUNK
        grid = map_of(poses[first:last], scans[first:last], resolution, hit_probability=HIT_PROBABILITY,
                      miss_probability=MISS_PROBABILITY)
        coarse = correlative.coarse_grid(grid)
        idx = np.flatnonzero(near)
        found = map_ordered(functools.partial(_match_scan, grid, coarse, scans, poses), idx, jobs)
        for i, (searched, pose) in zip(idx, found):
            candidates += searched
            if pose is None:
                continue
            matched[(int(i), j)] = pose
            corrections[(int(i), j)] = transform.compose(pose[None], transform.inverse(poses[i][None]))[0]

    constraints = ConstraintSet(capacity=n + len(matched))
    constraints.extend(chunk_of, np.arange(n), transform.relative(anchors[chunk_of], poses), *WEIGHT)
    accepted = 0
    for (node, chunk), pose in sorted(matched.items()):
        if not _confirmed(corrections, node, chunk):
            continue
        constraints.add(chunk, node, transform.relative(anchors[chunk][None], pose[None])[0], *WEIGHT, True)
        accepted += 1
    if accepted == 0:
        return LoopRefinement(poses, candidates, 0)
    steps = NodePairs.consecutive(poses, translation_weight=WEIGHT[0], rotation_weight=WEIGHT[1])
    result = optimize(poses, anchors, constraints, local_slam=steps, huber_scale=HUBER)
    return LoopRefinement(result.node_poses, candidates, accepted)


def _match_scan(grid, coarse, scans: list[RangeData], poses: np.ndarray, i: int) -> tuple[bool, np.ndarray | None]:
    return _match(grid, coarse, scans[i].returns, poses[i])


def _match(grid, coarse, points: np.ndarray, pose: np.ndarray) -> tuple[bool, np.ndarray | None]:
    """(searched, the scan's pose in the chunk's grid or None when the match is not a revisit)."""
    if known_score(grid, points, pose)[0] < PREFILTER_KNOWN:
        return False, None
    start = follow_to_peak(grid, points, pose, coarse)
    if start is None:
        return True, None
    found = least_squares.match(grid, points, start).pose
    share, probability = known_score(grid, points, found)
    if share < MIN_KNOWN or probability < MIN_PROBABILITY or np.hypot(*(found[:2] - pose[:2])) > MAX_MOVE_M:
        return True, None
    return True, found


def follow_to_peak(grid, points: np.ndarray, pose: np.ndarray,
                   coarse: correlative.CoarseGrid | None = None) -> np.ndarray | None:
    """The correlative search's best pose near ``pose``, searched again from there while it lies on the search
    window's edge (the score still rising outward); None when that leads beyond ``MAX_MOVE_M`` or is still on
    an edge after ``EDGE_SEARCHES`` searches. ``coarse``: ``correlative.coarse_grid(grid)``, for many searches
    in one grid (the exhaustive search's answer, about three times faster)."""
    params = correlative.search_parameters(points, grid.resolution, WINDOW_M, WINDOW_RAD)
    coarse = correlative.coarse_grid(grid) if coarse is None else coarse
    start = np.asarray(pose, dtype=np.float64)
    for _ in range(EDGE_SEARCHES):
        best = correlative.match_pruned(grid, coarse, points, start, linear_search_window=WINDOW_M,
                                        angular_search_window=WINDOW_RAD).pose
        cells = np.rint(np.abs(best[:2] - start[:2]) / grid.resolution)
        steps = round(abs(transform.wrap_angle_scalar(float(best[2] - start[2]))) / params.angular_step)
        if cells.max() < params.num_linear_perturbations and steps < params.num_angular_perturbations:
            return best
        if np.hypot(*(best[:2] - pose[:2])) > MAX_MOVE_M:
            return None
        start = best
    return None


def _confirmed(corrections: dict[tuple[int, int], np.ndarray], i: int, j: int) -> bool:
    """A scan within ``CONFIRM_SPAN`` of ``i`` moved by nearly the same correction in chunk ``j``."""
    own = corrections[(i, j)]
    for other in range(i - CONFIRM_SPAN, i + CONFIRM_SPAN + 1):
        c = corrections.get((other, j))
        if other == i or c is None:
            continue
        if (np.hypot(*(c[:2] - own[:2])) < CONFIRM_M
                and abs(transform.wrap_angle_scalar(float(c[2] - own[2]))) < CONFIRM_RAD):
            return True
    return False
