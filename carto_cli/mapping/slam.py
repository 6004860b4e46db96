"""The SLAM core object: scans, odometry and IMU in; poses, submaps and the pose graph out. No files.

Like kiss-icp's ``KissICP``: the caller owns reading (``carto_cli.pipeline`` feeds a recording,
tests feed arrays); this object only turns time-ordered measurements into a map.

With more than one job the pose graph runs beside local SLAM, as Cartographer's global SLAM does: in a
process of its own on Linux (forked; the two then share no interpreter lock), else on a thread
(``graph_runner``). Local SLAM never reads the graph, so the caller goes on matching scans while the graph
searches and optimizes. The graph gets its nodes and odometry in the order local SLAM made them, with each
submap's "finished" flag as it was when the node was made, so it does exactly what it would do inline and the
map is the same for any number of jobs.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Any, Protocol, TypedDict

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core import transform
from carto_cli.core.memory import give_back
from carto_cli.core.parallel import available_cores
from carto_cli.core.records import Imu, Odometry, Scan
from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.grid.occupancy_image import EAGER_CELLS, AssembledImage, OccupancyImage
from carto_cli.mapping.cleaning import compact_returns
from carto_cli.mapping.graph_runner import GraphPlace, GraphRunner, start_graph
from carto_cli.mapping.local_slam import LocalSlam
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options


class MappingSystem(Protocol):
    """What a mapping system is to the pipeline that feeds it (``Slam``; ``gmapping``'s ``GMappingSlam`` and
    ``ScanToMapSlam``): time-ordered measurements in, a :class:`SlamResult` out."""

    timer: Any
    num_scans: int  # scans fed

    @property
    def num_poses(self) -> int:
        """Scans that got a pose so far."""

    def add_scan(self, scan: Scan) -> bool:
        """Feed one scan; True when it became a node of the map."""

    def add_odometry(self, odometry: Odometry) -> None: ...

    def add_imu(self, imu: Imu) -> None: ...

    def close(self, abandon: bool = False) -> None:
        """Stop whatever runs beside the caller (``abandon``: mapping failed or was interrupted)."""

    def finish(self) -> SlamResult:
        """Every scan's pose and the map; call once."""


class RunStats(TypedDict, total=False):
    """A mapping run's statistics (summary.json's ``stats``), by the system that made the map. Times are the
    mapping's (wall, from the system's start), memory in MB or bytes as named."""

    algorithm: str  # GMapping's pipeline names itself; a Cartographer run leaves it out
    maps: int  # carto merge: the saved maps merged
    scans: int  # fed
    poses: int  # scans that got a pose
    nodes: int
    processed_scans: int  # GMapping: the scans that moved the robot far enough to be processed
    submaps: int
    wall_time_s: float  # after auto's second mapping, both passes (first_pass_wall_time_s: the first)
    first_pass_wall_time_s: float
    scans_per_s: float
    empty_scans: int
    transient_points: int  # Cartographer: scan points left out of local matching as transient (people, carts)
    transient_returns: int  # and returns kept out of the submaps
    constraints: int
    loop_closures: int
    loop_closure_candidates: int
    loop_closure_searches: int
    whole_map_searches: int  # carto merge: searches over a whole submap (trajectories not linked yet)
    optimizations: int
    optimization_time_s: float
    precomputation_bytes: int  # the most branch-and-bound stacks held at once
    precomputations: int  # stacks built, rebuilt ones included
    precomputation_evictions: int
    particles: int
    resamplings: int
    mean_neff: float | None
    map_tiles_peak: int
    map_memory_peak_bytes: int
    unconverged_matches: int  # scan-to-map: Gauss-Newton runs that stopped at the iteration limit
    graph_process_peak_memory_mb: float  # the pose graph's own process, when it ran in one (else 0)
    peak_memory_mb: float | None  # this process's, or with the graph's process while it ran if higher
    aligned_deg: float  # --align: the turn given to the map frame (0: none), also in map.carto's metadata


