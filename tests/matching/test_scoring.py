"""score_at and known_score on a grid with known cells of known probability, at poses that move the points."""
import math

import numpy as np
import pytest

from carto_cli.grid.probability_grid import ProbabilityGrid, probability_to_value
from carto_cli.matching.scoring import fit_scores, inlier_fraction, known_score, score_at


def _grid():
    """1 x 1 m at 0.1 m: cell (2, 3) at p = 0.9, cell (7, 3) at p = 0.3, every other cell unknown."""
    g = ProbabilityGrid(0.1, (0.0, 0.0), (10, 10))
    g.set_probability([[2, 3], [7, 3]], [0.9, 0.3])
    return g


def _p(g, cell):
    return float(g.probability(np.array([cell]))[0])  # stored probabilities are quantized


POINTS = np.array([[0.25, 0.35], [0.75, 0.35], [0.55, 0.55]])  # in cells (2, 3), (7, 3), (5, 5)


def test_score_at_averages_the_cells_under_the_points_unknown_counting_0_1():
    g = _grid()
    p9, p3 = _p(g, [2, 3]), _p(g, [7, 3])
    assert p9 == pytest.approx(0.9, abs=1e-3) and p3 == pytest.approx(0.3, abs=1e-3)
    assert score_at(g, POINTS, np.zeros(3)) == pytest.approx((p9 + p3 + 0.1) / 3, abs=1e-12)
    assert score_at(g, POINTS[:1], np.zeros(3)) == pytest.approx(p9)
    # Moved off the grid entirely: every point reads 0.1.
    assert score_at(g, POINTS, np.array([5.0, 5.0, 0.0])) == pytest.approx(0.1)
    assert score_at(g, np.zeros((0, 2)), np.zeros(3)) == 0.0


def test_the_pose_places_the_points():
    g = _grid()
    # (0.25, 0.35) rotated by 90 degrees about the origin is (-0.35, 0.25); shifted by (0.6, 0.1) it lands in
    # cell (2, 3), the occupied one.
    pose = np.array([0.6, 0.1, math.pi / 2])
    assert score_at(g, POINTS[:1], pose) == pytest.approx(_p(g, [2, 3]))
    assert known_score(g, POINTS[:1], pose) == (1.0, pytest.approx(_p(g, [2, 3])))


def test_known_score_is_the_share_and_mean_of_known_cells():
    g = _grid()
    share, mean = known_score(g, POINTS, np.zeros(3))
    assert share == pytest.approx(2 / 3)
    assert mean == pytest.approx((_p(g, [2, 3]) + _p(g, [7, 3])) / 2)
    assert known_score(g, POINTS, np.array([5.0, 5.0, 0.0])) == (0.0, 0.0)
    assert known_score(g, np.zeros((0, 2)), np.zeros(3)) == (0.0, 0.0)


def test_the_constraint_builder_scores_with_the_same_function():
    from carto_cli.mapping import constraint_builder

    assert constraint_builder.score_at is score_at


def test_fit_scores_are_the_three_scores_of_one_lookup():
    rng = np.random.default_rng(4)
    for trial in range(200):
        nx, ny = (int(v) for v in rng.integers(3, 50, 2))
        grid = ProbabilityGrid(0.05, rng.uniform(-1, 1, 2), (nx, ny))
        known = rng.random((ny, nx)) < rng.uniform(0.1, 0.9)
        grid.cells[known] = probability_to_value(rng.uniform(0.12, 0.9, known.sum()))
        points = rng.uniform(-2, 4, (int(rng.integers(0, 60)), 2))  # partly off the grid
        pose = np.array([rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(-3, 3)])
        mp = float(rng.choice([0.5, 0.3, 0.7]))
        expected = (score_at(grid, points, pose), *known_score(grid, points, pose),
                    inlier_fraction(grid, points, pose, min_probability=mp))
        got = fit_scores(grid, points, pose, min_probability=mp)
        assert got[1] == expected[1] and got[3] == expected[3], trial  # shares of counts: exact
        assert got == pytest.approx(expected, rel=1e-12, abs=1e-15), trial  # means: summed in another order
    with pytest.raises(ValueError):
        fit_scores(grid, points, pose, min_probability=0.0)
