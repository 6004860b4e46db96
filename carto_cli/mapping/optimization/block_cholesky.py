"""Block sparse Cholesky of the Gauss-Newton system, in 3×3 blocks (one per pose).

The normal equations of the pose graph are 3×3 blocks per pair of linked
poses. Their layout, a fill-reducing ordering and the symbolic factorisation
are computed once per ``optimize`` call (:class:`BlockSystem`); an iteration
is then one pass over the residuals that accumulates the closed-form block
products straight into the factorisation's input, a block sparse Cholesky
and two triangular solves (numba kernels: at 10⁵ residuals the numpy version
spent its time in temporaries and scipy's SuperLU in ordering overhead — see
bench/optimization_scaling.py).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from carto_cli.mapping.optimization.problem import Edges, linearize_kernel

# Ceres' bounds on the diagonal its Levenberg–Marquardt damping scales (solver.h); Cartographer keeps them.
MIN_LM_DIAGONAL = 1e-6
MAX_LM_DIAGONAL = 1e32

__all__ = ["BlockSystem", "block_ordering", "pair_ordering"]


# --------------------------------------------------------------------------- block sparse Cholesky
#
# SuperLU on the scalar normal equations spent most of each iteration recomputing
# the ordering, although the factor has barely more non-zeros than the matrix
# (docs/measurements.md). So the ordering is computed once per ``optimize`` call,
# on the 3×3-block graph where it is cheap, and the numeric factorisation is an
# up-looking block Cholesky (CSparse's cs_chol with 3×3 blocks), as Ceres'
# SPARSE_NORMAL_CHOLESKY would do.


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
def _numeric(cp, ci, cx, rp, ri, lp, li, lx, x, radius, min_diagonal, max_diagonal):
    """Block Cholesky of the matrix whose upper block triangle is (cp, ci, cx), each diagonal entry h raised by
    clamp(h, min_diagonal, max_diagonal) / radius (the solver's damping, applied here rather than to a copy
    of the matrix); False if not SPD.

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
            h = d[a, a]
            c = h
            if c < min_diagonal:
                c = min_diagonal
            if c > max_diagonal:
                c = max_diagonal
            d[a, a] = h + c / radius
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


def block_ordering(ur: np.ndarray, uc: np.ndarray, nb: int) -> np.ndarray:
    """Fill-reducing elimination position of every block (old index -> new index): minimum degree on the
    block graph (the pattern of (ur, uc), both triangles; the diagonal is ignored)."""
    off = ur != uc
    key = np.unique(ur[off] * nb + uc[off])
    rows, cols = key // nb, key % nb
    indptr = np.zeros(nb + 1, dtype=np.int64)
    np.cumsum(np.bincount(rows, minlength=nb), out=indptr[1:])
    return _positions(_minimum_degree(indptr, cols.astype(np.int64), nb))


def pair_ordering(lo: np.ndarray, hi: np.ndarray, nb: int) -> np.ndarray:
    """:func:`block_ordering` of the pattern of the pairs (lo, hi), given unique and sorted by (lo, hi) with
    lo <= hi, as :class:`BlockSystem` has them: its rows are built in that order without sorting (the sort was
    over half of the ordering's time on dense-freiburg-079's periodic optimizations), the same rows exactly."""
    indptr, cols = _pair_pattern(np.ascontiguousarray(lo, dtype=np.int64),
                                 np.ascontiguousarray(hi, dtype=np.int64), nb)
    return _positions(_minimum_degree(indptr, cols, nb))


def _positions(order: np.ndarray) -> np.ndarray:
    iperm = np.empty(len(order), dtype=np.int64)
    iperm[order] = np.arange(len(order))
    return iperm


@njit(cache=True, nogil=True)
def _pair_pattern(lo, hi, nb):
    """Both triangles of the pattern of the pairs (lo, hi) (unique, sorted by (lo, hi)), the diagonal left out,
    as rows of ascending columns: a row r gets its smaller neighbours from the pairs (l, r) in the order of l,
    then its larger ones from the pairs (r, h) in the order of h."""
    indptr = np.zeros(nb + 1, np.int64)
    for t in range(len(lo)):
        if lo[t] != hi[t]:
            indptr[lo[t] + 1] += 1
            indptr[hi[t] + 1] += 1
    for v in range(nb):
        indptr[v + 1] += indptr[v]
    fill = np.empty(nb, np.int64)
    for v in range(nb):
        fill[v] = indptr[v]
    cols = np.empty(indptr[nb], np.int64)
    for t in range(len(lo)):
        if lo[t] != hi[t]:
            cols[fill[hi[t]]] = lo[t]
            fill[hi[t]] += 1
    for t in range(len(lo)):
        if lo[t] != hi[t]:
            cols[fill[lo[t]]] = hi[t]
            fill[lo[t]] += 1
    return indptr, cols


