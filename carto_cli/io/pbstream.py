"""Cartographer's ``.pbstream``: its saved state, read into a :class:`~carto_cli.io.loaded_map.LoadedMap` and written
from one, so a Cartographer map can be relocalized in, re-exported or continued by carto, and a carto map handed
back to Cartographer (``cartographer_pbstream_to_ros_map``, ``--load_state_filename``).

The file is Cartographer's proto stream: the 8-byte magic ``0x7b1d1f7b5bf501db`` then, for each message, its
gzip-compressed size (uint64, little endian) and the gzip-compressed serialized ``SerializedData``. The messages
come in the order Cartographer writes them: a ``SerializationHeader`` (format version 2), the pose graph
(constraints, and per trajectory the optimized node and submap poses), the trajectory builder options (one entry
per trajectory), each submap, each node, each trajectory's data. Only 2D maps with probability grids are read.

The messages are declared here, field by field, from Cartographer's published ``.proto`` files (the numbers and
types are the format; tests/io/test_pbstream.py checks them against a transcription of those files) and encoded
by the protobuf library; only the fields carto reads or writes are declared, the others are skipped on reading.

Units and frames: carto's poses (x, y, yaw) are Cartographer's Rigid3d with z = 0 and a rotation about z (a node's
pose read is that of its gravity-aligned frame, which its points and constraints refer to); times
are Cartographer's "universal" ticks (100 ns since 0001-01-01). A carto grid (``cells[iy, ix]``, row 0 at the
lowest y) is Cartographer's Grid2D turned: Cartographer's cell (cx, cy) lies at ``max - (cy + 0.5, cx + 0.5)
* resolution``, i.e. its x index runs down the world's y axis and its y index down the world's x axis. Both store
the same uint16 correspondence-cost values. Node points are Cartographer's compressed point cloud (1 mm).
"""
from __future__ import annotations

import gzip
import math
import struct
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from carto_cli.core.errors import CartoError, FormatError

__all__ = ["MAGIC", "SCHEMA", "grid_from_message", "grid_to_message", "is_pbstream", "load_pbstream", "messages",
           "pose_of", "save_pbstream"]

MAGIC = 0x7B1D1F7B5BF501DB
MAGIC_BYTES = struct.pack("<Q", MAGIC)
FORMAT_VERSION = 2  # what Cartographer 1.0 and later write (submaps without histograms)
READABLE_VERSIONS = (1, 2)  # 1: submaps still carrying histograms, which 2D maps leave empty
UTS_EPOCH_OFFSET_S = 62135596800  # 0001-01-01 to 1970-01-01, Cartographer's common::Time
TICKS_PER_S = 10_000_000
POINT_PRECISION = 0.001  # compressed point clouds: metres per step
BLOCK_BITS = 10
INTRA_SUBMAP, INTER_SUBMAP = 0, 1
SENSOR_RANGE = 0
MAX_MESSAGE = 1 << 31

