"""Online scan-to-map SLAM on a dynamic distance map (IRIS LaMa's ``Slam2D``, as our own code).

One map, no submaps, no loop closure: each scan whose odometry moved more than ``d_thresh`` / ``a_thresh`` since
the last processed one is matched to the distance map from the odometry prediction
(:mod:`carto_cli.matching.distance_matcher`) and inserted at the matched pose
(:class:`carto_cli.grid.distance_map.DistanceMap`); the scans in between are placed by odometry from the last
processed one. Points arrive in the tracking frame (the robot body), with the sensor's origin in that frame.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core import transform
from carto_cli.grid.distance_map import DistanceMap
from carto_cli.matching import distance_matcher


@dataclass
class Slam2DOptions:
    resolution: float = 0.05
    max_distance: float = 0.5  # truncation of the distance field (LaMa's l2_max)
    d_thresh: float = 0.01  # m of odometry motion before a scan is processed (iris_lama_ros default)
    a_thresh: float = 0.25  # rad
    loss_scale: float = 0.15  # m, Cauchy
    max_iterations: int = 100
    multires: bool = False  # match on a 4x coarser map first (widens the basin; costs a second insertion)
    occupied_fraction: float = 0.25
    # A prior towards the odometry prediction (1 / m, 1 / rad; 0: none, as LaMa): holds the directions a scan
    # cannot see (a long corridor's axis) to odometry instead of letting noise slide them.
    translation_weight: float = 0.0
    rotation_weight: float = 0.0


@dataclass
class Slam2DResult:
    pose: np.ndarray  # tracking frame in the map
    processed: bool  # matched (when the map had something) and inserted
    match: distance_matcher.DistanceMatchResult | None


class Slam2D:
    def __init__(self, options: Slam2DOptions | None = None, initial_pose: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        self.options = o = options or Slam2DOptions()
        self.maps = [DistanceMap(o.resolution, o.max_distance, o.occupied_fraction)]
        if o.multires:
            self.maps.insert(0, DistanceMap(4 * o.resolution, 4 * o.max_distance, o.occupied_fraction))
        self.pose = transform.as_pose(initial_pose)
        self._odom: np.ndarray | None = None  # odometry at the last processed scan
        self.processed = 0
        self.iterations = 0

    @property
    def distance_map(self) -> DistanceMap:
        return self.maps[-1]

    def predict(self, odometry: ArrayLike) -> tuple[np.ndarray, bool]:
        """The pose odometry predicts, and whether a scan there moved enough to be processed."""
        if self._odom is None:
            return self.pose.copy(), True
        delta = transform.relative(self._odom, transform.as_pose(odometry))
        moved = math.hypot(delta[0], delta[1]) > self.options.d_thresh or abs(delta[2]) > self.options.a_thresh
        return transform.compose(self.pose, delta), moved

    def add_scan(self, odometry: ArrayLike, points: ArrayLike, sensor_origin: ArrayLike = (0.0, 0.0)) -> Slam2DResult:
        """``points`` (n, 2) returns in the tracking frame, ``odometry`` the odometry pose at the scan."""
        o = self.options
        prediction, moved = self.predict(odometry)
        if not moved:
            return Slam2DResult(prediction, False, None)
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 2)
        result = None
        pose = prediction
        if self._odom is not None and points.shape[0]:
            result = distance_matcher.match_multires(self.maps, points, prediction, loss_scale=o.loss_scale,
                                                     max_iterations=o.max_iterations, prior_pose=prediction,
                                                     translation_weight=o.translation_weight,
                                                     rotation_weight=o.rotation_weight)
            pose = result.pose
            self.iterations += result.iterations
        origin = transform.apply(pose, np.asarray(sensor_origin, dtype=np.float64).reshape(1, 2))[0]
        world = transform.apply(pose, points)
        for m in self.maps:
            m.insert(origin, world)
        self.pose = pose
        self._odom = transform.as_pose(odometry)
        self.processed += 1
        return Slam2DResult(pose.copy(), True, result)

    @property
    def memory_bytes(self) -> int:
        return sum(m.memory_bytes for m in self.maps)
