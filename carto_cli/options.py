"""Typed options mirroring Cartographer's 2D configuration, loaded from YAML profiles.

Names and defaults follow cartographer/configuration_files/trajectory_builder_2d.lua
and pose_graph.lua, so a line such as ``POSE_GRAPH.constraint_builder.min_score = 0.65``
translates to ``--set pose_graph.constraint_builder.min_score=0.65``. Options that only
matter in 3D or to ROS (grid types, thread counts, logging flags) are left out on
purpose: an option that does nothing is worse than a missing one.

Deviations from the Lua defaults, and why:
- ``use_imu_data`` is false: carto maps from recordings that often lack an IMU, and
  Cartographer's ``true`` would make it wait for IMU data forever.

Loading is layered: the packaged ``default.yaml``, then an optional profile, then
``--set key=value`` overrides. Every layer is checked for unknown keys, types and
ranges, and errors name the key and where it came from. Lengths are metres, times
seconds and angles radians everywhere except on the command line, where an explicit
``deg`` suffix (``--set ...angular_search_window=20deg``) is accepted.
"""
from __future__ import annotations

import dataclasses
import difflib
import math
import re
import typing
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Iterable

import yaml

from carto_cli.core.errors import CartoError

__all__ = [
    "Options", "TrajectoryBuilder2D", "PoseGraph", "Relocalization",
    "load_options", "apply_overrides", "validate_options",
    "options_to_dict", "dump_options_yaml", "option_names", "option_info", "OptionInfo",
    "get_option", "changed_options", "profiles_dir", "list_profiles",
]

PROFILE_SUFFIXES = (".yaml", ".yml")


def _opt(default, doc: str, *, unit: str = "", gt=None, ge=None, lt=None, le=None):
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


@dataclass(frozen=True)
class CeresSolverOptions20:
    max_num_iterations: int = _opt(20, "Levenberg-Marquardt iterations per match", ge=1)


@dataclass(frozen=True)
class LocalCeresScanMatcher:
    occupied_space_weight: float = _opt(1.0, "weight of the scan-to-grid residuals", ge=0)
    translation_weight: float = _opt(10.0, "weight pulling the translation to the prediction", ge=0)
    rotation_weight: float = _opt(40.0, "weight pulling the rotation to the initial angle", ge=0)
    ceres_solver_options: CeresSolverOptions20 = _section(CeresSolverOptions20)


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
class TrajectoryBuilder2D:
    min_range: float = _opt(0.0, "returns closer than this are dropped", unit="m", ge=0)
    max_range: float = _opt(30.0, "returns farther than this become misses", unit="m", gt=0)
    min_z: float = _opt(-0.8, "points below this height are dropped (point clouds only)", unit="m")
    max_z: float = _opt(2.0, "points above this height are dropped (point clouds only)", unit="m")
    missing_data_ray_length: float = _opt(5.0, "length of the free ray inserted for a return beyond max_range",
                                          unit="m", gt=0)
    num_accumulated_range_data: int = _opt(1, "scans accumulated into one before matching", ge=1)
    voxel_filter_size: float = _opt(0.025, "edge of the fixed voxel filter", unit="m", gt=0)
    adaptive_voxel_filter: AdaptiveVoxelFilter = _section(AdaptiveVoxelFilter)
    loop_closure_adaptive_voxel_filter: LoopClosureAdaptiveVoxelFilter = _section(LoopClosureAdaptiveVoxelFilter)
    use_online_correlative_scan_matching: bool = _opt(False, "run the real-time correlative matcher before least squares")
    real_time_correlative_scan_matcher: RealTimeCorrelativeScanMatcher = _section(RealTimeCorrelativeScanMatcher)
    ceres_scan_matcher: LocalCeresScanMatcher = _section(LocalCeresScanMatcher)
    motion_filter: MotionFilter = _section(MotionFilter)
    imu_gravity_time_constant: float = _opt(10.0, "time constant of the gravity low-pass filter", unit="s", gt=0)
    pose_extrapolator: PoseExtrapolator = _section(PoseExtrapolator)
    submaps: Submaps = _section(Submaps)
    use_imu_data: bool = _opt(False, "use IMU angular velocity for the yaw prediction (2D does not need it)")


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
class CeresSolverOptions10:
    max_num_iterations: int = _opt(10, "Levenberg-Marquardt iterations per refinement", ge=1)


@dataclass(frozen=True)
class ConstraintCeresScanMatcher:
    occupied_space_weight: float = _opt(20.0, "weight of the scan-to-grid residuals", ge=0)
    translation_weight: float = _opt(10.0, "weight pulling the translation to the fast matcher's result", ge=0)
    rotation_weight: float = _opt(1.0, "weight pulling the rotation to the fast matcher's result", ge=0)
    ceres_solver_options: CeresSolverOptions10 = _section(CeresSolverOptions10)


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


