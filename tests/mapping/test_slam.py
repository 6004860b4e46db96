"""The SLAM core object on its own: measurements in, map out, no file or recording involved."""
import threading
import time

import numpy as np
import pytest

from carto_cli.core import kernels
from carto_cli.core.errors import CartoError
from carto_cli.core.records import Imu, Odometry, Scan
from carto_cli.mapping import graph_runner
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.slam import Slam
from carto_cli.options import load_options
from carto_cli.pipeline import build
from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate


@pytest.fixture(scope="module")
def simulation():
    # The graph's warm-up adds nodes: run it before a test replaces PoseGraph.add_node, whichever test runs first.
    kernels.warm_up(systems=("cartographer",))
    world = loop_building()
    return simulate(world, loop_trajectory(world), duration=15.0, lidar=Lidar(beams=270), laser_pose=(0.15, 0.0, 0.0))


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
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, jobs=2, process=False)
    assert slam.graph_runs == "thread"

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
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, jobs=2, process=False)
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
    runner = slam.runner
    while not started:  # the graph's thread is inside the first node
        time.sleep(0.001)
    closer = threading.Thread(target=slam.close, kwargs={"abandon": True})
    closer.start()
    while not runner.abandoned:  # close() gives up on the queue before it waits
        time.sleep(0.001)
    release.set()
    closer.join(10)
    assert started == [1] and slam.num_poses > 1  # the node being added finished; the queued ones were dropped


def _feed(slam, records, limit=None):
    scans = 0
    for record in records:
        if isinstance(record, Scan):
            if limit is not None and scans == limit:
                break
            slam.add_scan(record)
            scans += 1
        elif isinstance(record, Odometry):
            slam.add_odometry(record)
    return slam


def test_the_graph_in_a_process_of_its_own_builds_the_same_map():
    world = loop_building()
    sim = simulate(world, loop_trajectory(world, laps=2), scan_rate=5.0, seed=0)  # closes its loop
    options = load_options(None, ["pose_graph.constraint_builder.fast_correlative_scan_matcher.multilevel=true"])
    with sim.recording() as rec:
        records = list(rec.records())
    alone = _feed(Slam(options, laser_pose=sim.laser_pose, jobs=1), records)
    beside = _feed(Slam(options, laser_pose=sim.laser_pose, jobs=2), records)
    assert alone.graph_runs == "inline" and beside.graph_runs == "process"
    one, two = alone.finish(), beside.finish()
    assert one.stats["loop_closures"] > 0
    for key in ("nodes", "submaps", "constraints", "loop_closures", "optimizations", "loop_closure_searches",
                "precomputations"):
        assert one.stats[key] == two.stats[key], key
    np.testing.assert_array_equal(one.poses, two.poses)
    np.testing.assert_array_equal(one.submap_poses, two.submap_poses)
    np.testing.assert_array_equal(one.image.probability, two.image.probability)
    for column in ("submap", "node", "relative", "is_loop_closure"):
        np.testing.assert_array_equal(getattr(one.graph.constraints, column), getattr(two.graph.constraints, column))
    assert two.stats["graph_process_peak_memory_mb"] > 0 and one.stats["graph_process_peak_memory_mb"] == 0
    # the caller's graph holds local SLAM's own submaps again (which took scans), not the process's stand-ins
    assert all(submap.num_range_data > 0 for submap in two.submaps)


def test_an_error_in_the_graphs_process_reaches_the_caller(simulation, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("graph failed")

    monkeypatch.setattr(PoseGraph, "add_node", broken)  # before the fork: the child has it too
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, jobs=2)
    assert slam.graph_runs == "process"
    with simulation.recording() as rec:
        _feed(slam, rec.records(), limit=20)
    with pytest.raises(RuntimeError, match="graph failed"):
        slam.finish()
    slam.close()  # nothing left running, nothing raised twice


def test_an_interrupt_in_the_graphs_process_reaches_the_caller_as_one(simulation, monkeypatch):
    """A SIGTERM of the child's own (`timeout` signals the whole group) lands in a kernel, which numba reports as a
    SystemError around the KeyboardInterrupt; the pickle that carries it over would drop that cause."""
    def interrupted(*args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise SystemError("CPUDispatcher(<function _match>) returned a result with an exception set") from e

    monkeypatch.setattr(PoseGraph, "add_node", interrupted)  # before the fork: the child has it too
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, jobs=2)
    assert slam.graph_runs == "process"
    with simulation.recording() as rec:
        _feed(slam, rec.records(), limit=20)
    with pytest.raises(KeyboardInterrupt):
        slam.finish()
    slam.close()


def test_an_early_error_in_the_graphs_process_stops_mapping_with_that_error(simulation, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("graph failed")

    monkeypatch.setattr(PoseGraph, "add_node", broken)
    monkeypatch.setattr(graph_runner, "BACKLOG", 1)  # the queue fills at once: mapping notices the child is gone
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, jobs=2)
    with simulation.recording() as rec, pytest.raises(RuntimeError, match="graph failed"):
        _feed(slam, rec.records(), limit=100)
    slam.close(abandon=True)


def test_a_graph_process_that_dies_is_a_clear_error(simulation):
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, jobs=2)
    with simulation.recording() as rec:
        _feed(slam, rec.records(), limit=20)
    slam.runner.child.kill()
    with pytest.raises(CartoError, match="pose graph's process ended unexpectedly, exit code -9"):
        slam.finish()


def test_abandoning_stops_the_graphs_process_at_once(simulation):
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose, jobs=2)
    child = slam.runner.child
    with simulation.recording() as rec:
        _feed(slam, rec.records(), limit=60)
    slam.close(abandon=True)
    assert not child.is_alive()


def test_add_scan_says_which_scans_became_nodes(simulation):
    slam = Slam(load_options("wheeled"), laser_pose=simulation.laser_pose)
    became = 0
    with simulation.recording() as rec:
        for record in rec.records():
            if isinstance(record, Scan):
                became += slam.add_scan(record) is True
            elif isinstance(record, Odometry):
                slam.add_odometry(record)
    result = slam.finish()
    assert 0 < became == result.stats["nodes"] < result.stats["scans"]
