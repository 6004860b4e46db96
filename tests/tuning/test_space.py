"""Search spaces: the packaged ones are valid, and a bad one is refused naming the file, the line and the key."""
import pytest

from carto_cli.core.errors import CartoError
from carto_cli.options import Options, apply_overrides
from carto_cli.tuning.space import Param, base_values, default_space_path, load_space, spaces_dir


def test_packaged_spaces_are_valid():
    assert default_space_path("default") == spaces_dir() / "default.yaml"
    assert default_space_path("sparse").name == "sparse.yaml"
    assert default_space_path("no-such-profile").name == "default.yaml"
    for path in sorted(spaces_dir().glob("*.yaml")):
        params = load_space(path)
        assert len(params) >= 5, path


def _space_error(tmp_path, text: str) -> str:
    path = tmp_path / "space.yaml"
    path.write_text(text)
    with pytest.raises(CartoError) as e:
        load_space(path)
    return str(e.value)


def test_unknown_option_names_the_closest(tmp_path):
    msg = _space_error(tmp_path, "pose_graph.constraint_builder.min_scor: {low: 0.5, high: 0.7}\n")
    assert "space.yaml" in msg and "line 1" in msg
    assert "did you mean 'pose_graph.constraint_builder.min_score'" in msg


def test_bounds_outside_the_option_are_rejected(tmp_path):
    msg = _space_error(tmp_path, "pose_graph.constraint_builder.min_score: {low: 0.5, high: 1.5}\n")
    assert "pose_graph.constraint_builder.min_score" in msg and "high" in msg and "<= 1" in msg
    msg = _space_error(tmp_path, "trajectory_builder_2d.submaps.range_data_inserter.hit_probability: "
                                 "{low: 0.4, high: 0.7}\n")
    assert "> 0.5" in msg


@pytest.mark.parametrize("spec, words", [
    ("{low: 10.5, high: 20, int: true}", "integer"),
    ("{low: a, high: 20}", "finite number"),
    ("{low: 20, high: 10}", "less than"),
    ("{low: 0, high: 10, log: true}", "log range"),
    ("{lo: 1, high: 10}", "unknown field"),
    ("{low: 1}", "both low and high"),
    ("{choices: []}", "non-empty"),
    ("{choices: [10, 20.5]}", "integer"),
    ("42", "expected"),
])
def test_bad_types_name_the_file_and_key(tmp_path, spec, words):
    msg = _space_error(tmp_path, f"trajectory_builder_2d.submaps.num_range_data: {spec}\n")
    assert "space.yaml" in msg and "trajectory_builder_2d.submaps.num_range_data" in msg
    assert words in msg


def test_bool_options_need_choices_and_nested_keys_work(tmp_path):
    msg = _space_error(tmp_path, "trajectory_builder_2d:\n  use_online_correlative_scan_matching: "
                                 "{low: 0, high: 1}\n")
    assert "choices" in msg and "line 2" in msg
    path = tmp_path / "nested.yaml"
    path.write_text("trajectory_builder_2d:\n  submaps:\n    num_range_data: {low: 10, high: 50}\n"
                    "  use_online_correlative_scan_matching: {choices: [false, true]}\n")
    params = load_space(path)
    assert [(p.name, p.kind) for p in params] == [
        ("trajectory_builder_2d.submaps.num_range_data", "int"),
        ("trajectory_builder_2d.use_online_correlative_scan_matching", "categorical")]


def test_a_dict_space_is_typed_like_the_options():
    params = load_space({"pose_graph.constraint_builder.min_score": {"low": 0.5, "high": 0.7},
                         "trajectory_builder_2d.submaps.num_range_data": {"low": 10, "high": 50},
                         "trajectory_builder_2d.use_imu_data": {"choices": [False, True]}})
    assert [(p.name, p.kind) for p in params] == [("pose_graph.constraint_builder.min_score", "float"),
                                                  ("trajectory_builder_2d.submaps.num_range_data", "int"),
                                                  ("trajectory_builder_2d.use_imu_data", "categorical")]
    with pytest.raises(CartoError, match="section, not an option"):
        load_space({"pose_graph.constraint_builder": [0.0, 1.0]})


def test_base_values_keep_only_what_lies_inside_the_space():
    params = [Param("pose_graph.constraint_builder.min_score", "float", 0.5, 0.7),
              Param("trajectory_builder_2d.submaps.num_range_data", "int", 10, 50),
              Param("trajectory_builder_2d.use_imu_data", "categorical", choices=(False, True))]
    # Defaults: min_score 0.55 (inside), num_range_data 90 (outside), use_imu_data False (a choice).
    assert base_values(Options(), params) == {"pose_graph.constraint_builder.min_score": 0.55,
                                              "trajectory_builder_2d.use_imu_data": False}
    inside = apply_overrides(Options(), {"trajectory_builder_2d.submaps.num_range_data": 40})
    assert base_values(inside, params)["trajectory_builder_2d.submaps.num_range_data"] == 40
    assert not Param("x", "categorical", choices=(1, 2)).contains(True)  # True == 1, but not a choice


def test_the_gmapping_space_varies_the_particle_filter():
    params = {p.name: p for p in load_space(spaces_dir() / "gmapping.yaml")}
    assert all(name.startswith("gmapping.") for name in params)
    ranges = {name[len("gmapping."):]: (p.kind, p.low, p.high, p.log) for name, p in params.items()}
    assert ranges == {
        "particles": ("int", 20, 150, False),
        "srr": ("float", 0.01, 0.4, True), "srt": ("float", 0.01, 0.4, True),
        "str": ("float", 0.01, 0.4, True), "stt": ("float", 0.01, 0.4, True),
        "sigma": ("float", 0.02, 0.1, False), "lsigma": ("float", 0.02, 0.2, True),
        "ogain": ("float", 1.0, 5.0, False), "resampleThreshold": ("float", 0.2, 0.8, False),
        "linearUpdate": ("float", 0.0, 1.0, False), "angularUpdate": ("float", 0.0, 0.5, False),
    }
    # GMapping's defaults lie inside, so a study's first trial measures them.
    assert set(base_values(Options(), list(params.values()))) == set(params)
