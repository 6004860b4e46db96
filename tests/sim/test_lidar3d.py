"""The simulated 3D lidar (sim.lidar3d): every point on a surface of the building, furniture below its top only,
per-point times over the turn, a recording carto reads as a user's; and a small map of it, furniture left out by
the band above the floor and drawn by a band through it."""
import math

import numpy as np
import pytest

from carto_cli import api
from carto_cli.core.records import Cloud, Imu, Odometry
from carto_cli.io.sources.open import open_recording
from carto_cli.sim import room
from carto_cli.sim.lidar3d import Building, Lidar3D, furnish, simulate_3d, sweep_distances
from carto_cli.sim.recording import compose
from carto_cli.sim.trajectory import loop_trajectory

EXACT = Lidar3D(columns=360, noise=0.0)
HEIGHT = 0.8


def furnished():
    boxes = [[2.0, 4.8, 1.0, 0.5, 0.45], [6.5, 2.5, 0.6, 0.8, 0.5], [4.0, 5.5, 1.2, 0.4, 0.35]]
    return Building(room(8.0, 7.0), ceiling=2.6, furniture=np.array(boxes))


def test_every_point_lies_on_a_surface_at_its_own_time():
    building = furnished()
    sim = simulate_3d(building, loop_trajectory(building.world), lidar=EXACT, height=HEIGHT, duration=1.0)
    clouds = list(sim.clouds())
    assert len(clouds) == 10 and all(c.frame == "lidar" and c.topic == "/points" for c in clouds)
    for cloud in clouds[::3]:
        t = cloud.time + cloud.point_times
        assert float(cloud.point_times.min()) >= 0.0 and float(cloud.point_times.max()) < 0.1
        pose = compose(sim.base.trajectory.poses(t - sim.base.start_time), sim.mount)
        x, y, z = cloud.points.astype(np.float64).T
        c, s = np.cos(pose[:, 2]), np.sin(pose[:, 2])
        world = np.column_stack([pose[:, 0] + c * x - s * y, pose[:, 1] + s * x + c * y])
        height = z + HEIGHT  # above the floor
        on_wall = building.world.distance_to_walls(world) < 1e-3
        on_floor = np.abs(height) < 1e-3
        on_ceiling = np.abs(height - building.ceiling) < 1e-3
        on_box = np.zeros(len(z), bool)
        for b in building.furniture:
            inside = (np.abs(world[:, 0] - b[0]) <= b[2] / 2 + 1e-3) & (np.abs(world[:, 1] - b[1]) <= b[3] / 2 + 1e-3)
            on_box |= inside & (height <= b[4] + 1e-3)
        assert np.all(on_wall | on_floor | on_ceiling | on_box)
        assert on_box.any() and on_floor.any() and on_ceiling.any() and on_wall.any()


def test_a_box_stops_the_rings_below_its_top_only():
    building = Building(room(10.0, 10.0), furniture=np.array([[5.0, 2.0, 0.4, 2.0, 0.5]]))
    pose = np.array([[2.0, 2.0, 0.0]])  # looking at the box's face 2.8 m ahead, the wall 8 m
    rings = np.radians(np.array([-3.0, -1.0, 1.0]))
    d = sweep_distances(building, pose, HEIGHT, rings, 30.0)[0]
    # From 0.8 m every ring passes over the 0.5 m box (-3 degrees is at 0.65 m over its face, would come down to its
    # top only 5.7 m away) and meets the wall.
    assert np.allclose(d, 8.0)
    low = sweep_distances(building, pose, 0.3, rings, 30.0)[0]
    assert np.allclose(low, 2.8)  # from 0.3 m, every ring is below its top at its face


def test_a_box_top_seen_from_above():
    building = Building(room(10.0, 10.0), furniture=np.array([[5.0, 2.0, 2.0, 2.0, 0.5]]))
    pose = np.array([[2.0, 2.0, 0.0]])
    d = sweep_distances(building, pose, HEIGHT, np.radians(np.array([-7.0])), 30.0)[0]
    assert d[0] == pytest.approx(0.3 / math.tan(math.radians(7.0)))  # 2.44 m: onto the top, past its face at 2 m


def test_furnish_puts_boxes_in_sight_of_the_route():
    from carto_cli.sim import loop_building

    world = loop_building()
    building = furnish(world, count=10, seed=3)
    assert len(building.furniture) == 10 and building.furniture_height <= 0.55
    centres = building.furniture[:, :2]
    assert world.distance_to_walls(centres).min() > 0.15
    # Not in the closed core of the 24 m x 16 m ring (2.5 m corridors round it): every box is where the robot drives.
    core = (centres[:, 0] > 2.6) & (centres[:, 0] < 21.4) & (centres[:, 1] > 2.6) & (centres[:, 1] < 13.4)
    assert not core.any()


