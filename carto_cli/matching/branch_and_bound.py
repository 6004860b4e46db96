"""Cartographer's FastCorrelativeScanMatcher2D: exact window search by depth-first branch and bound.

The candidate set is the real-time matcher's (see ``correlative``): the scan
rotated by every multiple of an angular step chosen so the farthest point
moves at most one cell per step, and discretised once per angle; every
translation is then an integer cell offset (scan_index, x, y). The score of
a candidate is the mean precomputation-grid value (level 0: the submap
itself, 0..255) under the scan's points, mapped back to a probability.

Branch and bound over that set: a node at height h stands for the 2^h × 2^h
offsets starting at (x, y) for one angle, and its score on precomputation
level h (the block maximum) bounds every offset in it. The top level lists
every angle on a 2^(depth-1) lattice; each node splits into four children
at h - 1; a subtree is dropped as soon as its bound cannot beat the best
leaf found so far (or ``min_score``). Visiting the best-bounded children
first finds a good leaf early, so most of the window is never looked at.

The result is exactly the exhaustive optimum (``exhaustive_match`` is the
same search without the bounds). Scores are kept as integer sums, so there is
no rounding in the comparisons, and ties are broken by one total order,
preferring the candidate closest to the initial estimate (in angle, then in
translation, then by index): where the map cannot tell candidates apart (a
corridor, a saturated map) the prior wins, and both searches agree.

Kernels are single-threaded and release the GIL: the constraint builder
runs many matches at once, so it parallelises across them with threads
rather than inside one search.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from carto_cli.core.kernels import register_warm_up
from carto_cli.core.transform import wrap_angle
from carto_cli.grid.probability_grid import MAX_PROBABILITY, MIN_PROBABILITY
from carto_cli.matching.correlative import search_parameters
from carto_cli.matching.kernels import discretize
from carto_cli.matching.precomputation import PrecomputationGridStack, cell_value_to_probability
from carto_cli.sensor.range_filter import Pose


class MatchResult(NamedTuple):
    found: bool  # score > min_score
    score: float  # mean probability under the scan at ``pose`` (0.1..0.9); 0 when not found
    pose: np.ndarray  # (x, y, theta) in the submap's (grid's) frame


# ------------------------------------------------------------------------------- kernels


@njit(cache=True, nogil=True)
def _score(data, start, wnx, wny, pad, discrete, bbox, k, x, y):
    """Integer sum of level values under scan ``k`` shifted by (x, y) cells; 0 beyond the stored level."""
    n = discrete.shape[1]
    # int64 from the start: numba widens anyway, but run as Python (NUMBA_DISABLE_JIT) a plain 0 plus a
    # uint8 cell stays uint8 and wraps at 255.
    total = np.int64(0)
    x_lo = bbox[k, 0] + x + pad
    x_hi = bbox[k, 1] + x + pad
    y_lo = bbox[k, 2] + y + pad
    y_hi = bbox[k, 3] + y + pad
    if x_lo >= 0 and y_lo >= 0 and x_hi < wnx and y_hi < wny:
        base = start + (y + pad) * wnx + x + pad
        for i in range(n):
            total += data[base + discrete[k, i, 1] * wnx + discrete[k, i, 0]]
    elif x_hi >= 0 and y_hi >= 0 and x_lo < wnx and y_lo < wny:
        for i in range(n):
            ix = discrete[k, i, 0] + x + pad
            iy = discrete[k, i, 1] + y + pad
            if ix >= 0 and iy >= 0 and ix < wnx and iy < wny:
                total += data[start + iy * wnx + ix]
    return total


@njit(cache=True, nogil=True)
def _axis_distance(lo, hi):
    """Smallest |offset| over the offsets lo..hi."""
    if lo > 0:
        return lo
    if hi < 0:
        return -hi
    return 0


@njit(cache=True, nogil=True)
def _may_beat(s, a, x, y, extent, thr, found, best):
    """Whether a node (bound ``s``; angle index a, offsets x..x+extent, y..y+extent) can hold a better leaf.

    ``best`` = (sum, |a|, d², a, x, y) of the best leaf so far. At equal sums
    the order is lexicographic on (|a|, d², a, x, y), and (|a|, min d² over the
    block, a, x, y) is a component-wise, hence lexicographic, lower bound of
    every leaf under the node: comparing it is exact, not a heuristic.
    """
    if s <= thr:
        return False
    if not found or s > best[0]:
        return True
    if s < best[0]:
        return False
    ang = abs(a)
    if ang != best[1]:
        return ang < best[1]
    dx = _axis_distance(x, x + extent)
    dy = _axis_distance(y, y + extent)
    d2 = dx * dx + dy * dy
    if d2 != best[2]:
        return d2 < best[2]
    if a != best[3]:
        return a < best[3]
    if x != best[4]:
        return x < best[4]
    return y < best[5]


@njit(cache=True, nogil=True)
def _set_best(best, s, a, x, y):
    best[0] = s
    best[1] = abs(a)
    best[2] = x * x + y * y
    best[3] = a
    best[4] = x
    best[5] = y


@njit(cache=True, nogil=True)
def _excluded(excl, a, x, y):
    """Whether the leaf (angle index a, offsets x, y) lies in one of the boxes (a0, a1, x0, x1, y0, y1)."""
    for e in range(excl.shape[0]):
        if excl[e, 0] <= a <= excl[e, 1] and excl[e, 2] <= x <= excl[e, 3] and excl[e, 4] <= y <= excl[e, 5]:
            return True
    return False


@njit(cache=True, nogil=True)
def _branch_and_bound(data, starts, widths, heights, pads, discrete, bbox, bounds, angle_index, top, leaf, thr,
                      scored, excl):
    """Best leaf (height ``leaf``) over all scans; returns (found, angle index, x, y, sum).

    Scan k is rotated by ``angle_index[k]`` angular steps from the estimate;
    ``bounds[k] = (min_x, max_x, min_y, max_y)`` are its cell offsets; a
    candidate with sum <= ``thr`` never counts. ``scored[h]`` is incremented
    by the number of nodes scored at height h (the cost of the search). Leaves inside a box of ``excl``
    (rows a0, a1, x0, x1, y0, y1; inclusive) never count either: a search for the best *other* place.
    """
    num_scans = discrete.shape[0]
    step = 1 << top
    count = 0
    for k in range(num_scans):
        if bounds[k, 0] <= bounds[k, 1] and bounds[k, 2] <= bounds[k, 3]:
            count += ((bounds[k, 1] - bounds[k, 0]) // step + 1) * ((bounds[k, 3] - bounds[k, 2]) // step + 1)
    ck = np.empty(count, dtype=np.int64)
    cx = np.empty(count, dtype=np.int64)
    cy = np.empty(count, dtype=np.int64)
    cs = np.empty(count, dtype=np.int64)
    c = 0
    st, wnx, wny, pad = starts[top], widths[top], heights[top], pads[top]
    for k in range(num_scans):
        if bounds[k, 0] > bounds[k, 1] or bounds[k, 2] > bounds[k, 3]:
            continue
        for x in range(bounds[k, 0], bounds[k, 1] + 1, step):
            for y in range(bounds[k, 2], bounds[k, 3] + 1, step):
                ck[c] = k
                cx[c] = x
                cy[c] = y
                cs[c] = _score(data, st, wnx, wny, pad, discrete, bbox, k, x, y)
                c += 1
    scored[top] += count

    # Explicit DFS stack; the next node to expand is the last pushed, so pushing
    # in ascending bound order expands the most promising node first.
    capacity = count + 4 * (top - leaf + 1)
    sk = np.empty(capacity, dtype=np.int64)
    sx = np.empty(capacity, dtype=np.int64)
    sy = np.empty(capacity, dtype=np.int64)
    sh = np.empty(capacity, dtype=np.int64)
    ss = np.empty(capacity, dtype=np.int64)
    # Counting sort by bound straight into the stack: linear, and it spares compiling np.argsort
    # (docs/measurements.md). Beyond 2^16 distinct sums, neighbouring sums share a
    # bucket; the visiting order then is only nearly sorted, which costs nothing in exactness.
    top_sum = thr
    for i in range(count):
        top_sum = max(top_sum, cs[i])
    shift = 0
    while (top_sum - thr) >> shift > 65536:
        shift += 1
    num_buckets = ((top_sum - thr) >> shift) + 1
    fill = np.zeros(num_buckets + 1, dtype=np.int64)
    for i in range(count):
        if cs[i] > thr:
            fill[((cs[i] - thr - 1) >> shift) + 1] += 1
    for b in range(num_buckets):
        fill[b + 1] += fill[b]
    sp = fill[num_buckets]
    for i in range(count):
        if cs[i] > thr:
            b = (cs[i] - thr - 1) >> shift
            j = fill[b]
            fill[b] += 1
            sk[j] = ck[i]
            sx[j] = cx[i]
            sy[j] = cy[i]
            sh[j] = top
            ss[j] = cs[i]

    best = np.zeros(6, dtype=np.int64)
    found = False
    child_k = np.empty(4, dtype=np.int64)
    child_x = np.empty(4, dtype=np.int64)
    child_y = np.empty(4, dtype=np.int64)
    child_s = np.empty(4, dtype=np.int64)
    leaf_width = 1 << leaf
    while sp > 0:
        sp -= 1
        k, x, y, h, s = sk[sp], sx[sp], sy[sp], sh[sp], ss[sp]
        extent = (1 << h) - leaf_width  # leaves under this node lie at x..x+extent
        a = angle_index[k]
        if not _may_beat(s, a, x, y, extent, thr, found, best):
            continue
        if h == leaf:
            if excl.shape[0] and _excluded(excl, a, x, y):
                continue
            _set_best(best, s, a, x, y)
            found = True
            continue
        half = 1 << (h - 1)
        lv = h - 1
        st, wnx, wny, pad = starts[lv], widths[lv], heights[lv], pads[lv]
        m = 0
        for ox in range(2):
            xx = x + ox * half
            if xx > bounds[k, 1]:
                break
            for oy in range(2):
                yy = y + oy * half
                if yy > bounds[k, 3]:
                    break
                v = _score(data, st, wnx, wny, pad, discrete, bbox, k, xx, yy)
                # Insertion sort, ascending: at most four children.
                j = m
                while j > 0 and child_s[j - 1] > v:
                    child_k[j] = child_k[j - 1]
                    child_x[j] = child_x[j - 1]
                    child_y[j] = child_y[j - 1]
                    child_s[j] = child_s[j - 1]
                    j -= 1
                child_k[j] = k
                child_x[j] = xx
                child_y[j] = yy
                child_s[j] = v
                m += 1
        scored[lv] += m
        for j in range(m):
            if _may_beat(child_s[j], a, child_x[j], child_y[j], half - leaf_width, thr, found, best):
                sk[sp] = child_k[j]
                sx[sp] = child_x[j]
                sy[sp] = child_y[j]
                sh[sp] = lv
                ss[sp] = child_s[j]
                sp += 1
    return found, best[3], best[4], best[5], best[0]


@njit(cache=True, nogil=True)
def _exhaustive(data, starts, widths, heights, pads, discrete, bbox, bounds, angle_index, level, thr):
    """Every candidate of ``bounds`` scored on ``level``, same order of preference as the B&B."""
    best = np.zeros(6, dtype=np.int64)
    found = False
    st, wnx, wny, pad = starts[level], widths[level], heights[level], pads[level]
    for k in range(discrete.shape[0]):
        a = angle_index[k]
        for x in range(bounds[k, 0], bounds[k, 1] + 1):
            for y in range(bounds[k, 2], bounds[k, 3] + 1):
                s = _score(data, st, wnx, wny, pad, discrete, bbox, k, x, y)
                if _may_beat(s, a, x, y, 0, thr, found, best):
                    _set_best(best, s, a, x, y)
                    found = True
    return found, best[3], best[4], best[5], best[0]


@njit(cache=True, nogil=True)
def _bounds(discrete, window, nx, ny):
    """Per scan: the box of its cells, and ``window`` (min_x, max_x, min_y, max_y) cut to the
    offsets at which the scan overlaps the grid.

    Cartographer's ShrinkToFit: outside those offsets every point reads 0, so
    they are pointless; for the whole-submap search it is what turns an
    unbounded window into the submap's extent.
    """
    num_scans, n = discrete.shape[0], discrete.shape[1]
    bbox = np.zeros((num_scans, 4), dtype=np.int64)
    bounds = np.empty((num_scans, 4), dtype=np.int64)
    for k in range(num_scans):
        if n == 0:
            bounds[k, 0] = bounds[k, 2] = 1  # empty: min > max
            bounds[k, 1] = bounds[k, 3] = 0
            continue
        x0 = discrete[k, 0, 0]
        x1 = x0
        y0 = discrete[k, 0, 1]
        y1 = y0
        for i in range(1, n):
            x0 = min(x0, discrete[k, i, 0])
            x1 = max(x1, discrete[k, i, 0])
            y0 = min(y0, discrete[k, i, 1])
            y1 = max(y1, discrete[k, i, 1])
        bbox[k, 0] = x0
        bbox[k, 1] = x1
        bbox[k, 2] = y0
        bbox[k, 3] = y1
        bounds[k, 0] = max(window[0], -x1)
        bounds[k, 1] = min(window[1], nx - 1 - x0)
        bounds[k, 2] = max(window[2], -y1)
        bounds[k, 3] = min(window[3], ny - 1 - y0)
    return bbox, bounds


# ------------------------------------------------------------------------------- set-up


def angular_step(points: ArrayLike, resolution: float) -> float:
    """Cartographer's step: the farthest point (at least 3 cells out) moves at most ``resolution``.

    The same as the real-time matcher's.
    """
    return search_parameters(points, resolution, 0.0, 0.0).angular_step


def _cells(length: float, resolution: float) -> int:
    return int(math.ceil(length / resolution - 1e-9))


class _Problem(NamedTuple):
    """One search: the scans at ``angle_index`` steps from the estimate, and their offset bounds."""

    estimate: tuple  # (x0, y0, theta0): offsets and angle indices are relative to it
    step: float  # angular step (rad) of one angle index
    angle_index: np.ndarray  # (num_scans,) int64
    discrete: np.ndarray  # (num_scans, n, 2) cell indices of the rotated, translated scans
    bbox: np.ndarray  # (num_scans, 4) min_x, max_x, min_y, max_y of each discretised scan
    bounds: np.ndarray  # (num_scans, 4) offsets to search for each scan


def _prepare(stack: PrecomputationGridStack, points: np.ndarray, estimate: Pose, step: float, angle_index: np.ndarray,
             window: Sequence[int]) -> _Problem:
    x0, y0, th0 = (float(v) for v in estimate)
    angle_index = np.ascontiguousarray(angle_index, dtype=np.int64)
    # Computed once here, so every search rotating by index a uses the very same float angle.
    angles = th0 + angle_index * step
    discrete = discretize(points, angles, x0, y0, stack.origin[0], stack.origin[1], 1.0 / stack.resolution)
    nx, ny = stack.num_cells
    bbox, bounds = _bounds(discrete, np.asarray(window, dtype=np.int64), nx, ny)
    return _Problem((x0, y0, th0), step, angle_index, discrete, bbox, bounds)


def _window_problem(stack: PrecomputationGridStack, points: np.ndarray, estimate: Pose, linear_search_window: float,
                    angular_search_window: float) -> _Problem:
    """The candidate set of :func:`match`: every angular step and every cell within the windows."""
    step = angular_step(points, stack.resolution)
    num_angular = _cells(angular_search_window, step)
    num_linear = _cells(linear_search_window, stack.resolution)
    return _prepare(stack, points, estimate, step, np.arange(-num_angular, num_angular + 1),
                    (-num_linear, num_linear, -num_linear, num_linear))


def _points(points: ArrayLike) -> np.ndarray:
    return np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)


def _threshold(min_score: float, n: int) -> int:
    """Largest integer sum that does *not* beat ``min_score`` for n points (sums are compared as ints)."""
    mean = (float(min_score) - MIN_PROBABILITY) * 255.0 / (MAX_PROBABILITY - MIN_PROBABILITY)
    if mean < 0.0:
        return -1  # every candidate, even an all-unknown one, beats a min_score below 0.1
    # Nudge so that a sum whose score equals min_score exactly (up to float noise) does not beat it.
    return int(math.floor(mean * n + 1e-9 * max(n, 1)))


def _not_found(estimate: Pose) -> MatchResult:
    x0, y0, th0 = (float(v) for v in estimate)
    return MatchResult(False, 0.0, np.array([x0, y0, wrap_angle(th0)]))


def _result(problem: _Problem, stack: PrecomputationGridStack, found: bool, a: int, x: int, y: int, s: int,
            n: int) -> MatchResult:
    if not found:
        return _not_found(problem.estimate)
    x0, y0, th0 = problem.estimate
    res = stack.resolution
    pose = np.array([x0 + x * res, y0 + y * res, wrap_angle(th0 + a * problem.step)])
    return MatchResult(True, float(cell_value_to_probability(s / n)), pose)


_NO_EXCLUSION = np.zeros((0, 6), dtype=np.int64)


def _run_bnb(stack: PrecomputationGridStack, problem: _Problem, top: int, leaf: int, thr: int,
             scored: np.ndarray | None = None, excl: np.ndarray | None = None) -> tuple[bool, int, int, int, int]:
    if scored is None:
        scored = np.zeros(stack.depth, dtype=np.int64)
    return _branch_and_bound(stack.data, stack.starts, stack.level_widths, stack.level_heights, stack.pads,
                             problem.discrete, problem.bbox, problem.bounds, problem.angle_index, top, leaf, thr,
                             scored, _NO_EXCLUSION if excl is None else excl)


# Fewer angles than this stay on one thread: a windowed search's coarse stage (7-40 angles, about a millisecond)
# took twice as long dealt to two threads (aces, rival searches with a prior); a whole map's has hundreds.
SPLIT_MIN_ANGLES = 128


def _run_bnb_split(stack: PrecomputationGridStack, problem: _Problem, top: int, leaf: int, thr: int,
                   excl: np.ndarray, jobs: int | None) -> tuple[bool, int, int, int, int]:
    """:func:`_run_bnb`'s answer, the angles dealt to ``jobs`` threads (every ``jobs``-th angle to each, so that
    every share holds angles near the best and prunes as early). Each share's best is exact and the kernel
    orders leaves totally (sum, then |angle|, distance, angle, x, y: :func:`_may_beat`), so the best of the
    shares' bests by that order is the whole search's, whatever the number of threads."""
    from carto_cli.core.parallel import available_cores, map_ordered

    parts = min(available_cores() if jobs is None else max(1, int(jobs)), len(problem.angle_index))
    if parts < 2 or len(problem.angle_index) < SPLIT_MIN_ANGLES:
        return _run_bnb(stack, problem, top, leaf, thr, excl=excl)

    def share(j: int) -> tuple[bool, int, int, int, int]:
        rows = np.arange(j, len(problem.angle_index), parts)
        sub = problem._replace(angle_index=np.ascontiguousarray(problem.angle_index[rows]),
                               discrete=np.ascontiguousarray(problem.discrete[rows]),
                               bbox=np.ascontiguousarray(problem.bbox[rows]),
                               bounds=np.ascontiguousarray(problem.bounds[rows]))
        return _run_bnb(stack, sub, top, leaf, thr, excl=excl)

    found = [r for r in map_ordered(share, range(parts), parts) if r[0]]
    if not found:
        return False, 0, 0, 0, 0
    return min(found, key=lambda r: (-r[4], abs(r[1]), r[2] * r[2] + r[3] * r[3], r[1], r[2], r[3]))


class SearchCost(NamedTuple):
    """What a windowed search cost: the candidates it scored per level against the candidates in its window."""

    found: bool
    scored: np.ndarray  # (depth,) candidates scored at each level of the stack
    window: int  # candidates (angle, x, y) in the window, cut to the grid: what an exhaustive search scores

    @property
    def scored_fraction(self) -> float:
        return float(self.scored.sum()) / max(self.window, 1)


def search_cost(stack: PrecomputationGridStack, points: ArrayLike, initial_pose_estimate: Pose, *,
                linear_search_window: float = 7.0, angular_search_window: float = math.radians(30.0),
                min_score: float = 0.55) -> SearchCost:
    """The same search as :func:`match`, reporting how much of its window the bounds let it skip."""
    pts = _points(points)
    problem = _window_problem(stack, pts, initial_pose_estimate, linear_search_window, angular_search_window)
    scored = np.zeros(stack.depth, dtype=np.int64)
    found = False
    if pts.shape[0]:
        found = bool(_run_bnb(stack, problem, stack.depth - 1, 0, _threshold(min_score, pts.shape[0]), scored)[0])
    b = problem.bounds
    window = int(((b[:, 1] - b[:, 0] + 1) * (b[:, 3] - b[:, 2] + 1)).sum())
    return SearchCost(found, scored, window)


def full_submap_center(stack: PrecomputationGridStack) -> np.ndarray:
    """The initial estimate of a whole-submap search: the submap's centre, angle 0."""
    nx, ny = stack.num_cells
    c = stack.origin + 0.5 * stack.resolution * np.array([nx, ny], dtype=np.float64)
    return np.array([c[0], c[1], 0.0])


