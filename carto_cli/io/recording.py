"""The interface every recording source implements, and topic kinds."""
from __future__ import annotations

import itertools
from abc import ABC, abstractmethod
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from carto_cli.core.records import Record, Scan, Transform

# Message types carto understands, by the kind of record they become.
# Names are normalised to the ROS2 form 'pkg/msg/Type' (ROS1 'pkg/Type' is mapped).
SCAN_TYPES = (
    "sensor_msgs/msg/LaserScan",
    "sensor_msgs/msg/MultiEchoLaserScan",
    "sensor_msgs/msg/PointCloud2",
    # Livox's own cloud (a list of points with a time each), read when the recording carries its definition.
    "livox_ros_driver/msg/CustomMsg",
    "livox_ros_driver2/msg/CustomMsg",
)
ODOMETRY_TYPES = ("nav_msgs/msg/Odometry",)
IMU_TYPES = ("sensor_msgs/msg/Imu",)
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")

# carto's name for the odometry a scan carries with it (a CARMEN laser line's robot pose, at the scan's time):
# the CARMEN reader gives it, the writers keep it, and the topic chooser takes it when there are several
# odometry topics, so that a recording carto wrote reads as its source did, in every format.
SCAN_TIME_ODOMETRY = "/odom_laser"


def normalise_type(msgtype: str) -> str:
    """'sensor_msgs/LaserScan' -> 'sensor_msgs/msg/LaserScan' (ROS1 and ROS2 spell it differently)."""
    parts = msgtype.split("/")
    if len(parts) == 2:
        return f"{parts[0]}/msg/{parts[1]}"
    return msgtype


def kind_of(topic: str, msgtype: str) -> str:
    """'scan', 'odometry', 'imu', 'tf_static', 'tf' or 'other'."""
    t = normalise_type(msgtype)
    if t in SCAN_TYPES:
        return "scan"
    if t in ODOMETRY_TYPES:
        return "odometry"
    if t in IMU_TYPES:
        return "imu"
    if t in TF_TYPES:
        return "tf_static" if topic.rstrip("/").endswith("tf_static") else "tf"
    return "other"


@dataclass(frozen=True)
class TopicInfo:
    name: str
    msgtype: str  # normalised, see normalise_type
    count: int

    @property
    def kind(self) -> str:
        return kind_of(self.name, self.msgtype)


@dataclass(frozen=True)
class ReadOptions:
    """How raw messages become records: which points of a PointCloud2 make its 2D scan.

    ``cloud_band`` (trajectory_builder_2d.cloud_band): 'auto' finds the floor and chooses a band above it from the
    first cloud's heights (``sensor.height_band``), the sensor slice [min_z, max_z] when it sees no floor;
    'LOW..HIGH' is a band in metres above the floor; 'sensor' keeps the points within [min_z, max_z] of the sensor
    frame, as Cartographer does. The defaults are trajectory_builder_2d's, so `info`, `convert` and `map` slice a
    cloud alike unless told otherwise (a test keeps them equal)."""

    min_z: float = -0.8
    max_z: float = 2.0
    cloud_band: str = "auto"


def head(recording: Recording, topics: Iterable[str], n: int) -> list[Record]:
    """The first ``n`` records of ``topics``, the reader's stream closed after them (its file handle goes with the
    generator, not at garbage collection)."""
    records = recording.records(topics)
    try:
        return list(itertools.islice(records, n))
    finally:
        close = getattr(records, "close", None)
        if close is not None:
            close()


def first_scan_frame(recording: Recording, topic: str) -> str | None:
    """The frame of the first scan on ``topic`` (None without one)."""
    return next((r.frame for r in head(recording, [topic], 1) if isinstance(r, Scan)), None)


class Recording(ABC):
    """An opened recording. Use as a context manager; ``records`` streams lazily.

    Implementations must stream in constant memory, yield records in time order
    across topics, and turn every decoding failure into a ``FormatError`` naming
    the file.
    """

    format: str = ""  # 'ros1', 'ros2-sqlite3', 'ros2-mcap', 'mcap', 'carmen'

    def __init__(self, path: Path, options: ReadOptions | None = None):
        self.path = Path(path)
        self.options = options or ReadOptions()
        # What the reader had to work around to read the file at all (a damaged bag read without its index);
        # every command that reads the recording shows them.
        self.warnings: list[str] = []
        # The height band each cloud topic's first cloud chose (``io.sources.messages.Decoder``), for `carto info`.
        self.cloud_bands: dict = {}

    @abstractmethod
    def topics(self) -> list[TopicInfo]:
        """Every topic in the recording with its type and message count."""

    @abstractmethod
    def static_transforms(self) -> list[Transform]:
        """Transforms from /tf_static (empty when there are none)."""

    @abstractmethod
    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        """Scan / Odometry / Imu records of the given topics (all supported ones when None), in time order; a
        dynamic TF topic (/tf) asked for by name gives a Transform record per transform it carries."""

    #: Whether a forked child may decode this recording (through :meth:`independent`) while this process maps:
    #: the file readers say so; records a program holds already (nothing to decode) are read where they are, and
    #: so is any reader that does not say it can be opened twice.
    read_ahead = False

    def before_fork(self) -> None:  # noqa: B027 - most readers have nothing to prepare
        """Load here what a forked child reading this recording would otherwise load on its own (a kernel: numba's
        start-up costs a process half a second)."""

    def independent(self) -> Recording:
        """In a forked child: the same recording read through handles of its own, while the parent goes on
        using this one (a file offset shared across fork would move under both). The file readers (the ones
        with ``read_ahead``) are opened again by their own class, from the same path and options."""
        return type(self)(self.path, self.options)

    def preferred_topic(self, kind: str) -> str | None:
        """The topic a format designates for ``kind`` when it has several (the chooser's own convention,
        ``SCAN_TIME_ODOMETRY``, comes after it)."""
        return None

    def close(self) -> None:  # noqa: B027 - a source that holds nothing open keeps this no-op
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
