"""Cleaning a finished map (mapping.cleaning): what stood a while and left is drawn free, what stays is kept.

Node returns are ray cast in code (``sim.lidar.cast``) against a room's walls and, for part of the time, a box
or a pillar; the evidence kernels are checked against a reference in numpy that samples each ray densely instead
of walking it cell by cell."""
import math

import numpy as np
import pytest

from carto_cli.mapping import cleaning
from carto_cli.mapping.cleaning import Transients, cleaned_probability, compact_returns, find_transients
from carto_cli.sim.lidar import cast
from carto_cli.sim.world import box, merge

RES = 0.05
ANGLES = np.linspace(-math.pi, math.pi, 720, endpoint=False)


def _scene(objects, n=240, duration=240.0):
    """A 10 x 8 m room, a robot circling it twice; ``objects``: (segments, start, end) present in [start, end).
    Returns (points per node in its frame, poses, times)."""
    walls = box(5.0, 4.0, 10.0, 8.0)
    times = np.linspace(0.0, duration, n)
    a = 4 * math.pi * times / duration
    poses = np.column_stack([5.0 + 3.2 * np.cos(a), 4.0 + 2.4 * np.sin(a), a + math.pi / 2])
    points = []
    for pose, t in zip(poses, times):
        segs = merge(walls, *[s for s, t0, t1 in objects if t0 <= t < t1])
        r = cast(pose, ANGLES, segs, 30.0)
        ok = np.isfinite(r)
        points.append(np.column_stack([r[ok] * np.cos(ANGLES[ok]), r[ok] * np.sin(ANGLES[ok])]))
    return points, poses, times


def _image(points, poses, shape=(180, 220), origin=(-0.5, -0.5)):
    """An image occupied wherever a return ended, free elsewhere: the cells cleaning judges."""
    prob = np.full(shape, 0.2, np.float32)
    for p, pose in zip(points, poses):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        x = c * p[:, 0] - s * p[:, 1] + pose[0]
        y = s * p[:, 0] + c * p[:, 1] + pose[1]
        prob[np.floor((y - origin[1]) / RES).astype(int), np.floor((x - origin[0]) / RES).astype(int)] = 0.9
    return prob, origin


def _cells_of(segments, origin, shape):
    """Cells within one of an outline's segments."""
    out = np.zeros(shape, bool)
    for x1, y1, x2, y2 in segments:
        t = np.linspace(0, 1, 200)
        ix = np.floor((x1 + t * (x2 - x1) - origin[0]) / RES).astype(int)
        iy = np.floor((y1 + t * (y2 - y1) - origin[1]) / RES).astype(int)
        out[iy, ix] = True
    grown = out.copy()
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            grown |= np.roll(np.roll(out, dy, 0), dx, 1)
    return grown


def _removed(found: Transients, shape) -> np.ndarray:
    out = np.zeros(shape, bool)
    out[found.cells[:, 1], found.cells[:, 0]] = True
    return out


@pytest.fixture(scope="module")
def cart_left():
    """A 1 x 0.6 m cart in the room for the first 100 s, gone after."""
    cart = box(5.0, 5.3, 1.0, 0.6)
    points, poses, times = _scene([(cart, 0.0, 100.0)])
    prob, origin = _image(points, poses)
    return cart, points, poses, times, prob, origin


def test_a_cart_that_left_is_drawn_free_and_the_walls_stay(cart_left):
    cart, points, poses, times, prob, origin = cart_left
    found = find_transients(prob, origin, RES, points, poses, times)
    removed = _removed(found, prob.shape)
    occupied = prob > 0.5
    cart_cells = occupied & _cells_of(cart, origin, prob.shape)
    wall_cells = occupied & _cells_of(box(5.0, 4.0, 10.0, 8.0), origin, prob.shape)
    assert cart_cells.sum() > 20
    assert (removed & cart_cells).sum() >= 0.95 * cart_cells.sum()
    assert not (removed & wall_cells).any()
    # Its time span: there from the start, gone by the second lap
    assert found.spans[:, 0].min() == 0.0
    assert np.all(found.spans[:, 1] <= 140.0)
    assert np.all(found.after >= cleaning.MIN_AFTER)
    # Drawn free, the rest of the image as it was
    clean = cleaned_probability(prob, origin, RES, found)
    assert np.all(clean[removed] <= cleaning.FREE)
    assert np.array_equal(clean[~removed], prob[~removed])


def test_what_stays_to_the_end_stays(cart_left):
    """A pillar put down halfway and there to the end is never seen through after it came: kept."""
    pillar = box(5.0, 5.3, 0.6, 0.6)
    points, poses, times = _scene([(pillar, 120.0, 1e9)])
    prob, origin = _image(points, poses)
    found = find_transients(prob, origin, RES, points, poses, times)
    pillar_cells = (prob > 0.5) & _cells_of(pillar, origin, prob.shape)
    assert pillar_cells.sum() > 10
    assert not (_removed(found, prob.shape) & pillar_cells).any()


def test_a_static_room_loses_nothing():
    points, poses, times = _scene([])
    prob, origin = _image(points, poses)
    found = find_transients(prob, origin, RES, points, poses, times)
    assert len(found) == 0 and found.candidates == int((prob > 0.5).sum())


