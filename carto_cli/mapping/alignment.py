"""A map square to its building (``carto map --align auto``): the walls' dominant direction read off the finished
map, and the map frame turned so that they run along the image axes.

map_server and nav2 ignore the origin's yaw in map.yaml, so a map drawn at 17° stays at 17° on every screen: the
image itself has to be turned, and with it every pose in the map frame, so that the outputs stay one map.

- **The walls' direction** (:func:`wall_axes`): the cells sure of a wall are projected onto lines across a
  direction and across its perpendicular; walls along that direction pile into few bins of the two profiles, whose
  summed squares score it (a numba kernel). Every half degree first, then every 0.02° about the best, the peak refined
  by a parabola. How much the best direction scores over the median one says whether there is a direction at all
  (a round hall, clutter: no). A histogram of occupancy-gradient directions was tried first and rejected: the steps
  of a slanted one-cell wall pull its gradients towards the axes (up to 8° off).
- **The rotation** (:func:`squaring`): the smallest turn that lays the peak on an axis, in (-45°, 45°]. Below
  ``DEAD_BAND`` the frame is left alone: the estimate is not that exact, and a map square already (a simulated
  building, a robot started along a corridor) keeps its frame and its outputs byte for byte.
- **Turning** (:func:`turned`): node and submap global poses, scan poses and the loop-closure segments move; the
  local-SLAM poses and the odometry stay, they are in frames of their own. An assembled map is assembled again
  from its submaps at the turned poses; an image of its own (GMapping's) is resampled.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
from numba import njit

from carto_cli.core import transform
from carto_cli.core.enums import TextEnum
from carto_cli.core.errors import CartoError
from carto_cli.core.kernels import register_warm_up
from carto_cli.grid.occupancy_image import EAGER_CELLS, STRIP_ROWS, AssembledImage, OccupancyImage, image_rows
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.slam import SlamResult

__all__ = ["DEAD_BAND", "MIN_CONTRAST", "Align", "Axes", "Squaring", "squaring", "turned", "turned_image",
           "turned_poses", "wall_axes"]


class Align(TextEnum):
    """Whether a new map's frame is turned square to its building."""

    AUTO = "auto"  # turned so that the dominant walls run along the image axes
    NONE = "none"  # the frame local SLAM started in: the robot's first pose

    @classmethod
    def named(cls, text: str) -> Align:
        """The member ``text`` names (``--align``'s value); a one-line error for any other."""
        try:
            return cls(text)
        except ValueError:
            raise CartoError(f"--align: unknown value '{text}' (choose from "
                             f"{', '.join(a.value for a in cls)})") from None


# The search for the walls' direction: every half degree with bins of COARSE_BIN cells (a 5 m wall then stands out
# over 2°, so no step misses it), then every FINE_STEP within FINE_SPAN of the best with bins of one cell, the peak
# refined by a parabola through the best three.
COARSE_STEP = math.radians(0.5)
COARSE_BIN = 4.0
FINE_SPAN = math.radians(1.0)
FINE_STEP = math.radians(0.02)
MAX_MOVES = 4
# The sharpest direction's score over the median direction's, less one, below which the map is said to have no
# clear direction (clutter, a round hall: every direction projects alike)
MIN_CONTRAST = 0.15
DEAD_BAND = math.radians(0.5)
SURE_WALL = 0.25  # occupied evidence (0 to 1) a cell needs to take part: grazed cells only blur the profiles
MARGIN_CELLS = 10  # unknown cells kept around a turned image's known ones, as an assembled map keeps


@dataclass(frozen=True)
class Axes:
    """The walls' dominant direction modulo 90° (rad, in (-45°, 45°]) and how much sharper the map projects along
    it than along the median direction (0: alike)."""

    angle: float
    contrast: float

    @property
    def clear(self) -> bool:
        return self.contrast >= MIN_CONTRAST


@dataclass(frozen=True)
class Squaring:
    """What ``--align`` did: the rotation applied to the map frame (rad; 0: none) and why, with the walls' direction
    it was read from (None when not looked for)."""

    rotation: float
    reason: str
    axes: Axes | None = None

    def describe(self) -> str:
        """One line for the terminal."""
        if self.rotation:
            return f"map turned {math.degrees(self.rotation):+.2f}° to lay the walls along the image axes"
        return self.reason

    def to_dict(self) -> dict:
        return {"rotation_deg": math.degrees(self.rotation), "reason": self.reason,
                "walls_deg": None if self.axes is None else math.degrees(self.axes.angle),
                "contrast": None if self.axes is None else self.axes.contrast}


def wall_axes(image: OccupancyImage | AssembledImage) -> Axes:
    """The dominant direction, modulo 90°, of the walls of ``image`` (read strip by strip, as it is written)."""
    x, y, w = _wall_cells(image)
    if len(x) < 2:
        return Axes(0.0, 0.0)
    coarse = np.arange(0.0, math.pi / 2, COARSE_STEP)
    scores = _sharpness(x, y, w, coarse, COARSE_BIN)
    median = float(np.median(scores))
    best = float(coarse[int(np.argmax(scores))])
    angle = _finest(x, y, w, best)
    return Axes(_square_turn(angle), float(scores.max()) / median - 1.0 if median > 0 else 0.0)


