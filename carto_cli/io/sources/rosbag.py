"""ROS1 ``.bag`` files and ROS2 bag directories (sqlite3 and mcap storage), read with rosbags."""
from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator
from pathlib import Path

from carto_cli.core.errors import CartoError, FormatError, TopicError
from carto_cli.core.records import Record, Transform
from carto_cli.io.recording import ReadOptions, Recording, TopicInfo, kind_of, normalise_type
from carto_cli.io.sources import messages
from carto_cli.io.sources.decode_errors import translate_errors
from carto_cli.io.sources.definitions import DefinitionFormat, check_type_name, checked_types


def _check_sqlite_size(db: Path) -> None:
    """Refuse a cut .db3: SQLite reads missing pages as zeros, so it would yield made-up messages."""
    try:
        with open(db, "rb") as f:
            head = f.read(100)
            size = f.seek(0, 2)
    except OSError as e:
        raise FormatError(f"cannot read {db.name}: {e.strerror}", db.parent) from e
    if len(head) < 100 or not head.startswith(b"SQLite format 3\0"):
        raise FormatError(f"corrupt or truncated ROS2 bag: {db.name} is not an SQLite database", db.parent)
    page_size = int.from_bytes(head[16:18], "big")
    page_size = 65536 if page_size == 1 else page_size
    change_counter, page_count, valid_for = (int.from_bytes(head[i:i + 4], "big") for i in (24, 28, 92))
    # The header's page count is only trustworthy when written by SQLite >= 3.7.0 (valid_for matches).
    if valid_for == change_counter and page_count and size < page_count * page_size:
        raise FormatError(
            f"corrupt or truncated ROS2 bag: {db.name} has {size} bytes of its {page_count * page_size}",
            db.parent)


def _checked_on_open(sub_reader) -> None:
    """Make ``sub_reader`` check and modernise its definitions when it opens, before AnyReader builds a typestore
    (and so Python source) from them: every definition passes definitions.checked_types first.

    Bags recorded before ROS Groovy embed ``Header`` as ``MSG: roslib/Header``;
    rosbags then resolves ``Header`` to a std_msgs/Header nobody defined. The
    fields (and so the md5 and the bytes) are the same as std_msgs/Header's.
    """
    from rosbags.interfaces import MessageDefinitionFormat

    formats = {MessageDefinitionFormat.MSG: DefinitionFormat.MSG, MessageDefinitionFormat.IDL: DefinitionFormat.IDL}
    open_ = sub_reader.open

    def open_and_check() -> None:
        open_()
        conns = sub_reader.connections
        for i, c in enumerate(conns):
            d = c.msgdef
            if d.format == MessageDefinitionFormat.MSG and "MSG: roslib/Header" in d.data:
                d = d._replace(data=d.data.replace("MSG: roslib/Header", "MSG: std_msgs/Header"))
                conns[i] = c._replace(msgdef=d)
            if d.format in formats:
                checked_types(d.data, formats[d.format], c.msgtype, c.topic)
            else:  # no definition: the default typestore's, looked up by this name
                check_type_name(c.msgtype, c.topic)

    sub_reader.open = open_and_check


