import math
from fractions import Fraction

import numpy as np
import pytest

from carto_cli.grid.probability_grid import UPDATE_MARKER, VALUE_TO_PROBABILITY, ProbabilityGrid, probability_to_value
from carto_cli.grid.range_inserter import (
    SUBPIXEL_SCALE,
    ProbabilityGridRangeDataInserter,
    compute_lookup_table_to_apply_odds,
    odds,
    ray_cells,
)
from carto_cli.sensor.range_filter import RangeData

# --- ray casting ----------------------------------------------------------------------------

def exact_cells(b, e, scale, closed):
    """Cells whose open (or closed) square the segment between sub-pixel points b+1/2 and e+1/2 meets."""
    p = [Fraction(2 * v + 1, 2 * scale) for v in b]
    q = [Fraction(2 * v + 1, 2 * scale) for v in e]
    d = [q[0] - p[0], q[1] - p[1]]
    out = set()
    lo_c = [math.floor(min(p[k], q[k])) - 1 for k in range(2)]
    hi_c = [math.floor(max(p[k], q[k])) + 1 for k in range(2)]
    for i in range(lo_c[0], hi_c[0] + 1):
        for j in range(lo_c[1], hi_c[1] + 1):
            lo, hi = Fraction(0), Fraction(1)
            ok = True
            for k, cell in ((0, i), (1, j)):
                if d[k] == 0:
                    inside = cell <= p[k] <= cell + 1 if closed else cell < p[k] < cell + 1
                    ok &= inside
                else:
                    t0, t1 = sorted(((cell - p[k]) / d[k], (cell + 1 - p[k]) / d[k]))
                    lo, hi = max(lo, t0), min(hi, t1)
            if ok and (lo <= hi if closed else lo < hi):
                out.add((i, j))
    return out


