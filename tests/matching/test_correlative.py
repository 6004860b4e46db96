import math

import numpy as np
import pytest

from room_sim import build_room_grid, scan_points
from carto_cli.mapping.grid import ProbabilityGrid
from carto_cli.matching.correlative import match, search_parameters

TRUTH = np.array([3.0, 2.8, 0.3])


@pytest.fixture(scope="module")
def room():
    rng = np.random.default_rng(11)
    poses = [TRUTH + rng.normal(0, [0.1, 0.1, 0.05]) for _ in range(10)]
    return build_room_grid(poses), scan_points(TRUTH, noise=0.01, rng=rng)


def test_search_parameters_follow_the_farthest_point():
    pts = np.array([[0.5, 0.0], [0.0, -4.0]])
    p = search_parameters(pts, 0.05, 0.1, math.radians(20))
    assert p.num_linear_perturbations == 2
    assert p.angular_step == pytest.approx((1 - 1e-3) * math.acos(1 - 0.05 ** 2 / (2 * 4.0 ** 2)))
    assert p.num_angular_perturbations == math.ceil(math.radians(20) / p.angular_step)
    assert p.num_candidates == 25 * (2 * p.num_angular_perturbations + 1)


@pytest.mark.parametrize("offset", [(0.05, -0.1, math.radians(5)), (-0.1, 0.05, -math.radians(12)),
                                    (0.0, 0.1, math.radians(18))])
def test_finds_known_offset_in_room(room, offset):
    grid, pts = room
    pose, score = match(grid, pts, TRUTH + np.array(offset))
    step = search_parameters(pts, grid.resolution, 0.1, math.radians(20)).angular_step
    assert np.hypot(*(pose[:2] - TRUTH[:2])) < 0.5 * grid.resolution
    assert abs(pose[2] - TRUTH[2]) <= step
    assert 0.5 < score <= 0.9


def test_prefers_the_prediction_where_the_map_says_nothing():
    grid = ProbabilityGrid.centered((0.0, 0.0))
    pose, score = match(grid, scan_points(TRUTH), (1.0, 2.0, 0.4))
    np.testing.assert_allclose(pose, [1.0, 2.0, 0.4], atol=1e-12)
    assert score == pytest.approx(0.1)  # unknown cells count as probability 0.1
