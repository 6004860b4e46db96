"""Sparse pose-graph optimization: Cartographer's OptimizationProblem2D without Ceres.

Variables are the global poses (x, y, theta) of every submap and every node.
Every residual is Cartographer's SpaCostFunction2D between a "start" and an
"end" pose with a measured pose of end in start's frame:

    h = (R(start.theta)^T (end.xy - start.xy),  end.theta - start.theta)
    r = (t_w, t_w, r_w) * (measured - h)           (angle part wrapped to [-pi, pi))

It is used for node-in-submap constraints (start = submap, end = node), and,
as Cartographer does, for consecutive nodes of a trajectory with the relative
local SLAM pose and, when odometry exists, the relative odometry pose.
Loop closures (inter-submap constraints) go through a Huber loss; nothing else does.

The solver is Ceres' Levenberg–Marquardt (same trust-region update, cost
1/2 Σ ρ(|r|²), function tolerance on the relative cost change, diagonal
damping clamped like Ceres). For the Huber loss Ceres' "corrector" reduces to
rescaling a block's residual and Jacobian by sqrt(ρ'), because ρ'' ≤ 0
everywhere, so iteratively reweighting each linearisation is exactly what Ceres does.

The normal equations are 3×3 blocks per pair of linked poses. Their layout,
a fill-reducing ordering and the symbolic factorisation are computed once per
call; an iteration is then one pass over the residuals that accumulates the
closed-form block products straight into the factorisation's input, a block
sparse Cholesky and two triangular solves (numba kernels: at 10⁵ residuals the
numpy version spent its time in temporaries and scipy's SuperLU in ordering
overhead — see bench/optimization_scaling.py).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
import scipy.sparse.linalg as spla
from numba import njit

from carto_cli.mapping.constraints import ConstraintSet
from carto_cli.core.transform import normalize_angle, relative as relative_pose

if TYPE_CHECKING:
    from carto_cli.options import PoseGraph

__all__ = ["NodePairs", "OptimizationSummary", "OptimizationResult", "optimize", "residuals",
           "solver_kwargs", "node_pairs_from_options"]

# Ceres' defaults (solver.h); Cartographer leaves them untouched.
FUNCTION_TOLERANCE = 1e-6
GRADIENT_TOLERANCE = 1e-10
PARAMETER_TOLERANCE = 1e-8
_INITIAL_TRUST_REGION_RADIUS = 1e4
_MAX_TRUST_REGION_RADIUS = 1e16
_MIN_TRUST_REGION_RADIUS = 1e-32
_MIN_RELATIVE_DECREASE = 1e-3
_MIN_LM_DIAGONAL = 1e-6
_MAX_LM_DIAGONAL = 1e32


# --------------------------------------------------------------------------- inputs and outputs


@dataclass(frozen=True)
class NodePairs:
    """Relative-pose constraints between two nodes: ``relative`` is second's pose in first's frame."""

    first: np.ndarray
    second: np.ndarray
    relative: np.ndarray
    translation_weight: np.ndarray
    rotation_weight: np.ndarray

    def __post_init__(self):
        first = np.atleast_1d(np.asarray(self.first, dtype=np.int64))
        k = len(first)
        object.__setattr__(self, "first", first)
        object.__setattr__(self, "second", np.broadcast_to(np.asarray(self.second, dtype=np.int64), (k,)))
        object.__setattr__(self, "relative", np.asarray(self.relative, dtype=np.float64).reshape(k, 3))
        for name in ("translation_weight", "rotation_weight"):
            value = np.broadcast_to(np.asarray(getattr(self, name), dtype=np.float64), (k,))
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.first)

    @classmethod
    def consecutive(cls, poses, trajectory_ids=None, *, translation_weight: float,
                    rotation_weight: float, node_indices=None) -> "NodePairs":
        """Link node i to node i+1 with the relative pose between ``poses[i]`` and ``poses[i+1]``.

        ``poses`` are per-node local SLAM poses, or odometry poses interpolated at the
        node times with NaN rows where odometry has no data; pairs touching a NaN
        are skipped, as Cartographer skips nodes outside the odometry's time range.
        Nodes are linked only within a trajectory and, given per-trajectory
        ``node_indices``, only when these are consecutive (Cartographer's rule,
        which leaves a gap where trimming removed nodes).
        """
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
        n = len(poses)
        keep = np.ones(max(n - 1, 0), dtype=bool)
        if trajectory_ids is not None:
            tid = np.asarray(trajectory_ids)
            keep &= tid[1:] == tid[:-1]
        if node_indices is not None:
            idx = np.asarray(node_indices, dtype=np.int64)
            keep &= idx[1:] == idx[:-1] + 1
        finite = np.isfinite(poses).all(axis=1)
        keep &= finite[1:] & finite[:-1]
        first = np.flatnonzero(keep)
        second = first + 1
        rel = relative_pose(poses[first], poses[second]) if len(first) else np.empty((0, 3))
        return cls(first, second, rel, translation_weight, rotation_weight)

    @classmethod
    def empty(cls) -> "NodePairs":
        return cls(np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, 3)), 0.0, 0.0)


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


def solver_kwargs(pose_graph: "PoseGraph", *, final: bool = False) -> dict:
    """``optimize`` keyword arguments from the pose_graph options (final: the last optimization)."""
    problem = pose_graph.optimization_problem
    iterations = (pose_graph.max_num_final_iterations if final
                  else problem.ceres_solver_options.max_num_iterations)
    return {"huber_scale": problem.huber_scale, "max_num_iterations": iterations}


def node_pairs_from_options(pose_graph: "PoseGraph", local_poses, odometry_poses=None, trajectory_ids=None,
                            node_indices=None) -> tuple[NodePairs | None, NodePairs]:
    """(odometry, local_slam) consecutive-node constraints weighted as the options say.

    ``local_poses``: every node's local SLAM pose; ``odometry_poses``: odometry
    interpolated at the node times (NaN rows where there is none), or None.
    """
    problem = pose_graph.optimization_problem
    local = NodePairs.consecutive(local_poses, trajectory_ids, node_indices=node_indices,
                                  translation_weight=problem.local_slam_pose_translation_weight,
                                  rotation_weight=problem.local_slam_pose_rotation_weight)
    odometry = None
    if odometry_poses is not None:
        odometry = NodePairs.consecutive(odometry_poses, trajectory_ids, node_indices=node_indices,
                                         translation_weight=problem.odometry_translation_weight,
                                         rotation_weight=problem.odometry_rotation_weight)
    return odometry, local


# --------------------------------------------------------------------------- residual blocks


@dataclass(frozen=True)
class _Edges:
    """All residual blocks, any kind, over the stacked variables [submaps; nodes]."""

    start: np.ndarray               # (K,) variable index
    end: np.ndarray                 # (K,)
    measured: np.ndarray            # (K, 3)
    translation_weight: np.ndarray  # (K,)
    rotation_weight: np.ndarray     # (K,)
    robust: np.ndarray              # (K,) bool: under the Huber loss

    def __len__(self) -> int:
        return len(self.start)

    @property
    def weight(self) -> np.ndarray:
        """(K, 3): the weights of the x, y and theta residuals."""
        t = self.translation_weight
        return np.stack([t, t, self.rotation_weight], axis=1)

    @property
    def kernel_args(self) -> tuple:
        return (self.start, self.end, self.measured, self.translation_weight, self.rotation_weight, self.robust)


def _check_index(name: str, idx: np.ndarray, n: int) -> None:
    if len(idx) and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"{name} index out of range [0, {n}): {idx.min()}..{idx.max()}")


def _build_edges(num_nodes: int, num_submaps: int, constraints: ConstraintSet,
                 pairs: list[NodePairs]) -> _Edges:
    submap = np.asarray(constraints.submap, dtype=np.int64)
    node = np.asarray(constraints.node, dtype=np.int64)
    _check_index("constraint submap", submap, num_submaps)
    _check_index("constraint node", node, num_nodes)
    starts = [submap]
    ends = [node + num_submaps]
    measured = [np.asarray(constraints.relative, dtype=np.float64).reshape(-1, 3)]
    tw = [np.asarray(constraints.translation_weight, dtype=np.float64)]
    rw = [np.asarray(constraints.rotation_weight, dtype=np.float64)]
    robust = [np.asarray(constraints.is_loop_closure, dtype=bool)]
    for p in pairs:
        _check_index("node pair", p.first, num_nodes)
        _check_index("node pair", p.second, num_nodes)
        if np.any(p.first == p.second):
            raise ValueError("a node pair links a node to itself")
        starts.append(p.first + num_submaps)
        ends.append(p.second + num_submaps)
        measured.append(p.relative)
        tw.append(p.translation_weight)
        rw.append(p.rotation_weight)
        robust.append(np.zeros(len(p), dtype=bool))
    edges = _Edges(np.concatenate(starts), np.concatenate(ends), np.concatenate(measured),
                   np.concatenate(tw), np.concatenate(rw), np.concatenate(robust))
    if not np.isfinite(edges.measured).all():
        raise ValueError("constraints hold non-finite relative poses")
    weights = np.concatenate([edges.translation_weight, edges.rotation_weight])
    if not (np.isfinite(weights).all() and (weights >= 0).all()):
        raise ValueError("constraint weights must be finite and non-negative")
    return edges


def _unscaled_error(x: np.ndarray, edges: _Edges):
    """measured ⊖ h for every block, plus the cos/sin/h terms the Jacobian reuses."""
    a = x[edges.start]
    b = x[edges.end]
    c = np.cos(a[:, 2])
    s = np.sin(a[:, 2])
    dx = b[:, 0] - a[:, 0]
    dy = b[:, 1] - a[:, 1]
    hx = c * dx + s * dy
    hy = -s * dx + c * dy
    err = np.empty((len(edges), 3))
    err[:, 0] = edges.measured[:, 0] - hx
    err[:, 1] = edges.measured[:, 1] - hy
    err[:, 2] = normalize_angle(edges.measured[:, 2] - (b[:, 2] - a[:, 2]))
    return err, c, s, hx, hy


def _huber_rho(sq: np.ndarray, robust: np.ndarray, huber_scale: float):
    """ρ(s) and ρ'(s) per block (identity outside ``robust`` or without a finite scale)."""
    rho = sq.copy()
    rho1 = np.ones_like(sq)
    if math.isfinite(huber_scale):
        b = huber_scale * huber_scale
        tail = robust & (sq > b)
        root = np.sqrt(sq[tail])
        rho[tail] = 2.0 * huber_scale * root - b
        rho1[tail] = huber_scale / root
    return rho, rho1


