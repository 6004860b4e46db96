"""Every shipped profile loads over the default, and the profiles commands show them."""
import pytest
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.options import changed_options, list_profiles, load_options

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
    full = runner.invoke(app, ["profiles", "show", "corridor", "--set", "trajectory_builder_2d.submaps.num_range_data=33"])
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
