"""A spinning 3D lidar (16 rings, a VLP-16's) in a building made 3D from a 2D ``World``.

The walls stand from the floor (z = 0) to the ceiling; furniture (tables, boxes, low shelves) are boxes on the floor
lower than the band a 2D map is drawn in, which the 2D walls do not include; floor and ceiling are planes. A sweep
turns once per period: each column of the 16 rings is fired at its own time from the robot's pose then (the motion
smears the sweep, as a real one is), and every point carries its time after the sweep's stamp.

A ray of elevation ``e`` from height ``h`` is at height ``h + d tan e`` after a horizontal distance ``d``, so every
surface is found in the plane: the walls by the 2D ray caster along the column's bearing (one cast serves all 16
rings), a box's side by casting against its outline where the ray is below its top there, a box's top where the
ray comes down to it within its outline, and floor and ceiling where the ray reaches their heights.

``Simulation3D.write`` writes a recording carto reads as a user's: PointCloud2 clouds with x, y, z and a per-point
time field, odometry, IMU and the lidar's static transform.
"""
from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carto_cli.core.records import Cloud, Imu, Odometry, Transform, yaw_quaternion
from carto_cli.io.recording_writers import write_recording
from carto_cli.sim.lidar import cast
from carto_cli.sim.recording import IMU_TOPIC, ODOM_TOPIC, Simulation, compose, simulate
from carto_cli.sim.trajectory import Trajectory
from carto_cli.sim.world import World, box

__all__ = ["Building", "Lidar3D", "Simulation3D", "furnish", "simulate_3d"]

CLOUD_TOPIC, CLOUD_FRAME = "/points", "lidar"
VLP16_RINGS = tuple(float(e) for e in range(-15, 16, 2))  # degrees
_CHUNK = 16  # sweeps cast per kernel call


@dataclass(frozen=True, eq=False)
class Building:
    """``world``'s walls from the floor to ``ceiling`` (m), and ``furniture``: (f, 5) boxes ``cx cy w d height``
    standing on the floor, axis-aligned."""

    world: World
    ceiling: float = 2.6
    furniture: np.ndarray = field(default_factory=lambda: np.zeros((0, 5)))

    def __post_init__(self):
        object.__setattr__(self, "furniture", np.asarray(self.furniture, dtype=np.float64).reshape(-1, 5))
        if self.ceiling <= 0 or np.any(self.furniture[:, 4] >= self.ceiling):
            raise ValueError("the ceiling must be above the floor and above every piece of furniture")

    @property
    def furniture_height(self) -> float:
        return float(self.furniture[:, 4].max()) if len(self.furniture) else 0.0


def furnish(world: World, *, count: int = 12, max_height: float = 0.55, seed: int = 0,
            clearance: float = 0.35) -> Building:
    """``world`` with ``count`` boxes (tables, crates, low shelves) up to ``max_height`` tall, placed by ``seed``
    where the robot sees them: each in sight of a point of the route (no wall between), clear of the route by
    ``clearance`` (the robot drives past them, never through) and of the walls by a little (a box pushed against a
    wall is part of the wall's line in any map)."""
    if world.route is None or len(world.route) < 2:
        raise ValueError("furnish needs a world with a route")
    rng = np.random.default_rng(seed)
    route = np.vstack([world.route, world.route[:1]]) if world.closed else world.route
    # Points along the route every 0.2 m: where the robot passes, and where boxes are seen from.
    along = np.concatenate([a + (b - a) * (np.arange(max(int(np.hypot(*(b - a)) / 0.2), 1))
                                           / max(int(np.hypot(*(b - a)) / 0.2), 1))[:, None]
                            for a, b in zip(route[:-1], route[1:])])
    boxes: list[list[float]] = []
    for _ in range(500 * count):
        if len(boxes) == count:
            break
        w, d = rng.uniform(0.4, 1.2), rng.uniform(0.3, 0.7)
        seen_from = along[rng.integers(len(along))]
        bearing = rng.uniform(-math.pi, math.pi)
        reach = rng.uniform(clearance + max(w, d) / 2, 4.0)
        cx, cy = seen_from + reach * np.array([math.cos(bearing), math.sin(bearing)])
        corners = box(cx, cy, w, d)[:, :2]
        if world.distance_to_walls(np.vstack([corners, [[cx, cy]]])).min() < 0.15:
            continue
        if cast(np.array([*seen_from, bearing]), np.zeros(1), world.segments)[0] < reach:
            continue  # behind a wall from where it would be seen
        if (np.abs(along - [cx, cy]) <= [w / 2 + clearance, d / 2 + clearance]).all(axis=1).any():
            continue
        if any(abs(cx - b[0]) < (w + b[2]) / 2 + 0.2 and abs(cy - b[1]) < (d + b[3]) / 2 + 0.2 for b in boxes):
            continue
        boxes.append([cx, cy, w, d, rng.uniform(0.3, max_height)])
    return Building(world, furniture=np.array(boxes).reshape(-1, 5))


