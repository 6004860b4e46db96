"""gmapping.maps: the ray walk, what a ray writes, copy-on-write tiles, growth and entropy."""
import math

import numpy as np
import pytest
from reference.gmapping import crossed_cells, map_counts, ray_counts

from carto_cli.gmapping.maps import CELL_BYTES, COUNT_MAX, FULLNESS, SEEN, TILE, UNKNOWN, WALL, TiledMaps, traverse

RES = 0.05


def _walk(x0, y0, x1, y1, size):
    buf = np.empty((int(abs(x1 - x0) / size + abs(y1 - y0) / size) + 8, 2), np.int64)
    n = traverse(x0, y0, x1, y1, size, buf)
    return [(int(a), int(b)) for a, b in buf[:n]]


def _assert_same_counts(got, want):
    assert got.keys() == want.keys(), (sorted(set(got) ^ set(want)))[:10]
    for cell, (h, v, sx, sy) in want.items():
        g = got[cell]
        assert (g[0], g[1]) == (h, v), (cell, g, (h, v))
        # the map keeps each mean endpoint in 1/65536ths of its cell: the sums agree to that step times the hits
        assert g[2] == pytest.approx(sx, abs=1e-5 * max(h, 1)) and g[3] == pytest.approx(sy, abs=1e-5 * max(h, 1))


def _bundle(rng, n, reach=3.0):
    """``n`` rays of random bearing and length from the tracking frame's sensor, 70 % ending in a wall."""
    a = rng.uniform(-math.pi, math.pi, n)
    r = rng.uniform(0.05, reach, n)
    return np.stack([r * np.cos(a), r * np.sin(a)], axis=1), rng.random(n) < 0.7


# --------------------------------------------------------------------------- traverse


def test_traverse_matches_the_reference_on_random_segments():
    rng = np.random.default_rng(0)
    for _ in range(4000):
        size = float(rng.choice([0.05, 0.03, 1.6]))
        x0, y0, x1, y1 = rng.uniform(-6.0, 6.0, 4) * (1.0 if size > 1 else rng.choice([0.05, 0.3, 1.0]))
        assert _walk(x0, y0, x1, y1, size) == crossed_cells(x0, y0, x1, y1, size), (x0, y0, x1, y1, size)


def test_traverse_on_the_lattice_is_a_4_connected_walk_from_start_to_end_cell():
    """Segments from and to grid points, along grid lines and through corners: every step is to a side
    neighbour, the walk starts in the start's cell, ends in the end's and takes the fewest steps."""
    rng = np.random.default_rng(1)
    for i in range(3000):
        size = float(rng.choice([0.05, 0.1, 1.6]))
        k = rng.integers(-40, 40, 4)
        if i % 4 == 1:
            k[3] = k[1]  # along a grid line
        elif i % 4 == 2:
            k[2] = k[0] + (k[3] - k[1])  # diagonal: through every corner on the way
        p = k * size + (rng.choice([0.0, 1e-12, -1e-12], 4) if i % 3 == 0 else 0.0)
        cells = _walk(*p, size)
        first = (math.floor(p[0] / size), math.floor(p[1] / size))
        last = (math.floor(p[2] / size), math.floor(p[3] / size))
        assert cells[0] == first and cells[-1] == last, (p, size, cells[:3], cells[-3:])
        steps = np.abs(np.diff(np.array(cells), axis=0)).sum(axis=1) if len(cells) > 1 else np.zeros(0)
        assert np.all(steps == 1), (p, size)
        assert len(cells) == abs(last[0] - first[0]) + abs(last[1] - first[1]) + 1, (p, size)


def test_traverse_hand_cases():
    assert _walk(0.01, 0.01, 0.04, 0.02, RES) == [(0, 0)]
    assert _walk(0.12, 0.01, -0.07, 0.01, RES) == [(2, 0), (1, 0), (0, 0), (-1, 0), (-2, 0)]
    assert _walk(-0.01, 0.06, -0.01, -0.06, RES) == [(-1, 1), (-1, 0), (-1, -1), (-1, -2)]
    assert _walk(0.01, 0.02, 0.09, 0.07, RES) == [(0, 0), (1, 0), (1, 1)]


# --------------------------------------------------------------------------- insert


