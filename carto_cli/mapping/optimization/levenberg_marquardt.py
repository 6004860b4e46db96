"""The solver: Ceres' Levenberg–Marquardt over the pose graph, with its termination rules.

Same trust-region update as Ceres, cost 1/2 Σ ρ(|r|²), function tolerance on
the relative cost change, diagonal damping clamped like Ceres. For the Huber
loss Ceres' "corrector" reduces to rescaling a block's residual and Jacobian
by sqrt(ρ'), because ρ'' ≤ 0 everywhere, so iteratively reweighting each
linearisation is exactly what Ceres does. The residuals come from
:mod:`problem`, the linear solves from :mod:`block_cholesky`.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core.transform import wrap_angle
from carto_cli.mapping.constraints import ConstraintSet
from carto_cli.mapping.optimization.block_cholesky import BlockSystem
from carto_cli.mapping.optimization.problem import (
    NodePairs,
    build_edges,
    check_index,
    cost_kernel,
    free_columns,
    model_kernel,
    unscaled_error,
)

__all__ = [
    "FUNCTION_TOLERANCE",
    "GRADIENT_TOLERANCE",
    "PARAMETER_TOLERANCE",
    "OptimizationResult",
    "OptimizationSummary",
    "optimize",
]

# Ceres' defaults (solver.h); Cartographer leaves them untouched.
FUNCTION_TOLERANCE = 1e-6
GRADIENT_TOLERANCE = 1e-10
PARAMETER_TOLERANCE = 1e-8
_INITIAL_TRUST_REGION_RADIUS = 1e4
_MAX_TRUST_REGION_RADIUS = 1e16
_MIN_TRUST_REGION_RADIUS = 1e-32
_MIN_RELATIVE_DECREASE = 1e-3


@dataclass(frozen=True)
class OptimizationSummary:
    iterations: int            # linear solves, successful or not (Ceres counts them the same way)
    successful_steps: int
    initial_cost: float        # 1/2 Σ ρ(|r|²), as Ceres reports it
    final_cost: float
    termination: str           # function_tolerance | gradient_tolerance | parameter_tolerance |
    #                            max_iterations | trust_region_too_small | no_residuals
    time: float                # seconds, whole call
    linear_solver_time: float  # seconds spent factorising and solving
    num_residual_blocks: int
    num_parameters: int        # free scalars after holding the gauge and unused poses constant
    factor_nnz: int            # scalars in the Cholesky factor (fill indicator)
    num_loop_closures_in_huber_tail: int  # at the final poses: |r| > huber_scale

    @property
    def converged(self) -> bool:
        return self.termination in ("function_tolerance", "gradient_tolerance", "parameter_tolerance",
                                    "no_residuals")


@dataclass(frozen=True)
class OptimizationResult:
    node_poses: np.ndarray    # (N, 3), theta in [-pi, pi)
    submap_poses: np.ndarray  # (M, 3)
    summary: OptimizationSummary


def optimize(node_poses: ArrayLike, submap_poses: ArrayLike, constraints: ConstraintSet,
             odometry: NodePairs | None = None, local_slam: NodePairs | None = None, *, huber_scale: float | None = 1e1,
             max_num_iterations: int = 50, fixed_submaps: ArrayLike = (0,), fixed_nodes: ArrayLike = (),
             function_tolerance: float = FUNCTION_TOLERANCE,
             gradient_tolerance: float = GRADIENT_TOLERANCE,
             parameter_tolerance: float = PARAMETER_TOLERANCE) -> OptimizationResult:
    """Optimise global node and submap poses; the inputs are the initial guesses.

    ``constraints`` are node-in-submap constraints (loop closures get the Huber
    loss with ``huber_scale``; ``None`` or ``inf`` turns it off). ``odometry`` and
    ``local_slam`` are consecutive-node constraints (see ``NodePairs.consecutive``).
    ``fixed_submaps``/``fixed_nodes`` are held constant; Cartographer holds the
    first submap (of the first trajectory) and every pose of frozen trajectories.
    ``fixed_submaps`` is ignored when there are no submaps at all, so the default
    also works for node-only graphs.
    """
    t0 = time.perf_counter()
    nodes = np.array(node_poses, dtype=np.float64).reshape(-1, 3)
    submaps = np.array(submap_poses, dtype=np.float64).reshape(-1, 3)
    n, m = len(nodes), len(submaps)
    if not (np.isfinite(nodes).all() and np.isfinite(submaps).all()):
        raise ValueError("initial poses must be finite")
    if max_num_iterations < 0:
        raise ValueError("max_num_iterations must be >= 0")
    huber = math.inf if huber_scale is None else float(huber_scale)
    if not huber > 0:
        raise ValueError(f"huber_scale must be positive, got {huber_scale}")

    pairs = [p for p in (odometry, local_slam) if p is not None]
    edges = build_edges(n, m, constraints, pairs)
    x = np.concatenate([submaps, nodes])
    fixed_s = np.asarray(fixed_submaps, dtype=np.int64).reshape(-1)
    if m == 0:
        fixed_s = fixed_s[:0]
    fixed_n = np.asarray(fixed_nodes, dtype=np.int64).reshape(-1)
    check_index("fixed submap", fixed_s, m)
    check_index("fixed node", fixed_n, n)
    column = free_columns(edges, m + n, np.concatenate([fixed_s, fixed_n + m]))
    num_free = int(np.count_nonzero(column >= 0))
    args = (*edges.kernel_args, huber)

    cost = initial_cost = cost_kernel(x, *args)
    iterations = successful = 0
    solve_time = 0.0
    factor_nnz = 0
    termination = "max_iterations"
    if num_free == 0 or len(edges) == 0:
        termination = "no_residuals"
    else:
        system = BlockSystem(edges, column, num_free)
        factor_nnz = system.factor_nnz
        # The variable behind each permuted block row.
        variable = np.flatnonzero(column >= 0)[system.perm]
        cost, h, rhs = system.linearize(x, edges, huber)
        radius = _INITIAL_TRUST_REGION_RADIUS
        decrease_factor = 2.0
        if np.abs(rhs).max() <= gradient_tolerance:
            termination = "gradient_tolerance"
        while termination == "max_iterations" and iterations < max_num_iterations:
            iterations += 1
            ts = time.perf_counter()
            step = system.solve(h, rhs, radius)
            solve_time += time.perf_counter() - ts
            accepted = False
            if step is not None and np.isfinite(step).all():
                # Plain sums, not BLAS: threaded dot products stall on a busy machine.
                step_norm = math.sqrt(float(np.sum(step * step)))
                x_norm = math.sqrt(float(np.sum(x[variable] ** 2)))
                if step_norm <= parameter_tolerance * (x_norm + parameter_tolerance):
                    termination = "parameter_tolerance"
                    break
                # Ceres' model: 1/2|r̃|² - 1/2|r̃ + J̃δ|², with J̃ and r̃ carrying sqrt(ρ').
                model_change = float(np.sum(rhs * step)) - 0.5 * model_kernel(
                    x, *args, system.rs, system.re, step)
                candidate = x.copy()
                candidate[variable] += step
                new_cost = cost_kernel(candidate, *args)
                if model_change > 0 and math.isfinite(new_cost):
                    if abs(cost - new_cost) <= function_tolerance * cost:
                        if new_cost < cost:
                            x, cost = candidate, new_cost
                            successful += 1
                        termination = "function_tolerance"
                        break
                    ratio = (cost - new_cost) / model_change
                    accepted = ratio > _MIN_RELATIVE_DECREASE
            if accepted:
                x = candidate
                successful += 1
                radius = min(radius / max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3), _MAX_TRUST_REGION_RADIUS)
                decrease_factor = 2.0
                cost, h, rhs = system.linearize(x, edges, huber)
                if np.abs(rhs).max() <= gradient_tolerance:
                    termination = "gradient_tolerance"
            else:
                radius /= decrease_factor
                decrease_factor *= 2.0
                if radius < _MIN_TRUST_REGION_RADIUS:
                    termination = "trust_region_too_small"

    x[:, 2] = wrap_angle(x[:, 2])
    tail = 0
    loop = edges.robust
    if math.isfinite(huber) and loop.any():
        u = unscaled_error(x, edges)[0][loop] * edges.weight[loop]
        tail = int(np.count_nonzero(np.einsum("ij,ij->i", u, u) > huber * huber))
    summary = OptimizationSummary(
        iterations=iterations, successful_steps=successful, initial_cost=initial_cost, final_cost=cost,
        termination=termination, time=time.perf_counter() - t0, linear_solver_time=solve_time,
        num_residual_blocks=len(edges), num_parameters=3 * num_free, factor_nnz=factor_nnz,
        num_loop_closures_in_huber_tail=tail)
    return OptimizationResult(node_poses=x[m:].copy(), submap_poses=x[:m].copy(), summary=summary)
