"""The relocalization search in a saved map: windowed passes around priors, fallbacks, global search, submap
filters, the acceptance checks, batch queries, errors.

The map and the second-pass queries come from ``reloc_map`` (fixtures in conftest.py).
"""
import math
from types import SimpleNamespace

import numpy as np
import pytest
from reloc_map import pose_error

from carto_cli.core import transform
from carto_cli.core.errors import CartoError, FormatError
from carto_cli.io.map_file import load_map
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options, apply_overrides
from carto_cli.relocalization import PATHS, Candidate, Relocalizer, Timings, read_queries, relocalize_many

# ------------------------------------------------------------------------------------------ searches


def test_perturbed_priors_are_found_within_10cm_and_1deg(relocalizer, queries):
    _, qs = queries
    rng = np.random.default_rng(1)
    for scan, truth in qs[::2]:
        direction = rng.uniform(0, 2 * math.pi)
        offset = rng.uniform(0, 1.5)
        prior = truth + np.array([offset * math.cos(direction), offset * math.sin(direction),
                                  math.radians(rng.uniform(-15, 15))])
        r = relocalizer.relocalize(scan, prior, sigma_xy=0.5, sigma_yaw=math.radians(5))
        assert r.success, r.reason
        assert r.path == "windowed"
        dxy, dyaw = pose_error(r.pose, truth)
        assert dxy < 0.1 and dyaw < 1.0, (prior, r)
        assert r.score >= relocalizer.ro.min_score
        assert set(r.timings) == {"submap preparation", "pose search", "scan scoring", "other"}
        assert r.total_ms >= sum(r.timings.values()) - 1e-6
        assert 1 <= len(r.submaps_considered) <= relocalizer.ro.max_windowed_submaps


def test_prior_off_by_its_full_stated_uncertainty_stays_windowed(relocalizer, queries):
    """A prior 3 sigma off (1.5 m / 15 deg at 0.5 m / 5 deg) is inside the first window or the wide pass,
    never a whole-submap search: the window has a margin over 3 sigma."""
    _, qs = queries
    for k, (scan, truth) in enumerate(qs[1::3]):
        direction = math.pi / 4 + k * math.pi / 2  # the window's corners are farther; the disc's rim is the test
        prior = truth + np.array([1.5 * math.cos(direction), 1.5 * math.sin(direction),
                                  math.radians(15 if k % 2 else -15)])
        r = relocalizer.relocalize(scan, prior, sigma_xy=0.5, sigma_yaw=math.radians(5))
        assert r.success, r.reason
        assert r.path in ("windowed", "windowed-wide"), r.reason
        assert len(r.submaps_considered) <= relocalizer.ro.max_windowed_submaps
        dxy, dyaw = pose_error(r.pose, truth)
        assert dxy < 0.1 and dyaw < 1.0


def test_answer_beyond_the_first_window_is_found_by_the_wide_pass(relocalizer, queries):
    _, qs = queries
    scan, truth = qs[9]
    # sigma 0.1 m / 2 deg: first window ±0.375 m / ±7.5 deg; the truth is 0.6 m and 9 deg away.
    r = relocalizer.relocalize(scan, truth + [0.6, 0.0, math.radians(9)], sigma_xy=0.1, sigma_yaw=math.radians(2))
    assert r.success, r.reason
    assert r.path == "windowed-wide" and "windowed search" in r.reason
    assert len(r.submaps_considered) <= relocalizer.ro.max_windowed_submaps
    dxy, dyaw = pose_error(r.pose, truth)
    assert dxy < 0.1 and dyaw < 1.0


def _doubled(mapped, shift=(60.0, 0.0, 0.0)):
    """The map plus a copy of it (submaps and nodes) 60 m away: every place exists twice."""
    m, n = mapped.num_submaps, mapped.num_nodes
    moved = np.array([transform.compose(shift, p) for p in mapped.submap_global_poses])
    nodes = np.array([transform.compose(shift, p) for p in mapped.node_global_poses])
    return SimpleNamespace(
        path=None, options=mapped.options, laser_pose=mapped.laser_pose, num_submaps=2 * m,
        submaps=list(mapped.submaps) * 2, submap_global_poses=np.concatenate([mapped.submap_global_poses, moved]),
        submap_nodes=list(mapped.submap_nodes) + [np.asarray(s) + n for s in mapped.submap_nodes],
        node_global_poses=np.concatenate([mapped.node_global_poses, nodes]))


