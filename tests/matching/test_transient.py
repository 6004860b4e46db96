import math

import numpy as np
import pytest
from room_sim import build_room_grid, scan_points

from carto_cli.core import transform
from carto_cli.grid.probability_grid import UNKNOWN_VALUE, VALUE_TO_PROBABILITY, ProbabilityGrid
from carto_cli.grid.range_inserter import ProbabilityGridRangeDataInserter
from carto_cli.matching.least_squares import match
from carto_cli.matching.transient import OCCUPIED_PROBABILITY, transient_mask
from carto_cli.sensor.range_filter import RangeData

TRUTH = np.array([3.0, 2.8, 0.3])
FREE = 0.3
CLEARANCE = 0.25


def reference_mask(grid, points, pose, max_free_probability, clearance):
    """Point by point, as the module's docstring states it."""
    reach = int(math.ceil(clearance / grid.resolution - 1e-9))
    cells = grid.cell_index(transform.apply(pose, points))
    ny, nx = grid.cells.shape
    out = np.zeros(len(points), dtype=bool)
    for k, (ix, iy) in enumerate(cells):
        if not (0 <= ix < nx and 0 <= iy < ny) or grid.cells[iy, ix] == UNKNOWN_VALUE:
            continue
        if VALUE_TO_PROBABILITY[grid.cells[iy, ix]] > max_free_probability:
            continue
        near = grid.cells[max(iy - reach, 0):iy + reach + 1, max(ix - reach, 0):ix + reach + 1]
        out[k] = not ((near != UNKNOWN_VALUE) & (VALUE_TO_PROBABILITY[near] >= OCCUPIED_PROBABILITY)).any()
    return out


def test_mask_matches_the_reference_on_a_random_grid():
    rng = np.random.default_rng(3)
    grid = ProbabilityGrid(0.05, (-1.0, -2.0), (60, 50))
    cells = np.argwhere(rng.random((60, 50)) < 0.7)
    grid.set_probability(cells, rng.choice([0.1, 0.2, 0.35, 0.45], len(cells)))
    grid.set_probability(cells[rng.choice(len(cells), 12)], rng.choice([0.5, 0.9], 12))  # a few walls
    points = rng.uniform(-2.0, 3.0, (2000, 2))  # some outside the grid
    pose = np.array([0.3, -0.2, 0.4])
    for free, clearance in ((0.3, 0.25), (0.25, 0.0), (0.45, 0.1)):
        got = transient_mask(grid, points, pose, max_free_probability=free, clearance=clearance)
        want = reference_mask(grid, points, pose, free, clearance)
        np.testing.assert_array_equal(got, want)
        assert 0 < got.sum() < len(points)


def _crowd(centres, radius=0.2, per_person=24):
    a = np.arange(per_person) * 2 * math.pi / per_person
    ring = radius * np.column_stack([np.cos(a), np.sin(a)])
    return np.vstack([c + ring for c in centres])


# Where people stood in the room (world frame), all in its free middle, clear of the walls and furniture.
PEOPLE = np.array([[2.2, 2.0], [2.9, 1.6], [3.6, 2.2], [2.6, 3.0], [4.1, 3.1], [3.3, 3.6], [1.8, 2.9]])
# Where the same people were when the submap took them in: a cell beside, within the bicubic's reach (a trail two
# or more cells off pulls a few millimetres at most, the interpolated cost is flat there)
TRAIL = np.array([0.04, 0.0])


@pytest.fixture(scope="module")
def crowded_room():
    """The room seen through from 40 poses, then the crowd inserted a few times where it stood moments ago; the
    scan at ``TRUTH``: the room's returns and the crowd where it stands now."""
    rng = np.random.default_rng(1)
    poses = [TRUTH + rng.normal(0, [0.1, 0.1, 0.05]) for _ in range(40)]
    grid = build_room_grid(poses, n=720)
    inserter = ProbabilityGridRangeDataInserter()
    earlier = _crowd(PEOPLE + TRAIL)
    for _ in range(3):
        inserter.insert(RangeData(TRUTH[:2].copy(), earlier, np.empty((0, 2))), grid)
    room = scan_points(TRUTH, noise=0.01, rng=rng)
    crowd = transform.apply(transform.inverse(TRUTH), _crowd(PEOPLE))
    return grid, np.vstack([room, crowd]), len(room)


def test_the_crowd_is_found_and_the_room_kept(crowded_room):
    grid, points, n_room = crowded_room
    mask = transient_mask(grid, points, TRUTH, max_free_probability=FREE, clearance=CLEARANCE)
    assert mask[n_room:].mean() > 0.95
    assert mask[:n_room].sum() == 0
    # A slightly wrong pose keeps the room's points: the clearance is what protects them.
    off = TRUTH + np.array([0.08, -0.06, math.radians(2.0)])
    assert transient_mask(grid, points, off, max_free_probability=FREE, clearance=CLEARANCE)[:n_room].sum() == 0


def test_without_the_mask_the_crowd_pulls_the_match_with_it_the_pose_is_right(crowded_room):
    grid, points, _ = crowded_room
    weights = dict(translation_weight=1.0, rotation_weight=1.0)
    pulled = match(grid, points, TRUTH, **weights).pose
    kept = points[~transient_mask(grid, points, TRUTH, max_free_probability=FREE, clearance=CLEARANCE)]
    matched = match(grid, kept, TRUTH, **weights).pose
    # Measured: pulled 6.8 mm along the trail, matched 0.8 mm off (the room's own noise).
    pulled_by = np.hypot(*(pulled[:2] - TRUTH[:2]))
    off_by = np.hypot(*(matched[:2] - TRUTH[:2]))
    assert pulled_by > 0.005
    assert off_by < 0.002
    assert pulled[0] - TRUTH[0] > 0.9 * pulled_by  # towards the trail