@dataclass(frozen=True)
class SlamResult:
    times: np.ndarray  # (S,) every scan that got a pose
    poses: np.ndarray  # (S, 3) tracking frame in the map frame
    local_poses: np.ndarray  # (S, 3) the same scans in the local SLAM frame
    node_scans: np.ndarray  # (N,) index into times/poses of every node
    submaps: list[Submap]
    submap_poses: np.ndarray  # (M, 3) global poses of the submaps' frames (local frame ↦ map frame)
    image: OccupancyImage | AssembledImage  # a large map is assembled strip by strip as it is written
    laser_pose: np.ndarray
    stats: RunStats = field(default_factory=lambda: RunStats())
    loop_closures: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (K, 4) x1 y1 x2 y2 for drawing
    graph: PoseGraph | None = None
    # (N, 3) the nodes' poses before a final refinement that made the map consistent (GMapping's loop step and
    # re-matching): the verdict judges them too, since consistency after that refinement is what it maximized
    unrefined_node_poses: np.ndarray | None = None
    # Every node of this run (graph nodes first_node, first_node + 1, ...): its inserted returns in its own frame,
    # in cm (cleaning.compact_returns), for judging what the map saw through after it was hit (mapping.cleaning)
    node_returns: list[np.ndarray] = field(default_factory=list)
    first_node: int = 0


