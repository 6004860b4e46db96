"""The one pipeline every subcommand runs: recording → local SLAM → (pose graph) → MapResult."""
from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from carto_cli import transform
from carto_cli.errors import CartoError
from carto_cli.io.map_writer import OccupancyImage
from carto_cli.io.recording import Recording
from carto_cli.io.tf_tree import laser_pose_from_tf
from carto_cli.io.topics import TopicSelection, select_topics
from carto_cli.mapping.local_slam import LocalSlam
from carto_cli.mapping.map_assembly import assemble
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options
from carto_cli.records import Imu, Odometry, Scan
from carto_cli.timing import NullTimer


@dataclass
class MapResult:
    times: np.ndarray  # (S,) every scan that got a pose
    poses: np.ndarray  # (S, 3) tracking frame in the map frame
    local_poses: np.ndarray  # (S, 3) the same scans in the local SLAM frame
    node_scans: np.ndarray  # (N,) index into times/poses of every node
    submaps: list[Submap]
    submap_poses: np.ndarray  # (M, 3) global poses of the submaps' frames (local frame ↦ map frame)
    image: OccupancyImage
    laser_pose: np.ndarray
    laser_pose_source: str
    selection: TopicSelection
    stats: dict = field(default_factory=dict)
    loop_closures: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (K, 4) x1 y1 x2 y2 for drawing
    graph: PoseGraph | None = None


def resolve_laser_pose(recording: Recording, scan_frame: str | None, explicit) -> tuple[np.ndarray, str]:
    """--laser-pose wins; else static TF; else the laser is at the tracking frame."""
    if explicit is not None:
        return transform.as_pose(explicit), "--laser-pose"
    if scan_frame:
        found = laser_pose_from_tf(recording.static_transforms(), scan_frame)
        if found is not None:
            pose, root = found
            return np.asarray(pose, dtype=np.float64), f"static TF {root} -> {scan_frame}"
    return np.zeros(3), "identity (no static TF for the laser)"


def _first_scan_frame(recording: Recording, topic: str) -> str | None:
    for record in recording.records([topic]):
        if isinstance(record, Scan):
            return record.frame
    return None


def build(
    recording: Recording,
    options: Options,
    *,
    selection: TopicSelection | None = None,
    laser_pose=None,
    timer=None,
    on_scan: Callable[[int], None] | None = None,
    use_odometry: bool = True,
    use_imu: bool = True,
    max_scans: int | None = None,
    loop_closure: bool = True,
    graph: PoseGraph | None = None,
    trajectory_id: int = 0,
) -> MapResult:
    """Map one recording. With ``graph`` (e.g. from a loaded map.carto) the recording becomes trajectory
    ``trajectory_id`` of that graph, linked to the earlier ones by loop closures, as Cartographer's
    offline node does with --load_state_filename."""
    timer = timer or NullTimer()
    wall0 = _time.perf_counter()
    selection = selection or select_topics(recording)
    scan_frame = _first_scan_frame(recording, selection.scan)
    if scan_frame is None:
        raise CartoError(f"no scans on {selection.scan}", recording.path)
    mount, mount_source = resolve_laser_pose(recording, scan_frame, laser_pose)
    tb = options.trajectory_builder_2d
    local = LocalSlam(tb, laser_pose=mount, timer=timer)

    topics = [selection.scan]
    if use_odometry and selection.odometry:
        topics.append(selection.odometry)
    if use_imu and selection.imu and tb.use_imu_data:
        topics.append(selection.imu)

    if graph is None:
        graph = PoseGraph(options, timer=timer, loop_closure=loop_closure)
    first_node = graph.num_nodes
    times: list[float] = []
    local_poses: list[np.ndarray] = []
    scan_node: list[int] = []  # latest node at or before each posed scan
    node_scans: list[int] = []
    n_scans = 0
    for record in recording.records(topics):
        if isinstance(record, Scan):
            if max_scans is not None and n_scans >= max_scans:
                break
            n_scans += 1
            # Global SLAM work a scan triggers counts in that scan, so per-scan percentiles show its spikes.
            with timer.scan():
                result = local.add_scan(record)
                if result is not None and result.insertion is not None:
                    ins = result.insertion
                    # The node's odometry is interpolated at its time from the samples around it
                    # when the graph is optimized (Cartographer's InterpolateOdometry).
                    with timer.stage("global"):
                        graph.add_node(result.time, result.local_pose, ins.loop_closure_points, ins.submaps,
                                       trajectory=trajectory_id)
                    node_scans.append(len(times))
            if on_scan is not None:
                on_scan(1)
            if result is None:
                continue
            if not node_scans:
                continue  # nothing to anchor a scan to before the first node
            times.append(result.time)
            local_poses.append(result.local_pose)
            scan_node.append(len(node_scans) - 1)
        elif isinstance(record, Odometry):
            graph.add_odometry(record.time, (record.x, record.y, record.yaw), trajectory=trajectory_id)
            local.add_odometry(record)
        elif isinstance(record, Imu):
            local.add_imu(record)

    if not times:
        raise CartoError("no scan could be matched (all scans empty after filtering?)", recording.path)
    if loop_closure:
        with timer.stage("global"):
            graph.optimize(final=True)
    submaps = [entry.submap for entry in graph.submaps]
    local_arr = np.array(local_poses)
    poses = graph.scan_poses(local_arr, np.asarray(scan_node) + first_node)
    submap_poses = graph.submap_global_poses
    with timer.stage("assemble map"):
        corrections = [graph.local_to_global(i) for i in range(len(graph.submaps))]
        image = assemble([sm.grid for sm in submaps], corrections)
    wall = _time.perf_counter() - wall0
    stats = {
        "scans": n_scans,
        "poses": len(times),
        "nodes": len(node_scans),
        "submaps": len(submaps),
        "wall_time_s": wall,
        "scans_per_s": n_scans / wall if wall > 0 else float("nan"),
        "empty_scans": local.stats.empty_scans,
        "constraints": len(graph.constraints),
        "loop_closures": graph.num_loop_closures,
        "optimizations": graph.stats.optimizations,
        "optimization_time_s": graph.stats.optimization_time_s,
        "loop_closure_searches": graph.builder.stats.searched,
        "precomputation_bytes": graph.builder.memory_bytes,
    }
    return MapResult(
        times=np.array(times), poses=poses, local_poses=local_arr, node_scans=np.array(node_scans, int),
        submaps=submaps, submap_poses=submap_poses, image=image, laser_pose=mount,
        laser_pose_source=mount_source, selection=selection, stats=stats,
        loop_closures=graph.loop_closure_segments(), graph=graph,
    )