def test_a_ray_visits_the_cells_it_crosses_and_hits_the_last():
    maps = TiledMaps(1, RES)
    pose = np.array([[0.01, 0.01, 0.0]])
    maps.insert(pose, np.zeros(2), np.array([[0.30, 0.0]]), np.array([True]))  # ends at x = 0.31: cell 6
    counts = map_counts(maps, 0)
    assert sorted(counts) == [(i, 0) for i in range(7)]
    assert all(counts[(i, 0)][:2] == [0, 1] for i in range(6))
    assert counts[(6, 0)][:2] == [1, 1] and counts[(6, 0)][2:] == pytest.approx([0.31, 0.01], abs=1e-6)
    prob, origin = maps.occupancy(0)
    ix, iy = round((0.0 - origin[0]) / RES), round((0.0 - origin[1]) / RES)
    np.testing.assert_array_equal(prob[iy, ix:ix + 7], [0, 0, 0, 0, 0, 0, 1])
    assert np.isnan(prob[iy + 1, ix]) and np.isnan(prob[iy, ix + 7]) and np.isnan(prob[iy, ix - 1])
    assert np.count_nonzero(~np.isnan(prob)) == 7
    # A ray without a return only clears: its last cell gets a visit, no hit.
    maps.insert(pose, np.zeros(2), np.array([[0.0, 0.20]]), np.array([False]))
    counts = map_counts(maps, 0)
    assert [counts[(0, i)][:2] for i in range(5)] == [[0, 2]] + [[0, 1]] * 4 and (0, 5) not in counts


def test_insert_matches_the_reference_counts():
    """Random bundles cast by particles at different poses with the sensor off the tracking frame's origin:
    every cell's hits, visits and endpoint sum, per particle, as the reference counts them."""
    rng = np.random.default_rng(3)
    origin = np.array([0.15, -0.05])
    maps = TiledMaps(3, RES, capacity=4)
    history = [[], [], []]
    for _ in range(3):
        poses = np.column_stack([rng.uniform(-3, 3, 3), rng.uniform(-3, 3, 3), rng.uniform(-math.pi, math.pi, 3)])
        ends, hit = _bundle(rng, 150)
        maps.insert(poses, origin, ends, hit)
        for p in range(3):
            history[p].append((poses[p], origin, ends, hit))
    for p in range(3):
        _assert_same_counts(map_counts(maps, p), ray_counts(history[p], RES))


def test_each_cell_state_follows_its_counts():
    """The byte the matcher reads: never seen, seen, or a wall (hits above FULLNESS of visits), for every cell of
    every tile in use after rays from several particles, a resampling and more rays."""
    rng = np.random.default_rng(4)
    maps = TiledMaps(3, RES, capacity=4)
    for k in range(4):
        poses = np.column_stack([rng.uniform(-2, 2, 3), rng.uniform(-2, 2, 3), rng.uniform(-math.pi, math.pi, 3)])
        ends, hit = _bundle(rng, 200)
        maps.insert(poses, np.array([0.1, 0.0]), ends, hit)
        if k == 1:
            maps.reindex(np.array([2, 2, 0]))
    used = np.unique(maps.table[maps.table >= 0])
    hits, visits = maps.hits[used], maps.visits[used]
    want = np.where(visits == 0, UNKNOWN, np.where(hits > FULLNESS * visits, WALL, SEEN))
    np.testing.assert_array_equal(maps.state[used], want)
    assert (want == WALL).any() and (want == SEEN).any() and (want == UNKNOWN).any()


def test_rays_ending_on_tile_corners_keep_every_hit():
    """The cell walk and the tile walk resolve a tile corner independently (a cell only touched at a
    corner may lose its visit); the end cell, and so the hit, is never lost."""
    span = RES * TILE
    pose = np.array([0.013, 0.021, 0.0])
    k = np.array([(i, j) for i in range(-3, 4) for j in range(-3, 4) if (i, j) != (0, 0)], float)
    ends = k * span - pose[:2]  # world endpoints on the tile lattice's corners
    maps = TiledMaps(1, RES)
    maps.insert(pose[None, :], np.zeros(2), ends, np.ones(len(ends), bool))
    counts = map_counts(maps, 0)
    assert sum(v[0] for v in counts.values()) == len(ends)
    for x, y in ends + pose[:2]:
        assert counts[(math.floor(x / RES), math.floor(y / RES))][0] >= 1


# --------------------------------------------------------------------------- copy on write


