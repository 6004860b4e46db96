"""GMapping's scan matcher and improved proposal, every particle against its own map in parallel.

An endpoint is compared with the walls its particle's map holds around it: within ``kernel`` cells, the
nearest cell that is a wall (hits / visits above ``maps.FULLNESS``) and seen from the side the beam came from
(the cell sqrt(2) cells back along the beam is not occupied), measured to that cell's mean endpoint. Matching
climbs the sum of exp(-d^2 / 2 sigma^2) over the beams from the motion model's pose (six moves, halving the
steps ``iterations`` times), after trying headings around it: the score is flat beyond a cell of each wall, so
the climb alone cannot bring back a heading a key scan's turn left far off. The proposal then samples a small
lattice around the climb's result, weights each sample by its likelihood and by the motion model, draws the
particle's pose from the Gaussian those weights make, and adds the log of their sum to the particle's weight
(Grisetti et al. 2007, "Improved Techniques for Grid Mapping With Rao-Blackwellized Particle Filters").
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit, prange

from carto_cli.core.kernels import register_warm_up
from carto_cli.core.transform import wrap_angle_kernel
from carto_cli.gmapping.maps import MEAN_SCALE, SEEN, TILE, TILE_BITS, TILE_MASK, UNKNOWN, WALL, TiledMaps
from carto_cli.options.schema import GMapping

INV_MEAN_SCALE = 1.0 / MEAN_SCALE  # a wall cell's mean endpoint: (cell + stored * this) * res
FREE_STEP = math.sqrt(2.0)  # cells back along the beam to the cell that must not be a wall
NULL_LIKELIHOOD = -0.5  # an endpoint with no wall near it, before dividing by lsigma
MAX_CLIMBS_PER_LEVEL = 10  # bounds a slow drift at one step size; a level normally stops after a few
# The heading sweep scores every heading on every SWEEP_EVERY-th point and the SWEEP_FINALISTS best on all points:
# a third of the matching time on intel went to the sweep, and a quarter of a scan still ranks headings
# degrees apart (docs/gmapping.md)
SWEEP_EVERY = 4
SWEEP_FINALISTS = 3
# A move is scored only as far as it can still beat the best pose: each point adds at most 1, so once the sum
# plus the points left falls below the best, the rest cannot change the decision (checked every 16 points; the
# slack keeps rounding from ever deciding). 10 % fewer points scored by the climb on replayed orebro and fhw
# inputs, the same poses and scores (docs/gmapping.md).
BOUND_SLACK = 1e-9


@njit(cache=True, inline="always")
def _state(table, p, h, w, state, cx, cy, ox, oy):
    """Cell (cx, cy)'s state in particle p's map, and its tile id (-1: no tile, UNKNOWN)."""
    tx = (cx >> TILE_BITS) - ox
    ty = (cy >> TILE_BITS) - oy
    if tx < 0 or ty < 0 or tx >= w or ty >= h:
        return UNKNOWN, -1
    t = table[p, ty, tx]
    if t < 0:
        return UNKNOWN, -1
    return state[t, cy & TILE_MASK, cx & TILE_MASK], t


@njit(cache=True)
def _back_steps(points, lx, ly, res):
    """For each point (tracking frame), the step from it back towards the sensor at (lx, ly) that reaches the
    cell the beam must have crossed free: ``FREE_STEP`` cells (GMapping's freeCellRatio; one cell often stays
    inside the endpoint's own cell, which then rejected the wall itself: a fifth of the beams of a scan against
    its own map). (0, 0) for a point within a cell of the sensor, which is not matched. A turn of the pose turns
    these steps, so they are made once per scan rather than per pose."""
    out = np.zeros_like(points)
    for i in range(points.shape[0]):
        dx = points[i, 0] - lx
        dy = points[i, 1] - ly
        norm = math.sqrt(dx * dx + dy * dy)
        if norm > res:
            out[i, 0] = FREE_STEP * res * dx / norm
            out[i, 1] = FREE_STEP * res * dy / norm
    return out


@njit(cache=True, inline="always")
def _offsets(kernel):
    """The kernel's cells, row by row: as flat offsets within a tile, and as (dx, dy)."""
    m = (2 * kernel + 1) * (2 * kernel + 1)
    offs = np.empty(m, np.int64)
    offs_x = np.empty(m, np.int64)
    offs_y = np.empty(m, np.int64)
    k = 0
    for ky in range(-kernel, kernel + 1):
        for kx in range(-kernel, kernel + 1):
            offs[k] = (ky << TILE_BITS) + kx
            offs_x[k] = kx
            offs_y[k] = ky
            k += 1
    return offs, offs_x, offs_y


