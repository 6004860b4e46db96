"""Real-time correlative scan matcher: exhaustive search in a small pose window.

The scan is rotated once per candidate angle (the angular step chosen so the
farthest point moves by at most one cell per step), discretised to cell
indices once per angle, and every translation candidate is then a pure integer
offset: scoring is additions of table lookups, no trigonometry. The score is
the mean probability under the points (unknown and outside cells count as
0.1, Cartographer's GetProbability), damped by how far the candidate is from
the initial estimate so that in ambiguous places the prediction wins.

The damping is Cartographer's exactly: ``score · exp(−(w_t·|Δt| + w_r·|Δθ|)²)``
with |Δt| the candidate's translation (m) and |Δθ| its rotation (rad) from the
initial estimate. The weights keep Cartographer's names and defaults, so a
value copied from a Lua configuration must mean the same thing here; a
quadratic-per-term form would turn, e.g., ``translation_delta_cost_weight = 10``
from a strong preference for the prediction into a mild one.
"""
from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from carto_cli.core.transform import wrap_angle_scalar
from carto_cli.grid.probability_grid import VALUE_TO_PROBABILITY, ProbabilityGrid
from carto_cli.matching.kernels import discretize


class CorrelativeResult(NamedTuple):
    pose: np.ndarray  # (3,)
    score: float


class SearchParameters(NamedTuple):
    num_linear_perturbations: int  # candidates span -n..n cells in x and in y
    angular_step: float
    num_angular_perturbations: int  # candidates span -n..n angular steps

    @property
    def num_candidates(self) -> int:
        return (2 * self.num_linear_perturbations + 1) ** 2 * (2 * self.num_angular_perturbations + 1)


def search_parameters(points: ArrayLike, resolution: float, linear_search_window: float,
                      angular_search_window: float) -> SearchParameters:
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    # At least a few cells, so acos stays defined for tiny or empty scans.
    max_range = max(3.0 * resolution, float(np.sqrt((pts ** 2).sum(axis=1)).max()) if len(pts) else 0.0)
    step = (1.0 - 1e-3) * math.acos(1.0 - resolution ** 2 / (2.0 * max_range ** 2))
    return SearchParameters(
        int(math.ceil(linear_search_window / resolution - 1e-9)),
        step,
        int(math.ceil(angular_search_window / step)),
    )


@functools.lru_cache(maxsize=4)
def _score_table(unknown_probability: float) -> np.ndarray:
    table = VALUE_TO_PROBABILITY.copy()
    table[0] = unknown_probability
    table.flags.writeable = False
    return table


@njit(cache=True, nogil=True)
def _search(grid_cells, table, discrete, num_linear, num_angular, angular_step, resolution,
            translation_weight, rotation_weight):
    ny, nx = grid_cells.shape
    num_scans = discrete.shape[0]
    n = discrete.shape[1]
    w = 2 * num_linear + 1
    unknown = table[0]
    sums = np.empty((w, w))
    best_score = -1.0
    best_k = num_angular
    best_dx = 0
    best_dy = 0
    for k in range(num_scans):
        sums[:, :] = 0.0
        for i in range(n):
            x0 = discrete[k, i, 0] - num_linear
            y0 = discrete[k, i, 1] - num_linear
            if x0 >= 0 and y0 >= 0 and x0 + w <= nx and y0 + w <= ny:
                for b in range(w):
                    for a in range(w):
                        sums[a, b] += table[grid_cells[y0 + b, x0 + a]]
            else:
                for b in range(w):
                    iy = y0 + b
                    for a in range(w):
                        ix = x0 + a
                        if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
                            sums[a, b] += unknown
                        else:
                            sums[a, b] += table[grid_cells[iy, ix]]
        rotation_cost = rotation_weight * abs((k - num_angular) * angular_step)
        for a in range(w):
            for b in range(w):
                dx = (a - num_linear) * resolution
                dy = (b - num_linear) * resolution
                score = sums[a, b] / n if n > 0 else 0.0
                cost = translation_weight * np.sqrt(dx * dx + dy * dy) + rotation_cost
                score *= np.exp(-cost * cost)
                if score > best_score:
                    best_score = score
                    best_k = k
                    best_dx = a - num_linear
                    best_dy = b - num_linear
    return best_k, best_dx, best_dy, best_score


