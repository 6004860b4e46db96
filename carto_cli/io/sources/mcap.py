"""Standalone MCAP files (ROS2 cdr with ros2msg or ros2idl schemas, ROS1 ros1 with ros1msg), read with the mcap
library and decoded by rosbags' typestores from their own schemas, each schema checked first (definitions.py)."""
from __future__ import annotations

import contextlib
import heapq
import io
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path
from typing import Any

from carto_cli.core.errors import CartoError, FormatError, TopicError
from carto_cli.core.records import Record, Transform
from carto_cli.io.recording import ReadOptions, Recording, TopicInfo, kind_of, normalise_type
from carto_cli.io.sources import messages
from carto_cli.io.sources.decode_errors import translate_errors
from carto_cli.io.sources.definitions import DefinitionFormat, checked_types, typestore_of

_MAGIC = b"\x89MCAP0\r\n"


class McapRecording(Recording):
    """An MCAP file decoded from its own schemas, in log-time order."""

    format = "mcap"
    read_ahead = True

    def __init__(self, path: Path, options: ReadOptions | None = None):
        super().__init__(path, options)
        self._static: list[Transform] | None = None
        self._cut = False  # the file ends before its summary: read up to the cut (_CutFile)
        if not self.path.is_file():
            raise CartoError("no such file" if not self.path.exists() else "not a file", self.path)
        self._decoders = _Decoders()
        with self._translate_errors():
            self._channels, self._counts = self._read_index()
        if self._cut:
            n = sum(self._counts.values())
            if not n:
                raise FormatError("truncated MCAP file (no closing magic bytes) with no whole message before the "
                                  "cut", self.path)
            self.warnings = [f"{self.path.name}: cut short (no summary, no closing magic bytes): read up to the "
                             f"cut, {n} messages recovered"]

    # -- errors and plumbing ----------------------------------------------------

    def _translate_errors(self):
        return translate_errors(self.path, "MCAP file")

    @contextlib.contextmanager
    def _open(self):
        from mcap.reader import make_reader

        # A handle per use: the library's linear fallback (files without chunk
        # indexes) reads the stream sequentially, so iterators must not share it.
        with open(self.path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(0)
            head = f.read(len(_MAGIC))
            if size >= 2 * len(_MAGIC):
                f.seek(size - len(_MAGIC))
            tail = f.read(len(_MAGIC))
            if head != _MAGIC:
                raise FormatError("not an MCAP file (missing magic bytes)", self.path)
            self._cut = tail != _MAGIC
            f.seek(0)
            if tail != _MAGIC:
                # The writer was killed or the copy cut short: the summary (written last) is gone, the
                # records before the cut are whole.
                yield _CutFile(f)
            else:
                yield make_reader(f, validate_crcs=True)

    def _read_index(self):
        """Channels as {id: (topic, normalised type)} and message counts by channel id. The schema of every
        channel carto reads is checked here, so a recording that carries a bad definition is refused when opened."""
        with self._open() as reader:
            summary = reader.get_summary()
            channels: dict[int, tuple[str, str]] = {}
            counts: dict[int, int] = {}
            if summary is not None:
                for cid, ch in summary.channels.items():
                    schema = summary.schemas.get(ch.schema_id)
                    channels[cid] = self._indexed(schema, ch)
                if summary.statistics is not None:
                    counts = {cid: int(summary.statistics.channel_message_counts.get(cid, 0)) for cid in channels}
                    return channels, counts
            # No summary or no statistics: count with one pass that decodes nothing.
            for schema, ch, _ in reader.iter_messages(log_time_order=False):
                if ch.id not in channels:
                    channels[ch.id] = self._indexed(schema, ch)
                counts[ch.id] = counts.get(ch.id, 0) + 1
            return channels, counts

    def _indexed(self, schema, channel) -> tuple[str, str]:
        msgtype = normalise_type(schema.name) if schema else ""
        if schema is not None and schema.encoding in _SCHEMA_FORMATS and messages.is_readable(channel.topic, msgtype):
            self._decoders.prepare(schema, channel)  # an encoding carto does not read is refused when decoded
        return channel.topic, msgtype

    # -- Recording --------------------------------------------------------------

    def topics(self) -> list[TopicInfo]:
        by_topic: dict[str, dict[str, int]] = {}
        for cid, (topic, msgtype) in self._channels.items():
            types = by_topic.setdefault(topic, {})
            types[msgtype] = types.get(msgtype, 0) + self._counts.get(cid, 0)
        return [
            TopicInfo(name=name, msgtype=max(types.items(), key=lambda kv: kv[1])[0], count=sum(types.values()))
            for name, types in sorted(by_topic.items())
        ]

    def static_transforms(self) -> list[Transform]:
        if self._static is None:
            wanted = sorted({t for t, ty in self._channels.values() if kind_of(t, ty) == "tf_static"})
            found: list[Transform] = []
            if wanted:
                with self._translate_errors(), self._open() as reader:
                    decode = self._decoders
                    for schema, channel, message in _in_log_time_order(reader, wanted):
                        if kind_of(channel.topic, schema.name if schema else "") == "tf_static":
                            found.extend(messages.transforms_from_tf(decode(schema, channel, message)))
            self._static = messages.merge_static_transforms(found)
        return list(self._static)

    def _selected(self, topics: Iterable[str] | None) -> list[str]:
        if topics is None:
            return sorted({t for t, ty in self._channels.values() if messages.is_supported(t, ty)})
        wanted = list(dict.fromkeys(topics))
        for t in wanted:
            types = sorted({ty for topic, ty in self._channels.values() if topic == t})
            if not types:
                raise TopicError(f"no topic {t} in the recording", self.path)
            if not any(messages.is_readable(t, ty) for ty in types):
                raise TopicError(f"topic {t} has type {', '.join(types)}, which carto does not read", self.path)
        return wanted

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        return self._iter_records(self._selected(topics))  # topic errors raised here, not at next()

    def _iter_records(self, topics: list[str]) -> Iterator[Record]:
        if not topics:
            return
        decoder = messages.Decoder(self.options, self.cloud_bands)
        with self._translate_errors(), self._open() as reader:
            decode = self._decoders
            for schema, channel, message in _in_log_time_order(reader, topics):
                msgtype = schema.name if schema is not None else ""
                if not messages.is_readable(channel.topic, msgtype):
                    continue  # another channel of a mixed-type topic: not worth decoding
                yield from decoder.to_records(decode(schema, channel, message), msgtype, channel.topic)


class _CutFile:
    """An MCAP file cut short, read from its start up to the cut: every whole record, and the whole records at
    the start of a chunk the cut went through (decompressed as far as its bytes go). No summary (it is written
    last), so messages come in file order."""

    def __init__(self, f):
        self._f = f

    def get_summary(self):
        return None

    def iter_messages(self, topics=None, log_time_order: bool = False):
        from mcap.records import Channel, Chunk, Message, Schema
        from mcap.stream_reader import breakup_chunk

        assert not log_time_order  # _in_log_time_order sorts an unindexed file itself
        wanted = None if topics is None else set(topics)
        schemas: dict[int, Any] = {}  # mcap.records.Schema, Channel
        channels: dict[int, Any] = {}

        def inner(records):
            for record in records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is not None and (wanted is None or channel.topic in wanted):
                        yield schemas.get(channel.schema_id), channel, record

        f = self._f
        f.seek(len(_MAGIC))
        while True:
            head = f.read(9)
            if len(head) < 9:
                return
            opcode, length = head[0], int.from_bytes(head[1:], "little")
            body = f.read(length)
            if opcode not in (_SCHEMA, _CHANNEL, _MESSAGE, _CHUNK):
                if len(body) < length:
                    return
                continue
            if len(body) == length:
                stream = _stream(body)
                if opcode == _SCHEMA:
                    yield from inner([Schema.read(stream)])
                elif opcode == _CHANNEL:
                    yield from inner([Channel.read(stream)])
                elif opcode == _MESSAGE:
                    yield from inner([Message.read(stream, length)])
                else:
                    yield from inner(breakup_chunk(Chunk.read(stream), validate_crc=True))
                continue
            if opcode == _CHUNK:
                yield from inner(_partial_chunk(body))
            return


_SCHEMA, _CHANNEL, _MESSAGE, _CHUNK = 0x03, 0x04, 0x05, 0x06


def _stream(data: bytes):
    from mcap.data_stream import ReadDataStream

    return ReadDataStream(io.BytesIO(data))


def _partial_chunk(body: bytes) -> list:
    """The whole Schema / Channel / Message records at the start of a chunk cut short."""
    from mcap.records import Channel, Message, Schema

    if len(body) < 32:
        return []
    name_len = int.from_bytes(body[28:32], "little")
    start = 32 + name_len + 8
    if len(body) < start:
        return []
    compression = body[32:32 + name_len].decode("utf-8", "replace")
    data = body[start:]
    try:
        if compression == "zstd":
            import zstandard

            data = zstandard.ZstdDecompressor().decompressobj().decompress(data)
        elif compression == "lz4":
            import lz4.frame

            data = lz4.frame.LZ4FrameDecompressor().decompress(data)
        elif compression:
            return []
    except Exception:  # a compressed stream cut mid-block: nothing certain in it
        return []
    out: list = []
    p = 0
    while p + 9 <= len(data):
        opcode, length = data[p], int.from_bytes(data[p + 1:p + 9], "little")
        if p + 9 + length > len(data):
            break
        stream = _stream(data[p + 9:p + 9 + length])
        if opcode == _SCHEMA:
            out.append(Schema.read(stream))
        elif opcode == _CHANNEL:
            out.append(Channel.read(stream))
        elif opcode == _MESSAGE:
            out.append(Message.read(stream, length))
        p += 9 + length
    return out


# How far out of log-time order an unindexed file's messages may be and still come out sorted.
REORDER_WINDOW = 256


def _in_log_time_order(reader, topics: list[str]):
    """(schema, channel, message) in log-time order, in bounded memory.

    With chunk indexes the library merges chunks lazily. Without them it would
    sort the whole file in memory; files without indexes come from live
    recorders and are nearly in order, so a small reordering heap suffices.
    """
    summary = reader.get_summary()
    if summary is not None and summary.chunk_indexes:
        yield from reader.iter_messages(topics=topics, log_time_order=True)
        return
    heap: list = []
    for seq, item in enumerate(reader.iter_messages(topics=topics, log_time_order=False)):
        heapq.heappush(heap, (item[2].log_time, seq, item))
        if len(heap) > REORDER_WINDOW:
            yield heapq.heappop(heap)[2]
    while heap:
        yield heapq.heappop(heap)[2]


# How each schema encoding is read, and the message encoding its messages come in.
_SCHEMA_FORMATS = {"ros1msg": (DefinitionFormat.MSG, "ros1"), "ros2msg": (DefinitionFormat.MSG, "cdr"),
                   "ros2idl": (DefinitionFormat.IDL, "cdr")}


class _Decoders:
    """A decoder per channel, built from its schema by rosbags once the schema has passed its checks."""

    def __init__(self):
        self._by_channel: dict[int, Callable[[bytes], Any]] = {}
        self._stores: dict[tuple, Any] = {}  # one typestore per schema: two schemas may define a type differently

    def prepare(self, schema, channel) -> Callable[[bytes], Any]:
        """The channel's decoder; raises FormatError for a schema carto cannot read or that is not a valid
        definition."""
        decoder = self._by_channel.get(channel.id)
        if decoder is None:
            decoder = self._by_channel[channel.id] = self._decoder(schema, channel)
        return decoder

    def _decoder(self, schema, channel) -> Callable[[bytes], Any]:
        known = _SCHEMA_FORMATS.get(schema.encoding) if schema is not None else None
        if known is None or channel.message_encoding != known[1]:
            raise FormatError(
                f"no decoder for topic {channel.topic}: message encoding {channel.message_encoding!r}, "
                f"schema encoding {schema.encoding if schema else None!r} (carto reads ROS1 and ROS2 messages)")
        fmt, encoding = known
        text = bytes(schema.data).decode("utf-8", "replace")
        types = checked_types(text, fmt, schema.name, channel.topic)
        msgtype = normalise_type(schema.name)
        if msgtype not in types:
            raise FormatError(f"topic {channel.topic}: its schema does not define {schema.name}")
        key = (schema.encoding, schema.name, text)
        store = self._stores.get(key)
        if store is None:
            store = self._stores[key] = typestore_of(types)
        if encoding == "ros1":
            return lambda data: store.deserialize_ros1(data, msgtype)
        return lambda data: store.deserialize_cdr(data, msgtype)

    def __call__(self, schema, channel, message):
        return self.prepare(schema, channel)(message.data)
