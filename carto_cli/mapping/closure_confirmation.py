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
           "LINK_CHECKS", "LINK_FOLLOWED", "LINK_PLACES", "LINK_SEPARATION", "ClosureConfirmation", "LinkConfirmation",
           "PendingClosure"]

# Two closures to one submap agree when they place their nodes, at most this many nodes apart, within this of
# local SLAM's relative pose (local SLAM is good to centimetres over a few nodes).
CONFIRM_MAX_NODES = 10
CONFIRM_MAX_TRANSLATION = 0.2  # m
CONFIRM_MAX_ROTATION = math.radians(2.0)
CONFIRM_NEIGHBOURS = 2  # nodes searched at once to confirm a new closure
# Two trajectories are linked once closures from this many places agree where the one lies in the other: places
# at least LINK_SEPARATION apart in the later trajectory. A neighbouring node's closure is nearly the same scan
# matched again, no evidence of its own, even into another submap: every scan lies in two overlapping submaps, and
# counting those as two places linked a session of a ring corridor turned half round from its first two nodes
# (bench/sessions.py sim, 5 sessions)
LINK_PLACES = 2
LINK_SEPARATION = 2.0  # m
LINK_CHECKS = 4  # nodes of the session searched where a waiting closure puts them (pose_graph._check_link)
LINK_FOLLOWED = 3  # waiting placements a pair, each checked again at the session's next key nodes


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


@dataclass(frozen=True, slots=True, eq=False)
class _Offered:
    closure: LoopClosure
    frame: np.ndarray  # where the closure puts the later trajectory's frame in the earlier one's
    place: np.ndarray  # the closure's place, in the later trajectory's frame


class LinkConfirmation:
    """The same rule for the first closures between two trajectories not yet linked (two recordings, each in a frame
    of its own): a whole-map search matches one scan anywhere, and a building has look-alike places (a ring
    corridor, rooms in a row), where one false closure would put a whole session in the wrong place. Each closure
    says where the one trajectory's frame lies in the other's, from local poses alone; the two are linked when
    closures from ``LINK_PLACES`` places agree on it (within the chain rule's tolerance, at the newest closure's
    place), and only then go into the graph."""

    def __init__(self) -> None:
        self.pending: dict[tuple[int, int], list[_Offered]] = {}  # (earlier, later) trajectory → closures offered

    def offer(self, lc: LoopClosure, submap_trajectory: int, submap_local_pose: np.ndarray, node_trajectory: int,
              node_local_pose: np.ndarray) -> tuple[list[LoopClosure], np.ndarray | None]:
        """Keep ``lc`` (between two trajectories not yet linked); the closures that link them now, ``lc`` and the
        earlier ones that agree with it, in the order offered, with where ``lc`` puts the later trajectory's frame
        in the earlier's; ([], None) while they wait."""
        # The node's pose in the submap's frame carried into both trajectories' frames: the later trajectory's
        # frame in the earlier's, from local SLAM's poses only (no optimization has seen the pair yet)
        frame = transform.compose(transform.compose(submap_local_pose, lc.relative_pose),
                                  transform.inverse(node_local_pose))
        place = np.asarray(node_local_pose, dtype=np.float64)[:2]
        pair = (submap_trajectory, node_trajectory)
        if submap_trajectory > node_trajectory:
            pair, frame = (node_trajectory, submap_trajectory), transform.inverse(frame)
            place = np.asarray(submap_local_pose, dtype=np.float64)[:2]
        offered = self.pending.setdefault(pair, [])
        new = _Offered(lc, np.asarray(frame, dtype=np.float64), place)
        agreeing = [o for o in offered if _same_frame(o, new)]
        offered.append(new)
        if _places(agreeing + [new]) < LINK_PLACES:
            return [], None
        del self.pending[pair]
        return [o.closure for o in agreeing] + [lc], new.frame

    def waiting(self, trajectory: int) -> list[LoopClosure]:
        """The newest closure of each placement still waiting that involves ``trajectory`` (up to LINK_FOLLOWED
        placements a pair, newest first): what the pose graph checks again at each new node of the trajectory,
        where that placement puts it, until one is confirmed from a second place or refuted."""
        out = []
        for pair, offered in self.pending.items():
            if trajectory not in pair:
                continue
            distinct: list[_Offered] = []
            for o in reversed(offered):
                if len(distinct) < LINK_FOLLOWED and not any(_same_frame(d, o) for d in distinct):
                    distinct.append(o)
            out += [d.closure for d in distinct]
        return out


def _places(offered: list[_Offered]) -> int:
    """How many independent places ``offered`` come from: greedily, each one LINK_SEPARATION from every place
    counted before it."""
    counted: list[_Offered] = []
    for o in offered:
        if all(math.hypot(*(o.place - c.place)) >= LINK_SEPARATION for c in counted):
            counted.append(o)
    return len(counted)


def _same_frame(a: _Offered, b: _Offered) -> bool:
    """Whether ``a``'s and ``b``'s frames put ``b``'s place at the same spot, heading alike."""
    pa = transform.apply(a.frame, b.place.reshape(1, 2))[0]
    pb = transform.apply(b.frame, b.place.reshape(1, 2))[0]
    turn = float(transform.wrap_angle(np.array([a.frame[2] - b.frame[2]]))[0])
    return math.hypot(pa[0] - pb[0], pa[1] - pb[1]) <= CONFIRM_MAX_TRANSLATION and abs(turn) <= CONFIRM_MAX_ROTATION
