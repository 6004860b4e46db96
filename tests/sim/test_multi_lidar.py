"""A robot with two lidars (sim.multi_lidar): each lidar's scans on its own topic and frame at its own rate, cast
from its own mount; one static transform each; `carto info` places both."""
import math

import numpy as np
import pytest

from carto_cli.core.records import Scan
from carto_cli.sim import Lidar, loop_building, loop_trajectory
from carto_cli.sim.lidar import cast
from carto_cli.sim.multi_lidar import MountedLidar, several_lidars

HALF = Lidar(beams=181, fov=math.pi, noise=0.0, dropout=0.0)
FRONT = MountedLidar(HALF, (0.15, 0.0, 0.0), "/scan_front", "laser_front", rate=10.0)
BACK = MountedLidar(HALF, (-0.15, 0.0, math.pi), "/scan_back", "laser_back", rate=7.0)


@pytest.fixture(scope="module")
def robot():
    world = loop_building()
    return world, several_lidars(world, loop_trajectory(world), [FRONT, BACK], duration=6.0)


def test_each_lidar_on_its_topic_at_its_rate(robot):
    _, (recording, _) = robot
    counts = {t.name: t.count for t in recording.topics()}
    assert counts["/scan_front"] == 60 and counts["/scan_back"] == 42
    assert counts["/odom"] == 300 and counts["/imu"] == 600  # from the first lidar's simulation only
    times = [r.time for r in recording.records()]
    assert times == sorted(times)
    frames = {(r.topic, r.frame) for r in recording.records() if isinstance(r, Scan)}
    assert frames == {("/scan_front", "laser_front"), ("/scan_back", "laser_back")}
    mounts = {t.child: (t.translation, t.rotation) for t in recording.static_transforms()}
    assert mounts["laser_front"][0] == (0.15, 0.0, 0.0)
    assert mounts["laser_back"][0] == (-0.15, 0.0, 0.0) and abs(mounts["laser_back"][1][2]) == pytest.approx(1.0)


def test_each_scan_is_cast_from_its_own_mount(robot):
    world, (recording, sims) = robot
    for mount, sim in zip((FRONT, BACK), sims):
        scan = next(r for r in recording.records([mount.topic]) if isinstance(r, Scan))
        pose = sim.laser_poses(np.array([scan.time]))[0]
        expected = cast(pose, HALF.angles(), world.segments, HALF.max_range)
        got = np.where(np.isfinite(scan.ranges), scan.ranges, np.inf)
        assert np.allclose(got, expected, atol=1e-4)


def test_topics_and_frames_must_differ():
    world = loop_building()
    with pytest.raises(ValueError, match="topic and a frame of its own"):
        several_lidars(world, loop_trajectory(world), [FRONT, FRONT], duration=1.0)


def test_carto_info_places_both_lidars(robot, tmp_path):
    from carto_cli.commands.info import run_info
    from carto_cli.io.recording_writers import write_recording

    _, (recording, _) = robot
    path = tmp_path / "two_lidars.mcap"
    write_recording(recording.records(), path, "mcap", static_transforms=recording.static_transforms(),
                    topics={t.name: t.msgtype for t in recording.topics()})
    info = run_info(path)
    placed = {m["frame"]: m for t in info.topics if t.scan is not None for m in t.scan.mounts}
    assert (placed["laser_front"]["x"], placed["laser_back"]["x"]) == (0.15, -0.15)
    assert abs(abs(placed["laser_back"]["yaw_deg"]) - 180.0) < 1e-6