@dataclass(frozen=True)
class CeresSolverOptions50:
    max_num_iterations: int = _opt(50, "solver iterations per periodic optimization", ge=1)


@dataclass(frozen=True)
class OptimizationProblem:
    huber_scale: float = _opt(1e1, "scale of the Huber loss on loop closures", gt=0)
    acceleration_weight: float = _opt(1.1e2, "weight of IMU acceleration terms (unused without IMU)", ge=0)
    rotation_weight: float = _opt(1.6e4, "weight of IMU rotation terms (unused without IMU)", ge=0)
    local_slam_pose_translation_weight: float = _opt(1e5, "weight of consecutive local SLAM translations", ge=0)
    local_slam_pose_rotation_weight: float = _opt(1e5, "weight of consecutive local SLAM rotations", ge=0)
    odometry_translation_weight: float = _opt(1e5, "weight of consecutive odometry translations", ge=0)
    odometry_rotation_weight: float = _opt(1e5, "weight of consecutive odometry rotations", ge=0)
    ceres_solver_options: CeresSolverOptions50 = _section(CeresSolverOptions50)


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
        0.2, "a match where more than this share of the scan's rays pass through walls of the map is rejected "
        "(aliased places put the endpoints on walls, rarely the rays through free space)", ge=0, le=1)
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


# --------------------------------------------------------------------------- introspection


@lru_cache(maxsize=None)
def _hints(cls) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _is_section(tp) -> bool:
    return isinstance(tp, type) and dataclasses.is_dataclass(tp)


@dataclass(frozen=True)
class OptionInfo:
    name: str
    type: str  # 'int' | 'float' | 'bool'
    default: Any
    unit: str
    doc: str
    bounds: str  # e.g. '> 0.5 and < 1', '' when unbounded


def _bounds_text(md) -> str:
    parts = [f"{op} {md[k]:g}" for k, op in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<=")) if md.get(k) is not None]
    return " and ".join(parts)


def _walk(cls, prefix: str = ""):
    """(dotted name, dataclass field, type) for every leaf, in declaration order."""
    hints = _hints(cls)
    for f in dataclasses.fields(cls):
        tp = hints[f.name]
        if _is_section(tp):
            yield from _walk(tp, f"{prefix}{f.name}.")
        else:
            yield f"{prefix}{f.name}", f, tp


@lru_cache(maxsize=None)
def _all_names() -> tuple[str, ...]:
    return tuple(name for name, _, _ in _walk(Options))


@lru_cache(maxsize=None)
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
    return [
        OptionInfo(name, tp.__name__, f.default, f.metadata.get("unit", ""), f.metadata.get("doc", ""),
                   _bounds_text(f.metadata))
        for name, f, tp in _walk(Options)
    ]


def get_option(options: Options, key: str) -> Any:
    """The value (or section) at a dotted key."""
    obj: Any = options
    for part in key.split("."):
        if not dataclasses.is_dataclass(obj) or part not in {f.name for f in dataclasses.fields(obj)}:
            raise CartoError(f"unknown option '{key}'{_suggestion(key)}")
        obj = getattr(obj, part)
    return obj


def options_to_dict(options: Options) -> dict:
    return dataclasses.asdict(options)


def dump_options_yaml(options: Options) -> str:
    """The complete options as YAML that ``load_options`` reads back to the same values."""
    return yaml.safe_dump(options_to_dict(options), sort_keys=False, default_flow_style=False)


def changed_options(options: Options, base: Options | None = None) -> dict[str, Any]:
    """Dotted key -> value for every option that differs from ``base`` (the defaults)."""
    base = Options() if base is None else base
    return {name: get_option(options, name) for name in _all_names()
            if get_option(options, name) != get_option(base, name)}


# --------------------------------------------------------------------------- suggestions


def _suggestion(written: str) -> str:
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


# --------------------------------------------------------------------------- YAML


class _Loader(yaml.SafeLoader):
    """SafeLoader that also reads '1e5' and '1.1e4' as floats.

    PyYAML follows YAML 1.1, which wants a dot and a signed exponent; Cartographer's
    Lua files are full of '1e5', and silently getting a string would be a trap.
    """


_Loader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."),
)


def _parse_scalar(text: str) -> Any:
    try:
        return yaml.load(text, Loader=_Loader)
    except yaml.YAMLError:
        # Not YAML (e.g. an unbalanced quote): keep the text, the type check will name it.
        return text


