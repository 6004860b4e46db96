"""How clean a map of a simulated building with people, carts and doors is: of the cells today's map would show
occupied, how many the movers left (``sim.movers.footprint``) and how many are the building's walls, and of each,
how many a cleaned map still shows."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from carto_cli.evaluation.changes import in_world
from carto_cli.grid.occupancy_image import AssembledImage, OccupancyImage
from carto_cli.sim.movers import Mover, footprint
from carto_cli.sim.world import World, grown, wall_cells

__all__ = ["CleanScore", "score_cleaning"]

WALL_MARGIN = 2  # cells: a map's wall is a cell or two thick, and its poses a cell off


@dataclass(frozen=True, slots=True)
class CleanScore:
    """``transient``: occupied cells of the uncleaned map that a mover crossed and no wall is near;
    ``static``: occupied cells of it near a wall and away from every mover; ``*_removed`` / ``*_kept``: of them,
    how many the cleaned map draws free / still occupied."""

    transient: int
    transient_removed: int
    static: int
    static_kept: int

    @property
    def removed_share(self) -> float:
        return self.transient_removed / self.transient if self.transient else float("nan")

    @property
    def kept_share(self) -> float:
        return self.static_kept / self.static if self.static else float("nan")

    def to_dict(self) -> dict:
        return {"transient": self.transient, "transient_removed": self.transient_removed,
                "removed_share": self.removed_share, "static": self.static, "static_kept": self.static_kept,
                "kept_share": self.kept_share}


def score_cleaning(before: OccupancyImage | AssembledImage, after: OccupancyImage | AssembledImage, world: World,
                   movers: Sequence[Mover], times: np.ndarray, alignment: np.ndarray) -> CleanScore:
    """Score the cleaned image ``after`` against the uncleaned ``before`` (the same grid), both in the map frame,
    which is the world's frame moved by ``alignment`` (the map frame as an (x, y, yaw) pose in the world);
    ``times``: the scans' times in s since the recording's start (when the movers were looked at)."""
    res = float(before.resolution)
    start = np.asarray(alignment, np.float64)
    old, origin = in_world(np.asarray(before.probability, np.float64), np.asarray(before.origin, float), res, start)
    new, _ = in_world(np.asarray(after.probability, np.float64), np.asarray(after.origin, float), res, start,
                      onto=(origin, old.shape))
    occupied = ~np.isnan(old) & (np.nan_to_num(old) > 0.5)
    still = ~np.isnan(new) & (np.nan_to_num(new) > 0.5)
    walls = grown(wall_cells(world, tuple(origin), res, old.shape), WALL_MARGIN)
    moved = grown(footprint(movers, times, tuple(origin), res, old.shape), WALL_MARGIN)
    transient = occupied & moved & ~walls
    static = occupied & walls & ~moved
    return CleanScore(int(transient.sum()), int((transient & ~still).sum()), int(static.sum()),
                      int((static & still).sum()))
