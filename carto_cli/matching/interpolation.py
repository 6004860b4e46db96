"""Bicubic interpolation of a grid's correspondence cost (1 - p), value and gradient.

Same scheme as ``ceres::BiCubicInterpolator`` used by Cartographer's Ceres
scan matcher: Catmull-Rom (cubic Hermite) splines along columns, then along
rows, with samples at cell centres. Unknown cells and cells outside the grid
read ``MAX_CORRESPONDENCE_COST`` (0.9), so the optimiser is never pulled
towards unexplored space. The interpolant is C1, which is what makes the
analytic Jacobian of the least-squares matcher well behaved.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from carto_cli.grid.probability_grid import MAX_CORRESPONDENCE_COST, VALUE_TO_CORRESPONDENCE_COST


@njit(cache=True, nogil=True)
def _masked(valid, value):
    return value if valid else MAX_CORRESPONDENCE_COST


@njit(cache=True, nogil=True)
def _hermite(p0, p1, p2, p3, x):
    a = 0.5 * (-p0 + 3.0 * p1 - 3.0 * p2 + p3)
    b = 0.5 * (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3)
    c = 0.5 * (-p0 + p2)
    f = p1 + x * (c + x * (b + x * a))
    dfdx = c + x * (2.0 * b + 3.0 * a * x)
    return f, dfdx


@njit(cache=True, nogil=True)
def cost_and_gradient(cells, table, ox, oy, inv_resolution, x, y):
    """Interpolated cost at world (x, y) and its gradient in world units (per metre)."""
    # Cell (ix, iy) has its centre at continuous index (ix, iy).
    c = (x - ox) * inv_resolution - 0.5
    r = (y - oy) * inv_resolution - 0.5
    c1 = np.int64(np.floor(c))
    r1 = np.int64(np.floor(r))
    fc = c - c1
    fr = r - r1
    ny, nx = cells.shape
    c0, c2, c3 = c1 - 1, c1 + 1, c1 + 2
    r0, r2, r3 = r1 - 1, r1 + 1, r1 + 2
    if r3 < 0 or c3 < 0 or r0 >= ny or c0 >= nx:
        return MAX_CORRESPONDENCE_COST, 0.0, 0.0
    # Indices are clamped so every read is in bounds, and reads outside the grid are then
    # replaced by the unknown cost; all with scalars, as a call passing the arrays per
    # sample costs a refcount round trip.
    vr0, vr1, vr2, vr3 = r0 >= 0, 0 <= r1 < ny, 0 <= r2 < ny, r3 < ny
    vc0, vc1, vc2, vc3 = c0 >= 0, 0 <= c1 < nx, 0 <= c2 < nx, c3 < nx
    r0, r1, r2, r3 = max(r0, 0), min(max(r1, 0), ny - 1), min(max(r2, 0), ny - 1), min(r3, ny - 1)
    c0, c1, c2, c3 = max(c0, 0), min(max(c1, 0), nx - 1), min(max(c2, 0), nx - 1), min(c3, nx - 1)
    f0, d0 = _hermite(_masked(vr0 and vc0, table[cells[r0, c0]]), _masked(vr0 and vc1, table[cells[r0, c1]]),
                      _masked(vr0 and vc2, table[cells[r0, c2]]), _masked(vr0 and vc3, table[cells[r0, c3]]), fc)
    f1, d1 = _hermite(_masked(vr1 and vc0, table[cells[r1, c0]]), _masked(vr1 and vc1, table[cells[r1, c1]]),
                      _masked(vr1 and vc2, table[cells[r1, c2]]), _masked(vr1 and vc3, table[cells[r1, c3]]), fc)
    f2, d2 = _hermite(_masked(vr2 and vc0, table[cells[r2, c0]]), _masked(vr2 and vc1, table[cells[r2, c1]]),
                      _masked(vr2 and vc2, table[cells[r2, c2]]), _masked(vr2 and vc3, table[cells[r2, c3]]), fc)
    f3, d3 = _hermite(_masked(vr3 and vc0, table[cells[r3, c0]]), _masked(vr3 and vc1, table[cells[r3, c1]]),
                      _masked(vr3 and vc2, table[cells[r3, c2]]), _masked(vr3 and vc3, table[cells[r3, c3]]), fc)
    f, dfdr = _hermite(f0, f1, f2, f3, fr)
    dfdc, _ = _hermite(d0, d1, d2, d3, fr)
    return f, dfdc * inv_resolution, dfdr * inv_resolution


@njit(cache=True, nogil=True)
def _interpolate_many(cells, table, ox, oy, inv_resolution, points):
    n = points.shape[0]
    values = np.empty(n)
    gradient = np.empty((n, 2))
    for i in range(n):
        f, gx, gy = cost_and_gradient(cells, table, ox, oy, inv_resolution, points[i, 0], points[i, 1])
        values[i] = f
        gradient[i, 0] = gx
        gradient[i, 1] = gy
    return values, gradient


def interpolate_correspondence_cost(grid, points):
    """(values (n,), gradient (n, 2)) of the bicubic cost at world points (grid frame)."""
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
    return _interpolate_many(grid.cells, VALUE_TO_CORRESPONDENCE_COST, grid.origin[0], grid.origin[1],
                             1.0 / grid.resolution, pts)
