"""A map of several sessions that shows the building as last seen, and whose state does not grow without bound
when the same building is mapped again and again (lifelong mapping).

Run on the pose graph after the last session's final optimization, as :class:`SessionPolicy` says: ``last-seen``
(the default) draws the newest sure evidence; ``lifelong`` also trims what later sessions superseded; ``fuse``
averages every session alike, as a map of one session does. Trimming is asked for, never the default: it deletes
what only an earlier session saw (dense intel cut in two halves: every submap of the first half superseded at
``SUPERSEDED``, 12 % of the map's known cells gone with them), which a user mapping a static building once more
wants kept, and a user mapping it again and again wants bounded.

- **Supersession and trimming.** An earlier session's submap is *superseded* when later sessions know, with
  confidence, most of the cells it knows with confidence (``SUPERSEDED``). Superseded submaps leave the state,
  with their constraints and with the nodes left in no submap, as Cartographer's pure-localization trimmer and
  slam_toolbox's lifelong mode drop what the newer data replaces. The newest session is never trimmed, nor is a
  session linked to none (it is no evidence about this map). A session left in pieces that no loop closure ties
  to the rest any more gets back the trimmed submaps that carried its closures, one at a time, until it is tied.
- **Last seen wins.** The image is assembled from the submaps kept, one layer a session: a cell takes the newest
  session that knows it with confidence (``SURE``); earlier sessions fill only where later ones saw nothing sure,
  and a cell no session is sure of averages them all, as a map of one session does.

Graph order is kept: the first submap kept is the one the optimizer holds, and global poses are in the map
frame already, so the first session's frame stays the map frame when its own submaps go. Knows no files.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from carto_cli.core import transform
from carto_cli.core.enums import TextEnum
from carto_cli.grid.occupancy_image import AssembledImage, known_box, logodds
from carto_cli.mapping.pose_graph_state import PoseGraphState, SubmapEntry

__all__ = ["SUPERSEDED", "SURE", "LastSeen", "SessionPolicy", "Trimmed", "last_seen", "superseded"]


class SessionPolicy(TextEnum):
    """How a map of several sessions weighs them."""

    FUSE = "fuse"  # every session's evidence averaged alike
    LAST_SEEN = "last-seen"  # the newest session sure of a cell draws it; nothing removed
    LIFELONG = "lifelong"  # last seen, and submaps later sessions superseded trimmed from the state

# A cell is known with confidence when its log-odds hold at least one hit's worth of evidence (hit probability
# 0.55), or about five misses' (0.49 each): a single grazing ray does not count as having seen a cell.
SURE = math.log(0.55 / 0.45)
# A submap goes when later sessions surely know this share of its sure cells. What it alone knows goes from the
# image with it; but another drive of the same route never sees a submap's fringe (the far ends of its rays, walls
# at a grazing angle) alike: one later lap of the loop building knows 77-98 % of an earlier lap's submaps, two laps
# 99 %, a second session of a building changed in three places 92-99 %. At 0.9 each session's state keeps the one
# before it almost whole (map.carto 1.9x one session's after 10); at 0.75 it stays at 1.0x (bench/lifelong.py).
SUPERSEDED = 0.75


@dataclass(frozen=True, slots=True)
class Trimmed:
    """What trimming took from one session: ``submaps`` and ``nodes`` out of ``of_submaps`` and ``of_nodes``, and
    the later sessions whose observations superseded them (the newest to see each of their cells)."""

    trajectory: int
    submaps: int
    nodes: int
    of_submaps: int
    of_nodes: int
    superseded_by: tuple[int, ...]

    def to_dict(self) -> dict:
        return {"submaps": self.submaps, "nodes": self.nodes, "of_submaps": self.of_submaps,
                "of_nodes": self.of_nodes, "superseded_by": list(self.superseded_by)}

    def describe(self) -> str:
        by = ", ".join(str(t) for t in self.superseded_by)
        return (f"{self.submaps} of {self.of_submaps} submaps, {self.nodes} of {self.of_nodes} nodes of trajectory "
                f"{self.trajectory} (superseded by {by})")


@dataclass(frozen=True, eq=False)
class LastSeen:
    """The state with what later sessions superseded trimmed, its image as last seen, and what was trimmed (one
    entry per session that lost anything)."""

    state: PoseGraphState
    image: AssembledImage
    trimmed: tuple[Trimmed, ...]


def last_seen(state: PoseGraphState, sessions: Sequence[int], *, trim: bool = True, sure: float = SURE,
              threshold: float | None = None) -> LastSeen:
    """``state`` (with ``trim``) trimmed of the submaps of ``sessions`` (trajectory ids, oldest first: the linked
    ones) that later ones supersede, and its image with the newest sure evidence winning. Submaps of other
    trajectories are kept and drawn with none (a session linked to nothing has no place in the map)."""
    order = {t: k for k, t in enumerate(sessions)}
    drop = np.zeros(len(state.submaps), dtype=bool)
    newest: list[dict] = [{} for _ in state.submaps]
    if trim:
        threshold = SUPERSEDED if threshold is None else threshold  # read here: bench/lifelong.py tries others
        fraction, newest = superseded(state, order, sure)
        drop = (fraction >= threshold) & np.array([e.trajectory in order and order[e.trajectory] < len(order) - 1
                                                   for e in state.submaps], dtype=bool)
        drop = _keep_linked(state, drop, order)
    trimmed_state = state.without_submaps(drop)
    kept = [e for e in trimmed_state.submaps if e.trajectory in order]
    image = AssembledImage([e.submap.grid for e in kept], [e.local_to_global() for e in kept],
                           layers=[order[e.trajectory] for e in kept], sure=sure)
    return LastSeen(trimmed_state, image, _report(state, trimmed_state, drop, newest))


def superseded(state: PoseGraphState, order: dict[int, int], sure: float = SURE) -> tuple[np.ndarray, list[dict]]:
    """For every submap: the share of its sure cells that a later session (by ``order``: trajectory -> rank) also
    knows surely, and how many of them each later trajectory is the newest to know. Submaps of trajectories not in
    ``order`` get 0."""
    entries = state.submaps
    boxes = [known_box(e.submap.grid, e.local_to_global()) for e in entries]
    fraction = np.zeros(len(entries))
    newest: list[dict] = [{} for _ in entries]
    for i, entry in enumerate(entries):
        rank, box = order.get(entry.trajectory), boxes[i]
        if rank is None or box is None:
            continue
        points = _sure_cells(entry, sure)
        if not len(points):
            continue
        seen_by = np.full(len(points), -1, np.int64)
        for j, later in enumerate(entries):
            other, later_box = order.get(later.trajectory), boxes[j]
            if other is None or other <= rank or later_box is None or not _overlap(box, later_box):
                continue
            hit = _sure_at(later, points, sure)
            seen_by[hit] = np.maximum(seen_by[hit], other)
        seen = seen_by >= 0
        fraction[i] = np.count_nonzero(seen) / len(points)
        ranks, counts = np.unique(seen_by[seen], return_counts=True)
        by_rank = {k: t for t, k in order.items()}
        newest[i] = {by_rank[int(r)]: int(c) for r, c in zip(ranks, counts)}
    return fraction, newest


def _overlap(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3])


def _sure_cells(entry: SubmapEntry, sure: float) -> np.ndarray:
    """(n, 2) the centres of the submap's sure cells, in the map frame."""
    grid = entry.submap.grid
    iy, ix = np.nonzero(np.abs(logodds(grid.cells)) >= sure)
    local = np.column_stack([grid.origin[0] + (ix + 0.5) * grid.resolution,
                             grid.origin[1] + (iy + 0.5) * grid.resolution])
    return transform.apply(entry.local_to_global(), local)


