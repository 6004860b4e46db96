"""Plain-Python references for carto_cli.gmapping.maps and .matcher: the cells a segment crosses, the counts a
bundle of rays leaves in one particle's map, the match score, the hill climb and the proposal's log-likelihood.

The cells are found from where the segment crosses the grid lines (every crossing parameter, sorted),
not by stepping from cell to cell as the kernel does, so the two share no arithmetic. Where a segment
passes exactly through a grid corner this reference goes diagonally, while a 4-connected walk steps
through one of the two side cells: compare on segments that pass no corner (random ones), and keep
sensors off the lattice (a ray starting on a cell corner is the same tie).
"""
import math
from collections import defaultdict

import numpy as np

from carto_cli.gmapping.maps import MEAN_SCALE, TILE, TILE_BITS, UNKNOWN, WALL


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
            mx, my = mean_endpoint(maps, t, *cell)
            out[cell] = [n, int(maps.visits[t, v, u]), n * mx, n * my]
    return out


def mean_endpoint(maps, tile, cx, cy):
    """World (x, y) of the mean endpoint kept by cell (cx, cy), which lies in pool tile ``tile``."""
    m = maps.mean[tile, cy & (TILE - 1), cx & (TILE - 1)]
    return ((cx + float(m[0]) / MEAN_SCALE) * maps.resolution, (cy + float(m[1]) / MEAN_SCALE) * maps.resolution)


def _state_at(maps, particle, cx, cy):
    """(state, tile) of cell (cx, cy) in ``particle``'s map: (UNKNOWN, -1) where it has no tile."""
    ox, oy = maps.tile_origin
    tx, ty = (cx >> TILE_BITS) - ox, (cy >> TILE_BITS) - oy
    h, w = maps.table.shape[1:]
    if not (0 <= tx < w and 0 <= ty < h) or maps.table[particle, ty, tx] < 0:
        return UNKNOWN, -1
    t = int(maps.table[particle, ty, tx])
    return int(maps.state[t, cy & (TILE - 1), cx & (TILE - 1)]), t


def nearest_wall(maps, particle, point, sensor, pose, kernel):
    """For one point (tracking frame, the sensor at ``sensor``) seen from ``pose``: the squared distance to the
    nearest wall's mean endpoint among the cells within ``kernel`` of the point's cell whose cell sqrt(2) cells
    back towards the sensor is not a wall (None: no such wall, or the point within a cell of the sensor), and
    whether the point's cell was ever observed. Each cell looked up on its own through the maps' arrays (the
    kernels read a tile's cells directly where the neighbourhood fits in one)."""
    res = maps.resolution
    x, y, th = (float(v) for v in pose)
    c, s = math.cos(th), math.sin(th)
    inv_res = 1.0 / res
    ux, uy = float(point[0]), float(point[1])
    dx, dy = ux - sensor[0], uy - sensor[1]
    norm = math.sqrt(dx * dx + dy * dy)
    if norm <= res:
        return None, None
    bxr, byr = math.sqrt(2.0) * res * dx / norm, math.sqrt(2.0) * res * dy / norm
    px = x + c * ux - s * uy
    py = y + s * ux + c * uy
    ix, iy = math.floor(px * inv_res), math.floor(py * inv_res)
    bx = math.floor((px - (c * bxr - s * byr)) * inv_res) - ix
    by = math.floor((py - (s * bxr + c * byr)) * inv_res) - iy
    best = None
    for ky in range(-kernel, kernel + 1):
        for kx in range(-kernel, kernel + 1):
            state, t = _state_at(maps, particle, ix + kx, iy + ky)
            if state != WALL or _state_at(maps, particle, ix + kx + bx, iy + ky + by)[0] == WALL:
                continue
            mx, my = mean_endpoint(maps, t, ix + kx, iy + ky)
            d2 = (px - mx) * (px - mx) + (py - my) * (py - my)
            best = d2 if best is None else min(best, d2)
    return best, _state_at(maps, particle, ix, iy)[0] != UNKNOWN


def match_score(maps, particle, points, sensor, pose, kernel, sigma):
    """GMapping's match score of ``points`` (tracking frame, the sensor at ``sensor``) at ``pose``: the sum over
    the points of exp(-d^2 / 2 sigma^2), d the distance to the nearest wall (``nearest_wall``), every point
    scored in full."""
    inv_two_sigma2 = 0.5 / (sigma * sigma)
    score = 0.0
    for point in points:
        best, _ = nearest_wall(maps, particle, point, sensor, pose, kernel)
        if best is not None:
            score += math.exp(-best * inv_two_sigma2)
    return score


def log_likelihood(maps, particle, points, sensor, pose, kernel, lsigma, stride, unknown_ll, null_likelihood):
    """GMapping's log-likelihood of every ``stride``-th point at ``pose``: -d^2 / lsigma for the nearest wall
    (``nearest_wall``), ``null_likelihood`` / lsigma without one in an observed cell, ``unknown_ll`` in a cell
    never observed; a point within a cell of the sensor counts nothing."""
    total = 0.0
    for point in points[::stride]:
        best, known = nearest_wall(maps, particle, point, sensor, pose, kernel)
        if best is not None:
            total -= best / lsigma
        elif known is not None:
            total += null_likelihood / lsigma if known else unknown_ll
    return total


def hill_climb(maps, particle, points, sensor, start, kernel, sigma, lstep, astep, iterations, max_climbs):
    """GMapping's hill climb without a heading sweep, every move scored in full: from ``start``, the best of the
    six moves (+-lstep in x and y, +-astep in heading, never straight back) while one improves, at most
    ``max_climbs`` times per step size, then the steps halved, ``iterations`` times. Returns (pose, score)."""
    pose = np.array(start, dtype=np.float64)
    best = match_score(maps, particle, points, sensor, pose, kernel, sigma)
    ls, a, level, climbs, undo = lstep, astep, 0, 0, -1
    while level <= iterations:
        climbs += 1
        taken = -1
        chosen = pose
        for move in range(6):
            if move == undo:
                continue
            trial = pose.copy()
            axis, sign = (0, 1, 2)[move // 2], (1.0, -1.0)[move % 2]
            trial[axis] += sign * (ls if axis < 2 else a)
            sc = match_score(maps, particle, points, sensor, trial, kernel, sigma)
            if sc > best:
                best, chosen, taken = sc, trial, move
        undo = taken ^ 1 if taken >= 0 else -1
        pose = chosen
        if taken < 0 or climbs >= max_climbs:
            undo, climbs, level = -1, 0, level + 1
            ls *= 0.5
            a *= 0.5
    return pose, best
