"""The pose-graph problem: variables, residual blocks and their evaluation.

Cartographer's OptimizationProblem2D without Ceres. Variables are the global
poses (x, y, theta) of every submap and every node. Every residual is
Cartographer's SpaCostFunction2D between a "start" and an "end" pose with a
measured pose of end in start's frame:

    h = (R(start.theta)^T (end.xy - start.xy),  end.theta - start.theta)
    r = (t_w, t_w, r_w) * (measured - h)           (angle part wrapped to [-pi, pi))

It is used for node-in-submap constraints (start = submap, end = node), and,
as Cartographer does, for consecutive nodes of a trajectory with the relative
local SLAM pose and, when odometry exists, the relative odometry pose.
Loop closures (inter-submap constraints) go through a Huber loss; nothing else does.

The kernels here evaluate every block in one pass: the cost, the model
change of a step, and J^T J / J^T r accumulated straight into the block
layout of :mod:`block_cholesky`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from carto_cli.core.transform import relative as relative_pose
from carto_cli.core.transform import wrap_angle
from carto_cli.mapping.constraints import ConstraintSet

__all__ = [
    "Edges",
    "NodePairs",
    "build_edges",
    "check_index",
    "connected_parts",
    "cost_kernel",
    "free_columns",
    "linearize_kernel",
    "model_kernel",
    "residuals",
    "unscaled_error",
]


@dataclass(frozen=True)
class NodePairs:
    """Relative-pose constraints between two nodes: ``relative`` is second's pose in first's frame.

    Every field is a (K,) or (K, 3) array once built; a scalar weight is broadcast to all pairs.
    """

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
    def consecutive(cls, poses: ArrayLike, trajectory_ids: ArrayLike | None = None, *, translation_weight: float,
                    rotation_weight: float, node_indices: ArrayLike | None = None) -> NodePairs:
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
        finite = np.all(np.isfinite(poses), axis=1)
        keep &= finite[1:] & finite[:-1]
        first = np.flatnonzero(keep)
        second = first + 1
        rel = relative_pose(poses[first], poses[second]) if len(first) else np.empty((0, 3))
        k = len(first)
        return cls(first, second, rel, np.full(k, translation_weight, dtype=np.float64),
                   np.full(k, rotation_weight, dtype=np.float64))

    @classmethod
    def empty(cls) -> NodePairs:
        return cls(np.empty(0, np.int64), np.empty(0, np.int64), np.empty((0, 3)), np.empty(0), np.empty(0))


# --------------------------------------------------------------------------- residual blocks


@dataclass(frozen=True)
class Edges:
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
    def kernel_args(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The blocks as the residual kernels take them: start, end, measured, weights, robust."""
        return (self.start, self.end, self.measured, self.translation_weight, self.rotation_weight, self.robust)


def check_index(name: str, idx: np.ndarray, n: int) -> None:
    if len(idx) and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"{name} index out of range [0, {n}): {idx.min()}..{idx.max()}")


def build_edges(num_nodes: int, num_submaps: int, constraints: ConstraintSet,
                pairs: list[NodePairs]) -> Edges:
    submap = np.asarray(constraints.submap, dtype=np.int64)
    node = np.asarray(constraints.node, dtype=np.int64)
    check_index("constraint submap", submap, num_submaps)
    check_index("constraint node", node, num_nodes)
    starts = [submap]
    ends = [node + num_submaps]
    measured = [np.asarray(constraints.relative, dtype=np.float64).reshape(-1, 3)]
    tw = [np.asarray(constraints.translation_weight, dtype=np.float64)]
    rw = [np.asarray(constraints.rotation_weight, dtype=np.float64)]
    robust = [np.asarray(constraints.is_loop_closure, dtype=bool)]
    for p in pairs:
        check_index("node pair", p.first, num_nodes)
        check_index("node pair", p.second, num_nodes)
        if np.any(p.first == p.second):
            raise ValueError("a node pair links a node to itself")
        starts.append(p.first + num_submaps)
        ends.append(p.second + num_submaps)
        measured.append(p.relative)
        tw.append(p.translation_weight)
        rw.append(p.rotation_weight)
        robust.append(np.zeros(len(p), dtype=bool))
    edges = Edges(np.concatenate(starts), np.concatenate(ends), np.concatenate(measured),
                   np.concatenate(tw), np.concatenate(rw), np.concatenate(robust))
    if not np.isfinite(edges.measured).all():
        raise ValueError("constraints hold non-finite relative poses")
    weights = np.concatenate([edges.translation_weight, edges.rotation_weight])
    if not (np.isfinite(weights).all() and (weights >= 0).all()):
        raise ValueError("constraint weights must be finite and non-negative")
    return edges


def unscaled_error(x: np.ndarray, edges: Edges) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
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
    err[:, 2] = wrap_angle(edges.measured[:, 2] - (b[:, 2] - a[:, 2]))
    return err, c, s, hx, hy


# --------------------------------------------------------------------------- residual kernels
#
# One pass over all residual blocks each; the formulas are those of
# ``unscaled_error`` and its Jacobian blocks (written out in tests/reference/optimization.py,
# which the kernels are tested against) with the products J^T J written out.
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
    et -= _TWO_PI * math.floor((et + math.pi) / _TWO_PI)  # as wrap_angle: [-pi, pi)
    return c, s, hx, hy, z[0] - hx, z[1] - hy, et


@njit(cache=True, nogil=True)
def cost_kernel(x, start, end, z, tw, rw, robust, huber):
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
def linearize_kernel(x, start, end, z, tw, rw, robust, huber, rs, re, pos_ss, pos_ee, pos_off,
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
def model_kernel(x, start, end, z, tw, rw, robust, huber, rs, re, step):
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


# --------------------------------------------------------------------------- gauge and entry points


def free_columns(edges: Edges, num_vars: int, fixed: np.ndarray) -> np.ndarray:
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
        label = connected_parts(edges.start, edges.end, num_vars)
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


@njit(cache=True, nogil=True)
def connected_parts(start, end, n):
    """Connected part of every pose (labels 0..parts-1 in order of each part's lowest pose), by union-find."""
    parent = np.arange(n)
    for e in range(len(start)):
        a = start[e]
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        b = end[e]
        while parent[b] != b:
            parent[b] = parent[parent[b]]
            b = parent[b]
        if a < b:
            parent[b] = a
        elif b < a:
            parent[a] = b
    label = np.empty(n, np.int64)
    parts = 0
    for v in range(n):
        root = v
        while parent[root] != root:
            root = parent[root]
        if root == v:
            label[v] = parts
            parts += 1
        else:
            label[v] = label[root]
    return label


def residuals(node_poses: ArrayLike, submap_poses: ArrayLike, constraints: ConstraintSet, *,
              scaled: bool = False) -> np.ndarray:
    """Per-constraint error (K, 3) = measured ⊖ (inverse(submap) ∘ node), in the submap frame.

    Unscaled (metres, radians) by default, to judge loop closures after optimisation;
    ``scaled`` multiplies by the weights, giving the residual the solver (and the
    Huber threshold) sees.
    """
    nodes = np.asarray(node_poses, dtype=np.float64).reshape(-1, 3)
    submaps = np.asarray(submap_poses, dtype=np.float64).reshape(-1, 3)
    edges = build_edges(len(nodes), len(submaps), constraints, [])
    err = unscaled_error(np.concatenate([submaps, nodes]), edges)[0]
    return err * edges.weight if scaled else err
