import math

import numpy as np
import pytest
from support import draws

from carto_cli.grid.probability_grid import MAX_PROBABILITY, MIN_PROBABILITY, ProbabilityGrid, probability_to_value
from carto_cli.grid.range_inserter import ProbabilityGridRangeDataInserter
from carto_cli.matching import branch_and_bound as bnb
from carto_cli.matching.precomputation import PrecomputationGridStack
from carto_cli.sensor.range_filter import crop_polar
from carto_cli.sim import Lidar, loop_building
from carto_cli.sim.world import World, polyline

LIDAR = Lidar(beams=360, fov=2 * math.pi, max_range=15.0, noise=0.01, dropout=0.0)


def scan(world, pose, rng):
    """Returns of one scan at ``pose`` in the sensor frame, (n, 2)."""
    ranges = LIDAR.measure(np.asarray(pose, float)[None], world.segments, rng)[0]
    return crop_polar(ranges, LIDAR.angles(), max_range=LIDAR.max_range).returns


def route_poses(world, spacing):
    wp = np.vstack([world.route, world.route[:1]]) if world.closed else world.route
    poses = []
    for a, b in zip(wp[:-1], wp[1:]):
        m = max(int(np.hypot(*(b - a)) / spacing), 1)
        yaw = math.atan2(b[1] - a[1], b[0] - a[0])
        poses += [[*(a + t * (b - a)), yaw] for t in np.arange(m) / m]
    return np.array(poses)


@pytest.fixture(scope="module")
def building():
    """A loop building mapped with the real inserter from scans every 0.5 m of its route."""
    world = loop_building()
    rng = np.random.default_rng(0)
    x0, y0, x1, y1 = world.bounds
    grid = ProbabilityGrid(0.05, (x0 - 1.0, y0 - 1.0), (int((x1 - x0 + 2) / 0.05), int((y1 - y0 + 2) / 0.05)))
    inserter = ProbabilityGridRangeDataInserter()
    for pose in route_poses(world, 0.5):
        ranges = LIDAR.measure(pose[None], world.segments, rng)[0]
        inserter.insert(crop_polar(ranges, LIDAR.angles(), max_range=LIDAR.max_range).transformed(pose), grid)
    return world, grid, PrecomputationGridStack(grid, 7)


def random_problem(rng, depth=None, ties=False):
    """A small grid, a few scan points near it and windows that reach past its edges."""
    nx, ny = (int(v) for v in rng.integers(4, 36, 2))
    grid = ProbabilityGrid(0.1, rng.uniform(-2, 2, 2), (nx, ny))
    known = rng.random((ny, nx)) < rng.uniform(0.3, 1.0)
    # Few distinct values make many equal scores, which the tie-break must order like the oracle.
    p = rng.choice([MIN_PROBABILITY, 0.5, MAX_PROBABILITY], known.sum()) if ties else \
        rng.uniform(MIN_PROBABILITY, MAX_PROBABILITY, known.sum())
    grid.cells[known] = probability_to_value(p)
    stack = PrecomputationGridStack(grid, int(rng.integers(1, 6)) if depth is None else depth)
    pts = rng.normal(0.0, rng.uniform(0.2, 1.2), (int(rng.integers(1, 25)), 2))
    initial = np.array([*(grid.origin + rng.uniform(-0.2, 1.2, 2) * np.array([nx, ny]) * 0.1),
                        rng.uniform(-math.pi, math.pi)])
    kw = dict(linear_search_window=float(rng.uniform(0.0, 2.0)), angular_search_window=float(rng.uniform(0, 0.6)),
              min_score=float(rng.choice([0.0, 0.3, rng.uniform(0.1, 0.6)])))
    return stack, pts, initial, kw


def assert_same(a, b):
    assert a.found == b.found
    assert a.score == b.score
    np.testing.assert_array_equal(a.pose, b.pose)


