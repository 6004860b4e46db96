"""Choosing which topics feed SLAM: automatic when unambiguous, explicit otherwise.

Several 2D lasers (front and back, say) are mapped together when the user names them (``--scan-topic A
--scan-topic B``) or, with no choice given, when every LaserScan topic has a frame of its own and each frame's
mount on the robot is known (TF, or ``--laser-pose TOPIC=x,y,yaw``): their scans are then merged into one scan of
the tracking frame a window (``sensor.merging``) by :func:`selected_records`, so every reader of the selection
(the survey, mapping, relocalization) sees the same scans.
"""
from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from carto_cli.core import transform
from carto_cli.core.errors import TopicError
from carto_cli.core.records import Record, Transform
from carto_cli.io.recording import SCAN_TIME_ODOMETRY, Recording, TopicInfo, first_scan_frame
from carto_cli.io.tf_odometry import TfOdometry, find_tf_odometry, tf_as_odometry
from carto_cli.io.tf_tree import laser_pose_from_tf
from carto_cli.sensor.merging import Laser, merged_records

# Scan messages of one laser each; a PointCloud2 may be anything (a 3D lidar, a merged cloud) and is never
# merged with others unasked
PLANAR_SCANS = frozenset({"sensor_msgs/msg/LaserScan", "sensor_msgs/msg/MultiEchoLaserScan"})


@dataclass(frozen=True)
class TopicSelection:
    scan: str  # the scan topic; with several lasers, the first of them
    odometry: str | None = None  # an Odometry topic, or the TF topic when ``tf_odometry`` is set
    imu: str | None = None
    tf_odometry: TfOdometry | None = None  # odometry read from dynamic TF (io.tf_odometry)
    # Several lasers mapped together, each with its mount: their scans reach mapping merged (sensor.merging)
    lasers: tuple[Laser, ...] = ()
    frame: str = "base_link"  # the tracking frame merged scans are in

    def describe_odometry(self) -> str:
        if self.tf_odometry is not None:
            return f"from TF {self.tf_odometry.describe()}"
        return self.odometry or "none"

    @property
    def scan_topics(self) -> tuple[str, ...]:
        return tuple(laser.topic for laser in self.lasers) if self.lasers else (self.scan,)

    @property
    def topics(self) -> list[str]:
        return [t for t in (*self.scan_topics, self.odometry, self.imu) if t]

    def describe_lasers(self) -> str:
        """The merged lasers in words (empty for one laser)."""
        if not self.lasers:
            return ""
        return (f"{len(self.lasers)} lasers merged in {self.frame}: "
                + "; ".join(laser.describe() for laser in self.lasers))


def laser_mount(recording: Recording, scan_frame: str | None, explicit,
                fixed_tf: Sequence[Transform] = ()) -> tuple[np.ndarray, str]:
    """Where a laser sits on the robot (x, y, yaw) and where that came from, in words: ``explicit``
    (--laser-pose) wins; else static TF; else transforms of /tf that never moved (``fixed_tf``: a mount broadcast
    on /tf); else the laser is at the tracking frame."""
    pose, source, _ = _mount(recording, scan_frame, explicit, fixed_tf)
    return pose, source


def _mount(recording: Recording, scan_frame: str | None, explicit,
           fixed_tf: Sequence[Transform]) -> tuple[np.ndarray, str, str | None]:
    """:func:`laser_mount`, and the TF frame the mount is in (None: not from TF)."""
    if explicit is not None:
        return transform.as_pose(explicit), "--laser-pose", None
    if scan_frame:
        found = laser_pose_from_tf(recording.static_transforms(), scan_frame)
        if found is not None:
            pose, root = found
            return np.asarray(pose, dtype=np.float64), f"static TF {root} -> {scan_frame}", root
        found = laser_pose_from_tf(list(recording.static_transforms()) + list(fixed_tf), scan_frame)
        if found is not None:
            pose, root = found
            return (np.asarray(pose, dtype=np.float64), f"TF {root} -> {scan_frame} (fixed transforms on /tf)",
                    root)
    return np.zeros(3), IDENTITY_MOUNT, None


IDENTITY_MOUNT = "identity (no static TF for the laser)"


_FLAGS = {"scan": "--scan-topic", "odometry": "--odom-topic", "imu": "--imu-topic"}