@njit(cache=True, nogil=True)
def _minimum_degree(indptr, indices, n):
    """Elimination order (new -> old) by minimum degree on the elimination graph, kept explicitly: eliminating
    a block joins its neighbours into a clique. The ties go to the block whose degree last changed, then to
    the lowest index. SciPy's SuperLU (multiple minimum degree) did this before, and importing scipy.sparse
    for it was a quarter of the mapping command's imports (docs/scaling.md, Start-up). A pose graph's
    elimination graph stays sparse (about five blocks a column of the factor), so explicit lists do: the fill
    is SuperLU's within 1.5 %, and the time too up to 10k poses (1.5 times SuperLU's at 30k)."""
    order = np.empty(n, np.int64)
    if n == 0:
        return order
    # Each block's neighbours live in one pool, in a slot with room to grow; a list that outgrows its slot
    # moves to the pool's end. (Element by element, not slices or np.full: those took numba 2.7 s more to
    # compile here, which a fresh install pays once.)
    slack = 4
    pool = np.empty(len(indices) + (slack + 1) * n + 16, np.int64)
    start = np.empty(n, np.int64)
    length = np.empty(n, np.int64)
    room = np.empty(n, np.int64)
    top = 0
    for v in range(n):
        d = indptr[v + 1] - indptr[v]
        start[v] = top
        length[v] = d
        room[v] = d + slack
        for t in range(d):
            pool[top + t] = indices[indptr[v] + t]
        top += d + slack
    # Blocks by degree, in doubly linked buckets
    head = np.empty(n + 1, np.int64)
    nxt = np.empty(n, np.int64)
    prv = np.empty(n, np.int64)
    mark = np.empty(n, np.int64)
    for v in range(n):
        nxt[v] = -1
        prv[v] = -1
        mark[v] = -1
        head[v] = -1
    head[n] = -1
    for v in range(n - 1, -1, -1):
        d = length[v]
        nxt[v] = head[d]
        if head[d] >= 0:
            prv[head[d]] = v
        head[d] = v
    eliminated = np.zeros(n, np.bool_)
    nbrs = np.empty(n, np.int64)
    buffer = np.empty(n, np.int64)
    stamp = 0
    lowest = 0
    for step in range(n):
        while head[lowest] < 0:
            lowest += 1
        if lowest == n - step - 1:
            # What is left is one clique (the submaps, at the end of a pose graph): every order fills it alike,
            # and eliminating it block by block would cost its size cubed
            rest = step
            for d in range(lowest, n + 1):
                u = head[d]
                while u >= 0:
                    order[rest] = u
                    rest += 1
                    u = nxt[u]
            break
        v = head[lowest]
        head[lowest] = nxt[v]
        if nxt[v] >= 0:
            prv[nxt[v]] = -1
        order[step] = v
        eliminated[v] = True
        k = 0
        for t in range(start[v], start[v] + length[v]):
            u = pool[t]
            if not eliminated[u]:
                nbrs[k] = u
                k += 1
        for j in range(k):
            u = nbrs[j]
            stamp += 1
            count = 0
            for t in range(start[u], start[u] + length[u]):
                w = pool[t]
                if not eliminated[w] and mark[w] != stamp:
                    mark[w] = stamp
                    buffer[count] = w
                    count += 1
            for i in range(k):
                w = nbrs[i]
                if w != u and mark[w] != stamp:
                    mark[w] = stamp
                    buffer[count] = w
                    count += 1
            if count > room[u]:
                need = top + count + slack
                if need > pool.shape[0]:
                    # twice is enough: need <= pool + n + slack, and the pool starts above 5 n
                    grown = np.empty(2 * pool.shape[0], np.int64)
                    for t in range(top):
                        grown[t] = pool[t]
                    pool = grown
                start[u] = top
                room[u] = count + slack
                top += count + slack
            for t in range(count):
                pool[start[u] + t] = buffer[t]
            old = length[u]
            length[u] = count
            if count != old:
                # out of bucket old, to the front of bucket count
                if prv[u] >= 0:
                    nxt[prv[u]] = nxt[u]
                else:
                    head[old] = nxt[u]
                if nxt[u] >= 0:
                    prv[nxt[u]] = prv[u]
                prv[u] = -1
                nxt[u] = head[count]
                if head[count] >= 0:
                    prv[head[count]] = u
                head[count] = u
                if count < lowest:
                    lowest = count
    return order


class BlockSystem:
    """Layout and factorisation of (J^T J + D) δ = -J^T r over the free poses, in 3×3 blocks.

    The damping D is the solver's (see :meth:`solve`). Only the
    upper block triangle of the symmetrically permuted matrix is stored, column by
    column (diagonal block last), which is what the up-looking Cholesky reads. The
    residual kernel writes into it directly.
    """

    def __init__(self, edges: Edges, column: np.ndarray, num_free: int):
        nb = self.nb = num_free
        ca = column[edges.start]
        cb = column[edges.end]
        both = (ca >= 0) & (cb >= 0)
        lo = np.minimum(ca[both], cb[both])
        hi = np.maximum(ca[both], cb[both])
        keys, inverse = np.unique(lo * nb + hi, return_inverse=True)
        ulo, uhi = keys // nb, keys % nb

        iperm = pair_ordering(ulo, uhi, nb)
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

    def linearize(self, x: np.ndarray, edges: Edges, huber: float) -> tuple[float, np.ndarray, np.ndarray]:
        """(cost, H upper blocks, -g) at x, both in the permuted order."""
        cx = np.empty((len(self.ci), 3, 3))
        rhs = np.empty((self.nb, 3))
        cost = linearize_kernel(x, *edges.kernel_args, huber, self.rs, self.re, self.pos_ss,
                                self.pos_ee, self.pos_off, self.transposed, cx, rhs)
        return cost, cx, rhs

    def solve(self, h: np.ndarray, rhs: np.ndarray, radius: float = math.inf) -> np.ndarray | None:
        """δ (permuted) for (H + D) δ = rhs, or None when the factorisation fails (not positive definite).

        ``h`` is in the layout of :meth:`linearize`'s H (upper block triangle, permuted); D is Ceres'
        Levenberg–Marquardt regularisation for the trust region ``radius``: diag(clamp(diag H, 1e-6, 1e32))
        / radius (none at the default, infinity).
        """
        if not _numeric(self.cp, self.ci, h, self.rp, self.ri, self.lp, self.li, self.lx, self.work,
                        float(radius), MIN_LM_DIAGONAL, MAX_LM_DIAGONAL):
            self.work[:] = 0.0
            return None
        step = rhs.copy()
        _block_solve(self.lp, self.li, self.lx, step)
        return step
