import pytest

from carto_cli.core.errors import TopicError
from carto_cli.io.recording import Recording, TopicInfo, kind_of, normalise_type
from carto_cli.io.topics import select_topics


class FakeRecording(Recording):
    format = "fake"

    def __init__(self, topics):
        super().__init__("fake.bag")
        self._topics = [TopicInfo(n, t, c) for n, t, c in topics]

    def topics(self):
        return self._topics

    def static_transforms(self):
        return []

    def records(self, topics=None):
        return iter(())


def test_normalise_and_kinds():
    assert normalise_type("sensor_msgs/LaserScan") == "sensor_msgs/msg/LaserScan"
    assert kind_of("/points", "sensor_msgs/PointCloud2") == "scan"
    assert kind_of("/tf_static", "tf2_msgs/msg/TFMessage") == "tf_static"
    assert kind_of("/tf", "tf2_msgs/msg/TFMessage") == "tf"
    assert kind_of("/chatter", "std_msgs/msg/String") == "other"


def test_automatic_when_unambiguous():
    rec = FakeRecording([("/scan", "sensor_msgs/msg/LaserScan", 10), ("/odom", "nav_msgs/msg/Odometry", 50),
                         ("/rosout", "rosgraph_msgs/msg/Log", 3)])
    sel = select_topics(rec)
    assert (sel.scan, sel.odometry, sel.imu) == ("/scan", "/odom", None)


def test_ambiguity_lists_candidates():
    rec = FakeRecording([("/front/scan", "sensor_msgs/msg/LaserScan", 10), ("/rear/scan", "sensor_msgs/msg/LaserScan", 9)])
    with pytest.raises(TopicError) as e:
        select_topics(rec)
    msg = str(e.value)
    assert "--scan-topic" in msg and "/front/scan" in msg and "/rear/scan" in msg and "fake.bag" in msg
    assert select_topics(rec, scan_topic="rear/scan").scan == "/rear/scan"


def test_missing_and_wrong_type():
    rec = FakeRecording([("/scan", "sensor_msgs/msg/LaserScan", 10), ("/chatter", "std_msgs/msg/String", 1)])
    with pytest.raises(TopicError, match="no topic '/nope'"):
        select_topics(rec, scan_topic="/nope")
    with pytest.raises(TopicError, match="not a supported scan type"):
        select_topics(rec, scan_topic="/chatter")
    with pytest.raises(TopicError, match="no laser scan topic"):
        select_topics(FakeRecording([("/chatter", "std_msgs/msg/String", 1)]))


def test_format_preference_breaks_a_tie():
    class Preferring(FakeRecording):
        def preferred_topic(self, kind):
            return "/odom_laser" if kind == "odometry" else None

    rec = Preferring([("/scan", "sensor_msgs/msg/LaserScan", 10), ("/odom", "nav_msgs/msg/Odometry", 50),
                      ("/odom_laser", "nav_msgs/msg/Odometry", 10)])
    assert select_topics(rec).odometry == "/odom_laser"
    assert select_topics(rec, odom_topic="/odom").odometry == "/odom"


def test_the_scan_time_odometry_carto_writes_breaks_a_tie_in_any_recording():
    # A bag converted from a CARMEN log designates nothing, but carries the log's /odom_laser.
    scan = ("/scan", "sensor_msgs/msg/LaserScan", 10)
    rec = FakeRecording([scan, ("/odom", "nav_msgs/msg/Odometry", 50), ("/odom_laser", "nav_msgs/msg/Odometry", 10)])
    assert select_topics(rec).odometry == "/odom_laser"
    other = FakeRecording([scan, ("/odom", "nav_msgs/msg/Odometry", 50), ("/odom2", "nav_msgs/msg/Odometry", 10)])
    with pytest.raises(TopicError, match="several odometry topics, choose one with --odom-topic"):
        select_topics(other)