class Slam:
    """Local SLAM feeding a pose graph, as Cartographer's MapBuilder wires them for one trajectory.

    With ``graph`` (e.g. restored from a map.carto) the measurements become trajectory
    ``trajectory_id`` of that graph, linked to the earlier ones by loop closures. ``jobs`` > 1 (None: every
    core) runs the graph beside local SLAM (``process``: in a forked process where that is safe, else on a
    thread) and its searches on ``jobs`` threads; call ``finish`` or ``close`` to stop them.
    """

    def __init__(self, options: Options, *, laser_pose: ArrayLike = (0.0, 0.0, 0.0),
                 timer: StageTimer | NullTimer | None = None, loop_closure: bool = True,
                 graph: PoseGraph | None = None, trajectory_id: int = 0, started: float | None = None,
                 jobs: int | None = 1, process: bool = True) -> None:
        self.options = options
        self.timer = timer or NullTimer()
        self.loop_closure = loop_closure
        self.laser_pose = np.asarray(laser_pose, dtype=np.float64)
        self.local = LocalSlam(options.trajectory_builder_2d, laser_pose=self.laser_pose, timer=self.timer)
        self.graph = graph if graph is not None else PoseGraph(options, timer=self.timer, loop_closure=loop_closure)
        self.trajectory_id = trajectory_id
        self._started = _time.perf_counter() if started is None else started
        self._first_node = self.graph.num_nodes
        self._times: list[float] = []
        self._local_poses: list[np.ndarray] = []
        self._node_returns: list[np.ndarray] = []
        self._scan_node: list[int] = []  # latest node at or before each posed scan
        self._node_scans: list[int] = []
        self.num_scans = 0
        self.jobs = available_cores() if jobs is None else max(1, int(jobs))
        self.runner: GraphRunner = start_graph(self.graph, jobs=self.jobs, loop_closure=loop_closure,
                                               process=process, timer=self.timer, trajectory=trajectory_id)
        self._joined = False
        # The peak memory of this process and the graph's together while the graph's process ran (each one's peak
        # over that time, added; the child's beyond the pages it shares with this one), or of this one before it.
        self.graph_process_peak_memory_mb = 0.0

    @property
    def graph_runs(self) -> GraphPlace:
        """Where the graph runs: inline (one job), on a thread, or in a process."""
        return self.runner.kind

    @property
    def num_poses(self) -> int:
        return len(self._times)

    def add_scan(self, scan: Scan) -> bool:
        """Feed one scan; True when it became a node of the map (a scan local SLAM matched and inserted)."""
        self.num_scans += 1
        timer = self.timer
        # Global SLAM work a scan triggers counts in that scan, so per-scan percentiles show its spikes.
        with timer.scan():
            result = self.local.add_scan(scan)
            if result is not None and result.insertion is not None:
                ins = result.insertion
                # The node's odometry is interpolated at its time from the samples around it
                # when the graph is optimized (Cartographer's InterpolateOdometry).
                finished = [s.finished for s in ins.submaps]
                self.runner.add_node(result.time, result.local_pose, ins.loop_closure_points, list(ins.submaps),
                                     self.trajectory_id, finished)
                self._node_scans.append(len(self._times))
                self._node_returns.append(compact_returns(ins.range_data_local.returns, result.local_pose))
        if result is None or not self._node_scans:
            return False  # nothing to anchor a scan to before the first node
        self._times.append(result.time)
        self._local_poses.append(result.local_pose)
        self._scan_node.append(len(self._node_scans) - 1)
        return result.insertion is not None

    def add_odometry(self, odometry: Odometry) -> None:
        self.runner.add_odometry(odometry.time, (odometry.x, odometry.y, odometry.yaw), self.trajectory_id)
        self.local.add_odometry(odometry)

    def add_imu(self, imu: Imu) -> None:
        self.local.add_imu(imu)

    def close(self, abandon: bool = False) -> None:
        """Wait for the graph's thread and stop the search threads (raises the graph's error, if any);
        ``abandon`` (mapping failed or was interrupted): drop the nodes the graph has not started on."""
        joined, self._joined = self._joined, True
        try:
            if not joined:  # once: the runner is done with, even when joining it raised
                self.runner.join(abandon)
                self.graph_process_peak_memory_mb = self.runner.peak_memory_mb
        finally:
            self.graph.close()

    def finish(self) -> SlamResult:
        """The final optimization, every scan's pose and the assembled map. Call once, with at least one pose."""
        self.close()
        if not self._times:
            raise ValueError("no scan got a pose")
        timer, graph = self.timer, self.graph
        if self.loop_closure:
            # Not "global": with more than one job that names the graph's own branch beside this stage.
            with timer.stage("final optimization"):
                graph.optimize(final=True)
        # No search follows the final optimization: the precomputation stacks (up to the whole budget) go back
        # before the map is assembled and judged, whose arrays would otherwise come on top of them (the 2-hour
        # campus: 1160 -> 950 MB peak, docs/scaling.md). A later search rebuilds what it needs.
        graph.builder.stacks.clear()
        give_back()
        submaps = [entry.submap for entry in graph.submaps]
        local_arr = np.array(self._local_poses)
        poses = scan_poses(graph, local_arr, np.asarray(self._scan_node) + self._first_node)
        submap_poses = graph.submap_global_poses
        with timer.stage("assemble map"):
            corrections = [entry.local_to_global() for entry in graph.submaps]
            image = AssembledImage([sm.grid for sm in submaps], corrections)
            if image.shape[0] * image.shape[1] <= EAGER_CELLS:
                image.probability  # noqa: B018 - assembled now, in this stage; a larger map as it is written
        wall = _time.perf_counter() - self._started
        n_scans = self.num_scans
        stats: RunStats = {
            "scans": n_scans,
            "poses": len(self._times),
            "nodes": len(self._node_scans),
            "submaps": len(submaps),
            "wall_time_s": wall,
            "scans_per_s": n_scans / wall if wall > 0 else float("nan"),
            "empty_scans": self.local.stats.empty_scans,
            "transient_points": self.local.stats.transient_matching,
            "transient_returns": self.local.stats.transient_inserted,
            "constraints": len(graph.constraints),
            "loop_closures": graph.constraints.num_loop_closures,
            "optimizations": graph.stats.optimizations,
            "optimization_time_s": graph.stats.optimization_time_s,
            "loop_closure_searches": graph.builder.stats.searched,
            "precomputation_bytes": graph.builder.stacks.peak_bytes,  # the most held at once
            "precomputations": graph.builder.stacks.misses,  # stacks built, rebuilt ones included
            "precomputation_evictions": graph.builder.stacks.evictions,
            "graph_process_peak_memory_mb": self.graph_process_peak_memory_mb,
        }
        return SlamResult(
            times=np.array(self._times), poses=poses, local_poses=local_arr,
            node_scans=np.array(self._node_scans, int), submaps=submaps, submap_poses=submap_poses, image=image,
            laser_pose=self.laser_pose, stats=stats, loop_closures=_closure_segments(graph), graph=graph,
            node_returns=self._node_returns, first_node=self._first_node,
        )


def scan_poses(graph: PoseGraph, scan_local: np.ndarray, scan_node: np.ndarray) -> np.ndarray:
    """Global poses of scans given their local poses and the latest node at or before each.

    A scan between nodes takes the correction of the node before it, which is what the robot would have reported
    at that moment had it known the optimized graph.
    """
    g = graph.global_poses[scan_node]
    local = graph.local_poses[scan_node]
    correction = transform.compose(g, transform.inverse(local))
    return transform.compose(correction, scan_local)


def _closure_segments(graph: PoseGraph) -> np.ndarray:
    """(K, 4) node xy → submap origin xy in the map frame of every loop closure, for drawing."""
    mask = graph.constraints.is_loop_closure
    if not mask.any():
        return np.zeros((0, 4))
    nodes = graph.constraints.node[mask]
    subs = graph.constraints.submap[mask]
    return np.concatenate([graph.global_poses[nodes, :2], graph.submap_global_poses[subs, :2]], axis=1)