def _jacobian_blocks(x: np.ndarray, edges: _Edges):
    """Weighted residuals W·e (K,3) and their Jacobians wrt start and end (K,3,3), before the loss.

    The reference the solver's kernels are tested against: they never form
    these, using the closed-form block products instead (see ``_linearize_kernel``).
    """
    err, c, s, hx, hy = _unscaled_error(x, edges)
    w = edges.weight
    k = len(edges)
    ja = np.zeros((k, 3, 3))
    jb = np.zeros((k, 3, 3))
    # d r / d start = -W dh/dstart, d r / d end = -W dh/dend.
    ja[:, 0, 0] = c * w[:, 0]
    ja[:, 0, 1] = s * w[:, 0]
    ja[:, 0, 2] = -hy * w[:, 0]
    ja[:, 1, 0] = -s * w[:, 1]
    ja[:, 1, 1] = c * w[:, 1]
    ja[:, 1, 2] = hx * w[:, 1]
    ja[:, 2, 2] = w[:, 2]
    jb[:, 0, 0] = -c * w[:, 0]
    jb[:, 0, 1] = -s * w[:, 0]
    jb[:, 1, 0] = s * w[:, 1]
    jb[:, 1, 1] = -c * w[:, 1]
    jb[:, 2, 2] = -w[:, 2]
    return err * w, ja, jb


