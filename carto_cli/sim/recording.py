"""A simulated recording: scans, odometry and IMU along a trajectory, with exact ground truth.

``simulate`` fixes every sample time and draws the odometry and IMU up front
(small arrays); scans are ray cast lazily in chunks while ``records`` streams,
so a long run costs memory only for its poses. Each stream has its own random
generator spawned from ``seed``: the result is the same for a seed whatever
topics are read and however often.
"""
from __future__ import annotations

import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carto_cli.core.errors import TopicError
from carto_cli.core.records import Imu, Odometry, Record, Scan, Transform, beam_angles, yaw_quaternion
from carto_cli.core.transform import wrap_angle
from carto_cli.io.recording import ReadOptions, Recording, TopicInfo
from carto_cli.sim.lidar import Lidar, cast
from carto_cli.sim.movers import Mover, segments_at
from carto_cli.sim.odometry import ImuModel, OdometryModel, gyro_and_accel, wheel_odometry
from carto_cli.sim.trajectory import Trajectory
from carto_cli.sim.world import World

SCAN_TOPIC, ODOM_TOPIC, IMU_TOPIC = "/scan", "/odom", "/imu"
MSGTYPES = {
    SCAN_TOPIC: "sensor_msgs/msg/LaserScan",
    ODOM_TOPIC: "nav_msgs/msg/Odometry",
    IMU_TOPIC: "sensor_msgs/msg/Imu",
}
# At equal times, inertial and odometry data come before the scan that they help place.
_PRIORITY = {IMU_TOPIC: 0, ODOM_TOPIC: 1, SCAN_TOPIC: 2}
_CHUNK = 256  # scans ray cast per kernel call
RECORD_BLOCK = 4096  # records turned from arrays into objects at a time


def _sample_times(duration: float, rate: float) -> np.ndarray:
    """k / rate for every k with k / rate in [0, duration); none when rate is 0."""
    if rate <= 0:
        return np.zeros(0)
    n = int(math.ceil(duration * rate - 1e-9))
    return np.arange(n) / rate


def compose(a: np.ndarray, b: tuple[float, float, float]) -> np.ndarray:
    """Poses (m, 3) ``a`` followed by the fixed offset ``b`` in their frames."""
    c, s = np.cos(a[:, 2]), np.sin(a[:, 2])
    return np.stack([a[:, 0] + c * b[0] - s * b[1], a[:, 1] + s * b[0] + c * b[1], wrap_angle(a[:, 2] + b[2])], axis=1)


@dataclass(eq=False)
class Simulation:
    world: World
    trajectory: Trajectory
    lidar: Lidar
    laser_pose: tuple[float, float, float]
    start_time: float
    seed: int
    scan_times: np.ndarray  # (m,) absolute
    odometry: np.ndarray  # (k, 6) t x y yaw vx wz
    imu_times: np.ndarray  # (j,)
    imu_gyro: np.ndarray  # (j, 3)
    imu_accel: np.ndarray  # (j, 3)
    movers: tuple[Mover, ...] = ()  # people, carts, doors: cast after the walls, at each scan's own time

    @property
    def ground_truth(self) -> np.ndarray:
        """(m, 4) t x y yaw of base_link in the world at every scan time."""
        p = self.trajectory.poses(self.scan_times - self.start_time)
        return np.column_stack([self.scan_times, p])

    @property
    def static_transforms(self) -> list[Transform]:
        x, y, yaw = self.laser_pose
        return [
            Transform("base_link", "laser", (float(x), float(y), 0.0), yaw_quaternion(float(yaw))),
            Transform("base_link", "imu", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0)),
        ]

    def counts(self) -> dict[str, int]:
        return {SCAN_TOPIC: len(self.scan_times), ODOM_TOPIC: len(self.odometry), IMU_TOPIC: len(self.imu_times)}

    def laser_poses(self, times: np.ndarray) -> np.ndarray:
        """(m, 3) true laser poses in the world at absolute ``times``."""
        return compose(self.trajectory.poses(np.asarray(times) - self.start_time), self.laser_pose)

    def scan_ranges(self) -> Iterator[np.ndarray]:
        """Noisy ranges of every scan, (n,) float32 each, in scan order."""
        rng = np.random.default_rng(np.random.SeedSequence(self.seed).spawn(3)[0])
        for i in range(0, len(self.scan_times), _CHUNK):
            times = self.scan_times[i:i + _CHUNK]
            poses = self.laser_poses(times)
            true = self.lidar.true_ranges(poses, self.world.segments, rng, self.world.materials)
            if self.movers:
                true = self._with_movers(true, poses, times)
            chunk = self.lidar.noisy(true, rng)
            for row in chunk:
                yield row.copy()  # a record owns its array, not a view into the chunk

    def _with_movers(self, true: np.ndarray, poses: np.ndarray, times: np.ndarray) -> np.ndarray:
        """``true`` ranges cut short where a mover there at the scan's time stands in the way."""
        angles = self.lidar.angles()
        for k, (pose, t) in enumerate(zip(poses, times)):
            seg = segments_at(self.movers, float(t - self.start_time), clear_of=pose[:2])
            if len(seg):
                true[k] = np.minimum(true[k], cast(pose, angles, seg, self.lidar.max_range))
        return true

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        """Scan / Odometry / Imu records in time order (all three topics when None)."""
        wanted = set(MSGTYPES) if topics is None else set(topics)
        unknown = wanted - set(MSGTYPES)
        if unknown:
            raise TopicError(f"no topic {', '.join(sorted(unknown))} in a simulation (topics: /scan /odom /imu)")
        streams = [(topic, times) for topic, times in (
            (SCAN_TOPIC, self.scan_times), (ODOM_TOPIC, self.odometry[:, 0]), (IMU_TOPIC, self.imu_times),
        ) if topic in wanted]
        if not streams:
            return
        times = np.concatenate([t for _, t in streams])
        topic_ix = np.concatenate([np.full(len(t), i) for i, (_, t) in enumerate(streams)])
        index = np.concatenate([np.arange(len(t)) for _, t in streams])
        priority = np.array([_PRIORITY[topic] for topic, _ in streams])[topic_ix]
        order = np.lexsort((priority, times))
        names = [topic for topic, _ in streams]
        scans = self.scan_ranges() if SCAN_TOPIC in wanted else iter(())
        angles = beam_angles(self.lidar.angle_min, self.lidar.angle_increment, self.lidar.beams)
        scan_period = 1.0 / self._rate(self.scan_times)
        lidar = self.lidar
        # Block by block, as a reader streams a file: the whole recording as Python lists (two hours of odometry and
        # IMU) would cost a bench run hundreds of MB it then charges to mapping.
        for start in range(0, len(order), RECORD_BLOCK):
            rows = order[start:start + RECORD_BLOCK]
            for s, i in zip(topic_ix[rows].tolist(), index[rows].tolist()):
                topic = names[s]
                if topic == SCAN_TOPIC:
                    yield Scan(
                        time=float(self.scan_times[i]), ranges=next(scans), angles=angles.copy(), frame="laser",
                        topic=SCAN_TOPIC, range_min=lidar.min_range, range_max=lidar.max_range,
                        angle_min=lidar.angle_min, angle_increment=lidar.angle_increment, scan_time=scan_period,
                    )
                elif topic == ODOM_TOPIC:
                    t, x, y, yaw, vx, wz = self.odometry[i].tolist()
                    yield Odometry(t, x, y, yaw, topic=ODOM_TOPIC, vx=vx, wz=wz)
                else:
                    yield Imu(float(self.imu_times[i]), self.imu_gyro[i].copy(), self.imu_accel[i].copy(),
                              topic=IMU_TOPIC)

    @staticmethod
    def _rate(times: np.ndarray) -> float:
        return 1.0 / float(times[1] - times[0]) if len(times) > 1 else 1.0

    def recording(self) -> SimulatedRecording:
        return SimulatedRecording(self)


