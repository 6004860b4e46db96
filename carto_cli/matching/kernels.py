"""Numba kernels the scan matchers share: one scan rotated and discretised to grid cells per candidate angle, and
the 3x3 solve of the least-squares matchers' normal equations."""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["discretize", "solve3"]


@njit(cache=True, nogil=True)
def discretize(points, angles, x0, y0, ox, oy, inv_res):
    """Cell indices (num_angles, n, 2) of the scan rotated by each angle and moved to (x0, y0).

    ``(ox, oy)`` is the grid's origin and ``inv_res`` one over its resolution. Every
    translation candidate of a matcher is then an integer offset of these cells. The
    angles are passed in rather than derived from a step, so that callers computing
    the same angle get bit-identical cells (a multilevel search rotates by a subset
    of the plain search's angles).
    """
    n = points.shape[0]
    cells = np.empty((angles.shape[0], n, 2), dtype=np.int64)
    for k in range(angles.shape[0]):
        c = np.cos(angles[k])
        s = np.sin(angles[k])
        for i in range(n):
            wx = c * points[i, 0] - s * points[i, 1] + x0
            wy = s * points[i, 0] + c * points[i, 1] + y0
            cells[k, i, 0] = np.int64(np.floor((wx - ox) * inv_res))
            cells[k, i, 1] = np.int64(np.floor((wy - oy) * inv_res))
    return cells


@njit(cache=True, nogil=True)
def solve3(a, b, out):
    """``out`` = the solution of the 3x3 system ``a x = b`` by Cramer's rule; False (``out`` untouched) when ``a``
    is singular to 1e-14 of its diagonal's product."""
    m00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    m01 = a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0]
    m02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * m00 - a[0, 1] * m01 + a[0, 2] * m02
    scale = abs(a[0, 0] * a[1, 1] * a[2, 2]) + 1e-300
    if not abs(det) > 1e-14 * scale:
        return False
    out[0] = (b[0] * m00 - a[0, 1] * (b[1] * a[2, 2] - a[1, 2] * b[2])
              + a[0, 2] * (b[1] * a[2, 1] - a[1, 1] * b[2])) / det
    out[1] = (a[0, 0] * (b[1] * a[2, 2] - a[1, 2] * b[2]) - b[0] * m01
              + a[0, 2] * (a[1, 0] * b[2] - b[1] * a[2, 0])) / det
    out[2] = (a[0, 0] * (a[1, 1] * b[2] - b[1] * a[2, 1]) - a[0, 1] * (a[1, 0] * b[2] - b[1] * a[2, 0])
              + b[0] * m02) / det
    return True
