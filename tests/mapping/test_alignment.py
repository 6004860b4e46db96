"""mapping.alignment: the walls' direction read off a map, the turn that squares it, and turning what is in the map
frame; on images drawn here of walls at known angles."""
import math

import numpy as np
import pytest

from carto_cli.core.errors import CartoError
from carto_cli.core.transform import wrap_angle_scalar
from carto_cli.grid.occupancy_image import AssembledImage, OccupancyImage
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.mapping.alignment import (
    DEAD_BAND,
    Align,
    Axes,
    squaring,
    turned_image,
    turned_poses,
    wall_axes,
)

RES = 0.05


def _building(angle_deg: float, size: float = 20.0) -> OccupancyImage:
    """Rooms 5 m apart with one diagonal wall, the whole turned ``angle_deg`` about the image centre: free inside,
    unknown outside, walls one cell wide (as a map draws them)."""
    a = math.radians(angle_deg)
    n = int(size * 1.6 / RES)
    c, s = math.cos(a), math.sin(a)
    yy, xx = np.mgrid[0:n, 0:n]
    wx, wy = (xx + 0.5) * RES - n * RES / 2, (yy + 0.5) * RES - n * RES / 2
    inside = (np.abs(c * wx + s * wy) < size / 2 + 0.5) & (np.abs(-s * wx + c * wy) < size / 2 + 0.5)
    p = np.where(inside, np.float32(0.1), np.float32(np.nan)).astype(np.float32)
    half = size / 2
    walls = [((x, -half), (x, half)) for x in np.linspace(-half, half, 5)]
    walls += [((-half, y), (half, y)) for y in np.linspace(-half, half, 5)]
    walls.append(((-half, -half), (3.0, 7.0)))
    for (x0, y0), (x1, y1) in walls:
        t = np.linspace(0.0, 1.0, int(math.hypot(x1 - x0, y1 - y0) / RES * 3))
        px, py = x0 + t * (x1 - x0), y0 + t * (y1 - y0)
        ix = ((c * px - s * py + n * RES / 2) / RES).astype(int)
        iy = ((s * px + c * py + n * RES / 2) / RES).astype(int)
        p[iy, ix] = 0.9
    return OccupancyImage(p, RES, (0.0, 0.0))


def _quarter_error(found: float, angle_deg: float) -> float:
    """Degrees between two directions taken modulo 90°."""
    return abs(math.degrees(wrap_angle_scalar(4 * (found - math.radians(angle_deg))) / 4))


@pytest.mark.parametrize("angle", [0.0, 0.3, 4.0, 17.0, 30.0, 44.8, 45.0, 45.2, 60.0, 75.0, 89.6, 90.0])
def test_the_walls_direction_is_found_to_well_under_half_a_degree(angle):
    axes = wall_axes(_building(angle))
    assert axes.clear
    assert -math.pi / 4 < axes.angle <= math.pi / 4
    assert _quarter_error(axes.angle, angle) < 0.1


@pytest.mark.parametrize(("walls", "rotation"), [(17.0, -17.0), (60.0, 30.0), (-44.0, 44.0), (45.0, 45.0),
                                                 (-45.0 + 1e-9, 45.0), (0.8, -0.8)])
def test_the_smallest_turn_in_minus_45_to_45_lays_the_walls_on_the_axes(walls, rotation):
    done = squaring(Axes(math.radians(walls), 1.0))
    assert math.degrees(done.rotation) == pytest.approx(rotation)
    assert done.to_dict()["rotation_deg"] == pytest.approx(rotation)


def test_a_map_square_within_the_dead_band_keeps_its_frame():
    inside = squaring(Axes(DEAD_BAND * 0.9, 1.0))
    assert inside.rotation == 0.0 and inside.describe().startswith("already square")
    assert squaring(Axes(-DEAD_BAND * 1.1, 1.0)).rotation == pytest.approx(DEAD_BAND * 1.1)
    # and on a drawn map: 0.3° of tilt is left alone
    assert squaring(wall_axes(_building(0.3))).rotation == 0.0


