"""How far a map of several sessions shows a building as the last session found it: the cells whose walls
changed between a simulated building's sessions (``sim.world.changed_cells``), read off the map image."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from carto_cli.grid.occupancy_image import AssembledImage, OccupancyImage
from carto_cli.sim.world import World, changed_cells, grown

__all__ = ["ChangeScore", "score_changes"]


@dataclass(frozen=True, slots=True)
class ChangeScore:
    """Of the changed cells the map knows: how many show the last session's state (a wall that appeared is
    occupied within a cell of where it is; one that vanished left no occupied cell within one of where it was),
    and of the walls both sessions found, how many the map still shows."""

    appeared: int
    appeared_shown: int
    vanished: int
    vanished_shown: int
    unchanged: int
    unchanged_shown: int

    @property
    def changed_shown(self) -> float:
        total = self.appeared + self.vanished
        return (self.appeared_shown + self.vanished_shown) / total if total else float("nan")

    @property
    def unchanged_kept(self) -> float:
        return self.unchanged_shown / self.unchanged if self.unchanged else float("nan")

    def to_dict(self) -> dict:
        return {"appeared": self.appeared, "appeared_shown": self.appeared_shown, "vanished": self.vanished,
                "vanished_shown": self.vanished_shown, "changed_shown": self.changed_shown,
                "unchanged": self.unchanged, "unchanged_shown": self.unchanged_shown,
                "unchanged_kept": self.unchanged_kept}


def score_changes(image: OccupancyImage | AssembledImage, before: World, after: World,
                  alignment: np.ndarray | None = None, observed: OccupancyImage | AssembledImage | None = None,
                  sure: float = 0.0) -> ChangeScore:
    """Score ``image`` (in the map frame, which is the worlds' frame moved by ``alignment``: the first session's
    start as an (x, y, yaw) pose in the world; None: the same frame) against the change from ``before`` to
    ``after``. A changed cell counts only where the map knows it (within one cell) and, given ``observed`` (the
    last session's own image, in the same frame), where that knows it with log-odds at least ``sure`` (a moved
    wall hides the old one behind it: no session can tell that it is gone)."""
    res = float(image.resolution)
    prob, origin = in_world(np.asarray(image.probability, dtype=np.float64), np.asarray(image.origin, float), res,
                             np.zeros(3) if alignment is None else np.asarray(alignment, dtype=np.float64))
    shape = prob.shape
    appeared, vanished, unchanged = changed_cells(before, after, tuple(origin), res, shape)
    known = ~np.isnan(prob)
    occupied = grown(known & (prob > 0.5), 1)
    near_known = grown(known, 1)
    a, v, u = appeared & near_known, vanished & near_known, unchanged & near_known
    if observed is not None:
        seen, _ = in_world(np.asarray(observed.probability, dtype=np.float64),
                                      np.asarray(observed.origin, float), float(observed.resolution),
                                      np.zeros(3) if alignment is None else np.asarray(alignment, dtype=np.float64),
                                      onto=(origin, shape))
        with np.errstate(divide="ignore"):
            sure_seen = ~np.isnan(seen) & (np.abs(np.log(seen / (1.0 - seen))) >= sure)
        a, v = a & grown(sure_seen, 1), v & grown(sure_seen, 1)
    return ChangeScore(int(a.sum()), int((a & occupied).sum()), int(v.sum()), int((v & ~occupied).sum()),
                       int(u.sum()), int((u & occupied).sum()))


def in_world(prob: np.ndarray, origin: np.ndarray, res: float, start: np.ndarray,
              onto: tuple[np.ndarray, tuple[int, int]] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The image resampled (nearest cell) onto a grid in the world's frame (``onto``: its origin and shape; None:
    one covering the image), the map frame being the frame of ``start`` (a pose in the world)."""
    c, s = np.cos(start[2]), np.sin(start[2])
    h, w = prob.shape
    if onto is None:
        corners = np.array([[0, 0], [w, 0], [0, h], [w, h]], dtype=np.float64) * res + origin
        world = corners @ np.array([[c, s], [-s, c]]) + start[:2]
        lo = np.floor(world.min(axis=0) / res) * res
        hi = np.ceil(world.max(axis=0) / res) * res
        nx, ny = int(round((hi[0] - lo[0]) / res)), int(round((hi[1] - lo[1]) / res))
    else:
        lo, (ny, nx) = np.asarray(onto[0], float), onto[1]
    gx, gy = np.meshgrid(lo[0] + (np.arange(nx) + 0.5) * res, lo[1] + (np.arange(ny) + 0.5) * res)
    dx, dy = gx - start[0], gy - start[1]
    mx, my = c * dx + s * dy, -s * dx + c * dy  # world point in the map frame
    ix = np.floor((mx - origin[0]) / res).astype(np.int64)
    iy = np.floor((my - origin[1]) / res).astype(np.int64)
    inside = (ix >= 0) & (iy >= 0) & (ix < w) & (iy < h)
    out = np.full((ny, nx), np.nan)
    out[inside] = prob[iy[inside], ix[inside]]
    return out, lo
