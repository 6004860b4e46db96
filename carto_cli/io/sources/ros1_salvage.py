"""ROS1 bags whose index cannot be used, read by walking their records from the start.

A recorder killed before it closed the file leaves a ``.bag.active`` with no index (its header's index
position is 0) or a file cut part-way; some writers wrote index records with a wrong length (the CCNY demo
bag of 2010). The index is only a table of contents: every connection and message is also in the chunks,
in order, so the readable part of such a bag is recovered by reading the chunks themselves, as
``rosbag reindex`` does. Nothing is written back: the bag is read as it is.

The walk keeps, for each message, where its bytes are (a chunk and an offset) and its time, not the bytes;
uncompressed chunks are read back from the file, compressed ones (bz2, lz4) decompressed again on demand.
"""
from __future__ import annotations

import bz2
import contextlib
import struct
from array import array
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from carto_cli.core.errors import CartoError, FormatError, TopicError
from carto_cli.core.records import Record, Transform
from carto_cli.io.recording import ReadOptions, Recording, TopicInfo, kind_of, normalise_type
from carto_cli.io.sources import messages
from carto_cli.io.sources.decode_errors import translate_errors
from carto_cli.io.sources.definitions import DefinitionFormat, checked_types, typestore_of

MAGIC = b"#ROSBAG V2.0\n"
OP_MESSAGE, OP_BAG_HEADER, OP_INDEX, OP_CHUNK, OP_CHUNK_INFO, OP_CONNECTION = 2, 3, 4, 5, 6, 7
MAX_HEADER = 1 << 20  # a record header longer than this is garbage, not a header: the walk stops there
CACHED_CHUNKS = 4  # decompressed chunks kept: messages are in time order within a few neighbouring chunks


def _fields(header: bytes) -> dict[str, bytes] | None:
    """A record header's ``name=value`` fields, or None when the bytes are not a header."""
    out: dict[str, bytes] = {}
    p, n = 0, len(header)
    while p < n:
        if p + 4 > n:
            return None
        length = int.from_bytes(header[p:p + 4], "little")
        field = header[p + 4:p + 4 + length]
        if length > n - p - 4 or b"=" not in field:
            return None
        name, value = field.split(b"=", 1)
        out[name.decode("latin-1")] = value
        p += 4 + length
    return out


@dataclass(frozen=True)
class Connection:
    """A connection record as the bag holds it (what a repaired bag needs to write it again)."""

    topic: str
    msgtype: str  # rosbags' form, 'pkg/msg/Type'
    msgdef: str
    md5sum: str
    callerid: str | None
    latching: int | None


@dataclass(frozen=True)
class _Chunk:
    start: int  # file offset of the chunk's data
    stored: int  # bytes of it in the file (fewer than written when the file was cut)
    compression: str
    size: int  # uncompressed size as written