# ------------------------------------------------------------------------------- public API


def match(stack: PrecomputationGridStack, points: ArrayLike, initial_pose_estimate: Pose, *,
          linear_search_window: float = 7.0, angular_search_window: float = math.radians(30.0),
          min_score: float = 0.55) -> MatchResult:
    """Best pose within ±windows of ``initial_pose_estimate`` (Cartographer's Match).

    ``points`` (n, 2) are in the scan's own frame; the estimate and the
    returned pose are in the submap frame (the grid's world coordinates).
    ``found`` is ``score > min_score``; when false the pose is the estimate.
    """
    pts = _points(points)
    n = pts.shape[0]
    if n == 0:
        return _not_found(initial_pose_estimate)
    problem = _window_problem(stack, pts, initial_pose_estimate, linear_search_window, angular_search_window)
    found, a, x, y, s = _run_bnb(stack, problem, stack.depth - 1, 0, _threshold(min_score, n))
    return _result(problem, stack, found, a, x, y, s, n)


def match_full_submap(stack: PrecomputationGridStack, points: ArrayLike, *, min_score: float = 0.55) -> MatchResult:
    """Search the whole submap at every angle (Cartographer's MatchFullSubmap): no prior needed."""
    nx, ny = stack.num_cells
    return match(stack, points, full_submap_center(stack),
                 linear_search_window=(nx + ny) * stack.resolution, angular_search_window=math.pi,
                 min_score=min_score)