# --------------------------------------------------------------------------- residual kernels
#
# One pass over all residual blocks each; the formulas are those of
# ``_unscaled_error``/``_jacobian_blocks`` with the products J^T J written out.
# Both translation rows carry the same weight t, so per block
#     H_ss = [[tt, 0, -e1], [0, tt, -e2], [-e1, -e2, tt·|h|² + rr]]
#     H_ee = diag(tt, tt, rr)
#     H_se = [[-tt, 0, 0], [0, -tt, 0], [e1, e2, -rr]]
# with tt = ρ' t², rr = ρ' r_w², e1 = tt (c hy + s hx), e2 = tt (s hy - c hx).

_TWO_PI = 2.0 * math.pi


@njit(cache=True, nogil=True)
def _edge_error(x, a, b, z):
    """(c, s, hx, hy, error x, error y, error theta) of one block, start pose a, end pose b."""
    c = math.cos(x[a, 2])
    s = math.sin(x[a, 2])
    dx = x[b, 0] - x[a, 0]
    dy = x[b, 1] - x[a, 1]
    hx = c * dx + s * dy
    hy = -s * dx + c * dy
    et = z[2] - (x[b, 2] - x[a, 2])
    et -= _TWO_PI * math.floor((et + math.pi) / _TWO_PI)  # as normalize_angle: [-pi, pi)
    return c, s, hx, hy, z[0] - hx, z[1] - hy, et


@njit(cache=True, nogil=True)
def _cost_kernel(x, start, end, z, tw, rw, robust, huber):
    """1/2 Σ ρ(|r|²)."""
    b2 = huber * huber
    total = 0.0
    for k in range(len(start)):
        _, _, _, _, ex, ey, et = _edge_error(x, start[k], end[k], z[k])
        sq = tw[k] * tw[k] * (ex * ex + ey * ey) + rw[k] * rw[k] * et * et
        if robust[k] and sq > b2:
            total += 2.0 * huber * math.sqrt(sq) - b2
        else:
            total += sq
    return 0.5 * total


