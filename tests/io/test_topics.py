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


def _two_lasers(static: bool = True, third: str | None = None):
    """A recording with front and back LaserScan topics (and ``third``, a PointCloud2-free extra scan topic on the
    front laser's frame), each laser placed by static TF when ``static``."""
    import numpy as np

    from carto_cli.core.records import Scan, Transform, yaw_quaternion
    from carto_cli.io.sources.memory import MemoryRecording

    def scan(t, topic, frame):
        return Scan(t, np.ones(3, np.float32), np.zeros(3, np.float32), frame, topic, range_max=10.0)

    records = [scan(0.1 * k, "/front", "laser_front") for k in range(3)]
    records += [scan(0.1 * k + 0.05, "/back", "laser_back") for k in range(3)]
    if third:
        records += [scan(0.1 * k + 0.02, third, "laser_front") for k in range(3)]
    statics = [Transform("base_link", "laser_front", (0.3, 0.0, 0.0), yaw_quaternion(0.0)),
               Transform("base_link", "laser_back", (-0.3, 0.0, 0.0), yaw_quaternion(3.14159))] if static else []
    return MemoryRecording(records, statics)


def test_every_laserscan_topic_when_each_has_its_frame_and_mount():
    sel = select_topics(_two_lasers())
    assert sel.scan_topics == ("/back", "/front") and sel.frame == "base_link"
    mounts = {x.topic: x.mount for x in sel.lasers}
    assert mounts["/front"] == pytest.approx((0.3, 0.0, 0.0)) and mounts["/back"][0] == pytest.approx(-0.3)
    assert "2 lasers merged in base_link" in sel.describe_lasers() and "static TF" in sel.describe_lasers()
    assert set(sel.topics) == {"/back", "/front"}


def test_several_lasers_without_mounts_or_on_one_frame_are_not_merged_unasked():
    with pytest.raises(TopicError, match="several scan topics.*--scan-topic A --scan-topic B"):
        select_topics(_two_lasers(static=False))
    with pytest.raises(TopicError, match="several scan topics"):
        select_topics(_two_lasers(third="/front_filtered"))
    # Mounts given by the user are enough
    sel = select_topics(_two_lasers(static=False), laser_poses={"/front": (0.3, 0.0, 0.0), "back": (-0.3, 0.0, 3.1)})
    assert {x.topic: x.source for x in sel.lasers} == {"/back": "--laser-pose", "/front": "--laser-pose"}


def test_lasers_named_by_the_user_and_their_poses():
    sel = select_topics(_two_lasers(third="/front_filtered"), ["/front_filtered", "/back"])
    assert sel.scan_topics == ("/front_filtered", "/back")
    assert select_topics(_two_lasers(), "/front").lasers == ()  # one topic named: one laser, as before
    with pytest.raises(TopicError, match="not a scan topic mapped"):
        select_topics(_two_lasers(), ["/front", "/back"], laser_poses={"/side": (0.0, 0.0, 0.0)})
    with pytest.raises(TopicError, match="give each one's --laser-pose as TOPIC=x,y,yaw"):
        select_topics(_two_lasers(), ["/front", "/back"], laser_poses={None: (0.0, 0.0, 0.0)})
    # A laser named without a mount is not guessed at the robot's origin
    with pytest.raises(TopicError, match="no mount known for /back"):
        select_topics(_two_lasers(static=False), ["/front", "/back"], laser_poses={"/front": (0.3, 0.0, 0.0)})


def test_merged_scans_reach_whoever_reads_the_selection():
    from carto_cli.io.topics import selected_records

    sel = select_topics(_two_lasers())
    scans = list(selected_records(_two_lasers(), sel))
    assert [s.topic for s in scans] == ["/back+/front"] * 3  # front then back, three times: three windows
    assert sum(s.num_beams for s in scans) == 18
