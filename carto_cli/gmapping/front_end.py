"""GMapping's pipeline with one pose instead of particles: scan-to-map matching on a distance map.

``--algorithm scan-to-map``. What a processed scan goes through is the only change from :class:`GMappingSlam`:
the odometry's increment since the last processed scan predicts the pose, a robust Gauss-Newton match on the
distance map of every scan so far (:mod:`carto_cli.matching.distance_matcher`, IRIS LaMa's ``Slam2D``) corrects
it, and the scan goes into that map at the corrected pose. Which scans are processed (``linearUpdate``,
``angularUpdate``), the loop step between passes, the re-matching against the map of all scans and the outputs
are GMapping's (``gmapping.*`` options, ``finish``), so the two systems differ only in how they choose a scan's
pose: many hypotheses, each matched on its own map, or one.

Why: on the key-scan logs the particles cost 40-120 s of CPU and 0.8-1.7 GB, where one pose matched on one
map and then the same loop step and re-matching cost 3-7 s (docs/measurements.md). But one pose cannot recover
from a wrong match (fhw: metres off), so auto never chooses it; it is there to be asked for and measured.
"""
from __future__ import annotations

import numpy as np

from carto_cli.core import kernels, transform
from carto_cli.gmapping import Algorithm, motion
from carto_cli.gmapping.filter import Beams, GMappingSlam
from carto_cli.grid.distance_map import DistanceMap
from carto_cli.mapping.slam import RunStats
from carto_cli.matching import distance_matcher

# The distance field's reach: a match must see a wall within it from where odometry puts the scan. LaMa's
# 0.5 m let dense aces drift its heading in long corridors (3.9 m); 1 m held every shared case
# (docs/measurements.md).
MAX_DISTANCE_M = 1.0
LOSS_SCALE_M = 0.15  # Cauchy: returns farther than this from the map (people, new walls) weigh little
MAX_ITERATIONS = 100
MATCH_RANGE_M = 16.0  # returns matched (all are inserted): LaMa's mrange; far returns' noise and sparse walls


class ScanToMapSlam(GMappingSlam):
    """GMapping's processed-scan pipeline with one pose, matched on a distance map (module doc)."""

    def __init__(self, options, **kwargs):
        super().__init__(options, **kwargs)
        kernels.warm_up(self.timer, systems=("scan-to-map",))
        self.distance_map = DistanceMap(self.g.delta, MAX_DISTANCE_M)
        self.maps = type(self.maps)(1, self.g.delta)  # unused but for the empty-refinement path: one "particle"
        self.poses = np.zeros((1, 3))
        self.log_weights = np.zeros(1)
        self.lineage = np.zeros(1)
        self.unconverged = 0

    def _process(self, t: float, odometry: np.ndarray | None, beams: Beams) -> None:
        pose = self.poses[0]
        if self._step_poses:
            previous = self._step_odometry[-1]
            delta = (motion.increment(previous, odometry) if previous is not None and odometry is not None
                     else np.zeros(3))
            prediction = transform.compose(pose, delta)
            with self.timer.stage("scan matching"):
                rel = beams.points - np.asarray(beams.origin, dtype=np.float64).reshape(1, 2)
                near = beams.points[np.hypot(rel[:, 0], rel[:, 1]) <= MATCH_RANGE_M]
                match = distance_matcher.match(self.distance_map, near, prediction, loss_scale=LOSS_SCALE_M,
                                               max_iterations=MAX_ITERATIONS)
            pose = match.pose
            self.unconverged += not match.converged
        with self.timer.stage("map update"):
            origin = transform.apply(pose, np.asarray(beams.origin, dtype=np.float64).reshape(1, 2))[0]
            self.distance_map.insert(origin, transform.apply(pose, beams.points))
        self.poses = np.asarray(pose, dtype=np.float64).reshape(1, 3).copy()
        self._record(t, odometry, beams, np.zeros(1, np.int32))

    def finish(self):
        result = super().finish()
        result.stats.update(RunStats(algorithm=Algorithm.SCAN_TO_MAP, particles=0, resamplings=0, mean_neff=None,
                                     unconverged_matches=self.unconverged,
                                     map_memory_peak_bytes=int(self.distance_map.memory_bytes)))
        return result
