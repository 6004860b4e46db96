"""The horizontal band of a 3D lidar's cloud that becomes a 2D scan, placed relative to the floor.

A level mount is assumed: the sensor's z axis is vertical, so the floor and the ceiling are planes of constant z in
the sensor frame and show in the histogram of the points' heights as its lowest and highest tall peaks (a sweep
meets them all around, a wall only over the heights of the rings that reach it). A mount tilted more than a degree
or two smears those peaks over heights; the floor is then not found and the cloud is sliced in the sensor frame.

The band is chosen above the clutter near the floor (tables, boxes, chairs) and below the ceiling and the door
lintels: walls are what spans heights. Every ring that meets a wall lands at the same horizontal distance along its
bearing, so a wall's cell of the ground plane holds points up to the sensor's height and beyond (the rings above
the horizon meet it higher up), while a table's or a box's cell holds points only up to its top. The tallest of the
cells that never reach the sensor's height is the clutter's height.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import maximum_filter

__all__ = ["HeightBand", "auto_band", "bearing_step", "given_band", "nearest_per_bearing", "sensor_band"]

BIN = 0.02  # m: height histogram bins; a floor seen by a level lidar fits in one or two of them
PLANE_SHARE = 0.01  # a horizontal plane holds at least this share of a sweep's points in one bin
STRAY_SHARE = 0.005  # and at most this share lies beyond it (below a floor, above a ceiling): noise, reflections
PLANE_TOLERANCE = 0.06  # m: points this near the floor or ceiling plane are the plane's (noise, a slight tilt)
MIN_ROOM = 1.5  # m: a ceiling is at least this far above the floor (a peak lower down is a table top)
FLAT = 0.05  # m: a cloud whose heights span less than this is a planar scan published as a cloud
MIN_POINTS = 200  # fewer points than this tell nothing about floor or walls
CELL = 0.1  # m: ground cells in which a column's top is taken
CLEARANCE = 0.1  # m: between the clutter's top and the band
# One sweep shows the clutter around where it was taken, not every chair and crate of the building: the band starts
# no lower than above clutter this tall.
MIN_CLUTTER = 0.5  # m above the floor
CEILING_CLEARANCE = 0.3  # m: between the band and the ceiling (lamps, ducts)
# Door lintels stand about 2 m above the floor: a band above them closes every door of the map.
LINTEL = 1.9  # m above the floor
MIN_WIDTH = 0.2  # m: a band thinner than this keeps too few rings' points on the walls
# Bounds on the bearing step read from a cloud: finer than any spinning lidar's columns, coarser than a sparse one's.
MIN_STEP, MAX_STEP = math.radians(0.05), math.radians(1.0)
SURFACE = 0.1  # m: returns of one bearing this near its nearest are off the same surface


@dataclass(frozen=True)
class HeightBand:
    """Which points of a cloud make the 2D scan: ``low <= z <= high`` in the sensor frame, minus the points of the
    floor and ceiling planes. ``floor`` and ``ceiling`` are their heights in the sensor frame (None: not seen);
    ``clutter`` the top of the clutter above the floor; ``how`` says where the band came from: 'auto', 'given'
    (floor-relative, by the user), 'sensor' (min_z / max_z in the sensor frame) or 'no floor' (auto, falling back
    to the sensor slice)."""

    low: float
    high: float
    how: str
    floor: float | None = None
    ceiling: float | None = None
    clutter: float | None = None
    # Radians: keep the nearest point of each bearing this wide, as a 2D lidar there would have returned it (None:
    # every point, Cartographer's way with a sliced cloud).
    bearing_step: float | None = None

    def keep(self, z: np.ndarray) -> np.ndarray:
        """Which of the heights ``z`` (sensor frame) the 2D scan keeps."""
        keep = (z >= self.low) & (z <= self.high)
        if self.floor is not None:
            keep &= z > self.floor + PLANE_TOLERANCE
        if self.ceiling is not None:
            keep &= z < self.ceiling - PLANE_TOLERANCE
        return keep

    def describe(self) -> str:
        if self.floor is None:
            why = "" if self.how == "sensor" else f" ({self.how})"
            return f"z {self.low:.2f} to {self.high:.2f} m in the sensor frame{why}"
        parts = [f"{self.low - self.floor:.2f} to {self.high - self.floor:.2f} m above the floor ({self.how})",
                 f"floor {-self.floor:.2f} m below the sensor"]
        if self.ceiling is not None:
            parts.append(f"ceiling {self.ceiling - self.floor:.2f} m")
        if self.clutter is not None:
            parts.append(f"clutter up to {self.clutter:.2f} m")
        if self.bearing_step is not None:
            parts.append(f"one return per {math.degrees(self.bearing_step):.2f}° of bearing")
        return ", ".join(parts)

    def to_dict(self) -> dict:
        floor = self.floor
        return {"how": self.how, "low": self.low, "high": self.high, "floor": floor, "ceiling": self.ceiling,
                "clutter": self.clutter,
                "above_floor": None if floor is None else [self.low - floor, self.high - floor],
                "bearing_step_deg": None if self.bearing_step is None else math.degrees(self.bearing_step)}


def sensor_band(min_z: float, max_z: float, how: str = "sensor") -> HeightBand:
    return HeightBand(low=float(min_z), high=float(max_z), how=how)


def floor_and_ceiling(z: np.ndarray) -> tuple[float | None, float | None]:
    """Heights of the floor and the ceiling planes among ``z`` (finite, sensor frame); None where there is none.

    A plane is a bin holding a share of the points no wall gives one bin far from the sensor's height, with
    (almost) nothing beyond it: the floor has nothing below, the ceiling nothing above. Rings meeting walls near
    the sensor's height pile up as much in a bin as a far ceiling does, but points lie above and below them."""
    n = z.shape[0]
    if n < MIN_POINTS or float(np.ptp(z)) < FLAT:
        return None, None
    lo = float(z.min())
    bins = np.minimum(((z - lo) / BIN).astype(np.int64), int(np.ptp(z) / BIN))
    counts = np.bincount(bins)
    index = np.arange(counts.shape[0])
    under = np.concatenate([[0], np.cumsum(counts)])  # under[k]: points in the bins below bin k
    # Two bins' slack: a plane's noise spills into its neighbours.
    beyond_floor = under[np.maximum(index - 2, 0)]
    beyond_ceiling = n - under[np.minimum(index + 3, counts.shape[0])]
    tall = counts >= PLANE_SHARE * n
    floors = np.flatnonzero(tall & (beyond_floor <= STRAY_SHARE * n))
    if floors.shape[0] == 0:
        return None, None
    floor = _plane_height(z, lo + (floors[0] + 0.5) * BIN)
    if floor > -FLAT:
        return None, None  # a plane at or above the sensor is no floor it stands over
    ceilings = np.flatnonzero(tall & (beyond_ceiling <= STRAY_SHARE * n))
    ceiling = None
    if ceilings.shape[0] and ceilings[-1] > floors[0]:
        top = _plane_height(z, lo + (ceilings[-1] + 0.5) * BIN)
        if top - floor >= MIN_ROOM:
            ceiling = top
    return floor, ceiling


