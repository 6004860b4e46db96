"""Oracles for carto_cli.mapping.optimization: explicit Jacobians and scalar sparse matrices.

The solver never forms these (its kernels accumulate closed-form block products);
the tests build them here and check the kernels against them.
"""
from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp

from carto_cli.mapping.optimization.block_cholesky import BlockSystem
from carto_cli.mapping.optimization.problem import Edges, unscaled_error


def huber_rho(sq: np.ndarray, robust: np.ndarray, huber_scale: float):
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


def jacobian_blocks(x: np.ndarray, edges: Edges):
    """Weighted residuals W·e (K,3) and their Jacobians wrt start and end (K,3,3), before the loss."""
    err, c, s, hx, hy = unscaled_error(x, edges)
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


def sparse_jacobian(ja: np.ndarray, jb: np.ndarray, edges: Edges, column: np.ndarray) -> sp.csr_matrix:
    """The Jacobian wrt the free poses (``column`` >= 0) as a scalar sparse matrix."""
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


def block_matrix_to_sparse(system: BlockSystem, cx: np.ndarray) -> sp.csr_matrix:
    """A symmetric matrix stored in ``system``'s layout (upper blocks, permuted) as a full scalar
    sparse matrix in the unpermuted free order."""
    i3 = np.arange(3)
    old_r = system.perm[system.ci]
    old_c = system.perm[system.cols]
    rows = np.broadcast_to(3 * old_r[:, None, None] + i3[:, None], cx.shape).ravel()
    cols = np.broadcast_to(3 * old_c[:, None, None] + i3, cx.shape).ravel()
    n = 3 * system.nb
    upper = sp.csr_matrix((cx.ravel(), (rows, cols)), shape=(n, n))
    off = system.ci != system.cols
    lower = sp.csr_matrix((cx[off].ravel(),
                           (rows.reshape(-1, 3, 3)[off].ravel(), cols.reshape(-1, 3, 3)[off].ravel())),
                          shape=(n, n)).T
    return (upper + lower).tocsr()