def exhaustive_match(stack: PrecomputationGridStack, points: ArrayLike, initial_pose_estimate: Pose, *,
                     linear_search_window: float = 7.0, angular_search_window: float = math.radians(30.0),
                     min_score: float = 0.55) -> MatchResult:
    """Same candidates and preference order as :func:`match`, every one scored on level 0.

    The test oracle for the branch and bound, and its baseline in benchmarks;
    O(angles × window² × points), so keep windows small.
    """
    pts = _points(points)
    n = pts.shape[0]
    if n == 0:
        return _not_found(initial_pose_estimate)
    problem = _window_problem(stack, pts, initial_pose_estimate, linear_search_window, angular_search_window)
    found, a, x, y, s = _exhaustive(stack.data, stack.starts, stack.level_widths, stack.level_heights, stack.pads,
                                    problem.discrete, problem.bbox, problem.bounds, problem.angle_index, 0,
                                    _threshold(min_score, n))
    return _result(problem, stack, found, a, x, y, s, n)


@dataclass(frozen=True, slots=True)
class PeakSearch:
    """What :func:`peaks` looks for: the window (m, rad) around the estimate, the lowest score kept, the (window
    scale, level) stages, how many places, how far apart two places are, and at most ``tries`` coarse leaves
    (None: count + 2) scoring at least ``coarse_min_score`` (None: ``min_score``)."""

    linear_search_window: float
    angular_search_window: float
    min_score: float
    levels: Sequence[tuple[float, int]]
    count: int
    distinct_xy: float
    distinct_yaw: float
    tries: int | None = None
    coarse_min_score: float | None = None