@njit(cache=True)
def _score(table, p, state, flat_state, flat_mean, ox, oy, res, points, back, x, y, th, sigma, offs, offs_x,
           offs_y, kernel, every=1, beat=-1.0):
    """The match score of ``points`` (tracking frame) seen from pose (x, y, th) in particle p's map: the sum over
    the points of exp(-d^2 / 2 sigma^2), d the distance to the nearest wall ``_walls`` would find. ``every`` > 1
    looks at only every ``every``-th point. ``beat`` >= 0: the caller only asks whether the score exceeds
    ``beat``; scoring stops, returning a score below ``beat``, as soon as the points left cannot lift it there.

    The walls are looked up here in place rather than through ``_walls``: the same lookup, but the climb ran 20 %
    slower sharing it with the candidates written out and then searched, 80 % with the distance returned beside
    them (replayed edmonton and orebro inputs)."""
    h, w = table.shape[1], table.shape[2]
    c, s = math.cos(th), math.sin(th)
    inv_two_sigma2 = 0.5 / (sigma * sigma)
    inv_res = 1.0 / res
    score = 0.0
    n = points.shape[0]
    for i in range(0, n, every):
        if beat >= 0.0 and (i & 15) == 0 and score + (n - i) < beat - BOUND_SLACK:
            return score
        px = x + c * points[i, 0] - s * points[i, 1]
        py = y + s * points[i, 0] + c * points[i, 1]
        # The cell one step back towards the sensor: a wall only counts if the beam came from free space.
        bxr, byr = back[i, 0], back[i, 1]
        if bxr == 0.0 and byr == 0.0:
            continue
        ix = int(math.floor(px * inv_res))
        iy = int(math.floor(py * inv_res))
        bx = int(math.floor((px - (c * bxr - s * byr)) * inv_res)) - ix
        by = int(math.floor((py - (s * bxr + c * byr)) * inv_res)) - iy
        best = 1e300
        u0 = ix & TILE_MASK
        v0 = iy & TILE_MASK
        if kernel <= u0 < TILE - kernel and kernel <= v0 < TILE - kernel:  # as in _walls
            tx = (ix >> TILE_BITS) - ox
            ty = (iy >> TILE_BITS) - oy
            t = -1
            if 0 <= tx < w and 0 <= ty < h:
                t = table[p, ty, tx]
            if t >= 0:
                centre = (t << (2 * TILE_BITS)) + (v0 << TILE_BITS) + u0
                ob = (by << TILE_BITS) + bx
                for k in range(offs.shape[0]):
                    q = centre + offs[k]
                    if flat_state[q] != WALL:
                        continue
                    ub = u0 + offs_x[k] + bx
                    vb = v0 + offs_y[k] + by
                    if 0 <= ub < TILE and 0 <= vb < TILE:
                        if flat_state[q + ob] == WALL:
                            continue
                    elif _state(table, p, h, w, state, ix + offs_x[k] + bx, iy + offs_y[k] + by, ox, oy)[0] == WALL:
                        continue
                    mx = (ix + offs_x[k] + flat_mean[2 * q] * INV_MEAN_SCALE) * res
                    my = (iy + offs_y[k] + flat_mean[2 * q + 1] * INV_MEAN_SCALE) * res
                    d2 = (px - mx) * (px - mx) + (py - my) * (py - my)
                    if d2 < best:
                        best = d2
        else:
            for k in range(offs.shape[0]):
                cx = ix + offs_x[k]
                cy = iy + offs_y[k]
                sc, t = _state(table, p, h, w, state, cx, cy, ox, oy)
                if sc != WALL or _state(table, p, h, w, state, cx + bx, cy + by, ox, oy)[0] == WALL:
                    continue
                q = (t << (2 * TILE_BITS)) + ((cy & TILE_MASK) << TILE_BITS) + (cx & TILE_MASK)
                mx = (cx + flat_mean[2 * q] * INV_MEAN_SCALE) * res
                my = (cy + flat_mean[2 * q + 1] * INV_MEAN_SCALE) * res
                d2 = (px - mx) * (px - mx) + (py - my) * (py - my)
                if d2 < best:
                    best = d2
        if best < 1e300:
            score += math.exp(-best * inv_two_sigma2)
    return score