def cast(b, e, scale=SUBPIXEL_SCALE, include_end=True):
    n = abs(e[0] // scale - b[0] // scale) + abs(e[1] // scale - b[1] // scale) + 1
    out = np.empty((n, 2), dtype=np.int64)
    k = ray_cells(b[0], b[1], e[0], e[1], scale, include_end, out)
    return [tuple(c) for c in out[:k]]


def test_ray_cells_match_exact_segment_cover():
    rng = np.random.default_rng(7)
    scale = 10  # small scale so that exact corner crossings actually occur
    cases = [((5, 5), (5, 5)), ((5, 5), (95, 5)), ((3, 14), (3, -70)), ((5, 5), (45, 45)), ((0, 0), (-31, 62))]
    cases += [tuple(map(tuple, rng.integers(-80, 80, (2, 2)))) for _ in range(150)]
    for b, e in cases:
        cells = cast(b, e, scale)
        assert cells[0] == (b[0] // scale, b[1] // scale) and cells[-1] == (e[0] // scale, e[1] // scale)
        assert len(cells) == len(set(cells))
        for c0, c1 in zip(cells[:-1], cells[1:]):  # 4-connected walk
            assert abs(c0[0] - c1[0]) + abs(c0[1] - c1[1]) == 1
        assert exact_cells(b, e, scale, closed=False) <= set(cells) <= exact_cells(b, e, scale, closed=True)
        assert cast(b, e, scale, include_end=False) == cells[:-1]


def test_ray_cells_at_cartographer_scale():
    rng = np.random.default_rng(8)
    for _ in range(25):
        b, e = rng.integers(0, 15 * SUBPIXEL_SCALE, (2, 2))
        cells = cast(tuple(b), tuple(e))
        assert exact_cells(b, e, SUBPIXEL_SCALE, False) <= set(cells) <= exact_cells(b, e, SUBPIXEL_SCALE, True)


# --- odds tables ----------------------------------------------------------------------------

@pytest.mark.parametrize("p_update", [0.55, 0.49])
def test_odds_table_matches_formula(p_update):
    table = compute_lookup_table_to_apply_odds(odds(p_update))
    assert table.shape == (32768,) and (table >= UPDATE_MARKER).all()
    assert table[0] - UPDATE_MARKER == probability_to_value(p_update)  # unknown: takes the update as prior
    for v in (1, 2, 100, 5000, 16384, 30000, 32767):
        p = VALUE_TO_PROBABILITY[v]
        o = odds(p_update) * p / (1 - p)
        expected = probability_to_value(min(max(o / (1 + o), 0.1), 0.9))
        assert table[v] - UPDATE_MARKER == expected


def test_repeated_updates_clamp():
    hit = compute_lookup_table_to_apply_odds(odds(0.55)).astype(np.int64) - UPDATE_MARKER
    miss = compute_lookup_table_to_apply_odds(odds(0.49)).astype(np.int64) - UPDATE_MARKER
    v_hit = v_miss = 0
    for _ in range(200):
        v_hit, v_miss = hit[v_hit], miss[v_miss]
    assert VALUE_TO_PROBABILITY[v_hit] == pytest.approx(0.9)
    assert VALUE_TO_PROBABILITY[v_miss] == pytest.approx(0.1)


# --- insertion ------------------------------------------------------------------------------

P_HIT = VALUE_TO_PROBABILITY[probability_to_value(0.55)]
P_MISS = VALUE_TO_PROBABILITY[probability_to_value(0.49)]


def small_grid():
    return ProbabilityGrid(0.1, (0.0, 0.0), (20, 20))


def test_hits_excluded_from_their_own_ray_misses_included():
    g = small_grid()
    rd = RangeData(np.array([0.05, 0.05]), np.array([[0.55, 0.05]]), np.array([[0.05, 0.75]]))
    ProbabilityGridRangeDataInserter().insert(rd, g)
    np.testing.assert_allclose(g.probability([[5, 0]]), [P_HIT])
    np.testing.assert_allclose(g.probability([[i, 0] for i in range(1, 5)]), P_MISS)
    np.testing.assert_allclose(g.probability([[0, j] for j in range(8)]), P_MISS)  # miss end cell (0, 7) too
    assert np.isnan(g.probability([[6, 0], [0, 8]])).all()
    assert (g.cells < UPDATE_MARKER).all()
    assert g.known_bounds == (0, 0, 5, 7)


def test_each_cell_updated_once_per_insertion():
    g = small_grid()
    origin = np.array([0.05, 0.05])
    # Two nearly identical rays cross the same cells; the first ray's hit cell lies on the second ray.
    returns = np.array([[0.95, 0.06], [1.45, 0.07], [0.96, 0.05]])
    ProbabilityGridRangeDataInserter().insert(RangeData(origin, returns, np.empty((0, 2))), g)
    np.testing.assert_allclose(g.probability([[9, 0], [14, 0]]), P_HIT)  # the hit survives the farther ray
    np.testing.assert_allclose(g.probability([[i, 0] for i in range(9)] + [[i, 0] for i in range(10, 14)]), P_MISS)
    # A second insertion updates again, through the odds tables.
    ProbabilityGridRangeDataInserter().insert(RangeData(origin, returns, np.empty((0, 2))), g)
    o = odds(0.49) * odds(P_MISS)
    np.testing.assert_allclose(g.probability([[3, 0]]), [o / (1 + o)], atol=1e-4)


def test_insert_free_space_false_marks_hits_only():
    g = small_grid()
    rd = RangeData(np.array([0.05, 0.05]), np.array([[0.55, 0.05], [0.05, 0.55]]), np.array([[1.0, 1.0]]))
    ProbabilityGridRangeDataInserter(insert_free_space=False).insert(rd, g)
    assert (g.cells != 0).sum() == 2
    np.testing.assert_allclose(g.probability([[5, 0], [0, 5]]), P_HIT)


def test_insert_grows_grid_and_keeps_old_cells():
    g = small_grid()
    ins = ProbabilityGridRangeDataInserter()
    ins.insert(RangeData(np.array([1.0, 1.0]), np.array([[1.5, 1.0]]), np.empty((0, 2))), g)
    before = g.probability(g.cell_index([[1.52, 1.0], [1.25, 1.0]]))
    ins.insert(RangeData(np.array([1.0, 1.0]), np.array([[-3.0, 1.0], [1.0, 6.0]]), np.empty((0, 2))), g)
    assert g.contains(g.cell_index([[-3.0, 1.0], [1.0, 6.0]])).all()
    np.testing.assert_allclose(g.probability(g.cell_index([[1.52, 1.0]])), before[:1])
    np.testing.assert_allclose(g.probability(g.cell_index([[-3.0, 1.0], [1.0, 6.0]])), P_HIT)


def test_insert_many_casts_once_per_lattice_and_matches_separate_insertions():
    from carto_cli.core.timing import StageTimer, report_json

    rng = np.random.default_rng(5)
    angles = np.linspace(-2.3, 2.3, 300)
    r = rng.uniform(0.5, 6.0, angles.size)
    origin = np.array([0.3, -0.2])
    rd = RangeData(origin, origin + np.c_[r * np.cos(angles), r * np.sin(angles)],
                   origin + 5.0 * np.c_[np.cos(angles[::7] + 0.01), np.sin(angles[::7] + 0.01)])
    # Two grids on one lattice (origins whole cells apart), one off it; all must grow.
    grids = [ProbabilityGrid(0.05, (-1.0, -1.0), (20, 20)), ProbabilityGrid(0.05, (0.5, 0.25), (30, 10)),
             ProbabilityGrid(0.05, (0.012, 0.031), (10, 10))]
    separate = [g.copy() for g in grids]
    timer = StageTimer()
    ins = ProbabilityGridRangeDataInserter()
    counts = ins.insert_many(rd, grids, timer)
    for g, counted in zip(separate, counts):
        assert ins.insert(rd, g) == counted > 0
    for g, s in zip(grids, separate):
        np.testing.assert_array_equal(g.cells, s.cells)
        np.testing.assert_array_equal(g.origin, s.origin)
        np.testing.assert_array_equal(g.known_box, s.known_box)
        assert (g.cells < UPDATE_MARKER).all()
    stages = report_json(timer)["stages"]
    assert stages["ray casting"]["calls"] == 2  # the third grid is off the lattice
    assert stages["update"]["calls"] == 3
