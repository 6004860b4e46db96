"""Numba kernels the scan matchers share: one scan rotated and discretised to grid cells per candidate angle."""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["discretize"]


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
