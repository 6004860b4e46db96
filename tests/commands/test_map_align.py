"""`carto map --align`: a simulated office mapped by a robot that set off at 30° to its walls, written by `carto map`
with the frame turned square (auto) and as it started (none): every output turned together, the saved state
rendering and relocalizing in the turned frame, and a map square already left as it was."""
import json
import math

import numpy as np
import pytest

from carto_cli.commands.map import run_map
from carto_cli.commands.relocalize import RelocalizeRequest, RelocalizeScans, run_relocalize
from carto_cli.commands.render import run_render
from carto_cli.core import transform
from carto_cli.io.map_file import load_map
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.trajectory import read_trajectory
from carto_cli.mapping.alignment import Align, squaring, turned_poses, wall_axes
from carto_cli.options import load_options
from carto_cli.pipeline import MapRequest, build
from carto_cli.sim import loop_building, loop_trajectory, simulate
from carto_cli.sim.trajectory import Trajectory
from carto_cli.sim.world import office

START = 1000.0  # the simulation's clock


def _office_run(heading_deg: float):
    """The office (walls along the world's axes) driven from a first leg at ``heading_deg``: the map's frame, the
    robot's first pose, is that far from square."""
    world = office(rooms_per_side=2)
    start = np.array([0.6, 0.4])
    a = math.radians(heading_deg)
    first = start + 1.2 * np.array([math.cos(a), math.sin(a)])
    trajectory = Trajectory.follow(np.vstack([start, first, world.route[1:]]))
    return simulate(world, trajectory, scan_rate=5.0), trajectory


@pytest.fixture(scope="module")
def turned(tmp_path_factory):
    base = tmp_path_factory.mktemp("align")
    sim, trajectory = _office_run(30.0)
    bag = base / "office.bag"
    write_recording(iter(list(sim.records(["/scan", "/odom"]))), bag, "ros1")
    runs = {align: run_map(MapRequest(bag, load_options(), align=align), base / align) for align in Align}
    return bag, trajectory, runs


def _quarter_mean_deg(angles: np.ndarray) -> float:
    """The circular mean of directions modulo 90° (degrees)."""
    return math.degrees(np.angle(np.mean(np.exp(4j * angles))) / 4)


def test_auto_turns_the_map_square_to_the_building(turned):
    _, trajectory, runs = turned
    result, outputs = runs[Align.AUTO]
    assert result.alignment is not None and result.alignment.rotation != 0.0
    assert math.degrees(result.alignment.rotation) == pytest.approx(30.0, abs=2.0)  # the start's turn, SLAM's error
    # In the turned frame every heading is the world's, whose walls run along the axes, to within half a degree
    saved = read_trajectory(outputs.trajectory)
    truth = trajectory.poses(saved.t - START)
    assert abs(_quarter_mean_deg(saved.poses[:, 2] - truth[:, 2])) < 0.5
    # and the walls of the written image along its axes: aligning it again would leave it as it is
    assert squaring(wall_axes(result.image)).rotation == 0.0
    summary = json.loads(outputs.summary.read_text())
    assert summary["align"]["rotation_deg"] == pytest.approx(math.degrees(result.alignment.rotation))
    assert load_map(outputs.state).metadata.stats["aligned_deg"] == pytest.approx(summary["align"]["rotation_deg"])