@njit(cache=True, inline="always")
def _walls(table, p, h, w, state, flat_state, flat_mean, ox, oy, res, ix, iy, bx, by, offs, offs_x, offs_y, kernel,
           out):
    """The walls an endpoint in cell (ix, iy) may be measured to: the cells within the kernel that are walls seen
    from free space (the cell (bx, by) from each, towards the sensor, is no wall). Their mean endpoints are
    written to ``out`` in the kernel's order; returns (how many, whether cell (ix, iy) was ever observed)."""
    count = 0
    known = False
    u0 = ix & TILE_MASK
    v0 = iy & TILE_MASK
    if kernel <= u0 < TILE - kernel and kernel <= v0 < TILE - kernel:
        # Most endpoints: the kernel lies in one tile, looked up once.
        tx = (ix >> TILE_BITS) - ox
        ty = (iy >> TILE_BITS) - oy
        t = -1
        if 0 <= tx < w and 0 <= ty < h:
            t = table[p, ty, tx]
        if t >= 0:
            centre = (t << (2 * TILE_BITS)) + (v0 << TILE_BITS) + u0
            known = flat_state[centre] != UNKNOWN
            ob = (by << TILE_BITS) + bx
            for k in range(offs.shape[0]):
                q = centre + offs[k]
                if flat_state[q] != WALL:
                    continue
                # the step back may leave the tile (a wall on its edge): then it is looked up in its own
                ub = u0 + offs_x[k] + bx
                vb = v0 + offs_y[k] + by
                if 0 <= ub < TILE and 0 <= vb < TILE:
                    if flat_state[q + ob] == WALL:
                        continue
                elif _state(table, p, h, w, state, ix + offs_x[k] + bx, iy + offs_y[k] + by, ox, oy)[0] == WALL:
                    continue
                out[count, 0] = (ix + offs_x[k] + flat_mean[2 * q] * INV_MEAN_SCALE) * res
                out[count, 1] = (iy + offs_y[k] + flat_mean[2 * q + 1] * INV_MEAN_SCALE) * res
                count += 1
    else:
        # Near a tile's edge: every cell looked up in its own tile.
        known = _state(table, p, h, w, state, ix, iy, ox, oy)[0] != UNKNOWN
        for k in range(offs.shape[0]):
            cx = ix + offs_x[k]
            cy = iy + offs_y[k]
            sc, t = _state(table, p, h, w, state, cx, cy, ox, oy)
            if sc != WALL or _state(table, p, h, w, state, cx + bx, cy + by, ox, oy)[0] == WALL:
                continue
            q = (t << (2 * TILE_BITS)) + ((cy & TILE_MASK) << TILE_BITS) + (cx & TILE_MASK)
            out[count, 0] = (cx + flat_mean[2 * q] * INV_MEAN_SCALE) * res
            out[count, 1] = (cy + flat_mean[2 * q + 1] * INV_MEAN_SCALE) * res
            count += 1
    return count, known


@dataclass(frozen=True, slots=True)
class ClimbSettings:
    """The climb's settings (gmapping's kernelSize, sigma, lstep, astep, iterations): a run's, the same at every
    scan, so built once rather than passed one by one at each."""

    kernel: int  # cells searched around an endpoint for a wall
    sigma: float  # m: a beam scores exp(-d^2 / 2 sigma^2)
    lstep: float  # m: the first translational step
    astep: float  # rad: the first rotational step
    iterations: int  # times the steps are halved

    @classmethod
    def of(cls, g: GMapping) -> ClimbSettings:
        return cls(g.kernelSize, g.sigma, g.lstep, g.astep, g.iterations)


def climb(maps: TiledMaps, res: float, points: np.ndarray, lx: float, ly: float, poses: np.ndarray,
          sweeps: np.ndarray, settings: ClimbSettings) -> tuple[np.ndarray, np.ndarray]:
    """Hill-climb every particle's pose on its own map of ``maps`` (cells of ``res``), first trying headings every
    astep / 2 within +-``sweeps[p]`` of its own (0: none). Returns (poses, scores)."""
    ox, oy = maps.tile_origin
    c = settings
    # The maps' cells come flat from here: reshaping in the kernel compiled numba's shape checks and their
    # messages (several seconds of a fresh install's compiling)
    return _climb(maps.table, maps.state, maps.state.reshape(-1), maps.mean.reshape(-1), ox, oy, res, points, lx, ly,
                  poses, c.kernel, c.sigma, c.lstep, c.astep, c.iterations, sweeps)


