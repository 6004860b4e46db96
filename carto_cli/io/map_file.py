"""The map file (``map.carto``): everything ``carto relocalize`` and ``carto map --load-state`` need, in one file.

A pose graph's state (:class:`~carto_cli.mapping.pose_graph_state.PoseGraphState`), the options and,
optionally, the trajectory, as arrays in carto's container (``io/container.py``: checked preamble,
JSON header, compressed arrays; magic ``b"CARTOMAP"``, format version 1). This module is the schema:
which arrays, what they mean, and how a state is turned into them and back.

Contents. Submap grids are stored cropped to their ``known_box`` (cells outside it are
unknown, i.e. zero, by construction; if a grid ever had a non-zero cell outside its box
the whole grid is stored instead), with the full shape and crop offset so loading rebuilds
a grid bit-identical to the one saved — same shape, origin, known box and cells. Nodes'
loop-closure points, which vary in length, are one concatenated (P, 2) array plus N+1
offsets; so are submaps' node lists. Options are the full effective options as a JSON
object (``options_to_dict``); keys this carto does not know (from another version) are
dropped on load and listed in ``LoadedMap.ignored_options``, while missing keys take
their defaults. What a state holds beyond this (odometry samples, key-frame poses, which
submaps were searched, linked trajectories) is not stored: loading sets it as it was when
the map was finished (see :meth:`LoadedMap.to_state`).

Header keys: ``format``, ``format_version``, ``carto_version``, ``created`` (UTC, ISO 8601; only when
``SOURCE_DATE_EPOCH`` is set, so that the same input gives the same bytes),
``recordings``, optionally ``laser_pose_source``, ``scan_topic``, ``stats``; ``options``;
``arrays`` (name -> dtype, shape, codec, offset and length in the data, raw_length);
``data_length``. Arrays (N nodes, M submaps, K constraints, S scans, P points, C cells):

    node_time (N) node_trajectory (N) node_local_pose node_global_pose node_odometry (N,3)
    node_points (P,2) node_points_offset (N+1) node_scan (N, optional)
    submap_trajectory submap_index submap_finished submap_num_range_data submap_resolution
    submap_grid_version (M) submap_local_pose submap_global_pose (M,3) submap_origin
    submap_num_cells [nx, ny] (M,2) submap_known_box submap_crop [x0, y0, x1, y1) (M,4)
    submap_cells (C) uint16 + submap_cells_offset (M+1), row-major per crop
    submap_nodes + submap_nodes_offset (M+1)
    constraint_submap constraint_node (K) constraint_relative (K,3)
    constraint_translation_weight constraint_rotation_weight (K) constraint_kind (K) uint8
    trajectory_time (S) trajectory_pose (S,3) laser_pose (3)       -- optional
    transient_centre transient_span [first, last hit time] transient_evidence [hits, rays after] (T,2)
                                                                   -- optional: what cleaning drew free
                                                                      (header key transient_resolution)
"""
from __future__ import annotations

import dataclasses
import datetime as _dt
import math
import os
import struct
import typing
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from carto_cli import __version__
from carto_cli.core.errors import CartoError, FormatError
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.io import container
from carto_cli.io.loaded_map import LoadedMap, MapMetadata
from carto_cli.io.trajectory import Trajectory
from carto_cli.mapping.cleaning import Transients
from carto_cli.mapping.constraints import ConstraintKind, ConstraintSet
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.pose_graph_state import PoseGraphState
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options, apply_overrides, options_to_dict

__all__ = ["FORMAT_VERSION", "MAGIC", "MAP_FORMAT", "load_map", "save_map"]

MAGIC = b"CARTOMAP"
FORMAT_VERSION = 1
MAP_FORMAT = container.ContainerFormat(MAGIC, FORMAT_VERSION, "map")


# ---------------------------------------------------------------------------------------- saving


