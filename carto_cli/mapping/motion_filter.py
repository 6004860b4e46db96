"""Motion filter: drop a node unless enough time, distance or rotation passed since the last kept one.

A stationary robot would otherwise pile identical scans into a submap,
over-confirming the same cells and bloating the pose graph with nodes that
add no information.
"""
from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core.transform import wrap_angle_scalar


class MotionFilter:
    def __init__(self, *, max_time_seconds: float = 5.0, max_distance_meters: float = 0.2,
                 max_angle_radians: float = math.radians(1.0)):
        self.max_time_seconds = float(max_time_seconds)
        self.max_distance_meters = float(max_distance_meters)
        self.max_angle_radians = float(max_angle_radians)
        self.num_total = 0
        self.num_kept = 0
        self._last_time = 0.0
        self._last_pose = np.zeros(3)

    def is_similar(self, time: float, pose: ArrayLike) -> bool:
        """True when the node should be dropped; a kept node becomes the new reference."""
        pose = np.asarray(pose, dtype=np.float64)
        self.num_total += 1
        if (self.num_total > 1
                and time - self._last_time <= self.max_time_seconds
                and math.hypot(pose[0] - self._last_pose[0], pose[1] - self._last_pose[1]) <= self.max_distance_meters
                and abs(wrap_angle_scalar(pose[2] - self._last_pose[2])) <= self.max_angle_radians):
            return True
        self._last_time = float(time)
        self._last_pose = pose.copy()
        self.num_kept += 1
        return False

    def keep(self, time: float, pose: ArrayLike) -> bool:
        return not self.is_similar(time, pose)

    @property
    def num_dropped(self) -> int:
        return self.num_total - self.num_kept

    @property
    def kept_fraction(self) -> float:
        return self.num_kept / self.num_total if self.num_total else 1.0