@njit(cache=True, nogil=True)
def _linearize_kernel(x, start, end, z, tw, rw, robust, huber, rs, re, pos_ss, pos_ee, pos_off,
                      transposed, cx, rhs):
    """Accumulate J^T J into ``cx`` (upper block triangle) and -J^T r into ``rhs``; return the cost.

    rs/re: permuted block row of start/end, -1 when held constant. pos_*: where
    the block's diagonal and off-diagonal contributions live in ``cx``;
    ``transposed`` when the stored off-diagonal block is (end, start).
    """
    cx[:] = 0.0
    rhs[:] = 0.0
    b2 = huber * huber
    total = 0.0
    for k in range(len(start)):
        c, s, hx, hy, ex, ey, et = _edge_error(x, start[k], end[k], z[k])
        t = tw[k]
        w = rw[k]
        u0 = t * ex
        u1 = t * ey
        u2 = w * et
        sq = u0 * u0 + u1 * u1 + u2 * u2
        rho1 = 1.0
        if robust[k] and sq > b2:
            root = math.sqrt(sq)
            total += 2.0 * huber * root - b2
            rho1 = huber / root
        else:
            total += sq
        tt = rho1 * t * t
        rr = rho1 * w * w
        e1 = tt * (c * hy + s * hx)
        e2 = tt * (s * hy - c * hx)
        gx = rho1 * t * (c * u0 - s * u1)
        gy = rho1 * t * (s * u0 + c * u1)
        gt = rho1 * w * u2
        i = rs[k]
        j = re[k]
        if i >= 0:
            p = pos_ss[k]
            cx[p, 0, 0] += tt
            cx[p, 1, 1] += tt
            cx[p, 0, 2] -= e1
            cx[p, 2, 0] -= e1
            cx[p, 1, 2] -= e2
            cx[p, 2, 1] -= e2
            cx[p, 2, 2] += tt * (hx * hx + hy * hy) + rr
            rhs[i, 0] -= gx
            rhs[i, 1] -= gy
            rhs[i, 2] -= rho1 * t * (hx * u1 - hy * u0) + gt
        if j >= 0:
            p = pos_ee[k]
            cx[p, 0, 0] += tt
            cx[p, 1, 1] += tt
            cx[p, 2, 2] += rr
            rhs[j, 0] += gx
            rhs[j, 1] += gy
            rhs[j, 2] += gt
        if i >= 0 and j >= 0:
            p = pos_off[k]
            cx[p, 0, 0] -= tt
            cx[p, 1, 1] -= tt
            cx[p, 2, 2] -= rr
            if transposed[k]:
                cx[p, 0, 2] += e1
                cx[p, 1, 2] += e2
            else:
                cx[p, 2, 0] += e1
                cx[p, 2, 1] += e2
    return 0.5 * total


@njit(cache=True, nogil=True)
def _model_kernel(x, start, end, z, tw, rw, robust, huber, rs, re, step):
    """Σ |J̃ δ|² at x for the permuted step (ρ' folded in as in the linearisation)."""
    b2 = huber * huber
    total = 0.0
    for k in range(len(start)):
        c, s, hx, hy, ex, ey, et = _edge_error(x, start[k], end[k], z[k])
        t2 = tw[k] * tw[k]
        w2 = rw[k] * rw[k]
        sq = t2 * (ex * ex + ey * ey) + w2 * et * et
        rho1 = 1.0
        if robust[k] and sq > b2:
            rho1 = huber / math.sqrt(sq)
        ax = ay = at = bx = by = bt = 0.0
        i = rs[k]
        j = re[k]
        if i >= 0:
            ax = step[i, 0]
            ay = step[i, 1]
            at = step[i, 2]
        if j >= 0:
            bx = step[j, 0]
            by = step[j, 1]
            bt = step[j, 2]
        dx = ax - bx
        dy = ay - by
        jx = c * dx + s * dy - hy * at
        jy = -s * dx + c * dy + hx * at
        jt = at - bt
        total += rho1 * (t2 * (jx * jx + jy * jy) + w2 * jt * jt)
    return total


# --------------------------------------------------------------------------- block sparse Cholesky
#
# SuperLU on the scalar normal equations took ~0.6 s per iteration at 10⁴ nodes
# (0.45 s of it recomputing the ordering; 0.16 s with the ordering reused)
# although the factor has barely more non-zeros than the matrix. So the ordering
# is computed once per ``optimize`` call, on the 3×3-block graph where it is
# cheap, and the numeric factorisation is an up-looking block Cholesky (CSparse's
# cs_chol with 3×3 blocks; ~25 ms there), as Ceres' SPARSE_NORMAL_CHOLESKY would do.