def save_map(path: str | Path, result_or_graph, options: Options, *, trajectory=None,
             recordings: Iterable[str | Path] = (), jobs: int | None = None) -> Path:
    """Write ``result_or_graph`` (a ``MapResult`` or a ``PoseGraph``) to ``path`` atomically.

    ``trajectory`` (a :class:`Trajectory` or ``(times, poses)``) defaults to the MapResult's
    per-scan poses; a bare PoseGraph has none unless given. ``recordings`` names what was mapped. ``jobs``:
    threads compressing the arrays (None: every core); the bytes do not depend on it.
    """
    path = Path(path)
    if isinstance(recordings, (str, Path)):
        recordings = [recordings]
    graph, result = _graph_of(result_or_graph)
    state = graph.to_state()
    meta: dict[str, Any] = {
        "carto_version": __version__,
        "recordings": [str(r) for r in recordings],
    }
    # No wall-clock time by default, so the same input gives the same bytes (the file's own time says when it
    # was written); SOURCE_DATE_EPOCH, the reproducible-builds convention, stamps one.
    epoch = os.environ.get("SOURCE_DATE_EPOCH", "").strip()
    if epoch.isdigit():
        meta["created"] = (_dt.datetime.fromtimestamp(int(epoch), _dt.timezone.utc).isoformat(timespec="seconds")
                           .replace("+00:00", "Z"))
    arrays: dict[str, np.ndarray] = {}
    arrays.update(_node_arrays(state))
    arrays.update(_submap_arrays(state))
    arrays.update(_constraint_arrays(state.constraints))

    if trajectory is None and result is not None:
        trajectory = (result.times, result.poses)
    if trajectory is not None:
        times, poses = _trajectory_arrays(trajectory)
        arrays["trajectory_time"] = times
        arrays["trajectory_pose"] = poses
    if result is not None:
        node_scans = np.asarray(result.node_scans, dtype=np.int64).reshape(-1)
        if node_scans.shape[0] == state.num_nodes:
            arrays["node_scan"] = node_scans
        if result.laser_pose is not None:
            arrays["laser_pose"] = np.asarray(result.laser_pose, dtype=np.float64).reshape(3)
        meta["laser_pose_source"] = result.laser_pose_source
        selection = getattr(result, "selection", None)
        if selection is not None and getattr(selection, "scan", None):
            meta["scan_topic"] = str(selection.scan)
        meta["stats"] = _json_safe_stats(result.stats)
        transients = getattr(result, "transients", None)
        if transients is not None and len(transients):
            arrays.update(_transient_arrays(transients))
            meta["transient_resolution"] = float(transients.resolution)

    return container.write(path, MAP_FORMAT, {**meta, "options": options_to_dict(options)}, arrays, jobs)


def _transient_arrays(transients: Transients) -> dict[str, np.ndarray]:
    return {"transient_centre": transients.centres().astype(np.float64),
            "transient_span": np.asarray(transients.spans, np.float64),
            "transient_evidence": np.column_stack([transients.hits, transients.after]).astype(np.int64)}


def _transients(header: dict, arrays: dict[str, np.ndarray], bad) -> Transients | None:
    """What cleaning removed, as saved (None: nothing, or a map from before cleaning)."""
    centre = arrays.get("transient_centre")
    if centre is None:
        return None
    span, evidence = arrays.get("transient_span"), arrays.get("transient_evidence")
    resolution = header.get("transient_resolution")
    t = len(centre)
    if (span is None or evidence is None or centre.shape != (t, 2) or span.shape != (t, 2)
            or evidence.shape != (t, 2) or not isinstance(resolution, (int, float)) or not resolution > 0):
        raise bad("inconsistent transient arrays")
    return Transients.of_centres(float(resolution), centre, span, evidence[:, 0], evidence[:, 1])


def _graph_of(obj) -> tuple[PoseGraph, Any]:
    if isinstance(obj, PoseGraph):
        return obj, None
    graph = getattr(obj, "graph", None)
    if not isinstance(graph, PoseGraph):
        raise TypeError(f"save_map needs a MapResult with a pose graph or a PoseGraph, got {type(obj).__name__}")
    return graph, obj


def _trajectory_arrays(trajectory) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(trajectory, Trajectory):
        times, poses = trajectory.t, trajectory.poses
    else:
        times, poses = trajectory
    times = np.ascontiguousarray(times, dtype=np.float64).reshape(-1)
    poses = np.ascontiguousarray(poses, dtype=np.float64).reshape(-1, 3)
    if poses.shape[0] != times.shape[0]:
        raise ValueError(f"trajectory has {times.shape[0]} times and {poses.shape[0]} poses")
    return times, poses


