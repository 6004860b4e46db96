"""People, carts and doors in the simulator (sim.movers): where they are when, what the laser sees of them, and the
ground truth of the cells they crossed."""
import math

import numpy as np

from carto_cli.sim import Lidar, loop_building, loop_trajectory, room, simulate
from carto_cli.sim.movers import KEEP_CLEAR, Mover, MoverKind, crowd, door, footprint, person, segments_at
from carto_cli.sim.world import box


def test_a_mover_is_there_only_along_its_track():
    m = Mover(MoverKind.WALKER, person(), np.array([[10.0, 0.0, 0.0, 0.0], [20.0, 5.0, 0.0, 0.0]]))
    assert m.pose(9.9) is None and m.pose(20.1) is None
    assert np.allclose(m.pose(15.0), (2.5, 0.0, 0.0))
    seg = m.segments(15.0)
    assert seg.shape == (8, 4)
    assert np.allclose(np.hypot(seg[:, 0] - 2.5, seg[:, 1]), 0.2)
    assert m.segments(25.0).shape == (0, 4)


def test_a_door_is_closed_then_open():
    closed, opened = door((1.0, 0.0), 1.0, 0.0, math.pi / 2, opens=30.0, end=60.0)
    assert np.allclose(segments_at([closed, opened], 10.0), [[1.0, 0.0, 2.0, 0.0]])
    assert np.allclose(segments_at([closed, opened], 40.0), [[1.0, 0.0, 1.0, 1.0]])


def test_no_mover_is_drawn_through_the_laser():
    near = Mover(MoverKind.WALKER, person(), np.array([[0.0, 0.1, 0.0, 0.0], [10.0, 0.1, 0.0, 0.0]]))
    far = Mover(MoverKind.WALKER, person(), np.array([[0.0, 3.0, 0.0, 0.0], [10.0, 3.0, 0.0, 0.0]]))
    assert len(segments_at([near, far], 5.0)) == 16
    kept = segments_at([near, far], 5.0, clear_of=np.zeros(2))
    assert len(kept) == 8 and np.all(np.hypot(kept[:, 0], kept[:, 1]) > KEEP_CLEAR)


def test_the_laser_sees_a_standing_person_only_while_there():
    world = room(8.0, 6.0)
    trajectory = loop_trajectory(world)
    standing = Mover(MoverKind.STANDING, person(), np.array([[5.0, 4.0, 3.0, 0.0], [15.0, 4.0, 3.0, 0.0]]))
    lidar = Lidar(noise=0.0, dropout=0.0)
    sim = simulate(world, trajectory, duration=20.0, lidar=lidar, movers=(standing,))
    bare = simulate(world, trajectory, duration=20.0, lidar=lidar)
    shorter = [bool(np.any(a < b - 0.05)) for a, b in zip(sim.scan_ranges(), bare.scan_ranges())]
    t = sim.scan_times - sim.start_time
    assert any(shorter) and not any(s for s, ti in zip(shorter, t) if ti < 5.0 or ti > 15.0)


def test_footprint_is_every_cell_an_outline_crossed():
    walker = Mover(MoverKind.WALKER, person(), np.array([[0.0, 1.0, 1.0, 0.0], [10.0, 4.0, 1.0, 0.0]]))
    cells = footprint([walker], np.linspace(0.0, 10.0, 101), (0.0, 0.0), 0.05, (60, 120))
    ys, xs = np.nonzero(cells)
    # the outline swept along the path, from x = 0.8 to 4.2 m, 0.2 m either side of it and no further
    assert xs.min() * 0.05 <= 0.85 and (xs.max() + 1) * 0.05 >= 4.15
    assert ys.min() * 0.05 >= 0.75 and (ys.max() + 1) * 0.05 <= 1.25
    assert cells[int(1.19 / 0.05), int(2.5 / 0.05)] and not cells[int(1.4 / 0.05), int(2.5 / 0.05)]


def test_a_crowd_stands_in_free_space_and_is_gone_by_the_second_lap():
    world = loop_building()
    trajectory = loop_trajectory(world, laps=2)
    t = np.arange(0.0, trajectory.duration, 0.1)
    robot = np.column_stack([t, trajectory.poses(t)])
    movers = crowd(world, robot, walkers=6, standing_people=3, carts=1, doors=[((4.78, 0.0), 1.0, 0.0, math.pi)])
    kinds = [m.kind for m in movers]
    assert kinds.count(MoverKind.WALKER) == 6 and kinds.count(MoverKind.STANDING) == 3
    assert kinds.count(MoverKind.CART) == 1 and kinds.count(MoverKind.DOOR) == 2
    for m in movers:
        if m.kind in (MoverKind.STANDING, MoverKind.CART):
            assert m.track[-1, 0] <= 0.45 * t[-1]
            assert world.distance_to_walls(m.segments(m.track[0, 0])[:, :2]).min() > 0.1
    # the same seed, the same scene
    again = crowd(world, robot, walkers=6, standing_people=3, carts=1, doors=[((4.78, 0.0), 1.0, 0.0, math.pi)])
    assert all(np.array_equal(a.track, b.track) for a, b in zip(movers, again))


def test_a_cart_is_a_box():
    m = Mover(MoverKind.CART, box(0.0, 0.0, 1.0, 0.6), np.array([[0.0, 2.0, 2.0, math.pi / 2]] * 2))
    seg = m.segments(0.0)
    assert np.allclose(seg[:, [0, 2]].min(), 1.7) and np.allclose(seg[:, [1, 3]].max(), 2.5)