@njit(cache=True, nogil=True)
def _etree(cp, ci, n):
    parent = np.full(n, -1, np.int64)
    ancestor = np.full(n, -1, np.int64)
    for k in range(n):
        for p in range(cp[k], cp[k + 1]):
            i = ci[p]
            while i != -1 and i < k:
                nxt = ancestor[i]
                ancestor[i] = k  # path compression
                if nxt == -1:
                    parent[i] = k
                i = nxt
    return parent


@njit(cache=True, nogil=True)
def _symbolic(cp, ci, parent, n):
    """Row patterns of L (strictly lower, each in etree topological order) and L's column layout."""
    mark = np.full(n, -1, np.int64)
    stack = np.empty(n, np.int64)
    out = np.empty(n, np.int64)
    rowcount = np.zeros(n, np.int64)
    colcount = np.ones(n, np.int64)
    for k in range(n):  # sizes first
        mark[k] = k
        for p in range(cp[k], cp[k + 1]):
            i = ci[p]
            while i != -1 and i < k and mark[i] != k:
                mark[i] = k
                rowcount[k] += 1
                colcount[i] += 1
                i = parent[i]
    rp = np.zeros(n + 1, np.int64)
    lp = np.zeros(n + 1, np.int64)
    for k in range(n):
        rp[k + 1] = rp[k] + rowcount[k]
        lp[k + 1] = lp[k] + colcount[k]
    ri = np.empty(rp[n], np.int64)
    li = np.empty(lp[n], np.int64)
    fill = lp[:n] + 1
    mark[:] = -1
    for k in range(n):
        mark[k] = k
        top = n
        for p in range(cp[k], cp[k + 1]):
            i = ci[p]
            length = 0
            while i != -1 and i < k and mark[i] != k:
                stack[length] = i
                length += 1
                mark[i] = k
                i = parent[i]
            while length > 0:
                top -= 1
                length -= 1
                out[top] = stack[length]
        for q in range(top, n):
            i = out[q]
            ri[rp[k] + q - top] = i
            li[fill[i]] = k
            fill[i] += 1
        li[lp[k]] = k
    return rp, ri, lp, li


@njit(cache=True, nogil=True)
def _numeric(cp, ci, cx, rp, ri, lp, li, lx, x):
    """Block Cholesky of the matrix whose upper block triangle is (cp, ci, cx); False if not SPD.

    ``x`` is an (n, 3, 3) zero workspace, returned zeroed.
    """
    n = len(cp) - 1
    fill = lp[:n] + 1
    y = np.empty((3, 3))
    d = np.empty((3, 3))
    for k in range(n):
        for p in range(cp[k], cp[k + 1]):
            i = ci[p]
            for a in range(3):
                for b in range(3):
                    x[i, a, b] = cx[p, a, b]
        for a in range(3):
            for b in range(3):
                d[a, b] = x[k, a, b]
                x[k, a, b] = 0.0
        for t in range(rp[k], rp[k + 1]):
            i = ri[t]
            q = lp[i]
            l00 = lx[q, 0, 0]
            l10 = lx[q, 1, 0]
            l11 = lx[q, 1, 1]
            l20 = lx[q, 2, 0]
            l21 = lx[q, 2, 1]
            l22 = lx[q, 2, 2]
            for b in range(3):  # y = L_ii^{-1} x_i
                y0 = x[i, 0, b] / l00
                y1 = (x[i, 1, b] - l10 * y0) / l11
                y2 = (x[i, 2, b] - l20 * y0 - l21 * y1) / l22
                y[0, b] = y0
                y[1, b] = y1
                y[2, b] = y2
                x[i, 0, b] = 0.0
                x[i, 1, b] = 0.0
                x[i, 2, b] = 0.0
            for p in range(lp[i] + 1, fill[i]):  # x_r -= L(r, i) y for the rows r < k filled so far
                r = li[p]
                for a in range(3):
                    for b in range(3):
                        x[r, a, b] -= lx[p, a, 0] * y[0, b] + lx[p, a, 1] * y[1, b] + lx[p, a, 2] * y[2, b]
            for a in range(3):
                for b in range(3):
                    d[a, b] -= y[0, a] * y[0, b] + y[1, a] * y[1, b] + y[2, a] * y[2, b]
            q = fill[i]
            fill[i] += 1
            for a in range(3):
                for b in range(3):
                    lx[q, a, b] = y[b, a]  # L(k, i) = y^T
        # 3×3 Cholesky of d
        q = lp[k]
        a00 = d[0, 0]
        if not a00 > 0.0:
            return False
        l00 = math.sqrt(a00)
        l10 = d[1, 0] / l00
        l20 = d[2, 0] / l00
        a11 = d[1, 1] - l10 * l10
        if not a11 > 0.0:
            return False
        l11 = math.sqrt(a11)
        l21 = (d[2, 1] - l20 * l10) / l11
        a22 = d[2, 2] - l20 * l20 - l21 * l21
        if not a22 > 0.0:
            return False
        lx[q, 0, 0] = l00
        lx[q, 0, 1] = 0.0
        lx[q, 0, 2] = 0.0
        lx[q, 1, 0] = l10
        lx[q, 1, 1] = l11
        lx[q, 1, 2] = 0.0
        lx[q, 2, 0] = l20
        lx[q, 2, 1] = l21
        lx[q, 2, 2] = math.sqrt(a22)
    return True
