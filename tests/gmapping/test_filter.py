"""gmapping.filter: the particle filter end to end on a simulated drive, and its determinism."""
import math

import numpy as np
import pytest

from carto_cli.core import transform
from carto_cli.core.records import Odometry, Scan
from carto_cli.evaluation.metrics import ate
from carto_cli.gmapping.filter import GMappingSlam
from carto_cli.io.trajectory import Trajectory
from carto_cli.options import load_options
from carto_cli.sim import Lidar, OdometryModel, loop_trajectory, room, simulate

# Small and quick: 5 cm cells, a scan processed every 25 cm or 0.4 rad, beams cut at 10 m (the room's
# diagonal), so the loop below is about 70 processed scans.
FAST = ["gmapping.delta=0.05", "gmapping.maxUrange=10", "gmapping.maxRange=12", "gmapping.linearUpdate=0.25",
        "gmapping.angularUpdate=0.4"]


@pytest.fixture(scope="module")
def drive():
    """One lap around an 8 x 6 m room (20 m, 42 s), 5 Hz scans of 180 beams from a laser 15 cm ahead of the
    base, 50 Hz odometry whose heading drifts 2 degrees per metre (on top of the default noise): by the
    end of the lap odometry's heading is off by some 40 degrees and its position by over 2 m."""
    world = room(8.0, 6.0)
    sim = simulate(world, loop_trajectory(world), scan_rate=5.0, lidar=Lidar(beams=180), seed=0,
                   laser_pose=(0.15, 0.0, 0.0), odom_noise=OdometryModel(heading_bias=math.radians(2.0)))
    return sim, list(sim.records(["/scan", "/odom"]))


def _feed(slam, records):
    for record in records:
        if isinstance(record, Scan):
            slam.add_scan(record)
        elif isinstance(record, Odometry):
            slam.add_odometry(record)
    return slam


def _run(sim, records, overrides):
    return _feed(GMappingSlam(load_options(None, FAST + overrides), laser_pose=sim.laser_pose), records).finish()


def _odometry_at_scans(records, times):
    odo = np.array([(r.time, r.x, r.y, r.yaw) for r in records if isinstance(r, Odometry)])
    yaw = np.unwrap(odo[:, 3])
    return np.column_stack([np.interp(times, odo[:, 0], odo[:, 1]), np.interp(times, odo[:, 0], odo[:, 2]),
                            transform.wrap_angle(np.interp(times, odo[:, 0], yaw))])


def _loop_error(poses, truth):
    """How far the last pose is from where the first says it should be (the error a loop closure removes)."""
    est = transform.relative(poses[0], poses[-1])
    true = transform.relative(truth[0], truth[-1])
    return math.hypot(est[0] - true[0], est[1] - true[1]), abs(transform.wrap_angle(est[2] - true[2]))


def test_the_filter_recovers_the_loop_that_odometry_gets_wrong(drive):
    sim, records = drive
    # gainParticles 10 (GMapping's own scaling at this count): with the default 50, ten particles' weights are
    # too flat for Neff to fall below the threshold on one short lap, and the resampler would go untested here
    result = _run(sim, records, ["gmapping.particles=10", "gmapping.gainParticles=10"])
    gt = sim.ground_truth
    np.testing.assert_array_equal(result.times, gt[:, 0])  # a pose for every scan
    truth = Trajectory.from_poses(gt[:, 0], gt[:, 1:])
    mapped = ate(Trajectory.from_poses(result.times, result.poses), truth)
    odometry = _odometry_at_scans(records, gt[:, 0])
    dead_reckoning = ate(Trajectory.from_poses(gt[:, 0], odometry), truth)
    # Measured over simulation seeds 0-2 and filter seeds 0-1: the filter's mean ATE 1.3-1.6 cm (max
    # 4-7 cm, 0.3 degrees mean), odometry's 44-65 cm (max 1.4-2.0 m, 9-13 degrees). The bounds leave 3x room
    # for the filter (a 5 cm cell) and still sit an order of magnitude below odometry.
    assert dead_reckoning.translation.mean > 0.3
    assert mapped.translation.mean < dead_reckoning.translation.mean / 2
    assert mapped.translation.mean < 0.05 and mapped.translation.max < 0.15
    assert mapped.rotation.mean < 1.0 < dead_reckoning.rotation.mean
    # Back at the start: odometry misses by 2.2-3.0 m and 36-45 degrees, the filter by 2-3.5 cm and at
    # most 0.5 degrees (same seeds).
    odo_gap, odo_turn = _loop_error(odometry, gt[:, 1:])
    gap, turn = _loop_error(result.poses, gt[:, 1:])
    assert odo_gap > 1.0 and odo_turn > math.radians(20)
    assert gap < 0.1 and turn < math.radians(1.5)
    assert result.stats["algorithm"] == "gmapping" and result.stats["resamplings"] >= 1
    assert 1.0 <= result.stats["mean_neff"] <= 10.0
    assert np.nanmax(result.image.probability) > 0.5  # walls in the map


