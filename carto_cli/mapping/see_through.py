"""The ``see_through`` check's measurement: the share of each scan's rays that pass through walls seen from
elsewhere (``mapping/quality.py`` turns it into a check with thresholds, and calibrates them).

A wall here is a 10 cm cell holding loop-closure returns of at least 3 nodes more than 5 m of local-SLAM travel away
from the scan, and a *solid* one: of the rays of the scans that built the walls in its 3 x 3 cells, or of their
neighbours within 5 m of travel, that reach those cells, at least 70 % end there rather than cross them more than
0.5 m before their end (``wall_solidity``, over up to 1000 nodes x 60 rays). The ray must cross the wall more than
0.5 m before its own endpoint, and no node within the scan's own 5 m may have a return within 0.4 m of the crossing
(the same wall met at a grazing angle or a corner, or one misplaced by less than that). A consistent map keeps every
ray in free space; a misplaced revisit doubles the walls and its rays cross them. Node returns rather than the
submaps' grids (the brief's first idea), because on key-scan logs a submap's walls are hit a few times only (0.02 %
of the known cells of aces's sparse submaps reach p = 0.8, against 0.6-1.9 % at 10 Hz), and because a submap that
holds a whole revisit (stock 90-scan submaps span 50-90 m of such logs) hides its own double walls: the mean share
of rays through another submap's p >= 0.6 cells was 1.9 % on aces with the stock options (12.4 m error), 5.0 % with
the sparse profile (0.083 m).

Why solid (issue 43, item 4): good maps were failed because the laser does see through some of what it returns. An
outdoor campus log mapped to 0.086 m had 15.2 % (hedges, trees, parked cars), a dense building's 0.021 m map 6.25 %
(walls one cell thick, gaps seen from both sides); glass and open doors do the same. What tells them from a
misplaced revisit is who sees through: a revisit placed wrong crosses walls that the scans which built them (and
their neighbours, as consistently placed as local SLAM makes them) only ever hit, while glass, a hedge, a gap, or a
hedge or car body lower than a slightly tilted scan plane (seen up close, passed over from afar) is passed through
from the builders' own viewpoints too. Counted over a 3 x 3 block rather than one cell, and over the builders'
neighbourhood rather than the builders alone, so that a glass pane met at a different angle or a hedge approached
from afar counts as the same surface. The simulator's ``courtyard`` (hedges returning 70 % of the rays within 6 m
and none from further, car bodies, glass returning near its normal only) shows the failure: its good maps had
41-45 % before, 0.0 % now. With that test in place the own-neighbourhood radius could shrink from 1 m (on 0.2 m
cells) to 0.4 m (on the walls' own 0.1 m cells): a revisit misplaced by 0.5 m or 3 degrees never counted before (0.0
% in the simulated glass office) and is failed now (28-35 %).

The solid share (0.7) and the own radius (0.4 m) were chosen by ``quality_calibration.py --loo`` over share 0 (no
solidity test), 0.5 ... 0.9 and radius 0.2 ... 1 m, leaving one building out at a time (aces, intel, freiburg-079,
orebro, edmonton, fhw with their bench-dense runs, the simulated office, the simulated courtyard): the pair with no
map within 0.05 m failed and no map worse than its odometry or misplaced on purpose left unfailed on the other
buildings, then the fewest maps within 0.1 m failed, then the widest margin to the failing threshold. 0.7 / 0.4 m
was chosen in 6 of the 8 folds (0.7 / 0.2 m with aces left out, 0.8 / 0.4 m with the courtyard); no held-out
building had such a map misjudged. Without the solidity test no radius does it (6-9 misjudged: the courtyard's good
maps, and with 1 m the misplaced revisits); with the test and a radius of 0.6 m or more, 3-5 (the revisits misplaced
by 0.5 m; and at 1 m aces, orebro and edmonton default, 1.8-12.4 m off, fall to 5.0-7.1 %, aces' to no longer
failed: their local SLAM is not consistent enough for all their walls to be solid, and only the smaller radius sees
the rest).

Cost (one call after mapping; numba kernels, Python loops over nodes only), back to back with the check before the
solidity test on the same maps: 9-49 ms against 6-39 ms (1.1-2.4 x: the solidity walk over up to 60,000 rays and a
finer own-radius search): orebro default 6 -> 9 ms (1.5 % of its 0.6 s map), aces sparse 9 -> 15, intel sparse 12 ->
26, dense-aces wheeled 26 -> 39 (0.6 % of 6.8 s), dense-intel wheeled (6530 nodes) 39 -> 44, the simulated courtyard
24 -> 49 ms; in the calibration run 0.0-1.1 % of the mapping time, but 1.5 and 2.4 % for edmonton and orebro default
(maps of 1.5 and 0.6 s). Per cell two int32 counters more (32 MB at the 4 million cells a very large map is held
to).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike

from carto_cli.core.kernels import register_warm_up

if TYPE_CHECKING:
    from carto_cli.mapping.pose_graph import PoseGraph

__all__ = ["ReturnIndex", "node_see_through", "node_travel", "rays_through_walls", "wall_solidity"]

# The module docstring says why; bench/quality_calibration.py measures.
CELL_M = 0.1  # walls
WINDOW_M = 5.0  # travel within which nodes are the scan's own neighbourhood
MARGIN_M = 0.5  # of a ray before its endpoint that is never checked
OWN_RADIUS_M = 0.4  # a neighbourhood return this close to a crossing makes it the same wall
NEAR_CELL_M = 0.1  # cells of that search (the walls' own: 49 lookups for 0.4 m)
MIN_OTHER_NODES = 3  # far nodes a wall cell needs, so that one stray return (a person) is no wall
MAX_NODES = 400
MAX_RAYS = 50
SOLID_SHARE = 0.7  # of the rays of a wall's own scans (and neighbours) into it that must end there
SOLIDITY_NODES = 1000  # nodes, evenly spread, whose rays measure that
SOLIDITY_RAYS = 60  # rays of each


@njit(cache=True, nogil=True)
def _first_at_least(values, a, b, x):
    """Index of the first of the sorted ``values[a:b]`` that is >= ``x`` (``b`` when none)."""
    while a < b:
        m = (a + b) // 2
        if values[m] < x:
            a = m + 1
        else:
            b = m
    return a


@njit(cache=True, nogil=True)
def _first_above(values, a, b, x):
    """Index of the first of the sorted ``values[a:b]`` that is > ``x`` (``b`` when none)."""
    while a < b:
        m = (a + b) // 2
        if values[m] <= x:
            a = m + 1
        else:
            b = m
    return a


@njit(cache=True, nogil=True)
def _solid(hit, passed, ix, iy, ny, nx, share):
    """Whether the rays that built the walls in the 3 x 3 cells around (ix, iy) mostly ended there: ``hit``
    >= ``share`` of (``hit`` + ``passed``) summed over them. No such ray there: solid."""
    h = 0
    p = 0
    for yy in range(max(iy - 1, 0), min(iy + 2, ny)):
        for xx in range(max(ix - 1, 0), min(ix + 2, nx)):
            h += hit[yy * nx + xx]
            p += passed[yy * nx + xx]
    return h >= share * (h + p)


@njit(cache=True, nogil=True, inline="always")
def _sensor_in_map(poses, i, sensor):
    """Node ``i``'s heading (cos, sin) and its sensor's position in the map frame, for both ray walks."""
    c = math.cos(poses[i, 2])
    s = math.sin(poses[i, 2])
    return c, s, c * sensor[0] - s * sensor[1] + poses[i, 0], s * sensor[0] + c * sensor[1] + poses[i, 1]


@njit(cache=True, nogil=True)
def _see_through(start, travel, gox, goy, cell, ny, nx, near_start, near_travel, nox, noy, near_cell, nny, nnx, disk,
                 radius, points, offsets, poses, node_travel, sensor, window, margin, min_other, hit, passed, share):
    """Per node: rays longer than ``margin``, and rays crossing a wall of nodes more than ``window`` away
    (see ``rays_through_walls``; ``hit`` empty: every wall solid)."""
    use_solid = hit.shape[0] > 0
    n = poses.shape[0]
    step = 0.5 * cell
    hits = np.zeros(n, np.int64)
    checked = np.zeros(n, np.int64)
    for i in range(n):
        c, s, sx, sy = _sensor_in_map(poses, i, sensor)
        lo = node_travel[i] - window
        hi = node_travel[i] + window
        for k in range(offsets[i], offsets[i + 1]):
            dx = c * points[k, 0] - s * points[k, 1] + poses[i, 0] - sx
            dy = s * points[k, 0] + c * points[k, 1] + poses[i, 1] - sy
            length = math.sqrt(dx * dx + dy * dy)
            stop = length - margin
            if stop <= step:
                continue
            checked[i] += 1
            ux = dx / length
            uy = dy / length
            near_until = 0
            for j in range(1, int(stop / step) + 1):
                wx = sx + j * step * ux
                wy = sy + j * step * uy
                ix = int(math.floor((wx - gox) / cell))
                iy = int(math.floor((wy - goy) / cell))
                if ix < 0 or iy < 0 or ix >= nx or iy >= ny or j <= near_until:
                    continue
                a = start[iy * nx + ix]
                b = start[iy * nx + ix + 1]
                if b - a < min_other or (travel[a] >= lo and travel[b - 1] <= hi):
                    continue
                inside = _first_above(travel, a, b, hi) - _first_at_least(travel, a, b, lo)
                if b - a - inside < min_other:
                    continue
                if use_solid and not _solid(hit, passed, ix, iy, ny, nx, share):
                    continue  # glass, a hedge, a gap: the rays of the scans that saw it here pass it as well
                # The same wall as the scan's own neighbourhood sees, met at a grazing angle or a corner:
                # ``disk`` (in the cells of the near index) runs outwards, so such a return is
                # usually found in the first few cells.
                cx = int(math.floor((wx - nox) / near_cell))
                cy = int(math.floor((wy - noy) / near_cell))
                near = -1.0
                for q in range(disk.shape[0]):
                    yy = cy + disk[q, 0]
                    xx = cx + disk[q, 1]
                    if yy < 0 or xx < 0 or yy >= nny or xx >= nnx:
                        continue
                    e = near_start[yy * nnx + xx + 1]
                    f = _first_at_least(near_travel, near_start[yy * nnx + xx], e, lo)
                    if f < e and near_travel[f] <= hi:
                        near = math.sqrt(disk[q, 0] ** 2 + disk[q, 1] ** 2)
                        break
                if near < 0:
                    hits[i] += 1
                    break
                # That return is also within the radius of the cells the next steps reach, as long as they
                # stay within (radius - near) cells, less 1.5 for where in their cells the crossings lie.
                near_until = j + int((radius - near - 1.5) * near_cell / step)
    return hits, checked


@njit(cache=True, nogil=True)
def _solidity(start, travel, gox, goy, cell, ny, nx, points, offsets, poses, node_travel, sensor, window, margin):
    """Per cell: rays ending in it, and rays crossing it (any part of it, cells walked exactly from the sensor)
    more than ``margin`` before their end from nodes within ``window`` of travel of a node with a return in
    it (see ``wall_solidity``)."""
    n = poses.shape[0]
    hit = np.zeros(ny * nx, np.int32)
    passed = np.zeros(ny * nx, np.int32)
    for i in range(n):
        c, s, sx, sy = _sensor_in_map(poses, i, sensor)
        lo = node_travel[i] - window
        hi = node_travel[i] + window
        # The sensor in cell units.
        fx = (sx - gox) / cell
        fy = (sy - goy) / cell
        for k in range(offsets[i], offsets[i + 1]):
            ex = (c * points[k, 0] - s * points[k, 1] + poses[i, 0] - gox) / cell
            ey = (s * points[k, 0] + c * points[k, 1] + poses[i, 1] - goy) / cell
            ix = int(math.floor(ex))
            iy = int(math.floor(ey))
            if ix >= 0 and iy >= 0 and ix < nx and iy < ny:
                hit[iy * nx + ix] += 1
            dx = ex - fx
            dy = ey - fy
            length = math.sqrt(dx * dx + dy * dy)
            stop = length - margin / cell  # in cells along the ray
            if stop <= 0.0:
                continue
            # Amanatides-Woo: the parameter (cells along the ray) at which it enters the next column / row.
            ix = int(math.floor(fx))
            iy = int(math.floor(fy))
            if dx > 0:
                step_x, tdx, tx = 1, length / dx, (ix + 1 - fx) * length / dx
            elif dx < 0:
                step_x, tdx, tx = -1, -length / dx, (fx - ix) * length / -dx
            else:
                step_x, tdx, tx = 0, math.inf, math.inf
            if dy > 0:
                step_y, tdy, ty = 1, length / dy, (iy + 1 - fy) * length / dy
            elif dy < 0:
                step_y, tdy, ty = -1, -length / dy, (fy - iy) * length / -dy
            else:
                step_y, tdy, ty = 0, math.inf, math.inf
            t = 0.0
            while t < stop:
                if ix >= 0 and iy >= 0 and ix < nx and iy < ny:
                    q = iy * nx + ix
                    a = start[q]
                    b = start[q + 1]
                    if a < b:
                        f = _first_at_least(travel, a, b, lo)
                        if f < b and travel[f] <= hi:
                            passed[q] += 1
                if tx < ty:
                    t = tx
                    tx += tdx
                    ix += step_x
                else:
                    t = ty
                    ty += tdy
                    iy += step_y
    return hit, passed


@njit(cache=True, nogil=True)
def _buckets(points, ox, oy, cell, nx, ny, nodes, travel):
    """Counting sort of the points into their cells, one entry per node and cell: (start, travel)."""
    cells = np.empty(points.shape[0], np.int64)
    for k in range(points.shape[0]):
        cells[k] = int(math.floor((points[k, 1] - oy) / cell)) * nx + int(math.floor((points[k, 0] - ox) / cell))
    last = np.full(nx * ny, -1, np.int32)
    start = np.zeros(nx * ny + 1, np.int32)
    for k in range(cells.shape[0]):
        if last[cells[k]] != nodes[k]:
            last[cells[k]] = nodes[k]
            start[cells[k] + 1] += 1
    for c in range(nx * ny):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    last[:] = -1
    out = np.empty(start[nx * ny], np.float64)
    for k in range(cells.shape[0]):
        c = cells[k]
        if last[c] != nodes[k]:
            last[c] = nodes[k]
            out[fill[c]] = travel[nodes[k]]
            fill[c] += 1
    return start, out


@njit(cache=True, nogil=True)
def _bounds(points):
    """(min, max) of the points: numpy's reductions along the short axis are strided and slow."""
    low = points[0].copy()
    high = points[0].copy()
    for k in range(points.shape[0]):
        for d in range(2):
            low[d] = min(low[d], points[k, d])
            high[d] = max(high[d], points[k, d])
    return low, high


