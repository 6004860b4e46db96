"""Standalone MCAP files (ROS2 cdr/ros2msg and ROS1 ros1/ros1msg), read with the mcap library."""
from __future__ import annotations

import contextlib
import heapq
import io
from collections.abc import Iterable, Iterator
from pathlib import Path

from carto_cli.core.errors import CartoError, FormatError, TopicError
from carto_cli.core.records import Record, Transform
from carto_cli.io.recording import ReadOptions, Recording, TopicInfo, kind_of, normalise_type
from carto_cli.io.sources import messages
from carto_cli.io.sources.decode_errors import translate_errors

_MAGIC = b"\x89MCAP0\r\n"


class McapRecording(Recording):
    """An MCAP file decoded from its own schemas, in log-time order."""

    format = "mcap"

    def __init__(self, path: Path, options: ReadOptions | None = None):
        super().__init__(path, options)
        self._static: list[Transform] | None = None
        if not self.path.is_file():
            raise CartoError("no such file" if not self.path.exists() else "not a file", self.path)
        with self._translate_errors():
            self._channels, self._counts = self._read_index()

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
            if tail != _MAGIC:
                # The writer was killed or the copy cut short; the summary and the
                # end of the data are gone, so nothing read from it could be trusted.
                raise FormatError("truncated MCAP file (no closing magic bytes)", self.path)
            f.seek(0)
            yield make_reader(f, validate_crcs=True,
                              decoder_factories=_decoder_factories())

    def _read_index(self):
        """Channels as {id: (topic, normalised type)} and message counts by channel id."""
        with self._open() as reader:
            summary = reader.get_summary()
            channels: dict[int, tuple[str, str]] = {}
            counts: dict[int, int] = {}
            if summary is not None:
                for cid, ch in summary.channels.items():
                    schema = summary.schemas.get(ch.schema_id)
                    channels[cid] = (ch.topic, normalise_type(schema.name) if schema else "")
                if summary.statistics is not None:
                    counts = {cid: int(summary.statistics.channel_message_counts.get(cid, 0)) for cid in channels}
                    return channels, counts
            # No summary or no statistics: count with one pass that decodes nothing.
            for schema, ch, _ in reader.iter_messages(log_time_order=False):
                if ch.id not in channels:
                    channels[ch.id] = (ch.topic, normalise_type(schema.name) if schema else "")
                counts[ch.id] = counts.get(ch.id, 0) + 1
            return channels, counts

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
                    decode = _Decoders()
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
        options = self.options
        with self._translate_errors(), self._open() as reader:
            decode = _Decoders()
            for schema, channel, message in _in_log_time_order(reader, topics):
                msgtype = schema.name if schema is not None else ""
                if not messages.is_readable(channel.topic, msgtype):
                    continue  # another channel of a mixed-type topic: not worth decoding
                yield from messages.to_records(decode(schema, channel, message), msgtype, channel.topic, options)


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


def _decoder_factories() -> list:
    from mcap_ros1.decoder import DecoderFactory as Ros1DecoderFactory
    from mcap_ros2.decoder import DecoderFactory as Ros2DecoderFactory

    return [Ros2DecoderFactory(), Ros1DecoderFactory()]


class _Decoders:
    """A decoder per channel, as iter_decoded_messages finds them, but only for messages carto reads."""

    def __init__(self):
        self._factories = _decoder_factories()
        self._by_channel: dict[int, object] = {}

    def __call__(self, schema, channel, message):
        decoder = self._by_channel.get(channel.id)
        if decoder is None:
            # mcap_ros2's schema parser prints its complaints to stderr before raising;
            # the FormatError carto reports says it once.
            with contextlib.redirect_stderr(io.StringIO()):
                for factory in self._factories:
                    decoder = factory.decoder_for(channel.message_encoding, schema)
                    if decoder is not None:
                        break
            if decoder is None:
                raise FormatError(
                    f"no decoder for topic {channel.topic}: message encoding {channel.message_encoding!r}, "
                    f"schema encoding {schema.encoding if schema else None!r} (carto reads ROS1 and ROS2 messages)")
            self._by_channel[channel.id] = decoder
        return decoder(message.data)