def _finest(x: np.ndarray, y: np.ndarray, w: np.ndarray, best: float) -> float:
    """The sharpest direction at one cell's bins near ``best``. The window follows its peak when that lies at an
    end: the coarse bins may favour the many short walls and the fine ones a few long ones a degree apart (a map
    whose far end bent)."""
    for _ in range(MAX_MOVES):
        fine = best + np.arange(-FINE_SPAN, FINE_SPAN + FINE_STEP / 2, FINE_STEP)
        sharp = _sharpness(x, y, w, fine, 1.0)
        k = int(np.argmax(sharp))
        if 0 < k < len(fine) - 1:
            return float(fine[k]) + _vertex(sharp[k - 1:k + 2]) * FINE_STEP
        best = float(fine[k])
    return best


def _vertex(three: np.ndarray) -> float:
    """Where a parabola through three equally spaced values peaks, in steps from the middle one (within ±1)."""
    a, b, c = (float(v) for v in three)
    curvature = a - 2 * b + c
    return 0.0 if curvature >= 0 else float(np.clip(0.5 * (a - c) / curvature, -1.0, 1.0))


def _wall_cells(image: OccupancyImage | AssembledImage) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centres (in cells, about the walls' centroid) and occupied evidence of the cells sure enough of a wall."""
    xs, ys, ws = [], [], []
    top = image.shape[0]
    for rows in image_rows(image, STRIP_ROWS):
        evidence = np.clip(np.nan_to_num(rows, nan=0.5) * 2.0 - 1.0, 0.0, 1.0)
        iy, ix = np.nonzero(evidence >= SURE_WALL)
        xs.append(ix.astype(np.float64))
        ys.append((top - iy).astype(np.float64))  # rows run top down: a y-up coordinate
        ws.append(evidence[iy, ix].astype(np.float64))
        top -= rows.shape[0]
    x, y, w = (np.concatenate(v) if v else np.zeros(0) for v in (xs, ys, ws))
    return (x - x.mean(), y - y.mean(), w) if len(x) else (x, y, w)


@njit(cache=True, nogil=True)
def _sharpness(x, y, w, angles, bin_cells):
    """For every angle, how sharply the cells project onto lines across it and across the perpendicular: the sum
    of the squared bins of both profiles (each cell split linearly between its two nearest bins, so the sum is
    smooth in the angle). Walls along a direction pile into few bins, and score most."""
    radius = 0.0
    for i in range(x.shape[0]):
        radius = max(radius, math.sqrt(x[i] * x[i] + y[i] * y[i]))
    half = int(radius / bin_cells) + 2
    hist = np.zeros(2 * half + 2)
    out = np.zeros(angles.shape[0])
    for k in range(angles.shape[0]):
        for turn in range(2):
            c = math.cos(angles[k] + turn * math.pi / 2)
            s = math.sin(angles[k] + turn * math.pi / 2)
            hist[:] = 0.0
            for i in range(x.shape[0]):
                u = (c * x[i] + s * y[i]) / bin_cells + half
                j = int(math.floor(u))
                f = u - j
                hist[j] += w[i] * (1.0 - f)
                hist[j + 1] += w[i] * f
            out[k] += np.sum(hist * hist)
    return out


def _square_turn(angle: float) -> float:
    """``angle`` moved by quarter turns into (-45°, 45°]."""
    turned = transform.wrap_angle_scalar(4.0 * angle) / 4.0  # a quarter turn is a whole one, four times over
    return math.pi / 4 if turned <= -math.pi / 4 + 1e-12 else turned


def squaring(axes: Axes) -> Squaring:
    """The smallest rotation that lays ``axes`` along the image axes, or none: no clear direction, or square
    within ``DEAD_BAND`` already."""
    rotation = _square_turn(-axes.angle)
    if not axes.clear:
        return Squaring(0.0, f"no clear wall direction (contrast {axes.contrast:.2f}, {MIN_CONTRAST} needed): "
                             "frame kept", axes)
    if abs(rotation) < DEAD_BAND:
        return Squaring(0.0, f"already square (walls at {math.degrees(axes.angle):+.2f}°)", axes)
    return Squaring(rotation, "turned square to the walls", axes)


def turned_poses(poses: np.ndarray, rotation: float) -> np.ndarray:
    """(N, 3) map-frame poses in the map frame turned by ``rotation`` about its origin."""
    poses = np.asarray(poses, dtype=np.float64)
    if not len(poses):
        return poses.copy()
    return transform.compose(np.array([0.0, 0.0, rotation]), poses.reshape(-1, 3)).reshape(poses.shape)


def _turned_points(xy: np.ndarray, rotation: float) -> np.ndarray:
    """(K, 2k) rows of x y pairs (loop-closure segments) turned alike."""
    xy = np.asarray(xy, dtype=np.float64)
    return transform.rotate(rotation, xy.reshape(-1, 2)).reshape(xy.shape)


def turned_image(image: OccupancyImage | AssembledImage, rotation: float) -> OccupancyImage | AssembledImage:
    """``image`` in the map frame turned by ``rotation``: an assembled one assembled again from its submaps (as
    sharp as the map was), an image of its own resampled, each cell the value of the cell under its centre (the
    way submaps are assembled; values stay the system's own, which interpolation would blur below its walls'
    threshold)."""
    frame = np.array([0.0, 0.0, rotation])
    if isinstance(image, AssembledImage):
        moved = image.moved(frame)
        if moved.shape[0] * moved.shape[1] <= EAGER_CELLS:
            moved.probability  # noqa: B018 - assembled now, in the align stage, as the map was when mapping ended
        return moved
    return _resampled(image, rotation)


def _resampled(image: OccupancyImage, rotation: float) -> OccupancyImage:
    res = image.resolution
    h, w = image.shape
    corners = np.array([[0, 0], [w, 0], [w, h], [0, h]], dtype=np.float64) * res + np.asarray(image.origin)
    placed = transform.rotate(rotation, corners)
    # a corner a turn puts on a cell's edge (a quarter turn: all) stays there, not one cell out by rounding
    lo = np.floor(placed.min(axis=0) / res + 1e-9) * res
    hi = np.ceil(placed.max(axis=0) / res - 1e-9) * res
    nx, ny = (int(round(v)) for v in (hi - lo) / res)
    out = np.full((ny, nx), np.nan, np.float32)
    c, s = math.cos(rotation), math.sin(rotation)
    xs = lo[0] + (np.arange(nx) + 0.5) * res
    for y0 in range(0, ny, STRIP_ROWS):
        ys = lo[1] + (np.arange(y0, min(y0 + STRIP_ROWS, ny)) + 0.5) * res
        wx, wy = xs[None, :], ys[:, None]
        # inverse rotation: where in the image before each output cell's centre lies
        ix = np.floor((c * wx + s * wy - image.origin[0]) / res).astype(np.int64)
        iy = np.floor((-s * wx + c * wy - image.origin[1]) / res).astype(np.int64)
        inside = (ix >= 0) & (iy >= 0) & (ix < w) & (iy < h)
        strip = out[y0:y0 + len(ys)]
        strip[inside] = image.probability[iy[inside], ix[inside]]
    # The turned rectangle's corners are unknown: cut back to the known cells and the margin an assembled map keeps
    known = ~np.isnan(out)
    rows, cols = np.flatnonzero(known.any(axis=1)), np.flatnonzero(known.any(axis=0))
    if not len(rows):
        return OccupancyImage(out, res, (float(lo[0]), float(lo[1])))
    y0, y1 = max(int(rows[0]) - MARGIN_CELLS, 0), min(int(rows[-1]) + MARGIN_CELLS + 1, ny)
    x0, x1 = max(int(cols[0]) - MARGIN_CELLS, 0), min(int(cols[-1]) + MARGIN_CELLS + 1, nx)
    return OccupancyImage(np.ascontiguousarray(out[y0:y1, x0:x1]), res,
                          (float(lo[0] + x0 * res), float(lo[1] + y0 * res)))


def turn_graph(graph: PoseGraph, rotation: float) -> None:
    """Turn ``graph``'s map frame in place: its node and submap global poses (what map.carto and a .pbstream hold
    in the map frame). Constraints are relative poses, local poses and odometry are in frames of their own: they
    stay. In place because the graph is the one mapping just made, held by its result alone, and a copy would
    copy every submap's grid."""
    graph.settle()  # nothing in flight may move a pose after it was turned
    if graph.num_nodes:
        graph.global_poses[:] = turned_poses(graph.global_poses, rotation)
    for entry in graph.submaps:
        entry.global_pose = turned_poses(entry.global_pose[None, :], rotation)[0]


R = TypeVar("R", bound=SlamResult)


def turned(result: R, rotation: float) -> R:
    """``result`` with its map frame turned by ``rotation``: scan poses, submap poses, loop-closure segments, the
    image and the pose graph (turned in place, :func:`turn_graph`)."""
    if result.graph is not None:
        turn_graph(result.graph, rotation)
    unrefined = result.unrefined_node_poses
    return dataclasses.replace(
        result, poses=turned_poses(result.poses, rotation), submap_poses=turned_poses(result.submap_poses, rotation),
        loop_closures=_turned_points(result.loop_closures, rotation), image=turned_image(result.image, rotation),
        unrefined_node_poses=None if unrefined is None else turned_poses(unrefined, rotation))


@register_warm_up
def warm_up() -> None:
    """The projection kernel on a few cells."""
    _sharpness(np.array([0.0, 1.0, 2.0]), np.array([0.0, 0.0, 1.0]), np.ones(3), np.array([0.0, 0.1]), 1.0)