def choose_topic(recording: Recording, topics: list[TopicInfo], kind: str, wanted: str | None,
                 required: bool) -> str | None:
    candidates = [t for t in topics if t.kind == kind and t.count > 0]
    if wanted is not None:
        match = {t.name: t for t in topics}.get(_topic_name(topics, wanted))
        if match is None:
            names = ", ".join(t.name for t in candidates) or "none"
            raise TopicError(f"no topic '{wanted}' ({kind} topics: {names})", recording.path)
        if match.kind != kind:
            raise TopicError(
                f"topic '{match.name}' is {match.msgtype}, not a supported {kind} type", recording.path
            )
        return match.name
    if not candidates:
        if required:
            others = ", ".join(f"{t.name} ({t.msgtype})" for t in topics) or "no topics at all"
            raise TopicError(f"no laser scan topic (LaserScan, MultiEchoLaserScan or PointCloud2); found {others}",
                             recording.path)
        return None
    if len(candidates) > 1:
        for preferred in (recording.preferred_topic(kind), SCAN_TIME_ODOMETRY if kind == "odometry" else None):
            if preferred is not None and any(t.name == preferred for t in candidates):
                return preferred
        names = ", ".join(f"{t.name} ({t.count} msgs)" for t in candidates)
        raise TopicError(f"several {kind} topics, choose one with {_FLAGS[kind]}: {names}", recording.path)
    return candidates[0].name


def select_topics(
    recording: Recording,
    scan_topic: str | Sequence[str] | None = None,
    odom_topic: str | None = None,
    imu_topic: str | None = None,
    *,
    odom_frame: str | None = None,
    base_frame: str | None = None,
    laser_poses: Mapping[str | None, Sequence[float]] | None = None,
) -> TopicSelection:
    """The scan, odometry and IMU topics. Without an Odometry topic (or with ``odom_frame`` / ``base_frame``
    given), odometry comes from dynamic TF when /tf carries an odom -> base transform (``io.tf_odometry``).
    ``scan_topic``: one topic or several (several lasers, merged); None: the one scan topic, or every LaserScan
    topic when each has a frame and a known mount of its own. ``laser_poses``: mounts (x, y, yaw) by topic, over
    TF's (None: the one laser's, unnamed)."""
    topics = recording.topics()
    frames: dict[str, str | None] = {}

    def frame_of(topic: str) -> str | None:  # read once a topic: each look opens the recording
        if topic not in frames:
            frames[topic] = first_scan_frame(recording, topic)
        return frames[topic]

    wanted = [scan_topic] if isinstance(scan_topic, str) else list(scan_topic or ())
    poses = {_topic_name(topics, k): v for k, v in (laser_poses or {}).items()}
    if len(wanted) > 1:
        scans = list(dict.fromkeys(_chosen(recording, topics, "scan", w) for w in wanted))
    elif wanted:
        scans = [_chosen(recording, topics, "scan", wanted[0])]
    else:
        scans = _every_laser(recording, topics, poses, frame_of)
    imu = choose_topic(recording, topics, "imu", imu_topic, False)
    if odom_topic is not None and (odom_frame or base_frame):
        raise TopicError("--odom-topic and --odom-frame / --base-frame exclude each other", recording.path)
    odom = None if (odom_frame or base_frame) else choose_topic(recording, topics, "odometry", odom_topic, False)
    tf = None
    if odom is None and odom_topic is None and (odom_frame or base_frame or any(t.kind == "tf" for t in topics)):
        laser = frame_of(scans[0])
        tf = find_tf_odometry(recording, odom_frame=odom_frame, base_frame=base_frame, laser_frame=laser)
    if None in poses and len(scans) > 1:
        raise TopicError(f"{len(scans)} lasers: give each one's --laser-pose as TOPIC=x,y,yaw", recording.path)
    unknown = sorted(k for k in poses if k is not None and k not in scans)
    if unknown:
        raise TopicError(f"--laser-pose for {', '.join(unknown)}, which is not a scan topic mapped "
                         f"({', '.join(scans)})", recording.path)
    selection = TopicSelection(scan=scans[0], odometry=tf.topic if tf is not None else odom, imu=imu,
                               tf_odometry=tf)
    if len(scans) == 1:
        return selection
    lasers, frame = _placed(recording, scans, poses, tf.fixed if tf is not None else (), frame_of)
    return TopicSelection(scan=scans[0], odometry=selection.odometry, imu=imu, tf_odometry=tf, lasers=lasers,
                          frame=frame)


