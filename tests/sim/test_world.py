"""Worlds: geometry of the builders, closed buildings, drivable routes, features for matching."""
from __future__ import annotations

import math

import numpy as np
import pytest

from carto_cli.sim.lidar import cast
from carto_cli.sim.world import (
    OPAQUE,
    Material,
    World,
    box,
    corridor,
    courtyard,
    glass_office,
    loop_building,
    merge_partial,
    office,
    polyline,
    room,
    wall,
)

BUILDERS = [room, corridor, loop_building, office, glass_office, courtyard]


def route_points(world: World, step: float = 0.5, with_directions: bool = False):
    """Points every ``step`` metres along a world's route (and the route's direction there)."""
    wp = world.route if not world.closed else np.vstack([world.route, world.route[:1]])
    pts, dirs = [], []
    for a, b in zip(wp[:-1], wp[1:]):
        length = np.hypot(*(b - a))
        n = max(1, int(length / step))
        pts.append(a + np.linspace(0, 1, n, endpoint=False)[:, None] * (b - a))
        dirs.append(np.tile((b - a) / length, (n, 1)))
    return (np.vstack(pts), np.vstack(dirs)) if with_directions else np.vstack(pts)


def test_primitives():
    np.testing.assert_array_equal(polyline([(0, 0), (1, 0), (1, 1)]), [[0, 0, 1, 0], [1, 0, 1, 1]])
    assert box(0, 0, 2, 1).shape == (4, 4)
    pieces = wall((0, 0), (10, 0), gaps=[(2, 1), (7, 2)])
    np.testing.assert_allclose(pieces, [[0, 0, 1.5, 0], [2.5, 0, 6, 0], [8, 0, 10, 0]])


def test_room_geometry():
    w = room(8, 6)
    assert w.segments.shape == (4, 4) and w.bounds == (0, 0, 8, 6)
    assert w.distance_to_walls([[4, 3]])[0] == pytest.approx(3.0)
    assert w.distance_to_walls([[1, 5.5]])[0] == pytest.approx(0.5)


def test_corridor_geometry():
    w = corridor(30, 2)
    assert w.bounds == (0, 0, 30, 2)
    assert w.distance_to_walls(route_points(w)).min() == pytest.approx(1.0)


@pytest.mark.parametrize("build", BUILDERS)
def test_routes_keep_clear_of_walls(build):
    w = build()
    assert w.route is not None and w.segments.dtype == np.float64
    assert w.distance_to_walls(route_points(w, 0.1)).min() >= 0.4  # a 0.9 m door leaves 0.45


@pytest.mark.parametrize("build", BUILDERS)
def test_buildings_are_closed(build):
    # No beam from anywhere on the route escapes to infinity: the walls form closed rooms.
    w = build()
    pts = route_points(w, 2.0)
    poses = np.column_stack([pts, np.zeros(len(pts))])
    ranges = cast(poses, np.linspace(-math.pi, math.pi, 720, endpoint=False), w.segments)
    assert np.isfinite(ranges).all()


def test_loop_building_is_a_ring_with_rooms_and_pillars():
    w = loop_building(width=24, height=16, corridor_width=2.5)
    assert w.closed and len(w.route) == 4
    xmin, ymin, xmax, ymax = w.bounds
    assert xmin < 0 and ymin < 0 and xmax > 24 and ymax > 16  # side rooms stick out
    # the core blocks the view across the ring
    r = cast(np.array([1.25, 8.0, 0.0]), np.array([0.0]), w.segments)
    assert r[0] == pytest.approx(1.25)


def test_office_route_visits_every_room():
    w = office(rooms_per_side=3, room_depth=4.0, corridor_width=2.0)
    inside = w.route[w.route[:, 1] > 2.0 + 1.0]
    assert len(inside) == 3
    # each visit goes through a door: the corridor wall is open where the route crosses it
    for x, _ in inside:
        r = cast(np.array([x, 1.0, math.pi / 2]), np.array([0.0]), w.segments)
        assert r[0] > 3.0


def scan_change_when_moving(w: World, max_range: float, step: float = 0.2):
    """For points along the route: how many beams change by > 5 cm when moving ``step`` along it."""
    pts, dirs = route_points(w, 1.0, with_directions=True)
    angles = np.linspace(-math.pi, math.pi, 360, endpoint=False)
    r0 = cast(np.column_stack([pts, np.zeros(len(pts))]), angles, w.segments, max_range)
    r1 = cast(np.column_stack([pts + step * dirs, np.zeros(len(pts))]), angles, w.segments, max_range)
    with np.errstate(invalid="ignore"):
        moved = np.abs(r1 - r0) > 0.05
    return (moved | (np.isfinite(r0) != np.isfinite(r1))).sum(axis=1)


def test_loop_building_is_well_posed_for_matching_but_a_corridor_is_not():
    # With an 8 m laser, every place on the loop sees something that moves when the robot does.
    assert scan_change_when_moving(loop_building(), 8.0).min() >= 10
    # In the middle of a long corridor nothing does.
    mid = scan_change_when_moving(corridor(40, 2), 8.0)
    assert (mid == 0).sum() >= 10


# ---------------------------------------------------------------- partly transparent worlds (issue 43)


def test_worlds_of_opaque_walls_have_no_materials():
    for build in (room, corridor, loop_building, office):
        assert build().materials is None


def test_materials_rows_and_checks():
    segments, rows = merge_partial([(box(0, 0, 2, 2), OPAQUE), (polyline([(0, 0), (1, 0)]), Material(0.3, 25.0, 6.0))])
    assert segments.shape == (5, 4) and rows.shape == (5, 3)
    np.testing.assert_allclose(rows[0], [1.0, 0.0, math.inf])
    np.testing.assert_allclose(rows[4], [0.3, math.cos(math.radians(25.0)), 6.0])
    with pytest.raises(ValueError, match="materials"):
        World(segments, materials=rows[:3])
    with pytest.raises(ValueError, match="opacity"):
        World(segments, materials=np.zeros((5, 3)))


@pytest.mark.parametrize("build", [glass_office, courtyard])
def test_buildings_with_glass_and_clutter(build):
    w = build()
    assert w.materials.shape == (len(w.segments), 3)
    partial = w.materials[:, 0] < 1
    assert 0 < partial.sum() < len(w.segments)
    assert build().segments.tobytes() == w.segments.tobytes()  # seeded: the same world every time
    assert build(seed=1).segments.tobytes() != w.segments.tobytes() or build is glass_office


def test_glass_office_walls_are_one_line_seen_from_both_sides():
    """The partition between the bottom rooms is a single line: visited rooms on both sides of it see it at
    the same x, from opposite directions."""
    w = glass_office(width=20.0, corridor_width=2.0)
    x = w.route[1, 0]  # the first room's door
    cut = 2.0 + 0.3 * 16.0  # 30 % across the core
    left = cast(np.array([x, 4.0, 0.0]), np.array([0.0]), w.segments)[0]
    right = cast(np.array([w.route[4, 0], 4.0, math.pi]), np.array([0.0]), w.segments)[0]
    assert x + left == pytest.approx(cut) and w.route[4, 0] - right == pytest.approx(cut)


def test_courtyard_needs_room_for_its_lawns():
    with pytest.raises(ValueError, match="26 m"):
        courtyard(width=20.0, height=30.0)