@dataclass(frozen=True)
class Lidar3D:
    """A spinning multi-ring lidar: ring elevations (deg), columns per turn, turns per second, the range it sees,
    its noise along the ray and the share of returns lost."""

    rings: tuple[float, ...] = VLP16_RINGS
    columns: int = 900  # 0.4 degrees apart
    rate: float = 10.0
    max_range: float = 30.0
    min_range: float = 0.3
    noise: float = 0.01
    dropout: float = 0.0
    # Every column at the stamp (an idealised flash lidar): what the flattening gives without any de-skewing.
    instantaneous: bool = False

    def azimuths(self) -> np.ndarray:
        return -math.pi + 2 * math.pi * np.arange(self.columns) / self.columns

    def column_offsets(self) -> np.ndarray:
        """Seconds after the sweep's stamp each column fires: the turn spread over the period."""
        if self.instantaneous:
            return np.zeros(self.columns)
        return np.arange(self.columns) / (self.columns * self.rate)


def _inside(points: np.ndarray, b: np.ndarray) -> np.ndarray:
    return (np.abs(points[..., 0] - b[0]) <= b[2] / 2) & (np.abs(points[..., 1] - b[1]) <= b[3] / 2)


def sweep_distances(building: Building, poses: np.ndarray, height: float, rings: np.ndarray,
                    max_distance: float) -> np.ndarray:
    """(m, r) horizontal distance at which each of ``rings`` (elevations, rad) fired from each of ``poses`` ((m, 3)
    x y bearing in the world, one per column) meets the first surface; inf where none is within
    ``max_distance``."""
    slope = np.tan(rings)[None, :]
    m = poses.shape[0]
    walls = cast(poses, np.zeros(1), building.world.segments, max_distance)[:, :1]
    with np.errstate(divide="ignore"):
        floor = np.where(slope < 0, -height / slope, np.inf)
        ceiling = np.where(slope > 0, (building.ceiling - height) / slope, np.inf)
    best = np.minimum(np.minimum(walls, floor), ceiling) * np.ones((m, 1))
    direction = np.stack([np.cos(poses[:, 2]), np.sin(poses[:, 2])], axis=1)
    for b in building.furniture:  # a few boxes; each one's test is vectorised over every ray
        side = cast(poses, np.zeros(1), box(*b[:4]), max_distance)[:, :1]
        below_top = height + side * slope <= b[4]
        best = np.minimum(best, np.where(below_top, side, np.inf))
        if height > b[4]:
            with np.errstate(divide="ignore"):
                top = np.where(slope < 0, (b[4] - height) / slope, np.inf)  # (1, r)
            finite = np.where(np.isfinite(top), top, 0.0)
            at = poses[:, None, :2] + finite[:, :, None] * direction[:, None, :]
            best = np.minimum(best, np.where(_inside(at, b) & np.isfinite(top), top, np.inf))
    return best


