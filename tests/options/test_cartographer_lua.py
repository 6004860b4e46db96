"""carto_cli.options.cartographer_lua: Cartographer's Lua configurations run by a Lua interpreter, as options."""
import math

import pytest
from support import SAMPLE_BAG
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.core.errors import CartoError
from carto_cli.options import load_options
from carto_cli.options.cartographer_lua import import_lua, stock_lua
from carto_cli.options.schema import changed_options

# Written the way cartographer_ros's 2D configurations are: stock includes, the node's options table, then the
# trajectory builder and pose graph changed in place (a local variable, math.rad, a float where an int is meant).
ROBOT_LUA = """
include "map_builder.lua"
include "trajectory_builder.lua"

options = {
  map_builder = MAP_BUILDER,
  trajectory_builder = TRAJECTORY_BUILDER,
  map_frame = "map",
  tracking_frame = "base_link",
  published_frame = "odom",
  provide_odom_frame = false,
  use_odometry = true,
  num_laser_scans = 1,
}

MAP_BUILDER.use_trajectory_builder_2d = true
local per_submap = 35
TRAJECTORY_BUILDER_2D.submaps.num_range_data = per_submap
TRAJECTORY_BUILDER_2D.min_range = 0.3
TRAJECTORY_BUILDER_2D.max_range = 8.
TRAJECTORY_BUILDER_2D.missing_data_ray_length = 1.
TRAJECTORY_BUILDER_2D.use_online_correlative_scan_matching = true
TRAJECTORY_BUILDER_2D.real_time_correlative_scan_matcher.angular_search_window = math.rad(15.)
TRAJECTORY_BUILDER_2D.ceres_scan_matcher.ceres_solver_options.max_num_iterations = 30.
TRAJECTORY_BUILDER_2D.submaps.range_data_inserter.probability_grid_range_data_inserter.hit_probability = 0.6
TRAJECTORY_BUILDER_2D.pose_extrapolator.imu_based.gravity_constant = 9.806
POSE_GRAPH.optimize_every_n_nodes = per_submap
POSE_GRAPH.constraint_builder.min_score = 0.65
POSE_GRAPH.optimization_problem.huber_scale = 1e2
POSE_GRAPH.optimization_problem.ceres_solver_options.num_threads = 4

return options
"""

EXPECTED = {
    "trajectory_builder_2d.min_range": 0.3,
    "trajectory_builder_2d.max_range": 8.0,
    "trajectory_builder_2d.missing_data_ray_length": 1.0,
    "trajectory_builder_2d.use_online_correlative_scan_matching": True,
    "trajectory_builder_2d.real_time_correlative_scan_matcher.angular_search_window": math.radians(15.0),
    "trajectory_builder_2d.ceres_scan_matcher.ceres_solver_options.max_num_iterations": 30,
    "trajectory_builder_2d.submaps.num_range_data": 35,
    "trajectory_builder_2d.submaps.range_data_inserter.hit_probability": 0.6,
    "pose_graph.optimize_every_n_nodes": 35,
    "pose_graph.constraint_builder.min_score": 0.65,
    "pose_graph.optimization_problem.huber_scale": 100.0,
}


