"""How far to trust an answer: covariance, ambiguity, verdicts, --max-jump."""
import math

import cv2
import numpy as np
import pytest
from reloc_map import pose_error

from carto_cli.core import transform
from carto_cli.core.records import Scan
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.io.map_server import load_map_server
from carto_cli.matching import least_squares
from carto_cli.relocalization import VERDICTS, Relocalizer
from carto_cli.sim import follow_route, office, simulate

RES = 0.05


def _segments_image(segments, size_m, tmp_path, name):
    """A trinary map_server map (free inside ``size_m``, walls drawn from ``segments``), origin at (0, 0)."""
    n = int(size_m / RES)
    px = np.full((n, n), 254, np.uint8)
    for x0, y0, x1, y1 in segments:
        p0 = (int(x0 / RES), n - 1 - int(y0 / RES))
        p1 = (int(x1 / RES), n - 1 - int(y1 / RES))
        cv2.line(px, p0, p1, 0, 1)
    cv2.imwrite(str(tmp_path / f"{name}.pgm"), px)
    (tmp_path / f"{name}.yaml").write_text(f"image: {name}.pgm\nresolution: {RES}\norigin: [0.0, 0.0, 0.0]\n")
    return tmp_path / f"{name}.yaml"


def _scan(segments, pose, max_range, n=360, noise=0.005, seed=0):
    """A LaserScan of the segments from ``pose`` (ray casting), ranges beyond ``max_range`` reported as no return."""
    rng = np.random.default_rng(seed)
    angles = -math.pi + np.arange(n) * (2 * math.pi / n)
    x, y, th = pose
    ranges = np.full(n, np.inf)
    for k, a in enumerate(angles + th):
        d = np.array([math.cos(a), math.sin(a)])
        for x0, y0, x1, y1 in segments:
            e = np.array([x1 - x0, y1 - y0])
            m = np.array([[d[0], -e[0]], [d[1], -e[1]]])
            if abs(np.linalg.det(m)) < 1e-12:
                continue
            t, u = np.linalg.solve(m, np.array([x0 - x, y0 - y]))
            if t > 0 and 0 <= u <= 1:
                ranges[k] = min(ranges[k], t)
    ranges = np.where(ranges <= max_range, ranges + rng.normal(0, noise, n), max_range + 1.0)
    return Scan(1000.0, ranges.astype(np.float32), angles.astype(np.float32), "laser", range_min=0.05,
                range_max=max_range)


def test_covariance_is_larger_along_a_featureless_corridor_than_across():
    grid = ProbabilityGrid(RES, (-20.0, -3.0), (800, 120))
    xs = np.arange(-15.0, 15.0, RES / 2)
    for y in (-1.0, 1.0):
        grid.set_probability(grid.cell_index(np.stack([xs, np.full_like(xs, y)], 1)), 0.9)
    # what a scan with a 4 m reach sees in the middle: the two walls, no end
    px = np.linspace(-4.0, 4.0, 120)
    points = np.concatenate([np.stack([px, np.full_like(px, -1.0)], 1), np.stack([px, np.full_like(px, 1.0)], 1)])
    cov = least_squares.covariance(grid, points, np.zeros(3))
    sx, sy = math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1])
    assert sx > 20 * sy and sy < 0.05
    # a room (walls across too) constrains x as well
    for x in (-4.0, 4.0):
        ys = np.arange(-1.0, 1.0, RES / 2)
        grid.set_probability(grid.cell_index(np.stack([np.full_like(ys, x), ys], 1)), 0.9)
    ends = np.stack([np.r_[np.full(40, -4.0), np.full(40, 4.0)], np.tile(np.linspace(-0.9, 0.9, 40), 2)], 1)
    cov2 = least_squares.covariance(grid, np.concatenate([points, ends]), np.zeros(3))
    assert math.sqrt(cov2[0, 0]) < sx / 10


def test_corridor_answer_reports_its_uncertainty_along_the_axis(tmp_path):
    walls = [(1.0, 9.0, 39.0, 9.0), (1.0, 11.0, 39.0, 11.0)]
    r = Relocalizer(load_map_server(_segments_image(walls, 40.0, tmp_path, "corridor")))
    res = r.relocalize(_scan(walls, (20.0, 10.0, 0.3), max_range=5.0), (20.2, 10.1, 0.3), sigma_xy=0.3,
                       sigma_yaw=0.1)
    assert res.verdict in VERDICTS and res.covariance is not None
    sx, sy, _ = res.sigmas
    assert sx > 5 * sy
    assert abs(res.pose[1] - 10.0) < 0.1  # across the corridor it is sure, and right


def test_two_identical_rooms_are_ambiguous_not_ok(tmp_path):
    def room(ox):
        return [(ox, 2.0, ox + 6.0, 2.0), (ox + 6.0, 2.0, ox + 6.0, 7.0), (ox + 6.0, 7.0, ox, 7.0),
                (ox, 7.0, ox, 2.0), (ox + 1.0, 5.0, ox + 2.5, 5.0), (ox + 2.5, 5.0, ox + 2.5, 6.0),
                (ox + 4.0, 3.0, ox + 4.6, 3.6)]
    walls = room(2.0) + room(14.0)
    r = Relocalizer(load_map_server(_segments_image(walls, 24.0, tmp_path, "twins")))
    scan = _scan(room(2.0), (4.0, 4.0, 0.2), max_range=8.0)
    res = r.relocalize(scan)
    assert res.verdict == "ambiguous", res.reason
    assert res.ambiguity >= 0.95 and res.rival is not None
    # the answer and its rival are the two rooms' same spot, 12 m apart
    assert sorted([round(res.pose[0]), round(res.rival[0])]) == [4, 16]
    assert "ambiguous" in res.reason


