"""One recording cut into several sessions of the same building, each with its odometry restarted at zero, as a
robot's after a reboot: recordings that share no frame, for multi-session mapping to place (tests, bench)."""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from carto_cli.core import transform
from carto_cli.core.records import Odometry, Record
from carto_cli.io.recording import Recording
from carto_cli.io.sources.memory import MemoryRecording
from carto_cli.sim.lidar import Lidar
from carto_cli.sim.recording import simulate
from carto_cli.sim.trajectory import Limits, Trajectory
from carto_cli.sim.world import World

__all__ = ["cut_sessions", "route_sessions"]


def route_sessions(world: World | Sequence[World], n: int, *, lidar: Lidar = Lidar(), scan_rate: float = 10.0,
                   limits: Limits = Limits()) -> tuple[list[MemoryRecording], list[np.ndarray]]:
    """``n`` recordings of ``world`` driven once around its closed route each, session k from the k/n point of the
    route and every other one the other way round, each with its own seed, times 1000 s apart and odometry
    starting at zero: the recordings, and each one's reference (m, 4) t, x, y, yaw in the world. ``world`` may
    be one world a session (a building that changes between sessions: ``sim.world.altered``), driven along the
    first one's route."""
    worlds = [world] * n if isinstance(world, World) else list(world)
    if len(worlds) != n:
        raise ValueError(f"{len(worlds)} worlds for {n} sessions")
    world = worlds[0]
    if world.route is None or not world.closed:
        raise ValueError(f"world '{world.name}' has no closed route")
    route = np.asarray(world.route, dtype=np.float64)
    recordings, references = [], []
    for k in range(n):
        world = worlds[k]
        turned = np.roll(route, -int(round(k * len(route) / n)), axis=0)
        if k % 2:
            turned = turned[::-1]
        path = Trajectory.follow(turned, closed=True, laps=1, limits=limits)
        sim = simulate(world, path, lidar=lidar, scan_rate=scan_rate, seed=k, start_time=1000.0 * (k + 1))
        recordings.append(cut_sessions(sim.recording(), [])[0])
        references.append(sim.ground_truth)
    return recordings, references


def cut_sessions(recording: Recording, cuts: Sequence[float]) -> list[MemoryRecording]:
    """``recording``'s records cut at the times ``cuts`` (increasing): len(cuts) + 1 recordings in memory, each
    one's odometry restarted at (0, 0, 0) at its first sample, the static transforms kept."""
    edges = [float("-inf"), *(float(c) for c in cuts), float("inf")]
    parts: list[list[Record]] = [[] for _ in range(len(edges) - 1)]
    topics = [t.name for t in recording.topics()]
    k = 0
    for record in recording.records(topics):
        while record.time >= edges[k + 1]:
            k += 1
        parts[k].append(record)
    name = recording.path.name
    return [MemoryRecording(_restarted(part), recording.static_transforms(), name=f"{name}.part{i}")
            for i, part in enumerate(parts)]


def _restarted(records: list[Record]) -> list[Record]:
    start = next((r for r in records if isinstance(r, Odometry)), None)
    if start is None:
        return records
    origin = transform.inverse((start.x, start.y, start.yaw))
    out: list[Record] = []
    for r in records:
        if isinstance(r, Odometry):
            x, y, yaw = (float(v) for v in transform.compose(origin, (r.x, r.y, r.yaw)))
            r = dataclasses.replace(r, x=x, y=y, yaw=yaw)
        out.append(r)
    return out