# How long the run took and how much memory it used are the machine's business, not the map's: left out so the
# same input gives the same bytes whatever the number of threads (summary.json next to the map keeps them)
_TIMING_STATS = ("wall_time_s", "scans_per_s", "optimization_time_s", "first_pass_wall_time_s", "peak_memory_mb",
                "graph_process_peak_memory_mb")


def _json_safe_stats(stats: dict) -> dict:
    out: dict[str, Any] = {}
    for k, v in (stats or {}).items():
        if k in _TIMING_STATS:
            continue
        if isinstance(v, (bool, np.bool_)):
            out[str(k)] = bool(v)
        elif isinstance(v, (int, np.integer)):
            out[str(k)] = int(v)
        elif isinstance(v, (float, np.floating)):
            out[str(k)] = float(v) if math.isfinite(v) else None
        elif isinstance(v, str):
            out[str(k)] = v
    return out


def _offsets(lengths) -> np.ndarray:
    out = np.zeros(len(lengths) + 1, dtype=np.int64)
    np.cumsum(np.asarray(lengths, dtype=np.int64), out=out[1:])
    return out


def _node_arrays(state: PoseGraphState) -> dict[str, np.ndarray]:
    n = state.num_nodes
    points = [np.asarray(p).reshape(-1, 2) for p in state.node_points]
    dtype = np.result_type(*[p.dtype for p in points]) if points else np.dtype(np.float64)
    if dtype not in (np.float32, np.float64):
        dtype = np.dtype(np.float64)
    return {
        "node_time": np.asarray(state.node_times, dtype=np.float64).reshape(n),
        "node_trajectory": np.asarray(state.node_trajectories, dtype=np.int64).reshape(n),
        "node_local_pose": state.node_local_poses,
        "node_global_pose": state.node_global_poses,
        # Interpolated per node: the raw odometry stream is not kept, and a restored graph must
        # see the same odometry constraints the mapped one had.
        "node_odometry": state.odometry_at_nodes(),
        "node_points_offset": _offsets([len(p) for p in points]),
        "node_points": np.concatenate(points).astype(dtype, copy=False) if points else np.zeros((0, 2), dtype),
    }


def _crop_box(grid: ProbabilityGrid) -> tuple[int, int, int, int]:
    """(x0, y0, x1, y1) exclusive end of the cells to store: the known box when nothing lies outside it."""
    ny, nx = grid.cells.shape
    b = grid.known_bounds
    if b is None:
        return (0, 0, 0, 0) if not grid.cells.any() else (0, 0, nx, ny)
    x0, y0, x1, y1 = b
    x0, y0 = max(x0, 0), max(y0, 0)
    x1, y1 = min(x1 + 1, nx), min(y1 + 1, ny)
    if x0 >= x1 or y0 >= y1:
        return (0, 0, nx, ny)
    inside = int(np.count_nonzero(grid.cells[y0:y1, x0:x1]))
    if inside != int(np.count_nonzero(grid.cells)):
        return (0, 0, nx, ny)  # a known cell outside the box: keep everything rather than lose it
    return (x0, y0, x1, y1)


