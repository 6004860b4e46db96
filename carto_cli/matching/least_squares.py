"""Ceres-style least-squares scan matcher: refine a pose against a probability grid.

Residuals, as in Cartographer's CeresScanMatcher2D:

* one per point: ``occupied_space_weight / sqrt(N) * C(T(pose) p_i)`` with C
  the bicubic correspondence cost (1 - p) of the grid;
* two for translation: ``translation_weight * (t - t_target)``, where
  ``t_target`` is the *predicted* translation (not the CSM result) so the
  CSM cannot drag the estimate away unopposed;
* one for rotation: ``rotation_weight * (theta - theta_initial)``.

Minimised with Levenberg-Marquardt (Ceres' trust-region update rules) on the
3x3 normal equations; residuals and the analytic Jacobian (chain rule through
the bicubic gradient and the rotation) are accumulated in one numba pass.
Cost is reported as Ceres does: 0.5 * sum of squared residuals.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from carto_cli.core.transform import wrap_angle_scalar
from carto_cli.grid.probability_grid import VALUE_TO_CORRESPONDENCE_COST, ProbabilityGrid
from carto_cli.matching.interpolation import cost_and_gradient
from carto_cli.matching.kernels import solve3
from carto_cli.options.schema import ConstraintCeresScanMatcher, LocalCeresScanMatcher
from carto_cli.sensor.range_filter import Pose


class LeastSquaresResult(NamedTuple):
    pose: np.ndarray  # (3,)
    cost: float  # final 0.5 * sum r^2
    iterations: int  # LM steps tried (accepted or not)
    converged: bool  # a tolerance was met before max_num_iterations
    initial_cost: float


@dataclass(frozen=True, slots=True)
class CeresScanMatcher:
    """The matcher with one component's weights and iteration limit (Cartographer's CeresScanMatcher2D), built once
    from that component's options section (local SLAM's, the constraint builder's) rather than unpacked at each
    call."""

    occupied_space_weight: float
    translation_weight: float
    rotation_weight: float
    max_num_iterations: int

    @classmethod
    def from_options(cls, options: LocalCeresScanMatcher | ConstraintCeresScanMatcher) -> CeresScanMatcher:
        """``options``: a ``ceres_scan_matcher`` section (``carto_cli.options`` Local/ConstraintCeresScanMatcher)."""
        return cls(float(options.occupied_space_weight), float(options.translation_weight),
                   float(options.rotation_weight), int(options.ceres_solver_options.max_num_iterations))

    def match(self, grid: ProbabilityGrid, points: ArrayLike, initial_pose: ArrayLike,
              target_translation: Pose | None = None) -> LeastSquaresResult:
        """:func:`match` with these weights: ``points`` refined from ``initial_pose``, the translation pulled
        towards ``target_translation`` (default: the initial pose's)."""
        return match(grid, points, initial_pose, target_translation, occupied_space_weight=self.occupied_space_weight,
                     translation_weight=self.translation_weight, rotation_weight=self.rotation_weight,
                     max_num_iterations=self.max_num_iterations)


@njit(cache=True, nogil=True)
def _evaluate(cells, table, ox, oy, inv_res, points, x, y, th, tx, ty, th0, s_occ, w_t, w_r,
              derivatives, h, g):
    c = np.cos(th)
    s = np.sin(th)
    total = 0.0
    # Scalars, not h/g elements, in the hot loop: LLVM cannot keep array elements in registers.
    h00 = h01 = h02 = h11 = h12 = h22 = g0 = g1 = g2 = 0.0
    for i in range(points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        f, gx, gy = cost_and_gradient(cells, table, ox, oy, inv_res, c * px - s * py + x, s * px + c * py + y)
        r = s_occ * f
        total += r * r
        if derivatives:
            j0 = s_occ * gx
            j1 = s_occ * gy
            j2 = s_occ * (gx * (-s * px - c * py) + gy * (c * px - s * py))
            h00 += j0 * j0
            h01 += j0 * j1
            h02 += j0 * j2
            h11 += j1 * j1
            h12 += j1 * j2
            h22 += j2 * j2
            g0 += j0 * r
            g1 += j1 * r
            g2 += j2 * r
    rx = w_t * (x - tx)
    ry = w_t * (y - ty)
    rt = w_r * (th - th0)
    total += rx * rx + ry * ry + rt * rt
    if derivatives:
        h[0, 0] = h00 + w_t * w_t
        h[1, 1] = h11 + w_t * w_t
        h[2, 2] = h22 + w_r * w_r
        h[0, 1] = h[1, 0] = h01
        h[0, 2] = h[2, 0] = h02
        h[1, 2] = h[2, 1] = h12
        g[0] = g0 + w_t * rx
        g[1] = g1 + w_t * ry
        g[2] = g2 + w_r * rt
    return 0.5 * total


@njit(cache=True, nogil=True)
def _levenberg_marquardt(cells, table, ox, oy, inv_res, points, x0, y0, th_init, tx, ty, s_occ, w_t, w_r,
                         max_iterations, function_tolerance, gradient_tolerance, parameter_tolerance):
    pose = np.array([x0, y0, th_init])
    trial = pose.copy()
    h = np.zeros((3, 3))
    g = np.zeros(3)
    h_trial = np.zeros((3, 3))
    g_trial = np.zeros(3)
    a = np.empty((3, 3))
    delta = np.zeros(3)
    minus_g = np.zeros(3)
    cost = 0.0
    initial_cost = 0.0
    model_reduction = 0.0
    radius = 1e4  # Ceres' initial_trust_region_radius
    decrease_factor = 2.0
    iterations = 0
    converged = False
    # Every trial is evaluated with derivatives, so an accepted step needs no second evaluation.
    while True:
        trial_cost = _evaluate(cells, table, ox, oy, inv_res, points, trial[0], trial[1], trial[2], tx, ty,
                               th_init, s_occ, w_t, w_r, True, h_trial, g_trial)
        if iterations == 0:
            accept = True
            initial_cost = trial_cost
            relative_decrease = 1.0
        else:
            rho = (cost - trial_cost) / model_reduction if model_reduction > 0.0 else -1.0
            accept = rho > 1e-3
            relative_decrease = (cost - trial_cost) / cost if cost > 0.0 else 0.0
            if accept:
                radius = min(radius / max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3), 1e16)
                decrease_factor = 2.0
            else:
                radius /= decrease_factor
                decrease_factor *= 2.0
        if accept:
            for k in range(3):
                pose[k] = trial[k]
                g[k] = g_trial[k]
                for m in range(3):
                    h[k, m] = h_trial[k, m]
            cost = trial_cost
            if iterations > 0 and relative_decrease <= function_tolerance:
                converged = True
                break
        if max(abs(g[0]), abs(g[1]), abs(g[2])) <= gradient_tolerance:
            converged = True
            break
        if iterations >= max_iterations or radius < 1e-32:
            break
        # Scalar loops instead of array expressions: numba compiles those slowly.
        for k in range(3):
            for m in range(3):
                a[k, m] = h[k, m]
            a[k, k] += min(max(h[k, k], 1e-6), 1e32) / radius
            minus_g[k] = -g[k]
        solve3(a, minus_g, delta)  # damped normal equations: positive definite, never singular
        iterations += 1
        step_norm = math.sqrt(delta[0] ** 2 + delta[1] ** 2 + delta[2] ** 2)
        pose_norm = math.sqrt(pose[0] ** 2 + pose[1] ** 2 + pose[2] ** 2)
        if step_norm <= parameter_tolerance * (pose_norm + parameter_tolerance):
            converged = True
            break
        hd0 = h[0, 0] * delta[0] + h[0, 1] * delta[1] + h[0, 2] * delta[2]
        hd1 = h[1, 0] * delta[0] + h[1, 1] * delta[1] + h[1, 2] * delta[2]
        hd2 = h[2, 0] * delta[0] + h[2, 1] * delta[1] + h[2, 2] * delta[2]
        model_reduction = -(g[0] * delta[0] + g[1] * delta[1] + g[2] * delta[2]) \
            - 0.5 * (delta[0] * hd0 + delta[1] * hd1 + delta[2] * hd2)
        for k in range(3):
            trial[k] = pose[k] + delta[k]
    return pose, cost, iterations, converged, initial_cost


def match(grid: ProbabilityGrid, points: ArrayLike, initial_pose: ArrayLike, target_translation: Pose | None = None,
          *, occupied_space_weight: float = 1.0,
          translation_weight: float = 10.0, rotation_weight: float = 40.0, max_num_iterations: int = 20,
          function_tolerance: float = 1e-6, gradient_tolerance: float = 1e-10,
          parameter_tolerance: float = 1e-8) -> LeastSquaresResult:
    """Refine ``initial_pose`` so ``points`` (tracking frame) fall on occupied cells of ``grid``.

    ``target_translation`` is the predicted (x, y) the translation residual
    pulls towards; it defaults to the initial pose's translation.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    x0, y0, th0 = (float(v) for v in np.asarray(initial_pose, dtype=np.float64))
    tx, ty = (x0, y0) if target_translation is None else (float(v) for v in target_translation)
    s_occ = occupied_space_weight / math.sqrt(pts.shape[0]) if pts.shape[0] else 0.0
    pose, cost, iterations, converged, initial_cost = _levenberg_marquardt(
        grid.cells, VALUE_TO_CORRESPONDENCE_COST, grid.origin[0], grid.origin[1], 1.0 / grid.resolution, pts,
        x0, y0, th0, tx, ty, s_occ, float(translation_weight), float(rotation_weight), int(max_num_iterations),
        float(function_tolerance), float(gradient_tolerance), float(parameter_tolerance))
    pose[2] = wrap_angle_scalar(pose[2])
    return LeastSquaresResult(pose, float(cost), int(iterations), bool(converged), float(initial_cost))


def evaluate(grid: ProbabilityGrid, points: ArrayLike, pose: ArrayLike, target_translation: Pose | None = None,
             initial_angle: float | None = None, *, occupied_space_weight: float = 1.0,
             translation_weight: float = 10.0,
             rotation_weight: float = 40.0) -> tuple[float, np.ndarray, np.ndarray]:
    """(cost, J^T J, J^T r) at ``pose``: the quantities the solver works with (for tests and diagnostics)."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    pose = np.asarray(pose, dtype=np.float64)
    tx, ty = (pose[0], pose[1]) if target_translation is None else target_translation
    th0 = pose[2] if initial_angle is None else initial_angle
    s_occ = occupied_space_weight / math.sqrt(pts.shape[0]) if pts.shape[0] else 0.0
    h = np.zeros((3, 3))
    g = np.zeros(3)
    cost = _evaluate(grid.cells, VALUE_TO_CORRESPONDENCE_COST, grid.origin[0], grid.origin[1], 1.0 / grid.resolution,
                     pts, float(pose[0]), float(pose[1]), float(pose[2]), float(tx), float(ty), float(th0), s_occ,
                     float(translation_weight), float(rotation_weight), True, h, g)
    return float(cost), h, g


def covariance(grid: ProbabilityGrid, points: ArrayLike, pose: ArrayLike, *, min_sigma_xy: float = 0.0,
               min_sigma_yaw: float = 0.0, max_sigma_xy: float = 10.0, max_sigma_yaw: float = math.pi) -> np.ndarray:
    """3x3 covariance of ``pose`` (x, y, yaw) from the scan's residuals alone (no prior terms).

    Gauss-Newton's: every point's cost residual an independent measurement whose variance is the residuals'
    own (sum r^2 / (n - 3)), so cov = sigma^2 (J^T J)^-1. Where the map constrains nothing (along a featureless
    corridor) J^T J has no information in that direction; ``max_sigma_*`` enter as a weak prior so the result
    stays finite there (and says "that far, or more"), and ``min_sigma_*`` (e.g. half a cell) are added as the
    grid's own quantisation, which the residuals cannot see.
    """
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    n = pts.shape[0]
    info = np.diag([1.0 / max_sigma_xy ** 2, 1.0 / max_sigma_xy ** 2, 1.0 / max_sigma_yaw ** 2])
    if n > 3:
        cost, h, _ = evaluate(grid, pts, pose, translation_weight=0.0, rotation_weight=0.0)
        # With s_occ = 1/sqrt(n): h = (1/n) sum j j^T and cost = (1/2n) sum f^2.
        sigma2 = max(2.0 * cost * n / (n - 3), 1e-12)
        info = info + n * h / sigma2
    cov = np.linalg.inv(info)
    cov[0, 0] += min_sigma_xy ** 2
    cov[1, 1] += min_sigma_xy ** 2
    cov[2, 2] += min_sigma_yaw ** 2
    return 0.5 * (cov + cov.T)