@njit(cache=True, nogil=True)
def _block_solve(lp, li, lx, b):
    """Solve L L^T x = b in place; b is (n, 3)."""
    n = len(lp) - 1
    for j in range(n):
        q = lp[j]
        y0 = b[j, 0] / lx[q, 0, 0]
        y1 = (b[j, 1] - lx[q, 1, 0] * y0) / lx[q, 1, 1]
        y2 = (b[j, 2] - lx[q, 2, 0] * y0 - lx[q, 2, 1] * y1) / lx[q, 2, 2]
        b[j, 0] = y0
        b[j, 1] = y1
        b[j, 2] = y2
        for p in range(q + 1, lp[j + 1]):
            r = li[p]
            for a in range(3):
                b[r, a] -= lx[p, a, 0] * y0 + lx[p, a, 1] * y1 + lx[p, a, 2] * y2
    for j in range(n - 1, -1, -1):
        v0 = b[j, 0]
        v1 = b[j, 1]
        v2 = b[j, 2]
        for p in range(lp[j] + 1, lp[j + 1]):
            r = li[p]
            v0 -= lx[p, 0, 0] * b[r, 0] + lx[p, 1, 0] * b[r, 1] + lx[p, 2, 0] * b[r, 2]
            v1 -= lx[p, 0, 1] * b[r, 0] + lx[p, 1, 1] * b[r, 1] + lx[p, 2, 1] * b[r, 2]
            v2 -= lx[p, 0, 2] * b[r, 0] + lx[p, 1, 2] * b[r, 1] + lx[p, 2, 2] * b[r, 2]
        q = lp[j]
        x2 = v2 / lx[q, 2, 2]
        x1 = (v1 - lx[q, 2, 1] * x2) / lx[q, 1, 1]
        x0 = (v0 - lx[q, 1, 0] * x1 - lx[q, 2, 0] * x2) / lx[q, 0, 0]
        b[j, 0] = x0
        b[j, 1] = x1
        b[j, 2] = x2


def _block_ordering(ur: np.ndarray, uc: np.ndarray, nb: int) -> np.ndarray:
    """Fill-reducing elimination position of every block (old index -> new index).

    SuperLU's multiple minimum degree on A^T + A, run on the block graph where it
    is cheap: a diagonally dominant stand-in matrix with the blocks' pattern.
    """
    off = ur != uc
    degree = np.bincount(ur[off], minlength=nb).astype(np.float64)
    values = np.where(off, -1.0, degree[ur] + 1.0)
    stand_in = sp.csc_matrix((values, (ur, uc)), shape=(nb, nb))
    lu = spla.splu(stand_in, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                   options={"SymmetricMode": True})
    return np.asarray(lu.perm_c, dtype=np.int64)


