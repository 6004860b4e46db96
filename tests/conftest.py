import background
import pytest
from support import STATIC_TF, synthetic_records


def pytest_collection_finish(session):
    """Start the checks that run beside the other tests (tests/background.py) once the tests are chosen; not when
    the tests are only listed (``--collect-only``), where nothing would wait for them."""
    if session.config.option.collectonly:
        return
    for name in dict.fromkeys(m.args[0] for item in session.items for m in item.iter_markers("background")):
        background.start(name)


def pytest_sessionfinish(session, exitstatus):
    background.stop_all()


@pytest.fixture(scope="session")
def written_recordings(tmp_path_factory):
    """The same synthetic records written to every output format (built once per session)."""
    from carto_cli.io.recording_writers import write_recording

    base = tmp_path_factory.mktemp("recordings")
    records = synthetic_records()
    paths = {
        "ros1": base / "synthetic.bag",
        "ros2-sqlite3": base / "synthetic_db3",
        "ros2-mcap": base / "synthetic_mcap",
        "mcap": base / "synthetic.mcap",
    }
    for fmt, path in paths.items():
        write_recording(iter(records), path, fmt, static_transforms=STATIC_TF,
                        topics={"/scan": "sensor_msgs/msg/LaserScan", "/odom": "nav_msgs/msg/Odometry",
                                "/imu": "sensor_msgs/msg/Imu"})
    return records, paths


@pytest.fixture(scope="session")
def merge_parts(tmp_path_factory):
    """`carto merge`'s inputs (tests/commands/test_merge.py, tests/mapping/test_merging.py): one simulated recording
    of the loop building, two laps, cut in the middle (each part's odometry restarted at zero, as after a reboot),
    each part mapped alone as `carto map PART -o DIR` writes it. The two output directories, and the recording's
    reference (m, 4) t, x, y, yaw."""
    from carto_cli.commands.map import run_map
    from carto_cli.pipeline import Auto, MapRequest
    from carto_cli.sim.recording import simulate
    from carto_cli.sim.sessions import cut_sessions
    from carto_cli.sim.trajectory import follow_route
    from carto_cli.sim.world import loop_building

    world = loop_building()
    sim = simulate(world, follow_route(world, laps=2), seed=3)
    t = sim.ground_truth[:, 0]
    root = tmp_path_factory.mktemp("merge")
    dirs = []
    for k, part in enumerate(cut_sessions(sim.recording(), [0.5 * (t[0] + t[-1])])):
        run_map(MapRequest(part, Auto()), root / f"part{k}")
        dirs.append(root / f"part{k}")
    return dirs, sim.ground_truth