def _submap_arrays(state: PoseGraphState) -> dict[str, np.ndarray]:
    entries = state.submaps
    m = len(entries)
    crops = [_crop_box(e.submap.grid) for e in entries]
    sizes = [(x1 - x0) * (y1 - y0) for x0, y0, x1, y1 in crops]
    cells_offset = _offsets(sizes)
    # One array filled a submap at a time: a packed grid's cells are unpacked for the copy only (through the
    # grids' shared LRU), where a list of crops would hold every submap unpacked at once (dense aces: 36
    # submaps, the save's peak 208 MB of arrays against the 53 MB it writes).
    all_cells = np.empty(int(cells_offset[-1]), np.uint16)
    for e, (x0, y0, x1, y1), start, stop in zip(entries, crops, cells_offset[:-1], cells_offset[1:]):
        all_cells[start:stop] = e.submap.grid.cells[y0:y1, x0:x1].reshape(-1)
    nodes = [np.asarray(e.nodes, dtype=np.int64).reshape(-1) for e in entries]
    return {
        "submap_trajectory": np.array([e.trajectory for e in entries], dtype=np.int64).reshape(m),
        "submap_index": np.array([e.submap.index for e in entries], dtype=np.int64).reshape(m),
        "submap_finished": np.array([bool(e.submap.finished) for e in entries], dtype=bool).reshape(m),
        "submap_num_range_data": np.array([e.submap.num_range_data for e in entries], dtype=np.int64).reshape(m),
        "submap_local_pose": np.array([e.submap.local_pose for e in entries], dtype=np.float64).reshape(m, 3),
        "submap_global_pose": np.array([e.global_pose for e in entries], dtype=np.float64).reshape(m, 3),
        "submap_resolution": np.array([e.submap.grid.resolution for e in entries], dtype=np.float64).reshape(m),
        "submap_origin": np.array([e.submap.grid.origin for e in entries], dtype=np.float64).reshape(m, 2),
        "submap_num_cells": np.array([e.submap.grid.num_cells for e in entries], dtype=np.int64).reshape(m, 2),
        "submap_known_box": np.array([e.submap.grid.known_box for e in entries], dtype=np.int64).reshape(m, 4),
        "submap_grid_version": np.array([e.submap.grid.version for e in entries], dtype=np.int64).reshape(m),
        "submap_crop": np.array(crops, dtype=np.int64).reshape(m, 4),
        "submap_cells_offset": cells_offset,
        "submap_cells": all_cells,
        "submap_nodes_offset": _offsets([len(v) for v in nodes]),
        "submap_nodes": np.concatenate(nodes) if nodes else np.zeros(0, np.int64),
    }


def _constraint_arrays(cs: ConstraintSet) -> dict[str, np.ndarray]:
    kind = np.where(cs.is_loop_closure, int(ConstraintKind.INTER_SUBMAP), int(ConstraintKind.INTRA_SUBMAP))
    return {
        "constraint_submap": cs.submap,
        "constraint_node": cs.node,
        "constraint_relative": cs.relative,
        "constraint_translation_weight": cs.translation_weight,
        "constraint_rotation_weight": cs.rotation_weight,
        "constraint_kind": kind.astype(np.uint8),
    }


# ---------------------------------------------------------------------------------------- loading


def load_map(path: str | Path) -> LoadedMap:
    """Read and check a map file (map.carto, or Cartographer's .pbstream). Raises :class:`FormatError` for anything
    but a good, supported map."""
    path = Path(path)
    from carto_cli.io import pbstream

    if pbstream.is_pbstream(path):  # Cartographer's own state: relocalize in it, render it, continue it
        return pbstream.load_pbstream(path)
    data = container.read_bytes(path, MAP_FORMAT)
    try:
        header, arrays = container.decode(data, path, MAP_FORMAT)
        return _build(header, arrays, path)
    except FormatError:
        raise
    except CartoError as e:  # e.g. options that no longer validate
        raise FormatError(f"malformed map file: {e.message}", path) from None
    except (ValueError, TypeError, KeyError, IndexError, AttributeError, OverflowError, MemoryError,
            struct.error, UnicodeDecodeError, RecursionError) as e:
        # Only reachable past the checksum, i.e. by a file written wrongly (or forged), not by damage.
        raise FormatError(f"malformed map file: {type(e).__name__}: {e}", path) from None


_REQUIRED = {
    # name: (ndim, trailing shape, kind)
    "node_time": ((), "f"), "node_trajectory": ((), "i"), "node_local_pose": ((3,), "f"),
    "node_global_pose": ((3,), "f"), "node_odometry": ((3,), "f"), "node_points_offset": ((), "i"),
    "node_points": ((2,), "f"),
    "submap_trajectory": ((), "i"), "submap_index": ((), "i"), "submap_finished": ((), "b"),
    "submap_num_range_data": ((), "i"), "submap_local_pose": ((3,), "f"), "submap_global_pose": ((3,), "f"),
    "submap_resolution": ((), "f"), "submap_origin": ((2,), "f"), "submap_num_cells": ((2,), "i"),
    "submap_known_box": ((4,), "i"), "submap_grid_version": ((), "i"), "submap_crop": ((4,), "i"),
    "submap_cells_offset": ((), "i"), "submap_cells": ((), "u"), "submap_nodes_offset": ((), "i"),
    "submap_nodes": ((), "i"),
    "constraint_submap": ((), "i"), "constraint_node": ((), "i"), "constraint_relative": ((3,), "f"),
    "constraint_translation_weight": ((), "f"), "constraint_rotation_weight": ((), "f"),
    "constraint_kind": ((), "u"),
}


