import numpy as np
import pytest

from carto_cli.mapping.submaps import ActiveSubmaps, Submap
from carto_cli.sensor.range_filter import RangeData


def range_data(x):
    return RangeData(np.array([x, 0.0]), np.array([[x + 1.0, 0.0], [x, 1.0]]), np.empty((0, 2)))


def test_life_cycle_with_two_active_submaps():
    n = 3
    active = ActiveSubmaps(num_range_data=n)
    history = []
    for k in range(1, 14):
        inserted = active.insert(range_data(0.1 * k))
        history.append([(s.index, s.num_range_data, s.finished) for s in inserted])
        # Every insertion goes into every active submap; matching is against the older one.
        assert [s.index for s in inserted] == [s.index for s in active.submaps]
        assert active.matching_submap is active.submaps[0]
    assert history[0] == [(0, 1, False)]
    assert history[2] == [(0, 3, False)]
    assert history[3] == [(0, 4, False), (1, 1, False)]
    assert history[5] == [(0, 6, True), (1, 3, False)]  # finished after 2 x num_range_data
    assert history[6] == [(1, 4, False), (2, 1, False)]  # the finished one has left the active set
    assert history[8] == [(1, 6, True), (2, 3, False)]
    assert history[12] == [(3, 4, False), (4, 1, False)]
    assert active.num_submaps_created == 5


def test_submap_origin_is_first_insertion_origin():
    active = ActiveSubmaps(num_range_data=2)
    for k in range(1, 4):
        active.insert(range_data(float(k)))
    first, second = active.submaps
    np.testing.assert_array_equal(first.local_pose, [1.0, 0.0, 0.0])
    np.testing.assert_array_equal(second.local_pose, [3.0, 0.0, 0.0])
    centre = first.grid.origin + 0.5 * first.grid.resolution * np.array(first.grid.num_cells)
    assert first.grid.contains(first.grid.cell_index([[1.0, 0.0], [4.0, 0.0]])).all()
    assert np.linalg.norm(centre - [1.0, 0.0]) < 5.0


def test_finished_submap_is_cropped_and_closed():
    s = Submap((0.0, 0.0), resolution=0.05)
    from carto_cli.grid.range_inserter import ProbabilityGridRangeDataInserter
    ins = ProbabilityGridRangeDataInserter()
    s.insert(range_data(0.0), ins)
    s.finish()
    assert s.finished and s.grid.num_cells == (21, 21)
    with pytest.raises(RuntimeError):
        s.insert(range_data(0.0), ins)
