"""The options schema: Cartographer's defaults, the option list ``carto options`` shows, lookups."""
import dataclasses
import math

import pytest

from carto_cli.core.errors import CartoError
from carto_cli.options import CeresSolverOptions, Options, get_option, option_info, option_names, suggestion
from carto_cli.options.schema import walk


def test_cartographer_defaults():
    o = Options()
    tb, pg = o.trajectory_builder_2d, o.pose_graph
    assert (tb.min_range, tb.max_range, tb.missing_data_ray_length) == (0.0, 30.0, 5.0)
    assert tb.num_accumulated_range_data == 1 and tb.voxel_filter_size == 0.025
    assert (tb.adaptive_voxel_filter.max_length, tb.adaptive_voxel_filter.min_num_points) == (0.5, 200)
    assert (tb.loop_closure_adaptive_voxel_filter.max_length,
            tb.loop_closure_adaptive_voxel_filter.min_num_points) == (0.9, 100)
    assert tb.use_online_correlative_scan_matching is False and tb.use_imu_data is False
    assert tb.real_time_correlative_scan_matcher.angular_search_window == pytest.approx(math.radians(20))
    assert (tb.ceres_scan_matcher.occupied_space_weight, tb.ceres_scan_matcher.translation_weight,
            tb.ceres_scan_matcher.rotation_weight) == (1.0, 10.0, 40.0)
    assert tb.ceres_scan_matcher.ceres_solver_options.max_num_iterations == 20
    assert (tb.motion_filter.max_time_seconds, tb.motion_filter.max_distance_meters) == (5.0, 0.2)
    assert tb.motion_filter.max_angle_radians == pytest.approx(math.radians(1))
    assert tb.pose_extrapolator.constant_velocity.pose_queue_duration == 0.001
    assert tb.submaps.num_range_data == 90 and tb.submaps.grid_options_2d.resolution == 0.05
    rdi = tb.submaps.range_data_inserter
    assert (rdi.insert_free_space, rdi.hit_probability, rdi.miss_probability) == (True, 0.55, 0.49)
    cb = pg.constraint_builder
    assert pg.optimize_every_n_nodes == 90
    assert (cb.sampling_ratio, cb.max_constraint_distance, cb.min_score, cb.global_localization_min_score) == \
        (0.3, 15.0, 0.55, 0.6)
    assert (cb.loop_closure_translation_weight, cb.loop_closure_rotation_weight) == (1.1e4, 1e5)
    fcsm = cb.fast_correlative_scan_matcher
    assert fcsm.linear_search_window == 7.0 and fcsm.branch_and_bound_depth == 7
    assert fcsm.angular_search_window == pytest.approx(math.radians(30))
    assert (cb.ceres_scan_matcher.occupied_space_weight, cb.ceres_scan_matcher.translation_weight,
            cb.ceres_scan_matcher.rotation_weight) == (20.0, 10.0, 1.0)
    assert (pg.matcher_translation_weight, pg.matcher_rotation_weight) == (5e2, 1.6e3)
    op = pg.optimization_problem
    assert op.huber_scale == 10.0 and op.ceres_solver_options.max_num_iterations == 50
    assert (op.local_slam_pose_translation_weight, op.odometry_rotation_weight) == (1e5, 1e5)
    assert (pg.max_num_final_iterations, pg.global_sampling_ratio,
            pg.global_constraint_search_after_n_seconds) == (200, 0.003, 10.0)


def test_option_names_and_info():
    names = option_names()
    assert len(names) == len(set(names)) > 50
    assert "trajectory_builder_2d.submaps.num_range_data" in names
    assert "pose_graph.optimization_problem.ceres_solver_options.max_num_iterations" in names
    info = {i.name: i for i in option_info()}
    hit = info["trajectory_builder_2d.submaps.range_data_inserter.hit_probability"]
    assert hit.type == "float" and hit.default == 0.55 and hit.bounds == "> 0.5 and < 1"
    assert info["trajectory_builder_2d.motion_filter.max_angle_radians"].unit == "rad"
    assert all(i.doc for i in info.values())


def test_options_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        Options().pose_graph.optimize_every_n_nodes = 3


def test_one_solver_section_with_each_owners_default_and_wording():
    o = Options()
    owners = {
        "trajectory_builder_2d.ceres_scan_matcher": (20, "Levenberg-Marquardt iterations per match"),
        "pose_graph.constraint_builder.ceres_scan_matcher": (10, "Levenberg-Marquardt iterations per refinement"),
        "pose_graph.optimization_problem": (50, "solver iterations per periodic optimization"),
    }
    info = {i.name: i for i in option_info()}
    for owner, (default, doc) in owners.items():
        section = get_option(o, owner + ".ceres_solver_options")
        assert type(section) is CeresSolverOptions and section.max_num_iterations == default
        leaf = info[owner + ".ceres_solver_options.max_num_iterations"]
        assert (leaf.default, leaf.doc, leaf.type, leaf.bounds) == (default, doc, "int", ">= 1")
    # No default of its own: a new owner has to say how many iterations its solve gets.
    with pytest.raises(TypeError):
        CeresSolverOptions()


def test_walk_yields_every_leaf_with_its_type():
    leaves = list(walk(Options))
    assert [leaf.name for leaf in leaves] == option_names()
    assert all(leaf.type in (int, float, bool, str) for leaf in leaves)
    by_name = {leaf.name: leaf for leaf in leaves}
    assert by_name["trajectory_builder_2d.use_imu_data"].type is bool
    assert by_name["trajectory_builder_2d.max_range"].field.metadata["unit"] == "m"


@pytest.mark.parametrize("written, expected", [
    ("TRAJECTORY_BUILDER_2D.max_range", "; did you mean 'trajectory_builder_2d.max_range'?"),
    ("submaps.num_range_data", "; did you mean 'trajectory_builder_2d.submaps.num_range_data'?"),
    ("pose_graph.min_score", "; did you mean 'pose_graph.constraint_builder.min_score'?"),
    ("completely_unrelated_words_here", ""),
])
def test_suggestion(written, expected):
    assert suggestion(written) == expected


def test_get_option():
    o = Options()
    assert get_option(o, "pose_graph.constraint_builder.min_score") == 0.55
    assert get_option(o, "trajectory_builder_2d.submaps").num_range_data == 90
    with pytest.raises(CartoError, match="did you mean 'pose_graph.constraint_builder.min_score'"):
        get_option(o, "pose_graph.constraint_builder.min_scor")
