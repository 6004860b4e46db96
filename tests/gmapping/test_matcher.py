"""gmapping.matcher: hill climbing to a scan's pose on a particle's map, and the improved proposal."""
import math

import numpy as np
import pytest
from reference.gmapping import hill_climb, log_likelihood
from room_sim import beam_angles, cast
from support import draws

from carto_cli.core.transform import compose, wrap_angle
from carto_cli.gmapping import matcher
from carto_cli.gmapping.maps import TiledMaps

RES = 0.05
MOUNT = np.array([0.15, -0.05, 0.1])  # the sensor on the robot: matching happens in the tracking frame
# The profile's matcher settings: kernelSize, sigma, lstep, astep, iterations, lsigma.
KERNEL, SIGMA, LSTEP, ASTEP, ITERATIONS, LSIGMA = 1, 0.05, 0.05, 0.05, 5, 0.075
MAP_POSE = np.array([2.2, 1.7, 0.3])
TRUTH = np.array([2.6, 1.5, 0.25])


def _room(w=6.0, h=4.0, shift=(0.013, 0.027)):
    """A w x h rectangle with its corner at ``shift``."""
    x0, y0 = shift
    return np.array([[x0, y0, x0 + w, y0], [x0 + w, y0, x0 + w, y0 + h], [x0 + w, y0 + h, x0, y0 + h],
                     [x0, y0 + h, x0, y0]], float)


def _scan(pose, walls, noise=0.0, seed=0, n=360):
    """Returns of a scan taken at robot ``pose``, in the tracking frame (the sensor at MOUNT)."""
    angles = beam_angles(n)
    r = cast(compose(pose, MOUNT), angles, segments=walls, noise=noise, rng=np.random.default_rng(seed))
    ok = np.isfinite(r)
    c, s = math.cos(MOUNT[2]), math.sin(MOUNT[2])
    px, py = r[ok] * np.cos(angles[ok]), r[ok] * np.sin(angles[ok])
    return np.ascontiguousarray(np.stack([MOUNT[0] + c * px - s * py, MOUNT[1] + s * px + c * py], axis=1))


def _map(particles, pose, points):
    """Every particle shares the map of one scan at ``pose``."""
    maps = TiledMaps(particles, RES)
    maps.insert(pose[None, :], MOUNT[:2], points, np.ones(len(points), bool))
    maps.reindex(np.zeros(particles, np.int64))
    return maps


def _climb(maps, points, starts, sweep=0.0):
    starts = np.ascontiguousarray(starts, dtype=np.float64)
    return matcher.climb(maps, RES, points, MOUNT[0], MOUNT[1], starts, np.full(len(starts), sweep),
                         matcher.ClimbSettings(KERNEL, SIGMA, LSTEP, ASTEP, ITERATIONS))


def _propose(maps, points, modes, means, sigmas, normals, lin=(0.01, 0.01), ang=(0.005, 0.005),
             unknown_ll=matcher.NULL_LIKELIHOOD / LSIGMA):
    """The proposal with the profile's lattice (+-1 cm by 1 cm, +-0.005 rad by 0.005 rad); an endpoint in
    never-observed space costs ``unknown_ll`` (by default what one in free space does, as in GMapping)."""
    ox, oy = maps.tile_origin
    f = np.ascontiguousarray
    return matcher.propose(maps.table, maps.state, maps.mean, ox, oy, RES, points, MOUNT[0], MOUNT[1],
                           f(modes, dtype=np.float64), f(means, dtype=np.float64), f(sigmas, dtype=np.float64),
                           f(normals, dtype=np.float64), kernel=KERNEL, lsigma=LSIGMA, stride=1,
                           unknown_ll=unknown_ll, lin_range=lin[0], lin_step=lin[1], ang_range=ang[0],
                           ang_step=ang[1])


OFFSETS = np.array([[0.08, 0.0, 0.0], [0.0, -0.07, math.radians(3)], [-0.05, 0.05, -math.radians(3)],
                    [0.06, 0.06, math.radians(3)], [-0.07, -0.04, math.radians(-2)]])


@pytest.fixture(scope="module")
def room_map():
    walls = _room()
    return walls, _map(len(OFFSETS), MAP_POSE, _scan(MAP_POSE, walls, noise=0.005, seed=1))