def test_clutter_has_no_clear_direction_and_keeps_its_frame():
    """Short walls at every angle (a yard of hedges, a round hall): no direction stands out."""
    rng = np.random.default_rng(3)
    n = 600
    p = np.full((n, n), 0.1, np.float32)
    for _ in range(400):
        x, y = rng.uniform(40, n - 40, 2)
        a = rng.uniform(0, math.pi)
        t = np.linspace(-20, 20, 120)
        p[(y + t * math.sin(a)).astype(int), (x + t * math.cos(a)).astype(int)] = 0.9
    axes = wall_axes(OccupancyImage(p, RES, (0.0, 0.0)))
    assert not axes.clear
    done = squaring(axes)
    assert done.rotation == 0.0 and done.describe().startswith("no clear wall direction")
    # the same yard with a building's walls in it has one
    assert wall_axes(_building(25.0)).clear


def test_an_unknown_map_has_no_direction():
    empty = OccupancyImage(np.full((50, 60), np.nan, np.float32), RES, (0.0, 0.0))
    assert squaring(wall_axes(empty)).rotation == 0.0


def test_an_image_of_its_own_turns_a_quarter_turn_cell_for_cell():
    """A quarter turn moves every cell's centre onto a cell's centre: the resampled image is the image turned,
    every value kept (no interpolation blurs a wall)."""
    rng = np.random.default_rng(0)
    p = rng.uniform(0, 1, (30, 50)).astype(np.float32)
    p[rng.uniform(size=p.shape) < 0.2] = np.nan
    image = OccupancyImage(p, RES, (-1.0, 2.0))
    turned = turned_image(image, math.pi / 2)
    assert isinstance(turned, OccupancyImage) and turned.shape == (50, 30)
    # rows run up (y), so a counter-clockwise turn of the world is numpy's clockwise one of the array
    np.testing.assert_array_equal(turned.probability, np.rot90(p, -1))
    # the cell at world (x, y) is at (-y, x) after the turn
    assert turned.origin == pytest.approx((-(2.0 + 30 * RES), -1.0))


def test_a_turned_image_keeps_its_walls_where_the_turned_frame_puts_them():
    image = _building(17.0)
    turned = turned_image(image, math.radians(-17.0))
    assert _quarter_error(wall_axes(turned).angle, 0.0) < 0.1
    # every value is one the image had: resampled, not interpolated
    assert set(np.unique(turned.probability[~np.isnan(turned.probability)])) <= {np.float32(0.1), np.float32(0.9)}


def test_an_assembled_map_is_assembled_again_from_its_submaps_turned():
    grid = ProbabilityGrid(RES, (0.0, 0.0), (80, 40))
    cells = np.argwhere(np.ones((40, 80), bool))[:, ::-1]
    grid.set_probability(cells, np.full(len(cells), 0.2))
    wall = cells[cells[:, 1] == 20]
    grid.set_probability(wall, np.full(len(wall), 0.9))
    image = AssembledImage([grid], [np.array([1.0, 0.5, 0.3])])
    turned = turned_image(image, 0.4)
    again = AssembledImage([grid], [turned_poses(np.array([[1.0, 0.5, 0.3]]), 0.4)[0]])
    assert isinstance(turned, AssembledImage) and turned.origin == pytest.approx(again.origin)
    np.testing.assert_array_equal(turned.probability, again.probability)


def test_poses_turn_about_the_map_origin():
    poses = np.array([[1.0, 0.0, 0.1], [0.0, 2.0, -3.0]])
    out = turned_poses(poses, math.pi / 2)
    np.testing.assert_allclose(out, [[0.0, 1.0, 0.1 + math.pi / 2], [-2.0, 0.0, -3.0 + math.pi / 2]], atol=1e-12)
    assert turned_poses(np.zeros((0, 3)), 1.0).shape == (0, 3)


def test_align_is_named_by_its_value_and_a_bad_one_is_one_line():
    assert Align.named("auto") is Align.AUTO and f"{Align.NONE}" == "none"
    with pytest.raises(CartoError, match="--align: unknown value 'square'"):
        Align.named("square")