@dataclass(frozen=True)
class ReturnIndex:
    """Which nodes put a return in each map cell, by their travel (m along their trajectory's local SLAM).

    Cell ``iy * nx + ix`` holds ``travel[start[cell]:start[cell + 1]]``, sorted, one entry per node.
    """

    start: np.ndarray  # (ny * nx + 1,) int64
    travel: np.ndarray  # (E,) float64
    origin: tuple[float, float]
    cell: float
    shape: tuple[int, int]  # (ny, nx)

    @classmethod
    def build(cls, points: np.ndarray, node: np.ndarray, travel: np.ndarray, *, cell: float = CELL_M,
              max_cells: int = 4_000_000) -> ReturnIndex:
        """``points`` (P, 2) in the map frame, ``node`` (P,) the node each came from (non-decreasing),
        ``travel`` (N,) per node (non-decreasing)."""
        points = np.asarray(points, np.float64).reshape(-1, 2)
        node = np.asarray(node, np.int64).reshape(-1)
        travel = np.asarray(travel, np.float64).reshape(-1)
        if np.any(np.diff(node) < 0) or np.any(np.diff(travel) < 0):
            raise ValueError("points must come in node order, and travel must not decrease with the node")
        if len(points) == 0:
            return cls(np.zeros(2, np.int64), np.zeros(0), (0.0, 0.0), float(cell), (1, 1))
        low, high = _bounds(points)
        lo = low - cell
        size = high - lo + cell
        # A very large map gets coarser cells rather than unbounded memory: walls only get thicker.
        cell = max(float(cell), math.sqrt(float(size[0] * size[1]) / max_cells))
        nx, ny = (int(math.ceil(v / cell)) for v in size)
        start, entries = _buckets(points, float(lo[0]), float(lo[1]), cell, nx, ny, node, travel)
        return cls(start, entries, (float(lo[0]), float(lo[1])), cell, (ny, nx))


