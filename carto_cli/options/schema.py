"""The options schema: typed dataclasses mirroring Cartographer's 2D configuration.

Names and defaults follow cartographer/configuration_files/trajectory_builder_2d.lua
and pose_graph.lua, so a line such as ``POSE_GRAPH.constraint_builder.min_score = 0.65``
translates to ``--set pose_graph.constraint_builder.min_score=0.65``. Options that only
matter in 3D or to ROS (grid types, thread counts, logging flags) are left out on
purpose: an option that does nothing is worse than a missing one.

Deviations from the Lua defaults, and why:
- ``use_imu_data`` is false: carto maps from recordings that often lack an IMU, and
  Cartographer's ``true`` would make it wait for IMU data forever.

Every leaf carries its one-line doc, unit and bounds in its field metadata; lengths are
metres, times seconds and angles radians. Reading values into this schema is
``options.layering``'s job.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import typing
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from functools import cache
from typing import Any, NamedTuple

from carto_cli.core.errors import CartoError

__all__ = [
    "CeresSolverOptions",
    "GMapping",
    "Leaf",
    "OptionInfo",
    "Options",
    "PoseGraph",
    "Relocalization",
    "TrajectoryBuilder2D",
    "bounds_text",
    "changed_options",
    "get_option",
    "hints",
    "is_section",
    "option_info",
    "option_names",
    "options_to_dict",
    "suggestion",
    "walk",
]


def _opt(default: Any, doc: str, *, unit: str = "", gt: float | None = None, ge: float | None = None,
         lt: float | None = None, le: float | None = None) -> Any:
    """A leaf option: default, one-line doc, unit and bounds, kept in field metadata."""
    return field(default=default, metadata={"doc": doc, "unit": unit, "gt": gt, "ge": ge, "lt": lt, "le": le})


def _section(cls):
    return field(default_factory=cls)


# --------------------------------------------------------------------------- trajectory_builder_2d


@dataclass(frozen=True)
class AdaptiveVoxelFilter:
    max_length: float = _opt(0.5, "largest voxel edge the filter may grow to", unit="m", gt=0)
    min_num_points: int = _opt(200, "shrink the voxel size until at least this many points remain", ge=0)
    max_range: float = _opt(50.0, "points farther than this from the origin are dropped", unit="m", gt=0)


@dataclass(frozen=True)
class LoopClosureAdaptiveVoxelFilter:
    max_length: float = _opt(0.9, "largest voxel edge the filter may grow to", unit="m", gt=0)
    min_num_points: int = _opt(100, "shrink the voxel size until at least this many points remain", ge=0)
    max_range: float = _opt(50.0, "points farther than this from the origin are dropped", unit="m", gt=0)


@dataclass(frozen=True)
class RealTimeCorrelativeScanMatcher:
    linear_search_window: float = _opt(0.1, "half-width of the translational search window", unit="m", ge=0)
    angular_search_window: float = _opt(math.radians(20.0), "half-width of the rotational search window",
                                        unit="rad", ge=0, le=math.pi)
    translation_delta_cost_weight: float = _opt(1e-1, "penalty on translating away from the prediction", ge=0)
    rotation_delta_cost_weight: float = _opt(1e-1, "penalty on rotating away from the prediction", ge=0)
    unknown_probability: float = _opt(0.1, "score of a point in never-observed space: Cartographer's 0.1 counts it "
                                           "as free space, 0.5 as no evidence either way (carto extension)",
                                      ge=0, le=1)
    # carto extension: a prior and a window that follow the motion since the last scan.
    motion_scaled_prior: bool = _opt(False, "derive each scan's delta cost weights and windows from the predicted "
                                            "motion and the odometry noise below (carto extension)")
    odometry_translation_noise: float = _opt(0.1, "odometry translation error per metre travelled "
                                                  "(GMapping's srr)", unit="m/m", ge=0)
    odometry_rotation_noise: float = _opt(0.2, "odometry heading error per radian turned (GMapping's stt)",
                                          unit="rad/rad", ge=0)
    odometry_rotation_noise_per_meter: float = _opt(0.2, "odometry heading error per metre travelled "
                                                         "(GMapping's srt)", unit="rad/m", ge=0)
    min_translation_noise: float = _opt(0.02, "floor of the translation prior's standard deviation", unit="m",
                                        gt=0)
    min_rotation_noise: float = _opt(math.radians(1.0), "floor of the rotation prior's standard deviation",
                                     unit="rad", gt=0)
    max_linear_search_window: float = _opt(1.0, "cap of the motion-scaled translational window", unit="m", ge=0)
    max_angular_search_window: float = _opt(math.radians(45.0), "cap of the motion-scaled rotational window",
                                            unit="rad", ge=0, le=math.pi)


@dataclass(frozen=True)
class CeresSolverOptions:
    """The solver settings of one least-squares problem; each owner gives its own default (``_solver``)."""

    max_num_iterations: int = _opt(dataclasses.MISSING, "solver iterations", ge=1)


def _solver(max_num_iterations: int, doc: str) -> Any:
    """An owner's ``ceres_solver_options``: its iteration default and what one of its iterations does.

    The doc lives on the owner's field because the same leaf means a different solve in
    each place (``option_info`` reads it from there).
    """
    return field(default_factory=lambda: CeresSolverOptions(max_num_iterations=max_num_iterations),
                 metadata={"docs": {"max_num_iterations": doc}})


@dataclass(frozen=True)
class LocalCeresScanMatcher:
    occupied_space_weight: float = _opt(1.0, "weight of the scan-to-grid residuals", ge=0)
    translation_weight: float = _opt(10.0, "weight pulling the translation to the prediction", ge=0)
    rotation_weight: float = _opt(40.0, "weight pulling the rotation to the initial angle", ge=0)
    ceres_solver_options: CeresSolverOptions = _solver(20, "Levenberg-Marquardt iterations per match")


@dataclass(frozen=True)
class MotionFilter:
    max_time_seconds: float = _opt(5.0, "insert a scan at least this often", unit="s", ge=0)
    max_distance_meters: float = _opt(0.2, "insert a scan after moving this far", unit="m", ge=0)
    max_angle_radians: float = _opt(math.radians(1.0), "insert a scan after turning this much",
                                    unit="rad", ge=0, le=math.pi)


@dataclass(frozen=True)
class ConstantVelocityExtrapolator:
    imu_gravity_time_constant: float = _opt(10.0, "time constant of the gravity low-pass filter", unit="s", gt=0)
    pose_queue_duration: float = _opt(0.001, "span of recent poses the velocity is estimated from",
                                      unit="s", ge=0)


@dataclass(frozen=True)
class PoseExtrapolator:
    constant_velocity: ConstantVelocityExtrapolator = _section(ConstantVelocityExtrapolator)


@dataclass(frozen=True)
class GridOptions2D:
    resolution: float = _opt(0.05, "edge of a grid cell", unit="m", gt=0)


@dataclass(frozen=True)
class RangeDataInserter:
    insert_free_space: bool = _opt(True, "apply misses along each ray, not only hits")
    hit_probability: float = _opt(0.55, "occupancy probability a hit moves a cell towards", gt=0.5, lt=1)
    miss_probability: float = _opt(0.49, "occupancy probability a miss moves a cell towards", gt=0, lt=0.5)


@dataclass(frozen=True)
class Submaps:
    num_range_data: int = _opt(90, "scans inserted before the next submap starts (a submap gets twice as many)",
                               ge=1)
    grid_options_2d: GridOptions2D = _section(GridOptions2D)
    range_data_inserter: RangeDataInserter = _section(RangeDataInserter)


@dataclass(frozen=True)
class TransientPoints:
    # carto addition (not in Cartographer): a person or a cart crossing space the submap has seen through many
    # times is matched as if it were a wall, and once inserted it is a wall later scans match against.
    # Off by default: on simulated crowds it did not lower the trajectory's error (docs/benchmarks.md, "Crowds do
    # not bend the trajectory"), and on the static benchmarks the few points it drops still move the result.
    enabled: bool = _opt(False, "carto: leave points in confidently free space, away from walls, out of local "
                         "matching, submap insertion and the node's loop-closure points")
    max_free_probability: float = _opt(0.3, "carto: a point's cell must be at most this likely occupied "
                                       "(about 20 rays through it with the stock miss probability)", gt=0, lt=0.5)
    clearance: float = _opt(0.25, "carto: no cell this near the point may be occupied (a wall point of a "
                            "slightly wrong pose keeps its pull)", unit="m", ge=0)
    max_fraction: float = _opt(0.5, "carto: when more of a scan than this looks transient the pose is more "
                               "likely wrong than the scan crowded: every point is kept", gt=0, le=1)


@dataclass(frozen=True)
class TrajectoryBuilder2D:
    min_range: float = _opt(0.0, "returns closer than this are dropped", unit="m", ge=0)
    max_range: float = _opt(30.0, "returns farther than this become misses", unit="m", gt=0)
    min_z: float = _opt(-0.8, "points below this height are dropped (point clouds only)", unit="m")
    max_z: float = _opt(2.0, "points above this height are dropped (point clouds only)", unit="m")
    cloud_band: str = _opt("auto", "point clouds: 'auto' (a band above the floor's clutter and below the ceiling, "
                           "from the first cloud's heights; min_z..max_z without a floor in sight), 'LOW..HIGH' "
                           "(m above the floor) or 'sensor' (min_z..max_z in the sensor frame)")
    missing_data_ray_length: float = _opt(5.0, "length of the free ray inserted for a return beyond max_range",
                                          unit="m", gt=0)
    num_accumulated_range_data: int = _opt(1, "scans accumulated into one before matching", ge=1)
    voxel_filter_size: float = _opt(0.025, "edge of the fixed voxel filter", unit="m", gt=0)
    adaptive_voxel_filter: AdaptiveVoxelFilter = _section(AdaptiveVoxelFilter)
    loop_closure_adaptive_voxel_filter: LoopClosureAdaptiveVoxelFilter = _section(LoopClosureAdaptiveVoxelFilter)
    use_online_correlative_scan_matching: bool = _opt(False,
                                                      "run the real-time correlative matcher before least squares")
    real_time_correlative_scan_matcher: RealTimeCorrelativeScanMatcher = _section(RealTimeCorrelativeScanMatcher)
    ceres_scan_matcher: LocalCeresScanMatcher = _section(LocalCeresScanMatcher)
    motion_filter: MotionFilter = _section(MotionFilter)
    imu_gravity_time_constant: float = _opt(10.0, "time constant of the gravity low-pass filter", unit="s", gt=0)
    pose_extrapolator: PoseExtrapolator = _section(PoseExtrapolator)
    submaps: Submaps = _section(Submaps)
    use_imu_data: bool = _opt(False, "use IMU angular velocity for the yaw prediction (2D does not need it)")
    transient_points: TransientPoints = _section(TransientPoints)


# --------------------------------------------------------------------------- pose_graph


@dataclass(frozen=True)
class FastCorrelativeScanMatcher:
    linear_search_window: float = _opt(7.0, "half-width of the translational loop-closure search", unit="m", ge=0)
    angular_search_window: float = _opt(math.radians(30.0), "half-width of the rotational loop-closure search",
                                        unit="rad", ge=0, le=math.pi)
    branch_and_bound_depth: int = _opt(7, "levels of the precomputation grid stack", ge=1, le=24)
    # carto addition (not in Cartographer): coarse-to-fine search, the whole window on the
    # 8-cell level then full resolution around the best; same answer as the plain search
    # on the benchmarks, several times faster.
    multilevel: bool = _opt(False, "carto: coarse-to-fine branch and bound (faster, same result in practice)")


@dataclass(frozen=True)
class ConstraintCeresScanMatcher:
    occupied_space_weight: float = _opt(20.0, "weight of the scan-to-grid residuals", ge=0)
    translation_weight: float = _opt(10.0, "weight pulling the translation to the fast matcher's result", ge=0)
    rotation_weight: float = _opt(1.0, "weight pulling the rotation to the fast matcher's result", ge=0)
    ceres_solver_options: CeresSolverOptions = _solver(10, "Levenberg-Marquardt iterations per refinement")


@dataclass(frozen=True)
class ConstraintBuilder:
    sampling_ratio: float = _opt(0.3, "fraction of candidate node-submap pairs searched for loop closures",
                                 ge=0, le=1)
    max_constraint_distance: float = _opt(15.0, "farthest node-submap distance searched", unit="m", ge=0)
    min_score: float = _opt(0.55, "lowest fast-matcher score accepted as a loop closure", ge=0, le=1)
    global_localization_min_score: float = _opt(0.6, "lowest score accepted by a whole-submap search",
                                                ge=0, le=1)
    loop_closure_translation_weight: float = _opt(1.1e4, "weight of a loop closure's translation", ge=0)
    loop_closure_rotation_weight: float = _opt(1e5, "weight of a loop closure's rotation", ge=0)
    fast_correlative_scan_matcher: FastCorrelativeScanMatcher = _section(FastCorrelativeScanMatcher)
    ceres_scan_matcher: ConstraintCeresScanMatcher = _section(ConstraintCeresScanMatcher)
    # carto additions (not in Cartographer; 0 keeps Cartographer's behaviour).
    min_search_distance: float = _opt(0.0, "carto: a node searches for loop closures only when it moved this far "
                                      "(or turned min_search_angle) since the last node that searched",
                                      unit="m", ge=0)
    min_search_angle: float = _opt(0.0, "carto: see min_search_distance (0 with a positive distance: "
                                   "distance alone decides)", unit="rad", ge=0, le=math.pi)
    max_loop_closure_residual: float = _opt(0.0, "carto: after the final optimization, loop closures whose "
                                            "translation residual exceeds this are removed and the graph is "
                                            "optimized again (0: keep all)", unit="m", ge=0)
    confirm_loop_closures: bool = _opt(False, "carto: a loop closure counts only once a closure of another nearby node "
                                              "to the same submap agrees with it (Karto's chain rule)")
    max_see_through: float = _opt(1.0, "carto: a loop closure is rejected when more than this share of the "
                                  "node's rays would pass through a wall of the submap (1: no check)", ge=0, le=1)
    max_drift: float = _opt(0.0, "carto: a loop closure between a node and a submap of its own trajectory is "
                            "rejected when it moves the node further from where the graph puts it than "
                            "0.5 m + this share of the local-SLAM travel between them (0: no check): a node a "
                            "few metres of travel from the submap cannot be metres off, only an aliased "
                            "match (a corridor) says so", ge=0)
    window_edge_margin: float = _opt(0.0, "carto: a windowed match this close to the edge of the search window "
                                     "(in x or y) is rejected: the best pose inside a window that does not hold "
                                     "the true one lies on its edge, and along a corridor it is an aliased match "
                                     "(0: no check)", unit="m", ge=0)
    precomputation_memory: float = _opt(256.0, "carto: memory for the finished submaps' precomputation grids "
                                        "(branch and bound); beyond it the least recently searched are dropped "
                                        "and rebuilt when searched again (the map does not change; the "
                                        "seed's submap cache). carto map --memory-budget sets it",
                                        unit="MB", gt=0)


@dataclass(frozen=True)
class OptimizationProblem:
    huber_scale: float = _opt(1e1, "scale of the Huber loss on loop closures", gt=0)
    acceleration_weight: float = _opt(1.1e2, "weight of IMU acceleration terms (unused without IMU)", ge=0)
    rotation_weight: float = _opt(1.6e4, "weight of IMU rotation terms (unused without IMU)", ge=0)
    local_slam_pose_translation_weight: float = _opt(1e5, "weight of consecutive local SLAM translations", ge=0)
    local_slam_pose_rotation_weight: float = _opt(1e5, "weight of consecutive local SLAM rotations", ge=0)
    odometry_translation_weight: float = _opt(1e5, "weight of consecutive odometry translations", ge=0)
    odometry_rotation_weight: float = _opt(1e5, "weight of consecutive odometry rotations", ge=0)
    ceres_solver_options: CeresSolverOptions = _solver(50, "solver iterations per periodic optimization")


@dataclass(frozen=True)
class PoseGraph:
    optimize_every_n_nodes: int = _opt(90, "run a global optimization after this many nodes (0: only at the end)",
                                       ge=0)
    constraint_builder: ConstraintBuilder = _section(ConstraintBuilder)
    matcher_translation_weight: float = _opt(5e2, "weight of intra-submap constraints' translation", ge=0)
    matcher_rotation_weight: float = _opt(1.6e3, "weight of intra-submap constraints' rotation", ge=0)
    optimization_problem: OptimizationProblem = _section(OptimizationProblem)
    max_num_final_iterations: int = _opt(200, "solver iterations of the final optimization", ge=1)
    global_sampling_ratio: float = _opt(0.003, "fraction of nodes tried against every submap of other trajectories",
                                        ge=0, le=1)
    global_constraint_search_after_n_seconds: float = _opt(10.0, "search all submaps when no loop closure was "
                                                           "found for this long", unit="s", ge=0)


# --------------------------------------------------------------------------- gmapping


@dataclass(frozen=True)
class GMapping:
    """``carto map --algorithm gmapping``: the Rao-Blackwellized particle filter (carto_cli/gmapping).

    Keys are GMapping's own parameter names (slam_gmapping's ROS parameters), so a launch file's
    ``<param name="linearUpdate" value="0.1"/>`` is ``--set gmapping.linearUpdate=0.1``; defaults are the
    seeds' template (50 particles, delta 0.03, ogain 3, resampleThreshold 0.5, linearUpdate 0.1,
    angularUpdate 0.2) over GMapping's own defaults, except delta (GMapping's 0.05, measured).
    """

    # 100, not the seeds' 50: with the gain's count fixed (gainParticles) more particles sample the same posterior
    # more densely: aces 0.048-0.117 m over five seeds at 50, 0.046-0.049 m over four at 100 (docs/gmapping.md)
    particles: int = _opt(100, "number of particles (each with its own map, shared copy-on-write)", ge=1)
    # GMapping's own 0.05, not the seeds' 0.03: at 0.03 the +-1-cell search kernel is too narrow to catch a
    # particle the motion model put a few centimetres off (aces 1.30 m vs 0.17 m, fhw 1.04 vs 0.067; intel,
    # edmonton no worse; docs/gmapping.md).
    delta: float = _opt(0.05, "map resolution", unit="m", gt=0)
    maxRange: float = _opt(80.0, "beams longer than this are no return", unit="m", gt=0)
    maxUrange: float = _opt(80.0, "usable range: longer beams clear free space up to it and are not matched",
                            unit="m", gt=0)
    sigma: float = _opt(0.05, "scan matcher: standard deviation of an endpoint's distance to the map's wall",
                        unit="m", gt=0)
    kernelSize: int = _opt(1, "scan matcher: cells searched around each endpoint for a wall", ge=0, le=4)
    lstep: float = _opt(0.05, "scan matcher: initial translational step of the hill climbing", unit="m", gt=0)
    astep: float = _opt(0.05, "scan matcher: initial rotational step of the hill climbing", unit="rad", gt=0)
    iterations: int = _opt(5, "scan matcher: times the steps are halved before the climb stops", ge=0)
    sweepSigmas: float = _opt(
        3.0, "scan matcher: before climbing, try headings every astep/2 within this many standard deviations of "
        "the motion model's rotational noise (capped at 45 degrees); 0: GMapping's climb alone, which cannot "
        "reach a heading a key scan's turn left tens of degrees off", ge=0)
    lsigma: float = _opt(0.075, "likelihood: squared endpoint distance is divided by this", unit="m^2", gt=0)
    ogain: float = _opt(3.0, "weights are exp(log-likelihood / (ogain x gainParticles)): smooths resampling",
                        gt=0)
    gainParticles: int = _opt(
        50, "carto: the particle count ogain is scaled by; 0: the filter's own count (GMapping), which flattens "
        "the weights as particles are added until resampling no longer selects (orebro at 150 particles fails "
        "on every seed tried; docs/gmapping.md)", ge=0)
    lskip: int = _opt(0, "likelihood: use every (lskip+1)-th beam", ge=0)
    minimumScore: float = _opt(0.0, "a scan match scoring below this keeps the motion model's pose", ge=0)
    unknownIsNoEvidence: bool = _opt(
        False, "likelihood: an endpoint in never-observed space costs what a wall at the kernel's edge would "
        "instead of what one in free space does (GMapping); off: with it a pose putting its endpoints where the "
        "map knows nothing scores as well as a match (aces 16 m instead of 0.17 m, docs/gmapping.md)")
    srr: float = _opt(0.1, "odometry error in translation as a function of translation", ge=0)
    srt: float = _opt(0.2, "odometry error in rotation as a function of translation", unit="rad/m", ge=0)
    str: float = _opt(0.1, "odometry error in translation as a function of rotation", unit="m/rad", ge=0)
    stt: float = _opt(0.2, "odometry error in rotation as a function of rotation", ge=0)
    linearUpdate: float = _opt(0.1, "process a scan once the robot has travelled this far", unit="m", ge=0)
    angularUpdate: float = _opt(0.2, "process a scan once the robot has turned this far", unit="rad", ge=0)
    temporalUpdate: float = _opt(-1.0, "process a scan at least this often however little the robot moved "
                                 "(negative: never for time alone)", unit="s")
    refineIterations: int = _opt(
        2, "carto: rounds of re-matching every processed scan of the best particle against the map of all of "
        "them at the end (a correlative search within 0.4 m / 3 deg, then Cartographer's least-squares matcher), "
        "the map drawn again from the moved scans; "
        "0: the particle's poses and map as the filter left them (GMapping)", ge=0)
    refineLoops: bool = _opt(
        True, "carto: before the re-matching, match every processed scan of the best particle against the scans "
        "of other times near it and optimize the trajectory with those loop closures (a pose graph), so a "
        "revisit that came back a few decimetres off no longer leaves two versions of the walls; false: "
        "GMapping's trajectory as the filter left it")
    resampleThreshold: float = _opt(0.5, "resample when Neff falls below this share of the particles", gt=0, le=1)
    adaptiveResampling: bool = _opt(True, "the seed's threshold: resampleThreshold / (1 + 2 H), H the best "
                                    "particle's map entropy (mean bits per known cell); uncertain maps resample less")
    llsamplerange: float = _opt(0.01, "proposal: translational half-range sampled around the match", unit="m", ge=0)
    llsamplestep: float = _opt(0.01, "proposal: translational step of those samples", unit="m", gt=0)
    lasamplerange: float = _opt(0.005, "proposal: rotational half-range sampled around the match", unit="rad", ge=0)
    lasamplestep: float = _opt(0.005, "proposal: rotational step of those samples", unit="rad", gt=0)
    seed: int = _opt(0, "random seed: the same input and seed give byte-identical outputs", ge=0)


# --------------------------------------------------------------------------- relocalization


@dataclass(frozen=True)
class Relocalization:
    """``carto relocalize``: finding a scan's pose in a saved map, with or without a prior.

    A prior with sigma_xy <= max_reliable_sigma_xy and sigma_yaw <= max_reliable_sigma_yaw is
    searched in a window of window_sigmas x sigma around it (clamped to the min/max windows),
    in the submaps within a radius of it that grows as the prior gets less certain; otherwise,
    or when that finds nothing above min_score, every nearby submap and then every submap is
    searched whole.
    """

    min_score: float = _opt(0.55, "lowest score a search around a prior accepts", ge=0, le=1)
    global_min_score: float = _opt(0.6, "lowest score a whole-submap search (fallback, no prior) accepts",
                                   ge=0, le=1)
    global_search_min_score: float = _opt(
        0.5, "whole-submap searches keep candidates down to this score on the coarser search points (which score "
        "~0.07 below the refined pose); the refined pose is still judged against global_min_score", ge=0, le=1)
    max_see_through: float = _opt(
        0.13, "a match where more than this share of the scan's rays pass through walls of the map is rejected "
        "(aliased places put the endpoints on walls, rarely the rays through free space)", ge=0, le=1)
    min_inlier_fraction: float = _opt(
        0.9, "an answer with less than this share of its points on walls of the map (among the points on cells the "
        "map knows) is 'lost': a scan from elsewhere can reach the score with half its points on walls", ge=0, le=1)
    max_ambiguity: float = _opt(
        0.95, "an answer whose best rival at a different place (> 1 m or > 10 deg away) scores at least this "
        "share of its score is 'ambiguous', not 'ok'", gt=0, le=1)
    context_scans: int = _opt(
        8, "an answer no window around the prior confirmed (a fallback's, a whole-map search's) is checked by up "
        "to this many scans of the recording each way from the query, one each 0.5 m of odometry (0: off)", ge=0)
    context_max_through_walls: int = _opt(
        2, "... and is 'lost' when more of those than this see through walls of the map (more than max_see_through "
        "of their rays): one scan of another building can fit a corridor, the robot's path there cannot", ge=0)
    fallback_max_submaps: int = _opt(
        8, "a reliable prior no window confirms is searched for in at most this many more submaps, nearest first "
        "(0: no limit); such a prior is mostly a place the map never saw, where failing fast is the answer", ge=0)
    default_sigma_xy: float = _opt(0.5, "position uncertainty of a prior given without one", unit="m", gt=0)
    default_sigma_yaw: float = _opt(math.radians(10.0), "heading uncertainty of a prior given without one",
                                    unit="rad", gt=0, le=math.pi)
    max_reliable_sigma_xy: float = _opt(1.2, "a prior less certain than this is not searched around",
                                        unit="m", gt=0)
    max_reliable_sigma_yaw: float = _opt(math.radians(15.0), "a prior less certain than this is not searched "
                                         "around", unit="rad", gt=0, le=math.pi)
    window_sigmas: float = _opt(3.0, "search windows are this many sigmas of the prior", gt=0)
    min_linear_search_window: float = _opt(0.3, "smallest half-width of the window around a prior",
                                           unit="m", ge=0)
    max_linear_search_window: float = _opt(4.0, "largest half-width of the window around a prior", unit="m", ge=0)
    min_angular_search_window: float = _opt(math.radians(5.0), "smallest rotational half-width around a prior",
                                            unit="rad", ge=0, le=math.pi)
    max_angular_search_window: float = _opt(math.radians(45.0), "largest rotational half-width around a prior",
                                            unit="rad", ge=0, le=math.pi)
    branch_and_bound_depth: int = _opt(7, "levels of the precomputation grid stacks", ge=1, le=24)
    high_confidence_sigma_xy: float = _opt(0.3, "a prior at most this uncertain is of high confidence",
                                           unit="m", gt=0)
    high_confidence_radius: float = _opt(4.0, "submaps searched around a high-confidence prior", unit="m", ge=0)
    medium_confidence_radius: float = _opt(8.0, "submaps searched around a reliable, not high-confidence prior",
                                           unit="m", ge=0)
    low_confidence_radius: float = _opt(15.0, "submaps searched whole around an unreliable prior", unit="m", ge=0)
    max_windowed_submaps: int = _opt(3, "a search around a prior tries at most this many of the filtered submaps, "
                                     "those whose scans were taken nearest the prior first", ge=1)
    max_prior_distance: float = _opt(15.0, "a prior farther than this from every submap is an error", unit="m",
                                     gt=0)
    corridor_forward_range: float = _opt(10.0, "corridor mode: submaps up to this far ahead of or behind the prior",
                                         unit="m", ge=0)
    corridor_side_range: float = _opt(2.0, "corridor mode: submaps up to this far to either side of the prior",
                                      unit="m", ge=0)
    max_refinement_translation: float = _opt(0.3, "a refinement moving the search's pose further is not trusted",
                                             unit="m", ge=0)
    max_refinement_rotation: float = _opt(math.radians(5.0), "a refinement turning the search's pose further "
                                          "is not trusted", unit="rad", ge=0, le=math.pi)
    multilevel_global_search: bool = _opt(True, "whole-submap searches go coarse to fine (faster, not exact)")
    cache_budget_mb: float = _opt(512.0, "memory for precomputation grids; least recently used ones are dropped",
                                  unit="MB", gt=0)


@dataclass(frozen=True)
class Options:
    trajectory_builder_2d: TrajectoryBuilder2D = _section(TrajectoryBuilder2D)
    pose_graph: PoseGraph = _section(PoseGraph)
    relocalization: Relocalization = _section(Relocalization)
    gmapping: GMapping = _section(GMapping)


# --------------------------------------------------------------------------- introspection


@cache
def hints(cls: type) -> dict[str, Any]:
    """The resolved field types of an options dataclass (the annotations are strings)."""
    return typing.get_type_hints(cls)


def is_section(tp: Any) -> bool:
    """Whether a field type is a section (a nested options dataclass) rather than a value."""
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


@dataclass(frozen=True)
class OptionInfo:
    """What ``carto options`` shows of one option."""

    name: str
    type: str  # 'int' | 'float' | 'bool'
    default: Any
    unit: str
    doc: str
    bounds: str  # e.g. '> 0.5 and < 1', '' when unbounded


def bounds_text(md: Mapping[str, Any]) -> str:
    """An option's bounds as text, e.g. '> 0.5 and < 1' ('' when unbounded), from its field metadata."""
    parts = [f"{op} {md[k]:g}" for k, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="))
             if md.get(k) is not None]
    return " and ".join(parts)