# message -> [(field name, number, type, label, message type)]; types: d double, f float, i int32, l int64,
# u uint32, b bool, s string, m message. label: "" optional, "r" repeated. Names and numbers are Cartographer's.
SCHEMA: dict[str, list[tuple[str, int, str, str, str]]] = {
    "Vector2d": [("x", 1, "d", "", ""), ("y", 2, "d", "", "")],
    "Vector3d": [("x", 1, "d", "", ""), ("y", 2, "d", "", ""), ("z", 3, "d", "", "")],
    "Quaterniond": [("x", 1, "d", "", ""), ("y", 2, "d", "", ""), ("z", 3, "d", "", ""), ("w", 4, "d", "", "")],
    "Rigid3d": [("translation", 1, "m", "", "Vector3d"), ("rotation", 2, "m", "", "Quaterniond")],
    "SubmapId": [("trajectory_id", 1, "i", "", ""), ("submap_index", 2, "i", "", "")],
    "NodeId": [("trajectory_id", 1, "i", "", ""), ("node_index", 2, "i", "", "")],
    "Constraint": [("submap_id", 1, "m", "", "SubmapId"), ("node_id", 2, "m", "", "NodeId"),
                   ("relative_pose", 3, "m", "", "Rigid3d"), ("tag", 5, "i", "", ""),
                   ("translation_weight", 6, "d", "", ""), ("rotation_weight", 7, "d", "", "")],
    "TrajectoryNode": [("timestamp", 1, "l", "", ""), ("pose", 5, "m", "", "Rigid3d"),
                       ("node_index", 7, "i", "", "")],
    "TrajectorySubmap": [("pose", 1, "m", "", "Rigid3d"), ("submap_index", 2, "i", "", "")],
    "Trajectory": [("node", 1, "m", "r", "TrajectoryNode"), ("submap", 2, "m", "r", "TrajectorySubmap"),
                   ("trajectory_id", 3, "i", "", "")],
    "PoseGraph": [("constraint", 2, "m", "r", "Constraint"), ("trajectory", 4, "m", "r", "Trajectory")],
    "CellLimits": [("num_x_cells", 1, "i", "", ""), ("num_y_cells", 2, "i", "", "")],
    "MapLimits": [("resolution", 1, "d", "", ""), ("max", 2, "m", "", "Vector2d"),
                  ("cell_limits", 3, "m", "", "CellLimits")],
    "CellBox": [("max_x", 1, "i", "", ""), ("max_y", 2, "i", "", ""), ("min_x", 3, "i", "", ""),
                ("min_y", 4, "i", "", "")],
    "ProbabilityGrid": [],
    "Grid2D": [("limits", 1, "m", "", "MapLimits"), ("cells", 2, "i", "r", ""),
               ("known_cells_box", 3, "m", "", "CellBox"), ("probability_grid_2d", 4, "m", "", "ProbabilityGrid"),
               ("tsdf_2d", 5, "m", "", "ProbabilityGrid"),  # only its presence matters: carto reads no TSDF
               ("min_correspondence_cost", 6, "f", "", ""), ("max_correspondence_cost", 7, "f", "", "")],
    "Submap2D": [("local_pose", 1, "m", "", "Rigid3d"), ("num_range_data", 2, "i", "", ""),
                 ("finished", 3, "b", "", ""), ("grid", 4, "m", "", "Grid2D")],
    "Submap": [("submap_id", 1, "m", "", "SubmapId"), ("submap_2d", 2, "m", "", "Submap2D"),
               ("submap_3d", 3, "m", "", "ProbabilityGrid")],  # presence only: a 3D map
    "CompressedPointCloud": [("num_points", 1, "i", "", ""), ("point_data", 3, "i", "r", "")],
    "TrajectoryNodeData": [("timestamp", 1, "l", "", ""), ("gravity_alignment", 2, "m", "", "Quaterniond"),
                           ("filtered_gravity_aligned_point_cloud", 3, "m", "", "CompressedPointCloud"),
                           ("local_pose", 7, "m", "", "Rigid3d")],
    "Node": [("node_id", 1, "m", "", "NodeId"), ("node_data", 5, "m", "", "TrajectoryNodeData")],
    "TrajectoryData": [("trajectory_id", 1, "i", "", ""), ("gravity_constant", 2, "d", "", ""),
                       ("imu_calibration", 3, "m", "", "Quaterniond")],
    "SensorId": [("type", 1, "i", "", ""), ("id", 2, "s", "", "")],
    "TrajectoryBuilderOptions": [],
    "TrajectoryBuilderOptionsWithSensorIds": [("sensor_id", 1, "m", "r", "SensorId"),
                                              ("trajectory_builder_options", 2, "m", "",
                                               "TrajectoryBuilderOptions")],
    "AllTrajectoryBuilderOptions": [("options_with_sensor_ids", 1, "m", "r",
                                     "TrajectoryBuilderOptionsWithSensorIds")],
    "SerializationHeader": [("format_version", 1, "u", "", "")],
    "SerializedData": [("pose_graph", 1, "m", "", "PoseGraph"),
                       ("all_trajectory_builder_options", 2, "m", "", "AllTrajectoryBuilderOptions"),
                       ("submap", 3, "m", "", "Submap"), ("node", 4, "m", "", "Node"),
                       ("trajectory_data", 5, "m", "", "TrajectoryData")],
}