@njit(cache=True, parallel=True)
def _climb(table, state, flat_state, flat_mean, ox, oy, res, points, lx, ly, poses, kernel, sigma, lstep, astep,
           iterations, sweeps):
    n_particles = poses.shape[0]
    out = poses.copy()
    scores = np.zeros(n_particles)
    back = _back_steps(points, lx, ly, res)
    offs, offs_x, offs_y = _offsets(kernel)
    # Every call passes every argument, as plain (not literal) integers: numba compiles a function once per
    # distinct signature, 2 s each on a fresh install (six of them before)
    every_point, sweep_every = np.int64(1), np.int64(SWEEP_EVERY)
    for p in prange(n_particles):
        x, y, th = poses[p, 0], poses[p, 1], poses[p, 2]
        best = _score(table, p, state, flat_state, flat_mean, ox, oy, res, points, back, x, y, th, sigma, offs,
                      offs_x, offs_y, kernel, every_point, -1.0)
        step = 0.5 * astep
        n_sweep = int(sweeps[p] / step)
        th0 = th
        if n_sweep > 0:
            # Every heading on a quarter of the points, then the few best on all of them
            coarse = np.empty(2 * n_sweep + 1)
            for k in range(-n_sweep, n_sweep + 1):
                coarse[k + n_sweep] = _score(table, p, state, flat_state, flat_mean, ox, oy, res, points, back, x,
                                             y, th0 + k * step, sigma, offs, offs_x, offs_y, kernel, sweep_every,
                                             -1.0)
            order = np.argsort(-coarse)
            for r in range(min(SWEEP_FINALISTS, order.shape[0])):
                k = order[r] - n_sweep
                if k == 0:
                    continue
                sc = _score(table, p, state, flat_state, flat_mean, ox, oy, res, points, back, x, y, th0 + k * step,
                            sigma, offs, offs_x, offs_y, kernel, every_point, best)
                if sc > best:
                    best = sc
                    th = th0 + k * step
        ls = lstep
        a = astep
        level = 0
        climbs = 0
        undo = -1  # the move back to where the last step came from: known to score lower, not evaluated
        while level <= iterations:
            climbs += 1
            bx, by, bt = x, y, th
            moved = False
            taken = -1
            for move in range(6):
                if move == undo:
                    continue
                cx, cy, ct = x, y, th
                if move == 0:
                    cx += ls
                elif move == 1:
                    cx -= ls
                elif move == 2:
                    cy += ls
                elif move == 3:
                    cy -= ls
                elif move == 4:
                    ct += a
                else:
                    ct -= a
                sc = _score(table, p, state, flat_state, flat_mean, ox, oy, res, points, back, cx, cy, ct, sigma,
                            offs, offs_x, offs_y, kernel, every_point, best)
                if sc > best:
                    best = sc
                    bx, by, bt = cx, cy, ct
                    moved = True
                    taken = move
            undo = taken ^ 1 if moved else -1  # moves come in opposite pairs: 0/1, 2/3, 4/5
            if moved:
                x, y, th = bx, by, bt
            if not moved or climbs >= MAX_CLIMBS_PER_LEVEL:
                undo = -1
                climbs = 0
                level += 1
                ls *= 0.5
                a *= 0.5
        out[p, 0] = x
        out[p, 1] = y
        out[p, 2] = th
        scores[p] = best
    return out, scores


