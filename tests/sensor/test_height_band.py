"""The floor, the ceiling, the clutter and the band above the floor, from simulated 3D lidar sweeps
(carto_cli.sensor.height_band); one return per bearing."""
import math

import numpy as np
import pytest

from carto_cli.sensor import height_band as H
from carto_cli.sim import room
from carto_cli.sim.lidar3d import Building, Lidar3D, simulate_3d
from carto_cli.sim.trajectory import loop_trajectory

LIDAR = Lidar3D(columns=600, noise=0.005)


def first_sweep(building, height, lidar=LIDAR):
    sim = simulate_3d(building, loop_trajectory(building.world), lidar=lidar, height=height, duration=0.1)
    cloud = next(sim.clouds())
    return cloud.points.astype(np.float64).T


def furnished_room(heights=(0.45, 0.5, 0.35), ceiling=2.6):
    # Boxes in the room's corners, where the first sweep from the route's start sees them.
    boxes = [[2.0, 4.8, 1.0, 0.5, heights[0]], [6.5, 1.5, 0.6, 0.8, heights[1]], [4.0, 5.5, 1.2, 0.4, heights[2]]]
    return Building(room(8.0, 7.0), ceiling=ceiling, furniture=np.array(boxes))


@pytest.mark.parametrize("height", [0.4, 0.8, 1.3])
def test_floor_and_ceiling_found_at_any_mount_height(height):
    _x, _y, z = first_sweep(furnished_room(), height)
    floor, ceiling = H.floor_and_ceiling(z)
    assert floor == pytest.approx(-height, abs=0.01)
    if height < 0.5:
        # 2.2 m below it, the +15 degree ring meets the ceiling 8 m away: in this room, too few points to tell.
        assert ceiling is None
    else:
        assert ceiling == pytest.approx(2.6 - height, abs=0.01)


def test_no_ceiling_outdoors():
    building = Building(room(8.0, 7.0), ceiling=30.0)  # the rings above the horizon meet nothing in range
    _x, _y, z = first_sweep(building, 0.8, Lidar3D(columns=600, noise=0.005, max_range=12.0))
    floor, ceiling = H.floor_and_ceiling(z)
    assert floor == pytest.approx(-0.8, abs=0.01) and ceiling is None


def test_clutter_is_the_tallest_box_the_sweep_shows():
    x, y, z = first_sweep(furnished_room(), 0.8)
    floor, ceiling = H.floor_and_ceiling(z)
    assert H.clutter_height(x, y, z, floor, ceiling) == pytest.approx(0.5, abs=0.03)
    empty = Building(room(8.0, 7.0))
    x, y, z = first_sweep(empty, 0.8)
    floor, ceiling = H.floor_and_ceiling(z)
    assert H.clutter_height(x, y, z, floor, ceiling) < 0.05  # the walls reach the sensor's height: no clutter


def test_auto_band_above_the_clutter_below_the_lintels():
    x, y, z = first_sweep(furnished_room(heights=(0.7, 0.5, 0.35)), 0.8)
    band = H.auto_band(x, y, z, H.sensor_band(-0.8, 2.0))
    assert band.how == "auto"
    assert band.floor == pytest.approx(-0.8, abs=0.01)
    low, high = band.low - band.floor, band.high - band.floor
    # Above the 0.7 m box: the sweep sees its side up to the last ring below its top (0.6 m, the next ring passes
    # over it), and the clearance covers the rest.
    assert 0.7 < low < 0.8
    assert high == pytest.approx(H.LINTEL)
    assert "above the floor (auto)" in band.describe()


def test_auto_band_under_a_low_ceiling_and_behind_tall_clutter():
    x, y, z = first_sweep(Building(room(8.0, 7.0), ceiling=2.0), 0.8)
    band = H.auto_band(x, y, z, H.sensor_band(-0.8, 2.0))
    assert band.high - band.floor == pytest.approx(2.0 - H.CEILING_CLEARANCE, abs=0.02)
    # Clutter almost as tall as the room (a box reaching the sensor's height is a wall): the band closes round the
    # sensor's own height.
    x, y, z = first_sweep(furnished_room(heights=(1.45, 0.5, 0.35), ceiling=2.0), 1.5)
    band = H.auto_band(x, y, z, H.sensor_band(-0.8, 2.0))
    assert band.low < 0 < band.high and band.high - band.low == pytest.approx(H.MIN_WIDTH)


def test_band_drops_floor_ceiling_and_furniture():
    building = furnished_room()
    x, y, z = first_sweep(building, 0.8)
    band = H.auto_band(x, y, z, H.sensor_band(-0.8, 2.0))
    keep = band.keep(z)
    # What is kept lies on the walls (the room's outline), nothing on boxes, floor or ceiling.
    kept = np.column_stack([x[keep], y[keep]]) + [1.0, 1.0]  # the route starts 1 m from the corner
    assert keep.sum() > 1000
    assert building.world.distance_to_walls(kept).max() < 0.05
    assert z[keep].min() > band.floor + 0.55 and z[keep].max() < band.ceiling


def test_flat_cloud_falls_back_to_the_sensor_slice():
    a = np.linspace(-math.pi, math.pi, 500)
    x, y, z = 3 * np.cos(a), 3 * np.sin(a), np.zeros(500)
    band = H.auto_band(x, y, z, H.sensor_band(-0.8, 2.0))
    assert band.how == "no floor" and (band.low, band.high) == (-0.8, 2.0) and band.floor is None


def test_given_band_is_placed_on_the_floor():
    x, y, z = first_sweep(furnished_room(), 0.5)
    band = H.given_band(x, y, z, (0.1, 0.4), H.sensor_band(-0.8, 2.0))
    assert band.how == "given"
    assert band.low == pytest.approx(-0.4, abs=0.01) and band.high == pytest.approx(-0.1, abs=0.01)


def test_bearing_step_is_the_column_spacing():
    x, y, _z = first_sweep(furnished_room(), 0.8)
    assert math.degrees(H.bearing_step(x, y)) == pytest.approx(360 / LIDAR.columns, rel=1e-3)


def test_one_return_per_bearing_the_median_off_the_nearest_surface():
    step = math.radians(1.0)
    angles = np.array([0.001, 0.002, 0.003, 0.004, 0.005, 0.02 + step, 0.021 + step])
    ranges = np.array([5.00, 5.02, 5.04, 9.0, 9.1, 3.0, 3.01])  # two surfaces in the first bin
    keep = H.nearest_per_bearing(angles, ranges, step)
    assert list(keep) == [1, 5]  # the first bin: the middle of 5.00/5.02/5.04, not the wall behind