class SimulatedRecording(Recording):
    """A ``Simulation`` behind the ``Recording`` interface, so that anything reading recordings reads it."""

    format = "sim"

    def __init__(self, simulation: Simulation, options: ReadOptions | None = None):
        name = simulation.world.name.replace(" ", "-") or "world"
        super().__init__(Path(f"simulation-{name}-seed{simulation.seed}"), options)
        self.simulation = simulation

    def topics(self) -> list[TopicInfo]:
        return [TopicInfo(t, MSGTYPES[t], n) for t, n in self.simulation.counts().items() if n > 0]

    def static_transforms(self) -> list[Transform]:
        return self.simulation.static_transforms

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        available = {t.name for t in self.topics()}
        wanted = available if topics is None else set(topics)
        unknown = wanted - available
        if unknown:
            raise TopicError(f"no topic {', '.join(sorted(unknown))} (available: {', '.join(sorted(available))})",
                             self.path)
        return self.simulation.records(wanted)


def simulate(
    world: World,
    trajectory: Trajectory,
    *,
    duration: float | None = None,
    scan_rate: float = 10.0,
    odom_rate: float = 50.0,
    imu_rate: float = 100.0,
    lidar: Lidar = Lidar(),
    odom_noise: OdometryModel = OdometryModel(),
    imu_noise: ImuModel = ImuModel(),
    seed: int = 0,
    laser_pose: tuple[float, float, float] = (0.0, 0.0, 0.0),
    start_time: float = 1000.0,
    movers: tuple[Mover, ...] = (),
) -> Simulation:
    """Simulate a robot driving ``trajectory`` in ``world`` for ``duration`` s (default: all of it), scanning with
    ``lidar`` (its beams, field of view, range and noise model).

    Sample times are ``start_time + k / rate``; a rate of 0 turns a sensor off.
    The clock starts at ``start_time`` rather than 0 so that code treating 0 as
    "no time" is caught. ``movers`` (``sim.movers``: people, carts, doors; their tracks in s since the start)
    stand in the laser's way while they are there.
    """
    duration = trajectory.duration if duration is None else float(duration)
    if duration <= 0:
        raise ValueError("duration must be positive")
    _, odom_seed, imu_seed = np.random.SeedSequence(seed).spawn(3)
    odom_t = _sample_times(duration, odom_rate)
    odom = wheel_odometry(trajectory, odom_t, odom_noise, np.random.default_rng(odom_seed))
    imu_t = _sample_times(duration, imu_rate)
    gyro, accel = gyro_and_accel(trajectory, imu_t, imu_noise, np.random.default_rng(imu_seed))
    return Simulation(
        world=world, trajectory=trajectory, lidar=lidar,
        laser_pose=(float(laser_pose[0]), float(laser_pose[1]), float(laser_pose[2])),
        start_time=float(start_time), seed=seed,
        scan_times=start_time + _sample_times(duration, scan_rate),
        odometry=np.column_stack([start_time + odom_t, odom]).reshape(-1, 6),
        imu_times=start_time + imu_t, imu_gyro=gyro, imu_accel=accel, movers=tuple(movers),
    )