def _plane_height(z: np.ndarray, near: float) -> float:
    """The median height of the points within two bins of ``near``: the plane's height to well under a bin."""
    return float(np.median(z[np.abs(z - near) <= 2 * BIN]))


def clutter_height(x: np.ndarray, y: np.ndarray, z: np.ndarray, floor: float, ceiling: float | None) -> float:
    """The top (m above the floor) of the tallest column of points that stays below the sensor's height: see the
    module's note. 0 when there is none."""
    off_planes = (z > floor + PLANE_TOLERANCE) & (z < (math.inf if ceiling is None else ceiling - PLANE_TOLERANCE))
    x, y, z = x[off_planes], y[off_planes], z[off_planes]
    if z.shape[0] == 0:
        return 0.0
    ix = np.floor(x / CELL).astype(np.int64)
    iy = np.floor(y / CELL).astype(np.int64)
    ix -= ix.min()
    iy -= iy.min()
    top = np.full((int(ix.max()) + 1, int(iy.max()) + 1), -np.inf)
    np.maximum.at(top, (ix, iy), z)
    # A column split across two cells (a wall just on a cell border) reaches as high as its taller half.
    reach = maximum_filter(top, size=3, mode="constant", cval=-np.inf)
    low = np.isfinite(top) & (reach < 0.0)
    if not low.any():
        return 0.0
    # The 99th percentile: a stray point (a reflection below the floor's tolerance) does not lift the band.
    return float(np.percentile(top[low], 99.0)) - floor


