"""The odometry the pose graph was given, per trajectory: what interpolates an odometry pose at every node (the
optimization's odometry terms) and what the map's verdict compares local SLAM with."""
from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core import transform

__all__ = ["GrowingArray", "OdometryLog"]


class GrowingArray:
    """An (n, k) float array with amortised O(1) append."""

    def __init__(self, width: int, capacity: int = 256):
        self._data = np.empty((capacity, width))
        self.n = 0

    def append(self, row: ArrayLike) -> int:
        if self.n == len(self._data):
            self._data = np.concatenate([self._data, np.empty_like(self._data)])
        self._data[self.n] = row
        self.n += 1
        return self.n - 1

    @property
    def array(self) -> np.ndarray:
        return self._data[: self.n]


class OdometryLog:
    def __init__(self) -> None:
        self._samples: dict[int, tuple[GrowingArray, GrowingArray]] = {}  # trajectory → (times, unwrapped poses)

    @classmethod
    def of(cls, samples: dict[int, tuple[np.ndarray, np.ndarray]]) -> OdometryLog:
        """A log holding ``samples`` (trajectory → times, unwrapped poses), copied."""
        log = cls()
        for trajectory, (times, poses) in samples.items():
            grown = log._samples[int(trajectory)] = (GrowingArray(1), GrowingArray(3))
            for t, pose in zip(times, poses):
                grown[0].append((float(t),))
                grown[1].append(pose)
        return log

    def add(self, time: float, pose: ArrayLike, trajectory: int = 0) -> None:
        """A sample (tracking frame in the odometry frame); out of order or duplicate ones are dropped, as
        Cartographer drops them."""
        times, poses = self._samples.setdefault(trajectory, (GrowingArray(1), GrowingArray(3)))
        sample = np.asarray(pose, dtype=np.float64).reshape(3).copy()
        if times.n:
            if time <= times.array[-1, 0]:
                return
            prev = poses.array[-1, 2]
            sample[2] = transform.unwrap_angle(sample[2], prev)  # for interpolation
        times.append((float(time),))
        poses.append(sample)

    def samples(self, trajectory: int = 0) -> np.ndarray | None:
        """(n, 4) t, x, y, yaw (unwrapped) of the odometry given for ``trajectory``; None with fewer than two."""
        samples = self._samples.get(trajectory)
        if samples is None or samples[0].n < 2:
            return None
        return np.column_stack([samples[0].array[:, 0], samples[1].array])

    def arrays(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """trajectory → (times, unwrapped poses), views of what the log holds."""
        return {t: (times.array[:, 0], poses.array) for t, (times, poses) in self._samples.items()}
