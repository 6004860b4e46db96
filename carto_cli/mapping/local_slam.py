"""Cartographer's 2D local SLAM: scan → filtered range data → predicted pose → matched pose → submaps.

One ``LocalSlam`` per trajectory. Scans arrive in the sensor frame together with the
laser's mount on the robot; everything downstream works in the tracking frame
(the robot body), which is what the extrapolator, odometry and the trajectory
files describe. A scan whose beams have times (``time_increment``, a per-point
time, several lasers merged) is de-skewed while cropped: each beam placed with the
motion the extrapolator predicts over the sweep, all points expressed at the
scan's own time (Cartographer does the same point by point).

What the stock (Cartographer) weights mean for tuning, measured on simulated and
bench-dense data: the least-squares matcher's priors (translation_weight 10,
rotation_weight 40) outweigh the scan's own information several times over
(J^T J of the points ~20 per m^2 and ~650 per rad^2 against 100 and 1600), so each
match moves only a fifth to a third of the way from the prediction to what the scan
says. With good odometry or an IMU that is what one wants; with drifting wheel
odometry the heading drifts with it (rotation_weight 1 fixes that), and with no
odometry the correlative matcher must be on and translation_weight low (1), or the
pose follows the constant-velocity guess.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from carto_cli.core import kernels, transform
from carto_cli.core.kernels import register_warm_up
from carto_cli.core.records import Imu, Odometry, Scan
from carto_cli.core.timing import NullTimer, StageTimer
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.mapping.extrapolator import PoseExtrapolator
from carto_cli.mapping.motion_filter import MotionFilter
from carto_cli.mapping.submaps import ActiveSubmaps, Submap
from carto_cli.matching import correlative, least_squares
from carto_cli.matching.transient import transient_mask
from carto_cli.options import TrajectoryBuilder2D
from carto_cli.sensor.range_filter import RangeData, accumulate, crop_polar, crop_scan
from carto_cli.sensor.voxel_filter import adaptive_voxel_filter, voxel_filter


@dataclass
class InsertionResult:
    """A scan the motion filter kept: it became a node and went into ``submaps``."""

    node_index: int
    submaps: list[Submap]
    range_data_local: RangeData  # the inserted range data, local frame
    loop_closure_points: np.ndarray  # (n, 2) tracking frame, for the constraint builder


@dataclass
class LocalSlamResult:
    time: float
    local_pose: np.ndarray  # tracking frame in the local SLAM frame
    matching_points: np.ndarray  # (n, 2) tracking frame, adaptive-voxel filtered
    score: float | None  # real-time correlative score when that matcher ran
    ls_cost: float | None
    insertion: InsertionResult | None = None


@dataclass
class LocalSlamStats:
    scans: int = 0
    empty_scans: int = 0
    matched: int = 0
    nodes: int = 0
    ls_iterations: int = 0
    transient_matching: int = 0  # points left out of matching as transient (people, carts)
    transient_inserted: int = 0  # returns kept out of the submaps as transient
    finished_submaps: list = field(default_factory=list)


@register_warm_up
def warm_up() -> None:
    """The per-scan path's kernels (crop, voxel filters, insertion, both matchers) on a toy scan."""
    angles = np.linspace(-2.0, 2.0, 64)
    ranges = 2.0 + 0.5 * np.sin(3.0 * angles)
    ranges[0] = np.inf
    data = crop_polar(ranges, angles, mount=(0.0, 0.0, 0.0), time_increment=1e-4, motion=(0.1, 0.0, 0.1))
    points = adaptive_voxel_filter(voxel_filter(data.returns, 0.025), max_length=0.5, min_num_points=32)
    active = ActiveSubmaps(num_range_data=1)
    active.insert(data.transformed((0.1, 0.2, 0.3)))
    submap = active.matching_submap
    assert submap is not None
    grid = submap.grid
    correlative.match(grid, points, np.zeros(3), angular_search_window=0.01)
    least_squares.match(grid, points, np.zeros(3))