def test_records_in_log_order_and_the_recording_reads_back(tmp_path):
    building = furnished()
    sim = simulate_3d(building, loop_trajectory(building.world), lidar=EXACT, height=HEIGHT, duration=1.0,
                      time_field="offset_time")
    records = list(sim.records())
    assert sum(isinstance(r, Cloud) for r in records) == 10
    assert sum(isinstance(r, Odometry) for r in records) == 50 and sum(isinstance(r, Imu) for r in records) == 100
    for i, r in enumerate(records):
        if isinstance(r, Cloud):  # after the odometry and IMU of its sweep, before what follows it
            end = r.time + float(r.point_times.max())
            assert all(o.time <= end for o in records[:i] if not isinstance(o, Cloud))
            assert all(o.time > end for o in records[i + 1:] if not isinstance(o, Cloud))
    out = sim.write(tmp_path / "lidar3d.bag", "ros1")
    with open_recording(out) as rec:
        kinds = {t.name: t.msgtype for t in rec.topics()}
        assert kinds["/points"] == "sensor_msgs/msg/PointCloud2"
        mount = next(t for t in rec.static_transforms() if t.child == "lidar")
        assert mount.translation == (0.0, 0.0, HEIGHT)
        scans = list(rec.records(["/points"]))
        band = rec.cloud_bands["/points"]
    assert len(scans) == 10 and all(s.point_times is not None for s in scans)
    assert band.floor == pytest.approx(-HEIGHT, abs=1e-3) and band.ceiling == pytest.approx(2.6 - HEIGHT, abs=1e-3)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    building = furnished()
    sim = simulate_3d(building, loop_trajectory(building.world), lidar=Lidar3D(columns=450, noise=0.01),
                      height=HEIGHT, duration=14.0)
    return building, sim, sim.write(tmp_path_factory.mktemp("cloud") / "room.mcap", "mcap")


def _box_cells(outdir, building, start):
    """(occupied cells over the boxes, occupied cells in all) of the map written in ``outdir``."""
    import cv2
    import yaml

    meta = yaml.safe_load((outdir / "map.yaml").read_text())
    pixels = cv2.imread(str(outdir / meta["image"]), cv2.IMREAD_GRAYSCALE)[::-1]
    occupied = pixels == 0
    res, origin = float(meta["resolution"]), np.asarray(meta["origin"][:2])
    rows, cols = np.nonzero(occupied)
    # The map frame is the first pose's: the world point p is at p - start there (the route starts heading along x).
    world = np.column_stack([origin[0] + (cols + 0.5) * res, origin[1] + (rows + 0.5) * res]) + start[:2]
    on_box = np.zeros(len(world), bool)
    for b in building.furniture:
        on_box |= (np.abs(world[:, 0] - b[0]) <= b[2] / 2 + 0.1) & (np.abs(world[:, 1] - b[1]) <= b[3] / 2 + 0.1)
    return int(on_box.sum()), len(world)


@pytest.fixture(scope="module")
def mapped(recording, tmp_path_factory):
    outdir = tmp_path_factory.mktemp("map")
    return api.map_recording(recording[2], align="none", outdir=outdir, force=True), outdir


def test_a_small_map_leaves_the_furniture_out_and_a_low_band_draws_it(recording, mapped, tmp_path):
    building, sim, path = recording
    start = sim.ground_truth[0, 1:]
    assert abs(start[2]) < 1e-9  # the map frame is the world's moved to the start
    auto, outdir = mapped
    assert auto.quality != "failed"
    # Every scan where it was: the trajectory in the map frame against the truth moved to the start (14 s round a
    # bare room, no loop closed yet: a few centimetres of drift).
    truth = sim.ground_truth[:, 1:3] - start[:2]
    assert np.abs(auto.poses[:, :2] - truth[: len(auto.poses)]).max() < 0.1
    on_box, total = _box_cells(outdir, building, start)
    assert total > 300 and on_box == 0
    api.map_recording(path, align="none", outdir=tmp_path / "low", overrides=["trajectory_builder_2d.cloud_band=0.1..0.4"])
    on_box_low, _ = _box_cells(tmp_path / "low", building, start)
    assert on_box_low > 20


def test_tracking_in_the_map_reads_the_clouds_as_mapping_did(recording, mapped, tmp_path):
    """`carto relocalize --track` slices the clouds in the map's band: every scan of the recording found where the
    map put it."""
    from carto_cli.commands.relocalize import RelocalizeRequest, run_track

    _, sim, path = recording
    made, outdir = mapped
    request = RelocalizeRequest(outdir / "map.carto", path, initial_pose="0,0,0")
    tracked = []
    run = run_track(request, tmp_path / "track", on_scan=tracked.append)
    assert run.summary.verdicts.get("ok", 0) >= 0.9 * run.summary.scans
    ok = np.array([s.pose for s in tracked if s.verdict == "ok"])
    times = np.array([s.time for s in tracked if s.verdict == "ok"])
    at = made.poses[np.searchsorted(sim.base.scan_times, times)]
    assert np.abs(ok[:, :2] - at[:, :2]).max() < 0.08  # a cell and a half: matched to the map, not to the scans
    assert np.median(np.hypot(*(ok[:, :2] - at[:, :2]).T)) < 0.03
