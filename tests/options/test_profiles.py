"""The packaged profiles: every one loads over the default, names resolve (with suggestions), the CLI shows them."""
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

import carto_cli.options.profiles as profiles_module
from carto_cli.cli import app
from carto_cli.core.errors import CartoError
from carto_cli.options import Options, changed_options, list_profiles, load_options, profiles_dir, resolve_profile

PROFILES = list_profiles()


def test_the_environment_profiles_exist():
    assert {"default", "office", "corridor", "warehouse"} <= set(PROFILES)


@pytest.mark.parametrize("name", PROFILES)
def test_profile_loads_and_changes_something(name):
    options = load_options(name)
    if name != "default":
        assert changed_options(options), f"{name} changes nothing"


def test_profiles_cli():
    runner = CliRunner()
    listed = runner.invoke(app, ["profiles", "list"])
    assert listed.exit_code == 0 and "corridor" in listed.stdout
    shown = runner.invoke(app, ["profiles", "show", "office", "--changed"])
    assert shown.exit_code == 0 and "use_online_correlative_scan_matching: true" in shown.stdout
    full = runner.invoke(app, ["profiles", "show", "corridor",
                               "--set", "trajectory_builder_2d.submaps.num_range_data=33"])
    assert full.exit_code == 0 and "num_range_data: 33" in full.stdout
    bad = runner.invoke(app, ["profiles", "show", "nope"])
    assert bad.exit_code == 2 and "nope" in bad.stderr


def test_repository_profiles_directory_is_the_packaged_one():
    from support import REPO

    from carto_cli.options import profiles_dir

    root = REPO / "profiles"
    assert (root / "default.yaml").is_file()
    assert (root / "office.yaml").read_text() == (profiles_dir() / "office.yaml").read_text()


def test_options_command_lists_every_option():
    import json

    from carto_cli.options import option_names

    runner = CliRunner()
    r = runner.invoke(app, ["options", "--json"])
    assert r.exit_code == 0
    assert [o["name"] for o in json.loads(r.stdout)] == option_names()
    one = runner.invoke(app, ["options", "num_range_data"])
    assert one.exit_code == 0 and "trajectory_builder_2d.submaps.num_range_data = 90" in one.stdout


# --------------------------------------------------------------------------- resolving and layering


@pytest.fixture
def profiles(tmp_path, monkeypatch):
    """A private profiles directory holding a copy of the packaged default.yaml."""
    d = tmp_path / "profiles"
    d.mkdir()
    shutil.copy(profiles_dir() / "default.yaml", d / "default.yaml")
    monkeypatch.setattr(profiles_module, "profiles_dir", lambda: d)
    return d


def test_named_profile_layers_over_default_and_set_over_profile(profiles):
    (profiles / "revo.yaml").write_text(
        "trajectory_builder_2d:\n"
        "  use_online_correlative_scan_matching: true\n"
        "  submaps:\n"
        "    num_range_data: 35\n"
        "pose_graph:\n"
        "  optimize_every_n_nodes: 35\n"
        "  constraint_builder.min_score: 0.65   # dotted keys work in files too\n")
    o = load_options("revo", ["pose_graph.optimize_every_n_nodes=50"])
    assert o.trajectory_builder_2d.use_online_correlative_scan_matching is True
    assert o.trajectory_builder_2d.submaps.num_range_data == 35
    assert o.pose_graph.constraint_builder.min_score == 0.65
    assert o.pose_graph.optimize_every_n_nodes == 50
    # Untouched values keep their defaults.
    assert o.trajectory_builder_2d.submaps.range_data_inserter.hit_probability == 0.55
    assert list_profiles() == ["default", "revo"]
    assert load_options("default") == Options()


def test_profile_path_is_read_directly(tmp_path):
    p = tmp_path / "mine.yaml"
    p.write_text("pose_graph: {optimize_every_n_nodes: 0}\n")
    assert load_options(str(p)).pose_graph.optimize_every_n_nodes == 0
    assert load_options(p).pose_graph.optimize_every_n_nodes == 0


def test_unknown_profile_name_suggests(profiles):
    (profiles / "office.yaml").write_text("{}\n")
    with pytest.raises(CartoError, match=r"unknown profile 'ofice'; did you mean 'office'\?.*default, office"):
        load_options("ofice")


def test_missing_profile_file(tmp_path):
    p = tmp_path / "nope.yaml"
    with pytest.raises(CartoError) as e:
        load_options(p)
    assert "no such profile file" in str(e.value) and e.value.path == str(p)


def test_resolve_profile_names_and_paths(profiles, tmp_path):
    (profiles / "office.yaml").write_text("{}\n")
    assert resolve_profile("office") == profiles / "office.yaml"
    assert resolve_profile("sub/dir/x") == Path("sub/dir/x")
    mine = tmp_path / "mine.yml"
    assert resolve_profile(str(mine)) == mine and resolve_profile(mine) == mine


def test_profiles_dir_is_the_package_data_directory():
    import carto_cli

    assert profiles_module.profiles_dir() == Path(carto_cli.__file__).resolve().parent / "profiles"
