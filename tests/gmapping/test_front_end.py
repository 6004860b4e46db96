"""gmapping.front_end: GMapping's pipeline with one pose matched on a distance map, end to end on a simulated drive."""
import math

import numpy as np
import pytest

from carto_cli.core import transform
from carto_cli.core.records import Odometry, Scan
from carto_cli.evaluation.metrics import ate
from carto_cli.gmapping.front_end import ScanToMapSlam
from carto_cli.io.trajectory import Trajectory
from carto_cli.options import load_options
from carto_cli.sim import Lidar, OdometryModel, loop_trajectory, room, simulate

FAST = ["gmapping.delta=0.05", "gmapping.maxUrange=10", "gmapping.maxRange=12", "gmapping.linearUpdate=0.25",
        "gmapping.angularUpdate=0.4"]


@pytest.fixture(scope="module")
def drive():
    """tests/gmapping/test_filter.py's lap: odometry's heading drifts 2 degrees per metre, 2 m off by the end."""
    world = room(8.0, 6.0)
    sim = simulate(world, loop_trajectory(world), scan_rate=5.0, lidar=Lidar(beams=180), seed=0,
                   laser_pose=(0.15, 0.0, 0.0), odom_noise=OdometryModel(heading_bias=math.radians(2.0)))
    return sim, list(sim.records(["/scan", "/odom"]))


def _run(sim, records, cls=ScanToMapSlam):
    slam = cls(load_options(None, FAST), laser_pose=sim.laser_pose)
    for record in records:
        if isinstance(record, Scan):
            slam.add_scan(record)
        elif isinstance(record, Odometry):
            slam.add_odometry(record)
    return slam, slam.finish()


def test_one_pose_on_a_distance_map_maps_the_lap_odometry_gets_wrong(drive):
    sim, records = drive
    slam, result = _run(sim, records)
    gt = sim.ground_truth
    np.testing.assert_array_equal(result.times, gt[:, 0])
    truth = Trajectory.from_poses(gt[:, 0], gt[:, 1:])
    mapped = ate(Trajectory.from_poses(result.times, result.poses), truth)
    odo = np.array([(r.time, r.x, r.y, r.yaw) for r in records if isinstance(r, Odometry)])
    odometry = np.column_stack([np.interp(gt[:, 0], odo[:, 0], odo[:, 1]), np.interp(gt[:, 0], odo[:, 0], odo[:, 2]),
                                transform.wrap_angle(np.interp(gt[:, 0], odo[:, 0], np.unwrap(odo[:, 3])))])
    dead_reckoning = ate(Trajectory.from_poses(gt[:, 0], odometry), truth)
    # The particle filter's bounds (test_filter.py): a tenth of odometry's error, centimetres, under a degree.
    assert dead_reckoning.translation.mean > 0.3
    assert mapped.translation.mean < 0.05 and mapped.translation.max < 0.15
    assert mapped.rotation.mean < 1.0 < dead_reckoning.rotation.mean
    assert result.stats["algorithm"] == "scan-to-map" and result.stats["particles"] == 0
    assert result.stats["processed_scans"] == slam.num_steps > 20
    assert slam.unconverged <= slam.num_steps // 10
    assert np.nanmax(result.image.probability) > 0.5