@njit(cache=True, inline="always")
def _lattice(table, p, state, flat_state, flat_mean, ox, oy, res, points, back, x0, y0, th0, nl, lin_step, na,
             ang_step, lsigma, stride, unknown_ll, offs, offs_x, offs_y, kernel):
    """The log-likelihood of every ``stride``-th point at each pose of the lattice around (x0, y0, th0): x and y
    ``lin_step`` apart within +-``nl`` steps, headings ``ang_step`` apart within +-``na``, indexed x, y, heading
    (the last fastest). Each point adds -d^2 / lsigma for its nearest wall at distance d, NULL_LIKELIHOOD / lsigma
    without one in a known cell, ``unknown_ll`` in a cell never observed.

    The lattice's positions share each point's turn, and most of them its cell: an endpoint moved by a fifth of a
    cell stays in it, so the walls around it are looked up once per cell (and step back) that the positions of
    one heading meet, about three of nine (the proposal 40 % faster on replayed edmonton, orebro and fhw inputs;
    docs/gmapping.md). Each pose's sum runs over the points in order, as scoring one pose at a time would."""
    h, w = table.shape[1], table.shape[2]
    inv_res = 1.0 / res
    n_lin = 2 * nl + 1
    n_ang = 2 * na + 1
    logs = np.zeros(n_lin * n_lin * n_ang)
    keys = np.empty((n_lin * n_lin, 4), np.int64)  # cell (ix, iy) and step back (bx, by) of each lookup made
    found = np.empty((n_lin * n_lin, offs.shape[0], 2))
    counts = np.empty(n_lin * n_lin, np.int64)
    knowns = np.empty(n_lin * n_lin, np.bool_)
    col_px = np.empty(n_lin)
    col_ix = np.empty(n_lin, np.int64)
    col_bx = np.empty(n_lin, np.int64)
    for a in range(-na, na + 1):
        th = th0 + a * ang_step
        c, s = math.cos(th), math.sin(th)
        for i in range(0, points.shape[0], stride):
            bxr, byr = back[i, 0], back[i, 1]
            if bxr == 0.0 and byr == 0.0:
                continue
            # the same sums as px = x + c * u - s * v, py = y + s * u + c * v at each lattice pose
            cu = c * points[i, 0]
            sv = s * points[i, 1]
            su = s * points[i, 0]
            cv = c * points[i, 1]
            back_x = c * bxr - s * byr
            back_y = s * bxr + c * byr
            for li in range(n_lin):
                px = x0 + (li - nl) * lin_step + cu - sv
                col_px[li] = px
                col_ix[li] = int(math.floor(px * inv_res))
                col_bx[li] = int(math.floor((px - back_x) * inv_res)) - col_ix[li]
            n_keys = 0
            for lj in range(n_lin):
                py = y0 + (lj - nl) * lin_step + su + cv
                iy = int(math.floor(py * inv_res))
                by = int(math.floor((py - back_y) * inv_res)) - iy
                for li in range(n_lin):
                    px, ix, bx = col_px[li], col_ix[li], col_bx[li]
                    slot = -1
                    for q in range(n_keys):
                        if keys[q, 0] == ix and keys[q, 1] == iy and keys[q, 2] == bx and keys[q, 3] == by:
                            slot = q
                            break
                    if slot < 0:
                        slot = n_keys
                        n_keys += 1
                        keys[slot, 0], keys[slot, 1], keys[slot, 2], keys[slot, 3] = ix, iy, bx, by
                        counts[slot], knowns[slot] = _walls(table, p, h, w, state, flat_state, flat_mean, ox, oy, res,
                                                            ix, iy, bx, by, offs, offs_x, offs_y, kernel,
                                                            found[slot])
                    best = 1e300
                    for q in range(counts[slot]):
                        mx = found[slot, q, 0]
                        my = found[slot, q, 1]
                        d2 = (px - mx) * (px - mx) + (py - my) * (py - my)
                        if d2 < best:
                            best = d2
                    k = (li * n_lin + lj) * n_ang + a + na
                    if best < 1e300:
                        logs[k] -= best / lsigma
                    elif knowns[slot]:
                        logs[k] += NULL_LIKELIHOOD / lsigma
                    else:
                        logs[k] += unknown_ll
    return logs