def match(grid: ProbabilityGrid, points: ArrayLike, initial_pose: ArrayLike, *, linear_search_window: float = 0.1,
          angular_search_window: float = math.radians(20.0), translation_delta_cost_weight: float = 1e-1,
          rotation_delta_cost_weight: float = 1e-1, unknown_probability: float | None = None) -> CorrelativeResult:
    """Best pose within ±``linear_search_window`` × ±``angular_search_window`` of ``initial_pose``.

    ``points`` are in the tracking frame; candidates step by one cell in x and
    y and by the angular step of :func:`search_parameters` in theta. ``unknown_probability`` replaces
    Cartographer's 0.1 for never-observed cells (None keeps it).
    """
    params, discrete = _candidates(grid, points, initial_pose, linear_search_window, angular_search_window)
    table = VALUE_TO_PROBABILITY if unknown_probability is None else _score_table(float(unknown_probability))
    found = _search(grid.cells, table, discrete, params.num_linear_perturbations, params.num_angular_perturbations,
                    params.angular_step, grid.resolution, float(translation_delta_cost_weight),
                    float(rotation_delta_cost_weight))
    return _result(grid, initial_pose, params, *found)


def _candidates(grid: ProbabilityGrid, points: ArrayLike, initial_pose: ArrayLike, linear_search_window: float,
                angular_search_window: float) -> tuple[SearchParameters, np.ndarray]:
    """The search's parameters and the scan's cells at every candidate angle (``discretize``)."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    x0, y0, th0 = (float(v) for v in np.asarray(initial_pose, dtype=np.float64))
    params = search_parameters(pts, grid.resolution, linear_search_window, angular_search_window)
    num_angular = params.num_angular_perturbations
    angles = th0 + np.arange(-num_angular, num_angular + 1) * params.angular_step
    return params, discretize(pts, angles, x0, y0, grid.origin[0], grid.origin[1], 1.0 / grid.resolution)


def _result(grid: ProbabilityGrid, initial_pose: ArrayLike, params: SearchParameters, k: int, dx: int, dy: int,
            score: float) -> CorrelativeResult:
    """The pose of candidate (angle ``k``, offset ``dx``, ``dy`` cells) and its score."""
    x0, y0, th0 = (float(v) for v in np.asarray(initial_pose, dtype=np.float64))
    dtheta = (k - params.num_angular_perturbations) * params.angular_step
    pose = np.array([x0 + dx * grid.resolution, y0 + dy * grid.resolution, wrap_angle_scalar(th0 + dtheta)])
    return CorrelativeResult(pose, float(score))


# --------------------------------------------------------------------------- pruned search

class CoarseGrid(NamedTuple):
    """A grid's probabilities (unknown and outside as ``unknown``) and their maximum over every 2 x 2 block of
    cells: for many searches in one grid, built once (:func:`coarse_grid`)."""

    probabilities: np.ndarray  # (ny + 2, nx + 2) float64, a ring of unknown cells around the grid
    block_max: np.ndarray  # (ny + 1, nx + 1): [y, x] = max of probabilities[y:y + 2, x:x + 2]
    # block_max's even and odd columns apart: a search steps two columns at a time, and contiguous memory
    # lets the compiler vectorize the sums
    block_max_by_parity: np.ndarray  # (2, ny + 1, nx // 2 + 1): [q, y, c] = block_max[y, 2 c + q]
    unknown: float


def coarse_grid(grid: ProbabilityGrid, unknown_probability: float | None = None) -> CoarseGrid:
    """``grid``'s :class:`CoarseGrid`, never-observed cells scored as ``unknown_probability`` (None: 0.1)."""
    table = VALUE_TO_PROBABILITY if unknown_probability is None else _score_table(float(unknown_probability))
    probabilities, block_max, by_parity = _coarse(grid.cells, table)
    return CoarseGrid(probabilities, block_max, by_parity, float(table[0]))


