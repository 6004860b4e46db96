"""`carto options` and `carto profiles` as library calls."""
from carto_cli.commands.options import format_option, list_options
from carto_cli.commands.profiles import describe_profiles, show_profile
from carto_cli.options import option_names


def test_list_options_filters_by_name():
    assert [i.name for i in list_options()] == option_names()
    assert [i.name for i in list_options("max_num_iterations")] == [
        "trajectory_builder_2d.ceres_scan_matcher.ceres_solver_options.max_num_iterations",
        "pose_graph.constraint_builder.ceres_scan_matcher.ceres_solver_options.max_num_iterations",
        "pose_graph.optimization_problem.ceres_solver_options.max_num_iterations",
    ]
    assert list_options("no such words") == []


def test_format_option():
    (hit,) = list_options("range_data_inserter.hit_probability")
    assert format_option(hit) == ("trajectory_builder_2d.submaps.range_data_inserter.hit_probability = 0.55 (float)"
                                  "  [> 0.5 and < 1]\n    occupancy probability a hit moves a cell towards")
    (max_range,) = list_options("trajectory_builder_2d.max_range")
    assert format_option(max_range).startswith("trajectory_builder_2d.max_range = 30.0 m (float)  [> 0]\n")


def test_describe_profiles():
    described = dict(describe_profiles())
    assert {"default", "office", "corridor", "warehouse"} <= set(described)
    assert all(isinstance(text, str) for text in described.values())
    assert described["office"] and "\n" not in described["office"]


def test_show_profile():
    changed = show_profile("office", changed=True)
    assert "trajectory_builder_2d.use_online_correlative_scan_matching: true" in changed
    full = show_profile("corridor", ["trajectory_builder_2d.submaps.num_range_data=33"])
    assert full.startswith("trajectory_builder_2d:") and "num_range_data: 33" in full and not full.endswith("\n")
    assert show_profile("default", changed=True) == "{}"


def test_profiles_list_shows_whole_first_sentences(monkeypatch):
    """Issue 42, item 10: `carto profiles list` cut each description at the end of its file's first line, often
    mid-sentence ("... tunnels, industrial")."""
    from typer.testing import CliRunner

    from carto_cli.cli import app

    described = dict(describe_profiles())
    assert described["corridor"].endswith("tens of metres long, few features along the axis.")
    assert described["sparse"].endswith("drifting by a few percent).")
    assert all(text.endswith(".") for text in described.values()), described
    monkeypatch.setenv("COLUMNS", "80")
    listed = CliRunner().invoke(app, ["profiles", "list"])
    assert listed.exit_code == 0, listed.output
    assert all(len(line) <= 80 for line in listed.stdout.splitlines()), listed.stdout
    text = " ".join(listed.stdout.split())
    for name, first in described.items():
        assert f"{name} {first}" in text, name


def test_profiles_show_auto_explains():
    """Issue 42, item 10: `carto profiles show auto` said "unknown profile" though auto is `carto map`'s default."""
    from typer.testing import CliRunner

    from carto_cli.cli import app

    shown = CliRunner().invoke(app, ["profiles", "show", "auto"])
    assert shown.exit_code == 0, shown.output
    text = " ".join(shown.stdout.split())
    assert "unknown profile" not in shown.output
    assert "for each recording" in text and "carto info REC" in text
    assert "carto profiles show default" in text  # the options auto starts from