def _build(header: dict, arrays: dict[str, np.ndarray], path: Path) -> LoadedMap:
    def bad(what: str) -> FormatError:
        return FormatError(f"malformed map file: {what}", path)

    for name, (tail, kind) in _REQUIRED.items():
        a = arrays.get(name)
        if a is None:
            raise bad(f"array {name!r} missing")
        if a.ndim != 1 + len(tail) or a.shape[1:] != tail or a.dtype.kind != kind:
            raise bad(f"array {name!r} has shape {a.shape} and dtype {a.dtype}")

    n = len(arrays["node_time"])
    m = len(arrays["submap_trajectory"])
    k = len(arrays["constraint_submap"])
    for prefix, count in (("node_", n), ("submap_", m), ("constraint_", k)):
        for name, a in arrays.items():
            if name.startswith(prefix) and name not in ("node_points", "node_points_offset", "node_scan",
                                                        "submap_cells", "submap_cells_offset",
                                                        "submap_nodes", "submap_nodes_offset") \
                    and len(a) != count:
                raise bad(f"array {name!r} has {len(a)} rows for {count}")

    node_points = _split(arrays["node_points"], arrays["node_points_offset"], n, "node_points", bad)
    submap_nodes = _split(arrays["submap_nodes"], arrays["submap_nodes_offset"], m, "submap_nodes", bad)
    cells_flat = _split(arrays["submap_cells"], arrays["submap_cells_offset"], m, "submap_cells", bad)

    if n and (arrays["node_trajectory"].min() < 0):
        raise bad("negative trajectory id")
    for nodes in submap_nodes:
        if nodes.size and (nodes.min() < 0 or nodes.max() >= n):
            raise bad("submap node id out of range")
    if k:
        if arrays["constraint_submap"].min() < 0 or arrays["constraint_submap"].max() >= m:
            raise bad("constraint submap id out of range")
        if arrays["constraint_node"].min() < 0 or arrays["constraint_node"].max() >= n:
            raise bad("constraint node id out of range")
        if arrays["constraint_kind"].max() > max(int(v) for v in ConstraintKind):
            raise bad("unknown constraint kind")

    submaps = [_submap(arrays, i, cells_flat[i], bad) for i in range(m)]
    keys = list(zip(arrays["submap_trajectory"].tolist(), arrays["submap_index"].tolist()))
    if len(set(keys)) != len(keys):
        raise bad("two submaps with the same trajectory and index")

    cs = ConstraintSet.from_arrays(
        arrays["constraint_submap"], arrays["constraint_node"], arrays["constraint_relative"],
        arrays["constraint_translation_weight"], arrays["constraint_rotation_weight"],
        arrays["constraint_kind"] == int(ConstraintKind.INTER_SUBMAP)) if k else ConstraintSet()

    trajectory = None
    if "trajectory_time" in arrays or "trajectory_pose" in arrays:
        t, p = arrays.get("trajectory_time"), arrays.get("trajectory_pose")
        if t is None or p is None or t.ndim != 1 or p.shape != (len(t), 3):
            raise bad("inconsistent trajectory arrays")
        trajectory = Trajectory.from_poses(t.astype(np.float64), p.astype(np.float64))
    node_scans = arrays.get("node_scan")
    if node_scans is not None:
        if node_scans.shape != (n,) or node_scans.dtype.kind != "i":
            raise bad("node_scan has the wrong shape")
        if n and trajectory is not None and (node_scans.min() < 0 or node_scans.max() >= len(trajectory)):
            raise bad("node_scan out of range")
    laser_pose = arrays.get("laser_pose")
    if laser_pose is not None and laser_pose.shape != (3,):
        raise bad("laser_pose has the wrong shape")

    options, ignored = _options(header.get("options"), bad)
    recordings = header.get("recordings", [])
    if not isinstance(recordings, list) or not all(isinstance(r, str) for r in recordings):
        raise bad("recordings are not a list of names")
    stats = header.get("stats", {})
    metadata = MapMetadata(
        format_version=FORMAT_VERSION,
        carto_version=str(header.get("carto_version", "")),
        created=str(header.get("created", "")),
        recordings=tuple(recordings),
        laser_pose_source=_opt_str(header.get("laser_pose_source")),
        scan_topic=_opt_str(header.get("scan_topic")),
        stats=stats if isinstance(stats, dict) else {},
    )
    return LoadedMap(
        path=path, options=options, metadata=metadata, submaps=submaps,
        submap_trajectories=arrays["submap_trajectory"], submap_global_poses=arrays["submap_global_pose"],
        submap_nodes=submap_nodes,
        node_times=arrays["node_time"], node_trajectories=arrays["node_trajectory"],
        node_local_poses=arrays["node_local_pose"], node_global_poses=arrays["node_global_pose"],
        node_odometry=arrays["node_odometry"], node_points=node_points, constraints=cs,
        trajectory=trajectory, node_scans=node_scans, laser_pose=laser_pose, ignored_options=ignored,
        transients=_transients(header, arrays, bad),
    )