def _topic_name(topics: list[TopicInfo], name):
    """``name`` as the recording spells it (ROS1 users often drop the leading slash); None stays None."""
    if name is None:
        return None
    names = {t.name for t in topics}
    return name if name in names else ("/" + name.lstrip("/") if "/" + name.lstrip("/") in names else name)


def _chosen(recording: Recording, topics: list[TopicInfo], kind: str, wanted: str | None) -> str:
    found = choose_topic(recording, topics, kind, wanted, True)
    assert found is not None  # a required topic that is missing raised TopicError
    return found


def _every_laser(recording: Recording, topics: list[TopicInfo], poses: Mapping,
                 frame_of: Callable[[str], str | None]) -> list[str]:
    """The scan topic, when there is one; else every LaserScan topic, when there are several, nothing else is a
    scan, each has a frame of its own and its mount is known (TF, or ``poses``); else :func:`choose_topic`'s
    answer (the format's preferred topic, or an error naming them)."""
    candidates = [t for t in topics if t.kind == "scan" and t.count > 0]
    if (len(candidates) > 1 and recording.preferred_topic("scan") is None
            and all(t.msgtype in PLANAR_SCANS for t in candidates)):
        frames = [frame_of(t.name) for t in candidates]
        if None not in frames and len(set(frames)) == len(frames) and all(
                t.name in poses or laser_mount(recording, f, None)[1] != IDENTITY_MOUNT
                for t, f in zip(candidates, frames)):
            return [t.name for t in candidates]
    if len(candidates) > 1 and recording.preferred_topic("scan") is None:
        names = ", ".join(f"{t.name} ({t.count} msgs)" for t in candidates)
        raise TopicError(f"several scan topics, choose one with --scan-topic, or map lasers together with "
                         f"--scan-topic A --scan-topic B (mounts from TF or --laser-pose TOPIC=x,y,yaw): {names}",
                         recording.path)
    return [_chosen(recording, topics, "scan", None)]


def _placed(recording: Recording, scans: Sequence[str], poses: Mapping, fixed_tf: Sequence[Transform],
            frame_of: Callable[[str], str | None]) -> tuple[tuple[Laser, ...], str]:
    """Each laser of ``scans`` with its mount (``poses`` over TF), and the tracking frame they are placed in."""
    lasers, roots = [], []
    for topic in scans:
        frame = frame_of(topic)
        if frame is None:
            raise TopicError(f"no scans on {topic}", recording.path)
        mount, source, root = _mount(recording, frame, poses.get(topic), fixed_tf)
        roots.append(root)
        lasers.append(Laser(topic, frame, (float(mount[0]), float(mount[1]), float(mount[2])), source))
    unplaced = [x.topic for x in lasers if x.source == IDENTITY_MOUNT]
    if unplaced:
        # Merged at a wrong mount, two lasers draw two offset maps over each other: never guessed
        raise TopicError(f"no mount known for {', '.join(unplaced)} (no static TF or fixed /tf for its frame): give "
                         "each one's --laser-pose as TOPIC=x,y,yaw", recording.path)
    known = sorted({r for r in roots if r is not None})
    if len(known) > 1:
        raise TopicError(f"the lasers' TF trees have different roots ({', '.join(known)}): their mounts are not in "
                         "one frame; give each one's --laser-pose as TOPIC=x,y,yaw", recording.path)
    return tuple(lasers), known[0] if known else "base_link"


def selected_records(recording: Recording, selection: TopicSelection,
                     topics: Sequence[str] | None = None) -> Iterator[Record]:
    """``recording.records(topics)`` (default: the selection's), with odometry from TF turned into Odometry and
    several lasers' scans merged into one scan a window (``sensor.merging``)."""
    topics = list(selection.topics if topics is None else topics)
    records = recording.records(topics)
    if selection.tf_odometry is not None and selection.odometry in topics:
        records = tf_as_odometry(records, selection.tf_odometry)
    if selection.lasers and all(laser.topic in topics for laser in selection.lasers):
        records = merged_records(records, selection.lasers, selection.frame)
    return records
