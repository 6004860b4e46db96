"""pipeline: a map request resolved once into a plan (topics, the laser, options and system), executed."""
import numpy as np
import pytest

from carto_cli.core.errors import CartoError, TopicError
from carto_cli.core.timing import StageTimer
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.sources.open import open_recording
from carto_cli.options import load_options
from carto_cli.pipeline import (
    Auto,
    MapRequest,
    MapResult,
    Plan,
    TopicChoice,
    execute,
    planned,
    read_options,
    resolve_laser_pose,
)
from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate


@pytest.fixture(scope="module")
def sim_bag(tmp_path_factory):
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=3.0, lidar=Lidar(beams=90), laser_pose=(0.15, -0.05, 0.1))
    rec = sim.recording()
    path = tmp_path_factory.mktemp("sim") / "sim.bag"
    write_recording(rec.records(), path, "ros1", static_transforms=rec.static_transforms(),
                    topics={t.name: t.msgtype for t in rec.topics()})
    return path, sim


def test_a_plan_chooses_the_topics_places_the_laser_and_counts_the_scans(sim_bag):
    path, sim = sim_bag
    with planned(MapRequest(path, load_options(None), jobs=1)) as plan:
        assert plan.selection.scan == "/scan" and plan.selection.odometry == "/odom"
        assert plan.scan_count == len(sim.scan_times)
        assert plan.mount_source.startswith("static TF") and np.allclose(plan.mount, sim.laser_pose)
        assert plan.configured.algorithm == "cartographer" and plan.recordings == ("sim.bag",)
    with planned(MapRequest(path, load_options(None), laser_pose=(1.0, 2.0, 0.5), jobs=1)) as plan:
        assert plan.mount_source == "--laser-pose" and np.allclose(plan.mount, (1.0, 2.0, 0.5))


def test_a_plan_names_a_missing_topic(sim_bag):
    with pytest.raises(TopicError, match="/nope"), planned(MapRequest(sim_bag[0], topics=TopicChoice("/nope"))):
        pass


def test_a_request_refuses_what_cannot_be_mapped_before_reading(tmp_path):
    with pytest.raises(CartoError, match="unknown algorithm 'ekf'"):
        MapRequest(tmp_path / "no-such.bag", algorithm="ekf")
    with pytest.raises(CartoError, match="gmapping starts every map afresh"):
        MapRequest(tmp_path / "no-such.bag", algorithm="gmapping", load_state=tmp_path / "m.carto")
    assert MapRequest(tmp_path / "r.bag", load_state=tmp_path / "m.carto").system == "cartographer"
    assert MapRequest(tmp_path / "r.bag").system is None  # auto chooses


def test_read_options_slice_clouds_as_the_options_say():
    options = load_options(None, ["trajectory_builder_2d.min_z=-0.3", "trajectory_builder_2d.max_z=0.4"])
    read = read_options(options)
    assert (read.min_z, read.max_z) == (-0.3, 0.4)


def test_laser_pose_from_the_command_line_then_static_tf_then_identity(sim_bag):
    path, sim = sim_bag
    with open_recording(path) as recording:
        frame = next(r.frame for r in recording.records(["/scan"]))
        pose, source = resolve_laser_pose(recording, frame, (1.0, 2.0, 0.5))
        assert source == "--laser-pose" and np.allclose(pose, (1.0, 2.0, 0.5))
        pose, source = resolve_laser_pose(recording, frame, None)
        assert source.startswith("static TF") and np.allclose(pose, sim.laser_pose)
        pose, source = resolve_laser_pose(recording, "no_such_frame", None)
        assert source.startswith("identity") and np.allclose(pose, 0.0)


def _fake_map_once(verdicts, calls):
    from carto_cli.mapping.quality import MapQuality, MapVerdict

    def map_once(plan, configured, timer, on_scan):
        calls.append(configured.algorithm)
        return MapResult(None, None, None, None, [], None, None, None, stats={"scans": 10, "wall_time_s": 0.0},
                         quality=MapQuality(MapVerdict(verdicts[configured.algorithm]), [], []),
                         regime=configured.regime, auto=configured.auto, options=configured.options)
    return map_once


def _plan(configured, options):
    return Plan(MapRequest("r.bag", options), None, None, np.zeros(3), "", configured)


@pytest.mark.parametrize("gm, carto, kept", [("suspect", "ok", "cartographer"), ("failed", "suspect", "cartographer"),
                                             ("suspect", "suspect", "gmapping"), ("suspect", "failed", "gmapping"),
                                             ("ok", "ok", "gmapping")])
def test_auto_falls_back_to_cartographer_when_gmappings_map_is_judged_worse(monkeypatch, gm, carto, kept):
    from carto_cli import pipeline
    from carto_cli.regime import AutoChoice

    calls: list[str] = []
    monkeypatch.setattr(pipeline, "_map_once", _fake_map_once({"gmapping": gm, "cartographer": carto}, calls))
    monkeypatch.setattr(pipeline, "configure_regime", lambda regime, spec, algorithm: pipeline.Configured(
        load_options(), regime, AutoChoice("sparse", algorithm=algorithm), algorithm))
    chosen = pipeline.Configured(load_options(), object(), AutoChoice("sparse", algorithm="gmapping",
                                                                      chose_algorithm=True), "gmapping")
    result = execute(_plan(chosen, Auto()))
    assert result.auto.algorithm == kept
    assert calls == (["gmapping"] if gm == "ok" else ["gmapping", "cartographer"])
    if gm != "ok":
        assert "gmapping's map judged" in result.auto.note or "kept gmapping's" in result.auto.note
        # The time reported is both mappings', not the second one's alone.
        assert result.stats["wall_time_s"] > 0 and "first_pass_wall_time_s" in result.stats


def test_no_fallback_when_the_user_chose_gmapping(monkeypatch):
    from carto_cli import pipeline
    from carto_cli.regime import AutoChoice

    calls: list[str] = []
    monkeypatch.setattr(pipeline, "_map_once", _fake_map_once({"gmapping": "failed", "cartographer": "ok"}, calls))
    forced = pipeline.Configured(load_options(), object(), AutoChoice("sparse", algorithm="gmapping"), "gmapping")
    result = execute(_plan(forced, Auto()))
    assert calls == ["gmapping"] and result.auto is forced.auto
    named = pipeline.Configured(load_options(), algorithm="gmapping")
    result = execute(_plan(named, load_options()))
    assert calls == ["gmapping", "gmapping"] and result.auto is None


def test_reading_the_recording_is_a_stage_of_its_own(sim_bag):
    """Decoding happens between scans, where no other stage sees it: it is timed as "read recording", one call a
    record the mapping loop took (scans and odometry)."""
    path, sim = sim_bag
    options = load_options(None)
    timer = StageTimer()
    with planned(MapRequest(path, options, loop_closure=False, jobs=1), timer) as plan:
        execute(plan, timer=timer)
        records = sum(1 for _ in plan.recording.records([plan.selection.scan, plan.selection.odometry]))
    timer.stop()
    read = timer.snapshot().find("read recording")
    assert read is not None and read.count == records > len(sim.scan_times)
    assert 0 < read.total_ns < timer.snapshot().wall_ns
