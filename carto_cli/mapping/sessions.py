"""Several recordings in one pose graph (sessions): which trajectories loop closures link, how firmly, and where
each trajectory's frame lies in the first one's.

A later session starts in a frame of its own (its odometry restarted, its start unknown) and is placed in the map
only by loop closures found by whole-map search (``constraint_builder``: trajectories not yet linked are searched
against every submap). Each closure between two trajectories implies where the one's frame lies in the other's;
their agreement is the link's uncertainty. A session linked to nothing has no place in the map: it is reported,
never drawn at the origin (``pipeline``). Reads the graph; changes nothing.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from carto_cli.core import transform
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.slam import scan_poses

__all__ = ["Session", "SessionLink", "SessionScans", "linked_to", "session_links", "trajectories"]


@dataclass(frozen=True, slots=True, eq=False)
class SessionScans:
    """A session's posed scans as its mapping left them, from which their map poses follow after any later joint
    optimization: each scan's local pose and the graph node (of the same trajectory) at or before it. From a saved
    map that kept only its nodes, the nodes themselves."""

    trajectory: int
    name: str  # the recording's
    times: np.ndarray  # (S,)
    local_poses: np.ndarray  # (S, 3)
    nodes: np.ndarray  # (S,) graph node ids

    def poses(self, graph: PoseGraph) -> np.ndarray:
        """(S, 3) the scans in the map frame: each carried by the correction of its node."""
        return scan_poses(graph, self.local_poses, self.nodes)


@dataclass(frozen=True, slots=True, eq=False)
class Session:
    """One recording of a map of several: its trajectory in the map frame after the joint optimization, and
    whether loop closures link it to the first recording's (an unlinked one has no place in the map)."""

    trajectory: int
    name: str
    times: np.ndarray
    poses: np.ndarray
    linked: bool


@dataclass(frozen=True, slots=True)
class SessionLink:
    """Loop closures between trajectories ``a`` < ``b``: how many, and the pose of ``b``'s frame in ``a``'s (x, y,
    yaw) as their mean, with the spread (standard deviation) of what each closure alone says, taken where the
    closures are (a frame's origin can lie far from them, where a tenth of a degree moves it by decimetres)."""

    a: int
    b: int
    closures: int
    relative_pose: np.ndarray  # (3,)
    spread: np.ndarray  # (3,) m, m, rad

    def to_dict(self) -> dict:
        x, y, yaw = (float(v) for v in self.relative_pose)
        sx, sy, syaw = (float(v) for v in self.spread)
        return {"trajectories": [self.a, self.b], "loop_closures": self.closures,
                "relative_pose": {"x": x, "y": y, "yaw": yaw},
                "spread": {"x": sx, "y": sy, "yaw": syaw}}

    def describe(self) -> str:
        x, y, yaw = (float(v) for v in self.relative_pose)
        sx, sy, syaw = (float(v) for v in self.spread)
        return (f"trajectories {self.a} and {self.b}: {self.closures} loop closures, {self.b}'s frame at "
                f"{x:.2f}, {y:.2f} m, {math.degrees(yaw):.1f} deg in {self.a}'s "
                f"(spread {math.hypot(sx, sy):.3f} m, {math.degrees(syaw):.2f} deg)")


def trajectories(graph: PoseGraph) -> list[int]:
    """The trajectory ids the graph holds nodes of, in order."""
    return sorted(set(graph.node_trajectory))


def session_links(graph: PoseGraph) -> list[SessionLink]:
    """Every pair of trajectories joined by at least one loop closure, by ``(a, b)``."""
    cs = graph.constraints
    if not len(cs):
        return []
    loops = np.flatnonzero(cs.is_loop_closure)
    node_traj = np.asarray(graph.node_trajectory, dtype=np.int64)
    estimates: dict[tuple[int, int], list[np.ndarray]] = {}
    places: dict[tuple[int, int], list[np.ndarray]] = {}  # where each closure is, in b's frame
    for i in loops.tolist():
        node, index = int(cs.node[i]), int(cs.submap[i])
        entry = graph.submaps[index]
        a, b = entry.trajectory, int(node_traj[node])
        if a == b:
            continue
        # Where the closure puts the node in the map, carried back through the node's own local pose: the frame of
        # the node's trajectory as this closure alone places it; then seen from the submap trajectory's frame.
        node_global = transform.compose(entry.global_pose, cs.relative[i])
        frame_b = transform.compose(node_global, transform.inverse(graph.local_poses[node]))
        relative = transform.compose(transform.inverse(entry.local_to_global()), frame_b)
        place = graph.local_poses[node][:2]
        if a > b:
            a, b, relative = b, a, transform.inverse(relative)
            place = entry.local_pose[:2]
        estimates.setdefault((a, b), []).append(np.asarray(relative, dtype=np.float64))
        places.setdefault((a, b), []).append(np.asarray(place, dtype=np.float64))
    links = []
    for (a, b), poses in sorted(estimates.items()):
        p = np.array(poses)
        yaw = math.atan2(float(np.sin(p[:, 2]).mean()), float(np.cos(p[:, 2]).mean()))
        spread_yaw = float(np.sqrt(np.mean(transform.wrap_angle(p[:, 2] - yaw) ** 2)))
        mean = np.array([p[:, 0].mean(), p[:, 1].mean(), yaw])
        centre = np.mean(places[(a, b)], axis=0)
        at_centre = np.array([transform.apply(pose, centre.reshape(1, 2))[0] for pose in p])
        spread = np.array([at_centre[:, 0].std(), at_centre[:, 1].std(), spread_yaw])
        links.append(SessionLink(a, b, len(poses), mean, spread))
    return links


def linked_to(first: int, links: list[SessionLink]) -> set[int]:
    """The trajectories joined to ``first`` through links, ``first`` included."""
    reached = {first}
    grew = True
    while grew:
        grew = False
        for link in links:
            if (link.a in reached) != (link.b in reached):
                reached.update((link.a, link.b))
                grew = True
    return reached
