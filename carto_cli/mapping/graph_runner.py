"""Where the pose graph runs beside local SLAM: inline, on a thread, or in a forked process, behind one interface.

``Slam`` hands every node and odometry sample to a :class:`GraphRunner` and joins it at the end; which one it gets
follows the jobs and the platform (:func:`start_graph`). Each gets the same calls in the same order, so the graph is
the same whichever runs it (the map is the same for any number of jobs):

* :class:`InlineGraph` (one job): the calls run at once, in the caller's thread;
* :class:`ThreadedGraph`: queued to one thread, the first error raised again in the caller's thread;
* :class:`ForkedGraph` (Linux, more than one job): a process of its own, forked from this one, so that local SLAM and
  the graph share no interpreter lock; its graph's data comes back at ``join`` and is put into the caller's graph.
"""
from __future__ import annotations

import os
import pickle
import queue
import signal
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core import interrupts
from carto_cli.core.enums import TextEnum
from carto_cli.core.errors import CartoError
from carto_cli.core.memory import give_back, peak_kb, reset_peak, status_kb
from carto_cli.core.parallel import die_with_parent, fork_safe
from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.pose_graph_state import SubmapEntry
from carto_cli.mapping.submaps import Submap

if TYPE_CHECKING:
    from multiprocessing.connection import Connection
    from multiprocessing.queues import Queue

__all__ = ["BACKLOG", "ForkedGraph", "GraphPlace", "GraphRunner", "InlineGraph", "ThreadedGraph", "export_graph",
           "import_graph", "start_graph"]


class GraphPlace(TextEnum):
    """Where the graph runs."""

    INLINE = "inline"
    THREAD = "thread"
    PROCESS = "process"


class GraphRunner(Protocol):
    """The pose graph as local SLAM feeds it (``Slam``): nodes and odometry in the order they were made."""

    kind: GraphPlace
    # the peak memory of this process and the graph's together while the graph ran apart (0: it ran here)
    peak_memory_mb: float

    def add_node(self, time: float, local_pose: ArrayLike, points: np.ndarray, submaps: list[Submap], trajectory: int,
                 finished: list[bool]) -> None: ...

    def add_odometry(self, time: float, pose: ArrayLike, trajectory: int) -> None: ...

    def join(self, abandon: bool = False) -> None:
        """Wait until the caller's graph holds every node given (``abandon``: drop the ones not started yet);
        raise the graph's first error."""


# Nodes and odometry samples local SLAM may run ahead of the graph's thread by; then it waits. Bounds the
# memory the queue holds (a node's points) on a recording where the graph is the slower side.
BACKLOG = 2000


class _Background:
    """One thread running queued calls in order; the first error is raised again in the caller's thread."""

    def __init__(self, timer: StageTimer | NullTimer) -> None:
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

    @property
    def abandoned(self) -> bool:
        return self._abandoned

    def submit(self, stage: str | None, fn: Callable, *args: Any, **kwargs: Any) -> None:
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

    def __init__(self, graph: PoseGraph, jobs: int, timer: StageTimer | NullTimer) -> None:
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

    @property
    def process(self):
        return self._process

    def odometry(self, time: float, pose: ArrayLike, trajectory: int) -> None:
        self._odometry.append((time, pose, trajectory))

    def node(self, time: float, local_pose: ArrayLike, points: np.ndarray, submaps: list[Submap], trajectory: int,
             finished: list[bool]) -> None:
        refs = []
        for submap, done in zip(submaps, finished):
            sent = self._known.get(submap.index)
            grid = submap.grid if done and not sent else None
            refs.append((submap.index, submap.local_pose if sent is None else None, grid))
            self._known[submap.index] = bool(sent) or done
        self._put((self._odometry, (time, local_pose, points, refs, trajectory, finished)))
        self._odometry = []

    def _put(self, item: tuple[list, tuple | None]) -> None:
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


