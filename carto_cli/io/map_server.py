"""A plain ROS map_server / nav2 map (YAML + PGM/PNG) read as a map carto can relocalize in.

slam_toolbox, GMapping, a floor plan or a hand-edited map all end up as this pair, and neither
Cartographer nor slam_toolbox localizes in one. The image's occupancy becomes a probability grid
as a submap would hold it: occupied 0.9, free 0.1, ``scale`` mode's grey levels linearly between,
and unknown stays unknown (0), so the matchers treat an image exactly like carto's own submaps.

The YAML's semantics are map_server's (ROS 1 ``image_loader`` / nav2 ``map_io``):

* ``image`` (relative to the YAML), ``resolution`` (m/cell), ``origin`` [x, y, yaw]: the pose of the
  lower-left pixel's corner in the map frame, yaw counter-clockwise;
* ``negate``: with 0 a pixel's occupancy is (255 - v) / 255, with 1 it is v / 255;
* ``mode`` ``trinary`` (above ``occupied_thresh`` occupied, below ``free_thresh`` free, else unknown),
  ``scale`` (between the two, occupancy linear in the grey level; a transparent pixel unknown), ``raw``
  (v itself is the occupancy 0..100, anything above unknown);
* colour pixels are the mean of their channels; a transparent pixel (alpha 0) is unknown in every mode.

Large images are cut into tiles (``TILE_CELLS`` square, each carrying a ``TILE_MARGIN_CELLS`` border of its
neighbours so a scan near a tile's edge still finds the walls it sees): every tile is one submap, so
the relocalizer's submap filtering touches only the tiles near a prior and its precomputation cache holds
only those. An image no larger than one tile with its margins is one submap.
"""
from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import yaml

from carto_cli.core import transform
from carto_cli.core.errors import FormatError
from carto_cli.grid.probability_grid import MAX_PROBABILITY, MIN_PROBABILITY, ProbabilityGrid, probability_to_value
from carto_cli.io.loaded_map import LoadedMap, MapMetadata
from carto_cli.mapping.constraints import ConstraintSet
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options

__all__ = ["MODES", "TILE_CELLS", "TILE_MARGIN_CELLS", "MapServerMap", "is_map_server_yaml", "load_map_server",
           "occupancy_from_pixels"]

MODES = ("trinary", "scale", "raw")
# 1024 cells (51 m at 0.05 m) with 256 on each side (12.8 m, about the reach that matters for matching):
# a building of 60 m x 60 m stays one submap, a campus of 1 km x 1 km becomes ~400 tiles.
TILE_CELLS = 1024
TILE_MARGIN_CELLS = 256
# An image's wall is a line of cells with free cells right beside it; a submap's wall is a ridge a few cells
# wide (every scan puts its hits a little apart). Matched as drawn, a scan a cell off scores as if it missed
# the wall entirely and least squares has no slope to climb, so walls are widened to a ridge of this sigma.
WALL_SIGMA_M = 0.075
_UNKNOWN = -1  # occupancy of an unknown cell (map_server's -1)


class MapServerMap(LoadedMap):
    """A :class:`LoadedMap` made from an occupancy image: tiles as submaps, no nodes, no constraints."""

    image_path: Path
    mode: str
    occupancy: np.ndarray  # (rows, cols) int8 0..100 or -1, row 0 the lowest y (the grid's orientation)
    origin: np.ndarray  # (3,) the lower-left corner's pose in the map frame


def is_map_server_yaml(path: str | Path) -> bool:
    return Path(path).suffix.lower() in (".yaml", ".yml")