_classes: dict[str, Any] | None = None


def messages() -> dict[str, Any]:
    """Message classes for :data:`SCHEMA`, built once through the protobuf library's descriptors."""
    global _classes
    if _classes is None:
        from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

        fdp = descriptor_pb2.FileDescriptorProto(name="carto_pbstream.proto", package="carto.pbstream",
                                                 syntax="proto3")
        kinds = {"d": "TYPE_DOUBLE", "f": "TYPE_FLOAT", "i": "TYPE_INT32", "l": "TYPE_INT64", "u": "TYPE_UINT32",
                 "b": "TYPE_BOOL", "s": "TYPE_STRING", "m": "TYPE_MESSAGE"}
        F = descriptor_pb2.FieldDescriptorProto
        for name, fields in SCHEMA.items():
            msg = fdp.message_type.add(name=name)
            for fname, number, kind, label, type_name in fields:
                f = msg.field.add(name=fname, number=number, type=getattr(F, kinds[kind]),
                                  label=F.LABEL_REPEATED if label == "r" else F.LABEL_OPTIONAL)
                if kind == "m":
                    f.type_name = f".carto.pbstream.{type_name}"
        pool = descriptor_pool.DescriptorPool()
        pool.Add(fdp)
        _classes = {name: message_factory.GetMessageClass(pool.FindMessageTypeByName(f"carto.pbstream.{name}"))
                    for name in SCHEMA}
    return _classes


