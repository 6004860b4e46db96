"""Whether a candidate link between two sessions puts the one's scans where the other saw free space.

The link rule (``closure_confirmation.LinkConfirmation``) accepts a placement once closures from two places agree
on it. A building can agree with itself turned round: in the simulated ring corridor a session placed half a turn
off matched at its first node and again at the next one (into another submap), and every later closure agreed
with the wrong placement (bench/sessions.py sim, 5 sessions: session 4 25 m off, judged ok). What the matches do
not weigh is free space: placed wrong, the session's pillars and room walls stand where the other sessions looked
through empty corridor. So before a link is made, the returns of the later session's scans around the closure
are placed as the link would place them, and the share of them that fall in the other side's surely free cells,
away from any wall, is measured.

Measured at every link made in bench/sessions.py and bench/lifelong.py (the simulated ring in 5 and in 10
sessions, mapped together, continued one by one, or merged; dense aces, intel and freiburg-079 in 2 and 5 parts):
placements within decimetres of the truth 0.00-0.31 %; the ring's look-alikes (half a turn, a quarter turn)
0.51-11 %, and one at 0.16 %. LINK_CONFLICT (0.5 %) refuses every look-alike measured but that one and none of the
right placements; the margins are thin (1.6 times above the highest right one), and the one it lets through is
said in docs/benchmarks.md. A placement refused only waits: its closures go, and the next ones are offered
afresh.

Knows the grids and poses it is handed, never the graph.
"""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numba import njit

from carto_cli.core import transform
from carto_cli.core.kernels import register_warm_up
from carto_cli.grid.occupancy_image import AssembledImage, known_box
from carto_cli.grid.probability_grid import ProbabilityGrid

__all__ = ["LINK_CONFLICT", "LINK_RANGE", "LINK_REACH", "free_space_conflict"]

LINK_REACH = 10.0  # m of the later session's travel either side of the closure whose scans are placed
LINK_RANGE = 8.0  # m: returns further from the scanner are left out (a far wall's returns scatter over cells)
FREE = 0.25  # a cell at most this likely occupied was seen through many times
WALL_MARGIN = 3  # cells: a return this close to a cell more likely occupied than not is on that wall
LINK_CONFLICT = 0.005  # share of the placed returns in free space above which a link is refused


@njit(cache=True, nogil=True)
def _conflicts(prob: np.ndarray, ox: float, oy: float, res: float, points: np.ndarray, free: float,
               margin: int) -> tuple[int, int]:  # pragma: no cover - numba
    ny, nx = prob.shape
    known = 0
    conflicting = 0
    for k in range(points.shape[0]):
        ix = int(np.floor((points[k, 0] - ox) / res))
        iy = int(np.floor((points[k, 1] - oy) / res))
        if ix < 0 or iy < 0 or ix >= nx or iy >= ny:
            continue
        p = prob[iy, ix]
        if np.isnan(p):
            continue
        known += 1
        if p > free:
            continue
        wall = False
        for dy in range(-margin, margin + 1):
            for dx in range(-margin, margin + 1):
                jy, jx = iy + dy, ix + dx
                if 0 <= jy < ny and 0 <= jx < nx and prob[jy, jx] > 0.5:
                    wall = True
        if not wall:
            conflicting += 1
    return conflicting, known


def free_space_conflict(points: Sequence[np.ndarray], poses: np.ndarray, grids: Sequence[ProbabilityGrid],
                        corrections: Sequence[np.ndarray]) -> tuple[float, int]:
    """The share of ``points`` (per scan, (n, 2) in its own frame, placed at ``poses`` in the map frame; those
    within LINK_RANGE of the scanner) that land in surely free cells of ``grids`` (at ``corrections``) with no
    wall within WALL_MARGIN cells, and how many landed in known cells at all."""
    placed = [transform.apply(pose, p[np.hypot(p[:, 0], p[:, 1]) <= LINK_RANGE, :2]) for pose, p in zip(poses, points)]
    placed = [p for p in placed if len(p)]
    if not placed or not len(grids):
        return 0.0, 0
    cloud = np.ascontiguousarray(np.concatenate(placed), dtype=np.float64)
    lo, hi = cloud.min(axis=0), cloud.max(axis=0)
    near = [(g, c) for g, c in zip(grids, corrections) if _overlaps(g, c, lo, hi)]  # only what the cloud can meet
    if not near:
        return 0.0, 0
    image = AssembledImage([g for g, _ in near], [c for _, c in near])
    if 0 in image.shape:
        return 0.0, 0
    prob = image.probability  # row 0 at the map's lowest y
    conflicting, known = _conflicts(prob, image.origin[0], image.origin[1], image.resolution, cloud, FREE,
                                    WALL_MARGIN)
    return (conflicting / known if known else 0.0), known


def _overlaps(grid: ProbabilityGrid, correction: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Whether ``grid``'s known cells, at ``correction``, reach the box ``lo``-``hi``."""
    box = known_box(grid, correction)
    return box is not None and bool(np.all(box[:2] <= hi) and np.all(box[2:] >= lo))


@register_warm_up(system="cartographer")
def _warm_up() -> None:
    _conflicts(np.full((4, 4), 0.1, np.float32), 0.0, 0.0, 0.05, np.zeros((1, 2)), FREE, WALL_MARGIN)