def _opt_str(v) -> str | None:
    return v if isinstance(v, str) else None


def _split(flat: np.ndarray, offsets: np.ndarray, count: int, name: str, bad) -> list[np.ndarray]:
    if offsets.shape != (count + 1,) or offsets[0] != 0 or offsets[-1] != len(flat) or np.any(np.diff(offsets) < 0):
        raise bad(f"{name} offsets are inconsistent")
    return [flat[offsets[i]:offsets[i + 1]] for i in range(count)]


def _submap(arrays: dict[str, np.ndarray], i: int, cells_flat: np.ndarray, bad) -> Submap:
    nx, ny = (int(v) for v in arrays["submap_num_cells"][i])
    x0, y0, x1, y1 = (int(v) for v in arrays["submap_crop"][i])
    resolution = float(arrays["submap_resolution"][i])
    if nx <= 0 or ny <= 0 or nx * ny > (1 << 31):
        raise bad(f"submap {i}: grid of {nx} x {ny} cells")
    if not (math.isfinite(resolution) and resolution > 0):
        raise bad(f"submap {i}: resolution {resolution}")
    if not (0 <= x0 <= x1 <= nx and 0 <= y0 <= y1 <= ny):
        raise bad(f"submap {i}: crop box outside the grid")
    if len(cells_flat) != (x1 - x0) * (y1 - y0):
        raise bad(f"submap {i}: {len(cells_flat)} cells for a {x1 - x0} x {y1 - y0} crop")
    # Built through the constructors, so attributes they gain later exist on loaded objects too.
    grid = ProbabilityGrid(resolution, arrays["submap_origin"][i], (nx, ny))
    grid.cells[y0:y1, x0:x1] = cells_flat.reshape(y1 - y0, x1 - x0)
    grid.known_box = arrays["submap_known_box"][i].astype(np.int64).copy()
    grid.version = int(arrays["submap_grid_version"][i])

    local_pose = arrays["submap_local_pose"][i].astype(np.float64).copy()
    submap = Submap(local_pose[:2], resolution=resolution, index=int(arrays["submap_index"][i]), initial_size=1)
    submap.local_pose = local_pose
    submap.grid = grid
    submap.num_range_data = int(arrays["submap_num_range_data"][i])
    submap.finished = bool(arrays["submap_finished"][i])
    return submap


def _options(data, bad) -> tuple[Options, tuple[str, ...]]:
    if not isinstance(data, dict):
        raise bad("no options")
    ignored: list[str] = []
    known = _known_only(data, Options, "", ignored, bad)
    try:
        return apply_overrides(Options(), known), tuple(ignored)
    except CartoError as e:
        raise bad(f"options: {e.message}") from None


def _known_only(data: dict, cls, prefix: str, ignored: list[str], bad) -> dict:
    """``data`` without the keys ``cls`` does not have (recorded in ``ignored``)."""
    fields = {f.name: f for f in dataclasses.fields(cls)}
    hints = typing.get_type_hints(cls)
    out = {}
    for key, value in data.items():
        if key not in fields:
            ignored.append(prefix + str(key))
            continue
        tp = hints[key]
        if dataclasses.is_dataclass(tp):
            if not isinstance(value, dict):
                raise bad(f"options: {prefix}{key} is not a section")
            out[key] = _known_only(value, tp, f"{prefix}{key}.", ignored, bad)
        else:
            out[key] = value
    return out