def auto_band(x: np.ndarray, y: np.ndarray, z: np.ndarray, fallback: HeightBand) -> HeightBand:
    """The band for a cloud like this one (finite points, sensor frame): ``fallback`` when no floor is seen."""
    floor, ceiling = floor_and_ceiling(z)
    if floor is None:
        return HeightBand(fallback.low, fallback.high, "no floor" if fallback.how == "sensor" else fallback.how)
    clutter = clutter_height(x, y, z, floor, ceiling)
    low = max(clutter, MIN_CLUTTER) + CLEARANCE
    high = LINTEL if ceiling is None else min(LINTEL, ceiling - floor - CEILING_CLEARANCE)
    if high - low < MIN_WIDTH:
        # Clutter as tall as the room (shelves to the ceiling): the sensor's own height is the plane a 2D lidar
        # there would have seen.
        sensor = -floor
        low, high = sensor - MIN_WIDTH / 2, sensor + MIN_WIDTH / 2
    return HeightBand(low=floor + low, high=floor + high, how="auto", floor=floor, ceiling=ceiling, clutter=clutter,
                      bearing_step=bearing_step(x, y))


def given_band(x: np.ndarray, y: np.ndarray, z: np.ndarray, above_floor: tuple[float, float],
               fallback: HeightBand) -> HeightBand:
    """The user's band (m above the floor) placed on the floor this cloud shows; ``fallback`` without a floor."""
    floor, ceiling = floor_and_ceiling(z)
    if floor is None:
        return HeightBand(fallback.low, fallback.high, "no floor")
    return HeightBand(low=floor + above_floor[0], high=floor + above_floor[1], how="given", floor=floor,
                      ceiling=ceiling, bearing_step=bearing_step(x, y))


def bearing_step(x: np.ndarray, y: np.ndarray) -> float:
    """The angle between a spinning lidar's columns: the rings of one column share a bearing, so the typical gap
    between distinct bearings of the sorted points is the step (clipped to ``MIN_STEP``..``MAX_STEP``)."""
    angles = np.sort(np.arctan2(y, x))
    gaps = np.diff(angles)
    gaps = gaps[gaps > MIN_STEP / 10]
    if gaps.shape[0] == 0:
        return MIN_STEP
    return float(np.clip(np.median(gaps), MIN_STEP, MAX_STEP))


def nearest_per_bearing(angles: np.ndarray, ranges: np.ndarray, step: float) -> np.ndarray:
    """Indices of one point per bearing bin ``step`` wide, in the order of ``angles``: of the bin's points within
    ``SURFACE`` of its nearest, the one of median range.

    A 2D lidar at the band's height returns the first thing along each bearing. The band's points behind it
    (higher or lower on a farther wall) would draw free rays through it; and the several rings' returns off that
    first surface, inserted all, would thicken it by their noise (their nearest alone would pull it towards the
    sensor by as much): their median is the surface's range."""
    if angles.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    bins = np.floor((angles + math.pi) / step).astype(np.int64)
    order = np.lexsort((ranges, bins))
    b, r = bins[order], ranges[order]
    starts = np.flatnonzero(np.concatenate([[True], b[1:] != b[:-1]]))
    counts = np.diff(np.concatenate([starts, [b.shape[0]]]))
    nearest = np.repeat(r[starts], counts)
    on_surface = np.flatnonzero(r <= nearest + SURFACE)  # sorted: each bin's surface points are its first ones
    sb = b[on_surface]
    first = np.flatnonzero(np.concatenate([[True], sb[1:] != sb[:-1]]))
    many = np.diff(np.concatenate([first, [sb.shape[0]]]))
    return np.sort(order[on_surface[first + (many - 1) // 2]])
