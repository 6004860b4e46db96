"""Recognise a recording by its path and contents, and open it with the right reader."""
from __future__ import annotations

from pathlib import Path

from carto_cli.core.errors import CartoError, FormatError
from carto_cli.io.recording import ReadOptions, Recording

_BAG_MAGIC = b"#ROSBAG V2.0"
_MCAP_MAGIC = b"\x89MCAP"
_GZIP_MAGIC = b"\x1f\x8b"

FORMATS = ("ros1", "ros2-sqlite3", "ros2-mcap", "mcap", "carmen")


def detect_format(path: Path) -> str:
    """Name the format of ``path`` or raise a CartoError saying why it is not one carto reads."""
    path = Path(path)
    if not path.exists():
        raise CartoError("no such file or directory", path)
    if path.is_dir():
        meta = path / "metadata.yaml"
        if not meta.exists():
            # A bag whose metadata.yaml was lost (or never written: the recorder was killed) still has its
            # storage files, which name their topics and types themselves.
            if any(path.glob("*.db3")):
                return "ros2-sqlite3"
            if any(path.glob("*.mcap")):
                return "ros2-mcap"
            raise FormatError("directory is not a ROS2 bag (no metadata.yaml, no .db3 or .mcap file)", path)
        try:
            text = meta.read_text(errors="replace")
        except OSError as e:
            raise FormatError(f"cannot read metadata.yaml: {e.strerror}", path) from e
        if "storage_identifier: mcap" in text:
            return "ros2-mcap"
        if "storage_identifier: sqlite3" in text:
            return "ros2-sqlite3"
        raise FormatError("ROS2 bag with an unsupported storage plugin (carto reads sqlite3 and mcap)", path)
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError as e:
        raise CartoError(f"cannot read: {e.strerror}", path) from e
    name = path.name.lower()
    if head.startswith(_BAG_MAGIC):
        return "ros1"
    if head.startswith(_MCAP_MAGIC):
        return "mcap"
    if name.endswith(".db3") and (path.parent / "metadata.yaml").exists():
        return detect_format(path.parent)
    if name.endswith(".db3") and head.startswith(b"SQLite format 3"):
        return "ros2-sqlite3"  # one storage file of a ROS2 bag, read without its metadata.yaml
    if head.startswith(_GZIP_MAGIC) or name.endswith((".clf", ".log", ".clf.gz", ".log.gz")):
        return "carmen"
    if name.endswith(".bag"):
        raise FormatError("not a ROS1 bag (missing '#ROSBAG V2.0' header)", path)
    if name.endswith(".mcap"):
        raise FormatError("not an MCAP file (missing magic bytes)", path)
    raise FormatError(
        "unknown recording format (carto reads ROS1 .bag, ROS2 bag directories, .mcap and CARMEN .clf/.log[.gz])",
        path,
    )


def open_recording(path: str | Path, options: ReadOptions | None = None) -> Recording:
    """Open any supported recording; the caller closes it (it is a context manager)."""
    path = Path(path)
    fmt = detect_format(path)
    if path.is_file() and path.suffix.lower() == ".db3" and (path.parent / "metadata.yaml").exists():
        path = path.parent
    if fmt == "ros1":
        from carto_cli.io.sources.ros1_salvage import SalvagedBag
        from carto_cli.io.sources.rosbag import RosbagRecording

        if path.suffix != ".bag":  # a recorder's .bag.active, or a renamed bag: rosbags goes by the suffix
            return SalvagedBag(path, options)
        try:
            return RosbagRecording(path, options)
        except FormatError as e:
            # A cut file or a damaged index: read what its chunks hold.
            return SalvagedBag(path, options, why=e.message.removeprefix("corrupt or truncated ROS1 bag: "))
    if fmt in ("ros2-sqlite3", "ros2-mcap"):
        from carto_cli.io.sources.rosbag import RosbagRecording

        return RosbagRecording(path, options)
    if fmt == "mcap":
        from carto_cli.io.sources.mcap import McapRecording

        return McapRecording(path, options)
    from carto_cli.io.sources.carmen import CarmenRecording

    return CarmenRecording(path, options)