def occupancy_from_pixels(pixels: np.ndarray, *, mode: str = "trinary", negate: bool = False,
                          occupied_thresh: float = 0.65, free_thresh: float = 0.196) -> np.ndarray:
    """map_server's occupancy (int8: 0..100, -1 unknown) of an image (rows, cols[, channels]), row 0 at the top."""
    px = np.asarray(pixels)
    if px.dtype == np.uint16:
        px = (px.astype(np.float64) / 257.0)
    px = px.astype(np.float64)
    alpha = None
    if px.ndim == 3:
        channels = px.shape[2]
        if channels in (2, 4):
            alpha = px[:, :, -1]
            px = px[:, :, :-1]
        px = px.mean(axis=2)
    value = 255.0 - px if negate else px
    out = np.full(px.shape, _UNKNOWN, dtype=np.int8)
    if mode == "raw":
        v = np.rint(value)
        keep = v <= 100
        out[keep] = v[keep].astype(np.int8)
    else:
        occ = (255.0 - value) / 255.0
        out[occ > occupied_thresh] = 100
        out[occ < free_thresh] = 0
        if mode == "scale":
            between = (occ <= occupied_thresh) & (occ >= free_thresh)
            ratio = (occ - free_thresh) / max(occupied_thresh - free_thresh, 1e-9)
            out[between] = np.rint(1 + 98 * ratio[between]).astype(np.int8)
    if alpha is not None:
        out[alpha == 0] = _UNKNOWN
    return out


def _probability_values(occupancy: np.ndarray, resolution: float) -> np.ndarray:
    """Grid cell values (uint16, 0 unknown) of an occupancy array, walls widened to a likelihood field."""
    p = np.clip(occupancy.astype(np.float64) / 100.0, MIN_PROBABILITY, MAX_PROBABILITY)
    known = occupancy >= 0
    occupied = occupancy >= 50
    if occupied.any():
        # Distance (cells) of every cell to the nearest occupied one.
        d = cv2.distanceTransform(np.where(occupied, 0, 255).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
        sigma = WALL_SIGMA_M / resolution
        near = d <= 2.0 * sigma
        field = MIN_PROBABILITY + (MAX_PROBABILITY - MIN_PROBABILITY) * np.exp(-0.5 * (d / sigma) ** 2)
        p = np.where(near, np.maximum(np.where(known, p, 0.0), field), p)
        known = known | near
    values = probability_to_value(p)
    values[~known] = 0
    return values


def _read_yaml(path: Path) -> dict:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise FormatError("no such map file", path) from None
    except OSError as e:
        raise FormatError(f"cannot read the map: {e.strerror}", path) from None
    except UnicodeDecodeError:
        raise FormatError("not a map_server YAML (not text)", path) from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise FormatError(f"not valid YAML: {str(e).splitlines()[0]}", path) from None
    if not isinstance(data, dict) or "image" not in data:
        raise FormatError("not a map_server YAML (no 'image' key)", path)
    return data


def _number(data: dict, key: str, path: Path, default=None) -> float:
    v = data.get(key, default)
    if v is None:
        raise FormatError(f"map_server YAML lacks '{key}'", path)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(float(v)):
        raise FormatError(f"'{key}' must be a number, got {v!r}", path)
    return float(v)


def load_map_server(path: str | Path, options: Options | None = None) -> MapServerMap:
    """The map_server map whose YAML is ``path`` (module doc). ``options``: what the relocalizer will use
    (default: carto's defaults); FormatError for anything map_server itself would not load."""
    path = Path(path)
    data = _read_yaml(path)
    resolution = _number(data, "resolution", path)
    if resolution <= 0:
        raise FormatError(f"'resolution' must be > 0, got {resolution:g}", path)
    origin = data.get("origin")
    if (not isinstance(origin, (list, tuple)) or len(origin) not in (2, 3)
            or not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in origin)):
        raise FormatError(f"'origin' must be [x, y, yaw] in metres and radians, got {origin!r}", path)
    origin_pose = np.array([float(origin[0]), float(origin[1]), float(origin[2]) if len(origin) == 3 else 0.0])
    mode = str(data.get("mode", "trinary")).lower()
    if mode not in MODES:
        raise FormatError(f"'mode' must be one of {', '.join(MODES)}, got {data.get('mode')!r}", path)
    negate = data.get("negate", 0)
    if negate not in (0, 1, True, False):
        raise FormatError(f"'negate' must be 0 or 1, got {negate!r}", path)
    occupied_thresh = _number(data, "occupied_thresh", path, 0.65)
    free_thresh = _number(data, "free_thresh", path, 0.196)
    if not 0.0 <= free_thresh <= occupied_thresh <= 1.0:
        raise FormatError(f"need 0 <= free_thresh ({free_thresh:g}) <= occupied_thresh ({occupied_thresh:g}) <= 1",
                          path)
    image_path = Path(str(data["image"]))
    if not image_path.is_absolute():
        image_path = path.parent / image_path
    if not image_path.is_file():
        raise FormatError(f"its image {image_path} does not exist", path)
    pixels = cv2.imread(str(image_path), cv2.IMREAD_UNCHANGED)
    if pixels is None or pixels.size == 0 or pixels.ndim not in (2, 3):
        raise FormatError("not an image OpenCV can read (PGM, PNG, ...)", image_path)
    occupancy = occupancy_from_pixels(pixels, mode=mode, negate=bool(negate), occupied_thresh=occupied_thresh,
                                      free_thresh=free_thresh)[::-1]
    if not (occupancy >= 0).any():
        raise FormatError("the map has no known cell (every pixel reads unknown)", image_path)

    if options is None:
        options = Options()
    submaps, global_poses = _tiles(occupancy, resolution, origin_pose)
    m = len(submaps)
    loaded = MapServerMap(
        path=path, options=options,
        metadata=MapMetadata(format_version=0, carto_version="", created="", recordings=(),
                             stats={"format": "map_server", "mode": mode, "image": str(image_path)}),
        submaps=submaps, submap_trajectories=np.zeros(m, dtype=np.int64), submap_global_poses=global_poses,
        submap_nodes=[np.zeros(0, dtype=np.int64) for _ in range(m)], node_times=np.zeros(0),
        node_trajectories=np.zeros(0, dtype=np.int64), node_local_poses=np.zeros((0, 3)),
        node_global_poses=np.zeros((0, 3)), node_odometry=np.zeros((0, 3)), node_points=[],
        constraints=ConstraintSet(capacity=1), trajectory=None, node_scans=None, laser_pose=None)
    loaded.image_path = image_path
    loaded.mode = mode
    loaded.occupancy = occupancy
    loaded.origin = origin_pose
    return loaded


