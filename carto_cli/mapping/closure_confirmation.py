"""Karto's chain rule for loop closures (``pose_graph.constraint_builder.confirm_loop_closures``): a false match
rarely repeats consistently for a neighbouring node, a true revisit does. A closure waits until a closure of
another node of the same trajectory, near it along the trajectory, places both nodes in the submap as local SLAM
places them relative to each other; then both go into the graph.

This object keeps the closures found per submap and says which agree; the pose graph searches the neighbours and
inserts the constraints. It sees the nodes' local poses and trajectories it is handed, never the graph.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from carto_cli.core import transform
from carto_cli.mapping.constraint_builder import LoopClosure

__all__ = ["CONFIRM_MAX_NODES", "CONFIRM_MAX_ROTATION", "CONFIRM_MAX_TRANSLATION", "CONFIRM_NEIGHBOURS",
           "ClosureConfirmation", "PendingClosure"]

# Two closures to one submap agree when they place their nodes, at most this many nodes apart, within this of
# local SLAM's relative pose (local SLAM is good to centimetres over a few nodes).
CONFIRM_MAX_NODES = 10
CONFIRM_MAX_TRANSLATION = 0.2  # m
CONFIRM_MAX_ROTATION = math.radians(2.0)
CONFIRM_NEIGHBOURS = 2  # nodes searched at once to confirm a new closure


@dataclass
class PendingClosure:
    """A loop closure found, kept per submap: ``inserted`` once a closure of a neighbouring node agreed with it and
    both went into the graph."""

    node: int
    relative: np.ndarray  # the node's pose in the submap's frame
    inserted: bool


class ClosureConfirmation:
    def __init__(self) -> None:
        self.pending: dict[int, list[PendingClosure]] = {}  # per submap, every closure found there
        self.unconfirmed = 0  # closures still waiting for a neighbour to agree

    def agreeing(self, lc: LoopClosure, local_poses: np.ndarray, trajectories: Sequence[int]) -> list[PendingClosure]:
        """The closures kept for ``lc``'s submap that agree with it."""
        return [entry for entry in self.pending.setdefault(lc.submap, [])
                if _agree(entry.node, entry.relative, lc.node, lc.relative_pose, local_poses, trajectories)]

    def neighbours(self, node: int, submap: int, submap_nodes: Sequence[int], trajectories: Sequence[int],
                   node_points: Sequence[np.ndarray]) -> list[int]:
        """Up to CONFIRM_NEIGHBOURS nodes nearest to ``node`` along its trajectory, not in ``submap`` (whose nodes
        are ``submap_nodes``) and without a closure to it already (a second search would only add the same
        constraint twice): the samplers search only a share of the pairs, so the neighbours that could confirm a
        closure may never be tried otherwise."""
        members = set(submap_nodes)
        members.update(entry.node for entry in self.pending.get(submap, ()))
        trajectory = trajectories[node]
        out = []
        for step in range(1, CONFIRM_MAX_NODES + 1):
            for other in (node - step, node + step):
                if (0 <= other < len(trajectories) and other not in members and trajectories[other] == trajectory
                        and len(node_points[other])):
                    out.append(other)
            if len(out) >= CONFIRM_NEIGHBOURS:
                break
        return out[:CONFIRM_NEIGHBOURS]

    def keep(self, lc: LoopClosure, agreeing: list[PendingClosure]) -> list[PendingClosure]:
        """Keep ``lc`` (confirmed when any closure agrees with it); the agreeing closures that go into the graph
        now with it, marked inserted."""
        newly = [entry for entry in agreeing if not entry.inserted]
        for entry in newly:
            entry.inserted = True
            self.unconfirmed -= 1
        self.pending.setdefault(lc.submap, []).append(PendingClosure(lc.node, lc.relative_pose, bool(agreeing)))
        self.unconfirmed += 0 if agreeing else 1
        return newly


def _agree(m: int, rel_m: np.ndarray, n: int, rel_n: np.ndarray, local_poses: np.ndarray,
           trajectories: Sequence[int]) -> bool:
    if m == n or trajectories[m] != trajectories[n] or abs(m - n) > CONFIRM_MAX_NODES:
        return False
    by_local_slam = transform.relative(local_poses[m], local_poses[n])
    by_closures = transform.relative(rel_m, rel_n)
    gap = transform.relative(by_local_slam, by_closures)
    return math.hypot(gap[0], gap[1]) <= CONFIRM_MAX_TRANSLATION and abs(gap[2]) <= CONFIRM_MAX_ROTATION
