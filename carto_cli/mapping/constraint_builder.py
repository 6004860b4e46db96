"""Loop-closure search: which node–submap pairs to try, branch and bound, refinement, acceptance.

Cartographer's ConstraintBuilder2D, inline rather than on a thread pool: a pair is
searched when the node is within ``max_constraint_distance`` of the submap and the
submap's fixed-ratio sampler fires; nodes of a trajectory not yet linked to the
submap's one get a whole-submap search at ``global_sampling_ratio``. The fast
matcher's pose is refined by least squares, then kept only if the refined pose
still scores (geometric check) and stayed near the fast matcher's answer
(consistency check: a refinement that wanders has slid along a corridor).

As Cartographer's ``MaybeAddConstraint``, it never sees the pose graph: the graph hands
it the node and the submap to try (:class:`NodeData`, :class:`SubmapData`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from carto_cli.core import transform
from carto_cli.core.timing import NullTimer
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.matching import branch_and_bound, least_squares
from carto_cli.matching.precomputation import PrecomputationGridStack
from carto_cli.matching.ray_consistency import see_through_fraction
from carto_cli.matching.scoring import score_at
from carto_cli.options import Options

# A refinement that moves the fast matcher's pose by more than this is not trusted.
MAX_REFINEMENT_TRANSLATION = 0.3  # m
MAX_REFINEMENT_ROTATION = math.radians(5.0)


class FixedRatioSampler:
    """Fires on a fixed share of pulses, spread evenly (Cartographer's FixedRatioSampler)."""

    def __init__(self, ratio: float):
        self.ratio = float(ratio)
        self.pulses = 0
        self.samples = 0

    def pulse(self) -> bool:
        self.pulses += 1
        if self.samples < self.ratio * self.pulses:
            self.samples += 1
            return True
        return False


@dataclass(frozen=True, slots=True)
class NodeData:
    """What a search needs of a node: its id, trajectory, pose in the map frame and loop-closure points."""

    index: int
    trajectory: int
    global_pose: np.ndarray  # (3,)
    points: np.ndarray  # (n, 2) in the tracking frame


@dataclass(frozen=True, slots=True)
class SubmapData:
    """What a search needs of a finished submap: its id in the pose graph, trajectory, grid, and its
    pose in its trajectory's local frame and in the map frame."""

    index: int
    trajectory: int
    grid: ProbabilityGrid
    local_pose: np.ndarray  # (3,)
    global_pose: np.ndarray  # (3,)


@dataclass(frozen=True)
class LoopClosure:
    node: int
    submap: int
    relative_pose: np.ndarray  # node in the submap frame
    score: float
    global_search: bool


@dataclass
class ConstraintBuilderStats:
    candidates: int = 0
    searched: int = 0
    global_searches: int = 0
    found: int = 0
    rejected_refinement: int = 0
    rejected_see_through: int = 0
    accepted: int = 0


class ConstraintBuilder:
    def __init__(self, options: Options, timer=None, seed: int = 0):
        self.cb = options.pose_graph.constraint_builder
        self.global_sampling_ratio = options.pose_graph.global_sampling_ratio
        self.timer = timer or NullTimer()
        self._samplers: dict[int, FixedRatioSampler] = {}
        self._global_samplers: dict[int, FixedRatioSampler] = {}
        self._stacks: dict[int, PrecomputationGridStack] = {}
        self.stats = ConstraintBuilderStats()
        self.connected: set[frozenset] = set()  # trajectory pairs linked by a loop closure

    def stack(self, index: int, grid) -> PrecomputationGridStack:
        """Precomputation grids are built once per finished submap and kept."""
        stack = self._stacks.get(index)
        if stack is None:
            with self.timer.stage("precomputation"):
                stack = PrecomputationGridStack(grid, self.cb.fast_correlative_scan_matcher.branch_and_bound_depth)
            self._stacks[index] = stack
        return stack

    @property
    def memory_bytes(self) -> int:
        return sum(s.memory_bytes for s in self._stacks.values())

    def maybe_add(self, node: NodeData, submap: SubmapData) -> LoopClosure | None:
        """Search ``node`` in ``submap`` if the candidate rules pick the pair; the loop closure found, or None."""
        linked = node.trajectory == submap.trajectory or \
            frozenset((node.trajectory, submap.trajectory)) in self.connected
        with self.timer.stage("candidate selection"):
            self.stats.candidates += 1
            if linked:
                distance = float(np.hypot(*(node.global_pose[:2] - submap.global_pose[:2])))
                if distance > self.cb.max_constraint_distance:
                    return None
                sampler = self._samplers.setdefault(submap.index, FixedRatioSampler(self.cb.sampling_ratio))
                if not sampler.pulse():
                    return None
            else:
                sampler = self._global_samplers.setdefault(submap.index,
                                                           FixedRatioSampler(self.global_sampling_ratio))
                if not sampler.pulse():
                    return None
        return self.search(node, submap, global_search=not linked)

    def search(self, node: NodeData, submap: SubmapData, global_search: bool = False) -> LoopClosure | None:
        """Match ``node`` against ``submap`` (near its current pose, or the whole submap) and check the result."""
        grid = submap.grid
        points = node.points
        if len(points) == 0:
            return None
        stack = self.stack(submap.index, grid)
        fc = self.cb.fast_correlative_scan_matcher
        self.stats.searched += 1
        with self.timer.stage("branch and bound"):
            if global_search:
                self.stats.global_searches += 1
                result = branch_and_bound.match_full_submap(stack, points,
                                                            min_score=self.cb.global_localization_min_score)
            else:
                # Where the graph currently believes the node is, in the submap's grid frame.
                estimate = transform.compose(
                    submap.local_pose,
                    transform.compose(transform.inverse(submap.global_pose), node.global_pose))
                matcher = branch_and_bound.match_multilevel if fc.multilevel else branch_and_bound.match
                result = matcher(stack, points, estimate,
                                 linear_search_window=fc.linear_search_window,
                                 angular_search_window=fc.angular_search_window,
                                 min_score=self.cb.min_score)
        if not result.found:
            return None
        self.stats.found += 1
        with self.timer.stage("refinement"):
            c = self.cb.ceres_scan_matcher
            ls = least_squares.match(grid, points, result.pose, target_translation=result.pose[:2],
                                     occupied_space_weight=c.occupied_space_weight,
                                     translation_weight=c.translation_weight, rotation_weight=c.rotation_weight,
                                     max_num_iterations=c.ceres_solver_options.max_num_iterations)
            moved = transform.relative(result.pose, ls.pose)
            min_score = self.cb.global_localization_min_score if global_search else self.cb.min_score
            if (np.hypot(moved[0], moved[1]) > MAX_REFINEMENT_TRANSLATION
                    or abs(moved[2]) > MAX_REFINEMENT_ROTATION
                    or score_at(grid, points, ls.pose) < min_score):
                self.stats.rejected_refinement += 1
                return None
        if self.cb.max_see_through < 1.0:
            # Endpoints on walls are all the score sees; at an aliased pose some rays also cross walls the
            # submap knows (matching/ray_consistency.py), which a right match's rays do not.
            with self.timer.stage("free-space check"):
                if see_through_fraction(grid, points, ls.pose) > self.cb.max_see_through:
                    self.stats.rejected_see_through += 1
                    return None
        self.stats.accepted += 1
        if global_search:
            self.connected.add(frozenset((node.trajectory, submap.trajectory)))
        relative = transform.compose(transform.inverse(submap.local_pose), ls.pose)
        return LoopClosure(node.index, submap.index, relative, result.score, global_search)