def _read_yaml(path: Path) -> tuple[dict, dict[str, int]]:
    """(mapping, dotted key -> 1-based line) of a YAML options file."""
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CartoError("no such profile file", path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise CartoError(f"cannot read profile: {e}", path) from None
    loader = _Loader(text)
    lines: dict[str, int] = {}
    try:
        node = loader.get_single_node()
        if node is None:
            return {}, lines
        if not isinstance(node, yaml.MappingNode):
            raise CartoError(f"line {node.start_mark.line + 1}: expected a mapping of option names to values", path)
        data = _construct(loader, node, "", lines, path)
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(e, "problem", None) or str(e)
        raise CartoError(f"{where}invalid YAML: {problem}", path) from None
    finally:
        loader.dispose()
    return data, lines


def _construct(loader, node, prefix: str, lines: dict[str, int], path: Path):
    if not isinstance(node, yaml.MappingNode):
        return loader.construct_object(node, deep=True)
    out: dict = {}
    for key_node, value_node in node.value:
        key = loader.construct_object(key_node, deep=True)
        line = key_node.start_mark.line + 1
        if not isinstance(key, str):
            raise CartoError(f"line {line}: option names are text, got {key!r}", path)
        full = prefix + key
        if key in out:
            raise CartoError(f"line {line}: '{full}' is given twice (first on line {lines[full]})", path)
        lines[full] = line
        out[key] = _construct(loader, value_node, full + ".", lines, path)
    return out


# --------------------------------------------------------------------------- applying values


_DEG = re.compile(r"^\s*([-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)\s*deg\s*$")


@dataclass
class _Layer:
    """Where values come from, for error messages."""

    path: Path | None      # the file, for CartoError.path; None for --set and code
    lines: dict[str, int]
    cli: bool

    def fail(self, key: str, message: str) -> CartoError:
        if self.cli:
            return CartoError(f"--set {key}: {message}")
        line = self.lines.get(key)
        where = f"line {line}: " if line else ""
        return CartoError(f"{where}{key}: {message}", self.path)


def _show(value: Any) -> str:
    """A value as the user would have typed it in YAML."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if value is None:
        return "null (no value)"
    return repr(value)


def _coerce(value: Any, tp, f: dataclasses.Field, key: str, layer: _Layer):
    unit = f.metadata.get("unit", "")
    # Values handed over by code (layer without a file) get no unit parsing at all.
    if isinstance(value, str) and _DEG.match(value) and (layer.cli or layer.path is not None):
        if unit != "rad":
            raise layer.fail(key, f"'deg' is only allowed on angles; this option is in {unit or 'no unit'}")
        degrees = float(_DEG.match(value).group(1))
        if not layer.cli:
            raise layer.fail(key, f"angles in profile files are radians: write {math.radians(degrees):.10g} "
                                  f"for {degrees:g}deg")
        value = math.radians(degrees)
    if tp is bool:
        if not isinstance(value, bool):
            raise layer.fail(key, f"expected true or false, got {_show(value)}")
    elif tp is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise layer.fail(key, f"expected an integer, got {_show(value)}")
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            hint = " (radians; on the command line '20deg' also works)" if unit == "rad" and layer.cli else ""
            raise layer.fail(key, f"expected a number, got {_show(value)}{hint}")
        value = float(value)
        if not math.isfinite(value):
            raise layer.fail(key, f"expected a finite number, got {_show(value)}")
    else:  # pragma: no cover - only int/float/bool leaves are declared
        raise TypeError(f"unsupported option type {tp!r} for {key}")
    md = f.metadata
    shown = f"{value:g}" if isinstance(value, float) else str(value)
    if unit:
        shown += f" {unit}"
    for k, op, bad in (("gt", ">", lambda v, b: v <= b), ("ge", ">=", lambda v, b: v < b),
                       ("lt", "<", lambda v, b: v >= b), ("le", "<=", lambda v, b: v > b)):
        bound = md.get(k)
        if bound is not None and bad(value, bound):
            raise layer.fail(key, f"must be {_bounds_text(md)}, got {shown}")
    return value


def _apply(obj, mapping: dict, layer: _Layer, prefix: str):
    cls = type(obj)
    hints = _hints(cls)
    by_name = {f.name: f for f in dataclasses.fields(cls)}
    for key, value in mapping.items():
        if not isinstance(key, str):
            raise layer.fail(prefix.rstrip(".") or "(top level)", f"option names are text, got {key!r}")
        head, dot, rest = key.partition(".")
        full = prefix + head
        f = by_name.get(head)
        if f is None:
            written = prefix + key
            raise layer.fail(written, f"unknown option{_suggestion(written)}")
        tp = hints[head]
        if _is_section(tp):
            current = getattr(obj, head)
            if dot:
                new = _apply(current, {rest: value}, layer, full + ".")
            elif isinstance(value, dict):
                new = _apply(current, value, layer, full + ".")
            elif value is None:  # 'submaps:' with nothing under it
                new = current
            else:
                keys = ", ".join(n.name for n in dataclasses.fields(tp))
                raise layer.fail(full, f"is a section, not a value; set one of its keys: {keys}")
            obj = dataclasses.replace(obj, **{head: new})
        else:
            if dot:
                raise layer.fail(prefix + key, f"'{full}' is a value, not a section")
            obj = dataclasses.replace(obj, **{head: _coerce(value, tp, f, full, layer)})
    return obj


def validate_options(options: Options, where: str | Path | None = None) -> Options:
    """Checks that involve more than one option; returns ``options`` unchanged."""
    tb = options.trajectory_builder_2d
    if tb.min_range >= tb.max_range:
        raise CartoError(f"trajectory_builder_2d.min_range ({tb.min_range:g} m) must be less than "
                         f"trajectory_builder_2d.max_range ({tb.max_range:g} m)", where)
    if tb.min_z > tb.max_z:
        raise CartoError(f"trajectory_builder_2d.min_z ({tb.min_z:g} m) must not exceed "
                         f"trajectory_builder_2d.max_z ({tb.max_z:g} m)", where)
    return options


def _parse_assignment(item: str) -> tuple[str, Any]:
    key, eq, text = item.partition("=")
    key = key.strip()
    if not eq or not key:
        raise CartoError(f"--set expects key=value, got {item!r}")
    if not text.strip():
        raise CartoError(f"--set {key}: no value given")
    return key, _parse_scalar(text)


def apply_overrides(options: Options, overrides: Iterable[str] | dict[str, Any]) -> Options:
    """``options`` with ``key=value`` strings (as given to --set) or a {dotted key: value} dict applied.

    Dict values are taken as they are (no YAML parsing, no 'deg' suffix): that form is
    for code such as ``tune``, which already has typed values.
    """
    if isinstance(overrides, dict):
        layer = _Layer(None, {}, cli=False)
        for key, value in overrides.items():
            options = _apply(options, {key: value}, layer, "")
        return validate_options(options)
    layer = _Layer(None, {}, cli=True)
    for item in overrides:
        key, value = _parse_assignment(item)
        options = _apply(options, {key: value}, layer, "")
    return validate_options(options, None)


# --------------------------------------------------------------------------- profiles


def profiles_dir() -> Path:
    """The directory of the packaged profiles (``carto_cli/profiles``)."""
    return Path(__file__).resolve().parent / "profiles"


def list_profiles() -> list[str]:
    """Names of the packaged profiles, 'default' included."""
    d = profiles_dir()
    return sorted(p.stem for p in d.iterdir() if p.suffix in PROFILE_SUFFIXES) if d.is_dir() else []


def _resolve_profile(profile: str | Path) -> Path:
    if isinstance(profile, Path):
        return profile
    text = str(profile)
    if text.endswith(PROFILE_SUFFIXES) or "/" in text or "\\" in text:
        return Path(text).expanduser()
    for suffix in PROFILE_SUFFIXES:
        candidate = profiles_dir() / f"{text}{suffix}"
        if candidate.is_file():
            return candidate
    names = list_profiles()
    close = difflib.get_close_matches(text, names, n=1)
    hint = f"; did you mean '{close[0]}'?" if close else ""
    raise CartoError(f"unknown profile '{text}'{hint} (profiles: {', '.join(names) or 'none'}; "
                     "a path ending in .yaml is read as a file)")


def _load_file(options: Options, path: Path) -> Options:
    data, lines = _read_yaml(path)
    layer = _Layer(path, lines, cli=False)
    return _apply(options, data, layer, "")


def load_options(profile: str | Path | None = None, overrides: Iterable[str] = ()) -> Options:
    """The packaged defaults, then ``profile`` (a name from ``profiles_dir()`` or a .yaml path), then --set.

    Raises CartoError naming the key and the file (or --set) for unknown keys,
    wrong types, out-of-range values and malformed files.
    """
    default_path = profiles_dir() / "default.yaml"
    options = _load_file(Options(), default_path)
    if profile is not None:
        path = _resolve_profile(profile)
        if path.resolve() != default_path.resolve():
            options = _load_file(options, path)
    # Cross-option checks run once, on the final values: a profile may set
    # min_range past the default max_range and --set may then fix max_range.
    return apply_overrides(options, list(overrides))
