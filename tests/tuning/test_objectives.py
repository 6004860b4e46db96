"""The objectives a trial is scored by: map quality without a reference, relocalization on held-out scans,
recordings mapped together as sessions, and which objective a set of recordings gets."""
import numpy as np
import pytest

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.evaluation.metrics import align_se2
from carto_cli.io.trajectory import Trajectory
from carto_cli.options import apply_overrides, load_options
from carto_cli.pipeline import MapRequest, build, map_sessions
from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate
from carto_cli.sim.sessions import route_sessions
from carto_cli.sim.world import room
from carto_cli.tuning.objectives import (
    UNLINKED_PENALTY,
    SessionsCase,
    check_space,
    evaluate_options,
    make_cases,
    map_quality,
    resolve_objective,
    score_case,
)


def test_map_quality_prefers_the_better_map(sim, poor):
    rec = sim.recording()
    good = map_quality(build(rec, load_options()), rec)
    worse = map_quality(build(rec, apply_overrides(load_options(), poor)), rec)
    assert 0 < good["endpoint_spread"] < 1
    assert 0 <= good["crispness"] <= 1 and 0 <= good["occupied_entropy"] <= 1
    assert good["map_quality"] < worse["map_quality"]


def test_map_quality_without_the_recording_leaves_out_the_spread(sim):
    result = build(sim.recording(), load_options(), max_scans=40)
    scores = map_quality(result)
    assert "endpoint_spread" not in scores and "map_quality" not in scores
    assert {"crispness", "occupied_entropy", "loop_closure_residual_m"} <= set(scores)


def test_ground_truth_score_is_the_ate_plus_the_time_term(sim):
    case, = make_cases([sim.recording()], ground_truth=[sim.ground_truth])
    value, metrics = score_case(case, load_options(), "ground-truth", max_scans=40)
    assert value == pytest.approx(metrics["ate_rmse_m"]) and metrics["ate_rmse_m"] > 0
    timed, timed_metrics = score_case(case, load_options(), "ground-truth", max_scans=40, time_weight=10.0)
    assert timed == pytest.approx(timed_metrics["ate_rmse_m"] + 10.0 * timed_metrics["s_per_scan"])


def test_resolve_objective():
    gt = Trajectory.from_arrays([0.0, 1.0], [0.0, 1.0], [0.0, 0.0], [0.0, 0.0])
    bare, with_gt = make_cases(["a.bag"]), make_cases(["a.bag"], ground_truth=[gt])
    assert resolve_objective("auto", bare) == "map-quality"
    assert resolve_objective("auto", with_gt) == "ground-truth"
    assert resolve_objective("relocalization", bare) == "relocalization"
    with pytest.raises(CartoError, match="needs a --ground-truth file for every recording"):
        resolve_objective("ground-truth", bare)
    with pytest.raises(CartoError, match="needs a --relations file"):
        resolve_objective("relations", with_gt)
    with pytest.raises(CartoError, match=r"unknown objective 'speed' \(one of auto, relations"):
        resolve_objective("speed", bare)


def test_make_cases_wants_one_reference_per_recording():
    with pytest.raises(CartoError, match="tune needs at least one recording"):
        make_cases([])
    with pytest.raises(CartoError, match="give one --ground-truth file per recording: 2 recording"):
        make_cases(["a.bag", "b.bag"], ground_truth=[[[0.0, 0.0, 0.0, 0.0]]])
    with pytest.raises(CartoError, match=r"ground truth must be \(m, 4\)"):
        make_cases(["a.bag"], ground_truth=[[[0.0, 0.0, 0.0]]])


def test_map_quality_cannot_tune_the_grid_it_scores():
    grid = ["trajectory_builder_2d.submaps.range_data_inserter.hit_probability",
            "trajectory_builder_2d.submaps.grid_options_2d.resolution"]
    with pytest.raises(CartoError, match="cannot tune .*hit_probability, .*resolution"):
        check_space("map-quality", grid + ["pose_graph.constraint_builder.min_score"])
    check_space("ground-truth", grid)
    check_space("map-quality", ["pose_graph.constraint_builder.min_score"])


def test_relocalization_objective():
    # The held-out last 30 % must revisit mapped places: most of two laps, scans at 2 Hz.
    world = loop_building()
    traj = loop_trajectory(world, laps=2)
    sim = simulate(world, traj, duration=0.7 * traj.duration, scan_rate=2.0, lidar=Lidar(beams=180))
    from carto_cli.tuning.objectives import prepare

    cases = make_cases([sim.recording()], ground_truth=[sim.ground_truth])
    prepare(cases, "relocalization", load_options(), None)
    value, metrics = evaluate_options(load_options(), cases, "relocalization")
    assert metrics["queries"] >= 10
    assert metrics["success_rate"] >= 0.5
    assert value == pytest.approx(1 - metrics["success_rate"] + metrics["latency_s"])