class Leaf(NamedTuple):
    """One option as the schema declares it."""

    name: str  # dotted key
    field: dataclasses.Field
    type: type
    doc: str  # the owning section's wording when it gives one (shared sections such as CeresSolverOptions)


def walk(cls: type, prefix: str = "", docs: dict[str, str] | None = None) -> Iterator[Leaf]:
    """Every leaf of ``cls``, in declaration order."""
    types = hints(cls)
    for f in dataclasses.fields(cls):
        tp = types[f.name]
        if is_section(tp):
            yield from walk(tp, f"{prefix}{f.name}.", f.metadata.get("docs"))
        else:
            doc = (docs or {}).get(f.name, f.metadata.get("doc", ""))
            yield Leaf(f"{prefix}{f.name}", f, tp, doc)


@cache
def _all_names() -> tuple[str, ...]:
    return tuple(leaf.name for leaf in walk(Options))


@cache
def _section_names() -> tuple[str, ...]:
    out = set()
    for name in _all_names():
        parts = name.split(".")
        for i in range(1, len(parts)):
            out.add(".".join(parts[:i]))
    return tuple(sorted(out))


def option_names() -> list[str]:
    """Every dotted option key, in declaration order."""
    return list(_all_names())


def option_info() -> list[OptionInfo]:
    """Name, type, default, unit, doc and bounds of every option (for ``carto options``)."""
    # Defaults are read from a default instance: a shared section's leaf (CeresSolverOptions)
    # gets its default from its owner, not from its own field.
    defaults = Options()
    return [
        OptionInfo(leaf.name, leaf.type.__name__, get_option(defaults, leaf.name),
                   leaf.field.metadata.get("unit", ""), leaf.doc, bounds_text(leaf.field.metadata))
        for leaf in walk(Options)
    ]