@pytest.fixture(scope="module")
def clip(drive):
    """The drive's first 15 s: along the first wall and into the first corner."""
    sim, records = drive
    return sim, [r for r in records if r.time < sim.start_time + 15.0]


def test_the_same_seed_gives_the_same_trajectory_and_map(clip):
    sim, records = clip
    a = _run(sim, records, ["gmapping.particles=6", "gmapping.seed=3"])
    b = _run(sim, records, ["gmapping.particles=6", "gmapping.seed=3"])
    assert np.array_equal(a.poses, b.poses) and np.array_equal(a.times, b.times)
    assert np.array_equal(a.image.probability, b.image.probability, equal_nan=True)
    assert a.image.origin == b.image.origin and a.stats["resamplings"] == b.stats["resamplings"]
    c = _run(sim, records, ["gmapping.particles=6", "gmapping.seed=4"])
    # Another seed draws other motion noise: the poses are not bit-identical (and both are still good).
    assert not np.array_equal(a.poses, c.poses)
    gt = sim.ground_truth
    truth = Trajectory.from_poses(gt[:, 0], gt[:, 1:])
    for r in (a, c):
        assert ate(Trajectory.from_poses(r.times, r.poses), truth).translation.mean < 0.05


def test_walls_above_slam_gmappings_threshold_are_occupied_in_map_yaml_terms(clip):
    """The image is the best particle's hit rate scaled so that slam_gmapping's occ_thresh (0.25) lands on
    map.yaml's occupied_thresh: the walls nav2 sees are the ones slam_gmapping would publish (measured on this
    clip: 821 such cells, against 600 with the raw hit rate)."""
    from carto_cli.gmapping import filter as gmapping_filter
    from carto_cli.io.map_image import OCCUPIED_THRESH

    assert gmapping_filter.OCCUPIED_THRESH == OCCUPIED_THRESH
    sim, records = clip
    # Without the final refinement the image is the best particle's own map, which the scaling is checked on.
    slam = GMappingSlam(load_options(None, FAST + ["gmapping.particles=6", "gmapping.refineIterations=0",
                                                  "gmapping.refineLoops=false"]),
                        laser_pose=sim.laser_pose)
    image = _feed(slam, records).finish().image.probability
    raw, _ = slam.maps.occupancy(slam.best_particle())
    known = np.isfinite(raw)
    assert np.array_equal(known, np.isfinite(image)) and image[known].max() <= 1.0
    walls = raw[known] > 0.25
    assert walls.sum() > 100
    assert np.array_equal(image[known] >= OCCUPIED_THRESH, raw[known] >= 0.25)


def test_the_particles_maps_are_released_before_the_refinement_draws_its_own(clip):
    """With the final refinement the map is drawn again from the refined poses, so the particles' maps (most of a
    key-scan log's memory) are let go first rather than held beside the refinement's grids."""
    sim, records = clip
    slam = GMappingSlam(load_options(None, FAST + ["gmapping.particles=6", "gmapping.refineIterations=1"]),
                        laser_pose=sim.laser_pose)
    _feed(slam, records)
    held = slam.maps.tiles_in_use
    result = slam.finish()
    assert held > 0 and slam.maps.tiles_in_use == 0
    assert result.stats["map_tiles_peak"] >= held
    assert np.isfinite(result.image.probability).sum() > 100  # the map itself is drawn all the same
