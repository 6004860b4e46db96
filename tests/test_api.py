"""carto_cli.api, the documented Python surface: a map from arrays equals the command line's map of the same
data written as a bag; relocalize and evaluate through it."""
import math

import numpy as np
import pytest
from typer.testing import CliRunner

from carto_cli import api
from carto_cli.cli import app
from carto_cli.core.records import Odometry, Scan
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.sources.messages import ns_to_seconds, seconds_to_ns
from carto_cli.io.trajectory import Trajectory, write_trajectory
from carto_cli.sim import loop_building, loop_trajectory, simulate


@pytest.fixture(scope="module")
def drive():
    w = loop_building()
    sim = simulate(w, loop_trajectory(w), duration=25.0, scan_rate=10.0, laser_pose=(0.1, 0.0, 0.0))
    return sim, list(sim.records(["/scan", "/odom"]))


def _as_arrays(records):
    """What a program holds: plain arrays and numbers, turned into records by the API's own constructors; times
    on the nanosecond grid a bag stores them on, so the bag written from them holds exactly the same."""
    out = []
    for r in records:
        t = ns_to_seconds(seconds_to_ns(r.time))
        if isinstance(r, Scan):
            out.append(api.scan(t, np.asarray(r.ranges, dtype=np.float64), angle_min=r.angle_min,
                                angle_increment=r.angle_increment, range_min=r.range_min, range_max=r.range_max))
        elif isinstance(r, Odometry):
            out.append(api.odometry(t, r.x, r.y, r.yaw))
    return out


def test_a_map_from_arrays_is_the_command_lines_map(drive, tmp_path):
    sim, records = drive
    arrays = _as_arrays(records)
    run = api.map_records(arrays, laser_pose=(0.1, 0.0, 0.0), profile="wheeled")
    assert run.quality == "ok" and run.poses.shape == (250, 3)
    outputs = run.write(tmp_path / "api")
    # The same scans and odometry written as a bag, the laser mount as static TF: what a robot would record.
    bag = tmp_path / "drive.bag"
    write_recording(iter(sorted(arrays, key=lambda r: r.time)), bag, "ros1", static_transforms=sim.static_transforms)
    r = CliRunner().invoke(app, ["map", str(bag), "-o", str(tmp_path / "cli"), "--profile", "wheeled"])
    assert r.exit_code == 0, r.output
    assert outputs.trajectory.read_bytes() == (tmp_path / "cli" / "trajectory.tum").read_bytes()
    assert outputs.pgm.read_bytes() == (tmp_path / "cli" / "map.pgm").read_bytes()
    with pytest.raises(api.CartoError, match="already holds a map"):
        run.write(tmp_path / "api")


def test_map_recording_relocalize_and_evaluate(drive, tmp_path):
    sim, records = drive
    bag = tmp_path / "drive.bag"
    write_recording(iter(records), bag, "ros1", static_transforms=sim.static_transforms)
    run = api.map_recording(bag, outdir=tmp_path / "m")  # auto
    assert run.result.auto is not None and run.options.trajectory_builder_2d.max_range > 0
    scan = next(r for r in records if isinstance(r, Scan) and r.time >= 1020.0)
    k = int(round((scan.time - 1000.0) * 10))
    answer = api.relocalize(tmp_path / "m" / "map.carto", scan, prior=run.poses[k] + [0.3, -0.2, 0.05])
    assert answer.verdict == "ok" and np.hypot(*(answer.pose[:2] - run.poses[k][:2])) < 0.05
    (tmp_path / "self.relations").write_text(
        "".join(f"{run.result.times[i]} {run.result.times[i + 10]} 0 0 0 0 0 0\n" for i in range(0, 200, 50)))
    report = api.evaluate(tmp_path / "m" / "trajectory.tum", relations=tmp_path / "self.relations")
    assert report.relations is not None
    assert math.isfinite(report.relations.translation.mean)


def test_map_recordings_makes_one_map_of_several(drive, tmp_path):
    sim, records = drive
    bag = tmp_path / "drive.bag"
    write_recording(iter(records), bag, "ros1", static_transforms=sim.static_transforms)
    run = api.map_recordings([bag, bag])  # the same drive twice
    assert [(s.trajectory, s.name, s.linked) for s in run.sessions] == [(0, "drive.bag", True), (1, "drive.bag", True)]
    assert np.max(np.hypot(*(run.sessions[0].poses[:, :2] - run.sessions[1].poses[:, :2]).T)) < 0.3
    assert run.recordings == ("drive.bag", "drive.bag") and len(run.result.links) == 1
    with pytest.raises(api.CartoError, match="no recording"):
        api.map_recordings([])
    run.write(tmp_path / "ab")
    truth = tmp_path / "truth.tum"
    gt = sim.ground_truth
    write_trajectory(truth, Trajectory.from_arrays(gt[:, 0], gt[:, 1], gt[:, 2], gt[:, 3]), fmt="tum")
    both = api.evaluate_sessions([tmp_path / "ab" / "trajectory_0.tum", tmp_path / "ab" / "trajectory_1.tum"], [truth])
    # One alignment for both: the same drive twice, so the same small error twice
    assert len(both) == 2 and both[0].alignment == both[1].alignment
    assert max(r.translation.rmse for r in both) < 0.3
    assert abs(both[0].translation.rmse - both[1].translation.rmse) < 0.1


def test_merge_maps_lays_a_map_on_itself(drive, tmp_path):
    sim, records = drive
    bag = tmp_path / "drive.bag"
    write_recording(iter(records), bag, "ros1", static_transforms=sim.static_transforms)
    api.map_recording(bag, outdir=tmp_path / "a")
    run = api.merge_maps([tmp_path / "a" / "map.carto"] * 2, jobs=1)  # the same map twice
    assert [(s.trajectory, s.name, s.linked) for s in run.sessions] == [(0, "drive.bag", True), (1, "drive.bag", True)]
    assert np.max(np.hypot(*(run.sessions[0].poses[:, :2] - run.sessions[1].poses[:, :2]).T)) < 0.05
    assert len(run.result.links) == 1 and run.quality == "ok"
    run.write(tmp_path / "m")
    assert (tmp_path / "m" / "trajectory_1.tum").is_file()
    with pytest.raises(api.CartoError, match="two maps or more"):
        api.merge_maps([tmp_path / "a" / "map.carto"])
    with pytest.raises(api.CartoError, match="no such file"):
        api.merge_maps([tmp_path / "a" / "map.carto", tmp_path / "none.carto"])


def test_bad_input_is_a_carto_error(tmp_path):
    with pytest.raises(api.CartoError, match="no scans"):
        api.map_records([api.odometry(0.0, 0.0, 0.0, 0.0)])
    with pytest.raises(api.CartoError):
        api.options("no-such-profile")