def is_pbstream(path: str | Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(8) == MAGIC_BYTES
    except OSError:
        return False


# --------------------------------------------------------------------------- conversions

def _rigid(msg, pose) -> None:
    x, y, yaw = (float(v) for v in pose)
    msg.translation.x, msg.translation.y, msg.translation.z = x, y, 0.0
    msg.rotation.x, msg.rotation.y = 0.0, 0.0
    msg.rotation.z, msg.rotation.w = math.sin(yaw / 2.0), math.cos(yaw / 2.0)


def _quaternion(q) -> tuple[float, float, float, float]:
    """(w, x, y, z); an unset rotation is the identity."""
    w, x, y, z = q.w, q.x, q.y, q.z
    return (1.0, 0.0, 0.0, 0.0) if w == x == y == z == 0.0 else (w, x, y, z)


def pose_of(msg, gravity=None) -> np.ndarray:
    """A Rigid3d as (x, y, yaw), Cartographer's Project2D. With a node's ``gravity`` alignment, the pose of its
    gravity-aligned frame (``pose * gravity^-1``), which its points and constraints are in (2D pose graph)."""
    w, x, y, z = _quaternion(msg.rotation)
    if gravity is not None:
        gw, gx, gy, gz = _quaternion(gravity)
        gx, gy, gz = -gx, -gy, -gz  # the inverse of a unit quaternion
        w, x, y, z = (w * gw - x * gx - y * gy - z * gz, w * gx + x * gw + y * gz - z * gy,
                      w * gy - x * gz + y * gw + z * gx, w * gz + x * gy - y * gx + z * gw)
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return np.array([msg.translation.x, msg.translation.y, yaw])


def to_ticks(t: float) -> int:
    """Unix seconds as Cartographer's universal time (100 ns ticks since 0001-01-01), exact to the tick."""
    whole = math.floor(t)
    return (whole + UTS_EPOCH_OFFSET_S) * TICKS_PER_S + int(round((t - whole) * TICKS_PER_S))


def from_ticks(ticks: int) -> float:
    s, rest = divmod(int(ticks) - UTS_EPOCH_OFFSET_S * TICKS_PER_S, TICKS_PER_S)
    return float(s) + rest / TICKS_PER_S


def compress_points(points: np.ndarray) -> tuple[int, np.ndarray]:
    """Cartographer's compressed point cloud of (n, 2) points (z = 0): per 1.024 m block its point count and
    block coordinates, then each point's three 10-bit offsets in millimetres."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(p)
    if n == 0:
        return 0, np.zeros(0, np.int64)
    raster = np.zeros((n, 3), np.int64)
    # RoundToInt rounds half away from zero.
    raster[:, :2] = (np.sign(p) * np.floor(np.abs(p) / POINT_PRECISION + 0.5)).astype(np.int64)
    block = raster >> BLOCK_BITS
    low = raster & ((1 << BLOCK_BITS) - 1)
    keys, inverse, counts = np.unique(block, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    packed = (((low[:, 2] << BLOCK_BITS) + low[:, 1]) << BLOCK_BITS) + low[:, 0]
    starts = np.concatenate([[0], np.cumsum(counts)])
    out = np.empty(4 * len(keys) + n, np.int64)
    pos = 0
    for b, (key, count) in enumerate(zip(keys, counts)):
        out[pos:pos + 4] = (count, key[0], key[1], key[2])
        out[pos + 4:pos + 4 + count] = packed[order[starts[b]:starts[b + 1]]]
        pos += 4 + count
    return n, out


def decompress_points(num_points: int, data) -> np.ndarray:
    """(n, 2) points (x, y) of a compressed point cloud; z is dropped (carto's points are planar)."""
    data = np.asarray(data, dtype=np.int64)
    out = np.empty((num_points, 2))
    pos = got = 0
    mask = (1 << BLOCK_BITS) - 1
    while got < num_points:
        if pos + 4 > len(data):
            raise ValueError("compressed point cloud ends early")
        count, bx, by = int(data[pos]), int(data[pos + 1]), int(data[pos + 2])
        pos += 4
        if count <= 0 or got + count > num_points or pos + count > len(data):
            raise ValueError("compressed point cloud has a bad block")
        v = data[pos:pos + count]
        out[got:got + count, 0] = ((bx << BLOCK_BITS) + (v & mask)) * POINT_PRECISION
        out[got:got + count, 1] = ((by << BLOCK_BITS) + ((v >> BLOCK_BITS) & mask)) * POINT_PRECISION
        pos += count
        got += count
    return out


def grid_to_message(msg, grid) -> None:
    """A carto ProbabilityGrid into Cartographer's Grid2D (see the module doc for the axes)."""
    nx, ny = grid.num_cells
    mx, my = grid.max_corner
    msg.limits.resolution = float(grid.resolution)
    msg.limits.max.x, msg.limits.max.y = float(mx), float(my)
    msg.limits.cell_limits.num_x_cells, msg.limits.cell_limits.num_y_cells = int(ny), int(nx)
    msg.cells.extend(np.ascontiguousarray(grid.cells[::-1, ::-1].T).reshape(-1).astype(np.int64).tolist())
    b = grid.known_bounds
    if b is not None:
        x0, y0, x1, y1 = (int(v) for v in b)
        msg.known_cells_box.min_x, msg.known_cells_box.max_x = ny - 1 - y1, ny - 1 - y0
        msg.known_cells_box.min_y, msg.known_cells_box.max_y = nx - 1 - x1, nx - 1 - x0
    msg.probability_grid_2d.SetInParent()
    from carto_cli.grid.probability_grid import MAX_CORRESPONDENCE_COST, MIN_CORRESPONDENCE_COST

    msg.min_correspondence_cost = MIN_CORRESPONDENCE_COST
    msg.max_correspondence_cost = MAX_CORRESPONDENCE_COST


def grid_from_message(msg, where: str):
    from carto_cli.grid.probability_grid import MAX_VALUE, ProbabilityGrid

    if msg.HasField("tsdf_2d"):
        raise ValueError(f"{where} is a TSDF grid (carto reads probability grids)")
    res = msg.limits.resolution
    ny, nx = msg.limits.cell_limits.num_x_cells, msg.limits.cell_limits.num_y_cells
    if not (res > 0 and math.isfinite(res)) or nx <= 0 or ny <= 0 or nx * ny > MAX_MESSAGE:
        raise ValueError(f"{where}: a grid of {nx} x {ny} cells at {res} m")
    cells = np.asarray(msg.cells, dtype=np.int64)
    if cells.shape[0] != nx * ny:
        raise ValueError(f"{where}: {cells.shape[0]} cells for a {nx} x {ny} grid")
    if cells.size and (cells.min() < 0 or cells.max() > MAX_VALUE):
        raise ValueError(f"{where}: cell values outside 0..{MAX_VALUE}")
    origin = np.array([msg.limits.max.x, msg.limits.max.y]) - res * np.array([nx, ny], dtype=np.float64)
    grid = ProbabilityGrid(res, origin, (nx, ny))
    grid.cells[:, :] = cells.reshape(nx, ny)[::-1, ::-1].T.astype(np.uint16)
    if msg.HasField("known_cells_box"):
        k = msg.known_cells_box
        grid.known_box = np.array([nx - 1 - k.max_y, ny - 1 - k.max_x, nx - 1 - k.min_y, ny - 1 - k.min_x],
                                  dtype=np.int64)
    else:
        known = np.argwhere(grid.cells > 0)
        if len(known):
            grid.known_box = np.array([known[:, 1].min(), known[:, 0].min(), known[:, 1].max(), known[:, 0].max()],
                                      dtype=np.int64)
    return grid


# --------------------------------------------------------------------------- the stream

def _read_messages(path: Path) -> Iterator[bytes]:
    with open(path, "rb") as f:
        if f.read(8) != MAGIC_BYTES:
            raise FormatError("not a Cartographer .pbstream (wrong magic number)", path)
        while True:
            head = f.read(8)
            if not head:
                return
            if len(head) < 8:
                raise FormatError("truncated .pbstream (a message size is cut)", path)
            (size,) = struct.unpack("<Q", head)
            if size > MAX_MESSAGE:
                raise FormatError(f"corrupt .pbstream: a message of {size} bytes", path)
            blob = f.read(size)
            if len(blob) < size:
                raise FormatError("truncated .pbstream (a message is cut)", path)
            try:
                yield gzip.decompress(blob)
            except (OSError, EOFError, ValueError) as e:
                raise FormatError(f"corrupt .pbstream: a message does not decompress ({e})", path) from None


def load_pbstream(path: str | Path, options=None):
    """A Cartographer state as a :class:`LoadedMap` (``options``: the carto options it gets; default carto's
    defaults, since a .pbstream holds Cartographer's, not carto's). Raises FormatError naming the file."""
    path = Path(path)
    try:
        return _load(path, options)
    except CartoError:
        raise
    except Exception as e:  # the protobuf library's DecodeError, a bad value in a field, ...
        raise FormatError(f"corrupt .pbstream: {type(e).__name__}: {e}", path) from None


def _load(path: Path, options):
    from carto_cli.io.loaded_map import LoadedMap, MapMetadata
    from carto_cli.io.trajectory import Trajectory
    from carto_cli.mapping.constraints import ConstraintSet
    from carto_cli.mapping.submaps import Submap
    from carto_cli.options import load_options

    M = messages()
    stream = _read_messages(path)
    first = next(stream, None)
    if first is None:
        raise FormatError("empty .pbstream", path)
    header = M["SerializationHeader"].FromString(first)
    if header.format_version not in READABLE_VERSIONS:
        raise FormatError(f".pbstream format version {header.format_version} (carto reads "
                          f"{', '.join(map(str, READABLE_VERSIONS))}; older files: migrate them with Cartographer's "
                          "cartographer_migrate_serialization_format)", path)
    pose_graph = None
    submaps: dict[tuple[int, int], Any] = {}
    nodes: dict[tuple[int, int], Any] = {}
    for blob in stream:
        data = M["SerializedData"].FromString(blob)
        if data.HasField("pose_graph"):
            pose_graph = data.pose_graph
        elif data.HasField("submap"):
            s = data.submap
            if s.HasField("submap_3d") or not s.HasField("submap_2d"):
                raise FormatError("a 3D map (carto reads 2D Cartographer maps)", path)
            submaps[(s.submap_id.trajectory_id, s.submap_id.submap_index)] = s.submap_2d
        elif data.HasField("node"):
            nodes[(data.node.node_id.trajectory_id, data.node.node_id.node_index)] = data.node.node_data
    if pose_graph is None:
        raise FormatError("no pose graph in the .pbstream", path)

    node_ids = sorted(nodes)
    submap_ids = sorted(submaps)
    node_of = {k: i for i, k in enumerate(node_ids)}
    submap_of = {k: i for i, k in enumerate(submap_ids)}
    global_node = np.full((len(node_ids), 3), np.nan)
    global_submap = np.full((len(submap_ids), 3), np.nan)
    for t in pose_graph.trajectory:
        for n in t.node:
            i = node_of.get((t.trajectory_id, n.node_index))
            if i is not None:
                global_node[i] = pose_of(n.pose, nodes[node_ids[i]].gravity_alignment)
        for s in t.submap:
            i = submap_of.get((t.trajectory_id, s.submap_index))
            if i is not None:
                global_submap[i] = pose_of(s.pose)
    missing = [str(node_ids[i]) for i in np.flatnonzero(np.isnan(global_node[:, 0]))[:3]]
    missing += [f"submap {submap_ids[i]}" for i in np.flatnonzero(np.isnan(global_submap[:, 0]))[:3]]
    if missing:
        raise FormatError(f"the pose graph has no optimized pose for {', '.join(missing)}", path)

    node_times = np.array([from_ticks(nodes[k].timestamp) for k in node_ids])
    node_local = np.array([pose_of(nodes[k].local_pose, nodes[k].gravity_alignment) for k in node_ids]).reshape(-1, 3)
    points = [decompress_points(nodes[k].filtered_gravity_aligned_point_cloud.num_points,
                                nodes[k].filtered_gravity_aligned_point_cloud.point_data) for k in node_ids]

    submap_objects = []
    for k in submap_ids:
        s = submaps[k]
        grid = grid_from_message(s.grid, f"submap {k}")
        local = pose_of(s.local_pose)
        sm = Submap(local[:2], resolution=grid.resolution, index=int(k[1]), initial_size=1)
        sm.local_pose = local
        sm.grid = grid
        sm.num_range_data = int(s.num_range_data)
        sm.finished = bool(s.finished)
        submap_objects.append(sm)

    rows = []
    for c in pose_graph.constraint:
        si = submap_of.get((c.submap_id.trajectory_id, c.submap_id.submap_index))
        ni = node_of.get((c.node_id.trajectory_id, c.node_id.node_index))
        if si is None or ni is None:
            continue  # a constraint to a submap or node not saved (Cartographer drops unfinished submaps)
        rows.append((si, ni, pose_of(c.relative_pose), c.translation_weight, c.rotation_weight, c.tag == INTER_SUBMAP))
    constraints = ConstraintSet.from_arrays(
        [r[0] for r in rows], [r[1] for r in rows], np.array([r[2] for r in rows]).reshape(-1, 3),
        [r[3] for r in rows], [r[4] for r in rows], np.array([r[5] for r in rows], dtype=bool)) if rows \
        else ConstraintSet()
    submap_nodes = [np.array(sorted({r[1] for r in rows if r[0] == i and not r[5]}), dtype=np.int64)
                    for i in range(len(submap_ids))]
    order = np.argsort(node_times, kind="stable")
    meta = MapMetadata(format_version=int(header.format_version), carto_version="cartographer", created="",
                       recordings=(), stats={"source": "cartographer pbstream"})
    return LoadedMap(
        path=path, options=options if options is not None else load_options(None), metadata=meta,
        submaps=submap_objects, submap_trajectories=np.array([k[0] for k in submap_ids], dtype=np.int64),
        submap_global_poses=global_submap, submap_nodes=submap_nodes, node_times=node_times,
        node_trajectories=np.array([k[0] for k in node_ids], dtype=np.int64), node_local_poses=node_local,
        node_global_poses=global_node, node_odometry=np.full((len(node_ids), 3), np.nan), node_points=points,
        constraints=constraints,
        trajectory=Trajectory.from_poses(node_times[order], global_node[order]) if len(node_ids) else None,
        node_scans=None, laser_pose=None)


def save_pbstream(path: str | Path, loaded) -> Path:
    """Write ``loaded`` (a LoadedMap: carto's map.carto, or a .pbstream read back) as Cartographer's state,
    atomically. Returns the path."""
    from carto_cli.io.atomic import write_bytes_atomic

    path = Path(path)
    M = messages()
    out = bytearray(MAGIC_BYTES)

    def put(message) -> None:
        blob = gzip.compress(message.SerializeToString(), mtime=0)
        out.extend(struct.pack("<Q", len(blob)))
        out.extend(blob)

    put(M["SerializationHeader"](format_version=FORMAT_VERSION))
    node_traj = np.asarray(loaded.node_trajectories, dtype=np.int64)
    submap_traj = np.asarray(loaded.submap_trajectories, dtype=np.int64)
    # Cartographer's ids count within a trajectory; carto's lists run over all of them.
    node_ids = _ids_within(node_traj)
    submap_ids = _ids_within(submap_traj)
    trajectories = sorted(set(node_traj.tolist()) | set(submap_traj.tolist()))

    data = M["SerializedData"]()
    pg = data.pose_graph
    cs = loaded.constraints
    for k in range(len(cs)):
        c = pg.constraint.add()
        s, n = int(cs.submap[k]), int(cs.node[k])
        c.submap_id.trajectory_id, c.submap_id.submap_index = int(submap_traj[s]), int(submap_ids[s])
        c.node_id.trajectory_id, c.node_id.node_index = int(node_traj[n]), int(node_ids[n])
        _rigid(c.relative_pose, cs.relative[k])
        c.translation_weight, c.rotation_weight = float(cs.translation_weight[k]), float(cs.rotation_weight[k])
        c.tag = INTER_SUBMAP if bool(cs.is_loop_closure[k]) else INTRA_SUBMAP
    for t in trajectories:
        tr = pg.trajectory.add(trajectory_id=t)
        for j in np.flatnonzero(node_traj == t).tolist():
            node = tr.node.add(node_index=int(node_ids[j]), timestamp=to_ticks(float(loaded.node_times[j])))
            _rigid(node.pose, loaded.node_global_poses[j])
        for j in np.flatnonzero(submap_traj == t).tolist():
            sm = tr.submap.add(submap_index=int(submap_ids[j]))
            _rigid(sm.pose, loaded.submap_global_poses[j])
    put(data)

    data = M["SerializedData"]()
    for _ in trajectories:
        entry = data.all_trajectory_builder_options.options_with_sensor_ids.add()
        entry.sensor_id.add(type=SENSOR_RANGE, id="scan")
        entry.trajectory_builder_options.SetInParent()
    put(data)

    for i, submap in enumerate(loaded.submaps):
        data = M["SerializedData"]()
        s = data.submap
        s.submap_id.trajectory_id, s.submap_id.submap_index = int(submap_traj[i]), int(submap_ids[i])
        _rigid(s.submap_2d.local_pose, submap.local_pose)
        s.submap_2d.num_range_data = int(submap.num_range_data)
        s.submap_2d.finished = bool(submap.finished)
        grid_to_message(s.submap_2d.grid, submap.grid)
        put(data)
    for i in range(len(node_traj)):
        data = M["SerializedData"]()
        node = data.node
        node.node_id.trajectory_id, node.node_id.node_index = int(node_traj[i]), int(node_ids[i])
        nd = node.node_data
        nd.timestamp = to_ticks(float(loaded.node_times[i]))
        nd.gravity_alignment.w = 1.0
        count, packed = compress_points(loaded.node_points[i])
        nd.filtered_gravity_aligned_point_cloud.num_points = count
        nd.filtered_gravity_aligned_point_cloud.point_data.extend(packed.tolist())
        _rigid(nd.local_pose, loaded.node_local_poses[i])
        put(data)
    for t in trajectories:
        data = M["SerializedData"]()
        td = data.trajectory_data
        td.trajectory_id, td.gravity_constant = t, 9.8
        td.imu_calibration.w = 1.0
        put(data)
    write_bytes_atomic(path, bytes(out))
    return path


def _ids_within(trajectories: np.ndarray) -> np.ndarray:
    """Each entry's index among the entries of its trajectory, in list order."""
    seen: dict[int, int] = {}
    out: list[int] = []
    for t in trajectories.tolist():
        out.append(seen.get(t, 0))
        seen[t] = out[-1] + 1
    return np.array(out, dtype=np.int64)
