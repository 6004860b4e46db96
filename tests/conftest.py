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