def test_a_scan_from_another_building_is_never_ok(relocalizer, mapped):
    sim = simulate(office(), follow_route(office()), duration=40.0, scan_rate=2.0, seed=3)
    scans = list(sim.records(["/scan"]))[::4]
    rng = np.random.default_rng(0)
    nodes = np.asarray(mapped.node_global_poses)
    assert len(scans) >= 8
    for k, scan in enumerate(scans):
        res = relocalizer.relocalize(scan)
        assert res.verdict != "ok", (k, res.score, res.reason)
        node = nodes[rng.integers(len(nodes))]
        res = relocalizer.relocalize(scan, node + [0.3, 0.2, 0.1], sigma_xy=0.5, sigma_yaw=0.2)
        assert res.verdict != "ok", (k, res.score, res.reason)


def test_an_answer_outside_the_map_is_lost_though_its_points_fit(tmp_path):
    """A room whose surroundings the map never saw (unknown in the image): a scan taken outside it, looking at
    the outer faces of a corner, puts every point on the map's walls and no ray through one. Only where the laser
    would stand says the robot cannot be there."""
    n = int(20.0 / RES)
    px = np.full((n, n), 128, np.uint8)  # unknown
    lo, hi = int(5.0 / RES), int(15.0 / RES)  # pixel (column c, row r) is the cell at (c, n - 1 - r) * RES
    px[n - 1 - hi:n - lo, lo:hi + 1] = 254  # the room's floor, free
    cv2.rectangle(px, (lo, n - 1 - hi), (hi, n - 1 - lo), 0, 3)  # its walls, three cells thick
    cv2.imwrite(str(tmp_path / "room.pgm"), px)
    (tmp_path / "room.yaml").write_text(f"image: room.pgm\nresolution: {RES}\norigin: [0.0, 0.0, 0.0]\n")
    r = Relocalizer(load_map_server(tmp_path / "room.yaml"))
    corner = [(5.0, 5.0, 15.0, 5.0), (5.0, 5.0, 5.0, 15.0)]

    def scan(pose):
        s = _scan(corner, pose, max_range=8.0)
        s.ranges[s.ranges > 8.0] = np.inf  # rays past the corner's ends meet nothing
        return s

    outside = (3.0, 3.5, math.radians(40.0))
    res = r.relocalize(scan(outside), outside, sigma_xy=0.2, sigma_yaw=0.05)
    assert res.verdict == "lost" and not res.success, res.reason
    assert "never seen" in res.reason and res.inlier_fraction > 0.95 and res.see_through == 0.0
    # the same corner seen from inside the room is found
    inside = (7.0, 6.5, math.radians(220.0))
    res = r.relocalize(scan(inside), inside, sigma_xy=0.2, sigma_yaw=0.05)
    assert res.verdict == "ok" and pose_error(res.pose, inside)[0] < 0.05, res.reason


def test_where_the_robot_stood_while_mapping_is_seen_by_the_map_not_only_by_one_submap(relocalizer, mapped):
    nodes = np.asarray(mapped.node_global_poses)[:, :2]
    # each node's position asked of submap 0: its own grid does not know most of them, another submap's does
    in_grid = transform.apply(relocalizer.map_to_grid[0], nodes)
    unknown_to_0 = ~relocalizer.grids[0].is_known(relocalizer.grids[0].cell_index(in_grid))
    assert unknown_to_0.sum() >= 10
    assert all(relocalizer.seen(0, xy) for xy in in_grid)
    far = transform.apply(relocalizer.map_to_grid[0], nodes.max(axis=0)[None] + 50.0)[0]
    assert not relocalizer.seen(0, far)


def test_max_jump_turns_a_far_answer_lost(relocalizer, queries):
    _, qs = queries
    scan, ref = qs[5]
    prior = np.asarray(ref) + [1.0, 0.0, 0.0]
    free = relocalizer.relocalize(scan, prior, sigma_xy=0.5, sigma_yaw=0.1)
    assert free.verdict == "ok" and pose_error(free.pose, ref)[0] < 0.2
    bounded = relocalizer.relocalize(scan, prior, sigma_xy=0.5, sigma_yaw=0.1, max_jump=0.5)
    assert bounded.verdict == "lost" and not bounded.success and "--max-jump" in bounded.reason
    assert relocalizer.relocalize(scan, prior, sigma_xy=0.5, sigma_yaw=0.1, max_jump=2.0).verdict == "ok"


def test_every_answer_carries_the_fields(relocalizer, queries):
    _, qs = queries
    scan, ref = qs[0]
    res = relocalizer.relocalize(scan, ref, sigma_xy=0.2, sigma_yaw=0.05)
    d = res.to_dict()
    assert d["verdict"] == "ok" and len(d["covariance"]) == 3 and 0.9 <= d["inlier_fraction"] <= 1.0
    cov = np.array(d["covariance"])
    assert np.allclose(cov, cov.T) and np.all(np.linalg.eigvalsh(cov) > 0)
    assert 0.0 <= d["ambiguity"] < 0.95
    with pytest.raises(ValueError):
        type(res)(res.pose, 0.5, "windowed", True, [], {}, 1.0, verdict="maybe")