def test_resampled_particles_share_tiles_until_they_write():
    rng = np.random.default_rng(5)
    origin = np.zeros(2)
    first, first_hit = _bundle(rng, 120)
    maps = TiledMaps(2, RES)
    p0 = np.array([0.31, 0.17, 0.4])  # off the lattice: a sensor on a cell corner is a tie for every walk
    maps.insert(p0[None, :], origin, first, first_hit)  # particle 0 only, as the filter's first scan
    assert map_counts(maps, 1) == {}
    used = maps.tiles_in_use
    maps.reindex(np.array([0, 0]))
    np.testing.assert_array_equal(maps.table[0], maps.table[1])
    assert maps.tiles_in_use == used  # sharing copies nothing

    # Both write: particle 1 from 1.2 m away, so their rays cross different cells.
    second, second_hit = _bundle(rng, 120, reach=2.0)
    p1 = np.array([1.53, -0.42, -0.3])
    maps.insert(np.stack([p0, p1]), origin, second, second_hit)
    a, b = maps.table[0], maps.table[1]
    both = (a >= 0) & (b >= 0)
    # Particle 0's counts are those of a map that never saw particle 1's rays.
    alone = TiledMaps(1, RES)
    alone.insert(p0[None, :], origin, first, first_hit)
    alone.insert(p0[None, :], origin, second, second_hit)
    _assert_same_counts(map_counts(maps, 0), map_counts(alone, 0))
    _assert_same_counts(map_counts(maps, 1), ray_counts([(p0, origin, first, first_hit),
                                                         (p1, origin, second, second_hit)], RES))
    # Tiles written by either now differ; the others are still one tile.
    differ = both & (a != b)
    assert differ.any() and (both & (a == b)).any()
    ids = np.concatenate([a[a >= 0], b[b >= 0]])
    assert maps.tiles_in_use == len(np.unique(ids))


def test_reindex_frees_the_tiles_no_particle_keeps():
    rng = np.random.default_rng(6)
    maps = TiledMaps(2, RES, capacity=8)
    ends, hit = _bundle(rng, 100)
    maps.insert(np.array([[0.01, 0.02, 0.0], [6.01, 6.02, 1.0]]), np.zeros(2), ends, hit)
    own1 = set(maps.table[1][maps.table[1] >= 0].tolist())
    assert maps.tiles_in_use > len(own1)
    before = map_counts(maps, 1)
    maps.reindex(np.array([1, 1]))
    assert maps.tiles_in_use == len(own1)
    assert map_counts(maps, 0) == before == map_counts(maps, 1)
    # The freed tiles come back clean: a particle writing where it had nothing gets zeroed cells.
    capacity = maps.capacity
    maps.insert(np.array([[-5.99, -5.98, 0.0], [-5.99, -5.98, 0.0]]), np.zeros(2), ends[:10], hit[:10])
    assert maps.capacity == capacity
    want = ray_counts([(np.array([6.01, 6.02, 1.0]), np.zeros(2), ends, hit),
                       (np.array([-5.99, -5.98, 0.0]), np.zeros(2), ends[:10], hit[:10])], RES)
    _assert_same_counts(map_counts(maps, 0), want)


def test_pool_and_memory_figures_are_consistent():
    rng = np.random.default_rng(8)
    maps = TiledMaps(4, RES, capacity=2)
    per_tile = TILE * TILE * CELL_BYTES
    assert maps.tiles_in_use == 0 and maps.memory_bytes >= 2 * per_tile
    small = maps.memory_bytes
    ends, hit = _bundle(rng, 200, reach=4.0)
    poses = np.column_stack([rng.uniform(-2, 2, 4), rng.uniform(-2, 2, 4), rng.uniform(-3, 3, 4)])
    maps.insert(poses, np.zeros(2), ends, hit)
    ids = maps.table[maps.table >= 0]
    assert maps.tiles_in_use == len(np.unique(ids)) == len(ids)  # different poses: nothing shared
    assert maps.tiles_in_use <= maps.capacity and maps.peak_tiles >= maps.tiles_in_use
    assert maps.capacity * per_tile <= maps.memory_bytes < maps.capacity * per_tile + 1_000_000
    assert maps.memory_bytes > small
    # Every tile a particle holds has a visit in it; rays of 4 m around a pose stay within an 8 m square of tiles.
    side = int(np.ceil(8.0 / (TILE * RES))) + 1
    for p in range(4):
        own = maps.table[p][maps.table[p] >= 0]
        assert all(maps.visits[t].any() for t in own) and len(own) <= side * side