class LocalSlam:
    def __init__(self, options: TrajectoryBuilder2D, laser_pose: ArrayLike = (0.0, 0.0, 0.0),
                 timer: StageTimer | NullTimer | None = None) -> None:
        self.options = options
        self.laser_pose = transform.as_pose(laser_pose)
        self.timer = timer or NullTimer()
        kernels.warm_up(self.timer, systems=("cartographer",))
        self.ceres = least_squares.CeresScanMatcher.from_options(options.ceres_scan_matcher)
        o = options
        self.extrapolator = PoseExtrapolator(
            pose_queue_duration=o.pose_extrapolator.constant_velocity.pose_queue_duration,
            use_imu_data=o.use_imu_data,
        )
        self.motion_filter = MotionFilter(
            max_time_seconds=o.motion_filter.max_time_seconds,
            max_distance_meters=o.motion_filter.max_distance_meters,
            max_angle_radians=o.motion_filter.max_angle_radians,
        )
        ri = o.submaps.range_data_inserter
        self.submaps = ActiveSubmaps(
            num_range_data=o.submaps.num_range_data,
            resolution=o.submaps.grid_options_2d.resolution,
            hit_probability=ri.hit_probability,
            miss_probability=ri.miss_probability,
            insert_free_space=ri.insert_free_space,
        )
        self.stats = LocalSlamStats()
        self._accumulated: list[RangeData] = []
        self._accumulated_poses: list[np.ndarray] = []
        self._has_odometry = False
        self._last_pose: np.ndarray | None = None

    def _search_window(self, prediction: np.ndarray) -> dict:
        """The real-time correlative search around ``prediction``: Cartographer's fixed window and weights, or
        with ``motion_scaled_prior`` a window and a prior as wide as odometry's error over the motion predicted
        since the last scan. Key scans a metre and 30 degrees apart need a window and a prior sized to that
        motion: a fixed 20 degree window with a near-flat prior let the scan's heading jump to a wrong but
        slightly better-scoring alignment, and local SLAM ended worse than odometry (docs/measurements.md)."""
        c = self.options.real_time_correlative_scan_matcher
        fixed = dict(linear_search_window=c.linear_search_window, angular_search_window=c.angular_search_window,
                     translation_delta_cost_weight=c.translation_delta_cost_weight,
                     rotation_delta_cost_weight=c.rotation_delta_cost_weight,
                     unknown_probability=c.unknown_probability)
        if not c.motion_scaled_prior or not self._has_odometry or self._last_pose is None:
            return fixed
        motion = transform.relative(self._last_pose, prediction)
        distance = float(np.hypot(motion[0], motion[1]))
        turn = abs(float(motion[2]))
        sigma_t = max(c.min_translation_noise, c.odometry_translation_noise * distance)
        sigma_r = max(c.min_rotation_noise, c.odometry_rotation_noise * turn
                      + c.odometry_rotation_noise_per_meter * distance)
        # Cartographer's damping exp(-(w |delta|)^2) is a Gaussian of standard deviation 1 / (sqrt(2) w).
        return dict(
            linear_search_window=min(max(c.linear_search_window, 3.0 * sigma_t), c.max_linear_search_window),
            angular_search_window=min(max(c.angular_search_window, 3.0 * sigma_r), c.max_angular_search_window),
            translation_delta_cost_weight=1.0 / (np.sqrt(2.0) * sigma_t),
            rotation_delta_cost_weight=1.0 / (np.sqrt(2.0) * sigma_r),
            unknown_probability=c.unknown_probability,
        )

    def _match(self, grid: ProbabilityGrid, points: np.ndarray,
               prediction: np.ndarray) -> tuple[np.ndarray, float | None, float]:
        """(pose, correlative score or None, least-squares cost) of ``points`` matched in ``grid`` from
        ``prediction``, transient points left out."""
        timer = self.timer
        if self.options.transient_points.enabled:  # off by default: no stage of its own in the timing tree
            with timer.stage("transient"):
                points = self._static(grid, points, prediction, "transient_matching")
        initial = prediction
        score = None
        if self.options.use_online_correlative_scan_matching:
            with timer.stage("correlative"):
                result = correlative.match(grid, points, prediction, **self._search_window(prediction))
                initial = result.pose
                score = result.score
        with timer.stage("least squares"):
            ls = self.ceres.match(grid, points, initial, target_translation=prediction[:2])
            self.stats.ls_iterations += ls.iterations
        return ls.pose, score, ls.cost

    def _static(self, grid: ProbabilityGrid, points: np.ndarray, pose: np.ndarray, counter: str) -> np.ndarray:
        """``points`` without those :func:`transient_mask` finds at ``pose`` (all of them when too many look
        transient); the dropped ones counted in ``stats.<counter>``."""
        t = self.options.transient_points
        if not t.enabled or len(points) == 0:
            return points
        mask = transient_mask(grid, points, pose, max_free_probability=t.max_free_probability,
                              clearance=t.clearance)
        dropped = int(mask.sum())
        if dropped == 0 or dropped > t.max_fraction * len(points):
            return points
        setattr(self.stats, counter, getattr(self.stats, counter) + dropped)
        return points[~mask]

    def add_odometry(self, odometry: Odometry) -> None:
        self._has_odometry = True
        self.extrapolator.add_odometry(odometry)

    def add_imu(self, imu: Imu) -> None:
        self.extrapolator.add_imu(imu)

    def _predicted_motion(self, scan: Scan) -> tuple[float, float, float] | None:
        """The motion the extrapolator gives over the time ``scan``'s beams span (odometry's over that time where
        it covers it, else its prediction; before the first pose, odometry's, else none); None for a scan taken at
        once."""
        if not scan.timed:
            return None
        times = scan.beam_times()
        if not len(times):
            return None
        start = float(times.min())
        return self.extrapolator.body_motion(scan.time, float(times.max()) - start, start=start)

    def _cropped(self, scan: Scan, motion: tuple[float, float, float] | None) -> RangeData:
        """``scan`` cropped straight into the tracking frame, its beams de-skewed by ``motion`` (None: as one
        instant)."""
        o = self.options
        return crop_scan(scan, mount=self.laser_pose, motion=motion, min_range=o.min_range, max_range=o.max_range,
                         missing_data_ray_length=o.missing_data_ray_length)

    def _filtered(self, data: RangeData) -> tuple[RangeData, np.ndarray]:
        """``data`` voxel filtered, and the adaptive-voxel filtered returns local matching uses."""
        o, timer = self.options, self.timer
        with timer.stage("voxel"):
            data = RangeData(data.origin, voxel_filter(data.returns, o.voxel_filter_size),
                             voxel_filter(data.misses, o.voxel_filter_size))
        with timer.stage("adaptive voxel"):
            f = o.adaptive_voxel_filter
            points = adaptive_voxel_filter(data.returns, max_length=f.max_length,
                                           min_num_points=f.min_num_points, max_range=f.max_range)
        return data, points

    def add_scan(self, scan: Scan) -> LocalSlamResult | None:
        """Process one scan; None while accumulating or when nothing usable was left after filtering."""
        o = self.options
        timer = self.timer
        self.stats.scans += 1
        with timer.stage("preprocess"):
            with timer.stage("crop"):
                # Straight into the tracking frame; a sweeping scanner's beams are de-skewed with
                # the motion the extrapolator predicts (Cartographer does the same per point).
                motion = self._predicted_motion(scan)
                data = self._cropped(scan, motion)
            if o.num_accumulated_range_data > 1:
                self._accumulated.append(data)
                self._accumulated_poses.append(self.extrapolator.extrapolate(scan.time))
                if len(self._accumulated) < o.num_accumulated_range_data:
                    return None
            # Accumulated scans are expressed in the tracking frame at the newest one, placed by
            # the poses predicted for each: that is how Cartographer de-skews a slow sensor.
            if len(self._accumulated) > 1:
                data = accumulate(self._accumulated, self._accumulated_poses)
            self._accumulated = []
            self._accumulated_poses = []
            data, points = self._filtered(data)
        if points.shape[0] == 0:
            self.stats.empty_scans += 1
            return None

        with timer.stage("extrapolate"):
            prediction = self.extrapolator.extrapolate(scan.time)

        score = None
        ls_cost = None
        pose = prediction
        matching = self.submaps.matching_submap
        if matching is not None:
            with timer.stage("match"):
                pose, score, ls_cost = self._match(matching.grid, points, prediction)
            self.stats.matched += 1

        with timer.stage("extrapolate"):
            self.extrapolator.add_pose(scan.time, pose)
        self._last_pose = pose

        out = LocalSlamResult(scan.time, pose.copy(), points, score, ls_cost)
        with timer.stage("motion filter"):
            similar = self.motion_filter.is_similar(scan.time, pose)
        if similar:
            return out
        if matching is not None and self.options.transient_points.enabled:
            with timer.stage("transient"):
                # Judged again at the matched pose: a person inserted as a wall is matched against by the
                # scans that follow, and stays in the map.
                data = RangeData(data.origin, self._static(matching.grid, data.returns, pose, "transient_inserted"),
                                 data.misses)
        with timer.stage("insert"):
            local_data = data.transformed(pose)
            inserted = self.submaps.insert(local_data, timer)
        with timer.stage("preprocess"):
            with timer.stage("adaptive voxel"):
                lc = o.loop_closure_adaptive_voxel_filter
                lc_points = adaptive_voxel_filter(data.returns, max_length=lc.max_length,
                                                  min_num_points=lc.min_num_points, max_range=lc.max_range)
        out.insertion = InsertionResult(self.stats.nodes, inserted, local_data, lc_points)
        self.stats.nodes += 1
        if inserted[0].finished:
            self.stats.finished_submaps.append(inserted[0].index)
        return out
