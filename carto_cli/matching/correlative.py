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

from carto_cli.core.transform import wrap_angle_scalar
from carto_cli.grid.probability_grid import VALUE_TO_PROBABILITY
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


def search_parameters(points, resolution: float, linear_search_window: float,
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


def match(grid, points, initial_pose, *, linear_search_window: float = 0.1,
          angular_search_window: float = math.radians(20.0), translation_delta_cost_weight: float = 1e-1,
          rotation_delta_cost_weight: float = 1e-1, unknown_probability: float | None = None) -> CorrelativeResult:
    """Best pose within ±``linear_search_window`` × ±``angular_search_window`` of ``initial_pose``.

    ``points`` are in the tracking frame; candidates step by one cell in x and
    y and by the angular step of :func:`search_parameters` in theta. ``unknown_probability`` replaces
    Cartographer's 0.1 for never-observed cells (None keeps it).
    """
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    x0, y0, th0 = (float(v) for v in np.asarray(initial_pose, dtype=np.float64))
    params = search_parameters(pts, grid.resolution, linear_search_window, angular_search_window)
    num_angular = params.num_angular_perturbations
    angles = th0 + np.arange(-num_angular, num_angular + 1) * params.angular_step
    discrete = discretize(pts, angles, x0, y0, grid.origin[0], grid.origin[1], 1.0 / grid.resolution)
    table = VALUE_TO_PROBABILITY if unknown_probability is None else _score_table(float(unknown_probability))
    k, dx, dy, score = _search(grid.cells, table, discrete, params.num_linear_perturbations,
                               params.num_angular_perturbations, params.angular_step, grid.resolution,
                               float(translation_delta_cost_weight), float(rotation_delta_cost_weight))
    dtheta = (k - params.num_angular_perturbations) * params.angular_step
    pose = np.array([x0 + dx * grid.resolution, y0 + dy * grid.resolution, wrap_angle_scalar(th0 + dtheta)])
    return CorrelativeResult(pose, float(score))