@dataclass(eq=False)
class Simulation3D:
    """The 3D lidar's sweeps along a 2D simulation's trajectory, with that simulation's odometry and IMU."""

    building: Building
    lidar: Lidar3D
    mount: tuple[float, float, float]  # x y yaw on base_link
    height: float  # m above the floor
    base: Simulation  # times, odometry, IMU, ground truth
    seed: int = 0
    time_field: str = "t"

    @property
    def sweep_times(self) -> np.ndarray:
        return self.base.scan_times

    @property
    def ground_truth(self) -> np.ndarray:
        return self.base.ground_truth

    @property
    def static_transforms(self) -> list[Transform]:
        x, y, yaw = self.mount
        return [Transform("base_link", CLOUD_FRAME, (float(x), float(y), float(self.height)),
                          yaw_quaternion(float(yaw))),
                Transform("base_link", "imu", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0, 1.0))]

    def clouds(self) -> Iterator[Cloud]:
        """Every sweep as a cloud in the lidar's frame, in time order."""
        lidar = self.lidar
        rng = np.random.default_rng(np.random.SeedSequence(self.seed).spawn(4)[3])
        rings = np.radians(np.asarray(lidar.rings, dtype=np.float64))
        azimuths, offsets = lidar.azimuths(), lidar.column_offsets()
        cos_e = np.cos(rings)[None, :]
        times = self.sweep_times
        for start in range(0, len(times), _CHUNK):
            stamps = times[start:start + _CHUNK]
            fire = (stamps[:, None] + offsets[None, :]).reshape(-1)
            # Each column from where the lidar is when it fires, looking along its bearing.
            poses = compose(self.base.trajectory.poses(fire - self.base.start_time), self.mount)
            poses[:, 2] += np.tile(azimuths, len(stamps))
            horizontal = sweep_distances(self.building, poses, self.height, rings, lidar.max_range)
            slant = horizontal / cos_e
            noisy = slant + lidar.noise * rng.standard_normal(slant.shape)
            seen = (slant <= lidar.max_range) & (noisy >= lidar.min_range) & (rng.random(slant.shape) >= lidar.dropout)
            along = noisy * cos_e  # horizontal distance of the noisy return
            for k, stamp in enumerate(stamps.tolist()):
                rows = slice(k * lidar.columns, (k + 1) * lidar.columns)
                keep = seen[rows]
                d = along[rows][keep]
                az = np.broadcast_to(azimuths[:, None], keep.shape)[keep]
                z = (noisy[rows] * np.sin(rings)[None, :])[keep]
                points = np.stack([d * np.cos(az), d * np.sin(az), z], axis=1).astype(np.float32)
                t = np.broadcast_to(offsets[:, None], keep.shape)[keep]
                yield Cloud(time=float(stamp), points=points, frame=CLOUD_FRAME, topic=CLOUD_TOPIC, point_times=t,
                            time_field=self.time_field)

    def records(self) -> Iterator[Cloud | Odometry | Imu]:
        """Clouds, odometry and IMU in the order a recording logs them: each cloud after the odometry and IMU
        until its last point."""
        base = self.base
        others = [r for r in base.records([ODOM_TOPIC, IMU_TOPIC]) if isinstance(r, (Odometry, Imu))]
        i = 0
        for cloud in self.clouds():
            # After the odometry and IMU of its whole sweep: a driver publishes a sweep once it has turned.
            end = cloud.time + (float(cloud.point_times.max()) if cloud.point_times is not None and
                                len(cloud.point_times) else 0.0)
            while i < len(others) and others[i].time <= end:
                yield others[i]
                i += 1
            yield cloud
        yield from others[i:]

    def write(self, path: str | Path, fmt: str = "mcap", *, overwrite: bool = False) -> Path:
        """A recording of this simulation in ``fmt`` (``io.recording_writers.FORMATS``) at ``path``."""
        write_recording(self.records(), Path(path), fmt, static_transforms=self.static_transforms,
                        overwrite=overwrite)
        return Path(path)


def simulate_3d(building: Building, trajectory: Trajectory, *, lidar: Lidar3D = Lidar3D(),
                mount: tuple[float, float, float] = (0.0, 0.0, 0.0), height: float = 0.8, seed: int = 0,
                duration: float | None = None, time_field: str = "t") -> Simulation3D:
    """The 3D lidar ``lidar`` mounted at ``mount`` (x, y, yaw on base_link), ``height`` m above the floor, driven
    along ``trajectory`` in ``building``. Odometry and IMU are ``sim.simulate``'s for the same ``seed``, so a 2D
    simulation of the same trajectory and seed has the very same odometry. ``time_field``: the per-point time
    field's name, in its driver's convention (``core.records.Cloud``)."""
    if not 0 < height < building.ceiling:
        raise ValueError("the lidar must be between the floor and the ceiling")
    base = simulate(building.world, trajectory, duration=duration, scan_rate=lidar.rate, seed=seed,
                    laser_pose=mount)
    return Simulation3D(building=building, lidar=lidar, mount=(float(mount[0]), float(mount[1]), float(mount[2])),
                        height=float(height), base=base, seed=seed, time_field=time_field)
