"""Scan-to-map matching on a distance field: robust Gauss-Newton / Levenberg-Marquardt on point distances.

The matcher of LaMa-style online SLAM (IRIS LaMa's ``MatchSurface2D`` solved by its Gauss-Newton): one residual per
point, ``r_i = D(T(x) p_i)``, the bilinearly interpolated distance (m) from the transformed point to the nearest
obstacle of a :class:`~carto_cli.grid.distance_map.DistanceMap`. A Cauchy loss ``rho(r) = c^2/2 log(1 + r^2/c^2)``
keeps returns from things not in the map (people, doors, new walls) from pulling: they weigh
``w = 1 / (1 + r^2/c^2)`` in the normal equations (iteratively reweighted least squares). The cost minimised is
``sum rho(r_i)`` plus, when asked, a prior ``0.5 (w_t^2 |t - t_0|^2 + w_r^2 (theta - theta_0)^2)`` towards a
predicted pose (off by default: LaMa has none; it steadies long featureless corridors).

Solver: Gauss-Newton steps on the 3x3 normal equations (``J^T W J d = -J^T W r``), damped Levenberg-Marquardt
style (``+ lambda diag``) only after a step fails to lower the cost; stops when a step is below the tolerances
(``1e-4`` m and rad by default), when the damping grows past use, or after ``max_iterations``. Residuals and the
analytic Jacobian (chain rule through the interpolated gradient and the rotation) are accumulated in one numba
pass per evaluation.

The information matrix returned is the final ``J^T W J`` (with the prior's terms when one is used), in 1 / m^2 and
1 / rad^2 of the robust cost; its inverse is the covariance reported (as LaMa does, unscaled).

``match_multires`` runs the same solver on coarser maps first to widen the basin (a map at 4x the cell size and
the same number of cells of truncation sees 4x as far).
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any, NamedTuple

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from carto_cli.core.kernels import register_warm_up
from carto_cli.grid.distance_map import DistanceMap, distance_and_gradient
from carto_cli.matching.kernels import solve3

DEFAULT_LOSS_SCALE = 0.15  # m: LaMa's Slam2D Cauchy scale


class DistanceMatchResult(NamedTuple):
    pose: np.ndarray  # (3,) x y theta of the scan's frame in the map
    cost: float  # final robust cost (sum rho(r_i), plus the prior)
    initial_cost: float
    iterations: int  # steps tried (accepted or not)
    converged: bool  # a step fell below the tolerances before max_iterations
    information: np.ndarray  # (3, 3) J^T W J at the final pose
    covariance: np.ndarray  # (3, 3) its inverse (pseudo-inverse when singular)
    rms: float  # root mean square distance of the points at the final pose (m, unweighted)


@njit(cache=True, nogil=True)
def _evaluate(table, tx0, ty0, sqdist, lut, inv_res, points, x, y, th, inv_c2, c2, px0, py0, pth0, w_t, w_r,
              derivatives, h, g):
    """Robust cost at (x, y, th); fills the normal equations h (3x3) and gradient g (3,) when ``derivatives``.
    Returns (cost, sum of squared plain distances)."""
    c = math.cos(th)
    s = math.sin(th)
    total = 0.0
    plain = 0.0
    h00 = h01 = h02 = h11 = h12 = h22 = g0 = g1 = g2 = 0.0
    for i in range(points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        rx = c * px - s * py
        ry = s * px + c * py
        r, gx, gy = distance_and_gradient(table, tx0, ty0, sqdist, lut, inv_res, rx + x, ry + y)
        q = r * r * inv_c2
        total += 0.5 * c2 * math.log1p(q)
        plain += r * r
        if derivatives:
            w = 1.0 / (1.0 + q)
            j2 = gy * rx - gx * ry  # d/dth of the rotated point is (-ry, rx)
            wr = w * r
            h00 += w * gx * gx
            h01 += w * gx * gy
            h02 += w * gx * j2
            h11 += w * gy * gy
            h12 += w * gy * j2
            h22 += w * j2 * j2
            g0 += wr * gx
            g1 += wr * gy
            g2 += wr * j2
    dx = x - px0
    dy = y - py0
    dt = th - pth0
    total += 0.5 * (w_t * w_t * (dx * dx + dy * dy) + w_r * w_r * dt * dt)
    if derivatives:
        wt2 = w_t * w_t
        wr2 = w_r * w_r
        h[0, 0] = h00 + wt2
        h[1, 1] = h11 + wt2
        h[2, 2] = h22 + wr2
        h[0, 1] = h[1, 0] = h01
        h[0, 2] = h[2, 0] = h02
        h[1, 2] = h[2, 1] = h12
        g[0] = g0 + wt2 * dx
        g[1] = g1 + wt2 * dy
        g[2] = g2 + wr2 * dt
    return total, plain


@njit(cache=True, nogil=True)
def _solve(table, tx0, ty0, sqdist, lut, inv_res, points, x0, y0, th0, loss_scale, px0, py0, pth0, w_t, w_r,
           max_iterations, translation_tolerance, rotation_tolerance):
    c2 = loss_scale * loss_scale
    inv_c2 = 1.0 / c2
    pose = np.array([x0, y0, th0])
    h = np.zeros((3, 3))
    g = np.zeros(3)
    ht = np.zeros((3, 3))
    gt = np.zeros(3)
    a = np.empty((3, 3))
    b = np.empty(3)
    d = np.zeros(3)
    cost, plain = _evaluate(table, tx0, ty0, sqdist, lut, inv_res, points, x0, y0, th0, inv_c2, c2, px0, py0, pth0,
                            w_t, w_r, True, h, g)
    initial_cost = cost
    lam = 0.0  # Gauss-Newton until a step fails
    iterations = 0
    converged = False
    while iterations < max_iterations:
        for k in range(3):
            for m in range(3):
                a[k, m] = h[k, m]
            a[k, k] += lam * (h[k, k] + 1e-9)
            b[k] = -g[k]
        if not solve3(a, b, d):
            if lam == 0.0:
                lam = 1e-3
                continue
            break
        iterations += 1
        small = abs(d[0]) < translation_tolerance and abs(d[1]) < translation_tolerance \
            and abs(d[2]) < rotation_tolerance
        trial_cost, trial_plain = _evaluate(table, tx0, ty0, sqdist, lut, inv_res, points, pose[0] + d[0],
                                            pose[1] + d[1], pose[2] + d[2], inv_c2, c2, px0, py0, pth0, w_t, w_r,
                                            True, ht, gt)
        if trial_cost <= cost:
            for k in range(3):
                pose[k] += d[k]
                g[k] = gt[k]
                for m in range(3):
                    h[k, m] = ht[k, m]
            cost = trial_cost
            plain = trial_plain
            lam = 0.0 if lam <= 1e-3 else lam * 0.1
            if small:
                converged = True
                break
        else:
            if small:  # the tolerance is reached either way
                converged = True
                break
            lam = 1e-3 if lam == 0.0 else lam * 10.0
            if lam > 1e6:
                break
    return pose, cost, initial_cost, iterations, converged, h, plain


def _covariance(information: np.ndarray) -> np.ndarray:
    try:
        return np.linalg.inv(information)
    except np.linalg.LinAlgError:
        return np.linalg.pinv(information)


def match(dmap: DistanceMap, points: ArrayLike, initial_pose: ArrayLike, *, loss_scale: float = DEFAULT_LOSS_SCALE,
          prior_pose: ArrayLike | None = None, translation_weight: float = 0.0, rotation_weight: float = 0.0,
          max_iterations: int = 100, translation_tolerance: float = 1e-4,
          rotation_tolerance: float = 1e-4) -> DistanceMatchResult:
    """Refine ``initial_pose`` (x, y, theta) so that ``points`` (n, 2, in the scan's frame) fall on obstacles of
    ``dmap``. ``prior_pose`` (default: the initial pose) with ``translation_weight`` / ``rotation_weight``
    (1 / m, 1 / rad; 0: no prior) holds the estimate towards a prediction."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    x0 = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    p0 = x0 if prior_pose is None else np.asarray(prior_pose, dtype=np.float64).reshape(3)
    ox, oy = dmap.tile_origin
    pose, cost, initial_cost, iterations, converged, h, plain = _solve(
        dmap.table, ox, oy, dmap.sqdist, dmap.lut, 1.0 / dmap.resolution, pts, x0[0], x0[1], x0[2],
        float(loss_scale), p0[0], p0[1], p0[2], float(translation_weight), float(rotation_weight),
        int(max_iterations), float(translation_tolerance), float(rotation_tolerance))
    rms = math.sqrt(plain / pts.shape[0]) if pts.shape[0] else 0.0
    return DistanceMatchResult(pose, float(cost), float(initial_cost), int(iterations), bool(converged), h,
                               _covariance(h), rms)


def match_multires(dmaps: Iterable[DistanceMap], points: ArrayLike, initial_pose: ArrayLike,
                   **kwargs: Any) -> DistanceMatchResult:
    """``match`` on each map of ``dmaps`` in turn (coarsest first), each starting where the previous ended;
    the result of the last (finest), with the iterations of all."""
    pose = np.asarray(initial_pose, dtype=np.float64).reshape(3)
    iterations = 0
    result = None
    for dmap in dmaps:
        result = match(dmap, points, pose, **kwargs)
        pose = result.pose
        iterations += result.iterations
    if result is None:
        raise ValueError("match_multires needs at least one map")
    return result._replace(iterations=iterations)


def evaluate(dmap: DistanceMap, points: ArrayLike, pose: ArrayLike, *, loss_scale: float = DEFAULT_LOSS_SCALE,
             prior_pose: ArrayLike | None = None, translation_weight: float = 0.0,
             rotation_weight: float = 0.0) -> tuple[float, np.ndarray, np.ndarray]:
    """(cost, J^T W J, J^T W r) at ``pose``: the quantities the solver uses, for tests."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    x = np.asarray(pose, dtype=np.float64).reshape(3)
    p0 = x if prior_pose is None else np.asarray(prior_pose, dtype=np.float64).reshape(3)
    h = np.zeros((3, 3))
    g = np.zeros(3)
    ox, oy = dmap.tile_origin
    c2 = float(loss_scale) ** 2
    cost, _ = _evaluate(dmap.table, ox, oy, dmap.sqdist, dmap.lut, 1.0 / dmap.resolution, pts, x[0], x[1], x[2],
                        1.0 / c2, c2, p0[0], p0[1], p0[2], float(translation_weight), float(rotation_weight), True,
                        h, g)
    return float(cost), h, g


@register_warm_up(system="scan-to-map")
def warm_up() -> None:
    """The solver and its evaluation on a toy map."""
    dm = DistanceMap(0.05, 0.3, capacity=4)
    angles = np.linspace(-3.0, 3.0, 48)
    ends = np.stack([2.0 * np.cos(angles), 1.5 * np.sin(angles)], axis=1)
    dm.insert((0.0, 0.0), ends)
    match(dm, ends, (0.02, -0.01, 0.01), translation_weight=1.0, rotation_weight=1.0)
    evaluate(dm, ends, (0.0, 0.0, 0.0))