def peaks(stack: PrecomputationGridStack, points: ArrayLike, initial_pose_estimate: Pose, *, search: PeakSearch,
          exclude: Sequence[np.ndarray] = (), jobs: int | None = 1) -> list[MatchResult]:
    """Up to ``search.count`` best poses of the window at *different places* (pairwise farther apart than
    ``distinct_xy`` or ``distinct_yaw``, and from every pose of ``exclude``), best first; none below ``min_score``.

    :func:`match_multilevel` bets on the best leaf of its first, coarse stage. Here that stage is repeated with
    the places already tried excluded (branch and bound that skips leaves in boxes around them), and each
    coarse leaf is searched coarse to fine in its own neighbourhood: at most ``tries`` leaves (default
    count + 2; on bench-dense/intel's map image 3 tries put 92 % of global queries right, 6 tries 97 % in twice
    the time), stopping once a coarse bound falls below the ``count``-th place found. A whole-map search
    so keeps its second place (the answer's rival, and the right answer when the best coarse block was not).
    ``jobs``: threads for each coarse stage (None: every core), the same answer for any number.
    """
    linear_search_window, angular_search_window = search.linear_search_window, search.angular_search_window
    min_score, count, tries, coarse_min_score = search.min_score, search.count, search.tries, search.coarse_min_score
    distinct_xy, distinct_yaw = search.distinct_xy, search.distinct_yaw
    levels = [(float(sc), int(lv)) for sc, lv in search.levels]
    if not levels or levels[-1][1] != 0:
        raise ValueError("the last level must be 0 (full resolution)")
    pts = _points(points)
    n = pts.shape[0]
    if n == 0 or count <= 0:
        return []
    res = stack.resolution
    step = angular_step(pts, res)
    max_a = _cells(angular_search_window, step)
    max_xy = _cells(linear_search_window, res)
    scale, lv = levels[0]
    lattice = 1 << lv
    half_a = _cells(scale * angular_search_window, step)
    half_xy = _cells(scale * linear_search_window, res)
    m = -(-half_a // lattice)
    angle_index = lattice * np.arange(-m, m + 1)
    angle_index = angle_index[np.abs(angle_index) <= max_a]
    problem = _prepare(stack, pts, initial_pose_estimate, step, angle_index,
                       (-min(half_xy, max_xy), min(half_xy, max_xy), -min(half_xy, max_xy), min(half_xy, max_xy)))
    thr = _threshold(min_score, n)
    coarse_thr = thr if coarse_min_score is None else _threshold(coarse_min_score, n)
    x0, y0, th0 = problem.estimate
    da = int(math.ceil(distinct_yaw / step))
    dxy = int(math.ceil(distinct_xy / res))

    def box(pose: np.ndarray) -> list[int]:
        a = int(round(float(wrap_angle(pose[2] - th0)) / step))
        x = int(round((pose[0] - x0) / res))
        y = int(round((pose[1] - y0) / res))
        return [a - da, a + da, x - dxy, x + dxy, y - dxy, y + dxy]

    def same_place(p: np.ndarray, q: np.ndarray) -> bool:
        return bool(math.hypot(p[0] - q[0], p[1] - q[1]) <= distinct_xy
                    and abs(float(wrap_angle(p[2] - q[2]))) <= distinct_yaw)

    avoid = [np.asarray(e, dtype=np.float64) for e in exclude]
    excl = [box(e) for e in avoid]
    rest = [(0.0, lvl) for _, lvl in levels[1:]] or [(0.0, 0)]
    found: list[MatchResult] = []
    limit = count + 2 if tries is None else int(tries)
    for _ in range(limit):
        ok, a, x, y, s = _run_bnb_split(stack, problem, stack.depth - 1, lv,
                                        thr if len(levels) == 1 else coarse_thr,
                                        np.array(excl, dtype=np.int64).reshape(-1, 6), jobs)
        if not ok:
            break
        if len(found) >= count and float(cell_value_to_probability(s / n)) <= found[-1].score:
            break  # a coarse leaf bounds every pose under it: nothing further down can enter the list
        centre = np.array([x0 + (x + lattice // 2) * res, y0 + (y + lattice // 2) * res, th0 + a * step])
        excl.append(box(centre))
        if len(levels) == 1:
            r = _result(problem, stack, ok, a, x, y, s, n)
        else:
            r = match_multilevel(stack, pts, centre, linear_search_window=1.5 * lattice * res,
                                 angular_search_window=1.5 * lattice * step, min_score=min_score,
                                 levels=[(1.0, rest[0][1])] + rest[1:])
        if not r.found or any(same_place(r.pose, q) for q in avoid):
            continue
        twin = [k for k, f in enumerate(found) if same_place(r.pose, f.pose)]
        if twin:
            if r.score > found[twin[0]].score:
                found[twin[0]] = r
        else:
            found.append(r)
        found.sort(key=lambda f: -f.score)
        del found[count:]
    return found


def default_levels(depth: int) -> tuple[tuple[float, int], ...]:
    """(window scale, level) stages of :func:`match_multilevel`: the whole window at 8-cell
    (0.4 m at 0.05 m) resolution, then full resolution around the best.

    Level 3 lost no query on the building benchmark; a further stage at level 2
    is faster still but sometimes settles on a neighbouring optimum.
    """
    return ((1.0, min(3, depth - 1)), (0.0, 0))


def match_multilevel(stack: PrecomputationGridStack, points: ArrayLike, initial_pose_estimate: Pose, *,
                     linear_search_window: float = 7.0, angular_search_window: float = math.radians(30.0),
                     min_score: float = 0.55, levels: Sequence[tuple[float, int]] | None = None,
                     coarse_min_score: float | None = None) -> MatchResult:
    """Coarse-to-fine search: the whole window on a coarse lattice, then shrinking windows around the best.

    Stage i searches ±``scale_i`` × the requested windows around the previous
    stage's best on a lattice of 2^``level_i`` cells and 2^``level_i`` angular
    steps, scoring candidates on precomputation level ``level_i`` (the block
    max, i.e. the map at 2^level_i times coarser resolution). A refining stage
    never looks narrower than 1.5 lattice steps of the stage before (a scale
    of 0 means just that), so it always reaches the neighbouring coarse
    candidates. Every stage's candidates are a subset of :func:`match`'s (same
    angles, same cell offsets, clipped to the same windows), so when the last
    stage's window holds the plain optimum the result is identical to
    :func:`match`; coarse stages keep only their best, so that is likely,
    not guaranteed (``bench/branch_and_bound.py`` measures how likely).

    Coarse stages reject at ``coarse_min_score`` (default ``min_score``): their
    block-max scores bound the fine ones at the same angle, but the fine
    optimum may sit between two coarse angles.
    """
    levels = [(float(sc), int(lv)) for sc, lv in (default_levels(stack.depth) if levels is None else levels)]
    if not levels or levels[-1][1] != 0:
        raise ValueError("the last level of a multilevel search must be 0 (full resolution)")
    for _, lv in levels:
        if not 0 <= lv < stack.depth:
            raise ValueError(f"level {lv} not in 0..{stack.depth - 1}")
    pts = _points(points)
    n = pts.shape[0]
    if n == 0:
        return _not_found(initial_pose_estimate)
    res = stack.resolution
    step = angular_step(pts, res)
    max_a = _cells(angular_search_window, step)
    max_xy = _cells(linear_search_window, res)
    thr = _threshold(min_score, n)
    coarse_thr = thr if coarse_min_score is None else _threshold(coarse_min_score, n)
    ca = cx = cy = 0  # current centre: angle index and cell offsets from the initial estimate
    prev_lattice = 0
    for i, (scale, lv) in enumerate(levels):
        lattice = 1 << lv
        half_a = _cells(scale * angular_search_window, step)
        half_xy = _cells(scale * linear_search_window, res)
        if i > 0:
            half_a = max(half_a, _cells(1.5 * prev_lattice, 1.0))
            half_xy = max(half_xy, _cells(1.5 * prev_lattice, 1.0))
        m = -(-half_a // lattice)
        angle_index = ca + lattice * np.arange(-m, m + 1)
        angle_index = angle_index[np.abs(angle_index) <= max_a]
        window = (max(cx - half_xy, -max_xy), min(cx + half_xy, max_xy),
                  max(cy - half_xy, -max_xy), min(cy + half_xy, max_xy))
        problem = _prepare(stack, pts, initial_pose_estimate, step, angle_index, window)
        last = i == len(levels) - 1
        found, a, x, y, s = _run_bnb(stack, problem, stack.depth - 1, lv, thr if last else coarse_thr)
        if not found:
            return _not_found(initial_pose_estimate)
        if last:
            return _result(problem, stack, found, a, x, y, s, n)
        # A coarse leaf stands for its whole block: the next stage centres on the block's middle.
        ca, cx, cy = int(a), int(x) + lattice // 2, int(y) + lattice // 2
        prev_lattice = lattice
    raise AssertionError("unreachable")


@register_warm_up
def warm_up() -> None:
    """The loop-closure search kernels (windowed, multilevel, whole-submap) on a toy room."""
    from carto_cli.grid.probability_grid import ProbabilityGrid

    grid = ProbabilityGrid(0.05, (0.0, 0.0), (40, 40))
    edge = np.arange(40)
    walls = np.concatenate([np.stack([edge, np.zeros_like(edge)], 1), np.stack([np.zeros_like(edge), edge], 1)])
    grid.set_probability(walls, 0.9)
    stack = PrecomputationGridStack(grid, 3)
    points = np.stack([np.linspace(0.1, 1.5, 20), np.full(20, -0.9)], 1)
    estimate = np.array([0.0, 1.0, 0.0])
    match(stack, points, estimate, linear_search_window=0.2, angular_search_window=0.1)
    match_multilevel(stack, points, estimate, linear_search_window=0.2, angular_search_window=0.1)
    match_full_submap(stack, points)
    peaks(stack, points, estimate, search=PeakSearch(0.5, 0.2, 0.1, ((1.0, 2), (0.0, 0)), count=2, distinct_xy=0.2,
                                                     distinct_yaw=0.1))
