import math

import numpy as np
import pytest

from carto_cli.core import transform as tf


def matrix(pose):
    c, s = math.cos(pose[2]), math.sin(pose[2])
    return np.array([[c, -s, pose[0]], [s, c, pose[1]], [0.0, 0.0, 1.0]])


def from_matrix(m):
    return np.array([m[0, 2], m[1, 2], math.atan2(m[1, 0], m[0, 0])])


@pytest.fixture
def poses():
    rng = np.random.default_rng(3)
    return rng.uniform([-5, -5, -4], [5, 5, 4], size=(20, 3))


def test_compose_matches_matrix_product(poses):
    for a, b in zip(poses[:-1], poses[1:]):
        expected = from_matrix(matrix(a) @ matrix(b))
        np.testing.assert_allclose(tf.compose(a, b), expected, atol=1e-12)


def test_inverse_and_relative(poses):
    for a, b in zip(poses[:-1], poses[1:]):
        np.testing.assert_allclose(tf.compose(a, tf.inverse(a)), np.zeros(3), atol=1e-12)
        np.testing.assert_allclose(tf.compose(a, tf.relative(a, b)), tf.compose(tf.IDENTITY, b), atol=1e-12)


def test_vectorised_over_pose_stacks(poses):
    stacked = tf.compose(poses[:-1], poses[1:])
    single = np.array([tf.compose(a, b) for a, b in zip(poses[:-1], poses[1:])])
    np.testing.assert_allclose(stacked, single, atol=1e-12)
    np.testing.assert_allclose(tf.inverse(poses), np.array([tf.inverse(p) for p in poses]), atol=1e-12)


def test_apply_to_points(poses):
    pts = np.random.default_rng(0).normal(size=(50, 2))
    for p in poses[:5]:
        expected = (matrix(p) @ np.c_[pts, np.ones(len(pts))].T).T[:, :2]
        np.testing.assert_allclose(tf.apply(p, pts), expected, atol=1e-12)
    np.testing.assert_allclose(tf.apply(tf.inverse(poses[0]), tf.apply(poses[0], pts)), pts, atol=1e-12)


def test_wrap_angle():
    assert tf.wrap_angle(3 * math.pi) == pytest.approx(-math.pi)
    assert tf.wrap_angle(-math.pi) == pytest.approx(-math.pi)
    assert tf.wrap_angle(0.5 + 4 * math.pi) == pytest.approx(0.5)
    a = tf.wrap_angle(np.linspace(-20, 20, 101))
    assert a.min() >= -math.pi and a.max() < math.pi
    np.testing.assert_allclose(np.cos(a), np.cos(np.linspace(-20, 20, 101)), atol=1e-12)