@njit(cache=True, nogil=True)
def _coarse(cells, table):
    ny, nx = cells.shape
    p = np.full((ny + 2, nx + 2), table[0])
    for y in range(ny):
        for x in range(nx):
            p[y + 1, x + 1] = table[cells[y, x]]
    m = np.empty((ny + 1, nx + 1))
    for y in range(ny + 1):
        for x in range(nx + 1):
            m[y, x] = max(max(p[y, x], p[y, x + 1]), max(p[y + 1, x], p[y + 1, x + 1]))
    half = nx // 2 + 1
    by_parity = np.full((2, ny + 1, half), table[0])
    for y in range(ny + 1):
        for x in range(nx + 1):
            by_parity[x % 2, y, x // 2] = m[y, x]
    return p, m, by_parity


def match_pruned(grid: ProbabilityGrid, coarse: CoarseGrid, points: ArrayLike, initial_pose: ArrayLike, *,
                 linear_search_window: float, angular_search_window: float, translation_delta_cost_weight: float = 1e-1,
                 rotation_delta_cost_weight: float = 1e-1) -> CorrelativeResult:
    """:func:`match`'s answer (the same pose and score, bit for bit), found by scoring 2 x 2 blocks of
    translations first with each point's best cell in the block, then in full the block with the best bound
    and every block whose bound can still beat the best candidate so far. ``coarse``: :func:`coarse_grid` of
    ``grid`` (with the unknown probability :func:`match` would use). Worth it from windows of about ten cells,
    for many searches in one grid."""
    params, discrete = _candidates(grid, points, initial_pose, linear_search_window, angular_search_window)
    found = _search_pruned(coarse.probabilities, coarse.block_max, coarse.block_max_by_parity, coarse.unknown,
                           discrete, params.num_linear_perturbations, params.num_angular_perturbations,
                           params.angular_step, grid.resolution, float(translation_delta_cost_weight),
                           float(rotation_delta_cost_weight))
    return _result(grid, initial_pose, params, *found)


@njit(cache=True, nogil=True)
def _search_pruned(p, block_max, by_parity, unknown, discrete, num_linear, num_angular, angular_step, resolution,
                   translation_weight, rotation_weight):
    # p has a ring of unknown cells: cell (x, y) of the grid is p[y + 1, x + 1]; block_max[y + 1, x + 1] is the
    # best of cells x..x+1, y..y+1.
    py, px = p.shape
    num_scans = discrete.shape[0]
    n = discrete.shape[1]
    w = 2 * num_linear + 1
    wb = (w + 1) // 2  # blocks per axis; the last one is half outside the window when w is odd
    bounds = np.zeros((num_scans, wb, wb))  # [angle, block row (y), block column (x)]
    last = 2 * (wb - 1)
    for k in range(num_scans):
        for i in range(n):
            bx = discrete[k, i, 0] - num_linear + 1
            by = discrete[k, i, 1] - num_linear + 1
            if bx >= 0 and by >= 0 and bx + last <= px - 2 and by + last <= py - 2:
                half = by_parity[bx % 2]
                c0 = bx // 2
                for bb in range(wb):
                    row = half[by + 2 * bb]
                    out = bounds[k, bb]
                    for ba in range(wb):
                        out[ba] += row[c0 + ba]
                continue
            for bb in range(wb):
                iy = by + 2 * bb
                for ba in range(wb):
                    ix = bx + 2 * ba
                    if ix < -1 or iy < -1 or ix >= px or iy >= py:  # the whole block outside the ring
                        bounds[k, bb, ba] += unknown
                    elif ix < 0 or iy < 0 or ix >= px - 1 or iy >= py - 1:
                        bounds[k, bb, ba] += _block_max_edge(p, ix, iy, unknown)
                    else:
                        bounds[k, bb, ba] += block_max[iy, ix]
    # Each block's bound: its points' best, damped as little as its candidate nearest the start is
    flat = bounds.ravel().copy()
    for j in range(flat.shape[0]):
        k = j // (wb * wb)
        bb = (j // wb) % wb
        ba = j % wb
        rotation_cost = rotation_weight * abs((k - num_angular) * angular_step)
        da = _nearest_offset(2 * ba - num_linear, w - 1 - num_linear)
        db = _nearest_offset(2 * bb - num_linear, w - 1 - num_linear)
        dx = da * resolution
        dy = db * resolution
        cost = translation_weight * np.sqrt(dx * dx + dy * dy) + rotation_cost
        flat[j] = (flat[j] / n if n > 0 else 0.0) * np.exp(-cost * cost)
    best = np.array([-1.0, 1 << 62, num_angular, num_linear, num_linear])  # score, rank, angle, x, y
    # The block with the best bound first (its score is usually near the best), then every block whose bound
    # can still reach the best score so far: no sort, the same answer
    _score_block(p, unknown, discrete, num_linear, w, wb, int(np.argmax(flat)), angular_step, num_angular,
                 resolution, translation_weight, rotation_weight, best)
    for j in range(flat.shape[0]):
        if flat[j] >= best[0]:
            _score_block(p, unknown, discrete, num_linear, w, wb, j, angular_step, num_angular, resolution,
                         translation_weight, rotation_weight, best)
    best_score = best[0]
    best_k = int(best[2])
    best_a = int(best[3])
    best_b = int(best[4])
    return best_k, best_a - num_linear, best_b - num_linear, best_score


@njit(cache=True, nogil=True)
def _score_block(p, unknown, discrete, num_linear, w, wb, j, angular_step, num_angular, resolution,
                 translation_weight, rotation_weight, best):
    """Score block ``j``'s candidates as :func:`_search` does, keeping the best in ``best`` (score, rank in the
    exhaustive search's (angle, x, y) order, angle, x, y: on a tie the exhaustive search keeps the first)."""
    py, px = p.shape
    n = discrete.shape[1]
    k = j // (wb * wb)
    bb = (j // wb) % wb
    ba = j % wb
    rotation_cost = rotation_weight * abs((k - num_angular) * angular_step)
    for a in range(2 * ba, min(2 * ba + 2, w)):
        for b in range(2 * bb, min(2 * bb + 2, w)):
            s = 0.0
            for i in range(n):
                ix = discrete[k, i, 0] - num_linear + a + 1
                iy = discrete[k, i, 1] - num_linear + b + 1
                if ix < 0 or iy < 0 or ix >= px or iy >= py:
                    s += unknown
                else:
                    s += p[iy, ix]
            dx = (a - num_linear) * resolution
            dy = (b - num_linear) * resolution
            score = s / n if n > 0 else 0.0
            cost = translation_weight * np.sqrt(dx * dx + dy * dy) + rotation_cost
            score *= np.exp(-cost * cost)
            rank = (k * w + a) * w + b
            if score > best[0] or (score == best[0] and rank < best[1]):
                best[0] = score
                best[1] = rank
                best[2] = k
                best[3] = a
                best[4] = b


@njit(cache=True, nogil=True)
def _block_max_edge(p, ix, iy, unknown):
    """The best of the 2 x 2 cells of p from (ix, iy), cells outside p counting as unknown."""
    py, px = p.shape
    best = unknown
    for y in range(iy, iy + 2):
        for x in range(ix, ix + 2):
            if 0 <= x < px and 0 <= y < py:
                best = max(best, p[y, x])
    return best


@njit(cache=True, nogil=True)
def _nearest_offset(lo, last):
    """Of the block's offsets lo, lo + 1 (not beyond ``last``), the one nearest zero."""
    if lo >= 0:
        return lo
    if lo + 1 <= last and lo + 1 <= 0:
        return lo + 1
    return lo