class _Walk:
    """One pass over the file's records: connections, chunks and where every message is."""

    def __init__(self, f, size: int):
        self.connections: dict[int, Connection] = {}
        self.chunks: list[_Chunk] = []
        # per message: time (ns), connection, chunk (-1: a record outside any chunk), offset, length; 8 bytes
        # each (array, not list: a long recording holds millions of messages)
        self.times = array("q")
        self.conns = array("q")
        self.chunk_of = array("q")
        self.offsets = array("q")
        self.lengths = array("q")
        self.cut = False  # the file ends inside a record
        self.garbage_at: int | None = None  # where the walk met bytes that are no record
        self.index_pos = 0
        self._walk(f, size)

    def _walk(self, f, size: int) -> None:
        pos = len(MAGIC)
        while pos < size:
            f.seek(pos)
            head = f.read(4)
            if len(head) < 4:
                self.cut = True
                return
            header_len = int.from_bytes(head, "little")
            if header_len > MAX_HEADER:
                self.garbage_at = pos
                return
            header = f.read(header_len)
            raw_len = f.read(4)
            if len(header) < header_len or len(raw_len) < 4:
                self.cut = True
                return
            fields = _fields(header)
            if fields is None or "op" not in fields:
                self.garbage_at = pos
                return
            data_len = int.from_bytes(raw_len, "little")
            data_start = pos + 8 + header_len
            op = fields["op"][0] if fields["op"] else -1
            if op == OP_INDEX and "count" in fields and fields.get("ver", b"\x01\0\0\0")[:1] == b"\x01":
                # Version 1 index data is 12 bytes per entry; some writers put another figure in data_len.
                data_len = 12 * int.from_bytes(fields["count"][:4], "little")
            available = min(data_len, size - data_start)
            if op == OP_BAG_HEADER:
                self.index_pos = int.from_bytes(fields.get("index_pos", b"\0" * 8)[:8], "little")
            elif op == OP_CHUNK:
                chunk = _Chunk(data_start, available, fields.get("compression", b"none").decode("latin-1"),
                               int.from_bytes(fields.get("size", b"\0\0\0\0")[:4], "little"))
                self.chunks.append(chunk)
                self._walk_chunk(len(self.chunks) - 1, _read_chunk(f, chunk))
            elif op == OP_CONNECTION and available == data_len:
                self._connection(fields, f.read(data_len))
            elif op == OP_MESSAGE and available == data_len:
                self._message(fields, -1, data_start, data_len)
            if available < data_len:
                self.cut = True
                return
            pos = data_start + data_len

    def _walk_chunk(self, index: int, data: bytes) -> None:
        p, n = 0, len(data)
        while p + 4 <= n:
            header_len = int.from_bytes(data[p:p + 4], "little")
            if header_len > MAX_HEADER or p + 8 + header_len > n:
                return
            fields = _fields(data[p + 4:p + 4 + header_len])
            if fields is None or "op" not in fields:
                return
            data_len = int.from_bytes(data[p + 4 + header_len:p + 8 + header_len], "little")
            start = p + 8 + header_len
            if start + data_len > n:
                return  # a record the cut went through
            op = fields["op"][0] if fields["op"] else -1
            if op == OP_CONNECTION:
                self._connection(fields, data[start:start + data_len])
            elif op == OP_MESSAGE:
                self._message(fields, index, start, data_len)
            p = start + data_len

    def _connection(self, fields: dict[str, bytes], data: bytes) -> None:
        inner = _fields(data)
        if inner is None or "conn" not in fields or "type" not in inner:
            return
        conn = int.from_bytes(fields["conn"][:4], "little")
        topic = (fields.get("topic") or inner.get("topic") or b"").decode("utf-8", "replace")
        topic = "/" * topic.startswith("/") + "/".join(x for x in topic.split("/") if x)
        msgtype = normalise_type(inner["type"].decode("utf-8", "replace"))
        msgdef = inner.get("message_definition", b"").decode("utf-8", "replace")
        # Bags recorded before ROS Groovy spell the embedded Header roslib/Header; its fields are std_msgs'.
        msgdef = msgdef.replace("MSG: roslib/Header", "MSG: std_msgs/Header")
        callerid = inner["callerid"].decode("utf-8", "replace") if "callerid" in inner else None
        latching = inner.get("latching", b"").decode("latin-1").strip()
        self.connections.setdefault(conn, Connection(
            topic, msgtype, msgdef, inner.get("md5sum", b"").decode("latin-1"), callerid,
            int(latching) if latching.isascii() and latching.isdigit() else None))

    def _message(self, fields: dict[str, bytes], chunk: int, offset: int, length: int) -> None:
        if "conn" not in fields or "time" not in fields or len(fields["time"]) < 8:
            return
        sec, nsec = struct.unpack("<II", fields["time"][:8])
        self.times.append(sec * 1_000_000_000 + nsec)
        self.conns.append(int.from_bytes(fields["conn"][:4], "little"))
        self.chunk_of.append(chunk)
        self.offsets.append(offset)
        self.lengths.append(length)