def _sure_at(entry: SubmapEntry, points: np.ndarray, sure: float) -> np.ndarray:
    """Which of ``points`` (map frame) fall in a sure cell of ``entry``'s grid."""
    grid = entry.submap.grid
    local = transform.apply(transform.inverse(entry.local_to_global()), points)
    ix = np.floor((local[:, 0] - grid.origin[0]) / grid.resolution).astype(np.int64)
    iy = np.floor((local[:, 1] - grid.origin[1]) / grid.resolution).astype(np.int64)
    ny, nx = grid.cells.shape
    inside = (ix >= 0) & (iy >= 0) & (ix < nx) & (iy < ny)
    out = np.zeros(len(points), bool)
    out[inside] = np.abs(logodds(grid.cells[iy[inside], ix[inside]])) >= sure
    return out


def _kept_nodes(state: PoseGraphState, drop: np.ndarray) -> np.ndarray:
    keep = np.zeros(state.num_nodes, bool)
    for entry, gone in zip(state.submaps, drop):
        if not gone:
            keep[np.asarray(entry.nodes, dtype=np.int64)] = True
    return keep


def _tied(state: PoseGraphState, drop: np.ndarray, order: dict[int, int]) -> set[int]:
    """The trajectories of ``order`` that the loop closures left after dropping ``drop`` tie to the newest."""
    cs = state.constraints
    nodes = _kept_nodes(state, drop)
    submap_traj = np.array([e.trajectory for e in state.submaps], dtype=np.int64)
    node, submap = cs.node, cs.submap
    live = cs.is_loop_closure & nodes[node] & ~drop[submap]
    a, b = state.node_trajectories[node[live]], submap_traj[submap[live]]
    pairs = {(int(x), int(y)) for x, y in zip(a.tolist(), b.tolist()) if x != y}
    reached = {max(order, key=order.__getitem__)}
    grew = True
    while grew:
        grew = False
        for x, y in pairs:
            if (x in reached) != (y in reached):
                reached.update((x, y))
                grew = True
    return reached & set(order)


