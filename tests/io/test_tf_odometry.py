"""Odometry only in dynamic TF (/tf: odom -> base_link), the laser mount on /tf too: maps as with an Odometry topic."""
import json
import math

import numpy as np
import pytest

from carto_cli.core.errors import TopicError
from carto_cli.core.records import Odometry, Scan, Transform, yaw_quaternion
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.sources.open import open_recording
from carto_cli.io.topics import select_topics, selected_records
from carto_cli.pipeline import MapRequest
from carto_cli.sim import loop_building, loop_trajectory, simulate

LASER = (0.2, 0.05, math.radians(3.0))
DURATION = 30.0


def _tf(parent, child, pose, t):
    x, y, yaw = pose
    return Transform(parent, child, (float(x), float(y), 0.0), yaw_quaternion(float(yaw)), t, topic="/tf")


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    """The same drive written twice as a ROS2 bag: with /odom and /tf_static, and with only /tf (odometry and,
    at 10 Hz, the never-moving laser mount)."""
    d = tmp_path_factory.mktemp("tf")
    w = loop_building()
    sim = simulate(w, loop_trajectory(w), duration=DURATION, scan_rate=10.0, laser_pose=LASER)
    records = list(sim.records(["/scan", "/odom"]))
    with_odom = d / "with_odom"
    write_recording(iter(records), with_odom, "ros2-sqlite3", static_transforms=sim.static_transforms)
    tf_only = []
    for r in records:
        if isinstance(r, Odometry):
            tf_only.append(_tf("odom", "base_link", (r.x, r.y, r.yaw), r.time))
        else:
            tf_only.append(r)
            tf_only.append(_tf("base_link", "laser", LASER, r.time))
    only_tf = d / "only_tf"
    write_recording(iter(tf_only), only_tf, "ros2-sqlite3")
    return with_odom, only_tf


def test_odometry_is_found_in_tf_and_read_as_odometry(bags):
    with_odom, only_tf = bags
    with open_recording(only_tf) as rec:
        assert rec.static_transforms() == []
        sel = select_topics(rec)
        assert sel.odometry == "/tf" and sel.tf_odometry is not None
        assert (sel.tf_odometry.odom_frame, sel.tf_odometry.base_frame) == ("odom", "base_link")
        assert [(t.parent, t.child) for t in sel.tf_odometry.fixed] == [("base_link", "laser")]
        assert sel.describe_odometry() == "from TF /tf (odom -> base_link)"
        from_tf = [r for r in selected_records(rec, sel) if isinstance(r, Odometry)]
    with open_recording(with_odom) as rec:
        sel = select_topics(rec)
        assert sel.tf_odometry is None and sel.odometry == "/odom"
        from_topic = [r for r in selected_records(rec, sel) if isinstance(r, Odometry)]
    assert len(from_tf) == len(from_topic) > 100
    for a, b in zip(from_tf, from_topic):
        assert a.time == b.time and (a.x, a.y) == pytest.approx((b.x, b.y), abs=1e-9)
        assert a.yaw == pytest.approx(b.yaw, abs=1e-9)


def test_frames_can_be_named_and_a_wrong_name_is_one_clear_error(bags):
    _, only_tf = bags
    with open_recording(only_tf) as rec:
        sel = select_topics(rec, odom_frame="odom", base_frame="base_link")
        assert sel.tf_odometry.base_frame == "base_link"
        with pytest.raises(TopicError, match=r"no transform odom\* -> base_footprint on /tf .*odom -> base_link"):
            select_topics(rec, base_frame="base_footprint")
        with pytest.raises(TopicError, match="exclude each other"):
            select_topics(rec, odom_topic="/odom", odom_frame="odom")


def test_a_tf_only_recording_maps_as_the_one_with_an_odometry_topic(bags, tmp_path):
    from carto_cli.commands.map import run_map
    from carto_cli.options import load_options

    with_odom, only_tf = bags
    options = load_options("wheeled")
    a, _ = run_map(MapRequest(with_odom, options), tmp_path / "a", state=False)
    b, _ = run_map(MapRequest(only_tf, options), tmp_path / "b", state=False)
    assert a.laser_pose_source.startswith("static TF base_link -> laser")
    assert b.laser_pose_source == "TF base_link -> laser (fixed transforms on /tf)"
    # Odometry from TF carries no twist; where local SLAM's extrapolator would use it the poses may differ a little.
    assert np.abs(a.poses - b.poses).max() < 0.02
    summary = json.loads((tmp_path / "b" / "summary.json").read_text())
    assert summary["odometry"] == "from TF /tf (odom -> base_link)"


def test_info_says_where_odometry_comes_from(bags):
    from carto_cli.commands.info import format_info, run_info

    _, only_tf = bags
    info = run_info(only_tf)
    assert info.has_odometry and info.odometry_source == "from TF /tf (odom -> base_link)"
    text = format_info(info)
    assert "odometry   yes (from TF /tf (odom -> base_link))" in text
    assert "odom -> base_link  (odometry: what map uses)" in text and "base_link -> laser  (never moves" in text


def test_scans_and_transforms_keep_their_time_order(bags):
    _, only_tf = bags
    with open_recording(only_tf) as rec:
        times = [r.time for r in rec.records(["/scan", "/tf"])]
        kinds = {type(r) for r in rec.records(["/scan", "/tf"])}
    assert times == sorted(times) and kinds == {Scan, Transform}


def test_the_frames_on_the_command_line(bags, tmp_path):
    from typer.testing import CliRunner

    from carto_cli.cli import app

    _, only_tf = bags
    run = CliRunner().invoke
    r = run(app, ["map", str(only_tf), "-o", str(tmp_path / "m"), "--profile", "wheeled", "--odom-frame", "odom",
                  "--base-frame", "base_link"])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "m" / "summary.json").read_text())["odometry"] == "from TF /tf (odom -> base_link)"
    r = run(app, ["profile", str(only_tf), "--base-frame", "base_footprint", "--max-scans", "20"])
    assert r.exit_code == 2 and "no transform odom* -> base_footprint on /tf" in r.output
    # A single query reads TF odometry too (the scans around it check a global answer)
    r = run(app, ["relocalize", str(tmp_path / "m" / "map.carto"), str(only_tf), "--global", "--odom-frame", "odom",
                  "--json"])
    assert r.exit_code in (0, 3, 4), r.output
    assert json.loads(r.stdout)["context_checked"] >= 0
    r = run(app, ["relocalize", str(tmp_path / "m" / "map.carto"), str(only_tf), "--global", "-o", str(tmp_path)])
    assert r.exit_code == 2 and "goes with --track" in r.output
