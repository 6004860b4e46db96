"""The map side of relocalization: a loaded map's submaps as the searches and the judge read them.

:class:`MapIndex` holds each submap's grid (cropped to its known cells), its frames (a submap's grid lives in its
trajectory's local frame; a map pose P is at ``local_pose ∘ inverse(global_pose) ∘ P`` in the grid, as in the
constraint builder), its known box, where the robot stood while building it (its nodes) and the small set of
submaps that holds every node (the covering set). From those it answers where a pose is in the map: the distance
filters around a prior (box radius, corridor), the submap to match a pose against, whether the laser could stand
at a place (``seen``); and it prepares a scan as local SLAM did when the map was built (``preprocess``).
It searches nothing and judges nothing: ``search.py`` and ``judge.py`` read it.
"""
from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.core.records import Scan
from carto_cli.grid.probability_grid import UNKNOWN_VALUE, VALUE_TO_PROBABILITY
from carto_cli.options import Options
from carto_cli.sensor.range_filter import crop_scan
from carto_cli.sensor.voxel_filter import adaptive_voxel_filter, voxel_filter

__all__ = ["NODE_MARGIN", "MapIndex"]

NODE_MARGIN = 2.0  # m: a whole-submap search covers the box of the submap's nodes plus this


class MapIndex:
    """A loaded map's submaps, their frames, boxes and nodes (module doc). ``options``: the relocalization's (its
    ``relocalization`` section bounds the filters, ``trajectory_builder_2d`` prepares the scans)."""

    def __init__(self, loaded_map, options: Options):
        self.map = loaded_map
        self.options = options
        self.ro = options.relocalization
        if loaded_map.num_submaps == 0:
            raise CartoError("the map has no submaps to relocalize in", getattr(loaded_map, "path", None))
        self.laser_pose = (np.zeros(3) if loaded_map.laser_pose is None
                           else np.asarray(loaded_map.laser_pose, dtype=np.float64).reshape(3))
        m = loaded_map.num_submaps
        # A map saved mid-trajectory holds its newest submaps as allocated while growing (several times their
        # known area: docs/measurements.md); their precomputation stacks would be as big, and evict each other
        # from the cache on every whole-map search.
        self.grids = [_tight(s.grid) for s in loaded_map.submaps]
        # map -> grid frame of each submap: local_pose ∘ inverse(global_pose)
        self.map_to_grid = np.array([
            transform.compose(s.local_pose, transform.inverse(loaded_map.submap_global_poses[i]))
            for i, s in enumerate(loaded_map.submaps)]).reshape(m, 3)
        self.grid_to_map = transform.inverse(self.map_to_grid).reshape(m, 3)
        # Known bounding box of each grid, in its grid frame: (x0, y0, x1, y1); NaN when empty.
        self.boxes = np.full((m, 4), np.nan)
        for i, g in enumerate(self.grids):
            kb = g.known_bounds
            if kb is not None:
                lo = g.origin + np.array(kb[:2], dtype=np.float64) * g.resolution
                hi = g.origin + (np.array(kb[2:], dtype=np.float64) + 1.0) * g.resolution
                self.boxes[i] = [lo[0], lo[1], hi[0], hi[1]]
        self.searchable = [i for i in range(m) if not np.isnan(self.boxes[i, 0])]
        self._searchable_set = set(self.searchable)
        if not self.searchable:
            raise CartoError("every submap of the map is empty", getattr(loaded_map, "path", None))
        # Where the robot was while building each submap (its nodes), to order the search.
        self.node_xy = [np.asarray(loaded_map.node_global_poses, dtype=np.float64)[
            np.asarray(nodes, dtype=np.int64), :2] if len(nodes) else
            transform.apply(self.grid_to_map[i], self.map.submaps[i].local_pose[None, :2])
            for i, nodes in enumerate(loaded_map.submap_nodes)]
        self.covering = self._covering_submaps()
        # Where a whole-submap search looks: the box of the submap's nodes plus a margin (the robot can only be
        # where it was while mapping), as (centre x, centre y, half-width) in the grid frame; for a grid without
        # nodes (a map_server image's tiles) the box of its free cells plus the margin (the laser stands in free
        # space); None: the whole grid.
        self.node_windows: list[tuple[float, float, float] | None] = []
        for i, nodes in enumerate(loaded_map.submap_nodes):
            if len(nodes) == 0:
                self.node_windows.append(_free_window(self.grids[i]) if i in self._searchable_set else None)
                continue
            xy = transform.apply(self.map_to_grid[i], self.node_xy[i]).reshape(-1, 2)
            lo, hi = xy.min(axis=0) - NODE_MARGIN, xy.max(axis=0) + NODE_MARGIN
            self.node_windows.append((float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2, float(max(hi - lo)) / 2))
        self._track_xy = np.concatenate(self.node_xy).reshape(-1, 2)
        self._track_submap = np.concatenate([np.full(len(p), i) for i, p in enumerate(self.node_xy)]).astype(np.int64)

    def _covering_submaps(self) -> list[int]:
        """A small set of submaps holding every node (greedy set cover, biggest first).

        Consecutive submaps overlap by half (every scan goes into two), so about half of them
        already hold every place the robot was: whole-map searches visit only those.
        """
        sets = {i: {int(n) for n in self.map.submap_nodes[i]} for i in self.searchable}
        uncovered = set().union(*sets.values()) if sets else set()
        chosen: list[int] = []
        while uncovered:
            i = max(sets, key=lambda j: (len(sets[j] & uncovered), -j))
            gain = sets[i] & uncovered
            if not gain:
                break
            chosen.append(i)
            uncovered -= gain
        # Submaps without nodes (hand-made maps) are searched too.
        chosen += [i for i in self.searchable if not sets[i]]
        return sorted(chosen)

    # ------------------------------------------------------------------ scan preprocessing

    def preprocess(self, scan: Scan, laser_pose=None, *, search: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """(search points, refinement points), both (n, 2) in the tracking frame; without ``search`` the search
        points are not filtered (an empty array: a step that only refines)."""
        tb = self.options.trajectory_builder_2d
        mount = self.laser_pose if laser_pose is None else transform.as_pose(laser_pose).reshape(3)
        data = crop_scan(scan, mount=mount, min_range=tb.min_range, max_range=tb.max_range,
                         missing_data_ray_length=tb.missing_data_ray_length)
        returns = voxel_filter(data.returns, tb.voxel_filter_size) if len(data.returns) else data.returns
        lc = tb.loop_closure_adaptive_voxel_filter
        coarse = (adaptive_voxel_filter(returns, max_length=lc.max_length, min_num_points=lc.min_num_points,
                                        max_range=lc.max_range) if search else np.zeros((0, 2)))
        f = tb.adaptive_voxel_filter
        fine = adaptive_voxel_filter(returns, max_length=f.max_length, min_num_points=f.min_num_points,
                                     max_range=f.max_range)
        return np.ascontiguousarray(coarse, dtype=np.float64), np.ascontiguousarray(fine, dtype=np.float64)

    # ------------------------------------------------------------------ submap filtering

    def box_distances(self, xy) -> np.ndarray:
        """Distance (m) from map point ``xy`` to every submap's known box; inf for empty submaps."""
        xy = np.asarray(xy, dtype=np.float64).reshape(2)
        g = self.map_to_grid
        c, s = np.cos(g[:, 2]), np.sin(g[:, 2])
        px = c * xy[0] - s * xy[1] + g[:, 0]
        py = s * xy[0] + c * xy[1] + g[:, 1]
        b = self.boxes
        with np.errstate(invalid="ignore"):
            dx = np.maximum(np.maximum(b[:, 0] - px, px - b[:, 2]), 0.0)
            dy = np.maximum(np.maximum(b[:, 1] - py, py - b[:, 3]), 0.0)
        out = np.hypot(dx, dy)
        out[np.isnan(out)] = np.inf
        return out

    def radius_for(self, sigma_xy: float, reliable: bool) -> float:
        """Search radius from the prior's confidence: high (sigma small), medium (reliable), low."""
        if not reliable:
            return self.ro.low_confidence_radius
        if sigma_xy <= self.ro.high_confidence_sigma_xy:
            return self.ro.high_confidence_radius
        return self.ro.medium_confidence_radius

    def filter_by_distance(self, prior, radius: float) -> list[int]:
        """Submaps whose known box is within ``radius`` of the prior, nearest track first."""
        d = self.box_distances(np.asarray(prior, dtype=np.float64)[:2])
        return self.order([i for i in self.searchable if d[i] <= radius], prior)

    def filter_corridor(self, prior, forward_range: float | None = None, side_range: float | None = None) -> list[int]:
        """Submaps whose known box meets the rectangle ±forward_range along the prior's heading, ±side_range across.

        Separating-axis test of two oriented rectangles (the submap box is axis-aligned in its grid frame).
        """
        fr = self.ro.corridor_forward_range if forward_range is None else float(forward_range)
        sr = self.ro.corridor_side_range if side_range is None else float(side_range)
        prior = transform.as_pose(prior).reshape(3)
        keep = []
        for i in self.searchable:
            # The corridor rectangle in the submap's grid frame.
            centre = transform.compose(self.map_to_grid[i], prior)
            c, s = math.cos(centre[2]), math.sin(centre[2])
            axes_r = np.array([[c, s], [-s, c]])  # rectangle's axes (rows)
            half_r = np.array([fr, sr])
            x0, y0, x1, y1 = self.boxes[i]
            box_c = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
            half_b = np.array([(x1 - x0) / 2, (y1 - y0) / 2])
            d = box_c - centre[:2]
            separated = False
            # Box axes (x, y).
            for k in range(2):
                proj_r = abs(axes_r[0, k]) * half_r[0] + abs(axes_r[1, k]) * half_r[1]
                if abs(d[k]) > half_b[k] + proj_r:
                    separated = True
                    break
            if not separated:
                for k in range(2):
                    a = axes_r[k]
                    proj_b = abs(a[0]) * half_b[0] + abs(a[1]) * half_b[1]
                    if abs(d @ a) > half_r[k] + proj_b:
                        separated = True
                        break
            if not separated:
                keep.append(i)
        return self.order(keep, prior)

    def track_distances(self, xy) -> np.ndarray:
        """Distance (m) from map point ``xy`` to the nearest node of every submap (where its scans were taken)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(2)
        d = np.hypot(self._track_xy[:, 0] - xy[0], self._track_xy[:, 1] - xy[1])
        out = np.full(self.map.num_submaps, np.inf)
        np.minimum.at(out, self._track_submap, d)
        return out

    def nearest_submap(self, xy) -> int:
        """The searchable submap to match a pose at ``xy`` against: the one whose scans were taken nearest it; in
        a map without nodes (a map_server image's tiles) the one whose known box holds it most centrally."""
        xy = np.asarray(xy, dtype=np.float64).reshape(2)
        if len(self._track_xy):
            d = self.track_distances(xy)
            return min(self.searchable, key=lambda i: (d[i], i))
        box = self.box_distances(xy)
        centre = np.array([transform.apply(self.grid_to_map[i], np.array([[(b[0] + b[2]) / 2, (b[1] + b[3]) / 2]]))[0]
                           if not np.isnan(b[0]) else (np.inf, np.inf) for i, b in enumerate(self.boxes)])
        off = np.hypot(centre[:, 0] - xy[0], centre[:, 1] - xy[1])
        return min(self.searchable, key=lambda i: (box[i], off[i], i))

    def order(self, indices: Sequence[int], prior) -> list[int]:
        """Nearest first, by the distance from the prior to the submap's nodes."""
        key = self.track_distances(np.asarray(prior, dtype=np.float64)[:2])
        return sorted(indices, key=lambda i: (key[i], i))

    def check_prior(self, prior) -> float:
        """Distance to the nearest submap; CartoError beyond ``max_prior_distance``."""
        prior = transform.as_pose(prior).reshape(3)
        if not np.all(np.isfinite(prior)):
            raise CartoError(f"initial pose must be finite numbers, got {prior[0]:g},{prior[1]:g},{prior[2]:g}")
        d = float(np.min(self.box_distances(prior[:2])))
        if d > self.ro.max_prior_distance:
            raise CartoError(f"initial pose {prior[0]:g},{prior[1]:g} is {d:.1f} m from the nearest submap "
                             f"(more than relocalization.max_prior_distance = {self.ro.max_prior_distance:g} m)",
                             getattr(self.map, "path", None))
        return d

    def seen(self, submap: int, xy) -> bool:
        """Whether a cell of the map knows grid point ``xy`` of submap ``submap`` (that submap's, else any other's).

        A scan's rays all start at the laser, so the map knows every place the robot stood while mapping, and a
        map_server image marks where a robot can stand as free. A match that puts the laser on an unknown cell has
        fitted the scan's walls to walls of the map from a place outside it: on bench-dense's map images, a scan of
        another building fitted to the lip of the map's outline (docs/localization.md); no right answer of the
        building's own scans stood on an unknown cell."""
        xy = np.asarray(xy, dtype=np.float64).reshape(1, 2)
        if self.grids[submap].is_known(self.grids[submap].cell_index(xy))[0]:
            return True
        # The point in every submap's grid frame at once; only those whose known box holds it are looked up (a
        # tracked robot at the map's edge asks this every scan, of maps with hundreds of submaps).
        x, y = transform.apply(self.grid_to_map[submap], xy)[0]
        m = self.map_to_grid
        c, s = np.cos(m[:, 2]), np.sin(m[:, 2])
        gx, gy = c * x - s * y + m[:, 0], s * x + c * y + m[:, 1]
        b = self.boxes  # NaN for empty submaps: every comparison false
        inside = (b[:, 0] <= gx) & (gx <= b[:, 2]) & (b[:, 1] <= gy) & (gy <= b[:, 3])
        inside[submap] = False
        for i in np.flatnonzero(inside):
            g = self.grids[i]
            if g.is_known(g.cell_index(np.array([[gx[i], gy[i]]])))[0]:
                return True
        return False


def _tight(grid):
    """The grid cropped to its known cells, unless it already is (no copy then)."""
    b = grid.known_bounds
    if b is None or (b[0] == 0 and b[1] == 0 and b[2] == grid.num_cells[0] - 1 and b[3] == grid.num_cells[1] - 1):
        return grid
    return grid.cropped()


def _free_window(grid) -> tuple[float, float, float] | None:
    """(centre x, centre y, half-width) of the box of ``grid``'s free cells (probability below 0.5) plus
    ``NODE_MARGIN``, in the grid frame; None without a free cell.

    Without it a whole-grid search tries every offset at which the scan still overlaps the grid, the laser up to
    the scan's reach outside it, where no answer may stand (``MapIndex.seen``): on bench-dense/aces's image
    (60 m) that is four times the positions, and global queries took 288 ms (p50 of 40) against 188 ms with the
    free box, the same 40 right (intel's image 96 -> 76 ms, freiburg-079's 54 -> 48 ms, all right both ways).
    """
    cells = grid.cells
    free = (cells != UNKNOWN_VALUE) & (VALUE_TO_PROBABILITY[cells] < 0.5)
    cols, rows = np.flatnonzero(free.any(axis=0)), np.flatnonzero(free.any(axis=1))
    if cols.size == 0:
        return None
    lo = grid.origin + np.array([cols[0], rows[0]], dtype=np.float64) * grid.resolution - NODE_MARGIN
    hi = grid.origin + np.array([cols[-1] + 1, rows[-1] + 1], dtype=np.float64) * grid.resolution + NODE_MARGIN
    return float(lo[0] + hi[0]) / 2, float(lo[1] + hi[1]) / 2, float(max(hi - lo)) / 2