def _keep_linked(state: PoseGraphState, drop: np.ndarray, order: dict[int, int]) -> np.ndarray:
    """``drop`` with trimmed submaps given back to any session whose kept part no loop closure ties to the rest
    any more: the one carrying most closures to tied trajectories first, until it is tied (an untied piece would
    stay where it is in the optimizer but is no longer known to belong to this map)."""
    drop = drop.copy()
    cs = state.constraints
    submap_traj = np.array([e.trajectory for e in state.submaps], dtype=np.int64)
    loops = np.flatnonzero(cs.is_loop_closure)
    node_of, submap_of = cs.node[loops], cs.submap[loops]
    member_node = np.concatenate([np.asarray(e.nodes, dtype=np.int64) for e in state.submaps] or [np.zeros(0, int)])
    member_submap = np.repeat(np.arange(len(state.submaps)), [len(e.nodes) for e in state.submaps])
    while True:
        tied = _tied(state, drop, order)
        nodes = _kept_nodes(state, drop)
        loose = {int(t) for t in np.unique(state.node_trajectories[nodes])} & set(order) - tied
        if not loose:
            return drop
        node_traj = state.node_trajectories[node_of]
        tied_arr = np.array(sorted(tied), dtype=np.int64)
        # A dropped submap of a loose session ties it back through closures of tied nodes into it, or of its own
        # nodes into kept submaps of tied sessions
        into = drop[submap_of] & np.isin(submap_traj[submap_of], list(loose)) & np.isin(node_traj, tied_arr) \
            & nodes[node_of]
        votes = np.bincount(submap_of[into], minlength=len(drop))
        own = np.isin(node_traj, list(loose)) & ~drop[submap_of] & np.isin(submap_traj[submap_of], tied_arr)
        per_node = np.bincount(node_of[own], minlength=state.num_nodes)
        votes = votes + np.bincount(member_submap, weights=per_node[member_node] * drop[member_submap],
                                    minlength=len(drop)).astype(np.int64)
        if not votes.any():
            return drop  # nothing would tie it: what is kept of it stays as it was
        drop[int(np.argmax(votes))] = False


def _report(before: PoseGraphState, after: PoseGraphState, drop: np.ndarray, newest: list[dict]) -> tuple[Trimmed, ...]:
    out = []
    traj = np.array([e.trajectory for e in before.submaps], dtype=np.int64)
    for t in sorted({int(v) for v in traj[drop]}):
        counts: dict[int, int] = {}
        for i in np.flatnonzero(drop & (traj == t)).tolist():
            for by, c in newest[i].items():
                counts[by] = counts.get(by, 0) + c
        nodes = int(np.count_nonzero(before.node_trajectories == t))
        left = int(np.count_nonzero(after.node_trajectories == t))
        out.append(Trimmed(t, int(np.count_nonzero(drop & (traj == t))), nodes - left,
                           int(np.count_nonzero(traj == t)), nodes, tuple(sorted(counts))))
    return tuple(out)
