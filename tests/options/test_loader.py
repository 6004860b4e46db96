"""Loading options: YAML files and --set layered onto the schema, every value checked, errors that name the key."""
import math

import pytest
import yaml

from carto_cli.core.errors import CartoError
from carto_cli.options import (
    Layer,
    Options,
    apply_overrides,
    apply_values,
    changed_options,
    dump_options_yaml,
    get_option,
    load_options,
    option_names,
    options_to_dict,
    profiles_dir,
    read_yaml,
)
from carto_cli.options.layering import YamlLoader


def _flatten(d, prefix=""):
    for k, v in d.items():
        if isinstance(v, dict):
            yield from _flatten(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}"


# --------------------------------------------------------------------------- defaults


def test_default_yaml_lists_every_option_with_the_dataclass_default():
    data = yaml.load((profiles_dir() / "default.yaml").read_text(), Loader=YamlLoader)
    assert list(_flatten(data)) == option_names()
    assert load_options() == Options()


# --------------------------------------------------------------------------- --set


def test_set_values_of_every_type():
    o = load_options(overrides=[
        "trajectory_builder_2d.submaps.num_range_data=35",
        "trajectory_builder_2d.max_range=12",                      # int is fine for a float
        "trajectory_builder_2d.use_online_correlative_scan_matching=true",
        "pose_graph.constraint_builder.loop_closure_rotation_weight=1e7",   # YAML 1.1 would read a string
        "pose_graph.optimization_problem.huber_scale=2.5E+1",
    ])
    tb = o.trajectory_builder_2d
    assert tb.submaps.num_range_data == 35
    assert tb.max_range == 12.0 and isinstance(tb.max_range, float)
    assert tb.use_online_correlative_scan_matching is True
    assert o.pose_graph.constraint_builder.loop_closure_rotation_weight == 1e7
    assert o.pose_graph.optimization_problem.huber_scale == 25.0
    assert changed_options(o) == {
        "trajectory_builder_2d.max_range": 12.0,
        "trajectory_builder_2d.use_online_correlative_scan_matching": True,
        "trajectory_builder_2d.submaps.num_range_data": 35,
        "pose_graph.constraint_builder.loop_closure_rotation_weight": 1e7,
        "pose_graph.optimization_problem.huber_scale": 25.0,
    }


def test_later_set_wins():
    o = load_options(overrides=["pose_graph.optimize_every_n_nodes=10", "pose_graph.optimize_every_n_nodes=20"])
    assert o.pose_graph.optimize_every_n_nodes == 20


def test_degrees_only_with_suffix_on_angles():
    key = "trajectory_builder_2d.real_time_correlative_scan_matcher.angular_search_window"
    assert get_option(load_options(overrides=[f"{key}=10deg"]), key) == pytest.approx(math.radians(10))
    assert get_option(load_options(overrides=[f"{key}=0.2"]), key) == 0.2
    assert get_option(load_options(overrides=[f"{key}= 45 deg"]), key) == pytest.approx(math.pi / 4)
    with pytest.raises(CartoError, match=r"'deg' is only allowed on angles"):
        load_options(overrides=["trajectory_builder_2d.max_range=20deg"])
    with pytest.raises(CartoError, match=r"must be >= 0 and <= 3.14159"):
        load_options(overrides=[f"{key}=200deg"])


@pytest.mark.parametrize("item, message", [
    ("trajectory_builder_2d.submaps.num_range_dat=3",
     "unknown option; did you mean 'trajectory_builder_2d.submaps.num_range_data'"),
    ("submaps.num_range_data=3", "did you mean 'trajectory_builder_2d.submaps.num_range_data'"),
    ("pose_graph.min_score=0.6", "did you mean 'pose_graph.constraint_builder.min_score'"),
    ("TRAJECTORY_BUILDER_2D.max_range=3", "did you mean 'trajectory_builder_2d.max_range'"),
    ("trajectory_builder_2d.submaps.range_data_inserter.probability_grid_range_data_inserter.hit_probability=0.6",
     "did you mean 'trajectory_builder_2d.submaps.range_data_inserter.hit_probability'"),
    ("trajectory_builder_2d.submaps.num_range_data=3.5", "expected an integer, got 3.5"),
    ("trajectory_builder_2d.submaps.num_range_data=true", "expected an integer, got true"),
    ("trajectory_builder_2d.max_range=far", "expected a number, got 'far'"),
    ("trajectory_builder_2d.max_range=.nan", "expected a finite number"),
    ("trajectory_builder_2d.use_imu_data=1", "expected true or false, got 1"),
    ("trajectory_builder_2d.submaps.range_data_inserter.hit_probability=0.5", "must be > 0.5 and < 1, got 0.5"),
    ("trajectory_builder_2d.submaps.range_data_inserter.miss_probability=0.5", "must be > 0 and < 0.5"),
    ("trajectory_builder_2d.submaps.grid_options_2d.resolution=0", "must be > 0, got 0 m"),
    ("trajectory_builder_2d.submaps.num_range_data=0", "must be >= 1, got 0"),
    ("pose_graph.constraint_builder.sampling_ratio=1.5", "must be >= 0 and <= 1"),
    ("trajectory_builder_2d.submaps=3", "is a section, not a value; set one of its keys: num_range_data"),
    ("trajectory_builder_2d.max_range.x=3", "'trajectory_builder_2d.max_range' is a value, not a section"),
    ("trajectory_builder_2d.max_range", "--set expects key=value"),
    ("trajectory_builder_2d.max_range=", "no value given"),
    ("trajectory_builder_2d.min_range=40", "min_range (40 m) must be less than trajectory_builder_2d.max_range"),
])
def test_set_errors_name_the_key(item, message):
    with pytest.raises(CartoError) as e:
        load_options(overrides=[item])
    text = str(e.value)
    assert message in text
    if "=" in item and item.split("=", 1)[1] and "min_range=40" not in item:
        assert text.startswith(f"--set {item.split('=')[0]}")