def _tiles(occupancy: np.ndarray, resolution: float, origin_pose: np.ndarray) -> tuple[list[Submap], np.ndarray]:
    """Submaps covering the image: its grid frame is the image's (lower-left corner at 0, 0), each tile a grid
    on the same lattice; a tile's submap pose is the image origin moved to the tile's corner."""
    rows, cols = occupancy.shape
    span = TILE_CELLS + 2 * TILE_MARGIN_CELLS
    if rows <= span and cols <= span:
        starts_x, starts_y, core, margin = [0], [0], max(rows, cols), 0
    else:
        core, margin = TILE_CELLS, TILE_MARGIN_CELLS
        starts_x = list(range(0, cols, core))
        starts_y = list(range(0, rows, core))
    submaps: list[Submap] = []
    poses = []
    for ty in starts_y:
        for tx in starts_x:
            x0, y0 = max(tx - margin, 0), max(ty - margin, 0)
            x1, y1 = min(tx + core + margin, cols), min(ty + core + margin, rows)
            block = occupancy[y0:y1, x0:x1]
            known = np.argwhere(block >= 0)
            if known.size == 0:
                continue
            (ky0, kx0), (ky1, kx1) = known.min(axis=0), known.max(axis=0)
            x0, x1, y0, y1 = x0 + int(kx0), x0 + int(kx1) + 1, y0 + int(ky0), y0 + int(ky1) + 1
            corner = np.array([x0 * resolution, y0 * resolution])
            grid = ProbabilityGrid(resolution, corner, (x1 - x0, y1 - y0))
            grid.cells[:, :] = _probability_values(occupancy[y0:y1, x0:x1], resolution)
            grid.known_box = np.array([0, 0, x1 - x0 - 1, y1 - y0 - 1], dtype=np.int64)
            grid.version = 1
            submap = Submap(corner, resolution=resolution, index=len(submaps), initial_size=1)
            submap.grid = grid
            submap.finished = True
            submaps.append(submap)
            # map <- grid: origin ∘ (corner, 0); with local_pose (corner, 0) the relocalizer's
            # map_to_grid = local ∘ inverse(global) is inverse(origin), the same for every tile.
            poses.append(transform.compose(origin_pose, np.array([corner[0], corner[1], 0.0])))
    return submaps, np.array(poses, dtype=np.float64).reshape(-1, 3)