def _read_chunk(f, chunk: _Chunk) -> bytes:
    """The chunk's records, as far as the file holds them (a cut compressed chunk gives what decompresses)."""
    f.seek(chunk.start)
    stored = f.read(chunk.stored)
    if chunk.compression == "none":
        return stored
    if chunk.compression == "bz2":
        with contextlib.suppress(OSError, ValueError, EOFError):
            return bz2.BZ2Decompressor().decompress(stored)
        return b""
    if chunk.compression == "lz4":
        import lz4.frame

        with contextlib.suppress(RuntimeError, ValueError, EOFError):
            return lz4.frame.LZ4FrameDecompressor().decompress(stored)
        return b""
    raise FormatError(f"unknown chunk compression '{chunk.compression}'")


class SalvagedBag(Recording):
    """A ROS1 bag read without its index (see the module's docstring); ``warnings`` says what was recovered."""

    format = "ros1"
    read_ahead = True

    def __init__(self, path: Path, options: ReadOptions | None = None, *, why: str | None = None):
        """``why``: what the indexed reader (rosbags) said of the file, when it refused it."""
        super().__init__(path, options)
        self._static: list[Transform] | None = None
        try:
            with open(self.path, "rb") as f:
                if f.read(len(MAGIC)) != MAGIC:
                    raise FormatError("not a ROS1 bag (missing '#ROSBAG V2.0' header)", self.path)
                size = f.seek(0, 2)
                with translate_errors(self.path, "ROS1 bag"):
                    walk = _Walk(f, size)
        except OSError as e:
            raise CartoError(f"cannot read: {e.strerror}", self.path) from e
        times, conns = np.frombuffer(walk.times, np.int64), np.frombuffer(walk.conns, np.int64)
        known = np.isin(conns, np.fromiter(walk.connections, np.int64, len(walk.connections)))
        order = np.flatnonzero(known)
        order = order[np.argsort(times[order], kind="stable")]  # equal stamps keep the file's order
        self._times = times[order]
        self._conns = conns[order]
        self._chunk_of = np.frombuffer(walk.chunk_of, np.int64)[order]
        self._offsets = np.frombuffer(walk.offsets, np.int64)[order]
        self._lengths = np.frombuffer(walk.lengths, np.int64)[order]
        self._connections = walk.connections
        self._chunks = walk.chunks
        if not len(self._times):
            raise FormatError(f"corrupt or truncated ROS1 bag: {why or 'no index'}, and no message could be "
                              "recovered from its chunks", self.path)
        types: dict = {}
        with translate_errors(self.path, "ROS1 bag"):
            for c in self._connections.values():
                if c.msgdef:
                    types.update(checked_types(c.msgdef, DefinitionFormat.MSG, c.msgtype, c.topic))
            self._typestore = typestore_of(types)
        if walk.index_pos == 0:
            why = "no index (the recorder never closed the file)"
        elif walk.cut or walk.index_pos >= size:
            why = f"cut short (the file ends at byte {size}, inside its records or its index)"
        elif why is not None:
            why = f"damaged index ({why})"
        else:
            why = "not named *.bag, which the indexed reader (rosbags) needs"
        ending = f"unreadable bytes from offset {walk.garbage_at} on" if walk.garbage_at is not None else ""
        self.recovery = {"reason": why, "messages": int(len(self._times)), "topics": len(self.topics()),
                         "chunks": len(walk.chunks), "ending": ending}
        self.warnings = [f"{self.path.name}: {why}: read its chunks instead, {len(self._times)} messages "
                         f"recovered" + (f" ({ending})" if ending else "")]

    # -- Recording --------------------------------------------------------------

    def topics(self) -> list[TopicInfo]:
        counts = np.bincount(self._conns) if len(self._conns) else np.zeros(0, np.int64)
        by_topic: dict[str, dict[str, int]] = {}
        for conn, c in self._connections.items():
            n = int(counts[conn]) if conn < len(counts) else 0
            types = by_topic.setdefault(c.topic, {})
            types[c.msgtype] = types.get(c.msgtype, 0) + n
        return [TopicInfo(name=name, msgtype=max(types.items(), key=lambda kv: kv[1])[0], count=sum(types.values()))
                for name, types in sorted(by_topic.items())]

    def static_transforms(self) -> list[Transform]:
        if self._static is None:
            conns = [k for k, c in self._connections.items() if kind_of(c.topic, c.msgtype) == "tf_static"]
            found: list[Transform] = []
            for _, conn, raw in self._raw(conns):
                with translate_errors(self.path, "ROS1 bag"):  # the conversion too (_records says why)
                    msg = self._typestore.deserialize_ros1(raw, self._connections[conn].msgtype)
                    found.extend(messages.transforms_from_tf(msg))
            self._static = messages.merge_static_transforms(found)
        return list(self._static)

    def _selected(self, topics: Iterable[str] | None) -> list[int]:
        conns = self._connections
        if topics is None:
            return [k for k, c in conns.items() if messages.is_supported(c.topic, c.msgtype)]
        wanted = list(dict.fromkeys(topics))
        for t in wanted:
            if not any(c.topic == t for c in conns.values()):
                raise TopicError(f"no topic {t} in the recording", self.path)
            if not any(messages.is_readable(c.topic, c.msgtype) for c in conns.values() if c.topic == t):
                types = sorted({c.msgtype for c in conns.values() if c.topic == t})
                raise TopicError(f"topic {t} has type {', '.join(types)}, which carto does not read", self.path)
        return [k for k, c in conns.items() if c.topic in wanted and messages.is_readable(c.topic, c.msgtype)]

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        conns = self._selected(topics)  # raised here, not at the first next()
        return self._iter_records(conns)

    def _iter_records(self, conns: list[int]) -> Iterator[Record]:
        decoder = messages.Decoder(self.options, self.cloud_bands)
        for _, conn, raw in self._raw(conns):
            yield from self._records(raw, conn, decoder)

    def _records(self, raw: bytes, conn: int, decoder: messages.Decoder) -> list[Record]:
        """One message's records. Its conversion fails inside the same translation as its decoding: a damaged
        connection header can define the type with a field renamed (a flipped byte: `intensities` ->
        `i0tensities`), which decodes and then lacks the field."""
        c = self._connections[conn]
        with translate_errors(self.path, "ROS1 bag"):
            return decoder.to_records(self._typestore.deserialize_ros1(raw, c.msgtype), c.msgtype, c.topic)

    @property
    def connections(self) -> dict[int, Connection]:
        """The bag's connections by id."""
        return dict(self._connections)

    def raw_messages(self) -> Iterator[tuple[int, int, bytes]]:
        """Every recovered message as (connection id, time in ns, serialized bytes), in time order: what a
        repaired copy of the bag holds."""
        for row, conn, raw in self._raw(list(self._connections)):
            yield conn, int(self._times[row]), raw

    def _raw(self, conns: list[int]) -> Iterator[tuple[int, int, bytes]]:
        """Each selected message's row, connection and bytes, in time order."""
        if not conns:
            return
        rows = np.flatnonzero(np.isin(self._conns, np.asarray(conns, np.int64)))
        cache: dict[int, bytes] = {}
        with open(self.path, "rb") as f:
            for i in rows:
                chunk, offset, length = int(self._chunk_of[i]), int(self._offsets[i]), int(self._lengths[i])
                if chunk < 0:
                    f.seek(offset)
                    raw = f.read(length)
                elif self._chunks[chunk].compression == "none":
                    f.seek(self._chunks[chunk].start + offset)
                    raw = f.read(length)
                else:
                    data = cache.get(chunk)
                    if data is None:
                        if len(cache) >= CACHED_CHUNKS:
                            cache.pop(next(iter(cache)))
                        data = cache[chunk] = _read_chunk(f, self._chunks[chunk])
                    raw = data[offset:offset + length]
                yield int(i), int(self._conns[i]), raw