def get_option(options: Options, key: str) -> Any:
    """The value (or section) at a dotted key."""
    obj: Any = options
    for part in key.split("."):
        if not dataclasses.is_dataclass(obj) or part not in {f.name for f in dataclasses.fields(obj)}:
            raise CartoError(f"unknown option '{key}'{suggestion(key)}")
        obj = getattr(obj, part)
    return obj


def options_to_dict(options: Options) -> dict:
    """The options as nested plain dicts, keyed as in a profile."""
    return dataclasses.asdict(options)


def changed_options(options: Options, base: Options | None = None) -> dict[str, Any]:
    """Dotted key -> value for every option that differs from ``base`` (the defaults)."""
    base = Options() if base is None else base
    return {name: get_option(options, name) for name in _all_names()
            if get_option(options, name) != get_option(base, name)}


# --------------------------------------------------------------------------- suggestions


def suggestion(written: str) -> str:
    """"; did you mean 'x'?" for the valid key closest to what was written, or ''."""
    names = _all_names() + _section_names()
    low = written.lower()
    # Lua spells the roots TRAJECTORY_BUILDER_2D / POSE_GRAPH: lower-casing fixes that.
    for n in names:
        if n == low:
            return f"; did you mean '{n}'?"
    # A key given without its sections, e.g. 'submaps.num_range_data'.
    tails = [n for n in names if n.endswith("." + low)]
    if len(tails) == 1:
        return f"; did you mean '{tails[0]}'?"
    # Right leaf name in the wrong section, e.g. 'pose_graph.min_score'.
    leaf = low.rsplit(".", 1)[-1]
    root = low.split(".", 1)[0]
    same_leaf = [n for n in names if n.endswith("." + leaf) and n.startswith(root + ".")]
    if len(same_leaf) == 1:
        return f"; did you mean '{same_leaf[0]}'?"
    close = difflib.get_close_matches(low, names, n=1, cutoff=0.6)
    if close:
        return f"; did you mean '{close[0]}'?"
    if same_leaf or tails:
        return "; did you mean one of " + ", ".join(f"'{n}'" for n in (same_leaf or tails)) + "?"
    return ""