def test_demanding_more_rays_than_the_second_lap_gives_keeps_the_cart(cart_left, monkeypatch):
    _, points, poses, times, prob, origin = cart_left
    monkeypatch.setattr(cleaning, "MIN_AFTER", 10_000)
    assert len(find_transients(prob, origin, RES, points, poses, times)) == 0


def _reference(prob, origin, points, poses, times, width, t0):
    """(hits, centre, passes) by the definition: every return's cell; every ray sampled every millimetre up to
    MARGIN short of its end, each cell it enters counted once if the ray passes within PASS_RADIUS of the mean
    point its returns ended at (no grazing exemption: the scene's walls are met steeply by construction)."""
    occupied = prob > 0.5
    bins = cleaning.BINS
    hits = np.zeros(prob.shape + (bins,), int)
    sums = np.zeros(prob.shape + (3,))
    world = []
    for p, pose, t in zip(points, poses, times):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        xy = np.column_stack([c * p[:, 0] - s * p[:, 1] + pose[0], s * p[:, 0] + c * p[:, 1] + pose[1]])
        world.append(xy)
        b = min(max(int((t - t0) / width), 0), bins - 1)
        for x, y in xy:
            ix, iy = int(math.floor((x - origin[0]) / RES)), int(math.floor((y - origin[1]) / RES))
            if occupied[iy, ix]:
                hits[iy, ix, b] += 1
                sums[iy, ix] += (x, y, 1.0)
    passes = np.zeros_like(hits)
    for xy, pose, t in zip(world, poses, times):
        b = min(max(int((t - t0) / width), 0), bins - 1)
        o = pose[:2]
        for e in xy:
            d = e - o
            length = float(np.hypot(*d))
            if length <= cleaning.MARGIN:
                continue
            u = d / length
            steps = np.arange(0.0, length - cleaning.MARGIN, 0.001)
            cells = np.floor((o + steps[:, None] * u - origin) / RES).astype(int)
            keep = np.ones(len(cells), bool)
            keep[1:] = np.any(cells[1:] != cells[:-1], axis=1)
            for ix, iy in cells[keep]:
                if occupied[iy, ix] and sums[iy, ix, 2] > 0:
                    m = sums[iy, ix, :2] / sums[iy, ix, 2] - o
                    if abs(u[0] * m[1] - u[1] * m[0]) <= cleaning.PASS_RADIUS:
                        passes[iy, ix, b] += 1
    return hits, sums, passes


def test_the_kernels_count_what_the_reference_counts():
    cart = box(5.0, 5.3, 1.0, 0.6)
    points, poses, times = _scene([(cart, 0.0, 20.0)], n=12, duration=40.0)
    points = [p[::24] for p in points]  # 30 rays a node: the reference walks them in Python
    prob, origin = _image(points, poses)
    t0, width = 0.0, 40.0 / cleaning.BINS
    e = cleaning.gather_evidence(prob, origin, RES, points, poses, times, grazing=0.0)  # times span 0-40 s
    ix, iy = e.cells[:, 0], e.cells[:, 1]
    hits, passes, centre = e.hits, e.passes, e.centre
    ref_hits, ref_sums, ref_passes = _reference(prob, origin, points, poses, times, width, t0)
    assert np.array_equal(hits, ref_hits[iy, ix])
    assert np.allclose(centre, ref_sums[iy, ix])
    # Sampling a millimetre apart can miss a cell's corner the exact walk enters: a ray or two in all
    assert passes.sum() > 0
    assert np.abs(passes.astype(int) - ref_passes[iy, ix]).sum() <= 2


def test_returns_are_kept_to_the_centimetre_in_the_nodes_frame():
    pose = np.array([2.0, -1.0, 0.7])
    local = np.array([[1.234, -0.5], [12.0, 3.3]])
    c, s = math.cos(pose[2]), math.sin(pose[2])
    placed = np.column_stack([c * local[:, 0] - s * local[:, 1] + pose[0], s * local[:, 0] + c * local[:, 1] + pose[1]])
    kept = compact_returns(placed, pose)
    assert kept.dtype == np.int16
    assert np.allclose(kept * cleaning.RETURN_UNIT, local, atol=0.006)
    flat, offsets = cleaning.flat_points([kept, local])
    assert np.allclose(flat[:2], local, atol=0.006) and offsets.tolist() == [0, 2, 4]


def test_saved_transients_land_on_the_cells_of_any_grid():
    found = Transients(0.05, (-1.0, -2.0), np.array([[3, 4], [10, 0]]), np.array([[0.0, 5.0], [1.0, 6.0]]),
                       np.array([7, 8]), np.array([20, 30]), 100)
    centres = found.centres()
    assert np.allclose(centres[0], (-1.0 + 3.5 * 0.05, -2.0 + 4.5 * 0.05))
    again = Transients.of_centres(0.05, centres, found.spans, found.hits, found.after)
    assert np.allclose(again.centres(), centres)
    # On the grid they were found on: the same cells; on a grid shifted by whole cells: shifted
    assert found.cells_on((-1.0, -2.0), 0.05, (50, 50)).tolist() == [[3, 4], [10, 0]]
    assert found.cells_on((-1.1, -2.0), 0.05, (50, 50)).tolist() == [[5, 4], [12, 0]]
    assert found.cells_on((-1.0, -1.9), 0.05, (50, 50)).tolist() == [[3, 2]]  # the other is off the grid
