"""Plain-Python references for carto_cli.gmapping.maps: the cells a segment crosses, and the counts a
bundle of rays leaves in one particle's map.

The cells are found from where the segment crosses the grid lines (every crossing parameter, sorted),
not by stepping from cell to cell as the kernel does, so the two share no arithmetic. Where a segment
passes exactly through a grid corner this reference goes diagonally, while a 4-connected walk steps
through one of the two side cells: compare on segments that pass no corner (random ones), and keep
sensors off the lattice (a ray starting on a cell corner is the same tie).
"""
import math
from collections import defaultdict

import numpy as np

from carto_cli.gmapping.maps import TILE


def crossed_cells(x0, y0, x1, y1, size):
    """Cells (ix, iy) of side ``size`` the segment passes through, in order; the first holds (x0, y0),
    the last (x1, y1) (cells are ``floor(coordinate / size)``)."""
    dx, dy = x1 - x0, y1 - y0
    ts = [0.0, 1.0]
    for a0, d in ((x0, dx), (y0, dy)):
        if d == 0.0:
            continue
        lo, hi = sorted((a0 / size, (a0 + d) / size))
        for k in range(math.floor(lo), math.ceil(hi) + 1):
            t = (k * size - a0) / d
            if 0.0 < t < 1.0:
                ts.append(t)
    ts.sort()
    cells = [(math.floor(x0 / size), math.floor(y0 / size))]
    for a, b in zip(ts, ts[1:]):
        if b > a:
            m = 0.5 * (a + b)
            cell = (math.floor((x0 + m * dx) / size), math.floor((y0 + m * dy) / size))
            if cell != cells[-1]:
                cells.append(cell)
    end = (math.floor(x1 / size), math.floor(y1 / size))
    if end != cells[-1]:
        cells.append(end)
    return cells


def ray_counts(bundles, resolution):
    """{cell: [hits, visits, endpoint sum x, endpoint sum y]} of one particle's map after inserting each
    (pose, origin, ends, hit) of ``bundles`` in turn: every cell a ray crosses gets a visit, the last one
    also a hit and the endpoint when the ray ends in a wall."""
    counts = defaultdict(lambda: [0, 0, 0.0, 0.0])
    for pose, origin, ends, hit in bundles:
        x, y, th = (float(v) for v in pose)
        c, s = math.cos(th), math.sin(th)
        sx = x + c * origin[0] - s * origin[1]
        sy = y + s * origin[0] + c * origin[1]
        for (ux, uy), h in zip(np.asarray(ends, dtype=np.float64), hit):
            ex = x + c * ux - s * uy
            ey = y + s * ux + c * uy
            cells = crossed_cells(sx, sy, ex, ey, resolution)
            for cell in cells:
                counts[cell][1] += 1
            if h:
                last = counts[cells[-1]]
                last[0] += 1
                last[2] += ex
                last[3] += ey
    return dict(counts)


def map_counts(maps, particle):
    """The same dictionary read out of a ``TiledMaps`` (endpoint sum: mean x hits): every cell of ``particle``'s map
    with a visit."""
    ox, oy = maps.tile_origin
    out = {}
    for ty, tx in np.argwhere(maps.table[particle] >= 0):
        t = maps.table[particle, ty, tx]
        for v, u in np.argwhere(maps.visits[t] > 0):
            cell = (int((ox + tx) * TILE + u), int((oy + ty) * TILE + v))
            n = int(maps.hits[t, v, u])
            out[cell] = [n, int(maps.visits[t, v, u]), n * float(maps.mean[t, v, u, 0]),
                         n * float(maps.mean[t, v, u, 1])]
    return out