def test_global_search_reports_aliasing_instead_of_guessing(mapped, queries):
    _, qs = queries
    rel = Relocalizer(_doubled(mapped))
    scan, truth = qs[5]
    r = rel.relocalize(scan, None)
    assert r.path == "global" and not r.success
    assert "ambiguous" in r.reason
    # A prior tells the two apart: the copy 60 m away is no rival of the place next to it.
    r = rel.relocalize(scan, truth + [1.0, -1.0, 0.3], sigma_xy=2.0, sigma_yaw=math.radians(10))
    assert r.success, r.reason
    assert pose_error(r.pose, truth)[0] < 0.1


def test_prior_in_the_wrong_place_is_detected_and_the_fallback_recovers(relocalizer, queries):
    _, qs = queries
    for scan, truth in (qs[3], qs[len(qs) - 4]):
        # Across the building (bottom stretch <-> right stretch), true heading, confident sigma.
        wrong = np.array([21.5, 9.0, truth[2]]) if truth[1] < 4 else np.array([8.0, 0.0, truth[2]])
        r = relocalizer.relocalize(scan, wrong, sigma_xy=0.1, sigma_yaw=math.radians(2))
        assert r.path in ("fallback-filtered", "fallback-all")
        assert "windowed" in r.reason
        assert r.success
        dxy, dyaw = pose_error(r.pose, truth)
        assert dxy < 0.1 and dyaw < 1.0


def test_unreliable_prior_skips_the_window(relocalizer, queries):
    _, qs = queries
    scan, truth = qs[10]
    r = relocalizer.relocalize(scan, truth + [1.0, -1.0, 0.3], sigma_xy=2.0, sigma_yaw=math.radians(10))
    assert r.path == "fallback-filtered" and "unreliable" in r.reason
    assert r.success
    dxy, dyaw = pose_error(r.pose, truth)
    assert dxy < 0.1 and dyaw < 1.0
    r = relocalizer.relocalize(scan, truth, sigma_xy=0.2, sigma_yaw=math.radians(20))  # yaw too uncertain
    assert r.path == "fallback-filtered"


def test_global_search_without_prior(relocalizer, queries):
    _, qs = queries
    for scan, truth in (qs[5], qs[20]):
        r = relocalizer.relocalize(scan, None)
        assert r.path == "global" and r.success
        assert sorted(r.submaps_considered) == relocalizer.covering
        dxy, dyaw = pose_error(r.pose, truth)
        assert dxy < 0.1 and dyaw < 1.0


def test_covering_submaps_hold_every_node(relocalizer, mapped):
    nodes = set()
    for i in relocalizer.covering:
        nodes |= set(mapped.submap_nodes[i].tolist())
    assert nodes == set(range(mapped.num_nodes))
    assert len(relocalizer.covering) < mapped.num_submaps


def test_explicit_laser_pose_is_used(relocalizer, queries):
    _, qs = queries
    scan, truth = qs[8]
    # A laser mounted 0.3 m ahead: the tracking frame sits 0.3 m behind where the laser is.
    r = relocalizer.relocalize(scan, truth, sigma_xy=0.3, sigma_yaw=0.05, laser_pose=(0.3, 0.0, 0.0))
    assert r.success
    expected = transform.compose(truth, (-0.3, 0.0, 0.0))
    assert pose_error(r.pose, expected)[0] < 0.1


# ------------------------------------------------------------------------------------------ filters


def _fake_map(boxes, global_poses=None):
    """A map of empty submaps whose known boxes are ``boxes`` (x0, y0, x1, y1) in their grid frames."""
    submaps = []
    for i, (x0, y0, x1, y1) in enumerate(boxes):
        sm = Submap((x0, y0), index=i, resolution=0.1, initial_size=4)
        sm.grid.grow_to_include(np.array([[x0, y0], [x1, y1]]))
        cells = sm.grid.cell_index(np.array([[x0 + 0.01, y0 + 0.01], [x1 - 0.01, y1 - 0.01]]))
        sm.grid.set_probability(cells, [0.9, 0.9])
        sm.local_pose = np.zeros(3)
        submaps.append(sm)
    m = len(boxes)
    return SimpleNamespace(
        path=None, options=Options(), laser_pose=None, num_submaps=m, submaps=submaps,
        submap_global_poses=np.zeros((m, 3)) if global_poses is None else np.asarray(global_poses, float),
        submap_nodes=[np.zeros(0, np.int64)] * m, node_global_poses=np.zeros((0, 3)))


