"""The SLAM core object on its own: measurements in, map out, no file or recording involved."""
import threading
import time

import numpy as np
import pytest

from carto_cli.core.records import Imu, Odometry, Scan
from carto_cli.mapping.slam import Slam
from carto_cli.options import load_options
from carto_cli.pipeline import build
from carto_cli.sim import loop_building, loop_trajectory, simulate


@pytest.fixture(scope="module")
def simulation():
    world = loop_building()
    return simulate(world, loop_trajectory(world), duration=15.0, beams=270, laser_pose=(0.15, 0.0, 0.0))


def test_fed_by_hand_it_maps_exactly_as_the_pipeline(simulation):
    options = load_options("wheeled")
    with simulation.recording() as rec:
        records = list(rec.records())
        from_pipeline = build(rec, options)
    slam = Slam(options, laser_pose=simulation.laser_pose)
    for record in records:
        if isinstance(record, Scan):
            slam.add_scan(record)
        elif isinstance(record, Odometry):
            slam.add_odometry(record)
        elif isinstance(record, Imu) and options.trajectory_builder_2d.use_imu_data:
            slam.add_imu(record)
    result = slam.finish()
    assert slam.num_scans == from_pipeline.stats["scans"] and result.stats["nodes"] == from_pipeline.stats["nodes"]
    np.testing.assert_array_equal(result.times, from_pipeline.times)
    np.testing.assert_array_equal(result.poses, from_pipeline.poses)
    np.testing.assert_array_equal(result.image.probability, from_pipeline.image.probability)


def test_every_posed_scan_follows_the_first_node(simulation):
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, loop_closure=False)
    with simulation.recording() as rec:
        scans = [r for r in rec.records() if isinstance(r, Scan)][:30]
    for scan in scans:
        slam.add_scan(scan)
    result = slam.finish()
    assert 0 < len(result.times) <= len(scans) and result.node_scans[0] == 0
    assert np.all(np.diff(result.times) > 0)


def test_finishing_without_a_pose_is_an_error():
    with pytest.raises(ValueError, match="no scan got a pose"):
        Slam(load_options(None)).finish()


def test_an_error_on_the_graphs_thread_reaches_the_caller(simulation, monkeypatch):
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, jobs=2)

    def broken(*args, **kwargs):
        raise RuntimeError("graph failed")

    monkeypatch.setattr(slam.graph, "add_node", broken)
    with simulation.recording() as rec:
        scans = [r for r in rec.records() if isinstance(r, Scan)][:20]
    with pytest.raises(RuntimeError, match="graph failed"):
        for scan in scans:
            slam.add_scan(scan)
        slam.finish()
    slam.close()  # after the error: nothing left running, nothing raised twice


def test_closing_after_a_failure_drops_the_nodes_the_graph_has_not_started(simulation, monkeypatch):
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, jobs=2)
    started = []
    release = threading.Event()

    def slow(*args, **kwargs):
        started.append(1)
        release.wait(5)

    monkeypatch.setattr(slam.graph, "add_node", slow)
    with simulation.recording() as rec:
        scans = [r for r in rec.records() if isinstance(r, Scan)][:60]
    for scan in scans:
        slam.add_scan(scan)
    background = slam._background
    while not started:  # the graph's thread is inside the first node
        time.sleep(0.001)
    closer = threading.Thread(target=slam.close, kwargs={"abandon": True})
    closer.start()
    while not background._abandoned:  # close() gives up on the queue before it waits
        time.sleep(0.001)
    release.set()
    closer.join(10)
    assert started == [1] and slam.num_poses > 1  # the node being added finished; the queued ones were dropped
