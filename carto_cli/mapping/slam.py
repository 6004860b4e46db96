"""The SLAM core object: scans, odometry and IMU in; poses, submaps and the pose graph out. No files.

Like kiss-icp's ``KissICP``: the caller owns reading (``carto_cli.pipeline`` feeds a recording,
tests feed arrays); this object only turns time-ordered measurements into a map.

With more than one job the pose graph runs beside local SLAM, as Cartographer's global SLAM does: in a
process of its own on Linux (forked; the two then share no interpreter lock), else on a thread. Local SLAM
never reads the graph, so the caller goes on matching scans while the graph searches and optimizes. The
graph gets its nodes and odometry in the order local SLAM made them, with each submap's "finished" flag as it
was when the node was made, so it does exactly what it would do inline and the map is the same for any number
of jobs.
"""
from __future__ import annotations

import os
import pickle
import queue
import signal
import threading
import time as _time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from carto_cli.core import interrupts
from carto_cli.core.errors import CartoError
from carto_cli.core.memory import give_back, peak_kb, reset_peak, status_kb
from carto_cli.core.parallel import available_cores, die_with_parent, fork_safe
from carto_cli.core.records import Imu, Odometry, Scan
from carto_cli.core.timing import NullTimer
from carto_cli.grid.occupancy_image import EAGER_CELLS, AssembledImage, OccupancyImage
from carto_cli.mapping.local_slam import LocalSlam, LocalSlamResult
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options


@dataclass
class SlamResult:
    times: np.ndarray  # (S,) every scan that got a pose
    poses: np.ndarray  # (S, 3) tracking frame in the map frame
    local_poses: np.ndarray  # (S, 3) the same scans in the local SLAM frame
    node_scans: np.ndarray  # (N,) index into times/poses of every node
    submaps: list[Submap]
    submap_poses: np.ndarray  # (M, 3) global poses of the submaps' frames (local frame ↦ map frame)
    image: OccupancyImage | AssembledImage  # a large map is assembled strip by strip as it is written
    laser_pose: np.ndarray
    stats: dict = field(default_factory=dict)
    loop_closures: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (K, 4) x1 y1 x2 y2 for drawing
    graph: PoseGraph | None = None
    # (N, 3) the nodes' poses before a final refinement that made the map consistent (GMapping's loop step and
    # re-matching): the verdict judges them too, since consistency after that refinement is what it maximized
    unrefined_node_poses: np.ndarray | None = None


# Nodes and odometry samples local SLAM may run ahead of the graph's thread by; then it waits. Bounds the
# memory the queue holds (a node's points) on a recording where the graph is the slower side.
BACKLOG = 2000


