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

import numpy as np
from numba import njit, prange

from carto_cli.core.transform import wrap_angle_kernel
from carto_cli.gmapping.maps import TILE, TILE_BITS, TILE_MASK, UNKNOWN, WALL

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


@njit(cache=True)
def _evaluate(table, p, state, mean, ox, oy, res, points, back, x, y, th, kernel, sigma, lsigma, stride,
              unknown_ll, every=1, beat=-1.0):
    """(score, log-likelihood) of ``points`` (tracking frame) seen from pose (x, y, th) in particle p's map;
    the likelihood uses every ``stride``-th point, and ``unknown_ll`` for one with no wall near it that fell
    in a cell never observed (GMapping: the same as one in free space). ``every`` > 1 looks at only every
    ``every``-th point (both values). ``beat`` >= 0: the caller only asks whether the score exceeds ``beat``;
    scoring stops, returning a score below ``beat``, as soon as the points left cannot lift it there."""
    h, w = table.shape[1], table.shape[2]
    c, s = math.cos(th), math.sin(th)
    inv_two_sigma2 = 0.5 / (sigma * sigma)
    inv_res = 1.0 / res
    score = 0.0
    loglik = 0.0
    n = points.shape[0]
    for i in range(0, n, every):
        if beat >= 0.0 and (i & 15) == 0 and score + (n - i) < beat - BOUND_SLACK:
            return score, loglik
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
        known = False
        u0 = ix & TILE_MASK
        v0 = iy & TILE_MASK
        reach = kernel + 2  # the kernel and the step back stay within this many cells of the endpoint
        if reach <= u0 < TILE - reach and reach <= v0 < TILE - reach:
            # Most endpoints: the whole neighbourhood lies in one tile, looked up once.
            tx = (ix >> TILE_BITS) - ox
            ty = (iy >> TILE_BITS) - oy
            t = -1
            if 0 <= tx < w and 0 <= ty < h:
                t = table[p, ty, tx]
            if t >= 0:
                ts = state[t]
                tm = mean[t]
                known = ts[v0, u0] != UNKNOWN
                for ky in range(-kernel, kernel + 1):
                    for kx in range(-kernel, kernel + 1):
                        u = u0 + kx
                        v = v0 + ky
                        if ts[v, u] != WALL or ts[v + by, u + bx] == WALL:
                            continue
                        mx = tm[v, u, 0]
                        my = tm[v, u, 1]
                        d2 = (px - mx) * (px - mx) + (py - my) * (py - my)
                        if d2 < best:
                            best = d2
        else:
            known = _state(table, p, h, w, state, ix, iy, ox, oy)[0] != UNKNOWN
            for ky in range(-kernel, kernel + 1):
                for kx in range(-kernel, kernel + 1):
                    cx = ix + kx
                    cy = iy + ky
                    sc, t = _state(table, p, h, w, state, cx, cy, ox, oy)
                    if sc != WALL or _state(table, p, h, w, state, cx + bx, cy + by, ox, oy)[0] == WALL:
                        continue
                    u = (cx & TILE_MASK)
                    v = (cy & TILE_MASK)
                    mx = mean[t, v, u, 0]
                    my = mean[t, v, u, 1]
                    d2 = (px - mx) * (px - mx) + (py - my) * (py - my)
                    if d2 < best:
                        best = d2
        if best < 1e300:
            score += math.exp(-best * inv_two_sigma2)
        if i % stride == 0:
            if best < 1e300:
                loglik -= best / lsigma
            elif known:
                loglik += NULL_LIKELIHOOD / lsigma
            else:
                loglik += unknown_ll
    return score, loglik


@njit(cache=True, parallel=True)
def climb(table, state, mean, ox, oy, res, points, lx, ly, poses, kernel, sigma, lstep, astep, iterations,
          sweeps):
    """Hill-climb every particle's pose on its own map, first trying headings every astep / 2 within
    +-``sweeps[p]`` of its own (0: none). Returns (poses, scores)."""
    n_particles = poses.shape[0]
    out = poses.copy()
    scores = np.zeros(n_particles)
    back = _back_steps(points, lx, ly, res)
    for p in prange(n_particles):
        x, y, th = poses[p, 0], poses[p, 1], poses[p, 2]
        best, _ = _evaluate(table, p, state, mean, ox, oy, res, points, back, x, y, th, kernel, sigma,
                            1.0, 1, 0.0)
        step = 0.5 * astep
        n_sweep = int(sweeps[p] / step)
        th0 = th
        if n_sweep > 0:
            # Every heading on a quarter of the points, then the few best on all of them
            coarse = np.empty(2 * n_sweep + 1)
            for k in range(-n_sweep, n_sweep + 1):
                coarse[k + n_sweep], _ = _evaluate(table, p, state, mean, ox, oy, res, points, back, x, y,
                                                   th0 + k * step, kernel, sigma, 1.0, 1, 0.0, SWEEP_EVERY)
            order = np.argsort(-coarse)
            for r in range(min(SWEEP_FINALISTS, order.shape[0])):
                k = order[r] - n_sweep
                if k == 0:
                    continue
                sc, _ = _evaluate(table, p, state, mean, ox, oy, res, points, back, x, y, th0 + k * step,
                                  kernel, sigma, 1.0, 1, 0.0, 1, best)
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
                sc, _ = _evaluate(table, p, state, mean, ox, oy, res, points, back, cx, cy, ct, kernel,
                                  sigma, 1.0, 1, 0.0, 1, best)
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


@njit(cache=True, parallel=True)
def propose(table, state, mean, ox, oy, res, points, lx, ly, modes, means, sigmas, normals, kernel, sigma,
            lsigma, stride, unknown_ll, lin_range, lin_step, ang_range, ang_step):
    """The improved proposal around each particle's match.

    ``modes``: the climbs' poses; ``means`` and ``sigmas`` (x, y, theta standard deviations): the motion
    model's Gaussian for each particle; ``normals``: standard normal draws (particles x 3) that make the
    sample. Returns (poses, log weight increments, log-likelihoods at the modes).
    """
    n_particles = modes.shape[0]
    nl = int(math.floor(lin_range / lin_step + 1e-9))
    na = int(math.floor(ang_range / ang_step + 1e-9))
    m = (2 * nl + 1) * (2 * nl + 1) * (2 * na + 1)
    out = modes.copy()
    log_eta = np.zeros(n_particles)
    back = _back_steps(points, lx, ly, res)
    at_mode = np.zeros(n_particles)
    for p in prange(n_particles):
        xs = np.empty((m, 3))
        logs = np.empty(m)
        k = 0
        for i in range(-nl, nl + 1):
            for j in range(-nl, nl + 1):
                for a in range(-na, na + 1):
                    x = modes[p, 0] + i * lin_step
                    y = modes[p, 1] + j * lin_step
                    th = modes[p, 2] + a * ang_step
                    _, ll = _evaluate(table, p, state, mean, ox, oy, res, points, back, x, y, th, kernel,
                                      sigma, lsigma, stride, unknown_ll)
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