def test_the_space_must_vary_what_the_algorithm_reads():
    carto, gm = "pose_graph.constraint_builder.min_score", "gmapping.particles"
    check_space("map-quality", [carto])
    check_space("map-quality", [gm], "gmapping")
    with pytest.raises(CartoError, match="cartographer does not use gmapping.particles"):
        check_space("ground-truth", [carto, gm])
    with pytest.raises(CartoError, match=f"gmapping does not use {carto}"):
        check_space("relations", [gm, carto], "gmapping")
    # Relocalization searches map.carto's submaps, which Cartographer's submap options build even for gmapping.
    check_space("relocalization", [gm, "trajectory_builder_2d.submaps.num_range_data"], "gmapping")


def test_a_gmapping_score_maps_with_gmapping(sim):
    case, = make_cases([sim.recording()], ground_truth=[sim.ground_truth])
    options = load_options(None, ["gmapping.particles=5"])
    value, metrics = score_case(case, options, "ground-truth", max_scans=30, algorithm="gmapping")
    direct = build(sim.recording(), options, max_scans=30, algorithm="gmapping")
    assert direct.stats["algorithm"] == "gmapping" and metrics["loop_closures"] == direct.stats["loop_closures"]
    # The filter is seeded: the trial's trajectory is the one built directly.
    from carto_cli.evaluation.metrics import ate

    assert case.ground_truth is not None
    direct_ate = ate(Trajectory.from_poses(direct.times, direct.poses), case.ground_truth).translation.rmse
    assert value == pytest.approx(metrics["ate_rmse_m"]) and value == pytest.approx(direct_ate)


@pytest.fixture(scope="module")
def sessions():
    """The loop building driven twice, the second time from the other side the other way round."""
    recordings, references = route_sessions(loop_building(), 2, scan_rate=5.0, lidar=Lidar(beams=180))
    return recordings, [_reference(r) for r in references]


def _reference(rows) -> Trajectory:
    return Trajectory.from_arrays(rows[:, 0], rows[:, 1], rows[:, 2], rows[:, 3])


def test_sessions_are_scored_in_the_one_frame_of_their_map(sessions):
    recordings, references = sessions
    case, = make_cases(recordings, ground_truth=references, sessions=True)
    assert isinstance(case, SessionsCase) and len(case.parts) == 2
    value, metrics = score_case(case, load_options(), "ground-truth")
    assert metrics["unlinked_sessions"] == 0
    # The reference computation: every session's poses against its truth under ONE alignment, one RMSE over all
    result = map_sessions(MapRequest(recordings[0], load_options(), later=(recordings[1],)))
    est = np.concatenate([s.poses[:, :2] for s in result.sessions])
    ref = np.concatenate([np.column_stack([np.interp(s.times, t.t, t.xy[:, 0]), np.interp(s.times, t.t, t.xy[:, 1])])
                          for s, t in zip(result.sessions, references)])
    moved = transform.apply(align_se2(est, ref), est)
    assert value == pytest.approx(float(np.sqrt(np.mean(np.sum((moved - ref) ** 2, axis=1)))), rel=1e-3)
    assert metrics["worst_session_ate_m"] >= value * 0.99


def test_a_session_linked_to_nothing_costs_the_penalty(sessions):
    recordings, references = sessions
    (other,), (truth,) = route_sessions(room(), 1, scan_rate=5.0, lidar=Lidar(beams=180))
    case, = make_cases([recordings[0], other], ground_truth=[references[0], _reference(truth)], sessions=True)
    value, metrics = score_case(case, load_options(), "ground-truth")
    assert metrics["unlinked_sessions"] == 1
    assert value == pytest.approx(metrics["ate_rmse_m"] + UNLINKED_PENALTY)
    quality, quality_metrics = score_case(case, load_options(), "map-quality")
    assert quality_metrics["unlinked_sessions"] == 1 and quality >= UNLINKED_PENALTY


def test_map_quality_of_sessions_spreads_every_sessions_returns_in_one_grid(sessions):
    recordings, _ = sessions
    case, = make_cases(recordings, sessions=True)
    _, joint = score_case(case, load_options(), "map-quality")
    # Each session alone: the joint grid must hold about as few cells per return as the sharper of the two (two
    # sessions placed alike put their returns on the same walls), far fewer than their returns side by side would
    alone = [score_case(c, load_options(), "map-quality")[1]["endpoint_spread"] for c in make_cases(recordings)]
    assert 0 < joint["endpoint_spread"] < 0.75 * sum(alone)


def test_sessions_refuse_what_has_no_multi_session_form(sessions):
    recordings, _ = sessions
    with pytest.raises(CartoError, match="--sessions maps several recordings"):
        make_cases(recordings[:1], sessions=True)
    cases = make_cases(recordings, sessions=True)
    with pytest.raises(CartoError, match="relocalization objective scores one recording's map"):
        resolve_objective("relocalization", cases)
    assert resolve_objective("auto", cases) == "map-quality"
    with pytest.raises(CartoError, match="one Cartographer pose graph; gmapping maps one"):
        score_case(cases[0], load_options(), "map-quality", algorithm="gmapping")