def _disk(radius: int) -> np.ndarray:
    """(K, 2) (dy, dx) of the cells within ``radius`` cells, nearest first."""
    d = np.arange(-radius, radius + 1)
    dy, dx = (v.ravel() for v in np.meshgrid(d, d, indexing="ij"))
    keep = dy * dy + dx * dx <= radius * radius
    order = np.argsort(dy[keep] ** 2 + dx[keep] ** 2, kind="stable")
    return np.ascontiguousarray(np.stack([dy[keep][order], dx[keep][order]], axis=1), np.int64)


def _flat(points: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    counts = np.array([len(p) for p in points], np.int64)
    offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    flat = np.concatenate([np.asarray(p, np.float64).reshape(-1, 2) for p in points]) if points else np.zeros((0, 2))
    return np.ascontiguousarray(flat), offsets


def wall_solidity(walls: ReturnIndex, points: list[np.ndarray], poses: np.ndarray, travel: np.ndarray,
                  sensor: ArrayLike = (0.0, 0.0), *, window: float = WINDOW_M, margin: float = MARGIN_M
                  ) -> tuple[np.ndarray, np.ndarray]:
    """(hit, passed) per cell of ``walls`` (``iy * nx + ix``), over the rays from ``sensor`` to ``points[i]``
    (node frame, placed at ``poses[i]``): the rays that end in the cell, and the rays that cross it more than
    ``margin`` before their end while a node within ``window`` of ``travel[i]`` has a return in it -- the
    scans that built a wall there, or their neighbours, seeing through it."""
    flat, offsets = _flat(points)
    return _solidity(walls.start, walls.travel, walls.origin[0], walls.origin[1], walls.cell, walls.shape[0],
                     walls.shape[1], flat, offsets, np.ascontiguousarray(poses, np.float64).reshape(-1, 3),
                     np.asarray(travel, np.float64).reshape(-1), np.asarray(sensor, np.float64).reshape(2),
                     float(window), float(margin))


def rays_through_walls(walls: ReturnIndex, near: ReturnIndex, points: list[np.ndarray], poses: np.ndarray,
                       travel: np.ndarray, sensor: ArrayLike = (0.0, 0.0), *, window: float = WINDOW_M,
                       margin: float = MARGIN_M, radius: float = OWN_RADIUS_M, min_other: int = MIN_OTHER_NODES,
                       solidity: tuple[np.ndarray, np.ndarray] | None = None, share: float = SOLID_SHARE
                       ) -> tuple[np.ndarray, np.ndarray]:
    """(hits, checked) per node ``i``: rays from ``sensor`` to ``points[i]`` (node frame, placed at ``poses[i]``)
    longer than ``margin``, and those among them that cross, more than ``margin`` before their endpoint, a
    cell of ``walls`` holding returns of ``min_other`` nodes more than ``window`` of travel from ``travel[i]``
    while no node within ``window`` has a return in the cells of ``near`` within ``radius`` (m) of it, and
    (with ``solidity``, ``wall_solidity``'s counts) where at least ``share`` of the counted rays in the 3 x 3
    cells around it ended there."""
    flat, offsets = _flat(points)
    cells = int(math.ceil(radius / near.cell - 1e-9))
    hit, passed = (np.zeros(0, np.int32), np.zeros(0, np.int32)) if solidity is None else solidity
    return _see_through(walls.start, walls.travel, walls.origin[0], walls.origin[1], walls.cell, walls.shape[0],
                        walls.shape[1], near.start, near.travel, near.origin[0], near.origin[1], near.cell,
                        near.shape[0], near.shape[1], _disk(cells), float(cells), flat, offsets,
                        np.ascontiguousarray(poses, np.float64).reshape(-1, 3),
                        np.asarray(travel, np.float64).reshape(-1), np.asarray(sensor, np.float64).reshape(2),
                        float(window), float(margin), int(min_other), hit, passed, float(share))


def node_travel(local_poses: np.ndarray, trajectories: np.ndarray, gap: float) -> np.ndarray:
    """(N,) metres of local-SLAM travel to each node; trajectories follow each other ``gap`` apart."""
    local_poses = np.asarray(local_poses, np.float64).reshape(-1, 3)
    trajectories = np.asarray(trajectories).reshape(-1)
    if len(local_poses) == 0:
        return np.zeros(0)
    step = np.hypot(*np.diff(local_poses[:, :2], axis=0).T)
    # Local frames of different trajectories are unrelated: a jump between them is no travel.
    step = np.where(np.diff(trajectories) != 0, gap, step)
    return np.concatenate([[0.0], np.cumsum(step)])


@njit(cache=True, nogil=True)
def _place(points, node, poses):
    """Every node's points (node frame) at its pose."""
    c = np.cos(poses[:, 2])
    s = np.sin(poses[:, 2])
    out = np.empty_like(points)
    for k in range(points.shape[0]):
        i = node[k]
        out[k, 0] = c[i] * points[k, 0] - s[i] * points[k, 1] + poses[i, 0]
        out[k, 1] = s[i] * points[k, 0] + c[i] * points[k, 1] + poses[i, 1]
    return out


def node_see_through(graph: PoseGraph, laser_pose: ArrayLike = (0.0, 0.0, 0.0), *, max_nodes: int = MAX_NODES,
                     max_rays: int = MAX_RAYS, poses: np.ndarray | None = None, solid_share: float = SOLID_SHARE,
                     solidity_nodes: int = SOLIDITY_NODES, solidity_rays: int = SOLIDITY_RAYS,
                     near_cell: float = NEAR_CELL_M, **kwargs: Any) -> tuple[np.ndarray, np.ndarray]:
    """(nodes, fraction): up to ``max_nodes`` nodes spread evenly over ``graph`` and the share of (up to
    ``max_rays`` of) each one's rays that cross walls seen from elsewhere (``rays_through_walls``, which
    ``kwargs`` go to; NaN for a node without a ray longer than the margin). Every node's returns make the walls;
    a wall counts where at least ``solid_share`` of the rays into it of (up to ``solidity_rays`` of) each of up
    to ``solidity_nodes`` nodes end there (``wall_solidity``; 0: every wall counts, the check before issue 43).
    ``near_cell``: the cells of the own-neighbourhood search.
    ``poses`` (N, 3) places the nodes instead of the graph's global poses."""
    n = graph.num_nodes
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0)
    travel = node_travel(graph.local_poses, np.asarray(graph.node_trajectory),
                         gap=2 * float(kwargs.get("window", WINDOW_M)) + 1.0)
    counts = np.array([len(p) for p in graph.node_points], np.int64)
    node = np.repeat(np.arange(n), counts)
    local = np.concatenate(graph.node_points).astype(np.float64, copy=False).reshape(-1, 2)
    placed_at = np.ascontiguousarray(graph.global_poses if poses is None else poses, np.float64).reshape(n, 3)
    placed = _place(local, node, placed_at)
    walls = ReturnIndex.build(placed, node, travel, cell=CELL_M)
    near = walls if near_cell == CELL_M else ReturnIndex.build(placed, node, travel, cell=near_cell)
    sensor = np.asarray(laser_pose, np.float64).reshape(-1)[:2]
    solidity = None
    if solid_share > 0:
        spread = np.unique(np.linspace(0, n - 1, min(n, solidity_nodes)).round().astype(np.int64))
        rays = [p[::max(1, math.ceil(len(p) / solidity_rays))] for p in (graph.node_points[i] for i in spread)]
        solidity = wall_solidity(walls, rays, placed_at[spread], travel[spread], sensor,
                                 **{k: v for k, v in kwargs.items() if k in ("window", "margin")})
    nodes = np.unique(np.linspace(0, n - 1, min(n, max_nodes)).round().astype(np.int64))
    rays = [p[::max(1, math.ceil(len(p) / max_rays))] for p in (graph.node_points[i] for i in nodes)]
    hits, checked = rays_through_walls(walls, near, rays, placed_at[nodes], travel[nodes], sensor,
                                       solidity=solidity, share=solid_share, **kwargs)
    return nodes, np.where(checked > 0, hits / np.maximum(checked, 1), np.nan)


@register_warm_up
def warm_up() -> None:
    """The see-through check's kernels (return index, rays through walls) on three toy nodes."""
    points = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    node = np.arange(3, dtype=np.int64)
    travel = np.array([0.0, 5.0, 10.0])
    poses = np.zeros((3, 3))
    placed = _place(points, node, poses)
    walls = ReturnIndex.build(placed, node, travel, cell=CELL_M)
    near = ReturnIndex.build(placed, node, travel, cell=NEAR_CELL_M)
    solidity = wall_solidity(walls, [points[:2]] * 3, poses, travel, np.zeros(2))
    rays_through_walls(walls, near, [points[:2]] * 3, poses, travel, np.zeros(2), solidity=solidity)