def test_moving_far_away_grows_the_table_and_keeps_what_was_there():
    rng = np.random.default_rng(9)
    maps = TiledMaps(2, RES)
    ends, hit = _bundle(rng, 80, reach=1.5)
    maps.insert(np.array([[0.2, 0.1, 0.0], [0.1, 0.3, 2.0]]), np.zeros(2), ends, hit)
    before = [maps.occupancy(p) for p in range(2)]
    counts = [map_counts(maps, p) for p in range(2)]
    shape = maps.table.shape
    for far in ([60.0, -45.0, 1.0], [-38.0, 52.0, -2.0]):
        maps.insert(np.array([far, far]), np.zeros(2), ends, hit)
    assert maps.table.shape[1] > shape[1] and maps.table.shape[2] > shape[2]
    for p in range(2):
        prob, origin = maps.occupancy(p)
        old, old_origin = before[p]
        i0, j0 = round((old_origin[1] - origin[1]) / RES), round((old_origin[0] - origin[0]) / RES)
        assert i0 >= 0 and j0 >= 0
        np.testing.assert_array_equal(prob[i0:i0 + old.shape[0], j0:j0 + old.shape[1]], old)
        now = map_counts(maps, p)
        assert all(now[c] == v for c, v in counts[p].items())
        # The far scans are there too (cells near 60, -45 and -38, 52).
        assert any(abs(c[0] * RES - 60) < 2 and abs(c[1] * RES + 45) < 2 for c in now)
        assert any(abs(c[0] * RES + 38) < 2 and abs(c[1] * RES - 52) < 2 for c in now)


# --------------------------------------------------------------------------- entropy


def _binary_entropy(q):
    return -(q * math.log2(q) + (1 - q) * math.log2(1 - q))


def test_entropy_of_a_tiny_map():
    """Rays along one row of cells from (0.025, 0.025): cells 0..5 known."""
    maps = TiledMaps(1, RES)
    pose = np.array([[0.025, 0.025, 0.0]])
    assert maps.entropy(0) == 0.0
    # Two rays ending in cell 3 and one beyond it (ending in cell 5): cell 3 hit 2 of the 3 times it was
    # reached, cell 5 hit once in one; cells 0-2 and 4 only crossed.
    maps.insert(pose, np.zeros(2), np.array([[0.15, 0.0], [0.15, 0.0], [0.25, 0.0]]), np.array([True, True, True]))
    assert maps.entropy(0) == pytest.approx(_binary_entropy(2 / 3) / 6)
    # Two rays ending in cell 5 without a return: cell 3 now 2 hits in 5, cell 5 1 in 3.
    maps.insert(pose, np.zeros(2), np.array([[0.25, 0.0], [0.25, 0.0]]), np.array([False, False]))
    assert maps.entropy(0) == pytest.approx((_binary_entropy(2 / 5) + _binary_entropy(1 / 3)) / 6)
    # One ray ending in a cell of the next row: cell (0, 1) certain, one more known cell.
    maps.insert(pose, np.zeros(2), np.array([[0.0, 0.05]]), np.array([True]))
    assert maps.entropy(0) == pytest.approx((_binary_entropy(2 / 5) + _binary_entropy(1 / 3)) / 7)


def test_entropy_is_one_bit_when_every_known_cell_is_as_often_hit_as_crossed():
    maps = TiledMaps(1, RES)
    pose = np.array([[0.025, 0.025, 0.0]])
    # Two rays that end where they start, one with a return: the sensor's cell, the only one known, hit 1 in 2.
    maps.insert(pose, np.zeros(2), np.array([[0.0, 0.0], [0.0, 0.0]]), np.array([True, False]))
    assert len(map_counts(maps, 0)) == 1
    assert maps.entropy(0) == pytest.approx(1.0)


def test_counts_near_their_limit_are_halved_together_not_wrapped():
    # One byte per count: a cell crossed 255 times must keep its occupancy, not wrap to an empty cell.
    rng = np.random.default_rng(10)
    maps = TiledMaps(1, RES)
    ends, hit = _bundle(rng, 100, reach=2.0)
    pose = np.zeros((1, 3))
    maps.insert(pose, np.zeros(2), ends, hit)
    known = maps.visits > 0
    added_hits, added_visits = maps.hits.astype(int), maps.visits.astype(int)  # what one insert adds
    maps.visits[known] = COUNT_MAX
    maps.hits[known] = np.where(maps.hits[known] > 0, 120, 0)
    maps.insert(pose, np.zeros(2), ends, hit)
    # each count halved once (an insert's rays cross a cell fewer than 128 times), then the insert's counts added
    np.testing.assert_array_equal(maps.visits[known], COUNT_MAX // 2 + added_visits[known])
    np.testing.assert_array_equal(maps.hits[known], np.where(added_hits[known] > 0, 60, 0) + added_hits[known])