class _Background:
    """One thread running queued calls in order; the first error is raised again in the caller's thread."""

    def __init__(self, timer):
        self.timer = timer
        self._queue: queue.Queue = queue.Queue(maxsize=BACKLOG)
        self._error: BaseException | None = None
        self._last_raised: BaseException | None = None  # raised once in the caller's thread, not at every call
        self._abandoned = False
        self._thread = threading.Thread(target=self._run, name="carto-global", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            if self._error is not None or self._abandoned:
                continue  # drain without running: the caller raises the first error, or has given up
            stage, fn, args, kwargs = item
            try:
                if stage:
                    with self.timer.stage(stage):
                        fn(*args, **kwargs)
                else:
                    fn(*args, **kwargs)
            except BaseException as e:  # handed to the caller's thread
                self._error = e

    def submit(self, stage: str | None, fn: Callable, *args, **kwargs) -> None:
        self._raise()
        self._queue.put((stage, fn, args, kwargs))

    def join(self, abandon: bool = False) -> None:
        """Wait until every queued call has run (``abandon``: the calls not yet started are dropped); raise the
        first error."""
        self._abandoned = self._abandoned or abandon
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        self._raise()

    def _raise(self) -> None:
        error = self._error
        if error is not None and not self._reported_before(error):
            raise error

    def _reported_before(self, error: BaseException) -> bool:
        seen = error is self._last_raised
        self._last_raised = error
        return seen


class _GraphProcess:
    """The pose graph in a process of its own, forked from this one: local SLAM and the graph no longer share
    one interpreter lock (on two cores the graph's thread slowed local SLAM's Python by half, docs/scaling.md).

    The child gets the same calls in the same order as the graph's thread would, so its graph is the same;
    submaps go over once when they first appear (origin only) and once when finished (the grid, which the
    child keeps packed), the only state the graph reads of them. ``join`` returns the child's graph data, to be
    put back into the caller's graph, whose submaps are the real ones.
    """

    def __init__(self, graph: PoseGraph, jobs: int, timer):
        self.timer = timer
        self._known: dict[int, bool] = {}  # submap index -> finished grid sent
        self._odometry: list = []  # samples since the last node, sent with it
        import multiprocessing  # only when the graph gets a process

        # The two processes' peaks over the child's life add up; this one's peak before and after is its own.
        self.peak_before_kb = peak_kb()
        ctx = multiprocessing.get_context("fork")
        self._inbox = ctx.Queue(maxsize=BACKLOG)
        self._reply, child_end = ctx.Pipe(duplex=False)
        self._process = ctx.Process(target=_serve_graph, args=(graph, jobs, timer, self._inbox, child_end,
                                                               os.getpid()),
                                    name="carto-global", daemon=True)
        self._process.start()
        reset_peak()
        child_end.close()
        self._done = False
        self.peak_beside_mb = 0.0  # both processes' peaks over the child's life, added (set by join)

    def odometry(self, time: float, pose, trajectory: int) -> None:
        self._odometry.append((time, pose, trajectory))

    def node(self, time: float, local_pose, points, submaps: list[Submap], trajectory: int,
             finished: list[bool]) -> None:
        refs = []
        for submap, done in zip(submaps, finished):
            sent = self._known.get(submap.index)
            grid = submap.grid if done and not sent else None
            refs.append((submap.index, submap.local_pose if sent is None else None, grid))
            self._known[submap.index] = bool(sent) or done
        self._put((self._odometry, (time, local_pose, points, refs, trajectory, finished)))
        self._odometry = []

    def _put(self, item) -> None:
        while True:
            try:
                self._inbox.put(item, timeout=1.0)
                return
            except queue.Full:
                if not self._process.is_alive():
                    raise self._died() from None

    def join(self, abandon: bool = False) -> dict | None:
        """Wait for the child's graph (None when abandoned: the child is stopped at once)."""
        if self._done:
            return None
        self._done = True
        try:
            if abandon:
                self._process.kill()
                return None
            self._put((self._odometry, None))
            mapping_kb = peak_kb()  # this process's peak while the child mapped
            try:
                kind, payload = self._reply.recv()
                if kind == "error":
                    raise payload
                data = pickle.loads(self._reply.recv_bytes())
            except EOFError:
                raise self._died() from None
            # An upper bound of what both held at once: each one's peak while the child mapped, then each one's
            # memory while the graph came over (the child's at its largest then, with the pickled graph).
            self.peak_beside_mb = max(mapping_kb / 1024 + payload["peak_added_mb"],
                                      peak_kb() / 1024 + payload["export_added_mb"])
            reset_peak()
            self._inbox.close()
            self._inbox.join_thread()  # everything was read: the feeder thread ends at once
            return data
        finally:
            self._inbox.close()
            self._inbox.cancel_join_thread()  # (after an error or kill: the pipe may hold what nobody reads)
            self._reply.close()
            self._process.join()

    def _died(self) -> BaseException:
        """Why the child is gone: the error it sent before it ended, else its exit code."""
        if self._reply.poll():
            try:
                kind, payload = self._reply.recv()
                if kind == "error":
                    return payload
            except (EOFError, OSError):
                pass
        self._process.join(5)
        code = self._process.exitcode
        why = " (killed: out of memory?)" if code == -9 else ""
        return CartoError(f"the pose graph's process ended unexpectedly, exit code {code}{why}")


def _serve_graph(graph: PoseGraph, jobs: int, timer, inbox, reply, parent: int) -> None:
    """The child's loop (see _GraphProcess): run the calls, send the graph's data back, exit."""
    die_with_parent(parent)  # its inbox's pipe is this process's too: a killed parent would leave it waiting
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides what Ctrl-C stops
    interrupts.clear()  # only a signal to this process counts here
    # A forked child starts with the parent's pages, shared until written: what it adds is its peak beyond them.
    inherited_kb = status_kb("VmRSS")
    try:
        graph.use_threads(jobs, timer=timer)
        stand_ins: dict[int, Submap] = {}
        while True:
            odometry, node = inbox.get()
            for time, pose, trajectory in odometry:
                graph.add_odometry(time, pose, trajectory=trajectory)
            if node is None:
                break
            time, local_pose, points, refs, trajectory, finished = node
            submaps = []
            for index, origin, grid in refs:
                submap = stand_ins.get(index)
                if submap is None:
                    submap = stand_ins[index] = Submap.stand_in(index, origin)
                if grid is not None:
                    submap.grid, submap.finished = grid, True
                    submap.retire()  # local SLAM's copy is packed once it is done matching against it
                submaps.append(submap)
            with timer.stage("node"):
                graph.add_node(time, local_pose, points, submaps, trajectory=trajectory, finished=finished)
        graph.settle()
        graph.close()
        peak_added_mb = max(0, peak_kb() - inherited_kb) / 1024
        # No search follows: the stacks go back before the graph is pickled (as Slam.finish does inline).
        graph.builder.stacks.clear()
        give_back()
        payload = pickle.dumps({"graph": graph.export_data(), "timer": timer.export_tree()},
                               protocol=pickle.HIGHEST_PROTOCOL)
        export_added_mb = max(0, status_kb("VmRSS") - inherited_kb) / 1024
        reply.send(("ok", {"peak_added_mb": peak_added_mb, "export_added_mb": export_added_mb}))
        reply.send_bytes(payload)
    except BaseException as e:  # handed to the parent
        if interrupts.is_interrupt(e):
            # A SIGTERM of its own (`timeout` signals the whole group), maybe wrapped by numba in a SystemError
            # whose cause a pickle drops: the parent must read it as an interrupt.
            e = KeyboardInterrupt()
        try:
            reply.send(("error", e))
        except Exception:  # not picklable
            reply.send(("error", RuntimeError(f"{type(e).__name__}: {e}")))
    finally:
        reply.close()
        os._exit(0)  # the parent's exit handlers and threads are not this process's


class Slam:
    """Local SLAM feeding a pose graph, as Cartographer's MapBuilder wires them for one trajectory.

    With ``graph`` (e.g. restored from a map.carto) the measurements become trajectory
    ``trajectory_id`` of that graph, linked to the earlier ones by loop closures. ``jobs`` > 1 (None: every
    core) runs the graph beside local SLAM (``process``: in a forked process where that is safe, else on a
    thread) and its searches on ``jobs`` threads; call ``finish`` or ``close`` to stop them.
    """

    def __init__(self, options: Options, *, laser_pose=(0.0, 0.0, 0.0), timer=None, loop_closure: bool = True,
                 graph: PoseGraph | None = None, trajectory_id: int = 0, started: float | None = None,
                 jobs: int | None = 1, process: bool = True):
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
        self._scan_node: list[int] = []  # latest node at or before each posed scan
        self._node_scans: list[int] = []
        self.num_scans = 0
        self.jobs = available_cores() if jobs is None else max(1, int(jobs))
        self._background: _Background | None = None
        self._process: _GraphProcess | None = None
        self._submaps: dict[int, Submap] = {}  # local SLAM's submaps the graph's process got, by index
        # The peak memory of this process and the graph's together while the graph's process ran (each one's peak
        # over that time, added; the child's beyond the pages it shares with this one), or of this one before it.
        self.graph_process_peak_memory_mb = 0.0
        self.graph_runs = "inline"  # where the graph runs: inline (one job) | thread | process
        if self.jobs > 1 and loop_closure:
            if process and fork_safe():
                self._process = _GraphProcess(self.graph, self.jobs, self.timer.concurrent("global"))
                self.graph_runs = "process"
            else:
                self._background = _Background(self.timer.concurrent("global"))
                self.graph.use_threads(self.jobs, timer=self._background.timer)
                self.graph_runs = "thread"

    @property
    def num_poses(self) -> int:
        return len(self._times)

    def add_scan(self, scan: Scan) -> LocalSlamResult | None:
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
                if self._process is not None:
                    with timer.stage("global queue"):
                        for submap in ins.submaps:
                            self._submaps.setdefault(submap.index, submap)
                        self._process.node(result.time, result.local_pose, ins.loop_closure_points,
                                           list(ins.submaps), self.trajectory_id, finished)
                elif self._background is not None:
                    with timer.stage("global queue"):
                        self._background.submit("node", self.graph.add_node, result.time, result.local_pose,
                                                ins.loop_closure_points, list(ins.submaps),
                                                trajectory=self.trajectory_id, finished=finished)
                else:
                    with timer.stage("global"):
                        self.graph.add_node(result.time, result.local_pose, ins.loop_closure_points, ins.submaps,
                                            trajectory=self.trajectory_id, finished=finished)
                self._node_scans.append(len(self._times))
        if result is None or not self._node_scans:
            return result  # nothing to anchor a scan to before the first node
        self._times.append(result.time)
        self._local_poses.append(result.local_pose)
        self._scan_node.append(len(self._node_scans) - 1)
        return result

    def add_odometry(self, odometry: Odometry) -> None:
        pose = (odometry.x, odometry.y, odometry.yaw)
        if self._process is not None:
            self._process.odometry(odometry.time, pose, self.trajectory_id)
        elif self._background is not None:  # in order with the nodes: the graph reads the samples when optimizing
            with self.timer.stage("global queue"):
                self._background.submit(None, self.graph.add_odometry, odometry.time, pose,
                                        trajectory=self.trajectory_id)
        else:
            self.graph.add_odometry(odometry.time, pose, trajectory=self.trajectory_id)
        self.local.add_odometry(odometry)

    def add_imu(self, imu: Imu) -> None:
        self.local.add_imu(imu)

    def close(self, abandon: bool = False) -> None:
        """Wait for the graph's thread and stop the search threads (raises the graph's error, if any);
        ``abandon`` (mapping failed or was interrupted): drop the nodes the graph has not started on."""
        background, self._background = self._background, None
        process, self._process = self._process, None
        try:
            if process is not None:
                with self.timer.stage("global wait"):
                    data = process.join(abandon)
                if data is not None:
                    self.graph.import_data(data["graph"], self._submaps, self.trajectory_id)
                    process.timer.import_tree(data["timer"])
                    self.graph_process_peak_memory_mb = max(process.peak_before_kb / 1024, process.peak_beside_mb)
            if background is not None:
                with self.timer.stage("global wait"):
                    background.join(abandon)
                self.graph.use_threads(1, timer=self.timer)
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
        poses = graph.scan_poses(local_arr, np.asarray(self._scan_node) + self._first_node)
        submap_poses = graph.submap_global_poses
        with timer.stage("assemble map"):
            corrections = [graph.local_to_global(i) for i in range(len(graph.submaps))]
            image = AssembledImage([sm.grid for sm in submaps], corrections)
            if image.shape[0] * image.shape[1] <= EAGER_CELLS:
                image.probability  # noqa: B018 - assembled now, in this stage; a larger map as it is written
        wall = _time.perf_counter() - self._started
        n_scans = self.num_scans
        stats = {
            "scans": n_scans,
            "poses": len(self._times),
            "nodes": len(self._node_scans),
            "submaps": len(submaps),
            "wall_time_s": wall,
            "scans_per_s": n_scans / wall if wall > 0 else float("nan"),
            "empty_scans": self.local.stats.empty_scans,
            "constraints": len(graph.constraints),
            "loop_closures": graph.num_loop_closures,
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
            laser_pose=self.laser_pose, stats=stats, loop_closures=graph.loop_closure_segments(), graph=graph,
        )