class RosbagRecording(Recording):
    """A ROS1 bag or a ROS2 bag directory opened with ``rosbags.highlevel.AnyReader``."""

    read_ahead = True

    def __init__(self, path: Path, options: ReadOptions | None = None):
        super().__init__(path, options)
        self._reader = None
        self._static: list[Transform] | None = None
        p = self.path
        if not p.exists():
            raise CartoError("no such file or directory", p)
        sources = [p]
        if p.is_dir():
            meta = p / "metadata.yaml"
            text = meta.read_text(errors="replace") if meta.is_file() else ""
            self.format = "ros2-mcap" if "storage_identifier: mcap" in text else "ros2-sqlite3"
            self._what = "ROS2 bag"
            if not meta.is_file():
                # rosbags reads a storage file by itself (topics and types are in it); a split bag's files
                # are read together, merged in time order.
                sources = sorted(p.glob("*.db3")) or sorted(p.glob("*.mcap"))
                if not sources:
                    raise FormatError("directory is not a ROS2 bag (no metadata.yaml, no .db3 or .mcap file)", p)
                self.format = "ros2-sqlite3" if sources[0].suffix == ".db3" else "ros2-mcap"
                self.warnings = [f"{p.name}: no metadata.yaml: read {', '.join(f.name for f in sources)} "
                                 "directly"]
        elif p.suffix == ".db3":
            self.format = "ros2-sqlite3"
            self._what = "ROS2 bag"
        elif p.suffix == ".bag":
            self.format = "ros1"
            self._what = "ROS1 bag"
        else:
            # AnyReader picks ROS1 or ROS2 by the '.bag' suffix alone.
            raise FormatError("a ROS1 bag must have the .bag suffix, and a ROS2 bag is a directory", p)

        if self.format == "ros2-sqlite3":
            for db in sorted(p.glob("*.db3")) if p.is_dir() else [p]:
                _check_sqlite_size(db)
        with self._translate_errors():
            from rosbags.highlevel import AnyReader

            # Used only when a ROS2 bag carries no message definitions (metadata version < 8); ROS1 bags
            # always carry theirs and AnyReader registers them, so a ROS1 run does not build the store
            # (0.1 s of every start-up).
            default = None
            if self.format != "ros1":
                from rosbags.typesys import Stores, get_typestore

                default = get_typestore(Stores.ROS2_HUMBLE)
            reader = AnyReader(sources, default_typestore=default)
            for sub in reader.readers:
                _checked_on_open(sub)
            reader.open()
        self._reader = reader
        self._connections = list(reader.connections)
        self.sources = list(sources)  # what rosbags reads: the bag, or a ROS2 bag's storage files without metadata

    # -- errors ---------------------------------------------------------------

    def _translate_errors(self):
        return translate_errors(self.path, self._what)

    # -- Recording --------------------------------------------------------------

    def topics(self) -> list[TopicInfo]:
        by_topic: dict[str, dict[str, int]] = {}
        for c in self._connections:
            types = by_topic.setdefault(c.topic, {})
            t = normalise_type(c.msgtype)
            types[t] = types.get(t, 0) + int(c.msgcount)
        out = []
        for name, types in sorted(by_topic.items()):
            # A ROS1 topic can have connections of several types; report the commonest.
            msgtype = max(types.items(), key=lambda kv: kv[1])[0]
            out.append(TopicInfo(name=name, msgtype=msgtype, count=sum(types.values())))
        return out

    def static_transforms(self) -> list[Transform]:
        if self._static is None:
            if self._reader is None:
                raise CartoError("recording is closed", self.path)
            conns = [c for c in self._connections if kind_of(c.topic, c.msgtype) == "tf_static"]
            found: list[Transform] = []
            if conns:
                with self._translate_errors():
                    for conn, _, raw in self._reader.messages(connections=conns):
                        found.extend(messages.transforms_from_tf(self._reader.deserialize(raw, conn.msgtype)))
            self._static = messages.merge_static_transforms(found)
        return list(self._static)

    def _selected(self, topics: Iterable[str] | None):
        if topics is None:
            return [c for c in self._connections if messages.is_supported(c.topic, c.msgtype)]
        wanted = list(dict.fromkeys(topics))
        known = {c.topic for c in self._connections}
        for t in wanted:
            if t not in known:
                raise TopicError(f"no topic {t} in the recording", self.path)
        conns = [c for c in self._connections if c.topic in wanted]
        for t in wanted:
            if not any(messages.is_readable(c.topic, c.msgtype) for c in conns if c.topic == t):
                types = sorted({normalise_type(c.msgtype) for c in conns if c.topic == t})
                raise TopicError(f"topic {t} has type {', '.join(types)}, which carto does not read", self.path)
        return [c for c in conns if messages.is_readable(c.topic, c.msgtype)]

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        if self._reader is None:
            raise CartoError("recording is closed", self.path)
        conns = self._selected(topics)  # raised here, not at the first next()
        return self._iter_records(conns)

    def _iter_records(self, conns) -> Iterator[Record]:
        if not conns:
            return
        reader, decoder = self._reader, messages.Decoder(self.options, self.cloud_bands)
        assert reader is not None  # set by __init__, cleared only by close()
        with self._translate_errors():
            for conn, _, raw in reader.messages(connections=conns):
                yield from decoder.to_records(reader.deserialize(raw, conn.msgtype), conn.msgtype, conn.topic)

    def close(self) -> None:
        reader, self._reader = self._reader, None
        if reader is not None:
            with contextlib.suppress(Exception):
                reader.close()