def test_distance_filter_uses_the_submap_box_not_its_origin():
    # Submap 0: a long strip from x=0 to 20 (origin at 0); the prior at x=18 is inside it.
    rel = Relocalizer(_fake_map([(0, 0, 20, 2), (30, 0, 32, 2), (18, 6, 20, 8)]))
    assert rel.filter_by_distance((18.0, 1.0, 0.0), 3.0) == [0]
    assert sorted(rel.filter_by_distance((18.0, 1.0, 0.0), 5.2)) == [0, 2]
    assert np.allclose(rel.box_distances((18.0, 1.0))[:3], [0.0, 12.0, 5.0], atol=0.11)
    # The box moves with the submap's global pose: submap 1 turned by 90 deg about the origin.
    rel = Relocalizer(_fake_map([(0, 0, 20, 2), (30, 0, 32, 2)], [(0, 0, 0), (0, 0, math.pi / 2)]))
    assert rel.box_distances((-1.0, 31.0))[1] < 0.11


def test_radius_follows_the_priors_confidence(relocalizer):
    ro = relocalizer.ro
    assert relocalizer.radius_for(0.1, True) == ro.high_confidence_radius
    assert relocalizer.radius_for(1.0, True) == ro.medium_confidence_radius
    assert relocalizer.radius_for(2.0, False) == ro.low_confidence_radius
    assert relocalizer.windows(0.05, math.radians(1)) == (pytest.approx(ro.min_linear_search_window),
                                                          pytest.approx(ro.min_angular_search_window))
    # 3 sigma plus a 25 % margin: a prior off by 3 sigma is inside the window, not on its edge.
    lin, ang = relocalizer.windows(0.5, math.radians(5))
    assert lin >= 1.5 * 1.2 and ang >= math.radians(15) * 1.2
    assert lin == pytest.approx(1.875) and ang == pytest.approx(math.radians(18.75))
    assert relocalizer.windows(5.0, 1.0)[0] == ro.max_linear_search_window


def test_corridor_filter_keeps_submaps_along_the_heading():
    # A corridor along x: boxes ahead, behind, beside (out of the side range) and far ahead.
    boxes = [(0, -1, 4, 1), (6, -1, 10, 1), (-8, -1, -5, 1), (0, 5, 4, 7), (25, -1, 30, 1)]
    rel = Relocalizer(_fake_map(boxes))
    kept = rel.filter_corridor((2.0, 0.0, 0.0), forward_range=10.0, side_range=2.0)
    assert sorted(kept) == [0, 1, 2]
    # Heading along y instead: the side box is now ahead, the ones along x are beside.
    kept = rel.filter_corridor((2.0, 0.0, math.pi / 2), forward_range=10.0, side_range=1.5)
    assert sorted(kept) == [0, 3]
    # A diagonal heading: the rectangle is oriented, not the prior's axis-aligned hull.
    kept = rel.filter_corridor((0.0, 0.0, math.pi / 4), forward_range=12.0, side_range=0.5)
    assert 3 not in kept and 4 not in kept and 0 in kept


def test_corridor_mode_on_the_real_map(relocalizer, queries):
    _, qs = queries
    scan, truth = qs[6]  # bottom stretch, heading +x
    assert abs(truth[2]) < 0.2
    kept = relocalizer.filter_corridor(truth, forward_range=4.0, side_range=0.5)
    near = relocalizer.filter_by_distance(truth, 0.0)
    assert set(kept) <= set(relocalizer.searchable) and set(near) <= set(kept)
    r = relocalizer.relocalize(scan, truth + [0.3, 0.2, 0.05], corridor=True)
    assert r.success and pose_error(r.pose, truth)[0] < 0.1


# ------------------------------------------------------------------------------------------ stacks


def test_relocalizer_reuses_stacks_across_queries(mapped, queries):
    _, qs = queries
    rel = Relocalizer(mapped)
    scan, truth = qs[2]
    rel.relocalize(scan, truth)
    built = rel.cache.misses
    rel.relocalize(scan, truth)
    assert rel.cache.misses == built and rel.cache.hits > 0


# ------------------------------------------------------------------------------------------ errors


def test_prior_outside_the_map_is_an_error(relocalizer, queries):
    scan, _ = queries[1][0]
    with pytest.raises(CartoError, match=r"initial pose 200,-50 is \d+\.\d m from the nearest submap"):
        relocalizer.relocalize(scan, (200.0, -50.0, 0.0))
    with pytest.raises(CartoError, match="finite"):
        relocalizer.relocalize(scan, (math.nan, 0.0, 0.0))
    with pytest.raises(CartoError, match="sigma"):
        relocalizer.relocalize(scan, (1.0, 1.0, 0.0), sigma_xy=-1.0)