def test_climb_finds_the_pose_of_a_scan_from_5_to_10_cm_and_3_degrees_off(room_map):
    walls, maps = room_map
    for seed in range(draws(3, 1)):
        points = _scan(TRUTH, walls, noise=0.005, seed=10 + seed)
        poses, scores = _climb(maps, points, TRUTH + OFFSETS)
        err = poses - TRUTH
        # Measured over ten noise seeds: at most 1.0 cm and 0.14 degrees (5 mm range noise, the map from a
        # scan 0.45 m away); 0.25 cm once every beam finds its wall (test_a_scan_fits_the_map_it_built...).
        assert np.all(np.hypot(err[:, 0], err[:, 1]) < 0.015), err
        assert np.all(np.abs(np.degrees(wrap_angle(err[:, 2]))) < 0.5), err
        assert np.all(scores > 0.8 * len(points)), scores  # most endpoints lie on a wall of the map


def test_climb_makes_the_decisions_of_a_climb_that_scores_every_move_in_full():
    """The kernel stops scoring a move once the points left cannot lift it above the best pose; a plain climb
    that scores every move in full (tests/reference) must reach the same poses and scores, from starts near the
    match and from starts far enough off that many moves lose by a wide margin."""
    walls = _room()
    points = _scan(TRUTH, walls, noise=0.005, seed=30, n=120)
    offsets = OFFSETS[:draws(len(OFFSETS), 2)]
    starts = np.concatenate([TRUTH + offsets, TRUTH + 2.0 * offsets])
    maps = _map(len(starts), MAP_POSE, _scan(MAP_POSE, walls, noise=0.005, seed=1))
    poses, scores = _climb(maps, points, starts)
    for p, start in enumerate(starts):
        pose, score = hill_climb(maps, p, points, MOUNT[:2], start, KERNEL, SIGMA, LSTEP, ASTEP, ITERATIONS,
                                 matcher.MAX_CLIMBS_PER_LEVEL)
        np.testing.assert_array_equal(poses[p], pose)
        assert scores[p] == pytest.approx(score, rel=1e-12, abs=1e-12)


def test_the_heading_sweep_recovers_a_turn_the_climb_alone_cannot():
    """In a 30 m x 20 m hall (walls 10-15 m away) a heading 15 degrees off is beyond the climb's reach: the score
    is flat that far out (measured: the climb alone stays 14.8 degrees off, from 10 degrees on). Trying headings
    within +-30 degrees first brings it back (measured 0.13 degrees, 2.6 cm)."""
    walls = _room(w=30.0, h=20.0)
    map_pose, truth = np.array([15.0, 10.0, 0.3]), np.array([15.4, 9.8, 0.25])
    maps = _map(1, map_pose, _scan(map_pose, walls, noise=0.005, seed=1))
    points = _scan(truth, walls, seed=21)
    start = (truth + [0.03, -0.02, np.radians(15.0)])[None, :]
    alone, _ = _climb(maps, points, start)
    swept, _ = _climb(maps, points, start, sweep=np.radians(30.0))
    assert abs(np.degrees(wrap_angle(alone[0, 2] - truth[2]))) > 5.0
    assert abs(np.degrees(wrap_angle(swept[0, 2] - truth[2]))) < 0.5
    assert np.hypot(*(swept[0, :2] - truth[:2])) < 0.05


def test_climb_leaves_each_particle_on_its_own_map():
    """Particle 1's map is the room shifted by 0.3 m: the same scan climbs to a pose 0.3 m apart."""
    walls = _room()
    maps = TiledMaps(2, RES)
    scan = _scan(MAP_POSE, walls, seed=2)
    shifted = MAP_POSE + [0.3, 0.0, 0.0]
    maps.insert(np.stack([MAP_POSE, shifted]), MOUNT[:2], scan, np.ones(len(scan), bool))
    starts = np.stack([TRUTH + OFFSETS[0], TRUTH + [0.3, 0.0, 0.0] + OFFSETS[1]])
    poses, _ = _climb(maps, _scan(TRUTH, walls, seed=3), starts)
    np.testing.assert_allclose(poses[0, :2], TRUTH[:2], atol=0.015)
    np.testing.assert_allclose(poses[1, :2], TRUTH[:2] + [0.3, 0.0], atol=0.015)


def test_propose_draws_near_the_mode_with_finite_weights(room_map):
    walls, maps = room_map
    points = _scan(TRUTH, walls, noise=0.005, seed=20)
    n = len(OFFSETS)
    modes, _ = _climb(maps, points, TRUTH + OFFSETS)
    sigmas = np.tile([0.05, 0.05, 0.05], (n, 1))
    normals = np.random.default_rng(0).standard_normal((n, 3))
    poses, log_eta, at_mode = _propose(maps, points, modes, modes, sigmas, normals)
    assert np.all(np.isfinite(poses)) and np.all(np.isfinite(log_eta)) and np.all(np.isfinite(at_mode))
    # The lattice spans +-1 cm and +-0.3 degrees around the mode; the drawn pose stays within a few of it.
    d = poses - modes
    assert np.all(np.hypot(d[:, 0], d[:, 1]) < 0.03) and np.all(np.abs(d[:, 2]) < math.radians(1.0)), d
    # Zero normals draw the lattice's weighted mean, which sits within the lattice.
    mean_poses, log_eta0, _ = _propose(maps, points, modes, modes, sigmas, np.zeros((n, 3)))
    assert np.all(np.abs(mean_poses[:, :2] - modes[:, :2]) <= 0.01 + 1e-12)
    assert np.all(np.abs(mean_poses[:, 2] - modes[:, 2]) <= 0.005 + 1e-12)
    np.testing.assert_array_equal(log_eta0, log_eta)  # the weight does not depend on the draw


