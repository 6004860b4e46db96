"""gmapping.resampling: smoothed weights, Neff, the (adaptive) threshold and low-variance resampling."""
import math

import numpy as np
import pytest

from carto_cli.gmapping import resampling


def test_normalized_divides_the_log_weights_by_ogain_times_particles():
    # [0, -6] over ogain 3 x 2 particles: exp(0) and exp(-1), normalised.
    e = math.exp(-1.0)
    np.testing.assert_allclose(resampling.normalized(np.array([0.0, -6.0]), 3.0), [1 / (1 + e), e / (1 + e)],
                               rtol=1e-12)
    # ogain 1: exp(-6 / 2) = exp(-3).
    e3 = math.exp(-3.0)
    np.testing.assert_allclose(resampling.normalized(np.array([0.0, -6.0]), 1.0), [1 / (1 + e3), e3 / (1 + e3)],
                               rtol=1e-12)
    # Four particles, ogain 3: the divisor is 12, so exp(0, -1, -2, -3) normalised.
    z = np.exp([0.0, -1.0, -2.0, -3.0])
    np.testing.assert_allclose(resampling.normalized(np.array([0.0, -12.0, -24.0, -36.0]), 3.0), z / z.sum(),
                               rtol=1e-12)


def test_a_fixed_gain_count_makes_the_weights_independent_of_the_particle_count():
    # gain_particles 2, ogain 3: a particle 6 below the best weighs exp(-1) of it, among 2 particles or 200
    e = math.exp(-1.0)
    two = resampling.normalized(np.array([0.0, -6.0]), 3.0, 2)
    np.testing.assert_allclose(two, [1 / (1 + e), e / (1 + e)], rtol=1e-12)
    many = resampling.normalized(np.concatenate([[0.0], np.full(199, -6.0)]), 3.0, 2)
    np.testing.assert_allclose(many[1:] / many[0], e, rtol=1e-12)
    # GMapping's own scaling (0): among 200 particles the same gap is nearly no difference at all
    own = resampling.normalized(np.concatenate([[0.0], np.full(199, -6.0)]), 3.0, 0)
    np.testing.assert_allclose(own[1:] / own[0], math.exp(-6.0 / 600.0), rtol=1e-12)


def test_normalized_depends_on_differences_only_and_never_overflows():
    w = resampling.normalized(np.array([-5000.0, -5006.0]), 3.0)
    np.testing.assert_allclose(w, resampling.normalized(np.array([0.0, -6.0]), 3.0), rtol=1e-12)
    w = resampling.normalized(np.array([1e6, 1e6 - 30.0, 1e6 - 60.0]), 2.0)
    assert np.all(np.isfinite(w)) and w.sum() == pytest.approx(1.0)
    np.testing.assert_allclose(resampling.normalized(np.full(5, -7.0), 3.0), np.full(5, 0.2))


def test_neff_of_hand_computed_weights():
    assert resampling.neff(np.full(8, 1 / 8)) == pytest.approx(8.0)
    assert resampling.neff(np.array([0.0, 1.0, 0.0, 0.0])) == pytest.approx(1.0)
    assert resampling.neff(np.array([0.5, 0.5, 0.0, 0.0])) == pytest.approx(2.0)
    assert resampling.neff(np.array([0.25, 0.75])) == pytest.approx(1 / (0.0625 + 0.5625))  # 1.6


def test_threshold_is_the_share_of_particles_divided_by_one_plus_twice_the_entropy():
    assert resampling.threshold(50, 0.5) == pytest.approx(25.0)
    assert resampling.threshold(50, 0.5, 0.0) == pytest.approx(25.0)
    assert resampling.threshold(50, 0.5, 1.0) == pytest.approx(25.0 / 3.0)
    assert resampling.threshold(20, 0.5, 0.25) == pytest.approx(10.0 / 1.5)
    assert resampling.threshold(30, 0.8, 0.1) == pytest.approx(24.0 / 1.2)


def _counts(indices, n):
    return np.bincount(indices, minlength=n)


@pytest.mark.parametrize("n", [2, 7, 30])
def test_low_variance_copies_a_particle_floor_or_ceil_of_n_w_times(n):
    rng = np.random.default_rng(n)
    for trial in range(300):
        w = rng.dirichlet(np.full(n, 0.7))
        if trial % 3 == 0:
            w[rng.integers(0, n, max(1, n // 3))] = 0.0  # particles with no weight at all
            w /= w.sum()
        draw = np.random.default_rng(1000 + trial)
        for _ in range(5):
            idx = resampling.low_variance(w, draw)
            assert idx.shape == (n,) and idx.min() >= 0 and idx.max() < n
            counts = _counts(idx, n)
            nw = n * w
            assert np.all(counts >= np.floor(nw - 1e-9)) and np.all(counts <= np.ceil(nw + 1e-9)), (w, counts)
            assert np.all(counts[w == 0.0] == 0)


def test_low_variance_keeps_exact_shares_exactly():
    draw = np.random.default_rng(3)
    for _ in range(200):
        np.testing.assert_array_equal(_counts(resampling.low_variance(np.array([0.5, 0.5, 0.0, 0.0]), draw), 4),
                                      [2, 2, 0, 0])
        np.testing.assert_array_equal(_counts(resampling.low_variance(np.array([0.0, 0.25, 0.0, 0.75]), draw), 4),
                                      [0, 1, 0, 3])


def test_low_variance_frequencies_match_the_weights_on_average():
    n = 10
    w = np.array([0.31, 0.005, 0.12, 0.0, 0.0475, 0.2, 0.0825, 0.01, 0.195, 0.03])
    assert w.sum() == pytest.approx(1.0)
    rng = np.random.default_rng(7)
    draws = 4000
    total = np.zeros(n)
    for _ in range(draws):
        total += _counts(resampling.low_variance(w, rng), n)
    # Each count is floor or ceil of N w (variance <= 1/4), so the mean count over 4000 draws is within
    # 0.0079 of N w at one sigma: 0.004 on the frequency is five sigma after dividing by N.
    np.testing.assert_allclose(total / (draws * n), w, atol=0.004)


def test_low_variance_follows_the_generator():
    w = np.random.default_rng(0).dirichlet(np.ones(12))
    a = [resampling.low_variance(w, np.random.default_rng(5)) for _ in range(2)]
    np.testing.assert_array_equal(a[0], a[1])
    b = np.random.default_rng(5)
    runs = [resampling.low_variance(w, b) for _ in range(20)]
    assert any(not np.array_equal(runs[0], r) for r in runs[1:])