class _BlockSystem:
    """Layout and factorisation of (J^T J + D/radius) δ = -J^T r over the free poses, in 3×3 blocks.

    Only the upper block triangle of the symmetrically permuted matrix is
    stored, column by column (diagonal block last), which is what the
    up-looking Cholesky reads. The residual kernel writes into it directly.
    """

    def __init__(self, edges: _Edges, column: np.ndarray, num_free: int):
        nb = self.nb = num_free
        ca = column[edges.start]
        cb = column[edges.end]
        both = (ca >= 0) & (cb >= 0)
        lo = np.minimum(ca[both], cb[both])
        hi = np.maximum(ca[both], cb[both])
        keys, inverse = np.unique(lo * nb + hi, return_inverse=True)
        ulo, uhi = keys // nb, keys % nb

        iperm = _block_ordering(np.concatenate([ulo, uhi, np.arange(nb)]),
                                np.concatenate([uhi, ulo, np.arange(nb)]), nb)
        self.perm = np.argsort(iperm)  # new -> old
        pi, pj = iperm[ulo], iperm[uhi]
        rows = np.concatenate([np.minimum(pi, pj), np.arange(nb)])
        cols = np.concatenate([np.maximum(pi, pj), np.arange(nb)])
        order = np.lexsort((rows, cols))
        where = np.empty(len(order), dtype=np.int64)
        where[order] = np.arange(len(order))
        self.ci = rows[order]
        self.cols = cols[order]
        self.cp = np.zeros(nb + 1, dtype=np.int64)
        np.cumsum(np.bincount(self.cols, minlength=nb), out=self.cp[1:])
        self.cdiag = self.cp[1:] - 1

        k = len(edges)
        self.rs = np.where(ca >= 0, iperm[np.maximum(ca, 0)], -1)
        self.re = np.where(cb >= 0, iperm[np.maximum(cb, 0)], -1)
        self.pos_ss = np.where(ca >= 0, self.cdiag[np.maximum(self.rs, 0)], -1)
        self.pos_ee = np.where(cb >= 0, self.cdiag[np.maximum(self.re, 0)], -1)
        self.pos_off = np.full(k, -1, dtype=np.int64)
        self.pos_off[both] = where[inverse.ravel()]
        self.transposed = np.zeros(k, dtype=bool)
        self.transposed[both] = self.rs[both] > self.re[both]

        parent = _etree(self.cp, self.ci, nb)
        self.rp, self.ri, self.lp, self.li = _symbolic(self.cp, self.ci, parent, nb)
        self.lx = np.empty((self.lp[-1], 3, 3))
        self.work = np.zeros((nb, 3, 3))

    @property
    def factor_nnz(self) -> int:
        return 9 * len(self.li)

    def linearize(self, x: np.ndarray, edges: _Edges, huber: float):
        """(cost, H upper blocks, -g) at x, both in the permuted order."""
        cx = np.empty((len(self.ci), 3, 3))
        rhs = np.empty((self.nb, 3))
        cost = _linearize_kernel(x, *edges.kernel_args, huber, self.rs, self.re, self.pos_ss,
                                 self.pos_ee, self.pos_off, self.transposed, cx, rhs)
        return cost, cx, rhs

    def solve(self, cx: np.ndarray, rhs: np.ndarray, radius: float):
        """δ (permuted) for (H + clamp(diag H)/radius) δ = rhs, or None when the factorisation fails."""
        damped = cx.copy()
        i3 = np.arange(3)
        diagonal = np.clip(cx[self.cdiag][:, i3, i3], _MIN_LM_DIAGONAL, _MAX_LM_DIAGONAL)
        damped[self.cdiag[:, None], i3, i3] += diagonal / radius
        if not _numeric(self.cp, self.ci, damped, self.rp, self.ri, self.lp, self.li, self.lx, self.work):
            self.work[:] = 0.0
            return None
        step = rhs.copy()
        _block_solve(self.lp, self.li, self.lx, step)
        return step

    def to_sparse(self, cx: np.ndarray) -> sp.csr_matrix:
        """H as a full scalar sparse matrix in the unpermuted free order (for checking)."""
        i3 = np.arange(3)
        old_r = self.perm[self.ci]
        old_c = self.perm[self.cols]
        rows = np.broadcast_to(3 * old_r[:, None, None] + i3[:, None], cx.shape).ravel()
        cols = np.broadcast_to(3 * old_c[:, None, None] + i3, cx.shape).ravel()
        n = 3 * self.nb
        upper = sp.csr_matrix((cx.ravel(), (rows, cols)), shape=(n, n))
        off = self.ci != self.cols
        lower = sp.csr_matrix((cx[off].ravel(),
                               (rows.reshape(-1, 3, 3)[off].ravel(), cols.reshape(-1, 3, 3)[off].ravel())),
                              shape=(n, n)).T
        return (upper + lower).tocsr()


def _sparse_jacobian(ja: np.ndarray, jb: np.ndarray, edges: _Edges, column: np.ndarray) -> sp.csr_matrix:
    """The Jacobian wrt the free poses as a sparse matrix (for checking: the solver never forms it)."""
    k = len(edges)
    num_cols = 3 * int(column.max() + 1) if (column >= 0).any() else 0
    rows = np.broadcast_to(3 * np.arange(k)[:, None, None] + np.arange(3)[:, None], (k, 3, 3))
    parts = []
    for blocks, var in ((ja, edges.start), (jb, edges.end)):
        col = column[var]
        keep = col >= 0
        cols = np.broadcast_to(3 * col[:, None, None] + np.arange(3), (k, 3, 3))
        parts.append((blocks[keep].ravel(), rows[keep].ravel(), cols[keep].ravel()))
    data, r, c = (np.concatenate(z) for z in zip(*parts))
    return sp.csr_matrix((data, (r, c)), shape=(3 * k, num_cols))