def write(tmp_path, text, name="robot.lua"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_a_configuration_sets_exactly_what_it_changes(tmp_path):
    imported = import_lua(write(tmp_path, ROBOT_LUA))
    assert imported.overrides == pytest.approx(EXPECTED)
    assert isinstance(imported.overrides["trajectory_builder_2d.submaps.num_range_data"], int)
    assert isinstance(imported.overrides["trajectory_builder_2d.ceres_scan_matcher.ceres_solver_options."
                                         "max_num_iterations"], int)
    # What carto has no key for is reported, with its value, not dropped silently.
    assert imported.unused["trajectory_builder_2d.pose_extrapolator.imu_based.gravity_constant"] == 9.806
    assert imported.unused["pose_graph.optimization_problem.ceres_solver_options.num_threads"] == 4
    assert imported.unused["tracking_frame"] == "base_link"
    assert not any(k.startswith(("trajectory_builder_2d.submaps", "pose_graph.constraint_builder"))
                   for k in imported.unused)
    note = imported.note()
    assert note.startswith("robot.lua: 2 setting(s) carto does not use") and "ROS node option" in note


def test_the_lua_profile_and_the_yaml_it_imports_to_give_the_same_options(tmp_path):
    lua = write(tmp_path, ROBOT_LUA)
    yaml_path = tmp_path / "robot.yaml"
    yaml_path.write_text(import_lua(lua).to_yaml())
    from_lua = load_options(lua)
    assert from_lua == load_options(yaml_path)
    assert changed_options(from_lua) == pytest.approx(EXPECTED)
    # --set still goes on top of a Lua profile.
    assert load_options(lua, ["pose_graph.constraint_builder.min_score=0.7"]).pose_graph.constraint_builder \
        .min_score == 0.7


def test_stock_includes_hold_carto_defaults(tmp_path):
    """A configuration that changes nothing imports to no override: the stock files are carto's defaults."""
    plain = write(tmp_path, 'include "map_builder.lua"\ninclude "trajectory_builder.lua"\n'
                  "return {map_builder = MAP_BUILDER, trajectory_builder = TRAJECTORY_BUILDER}\n")
    assert import_lua(plain).overrides == {} and import_lua(plain).unused == {}
    assert set(stock_lua()) >= {"map_builder.lua", "trajectory_builder.lua", "trajectory_builder_2d.lua",
                                "pose_graph.lua"}


def test_globals_without_a_returned_table_and_an_include_next_to_the_file(tmp_path):
    """A file of its own next to the configuration is included before the stock one of that name; a file that
    returns nothing is read from its globals."""
    write(tmp_path, "TRAJECTORY_BUILDER_2D = carto_open({min_range = 0.5, max_range = 12.})\n",
          "trajectory_builder_2d.lua")
    cfg = write(tmp_path, 'include "trajectory_builder_2d.lua"\ninclude "pose_graph.lua"\n'
                "POSE_GRAPH.constraint_builder.sampling_ratio = 0.1\n")
    got = import_lua(cfg).overrides
    assert got == {"trajectory_builder_2d.min_range": 0.5, "trajectory_builder_2d.max_range": 12.0,
                   "pose_graph.constraint_builder.sampling_ratio": 0.1}


def test_a_kind_carto_does_not_build_is_reported(tmp_path):
    cfg = write(tmp_path, 'include "trajectory_builder_2d.lua"\n'
                'TRAJECTORY_BUILDER_2D.submaps.grid_options_2d.grid_type = "TSDF"\n')
    imported = import_lua(cfg)
    assert imported.unused == {"trajectory_builder_2d.submaps.grid_options_2d.grid_type": "TSDF"}


@pytest.mark.parametrize("text, message", [
    ('include "map_builder.lua"\nMAP_BUILDER.x = = 1\n', "Lua error"),
    ('include "no_such_file.lua"\n', 'include "no_such_file.lua": not found'),
    ('include "trajectory_builder_2d.lua"\nTRAJECTORY_BUILDER_2D.min_range = "far"\n',
     "trajectory_builder_2d.min_range: expected a number"),
    ('include "trajectory_builder_2d.lua"\n'
     "TRAJECTORY_BUILDER_2D.submaps.range_data_inserter.probability_grid_range_data_inserter.hit_probability = 1.5\n",
     "hit_probability: must be"),
    ("x = 1\n", "no TRAJECTORY_BUILDER_2D or POSE_GRAPH"),
])
def test_bad_configurations_are_one_error_naming_the_file(tmp_path, text, message):
    cfg = write(tmp_path, text)
    with pytest.raises(CartoError) as info:
        import_lua(cfg)
    assert message in str(info.value) and str(cfg) in str(info.value)


def test_the_command_line(tmp_path):
    lua = write(tmp_path, ROBOT_LUA)
    runner = CliRunner()
    imported = runner.invoke(app, ["options", "import", str(lua)])
    assert imported.exit_code == 0, imported.output
    assert "num_range_data: 35" in imported.stdout and "carto does not use" in imported.stderr
    (tmp_path / "robot.yaml").write_text(imported.stdout)
    outs = []
    for profile in ("robot.lua", "robot.yaml"):
        out = tmp_path / profile.replace(".", "_")
        r = runner.invoke(app, ["map", str(SAMPLE_BAG), "-o", str(out), "--profile", str(tmp_path / profile)])
        assert r.exit_code == 0, r.output
        outs.append((out / "map.pgm").read_bytes())
        assert ("carto does not use" in r.stderr) == profile.endswith(".lua")
    assert outs[0] == outs[1]
    bad = runner.invoke(app, ["options", "import"])
    assert bad.exit_code == 2 and "usage: carto options import" in bad.stderr