def test_every_output_in_the_map_frame_turns_together(turned):
    _, _, runs = turned
    (auto, auto_out), (_, none_out) = runs[Align.AUTO], runs[Align.NONE]
    rotation = auto.alignment.rotation
    np.testing.assert_allclose(read_trajectory(auto_out.trajectory).poses,
                               turned_poses(read_trajectory(none_out.trajectory).poses, rotation), atol=1e-6)
    a, n = load_map(auto_out.state), load_map(none_out.state)
    np.testing.assert_allclose(a.node_global_poses, turned_poses(n.node_global_poses, rotation), atol=1e-9)
    np.testing.assert_allclose(a.submap_global_poses, turned_poses(n.submap_global_poses, rotation), atol=1e-9)
    # local SLAM's poses, the odometry and the constraints are in frames of their own
    np.testing.assert_array_equal(a.node_local_poses, n.node_local_poses)
    np.testing.assert_array_equal(a.node_odometry, n.node_odometry)
    np.testing.assert_array_equal(a.constraints.relative, n.constraints.relative)
    # the state's nodes where the trajectory has their scans
    np.testing.assert_allclose(a.node_global_poses, a.trajectory.poses[a.node_scans], atol=1e-9)
    # loop-closure segments, drawn in map.png, turned as the nodes
    np.testing.assert_allclose(auto.loop_closures[:, :2], a.node_global_poses[a.constraints.node[
        a.constraints.is_loop_closure], :2], atol=1e-9)


def test_the_saved_turned_state_renders_the_written_map(turned, tmp_path):
    _, _, runs = turned
    _, outputs = runs[Align.AUTO]
    mapdir = outputs.state.parent
    done = run_render(outputs.state, tmp_path / "r", pbstream=True)
    assert done.image_file.read_bytes() == (mapdir / "map.pgm").read_bytes()
    assert (tmp_path / "r" / "map.yaml").read_text() == (mapdir / "map.yaml").read_text()
    # Cartographer's state written from it holds the turned frame too
    again = run_render(done.pbstream, tmp_path / "again")
    assert again.image_file.read_bytes() == (mapdir / "map.pgm").read_bytes()


def test_relocalizing_in_the_turned_map_answers_in_its_frame(turned):
    bag, _, runs = turned
    answers = {}
    for align in Align:
        _, outputs = runs[align]
        # a scan in a room (in the corridor the two rooms' doors look alike: ambiguous in either frame)
        run = run_relocalize(RelocalizeScans(RelocalizeRequest(outputs.state, bag), scan_index=160,
                                             global_search=True))
        saved = read_trajectory(outputs.trajectory)
        mapped = saved.poses[int(np.argmin(np.abs(saved.t - run.scan.time)))]
        assert run.result.success
        gap = transform.relative(mapped, run.result.pose)
        assert math.hypot(gap[0], gap[1]) < 0.1 and abs(math.degrees(gap[2])) < 1.0
        answers[align] = run.result.pose
    # the two answers are the same place in two frames: the turn apart
    turn = math.degrees(transform.wrap_angle(answers[Align.AUTO][2] - answers[Align.NONE][2]))
    assert turn == pytest.approx(math.degrees(runs[Align.AUTO][0].alignment.rotation), abs=1.0)


def test_none_keeps_the_frame_mapping_made(turned):
    bag, _, runs = turned
    result, outputs = runs[Align.NONE]
    assert result.alignment is None and "aligned_deg" not in result.stats
    assert "align" not in json.loads(outputs.summary.read_text())
    from carto_cli.io.sources.open import open_recording

    with open_recording(bag) as recording:
        made = build(recording, load_options())
    np.testing.assert_array_equal(result.poses, made.poses)


def test_a_map_square_already_is_written_as_without_align(tmp_path):
    """The loop building's first stretch, driven along its walls, maps within the dead band: the frame and every
    map output stay as --align none writes them. (The office above, driven from along its corridor, is not: its
    map comes out a degree off, which auto does turn.)"""
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=30.0, scan_rate=5.0)
    runs = {align: run_map(MapRequest(sim.recording(), load_options(), align=align), tmp_path / align, state=False)
            for align in Align}
    auto, auto_out = runs[Align.AUTO]
    assert auto.alignment is not None and auto.alignment.rotation == 0.0
    assert auto.alignment.describe().startswith("already square")
    for name in ("map.pgm", "map.yaml", "map.png", "trajectory.tum"):
        assert (auto_out.pgm.parent / name).read_bytes() == (tmp_path / "none" / name).read_bytes(), name