@pytest.mark.parametrize("depth", [1, 2, 3, 4, 5])
@pytest.mark.parametrize("ties", [False, True])
def test_branch_and_bound_equals_exhaustive_search(depth, ties):
    rng = np.random.default_rng(depth * 10 + ties)
    found = 0
    for _ in range(draws(12, 4)):  # 4: found at least 3 times for every depth and seed here too
        stack, pts, initial, kw = random_problem(rng, depth, ties)
        result = bnb.match(stack, pts, initial, **kw)
        assert_same(result, bnb.exhaustive_match(stack, pts, initial, **kw))
        found += result.found
        # Coarse-to-fine searches a subset of the same candidates: never better, never found alone.
        coarse = bnb.match_multilevel(stack, pts, initial, levels=[(1.0, depth - 1), (0.0, 0)], **kw)
        assert coarse.score <= result.score and (result.found or not coarse.found)
    assert found >= 3  # the comparison must not be vacuous


@pytest.mark.parametrize("seed", range(3))
def test_full_submap_search_equals_exhaustive_search(seed):
    rng = np.random.default_rng(100 + seed)
    stack, pts, _, _ = random_problem(rng)
    pts = pts[:6] * 0.5  # few, close points: a small angular step count keeps the oracle quick
    nx, ny = stack.num_cells
    result = bnb.match_full_submap(stack, pts, min_score=0.2)
    oracle = bnb.exhaustive_match(stack, pts, bnb.full_submap_center(stack),
                                  linear_search_window=(nx + ny) * stack.resolution,
                                  angular_search_window=math.pi, min_score=0.2)
    assert_same(result, oracle)


def test_found_means_strictly_above_min_score():
    rng = np.random.default_rng(7)
    stack, pts, initial, kw = random_problem(rng, 3)
    kw["min_score"] = 0.1
    best = bnb.match(stack, pts, initial, **kw)
    assert best.found
    kw["min_score"] = best.score
    at = bnb.match(stack, pts, initial, **kw)
    assert not at.found and at.score == 0.0
    np.testing.assert_array_equal(at.pose, initial)
    kw["min_score"] = best.score - 1e-6
    assert_same(bnb.match(stack, pts, initial, **kw), best)


def test_empty_scan_finds_nothing():
    stack = PrecomputationGridStack(ProbabilityGrid(0.05, (0, 0), (10, 10)), 3)
    assert not bnb.match(stack, np.empty((0, 2)), (0.1, 0.2, 0.3)).found
    assert not bnb.match_full_submap(stack, np.empty((0, 2))).found
    assert not bnb.match_multilevel(stack, np.empty((0, 2)), (0.1, 0.2, 0.3)).found


def test_where_the_map_cannot_tell_the_prior_wins():
    # A uniformly occupied grid: every candidate scores the same.
    grid = ProbabilityGrid(0.05, (0.0, 0.0), (60, 60))
    grid.cells[:] = probability_to_value(0.9)
    stack = PrecomputationGridStack(grid, 4)
    initial = np.array([1.5, 1.5, 0.2])
    result = bnb.match(stack, [[0.3, 0.0], [0.0, 0.2]], initial, linear_search_window=0.5, min_score=0.5)
    assert result.found and result.score == pytest.approx(0.9)
    np.testing.assert_allclose(result.pose, initial, atol=1e-12)


TRUTHS = [np.array([12.0, 1.25, 0.3]), np.array([22.75, 9.0, 1.9])]
OFFSETS = [(1.3, 0.0, math.radians(12)), (-0.7, 1.1, -math.radians(12)), (0.9, -0.94, math.radians(25))]


@pytest.mark.slow_without_jit
@pytest.mark.parametrize("truth", TRUTHS, ids=["bottom", "right"])
@pytest.mark.parametrize("offset", OFFSETS, ids=["x+", "xy-", "xy+"])
def test_finds_a_known_offset_in_a_building(building, truth, offset):
    world, grid, stack = building
    pts = scan(world, truth, np.random.default_rng(1))
    initial = truth + np.array(offset)
    step = bnb.angular_step(pts, grid.resolution)
    result = bnb.match(stack, pts, initial)
    assert result.found and result.score > 0.65
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 1.5 * grid.resolution
    assert abs(result.pose[2] - truth[2]) < 3 * step
    # Here the coarse stage lands in the right neighbourhood, so the result is the exact one.
    assert_same(bnb.match_multilevel(stack, pts, initial), result)