def test_corrupt_map_is_a_format_error(mapped, tmp_path):
    data = bytearray(mapped.path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    bad = tmp_path / "bad.carto"
    bad.write_bytes(bytes(data))
    with pytest.raises(FormatError):
        load_map(bad)


# ------------------------------------------------------------------------------------------ acceptance


def test_points_in_unmapped_space_do_not_sink_a_right_pose(mapped, queries):
    """A scan seeing partly unmapped space is judged on its points in known cells (first windowed pass)."""
    from carto_cli.matching.scoring import known_score

    # The made-up far points below are rays straight through the building's walls: the free-space check would
    # (rightly) reject them, and is tested on its own.
    relocalizer = Relocalizer(mapped, apply_overrides(mapped.options, ["relocalization.max_see_through=1"]))
    _, qs = queries
    scan, truth = qs[5]
    _, fine = relocalizer.preprocess(scan)
    i = relocalizer.filter_by_distance(truth, 1.0)[0]
    grid_pose = transform.compose(relocalizer.map_to_grid[i], np.asarray(truth, float))
    known, score = known_score(relocalizer.grids[i], fine, grid_pose)
    assert known > 0.9 and score > 0.6
    # As many points again far outside every submap: unknown cells, 0.1 each in the plain score.
    far = fine + np.array([500.0, 500.0])
    pts = np.vstack([fine, far[: int(0.6 * len(fine))]])
    cand = Candidate(i, grid_pose, 0.5, grid_pose)
    _, fit = relocalizer.refine(pts, cand, 0.55, Timings())
    plain, ok, reason = fit.score, fit.ok, fit.reason
    assert plain < 0.55 and not ok and "below" in reason
    _, fit = relocalizer.refine(pts, cand, 0.55, Timings(), known_ok=True)
    ok, known, kscore = fit.ok, fit.known_fraction, fit.known_score
    assert ok and 0.55 < known < 0.7 and kscore >= 0.55
    # Mostly unmapped: not enough of the scan to judge on.
    pts = np.vstack([fine, far, far])
    assert not relocalizer.refine(pts, cand, 0.55, Timings(), known_ok=True)[1].ok


def test_fallback_submap_limit_bounds_a_confident_prior_no_window_confirms(mapped, queries):
    """A reliable prior that no window confirms searches at most fallback_max_submaps more submaps."""
    _, qs = queries
    scan, truth = qs[3]
    wrong = np.array([21.5, 9.0, truth[2]]) if truth[1] < 4 else np.array([8.0, 0.0, truth[2]])
    rel = Relocalizer(mapped, apply_overrides(mapped.options, ["relocalization.fallback_max_submaps=1"]))
    r = rel.relocalize(scan, wrong, sigma_xy=0.1, sigma_yaw=math.radians(2))
    assert "fallback limited to the nearest 1 submaps" in r.reason
    windowed = rel.ro.max_windowed_submaps
    assert len(r.submaps_considered) <= windowed + 1
    # Without the limit the same query searches further (and finds the pose: the test above).
    free = Relocalizer(mapped, apply_overrides(mapped.options, ["relocalization.fallback_max_submaps=0"]))
    r = free.relocalize(scan, wrong, sigma_xy=0.1, sigma_yaw=math.radians(2))
    assert r.success and len(r.submaps_considered) > windowed + 1


def test_a_match_whose_rays_cross_walls_is_rejected(relocalizer, queries):
    """The free-space check: a scan placed where its rays pass through the map's walls is no match."""
    _, qs = queries
    scan, truth = qs[5]
    _, fine = relocalizer.preprocess(scan)
    i = relocalizer.filter_by_distance(truth, 1.0)[0]
    grid_pose = transform.compose(relocalizer.map_to_grid[i], np.asarray(truth, float))
    cand = Candidate(i, grid_pose, 0.7, grid_pose)
    fit = relocalizer.refine(fine, cand, 0.55, Timings())[1]
    ok, see = fit.ok, fit.see_through
    assert ok and see < 0.05
    # The same endpoints seen from a sensor 3 m away through the wall: most rays now cross it.
    for offset in ([-3.0, 0.0], [0.0, -3.0], [3.0, 0.0], [0.0, 3.0]):
        fit = relocalizer.refine(fine, cand, 0.55, Timings(), sensor=offset)[1]
        ok, reason, see = fit.ok, fit.reason, fit.see_through
        if see > relocalizer.ro.max_see_through:
            assert not ok and "pass through walls" in reason
            break
    else:
        raise AssertionError("no sensor offset made the rays cross a wall")


# ------------------------------------------------------------------------------------------ stages and batch


def test_relocalize_many_answers_every_query_in_file_order(relocalizer, queries, tmp_path):
    sim, qs = queries
    (s0, t0), (s1, t1), (s2, t2) = qs[4], qs[12], qs[25]
    p = tmp_path / "q.txt"
    p.write_text(f"t x y yaw\n{s0.time + 0.04} {t0[0] + 0.5} {t0[1]} {t0[2]}\n"
                 f"{s1.time} {t1[0]} {t1[1] - 0.4} {t1[2] + 0.1} 0.2 5deg\n"
                 f"{s2.time} {t2[0]} {t2[1]} {t2[2]}\n")
    advanced = []
    results, summary = relocalize_many(relocalizer, sim.recording(), read_queries(p), on_query=advanced.append)
    assert [r.scan_time for r in results] == pytest.approx([s0.time, s1.time, s2.time])
    for r, truth in zip(results, (t0, t1, t2)):
        assert r.result.success and pose_error(r.result.pose, truth)[0] < 0.1
    assert [r.query.line for r in results] == [2, 3, 4] and advanced == [1, 1, 1]
    assert summary.queries == 3 and summary.success_rate == 1.0
    assert summary.paths["windowed"] == 3
    with pytest.raises(CartoError, match="no queries"):
        relocalize_many(relocalizer, sim.recording(), [])


def test_a_query_tries_its_stages_in_order(relocalizer, queries):
    """Every answer names the stage it came from, and its reason names the stages tried before it."""
    _, qs = queries
    scan, truth = qs[3]
    wrong = np.array([21.5, 9.0, truth[2]]) if truth[1] < 4 else np.array([8.0, 0.0, truth[2]])
    r = relocalizer.relocalize(scan, wrong, sigma_xy=0.1, sigma_yaw=math.radians(2))
    assert r.path in PATHS[2:4]
    # Pass 1 (or its edge check), then the wide pass, were tried and said why they did not answer.
    tried = r.reason.split("; ")
    assert any("windowed search" in t and "wide" not in t for t in tried)
    assert any(t.startswith("wide windowed search") for t in tried)
    first_wide = next(k for k, t in enumerate(tried) if t.startswith("wide windowed search"))
    assert all("wide" not in t for t in tried[:first_wide])
    # Without a prior only the global stage answers.
    assert relocalizer.relocalize(scan, None).path == "global"


# ------------------------------------------------------------------------------------------ map shapes


def test_grids_allocated_beyond_their_known_cells_are_searched_cropped(mapped, queries):
    """A map saved mid-trajectory keeps its newest submaps as allocated; the relocalizer crops them."""
    from carto_cli.grid.probability_grid import ProbabilityGrid

    big = []
    for s in mapped.submaps:
        g = s.grid
        padded = ProbabilityGrid(g.resolution, g.origin - 200 * g.resolution,
                                 (g.num_cells[0] + 400, g.num_cells[1] + 400))
        padded.cells[200:200 + g.num_cells[1], 200:200 + g.num_cells[0]] = g.cells
        padded.known_box = g.known_box + 200
        big.append(SimpleNamespace(grid=padded, local_pose=s.local_pose))
    padded_map = SimpleNamespace(**{k: getattr(mapped, k) for k in (
        "options", "laser_pose", "submap_global_poses", "node_global_poses", "submap_nodes", "num_submaps",
        "trajectory", "node_scans")}, submaps=big, path=None)
    rel = Relocalizer(padded_map)
    plain = Relocalizer(mapped)
    assert [g.num_cells for g in rel.grids] == [g.num_cells for g in plain.grids]
    assert rel.stack_bytes_needed == plain.stack_bytes_needed and not rel.warnings
    _, qs = queries
    scan, truth = qs[5]
    r = rel.relocalize(scan, truth + [0.5, -0.5, 0.1], sigma_xy=0.5, sigma_yaw=math.radians(5))
    assert r.success and pose_error(r.pose, truth)[0] < 0.1


def test_a_cache_budget_below_the_maps_stacks_is_reported(mapped):
    rel = Relocalizer(mapped, cache_budget_bytes=1000)
    assert len(rel.warnings) == 1 and "cache_budget_mb" in rel.warnings[0]
    assert not Relocalizer(mapped).warnings
