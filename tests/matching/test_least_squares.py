import math

import numpy as np
import pytest
from room_sim import build_room_grid, scan_points

from carto_cli.matching.least_squares import CeresScanMatcher, evaluate, match

TRUTH = np.array([3.0, 2.8, 0.3])


@pytest.fixture(scope="module")
def room():
    rng = np.random.default_rng(1)
    poses = [TRUTH + rng.normal(0, [0.1, 0.1, 0.05]) for _ in range(20)]
    return build_room_grid(poses), scan_points(TRUTH, noise=0.01, rng=rng)


@pytest.mark.parametrize("direction_deg, dtheta_deg", [(30, 3), (135, -3), (250, 3), (330, -3)])
def test_converges_from_perturbed_pose(room, direction_deg, dtheta_deg):
    grid, pts = room
    a = math.radians(direction_deg)
    start = TRUTH + np.array([0.1 * math.cos(a), 0.1 * math.sin(a), math.radians(dtheta_deg)])
    # Regularisers off: this checks the occupied-space term and the solver, not the priors.
    result = match(grid, pts, start, translation_weight=1e-6, rotation_weight=1e-6)
    assert np.hypot(*(result.pose[:2] - TRUTH[:2])) < 0.01
    assert abs(math.degrees(result.pose[2] - TRUTH[2])) < 0.2
    assert result.cost < result.initial_cost
    assert 1 <= result.iterations <= 20


def test_default_weights_with_a_good_prediction(room):
    grid, pts = room
    result = match(grid, pts, TRUTH + np.array([0.04, -0.03, 0.0]), target_translation=TRUTH[:2])
    assert result.converged
    assert np.hypot(*(result.pose[:2] - TRUTH[:2])) < 0.01
    assert abs(math.degrees(result.pose[2] - TRUTH[2])) < 0.2


def test_a_component_s_matcher_uses_its_own_section(room):
    """Built once from an options section, it solves with that section's weights and iteration limit."""
    from carto_cli.options import load_options

    grid, pts = room
    section = load_options(None).pose_graph.constraint_builder.ceres_scan_matcher
    matcher = CeresScanMatcher.from_options(section)
    assert (matcher.occupied_space_weight, matcher.translation_weight, matcher.rotation_weight,
            matcher.max_num_iterations) == (20.0, 10.0, 1.0, 10)
    start = TRUTH + np.array([0.05, -0.04, 0.02])
    got = matcher.match(grid, pts, start, target_translation=TRUTH[:2])
    want = match(grid, pts, start, TRUTH[:2], occupied_space_weight=20.0, translation_weight=10.0,
                 rotation_weight=1.0, max_num_iterations=10)
    np.testing.assert_array_equal(got.pose, want.pose)
    assert got.iterations == want.iterations
    default = match(grid, pts, start, TRUTH[:2])  # local SLAM's defaults: another answer
    assert not np.array_equal(default.pose, got.pose)


def test_priors_alone_pull_to_target_and_initial_angle(room):
    grid, _ = room
    result = match(grid, np.empty((0, 2)), (1.0, 1.0, 0.2), target_translation=(1.5, 0.5))
    np.testing.assert_allclose(result.pose, [1.5, 0.5, 0.2], atol=1e-6)


def test_analytic_gradient_matches_finite_differences(room):
    grid, pts = room
    pose = TRUTH + np.array([0.013, -0.021, 0.011])
    kwargs = dict(target_translation=TRUTH[:2], initial_angle=TRUTH[2] + 0.02)
    _, jtj, jtr = evaluate(grid, pts, pose, **kwargs)
    h = 1e-6
    for k in range(3):
        d = np.zeros(3)
        d[k] = h
        fd = (evaluate(grid, pts, pose + d, **kwargs)[0] - evaluate(grid, pts, pose - d, **kwargs)[0]) / (2 * h)
        assert jtr[k] == pytest.approx(fd, rel=1e-4, abs=1e-7)
    assert np.all(np.linalg.eigvalsh(jtj) > 0)
