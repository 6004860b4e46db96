"""pipeline: the one place a recording is opened, its topics chosen and the laser placed."""
import numpy as np
import pytest

from carto_cli.core.errors import TopicError
from carto_cli.core.timing import StageTimer
from carto_cli.io.recording_writers import write_recording
from carto_cli.options import load_options
from carto_cli.pipeline import build, opened, read_options, resolve_laser_pose
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


def test_opened_chooses_the_topics_and_counts_the_scans(sim_bag):
    path, sim = sim_bag
    with opened(path, read_options(load_options(None))) as o:
        assert o.selection.scan == "/scan" and o.selection.odometry == "/odom"
        assert o.scan_count == len(sim.scan_times)


def test_opened_names_a_missing_topic(sim_bag):
    with pytest.raises(TopicError, match="/nope"), opened(sim_bag[0], scan_topic="/nope"):
        pass


def test_read_options_slice_clouds_as_the_options_say():
    options = load_options(None, ["trajectory_builder_2d.min_z=-0.3", "trajectory_builder_2d.max_z=0.4"])
    read = read_options(options)
    assert (read.min_z, read.max_z) == (-0.3, 0.4)


def test_laser_pose_from_the_command_line_then_static_tf_then_identity(sim_bag):
    path, sim = sim_bag
    with opened(path) as o:
        frame = next(r.frame for r in o.recording.records(["/scan"]))
        pose, source = resolve_laser_pose(o.recording, frame, (1.0, 2.0, 0.5))
        assert source == "--laser-pose" and np.allclose(pose, (1.0, 2.0, 0.5))
        pose, source = resolve_laser_pose(o.recording, frame, None)
        assert source.startswith("static TF") and np.allclose(pose, sim.laser_pose)
        pose, source = resolve_laser_pose(o.recording, "no_such_frame", None)
        assert source.startswith("identity") and np.allclose(pose, 0.0)


def _fake_build(verdicts, calls):
    from types import SimpleNamespace

    from carto_cli.mapping.quality import MapQuality, MapVerdict

    def build(recording, options, *, algorithm, **kwargs):
        calls.append(algorithm)
        return SimpleNamespace(quality=MapQuality(MapVerdict(verdicts[algorithm]), [], []), algorithm=algorithm,
                               stats={"scans": 10, "wall_time_s": 0.0})
    return build


@pytest.mark.parametrize("gm, carto, kept", [("suspect", "ok", "cartographer"), ("failed", "suspect", "cartographer"),
                                             ("suspect", "suspect", "gmapping"), ("suspect", "failed", "gmapping"),
                                             ("ok", "ok", "gmapping")])
def test_auto_falls_back_to_cartographer_when_gmappings_map_is_judged_worse(monkeypatch, gm, carto, kept):
    from carto_cli import pipeline
    from carto_cli.options import load_options
    from carto_cli.regime import AutoChoice

    calls: list[str] = []
    monkeypatch.setattr(pipeline, "build", _fake_build({"gmapping": gm, "cartographer": carto}, calls))
    monkeypatch.setattr(pipeline, "configure_regime", lambda regime, spec, algorithm: pipeline.Configured(
        load_options(), regime, AutoChoice("sparse", algorithm=algorithm), algorithm))
    chosen = pipeline.Configured(load_options(), object(), AutoChoice("sparse", algorithm="gmapping",
                                                                      chose_algorithm=True), "gmapping")
    result, configured = pipeline.build_configured(None, chosen, pipeline.Auto())
    assert result.algorithm == kept == configured.algorithm
    assert calls == (["gmapping"] if gm == "ok" else ["gmapping", "cartographer"])
    if gm != "ok":
        assert "gmapping's map judged" in configured.auto.note or "kept gmapping's" in configured.auto.note
        # The time reported is both mappings', not the second one's alone.
        assert result.stats["wall_time_s"] > 0 and "first_pass_wall_time_s" in result.stats


def test_no_fallback_when_the_user_chose_gmapping(monkeypatch):
    from carto_cli import pipeline
    from carto_cli.options import load_options
    from carto_cli.regime import AutoChoice

    calls: list[str] = []
    monkeypatch.setattr(pipeline, "build", _fake_build({"gmapping": "failed", "cartographer": "ok"}, calls))
    forced = pipeline.Configured(load_options(), object(), AutoChoice("sparse", algorithm="gmapping"), "gmapping")
    _, configured = pipeline.build_configured(None, forced, pipeline.Auto())
    assert calls == ["gmapping"] and configured is forced
    named = pipeline.Configured(load_options(), algorithm="gmapping")
    _, configured = pipeline.build_configured(None, named, load_options())
    assert calls == ["gmapping", "gmapping"] and configured is named


def test_reading_the_recording_is_a_stage_of_its_own(sim_bag):
    """Decoding happens between scans, where no other stage sees it: it is timed as "read recording", one call a
    record the mapping loop took (scans and odometry)."""
    path, sim = sim_bag
    options = load_options(None)
    timer = StageTimer()
    with opened(path, read_options(options)) as o:
        build(o.recording, options, selection=o.selection, timer=timer, loop_closure=False, jobs=1)
        records = sum(1 for _ in o.recording.records([o.selection.scan, o.selection.odometry]))
    timer.stop()
    read = timer.snapshot().find("read recording")
    assert read is not None and read.count == records > len(sim.scan_times)
    assert 0 < read.total_ns < timer.snapshot().wall_ns