# numba's prange compiles slowly (23 s for this kernel on a fresh install), but its outlined loop ran faster than the
# same loop split over threads of ours (nogil kernels): 4.5-4.8 against 6.2-6.6 ms for 30 particles on one thread,
# alternating in one process, and a pool of ours beside numba's OpenMP threads (which spin after each parallel
# loop) made a GMapping run slower still.
@njit(cache=True, parallel=True)
def propose(table, state, mean, ox, oy, res, points, lx, ly, modes, means, sigmas, normals, kernel, lsigma, stride,
            unknown_ll, lin_range, lin_step, ang_range, ang_step):
    """The improved proposal around each particle's match.

    ``modes``: the climbs' poses; ``means`` and ``sigmas`` (x, y, theta standard deviations): the motion
    model's Gaussian for each particle; ``normals``: standard normal draws (particles x 3) that make the
    sample. The likelihood counts every ``stride``-th point. Returns (poses, log weight increments,
    log-likelihoods at the modes).
    """
    n_particles = modes.shape[0]
    nl = int(math.floor(lin_range / lin_step + 1e-9))
    na = int(math.floor(ang_range / ang_step + 1e-9))
    m = (2 * nl + 1) * (2 * nl + 1) * (2 * na + 1)
    out = modes.copy()
    log_eta = np.zeros(n_particles)
    back = _back_steps(points, lx, ly, res)
    flat_state = state.reshape(-1)
    flat_mean = mean.reshape(-1)
    offs, offs_x, offs_y = _offsets(kernel)
    at_mode = np.zeros(n_particles)
    for p in prange(n_particles):
        xs = np.empty((m, 3))
        logs = _lattice(table, p, state, flat_state, flat_mean, ox, oy, res, points, back, modes[p, 0], modes[p, 1],
                        modes[p, 2], nl, lin_step, na, ang_step, lsigma, stride, unknown_ll, offs, offs_x, offs_y,
                        kernel)
        k = 0
        for i in range(-nl, nl + 1):
            for j in range(-nl, nl + 1):
                for a in range(-na, na + 1):
                    x = modes[p, 0] + i * lin_step
                    y = modes[p, 1] + j * lin_step
                    th = modes[p, 2] + a * ang_step
                    ll = logs[k]
                    if i == 0 and j == 0 and a == 0:
                        at_mode[p] = ll
                    ex = (x - means[p, 0]) / sigmas[p, 0]
                    ey = (y - means[p, 1]) / sigmas[p, 1]
                    d = th - means[p, 2]
                    d = wrap_angle_kernel(d)
                    et = d / sigmas[p, 2]
                    xs[k, 0] = x
                    xs[k, 1] = y
                    xs[k, 2] = th
                    logs[k] = ll - 0.5 * (ex * ex + ey * ey + et * et)
                    k += 1
        top = logs.max()
        wsum = 0.0
        mu = np.zeros(3)
        wts = np.empty(m)
        for k in range(m):
            wts[k] = math.exp(logs[k] - top)
            wsum += wts[k]
            for d in range(3):
                mu[d] += wts[k] * xs[k, d]
        mu /= wsum
        cov = np.zeros((3, 3))
        for k in range(m):
            for r in range(3):
                for q in range(3):
                    cov[r, q] += wts[k] * (xs[k, r] - mu[r]) * (xs[k, q] - mu[q])
        cov /= wsum
        # A lattice this fine resolves the peak's width only when the peak is wider than a step:
        # keep a floor of a tenth of a step so the Cholesky factor exists.
        cov[0, 0] += (0.1 * lin_step) ** 2
        cov[1, 1] += (0.1 * lin_step) ** 2
        cov[2, 2] += (0.1 * ang_step) ** 2
        chol = np.linalg.cholesky(cov)
        for r in range(3):
            v = mu[r]
            for q in range(r + 1):
                v += chol[r, q] * normals[p, q]
            out[p, r] = v
        log_eta[p] = top + math.log(wsum)
    return out, log_eta, at_mode


def _toy_map():
    """Two particles sharing one tile with a wall across it, built without the map update's kernels (a helper
    process compiling the matcher's warm-up need not compile those too), and a scan that sees it."""
    maps = TiledMaps(2, 0.05, capacity=1)
    maps.table = np.zeros((2, 1, 1), np.int32)
    maps.state[0, 20, :] = WALL
    maps.state[0, :20, :] = SEEN
    maps.mean[0, 20, :, 0] = (np.arange(TILE) + 0.5) * 0.05
    maps.mean[0, 20, :, 1] = 20.5 * 0.05
    points = np.stack([(np.arange(8) + 4.5) * 0.05, np.full(8, 20.5 * 0.05)], axis=1)
    return maps, points


@register_warm_up(system="gmapping")
def warm_up_climb() -> None:
    """The climb's kernels (a warm-up of its own: a fresh install compiles it beside the proposal's)."""
    maps, points = _toy_map()
    climb(maps, 0.05, points, 0.0, 0.0, np.zeros((2, 3)), np.full(2, 0.05), ClimbSettings(1, 0.05, 0.05, 0.05, 1))


@register_warm_up(system="gmapping")
def warm_up_proposal() -> None:
    """The proposal's kernel (23 s to compile on a fresh install)."""
    maps, points = _toy_map()
    poses = np.zeros((2, 3))
    propose(maps.table, maps.state, maps.mean, 0, 0, 0.05, points, 0.0, 0.0, poses, poses, np.full((2, 3), 0.1),
            np.zeros((2, 3)), 1, 0.075, 1, -0.1, 0.01, 0.01, 0.005, 0.005)
