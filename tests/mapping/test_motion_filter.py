import math

from carto_cli.mapping.motion_filter import MotionFilter


def test_keeps_first_then_only_on_enough_motion():
    f = MotionFilter(max_time_seconds=5.0, max_distance_meters=0.2, max_angle_radians=math.radians(1.0))
    assert f.keep(0.0, (0.0, 0.0, 0.0))
    assert not f.keep(1.0, (0.1, 0.0, 0.0))
    assert not f.keep(2.0, (0.2, 0.0, 0.0))  # exactly the threshold is still similar
    assert f.keep(3.0, (0.21, 0.0, 0.0))  # distance
    assert not f.keep(4.0, (0.21, 0.0, math.radians(0.9)))
    assert f.keep(5.0, (0.21, 0.0, math.radians(1.1)))  # angle
    assert not f.keep(10.0, (0.21, 0.0, math.radians(1.1)))
    assert f.keep(10.2, (0.21, 0.0, math.radians(1.1)))  # time since the last kept node
    assert f.keep(11.0, (0.21, 0.0, math.radians(1.1) - 2 * math.pi + 0.1))  # angles wrap
    assert (f.num_total, f.num_kept, f.num_dropped) == (9, 5, 4)
    assert f.kept_fraction == 5 / 9


def test_dropped_nodes_do_not_move_the_reference():
    f = MotionFilter(max_distance_meters=0.2)
    assert f.keep(0.0, (0.0, 0.0, 0.0))
    for k in range(1, 5):
        assert not f.keep(0.1 * k, (0.05 * k, 0.0, 0.0))  # each step 5 cm, total 20 cm
    assert f.keep(0.5, (0.25, 0.0, 0.0))
