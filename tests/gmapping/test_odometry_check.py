"""gmapping.odometry_check: how far odometry is off, measured by the filter with one particle, against the truth."""
import numpy as np
import pytest

from carto_cli.core import transform
from carto_cli.core.records import Odometry, Scan
from carto_cli.gmapping.odometry_check import MIN_STEP, odometry_error
from carto_cli.options import Options
from carto_cli.sim import Lidar, OdometryModel, loop_trajectory, room, simulate

MODELS = {
    "perfect": OdometryModel.perfect(),
    "default": OdometryModel(),  # 2 % scale bias, 2 cm per sqrt(m) of noise
    "rough": OdometryModel(scale_bias=0.12, noise_forward=0.08, noise_lateral=0.05),
}


@pytest.fixture(scope="module", params=list(MODELS))
def drive(request):
    """A lap of an 8 x 6 m room with one scan a second (key scans about half a metre apart), laser 15 cm ahead of
    the base, and odometry of the given quality; with the true per-metre error of that odometry, as the check
    measures it (median over steps of at least MIN_STEP)."""
    world = room(8.0, 6.0)
    sim = simulate(world, loop_trajectory(world), scan_rate=1.0, lidar=Lidar(beams=180), seed=0,
                   laser_pose=(0.15, 0.0, 0.0), odom_noise=MODELS[request.param])
    records = list(sim.records(["/scan", "/odom"]))
    scans = [r for r in records if isinstance(r, Scan)]
    odometry = [r for r in records if isinstance(r, Odometry)]
    gt = sim.ground_truth
    odo = np.array([(r.time, r.x, r.y, r.yaw) for r in odometry])
    at = np.column_stack([np.interp(gt[:, 0], odo[:, 0], odo[:, 1]), np.interp(gt[:, 0], odo[:, 0], odo[:, 2]),
                          np.interp(gt[:, 0], odo[:, 0], np.unwrap(odo[:, 3]))])
    by_odometry = transform.relative(at[:-1], at[1:])
    truly = transform.relative(gt[:-1, 1:], gt[1:, 1:])
    step = np.hypot(by_odometry[:, 0], by_odometry[:, 1])
    keep = step >= MIN_STEP
    truth = float(np.median(np.hypot(*(by_odometry[keep, :2] - truly[keep, :2]).T) / step[keep]))
    return request.param, sim, scans, odometry, truth


def test_the_measured_error_follows_the_odometrys_own(drive):
    name, sim, scans, odometry, truth = drive
    measured = odometry_error(scans, odometry, Options(), laser_pose=sim.laser_pose)
    assert measured is not None
    # Measured at 0.010 / 0.026 / 0.127 against true 0 / 0.035 / 0.151 (a 5 cm map's match errs by about a
    # centimetre a step): within half to one and a half times the truth, plus that centimetre.
    assert 0.5 * truth <= measured <= 1.5 * truth + 0.015, (name, measured, truth)


def test_too_little_motion_leaves_the_error_unmeasured(drive):
    _, sim, scans, odometry, _ = drive
    # Five scans give four steps: fewer than the ten a median needs.
    assert odometry_error(scans[:5], odometry, Options(), laser_pose=sim.laser_pose) is None
