"""`carto map` of a robot with two lasers (issue 47): front and back, 180 degrees each, 0.3 m apart, at 10 and 7 Hz,
on two topics with a static transform each. With no flags both are mapped together and the `auto:` line says so;
either alone still maps; GMapping, which maps one laser's scans, is refused for both; relocalization reads the
recording's scans as mapping did."""
import json
import math

import pytest
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.io.recording_writers import write_recording
from carto_cli.sim import Lidar, loop_building, loop_trajectory
from carto_cli.sim.multi_lidar import MountedLidar, several_lidars

runner = CliRunner()
HALF = Lidar(beams=181, fov=math.pi)
FRONT = MountedLidar(HALF, (0.15, 0.0, 0.0), "/scan_front", "laser_front", rate=10.0)
BACK = MountedLidar(HALF, (-0.15, 0.0, math.pi), "/scan_back", "laser_back", rate=7.0)


@pytest.fixture(scope="module")
def two_lasers(tmp_path_factory):
    """The loop building's first 40 s with both lasers, as an MCAP file a robot would record."""
    world = loop_building()
    recording, _ = several_lidars(world, loop_trajectory(world), [FRONT, BACK], duration=40.0)
    path = tmp_path_factory.mktemp("lasers") / "two_lasers.mcap"
    write_recording(recording.records(), path, "mcap", static_transforms=recording.static_transforms(),
                    topics={t.name: t.msgtype for t in recording.topics()})
    return path


def test_both_lasers_are_mapped_together_with_no_flags(tmp_path, two_lasers):
    out = tmp_path / "both"
    r = runner.invoke(app, ["map", str(two_lasers), "-o", str(out)])
    assert r.exit_code == 0, r.output
    auto = next(line for line in r.stderr.splitlines() if line.startswith("auto:"))
    assert "2 lasers merged (/scan_back, /scan_front)" in auto
    summary = json.loads((out / "summary.json").read_text())
    assert summary["auto"]["detected"]["lasers"] == ["/scan_back", "/scan_front"]
    assert summary["algorithm"] == "cartographer" and summary["quality"]["verdict"] == "ok"
    assert summary["laser_pose_source"].startswith("2 lasers merged in base_link")
    # One merged scan a window of at most one scan of each laser: at the faster laser's rate
    assert 390 <= summary["stats"]["scans"] <= 401


@pytest.mark.parametrize("topic", ["/scan_back", "/scan_front"])
def test_either_laser_alone_still_maps(tmp_path, two_lasers, topic):
    out = tmp_path / topic.strip("/")
    r = runner.invoke(app, ["map", str(two_lasers), "-o", str(out), "--scan-topic", topic])
    assert r.exit_code == 0, r.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["auto"]["detected"]["lasers"] == [] and summary["quality"]["verdict"] == "ok"
    assert summary["laser_pose_source"].startswith("static TF base_link -> laser_")


def test_gmapping_and_unnamed_poses_are_refused_for_several_lasers(tmp_path, two_lasers):
    r = runner.invoke(app, ["map", str(two_lasers), "-o", str(tmp_path / "g"), "--algorithm", "gmapping"])
    assert r.exit_code == 2 and "gmapping maps one laser's scans" in r.stderr
    r = runner.invoke(app, ["map", str(two_lasers), "-o", str(tmp_path / "p"), "--laser-pose", "0,0,0"])
    assert r.exit_code == 2 and "give each one's --laser-pose as TOPIC=x,y,yaw" in r.stderr
    assert not (tmp_path / "g").exists() and not (tmp_path / "p").exists()


def test_relocalization_and_tracking_read_both_lasers_as_mapping_did(tmp_path, two_lasers):
    """In the map both lasers made, a merged scan relocalizes globally where mapping put it, and --track follows
    the whole recording; a map made with one laser is relocalized into with both (their mount is the tracking
    frame's origin, not the map's laser's)."""
    import numpy as np

    from carto_cli.evaluation.metrics import interpolate_poses
    from carto_cli.io.trajectory import read_trajectory

    both, front = tmp_path / "both", tmp_path / "front"
    assert runner.invoke(app, ["map", str(two_lasers), "-o", str(both), "--align", "none"]).exit_code == 0
    assert runner.invoke(app, ["map", str(two_lasers), "-o", str(front), "--align", "none", "--scan-topic",
                               "/scan_front"]).exit_code == 0
    mapped = read_trajectory(both / "trajectory.tum")
    for made in (both, front):
        r = runner.invoke(app, ["relocalize", str(made / "map.carto"), str(two_lasers), "--scan-index", "300",
                                "--global", "--json"])
        assert r.exit_code == 0, r.output
        answer = json.loads(r.stdout)
        assert answer["verdict"] == "ok"
        # scan 300 of the merged stream: the pose mapping gave it (both maps' frames are their first pose's)
        assert np.hypot(answer["pose"]["x"] - mapped.xy[300, 0], answer["pose"]["y"] - mapped.xy[300, 1]) < 0.05
    out = tmp_path / "track"
    r = runner.invoke(app, ["relocalize", str(both / "map.carto"), str(two_lasers), "--track", "-o", str(out),
                            "--global"])
    assert r.exit_code == 0, r.output
    tracked = read_trajectory(out / "trajectory.tum")
    assert len(tracked) >= 0.95 * len(mapped)
    xy, _, valid = interpolate_poses(mapped, tracked.t)
    assert valid.all() and np.median(np.hypot(*(tracked.xy - xy).T)) < 0.03
