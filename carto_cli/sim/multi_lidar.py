"""A robot with several 2D lidars (front and back, say), each on its own topic, in its own frame, at its own rate.

Each lidar is simulated along the same trajectory as a ``Simulation`` of its own (its own seed for its noise), its
scans renamed to its topic and frame; odometry and IMU come from the first. The recording holds every scan in time
order and one static transform per lidar, base_link to its frame, as a robot's URDF publishes them.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

from carto_cli.core.records import Scan, Transform, yaw_quaternion
from carto_cli.io.sources.memory import MemoryRecording
from carto_cli.sim.lidar import Lidar
from carto_cli.sim.recording import IMU_TOPIC, ODOM_TOPIC, SCAN_TOPIC, Simulation, simulate
from carto_cli.sim.trajectory import Trajectory
from carto_cli.sim.world import World

__all__ = ["MountedLidar", "several_lidars"]


@dataclass(frozen=True)
class MountedLidar:
    """One lidar on the robot: its model, where it sits (x, y, yaw in base_link), its topic, frame and rate."""

    lidar: Lidar
    pose: tuple[float, float, float]
    topic: str
    frame: str
    rate: float = 10.0


def several_lidars(world: World, trajectory: Trajectory, mounts: Sequence[MountedLidar], *, seed: int = 0,
                   duration: float | None = None, name: str = "several-lidars") -> tuple[MemoryRecording,
                                                                                        list[Simulation]]:
    """The recording of ``trajectory`` in ``world`` by every lidar of ``mounts``, and each lidar's simulation (its
    scan times, true poses, the truth: ``Simulation.ground_truth``)."""
    if not mounts:
        raise ValueError("give at least one lidar")
    if len({m.topic for m in mounts}) != len(mounts) or len({m.frame for m in mounts}) != len(mounts):
        raise ValueError("every lidar needs a topic and a frame of its own")
    sims = [simulate(world, trajectory, duration=duration, scan_rate=m.rate, lidar=m.lidar, laser_pose=m.pose,
                     seed=seed + 1000 * k, odom_rate=50.0 if k == 0 else 0.0, imu_rate=100.0 if k == 0 else 0.0)
            for k, m in enumerate(mounts)]
    records = []
    for k, (sim, mount) in enumerate(zip(sims, mounts)):
        topics = [SCAN_TOPIC, ODOM_TOPIC, IMU_TOPIC] if k == 0 else [SCAN_TOPIC]
        for r in sim.records(topics):
            records.append(dataclasses.replace(r, topic=mount.topic, frame=mount.frame) if isinstance(r, Scan) else r)
    statics = [Transform("base_link", m.frame, (float(m.pose[0]), float(m.pose[1]), 0.0),
                         yaw_quaternion(float(m.pose[2]))) for m in mounts]
    return MemoryRecording(records, statics, name=name), sims