def _serve_graph(graph: PoseGraph, jobs: int, timer: StageTimer | NullTimer, inbox: Queue, reply: Connection,
                 parent: int) -> None:
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
        payload = pickle.dumps({"graph": export_graph(graph), "timer": timer.export_tree()},
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


class InlineGraph:
    """One job: each call runs at once, in the caller's thread."""

    kind = GraphPlace.INLINE
    peak_memory_mb = 0.0

    def __init__(self, graph: PoseGraph, timer: StageTimer | NullTimer) -> None:
        self.graph = graph
        self.timer = timer

    def add_node(self, time: float, local_pose: ArrayLike, points: np.ndarray, submaps: list[Submap], trajectory: int,
                 finished: list[bool]) -> None:
        with self.timer.stage("global"):
            self.graph.add_node(time, local_pose, points, submaps, trajectory=trajectory, finished=finished)

    def add_odometry(self, time: float, pose: ArrayLike, trajectory: int) -> None:
        self.graph.add_odometry(time, pose, trajectory=trajectory)

    def join(self, abandon: bool = False) -> None:
        pass


class ThreadedGraph:
    """The graph's calls queued to one thread of its own; its searches on ``jobs`` threads."""

    kind = GraphPlace.THREAD
    peak_memory_mb = 0.0

    def __init__(self, graph: PoseGraph, jobs: int, timer: StageTimer | NullTimer) -> None:
        self.graph = graph
        self.timer = timer
        self._thread = _Background(timer.concurrent("global"))
        graph.use_threads(jobs, timer=self._thread.timer)

    @property
    def abandoned(self) -> bool:
        """``join(abandon=True)`` has begun: queued calls are dropped."""
        return self._thread.abandoned

    def add_node(self, time: float, local_pose: ArrayLike, points: np.ndarray, submaps: list[Submap], trajectory: int,
                 finished: list[bool]) -> None:
        with self.timer.stage("global queue"):
            self._thread.submit("node", self.graph.add_node, time, local_pose, points, submaps,
                                trajectory=trajectory, finished=finished)

    def add_odometry(self, time: float, pose: ArrayLike, trajectory: int) -> None:
        # in order with the nodes: the graph reads the samples when optimizing
        with self.timer.stage("global queue"):
            self._thread.submit(None, self.graph.add_odometry, time, pose, trajectory=trajectory)

    def join(self, abandon: bool = False) -> None:
        with self.timer.stage("global wait"):
            self._thread.join(abandon)
        self.graph.use_threads(1, timer=self.timer)


class ForkedGraph:
    """The graph in a forked process (:class:`_GraphProcess`); at ``join`` its data is put into the caller's graph,
    whose submaps are local SLAM's own (the process had stand-ins)."""

    kind = GraphPlace.PROCESS

    def __init__(self, graph: PoseGraph, jobs: int, timer: StageTimer | NullTimer, trajectory: int) -> None:
        self.graph = graph
        self.timer = timer
        self.trajectory = trajectory
        self.peak_memory_mb = 0.0
        self._submaps: dict[int, Submap] = {}  # local SLAM's submaps the process got, by index
        self._process = _GraphProcess(graph, jobs, timer.concurrent("global"))

    @property
    def child(self):
        """The graph's process (``multiprocessing.Process``)."""
        return self._process.process

    def add_node(self, time: float, local_pose: ArrayLike, points: np.ndarray, submaps: list[Submap], trajectory: int,
                 finished: list[bool]) -> None:
        with self.timer.stage("global queue"):
            for submap in submaps:
                self._submaps.setdefault(submap.index, submap)
            self._process.node(time, local_pose, points, submaps, trajectory, finished)

    def add_odometry(self, time: float, pose: ArrayLike, trajectory: int) -> None:
        self._process.odometry(time, pose, trajectory)

    def join(self, abandon: bool = False) -> None:
        process = self._process
        with self.timer.stage("global wait"):
            data = process.join(abandon)
        if data is not None:
            import_graph(self.graph, data["graph"], self._submaps, self.trajectory)
            process.timer.import_tree(data["timer"])
            self.peak_memory_mb = max(process.peak_before_kb / 1024, process.peak_beside_mb)


def start_graph(graph: PoseGraph, *, jobs: int, loop_closure: bool, process: bool, timer: StageTimer | NullTimer,
                trajectory: int) -> GraphRunner:
    """The runner for ``jobs``: inline for one job or without loop closure (the graph then only chains nodes),
    else a forked process where that is safe (``process``) or a thread."""
    if jobs > 1 and loop_closure:
        if process and fork_safe():
            return ForkedGraph(graph, jobs, timer, trajectory)
        return ThreadedGraph(graph, jobs, timer)
    return InlineGraph(graph, timer)


def export_graph(graph: PoseGraph) -> dict:
    """Everything ``graph`` holds but its options, timer, threads and stacks, as one picklable value: the graph of
    a process of its own handing its work back (:func:`import_graph`). What goes is what ``PoseGraph.EXPORTED``
    names; submaps go by key, not grid; the constraint builder as what it learnt."""
    graph.settle()
    graph.close()
    data = {name: getattr(graph, name) for name in PoseGraph.EXPORTED}
    data["submaps"] = [(e.trajectory, e.submap.index, e.global_pose, e.nodes, e.searched) for e in graph.submaps]
    data["builder"] = graph.builder.export_data()
    return data


def import_graph(graph: PoseGraph, data: dict, submaps: dict[int, Submap], trajectory: int) -> None:
    """Make ``graph`` the graph :func:`export_graph` gave, whose submaps of ``trajectory`` are ``submaps`` (by
    index) and whose other submaps are ``graph``'s own."""
    data = dict(data)
    own = {(e.trajectory, e.submap.index): e.submap for e in graph.submaps}
    entries = [SubmapEntry(submaps[index] if t == trajectory and index in submaps else own[(t, index)], t, pose,
                           nodes, searched) for t, index, pose, nodes, searched in data.pop("submaps")]
    graph.builder.import_data(data.pop("builder"))
    for name in PoseGraph.EXPORTED:
        setattr(graph, name, data[name])
    graph.submaps = entries
