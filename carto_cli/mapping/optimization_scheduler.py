"""When the pose graph's periodic optimization runs: beside the next ``optimize_every_n_nodes`` nodes (as
Cartographer's runs beside its constraint searches), on a thread of its own with more than one job, its poses
taken when the next one starts.

Waiting for each optimization before the next node left the search threads idle for about a third of the graph's
work (docs/scaling.md). The optimization gets a copy of the graph as it is when it starts
(:class:`OptimizationProblem`) and its result is taken at a fixed point, one period later, on every job count (one
job: computed at once, taken at the same point), so the graph is the same for any number of jobs. The scheduler
knows the problem it was handed, never the graph; it reads no file.
"""
from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from carto_cli.core.parallel import Done
from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.mapping.constraints import ConstraintSet
from carto_cli.mapping.optimization import NodePairs, OptimizationResult, optimize
from carto_cli.options.schema import PoseGraph as PoseGraphOptions

__all__ = ["OPTIMIZER_THREAD", "OptimizationProblem", "OptimizationScheduler", "RunningOptimization"]

# The concurrent branch of the graph's timer that periodic optimizations solved on the optimizer's own thread go to
# (they run beside the next nodes; the graph's own stage for them is "optimization wait").
OPTIMIZER_THREAD = "optimizer thread"


@dataclass(frozen=True)
class OptimizationProblem:
    """One optimization's inputs, copied when it starts: a solve beside the next nodes reads nothing live."""

    node_poses: np.ndarray
    submap_poses: np.ndarray
    constraints: ConstraintSet
    odometry: NodePairs | None
    local_slam: NodePairs
    huber_scale: float
    max_num_iterations: int
    fixed_submaps: tuple[int, ...] = (0,)

    @classmethod
    def of(cls, options: PoseGraphOptions, *, local_poses: np.ndarray, global_poses: np.ndarray,
           trajectories: np.ndarray, odometry: np.ndarray, submap_poses: np.ndarray, constraints: ConstraintSet,
           final: bool) -> OptimizationProblem:
        """The problem of a graph with these nodes (local-SLAM and global poses, trajectories, odometry at each,
        NaN where none), submaps and constraints, copied; ``final``: with the final optimization's iterations."""
        op = options.optimization_problem
        local = NodePairs.consecutive(local_poses, trajectories,
                                      translation_weight=op.local_slam_pose_translation_weight,
                                      rotation_weight=op.local_slam_pose_rotation_weight)
        pairs = None
        if np.isfinite(odometry).any():
            pairs = NodePairs.consecutive(odometry, trajectories, translation_weight=op.odometry_translation_weight,
                                          rotation_weight=op.odometry_rotation_weight)
        iterations = options.max_num_final_iterations if final else op.ceres_solver_options.max_num_iterations
        return cls(global_poses.copy(), submap_poses, constraints.copy(), pairs, local, op.huber_scale, iterations)

    def solve(self) -> tuple[OptimizationResult, int]:
        """The optimized poses and how long the solve took (ns), on whichever thread runs it."""
        start = time.perf_counter_ns()
        result = optimize(self.node_poses, self.submap_poses, self.constraints, self.odometry, self.local_slam,
                          huber_scale=self.huber_scale, max_num_iterations=self.max_num_iterations,
                          fixed_submaps=self.fixed_submaps)
        return result, time.perf_counter_ns() - start


@dataclass(frozen=True)
class RunningOptimization:
    """The periodic optimization running beside the next nodes: its result to come, and what it had."""

    task: Any  # a Future or core.parallel.Done of OptimizationProblem.solve's answer
    num_nodes: int
    num_submaps: int
    thread: Any  # its timer branch when it runs on the solver's thread; None when computed inline


class OptimizationScheduler:
    def __init__(self) -> None:
        self.running: RunningOptimization | None = None
        self._solver: ThreadPoolExecutor | None = None  # its thread, with more than one job

    def start(self, problem: OptimizationProblem, num_nodes: int, num_submaps: int, *, jobs: int,
              timer: StageTimer | NullTimer) -> None:
        """Solve ``problem`` (of the first ``num_nodes`` nodes and ``num_submaps`` submaps) beside the caller with
        more than one job, else now; :meth:`take` hands the result over."""
        if self._solver is None and jobs > 1:
            self._solver = ThreadPoolExecutor(max_workers=1, thread_name_prefix="carto-optimize")
        if self._solver is None:
            with timer.stage("optimization"):
                task: Any = Done(problem.solve())
            thread = None
        else:
            task = self._solver.submit(problem.solve)
            thread = timer.concurrent(OPTIMIZER_THREAD)
        self.running = RunningOptimization(task, num_nodes, num_submaps, thread)

    def take(self, timer: StageTimer | NullTimer) -> tuple[OptimizationResult, int, int] | None:
        """The result of the optimization started, waiting for it, with the nodes and submaps it had; None when
        none runs."""
        running, self.running = self.running, None
        if running is None:
            return None
        with timer.stage("optimization wait"):
            result, ns = running.task.result()
        if running.thread is not None:  # computed inline, it was timed where it ran
            running.thread.add("optimization", ns)
        return result, running.num_nodes, running.num_submaps

    def close(self) -> None:
        """Stop the solver's thread (an optimization running is finished first)."""
        if self._solver is not None:
            self._solver.shutdown()
            self._solver = None
