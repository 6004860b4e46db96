"""gmapping.motion: the odometry increment, the noise it implies, and sampling from it."""
import math

import numpy as np
import pytest

from carto_cli.core.transform import wrap_angle
from carto_cli.gmapping import motion

# slam_gmapping's defaults (and the profile's): srr, srt, str, stt.
SRR, SRT, STR, STT = 0.1, 0.2, 0.1, 0.2


def _in_robot_frame(start, poses):
    """Each pose's offset from ``start`` in ``start``'s frame: the increment that was applied."""
    c, s = math.cos(start[2]), math.sin(start[2])
    dx, dy = poses[:, 0] - start[0], poses[:, 1] - start[1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, wrap_angle(poses[:, 2] - start[2])], axis=1)


def test_increment_is_the_motion_in_the_previous_pose_frame():
    np.testing.assert_allclose(motion.increment((1.0, 2.0, math.pi / 2), (1.0, 3.0, math.pi / 2 + 0.1)),
                               [1.0, 0.0, 0.1], atol=1e-12)
    np.testing.assert_allclose(motion.increment((0.0, 0.0, math.pi), (-2.0, 0.5, math.pi)), [2.0, -0.5, 0.0],
                               atol=1e-12)
    # Across the +-pi seam the heading change is the short way round.
    np.testing.assert_allclose(motion.increment((0.0, 0.0, 3.1), (0.0, 0.0, -3.1)), [0.0, 0.0, 2 * math.pi - 6.2],
                               atol=1e-12)


def test_predict_undoes_increment():
    rng = np.random.default_rng(0)
    for _ in range(300):
        p0 = np.array([*rng.uniform(-20, 20, 2), rng.uniform(-math.pi, math.pi)])
        p1 = np.array([*(p0[:2] + rng.uniform(-3, 3, 2)), rng.uniform(-math.pi, math.pi)])
        back = motion.predict(p0[None, :], motion.increment(p0, p1), np.zeros((1, 3)))[0]
        np.testing.assert_allclose(back[:2], p1[:2], atol=1e-9)
        assert abs(wrap_angle(back[2] - p1[2])) < 1e-9 and -math.pi <= back[2] <= math.pi


def test_predict_applies_noise_in_the_robot_frame():
    start = np.array([[2.0, 1.0, math.pi / 2]])
    out = motion.predict(start, (1.0, 0.0, 0.0), np.array([[0.1, -0.2, 0.3]]))[0]
    # (1.1, -0.2) along a robot facing +y is (+0.2, +1.1) in the world.
    np.testing.assert_allclose(out, [2.2, 2.1, math.pi / 2 + 0.3], atol=1e-12)


def test_sigmas_of_hand_computed_increments():
    np.testing.assert_allclose(motion.sigmas((1.0, 0.0, 0.0), SRR, SRT, STR, STT), [0.1, 0.03, 0.2])
    np.testing.assert_allclose(motion.sigmas((0.0, 0.0, -0.5), SRR, SRT, STR, STT), [0.05, 0.05, 0.1])
    # along 0.1*0.3 + 0.1*0.2 + 0.3*0.1*0.1, lateral 0.1*0.1 + 0.1*0.2 + 0.3*0.1*0.3, heading 0.2*0.2 + 0.2*|(0.3, 0.1)|
    np.testing.assert_allclose(motion.sigmas((0.3, -0.1, -0.2), SRR, SRT, STR, STT),
                               [0.053, 0.039, 0.04 + 0.2 * math.hypot(0.3, 0.1)])
    np.testing.assert_allclose(motion.sigmas((0.0, 0.0, 0.0), SRR, SRT, STR, STT),
                               [motion.MIN_SIGMA_XY, motion.MIN_SIGMA_XY, motion.MIN_SIGMA_THETA])


@pytest.mark.parametrize("delta", [(0.5, 0.0, 0.0), (0.0, 0.0, 0.6), (0.3, 0.05, -0.4)],
                         ids=["translation", "rotation", "mixed"])
def test_sample_spreads_as_sigmas_say(delta):
    start = np.array([1.0, -2.0, 2.5])
    n = 40000
    sigma = motion.sigmas(delta, SRR, SRT, STR, STT)
    out = motion.sample(np.tile(start, (n, 1)), delta, sigma, np.random.default_rng(11))
    inc = _in_robot_frame(start, out)
    # The sample std of 40000 normal draws is within 0.4 % of sigma at one sigma: 3 % is over seven.
    np.testing.assert_allclose(inc.std(axis=0), sigma, rtol=0.03)
    np.testing.assert_allclose(inc.mean(axis=0), delta, atol=5 * float(sigma.max()) / math.sqrt(n))
    # The three axes are drawn independently.
    corr = np.corrcoef(inc.T)
    assert np.all(np.abs(corr[np.triu_indices(3, 1)]) < 0.03)


def test_standing_still_barely_spreads():
    start = np.array([0.5, 0.5, -1.0])
    sigma = motion.sigmas((0.0, 0.0, 0.0), SRR, SRT, STR, STT)
    out = motion.sample(np.tile(start, (20000, 1)), (0.0, 0.0, 0.0), sigma, np.random.default_rng(2))
    inc = _in_robot_frame(start, out)
    sd = inc.std(axis=0)
    assert np.all(sd[:2] < 1.5e-3) and sd[2] < math.radians(0.1)
    np.testing.assert_allclose(sd, [motion.MIN_SIGMA_XY, motion.MIN_SIGMA_XY, motion.MIN_SIGMA_THETA], rtol=0.05)


def test_world_sigmas_are_the_spread_of_the_samples_in_the_world():
    # The noise is drawn in the frame of the pose the particle moves from: that pose's heading turns the ellipse.
    delta = (0.5, 0.0, 0.2)
    sigma = motion.sigmas(delta, SRR, SRT, STR, STT)
    for heading in (0.0, 0.7, math.pi / 2, -2.0):
        start = np.array([3.0, 4.0, heading])
        out = motion.sample(np.tile(start, (40000, 1)), delta, sigma, np.random.default_rng(4))
        expected = motion.world_sigmas(start[None, :], sigma)[0]
        np.testing.assert_allclose(out[:, :2].std(axis=0), expected[:2], rtol=0.03)
        assert expected[2] == sigma[2]
        # The ellipse is the robot frame's: at heading 0 the world's x is the robot's axis.
        if heading == 0.0:
            np.testing.assert_allclose(expected[:2], sigma[:2])
        if heading == math.pi / 2:
            np.testing.assert_allclose(expected[:2], sigma[1::-1])