def test_propose_weighs_the_lattice_by_the_log_likelihood_of_each_pose_scored_alone():
    """The kernel looks the walls up once per cell the lattice's positions meet; scoring each lattice pose on its
    own (tests/reference) must give the same log-likelihoods, so the same weights: at the mode, and summed over
    the lattice with the motion model's terms. Modes near the match (endpoints on walls, many near tile edges:
    the room spans four tiles), 6 cm and 3 degrees off it, and half out of the mapped room (never observed);
    every second point counted, the lattice +-2 cm by 1 cm, +-0.01 rad by 0.005."""
    walls = _room()
    points = _scan(TRUTH, walls, noise=0.005, seed=50, n=150)
    modes = np.array([TRUTH, TRUTH + [0.004, -0.003, 0.001], TRUTH + [0.06, 0.0, math.radians(3)],
                      TRUTH + [-2.9, 0.4, 0.0]])
    maps = _map(len(modes), MAP_POSE, _scan(MAP_POSE, walls, noise=0.005, seed=1))
    means = modes + [0.01, -0.02, 0.01]
    sigmas = np.tile([0.05, 0.04, 0.03], (len(modes), 1))
    lin, ang, stride, unknown_ll = (0.02, 0.01), (0.01, 0.005), 2, -1.25
    ox, oy = maps.tile_origin
    _, log_eta, at_mode = matcher.propose(
        maps.table, maps.state, maps.mean, ox, oy, RES, points, MOUNT[0], MOUNT[1], modes, means, sigmas,
        np.zeros_like(modes), kernel=KERNEL, lsigma=LSIGMA, stride=stride, unknown_ll=unknown_ll,
        lin_range=lin[0], lin_step=lin[1], ang_range=ang[0], ang_step=ang[1])
    steps = range(-2, 3)
    for p, mode in enumerate(modes):
        terms = []
        for i in steps:
            for j in steps:
                for a in range(-2, 3):
                    pose = np.array([mode[0] + i * lin[1], mode[1] + j * lin[1], mode[2] + a * ang[1]])
                    ll = log_likelihood(maps, p, points, MOUNT[:2], pose, KERNEL, LSIGMA, stride, unknown_ll,
                                        matcher.NULL_LIKELIHOOD)
                    if i == j == a == 0:
                        assert at_mode[p] == pytest.approx(ll, rel=1e-12, abs=1e-12)
                    z = (pose - means[p]) / sigmas[p]
                    terms.append(ll - 0.5 * float(z @ z))
        top = max(terms)
        assert log_eta[p] == pytest.approx(top + math.log(sum(math.exp(t - top) for t in terms)), rel=1e-12)
    assert at_mode[3] < at_mode[0] - 50.0  # half the points out of the map cost unknown_ll each


def test_a_mode_far_from_the_motion_mean_weighs_less(room_map):
    walls, maps = room_map
    points = _scan(TRUTH, walls, noise=0.005, seed=30)
    mode, _ = _climb(maps, points, (TRUTH + OFFSETS[0])[None, :])
    modes = np.repeat(mode, 3, axis=0)
    sigmas = np.tile([0.1, 0.1, 0.1], (3, 1))
    # The motion model expected the robot at the match, 0.25 m off, and 0.5 m off.
    means = modes + [[0.0, 0.0, 0.0], [0.25, 0.0, 0.0], [0.0, -0.5, 0.0]]
    _, log_eta, at_mode = _propose(maps, points, modes, means, sigmas, np.zeros((3, 3)))
    assert at_mode[0] == at_mode[1] == at_mode[2]  # same scan, same map, same pose: same likelihood
    # exp(-(d / sigma)^2 / 2) of the motion model: 2.5 and 5 sigmas off cost about 3.1 and 12.5 in log weight.
    assert log_eta[0] > log_eta[1] + 2.5 and log_eta[1] > log_eta[2] + 8.0
    assert log_eta[0] - log_eta[1] == pytest.approx(0.5 * 2.5 ** 2, abs=0.5)
    assert log_eta[0] - log_eta[2] == pytest.approx(0.5 * 5.0 ** 2, abs=1.0)