def _free_columns(edges: _Edges, num_vars: int, fixed: np.ndarray) -> np.ndarray:
    """Block column of each pose, -1 for the ones held constant.

    Constant are: the requested ones, poses no residual touches (Ceres drops
    those), and one pose in each connected part of the graph that has no
    constant pose yet. The last keeps the system non-singular when, say, a
    second trajectory has no loop closure to the first; Ceres would leave that
    gauge to the damping alone, and a nearly singular system lets it drift.
    """
    held = np.zeros(num_vars, dtype=bool)
    held[fixed] = True
    used = np.zeros(num_vars, dtype=bool)
    used[edges.start] = True
    used[edges.end] = True
    held |= ~used
    if len(edges):
        graph = sp.coo_matrix((np.ones(len(edges)), (edges.start, edges.end)), shape=(num_vars, num_vars))
        _, label = csgraph.connected_components(graph, directed=False)
        anchored = np.zeros(label.max() + 1, dtype=bool)
        anchored[label[held & used]] = True
        # Poses are ordered submaps first, so the anchor is the part's first submap.
        first = np.full(label.max() + 1, num_vars)
        np.minimum.at(first, label[used], np.flatnonzero(used))
        held[first[~anchored & (first < num_vars)]] = True
    column = np.full(num_vars, -1, dtype=np.int64)
    free = np.flatnonzero(~held)
    column[free] = np.arange(len(free))
    return column


# --------------------------------------------------------------------------- public API


def optimize(node_poses, submap_poses, constraints: ConstraintSet, odometry: NodePairs | None = None,
             local_slam: NodePairs | None = None, *, huber_scale: float | None = 1e1,
             max_num_iterations: int = 50, fixed_submaps=(0,), fixed_nodes=(),
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
    edges = _build_edges(n, m, constraints, pairs)
    x = np.concatenate([submaps, nodes])
    fixed_s = np.asarray(fixed_submaps, dtype=np.int64).reshape(-1)
    if m == 0:
        fixed_s = fixed_s[:0]
    fixed_n = np.asarray(fixed_nodes, dtype=np.int64).reshape(-1)
    _check_index("fixed submap", fixed_s, m)
    _check_index("fixed node", fixed_n, n)
    column = _free_columns(edges, m + n, np.concatenate([fixed_s, fixed_n + m]))
    num_free = int(np.count_nonzero(column >= 0))
    args = (*edges.kernel_args, huber)

    cost = initial_cost = _cost_kernel(x, *args)
    iterations = successful = 0
    solve_time = 0.0
    factor_nnz = 0
    termination = "max_iterations"
    if num_free == 0 or len(edges) == 0:
        termination = "no_residuals"
    else:
        system = _BlockSystem(edges, column, num_free)
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
                model_change = float(np.sum(rhs * step)) - 0.5 * _model_kernel(
                    x, *args, system.rs, system.re, step)
                candidate = x.copy()
                candidate[variable] += step
                new_cost = _cost_kernel(candidate, *args)
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

    x[:, 2] = normalize_angle(x[:, 2])
    tail = 0
    loop = edges.robust
    if math.isfinite(huber) and loop.any():
        u = _unscaled_error(x, edges)[0][loop] * edges.weight[loop]
        tail = int(np.count_nonzero(np.einsum("ij,ij->i", u, u) > huber * huber))
    summary = OptimizationSummary(
        iterations=iterations, successful_steps=successful, initial_cost=initial_cost, final_cost=cost,
        termination=termination, time=time.perf_counter() - t0, linear_solver_time=solve_time,
        num_residual_blocks=len(edges), num_parameters=3 * num_free, factor_nnz=factor_nnz,
        num_loop_closures_in_huber_tail=tail)
    return OptimizationResult(node_poses=x[m:].copy(), submap_poses=x[:m].copy(), summary=summary)


def residuals(node_poses, submap_poses, constraints: ConstraintSet, *, scaled: bool = False) -> np.ndarray:
    """Per-constraint error (K, 3) = measured ⊖ (inverse(submap) ∘ node), in the submap frame.

    Unscaled (metres, radians) by default, to judge loop closures after optimisation;
    ``scaled`` multiplies by the weights, giving the residual the solver (and the
    Huber threshold) sees.
    """
    nodes = np.asarray(node_poses, dtype=np.float64).reshape(-1, 3)
    submaps = np.asarray(submap_poses, dtype=np.float64).reshape(-1, 3)
    edges = _build_edges(len(nodes), len(submaps), constraints, [])
    err = _unscaled_error(np.concatenate([submaps, nodes]), edges)[0]
    return err * edges.weight if scaled else err