@pytest.mark.slow_without_jit
def test_full_submap_search_localises_without_a_prior(building):
    world, grid, stack = building
    truth = TRUTHS[1]
    pts = scan(world, truth, np.random.default_rng(2))
    result = bnb.match_full_submap(stack, pts, min_score=0.6)
    assert result.found
    assert np.hypot(*(result.pose[:2] - truth[:2])) < 1.5 * grid.resolution
    assert abs(result.pose[2] - truth[2]) < 3 * bnb.angular_step(pts, grid.resolution)


@pytest.mark.slow_without_jit
def test_min_score_rejects_a_scan_of_a_different_place(building):
    _, _, stack = building
    # A heptagonal hall: no wall of it lines up with the building's corridors and rooms for long.
    a = np.linspace(0.0, 2 * math.pi, 8)[:-1] + 0.2
    hall = World(polyline(np.stack([5 + 4 * np.cos(a), 5 + 4 * np.sin(a)], axis=1), closed=True))
    pts = scan(hall, (5.5, 4.5, 0.0), np.random.default_rng(3))
    for initial in TRUTHS:
        for matcher in (bnb.match, bnb.match_multilevel):
            result = matcher(stack, pts, initial)
            assert not result.found and result.score == 0.0
            np.testing.assert_allclose(result.pose, initial)  # the estimate comes back untouched
        # Not a near miss: the best pose in the window is far below the threshold.
        assert bnb.match(stack, pts, initial, min_score=0.1).score < 0.45
    assert not bnb.match_full_submap(stack, pts).found


@pytest.mark.slow_without_jit
def test_pruning_scores_a_small_part_of_the_window(building):
    world, _, stack = building
    truth = TRUTHS[0]
    pts = scan(world, truth, np.random.default_rng(4))
    initial = truth + np.array(OFFSETS[0])
    cost = bnb.search_cost(stack, pts, initial, linear_search_window=7.0, angular_search_window=math.radians(30))
    assert cost.found == bnb.match(stack, pts, initial).found
    assert cost.found and cost.scored_fraction < 0.01


@pytest.mark.slow_without_jit
def test_single_level_multilevel_is_the_plain_search(building):
    world, _, stack = building
    pts = scan(world, TRUTHS[0], np.random.default_rng(5))
    initial = TRUTHS[0] + np.array(OFFSETS[1])
    assert_same(bnb.match_multilevel(stack, pts, initial, levels=[(1.0, 0)]), bnb.match(stack, pts, initial))
    with pytest.raises(ValueError):
        bnb.match_multilevel(stack, pts, initial, levels=[(1.0, 2)])
    with pytest.raises(ValueError):
        bnb.match_multilevel(stack, pts, initial, levels=[(1.0, 7), (0.1, 0)])


@pytest.mark.slow_without_jit
def test_peaks_answers_the_same_on_any_number_of_threads(building, monkeypatch):
    """Each coarse stage's angles dealt to threads: the kernel orders leaves totally, so the best of the shares'
    bests is the whole search's (ties included: grids of three values; small windows split too, here)."""
    monkeypatch.setattr(bnb, "SPLIT_MIN_ANGLES", 2)
    rng = np.random.default_rng(11)
    cases = []
    for trial in range(25):
        stack, pts, initial, kw = random_problem(rng, ties=trial % 2 == 0)
        kw["angular_search_window"] = float(rng.uniform(0.3, math.pi))
        window = (kw["linear_search_window"], kw["angular_search_window"], kw["min_score"])
        cases.append((stack, pts, initial, window, [(1.0, min(2, stack.depth - 1)), (0.0, 0)]))
    world, grid, stack = building
    for k, truth in enumerate(TRUTHS):
        pts = scan(world, truth, np.random.default_rng(20 + k))
        centre = bnb.full_submap_center(stack)
        nx, ny = stack.num_cells
        cases.append((stack, pts, centre, ((nx + ny) * grid.resolution, math.pi, 0.4), [(1.0, 3), (0.0, 0)]))
    for stack, pts, initial, window, levels in cases:
        search = bnb.PeakSearch(*window, levels=levels, count=2, distinct_xy=0.3, distinct_yaw=0.3, tries=4)
        answers = [bnb.peaks(stack, pts, initial, search=search, jobs=jobs) for jobs in (1, 2, 3)]
        for other in answers[1:]:
            assert len(other) == len(answers[0])
            for a, b in zip(answers[0], other):
                assert_same(a, b)
    assert answers[0], "the last case, a scan of the building searched over the whole map, finds places"