def test_a_mode_off_the_scan_weighs_less_than_the_match(room_map):
    walls, maps = room_map
    points = _scan(TRUTH, walls, noise=0.005, seed=40)
    mode, _ = _climb(maps, points, (TRUTH + OFFSETS[1])[None, :])
    # The motion model agrees with each mode, so only the scan's fit tells them apart.
    modes = np.concatenate([mode, mode + [[0.06, 0.0, 0.0]], mode + [[0.0, 0.0, math.radians(2)]]])
    _, log_eta, at_mode = _propose(maps, points, modes, modes, np.tile([0.1, 0.1, 0.1], (3, 1)), np.zeros((3, 3)))
    assert at_mode[0] > at_mode[1] and at_mode[0] > at_mode[2]
    assert log_eta[0] > log_eta[1] + 5.0 and log_eta[0] > log_eta[2] + 5.0


def test_an_endpoint_without_a_wall_costs_by_what_the_map_knows_there(room_map):
    """Far from any wall: in the room's free space it scores NULL_LIKELIHOOD / lsigma, outside everything
    the map has seen it scores ``unknown_ll``; next to a wall, minus its squared distance / lsigma."""
    _, maps = room_map
    pose = MAP_POSE[None, :]
    sensor = compose(MAP_POSE, MOUNT)[:2]
    c, s = math.cos(MAP_POSE[2]), math.sin(MAP_POSE[2])

    def tracking(world_xy):  # a world point in MAP_POSE's tracking frame
        d = np.asarray(world_xy) - MAP_POSE[:2]
        return np.array([[c * d[0] + s * d[1], -s * d[0] + c * d[1]]])

    def at_mode(world_xy, unknown_ll):
        return _propose(maps, tracking(world_xy), pose, pose, np.full((1, 3), 0.1), np.zeros((1, 3)),
                        lin=(0.0, 0.01), ang=(0.0, 0.005), unknown_ll=unknown_ll)[2][0]

    free = sensor + [0.9, 0.3]  # inside the room, a metre from the nearest wall
    assert at_mode(free, -1.25) == pytest.approx(matcher.NULL_LIKELIHOOD / LSIGMA)
    assert at_mode([20.0, 20.0], -1.25) == pytest.approx(-1.25)  # never observed
    assert at_mode([20.0, 20.0], -0.5) == pytest.approx(-0.5)
    # 1 cm inside the room from the right-hand wall (x = 6.013): a wall within the kernel, about 1 cm away.
    near = np.array([6.013 - 0.01, sensor[1]])
    assert -(0.02 ** 2) / LSIGMA < at_mode(near, -1.25) <= 0.0


def _beams_finding_a_wall(maps, points, pose):
    """How many of ``points`` seen from ``pose`` find a wall: with sigma 100 km each such beam scores
    exp(-d^2 / 2 sigma^2) = 1 to within 1e-12 and the others 0, and steps of 1e-12 leave the pose where it is."""
    _, score = matcher.climb(maps, RES, points, MOUNT[0], MOUNT[1], np.ascontiguousarray(pose[None, :]), np.zeros(1),
                             matcher.ClimbSettings(KERNEL, 1e5, 1e-12, 1e-12, 0))
    return float(score[0])


@pytest.mark.parametrize("shift", [(0.0, 0.0), (0.02, 0.04), (0.041, 0.007)],
                         ids=["walls-on-cell-edges", "walls-off-cell-edges", "walls-near-far-cell-edges"])
def test_a_scan_fits_the_map_it_built_at_the_pose_it_was_taken(shift):
    """At the pose that built the map every endpoint lies in a wall cell entered from free space: each beam
    finds its wall (a few near the room's corners may see the other wall's cell behind them), and climbing
    from that pose stays there."""
    walls = _room(shift=shift)
    for pose in (MAP_POSE, np.array([3.1, 2.2, -1.0]), np.array([1.3, 0.9, 2.0])):
        points = _scan(pose, walls, seed=4)
        maps = _map(1, pose, points)
        found = _beams_finding_a_wall(maps, points, pose)
        assert found == pytest.approx(round(found), abs=1e-6)
        n = len(points)
        missing = n - round(found)
        assert missing <= 0.02 * n, f"{missing} of {n} beams find no wall at their own pose {pose}"
        moved, _ = _climb(maps, points, pose[None, :])
        assert math.hypot(*(moved[0, :2] - pose[:2])) < 0.01 and abs(moved[0, 2] - pose[2]) < math.radians(0.2)