def test_apply_overrides_with_typed_dict():
    o = apply_overrides(Options(), {"pose_graph.constraint_builder.min_score": 0.7,
                                    "trajectory_builder_2d.submaps.num_range_data": 40})
    assert o.pose_graph.constraint_builder.min_score == 0.7
    assert o.trajectory_builder_2d.submaps.num_range_data == 40
    with pytest.raises(CartoError, match="expected an integer"):
        apply_overrides(Options(), {"trajectory_builder_2d.submaps.num_range_data": 40.0})


def test_apply_values_from_code_checks_types_and_bounds_but_reads_no_text():
    o = apply_values(Options(), {"trajectory_builder_2d": {"submaps": {"num_range_data": 40}}}, Layer())
    assert o.trajectory_builder_2d.submaps.num_range_data == 40
    key = "trajectory_builder_2d.real_time_correlative_scan_matcher.angular_search_window"
    with pytest.raises(CartoError, match="expected a number, got '10deg'"):
        apply_values(Options(), {key: "10deg"}, Layer())
    with pytest.raises(CartoError, match=r"^trajectory_builder_2d.max_range: must be > 0"):
        apply_values(Options(), {"trajectory_builder_2d.max_range": -1.0}, Layer())
    # Cross-option checks are not apply_values' job: they run once on the final values.
    o = apply_values(Options(), {"trajectory_builder_2d.min_range": 40.0}, Layer())
    assert o.trajectory_builder_2d.min_range == 40.0


def test_read_yaml_gives_the_line_of_every_key(tmp_path):
    p = tmp_path / "lines.yaml"
    p.write_text("# comment\npose_graph:\n  optimize_every_n_nodes: 1e1\n  constraint_builder.min_score: 0.6\n")
    data, lines = read_yaml(p)
    assert data == {"pose_graph": {"optimize_every_n_nodes": 10.0, "constraint_builder.min_score": 0.6}}
    assert lines == {"pose_graph": 2, "pose_graph.optimize_every_n_nodes": 3,
                     "pose_graph.constraint_builder.min_score": 4}


# --------------------------------------------------------------------------- files


def test_empty_profile_and_empty_section(tmp_path):
    p = tmp_path / "empty.yaml"
    p.write_text("# nothing yet\n")
    assert load_options(p) == Options()
    p.write_text("trajectory_builder_2d:\n  submaps:\n")
    assert load_options(p) == Options()


@pytest.mark.parametrize("text, message", [
    ("trajectory_builder_2d:\n  submaps:\n    num_range_dat: 3\n",
     "line 3: trajectory_builder_2d.submaps.num_range_dat: unknown option; "
     "did you mean 'trajectory_builder_2d.submaps.num_range_data'?"),
    ("pose_graph:\n  optimize_every_n_nodes: 1.5\n",
     "line 2: pose_graph.optimize_every_n_nodes: expected an integer, got 1.5"),
    ("pose_graph:\n  constraint_builder:\n    fast_correlative_scan_matcher:\n      angular_search_window: 30deg\n",
     "angles in profile files are radians: write 0.5235987756 for 30deg"),
    ("pose_graph:\n  optimize_every_n_nodes: 1\n  optimize_every_n_nodes: 2\n",
     "line 3: 'pose_graph.optimize_every_n_nodes' is given twice (first on line 2)"),
    ("pose_graph:\n  optimize_every_n_nodes: [1\n", "invalid YAML"),
    ("- 1\n- 2\n", "line 1: expected a mapping of option names to values"),
    ("pose_graph: 3\n", "line 1: pose_graph: is a section, not a value"),
    ("trajectory_builder_2d:\n  submaps:\n    range_data_inserter:\n      miss_probability: 0.7\n",
     "line 4: trajectory_builder_2d.submaps.range_data_inserter.miss_probability: must be > 0 and < 0.5, got 0.7"),
])
def test_file_errors_name_file_line_and_key(tmp_path, text, message):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(CartoError) as e:
        load_options(p)
    assert message in str(e.value)
    assert e.value.path == str(p)


def test_a_control_character_is_one_line_naming_it(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text('gmapping:\n  particles: "\x01"\n')
    with pytest.raises(CartoError) as e:
        load_options(p)
    assert "invalid YAML: unacceptable character #x0001" in str(e.value)
    assert "\n" not in str(e.value)


def test_cross_checks_apply_to_the_final_values(tmp_path):
    p = tmp_path / "far.yaml"
    p.write_text("trajectory_builder_2d: {min_range: 40.0}\n")
    with pytest.raises(CartoError, match="must be less than"):
        load_options(p)
    o = load_options(p, ["trajectory_builder_2d.max_range=60"])
    assert (o.trajectory_builder_2d.min_range, o.trajectory_builder_2d.max_range) == (40.0, 60.0)


# --------------------------------------------------------------------------- output


def test_dump_round_trips(tmp_path):
    o = load_options(overrides=["trajectory_builder_2d.submaps.num_range_data=35",
                                "pose_graph.constraint_builder.loop_closure_rotation_weight=1e-5",
                                "trajectory_builder_2d.motion_filter.max_angle_radians=0.5deg"])
    p = tmp_path / "dump.yaml"
    p.write_text(dump_options_yaml(o))
    assert load_options(p) == o
    d = options_to_dict(o)
    assert d["trajectory_builder_2d"]["submaps"]["num_range_data"] == 35
    assert list(_flatten(d)) == option_names()
