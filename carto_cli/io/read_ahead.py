"""A recording's records decoded ahead of whoever consumes them, in a process of its own, and read once.

Decoding is Python work (a CARMEN line's tokens, a bag's messages), a sixth of a dense log's mapping time on
the mapping process (dense-freiburg-079: 4.5 s of 29), and the interpreter lock keeps a thread from doing it
beside local SLAM. With two jobs or more on Linux a forked child decodes the records and sends them over a
pipe in batches while the caller maps (as ``rosbag play`` does in a node of its own); the pipe's buffer bounds
what waits there, so memory does not grow with the recording. The child starts when the stream is made, so
it decodes while the caller loads its kernels. One job, or a recording that is not a file reader's (records
already in memory, a simulation): read here.

The survey looks at the first records before mapping starts; :meth:`RecordStream.prefix` keeps what it
took, and the mapping pass (:meth:`RecordStream.records`) replays that before reading on, so the start of
the recording is decoded once. Records come in the reader's order whatever the number of jobs (each pass
filters one stream of the union of the topics, in which every topic keeps its place), so the map is the
same.
"""
from __future__ import annotations

import os
import pickle
import signal
import time
from collections.abc import Generator, Iterable, Iterator, Sequence
from typing import TYPE_CHECKING

from carto_cli.core import interrupts
from carto_cli.core.errors import CartoError
from carto_cli.core.parallel import available_cores, die_with_parent, fork_safe
from carto_cli.core.records import Record
from carto_cli.core.timing import NullTimer
from carto_cli.io.recording import Recording
from carto_cli.io.topics import TopicSelection, selected_records
from carto_cli.sensor.merging import merged_topic

if TYPE_CHECKING:
    from multiprocessing.connection import Connection
    from multiprocessing.process import BaseProcess

__all__ = ["BATCH", "RecordStream"]

BATCH = 64  # records a message: a pickle and a pipe write a record cost more than the record's decoding
PIPE_BYTES = 1 << 20  # what may wait in the pipe: Linux's limit for an unprivileged process (pipe-max-size)
STAGE = "read ahead"  # the child's decoding, a concurrent stage of the caller's timer


class RecordStream:
    """The records of ``topics`` of an opened recording, for a survey's look at the start and then the passes
    that map it. ``jobs`` (None: every core): two or more read ahead in a forked child where that is safe.
    Close it (or use it as a context manager) so that a child whose records nobody took is stopped."""

    def __init__(self, recording: Recording, selection: TopicSelection, topics: Sequence[str], *,
                 jobs: int | None = None):
        self.recording = recording
        self.selection = selection
        self.topics = list(topics)
        jobs = available_cores() if jobs is None else max(1, int(jobs))
        self._ahead = jobs >= 2
        self._pass: Iterator[Record] | None = None  # the pass the survey looks at and mapping then takes
        self._kept: list[Record | None] = []  # what the survey took of it, for mapping to replay
        self._started: list[Iterator[Record]] = []
        self.start()

    def start(self) -> None:
        """Begin the first pass now (its child decodes while the caller does other things)."""
        if self._pass is None:
            self._pass = self._begin()

    def _begin(self) -> Iterator[Record]:
        records: Iterator[Record]
        if self._ahead and self.recording.read_ahead and fork_safe():
            records = _read_in_child(self.recording, self.selection, self.topics)
        else:
            records = selected_records(self.recording, self.selection, self.topics)
        self._started.append(records)
        return records

    def prefix(self, topics: Iterable[str]) -> Iterator[Record]:
        """The records of ``topics`` from the start of the recording, for as long as the caller iterates; what
        is read on the way is kept for :meth:`records` to replay."""
        self.start()
        wanted = self._covered(topics)
        kept, source = self._kept, self._pass
        assert source is not None

        def look() -> Iterator[Record]:
            for earlier in list(kept):
                if earlier is not None and earlier.topic in wanted:
                    yield earlier
            for record in source:
                kept.append(record)
                if record.topic in wanted:
                    yield record

        return look()

    def records(self, topics: Iterable[str], timer=None) -> Iterator[Record]:
        """One whole pass over the records of ``topics``: the first one replays what :meth:`prefix` read and
        reads on; a later one reads the recording again (a second mapping of it). ``timer``: where a child's
        decoding shows, as the concurrent stage ``read ahead``."""
        wanted = self._covered(topics)
        if self._pass is None:
            self._pass = self._begin()
        source, kept = self._pass, self._kept
        if timer is not None and isinstance(source, _ChildRecords):
            source.timer = timer
        self._pass, self._kept = None, []

        def read() -> Iterator[Record]:
            for i in range(len(kept)):
                record, kept[i] = kept[i], None  # let go of each as it goes: mapping keeps what it needs
                if record is not None and record.topic in wanted:
                    yield record
            try:
                for record in source:
                    if record.topic in wanted:
                        yield record
            finally:
                close = getattr(source, "close", None)
                if close is not None:
                    close()  # mapping stopped early (--max-scans, an error): so does the reading

        return read()

    def _covered(self, topics: Iterable[str]) -> set[str]:
        wanted = set(topics)
        if not wanted <= set(self.topics):  # a pass of this stream would silently lack them
            raise ValueError(f"topics {sorted(wanted - set(self.topics))} are not read by this stream")
        lasers = self.selection.lasers
        if lasers and all(x.topic in wanted for x in lasers):
            wanted.add(merged_topic(lasers))  # the lasers' scans come merged (io.topics.selected_records)
        return wanted

    def close(self) -> None:
        """Stop every pass's child that is still running (its records are no longer wanted)."""
        for records in self._started:
            close = getattr(records, "close", None)
            if close is not None:
                close()
        self._started.clear()
        self._pass, self._kept = None, []

    def __enter__(self) -> RecordStream:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _read_in_child(recording: Recording, selection: TopicSelection, topics: list[str]) -> _ChildRecords:
    """Fork the child now; the records it sends, as they come. Its warnings about the file (what the reader
    worked around) are added to ``recording``'s at the end, where reading here would have added them."""
    import multiprocessing  # only when reading ahead

    recording.before_fork()
    ctx = multiprocessing.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)
    _widen(send)
    process = ctx.Process(target=_serve, args=(recording, selection, topics, send, receive, os.getpid()),
                          name="carto-read", daemon=True)
    process.start()
    send.close()
    return _ChildRecords(process, receive, recording)


def _widen(send: Connection) -> None:
    """Let the pipe hold a few batches (Linux: 64 kB by default, a third of one batch of 360-beam scans), so
    that the child reads on while this process is busy instead of waiting for each batch to be taken."""
    import fcntl

    try:
        fcntl.fcntl(send.fileno(), fcntl.F_SETPIPE_SZ, PIPE_BYTES)
    except (AttributeError, OSError):  # not Linux, or a lower system limit: the default pipe still works
        pass


class _ChildRecords:
    """The records a child sends, as an iterator; ``close`` stops the child, whether or not it was read."""

    def __init__(self, process: BaseProcess, receive: Connection, recording: Recording):
        self._process = process
        self._receive = receive
        self.timer = NullTimer()  # where the child's decoding time goes, once it is known
        self._records = self._read(recording)

    def __iter__(self) -> _ChildRecords:
        return self

    def __next__(self) -> Record:
        return next(self._records)

    def _read(self, recording: Recording) -> Generator[Record, None, None]:
        try:
            while True:
                try:
                    kind, payload = pickle.loads(self._receive.recv_bytes())
                except EOFError:
                    self._process.join(5)
                    raise CartoError(f"the process reading the recording ended unexpectedly, exit code "
                                     f"{self._process.exitcode}", recording.path) from None
                if kind == "records":
                    yield from payload
                elif kind == "end":
                    warnings, ns, count = payload
                    recording.warnings.extend(w for w in warnings if w not in recording.warnings)
                    self.timer.concurrent(STAGE).add("read recording", ns, count)
                    return
                else:
                    raise payload
        finally:
            self._stop()

    def close(self) -> None:
        self._records.close()
        self._stop()

    def _stop(self) -> None:
        self._receive.close()
        if self._process.is_alive():
            self._process.kill()  # abandoned: --max-scans reached, an error, Ctrl-C
        self._process.join()


def _serve(recording: Recording, selection: TopicSelection, topics: list[str], send: Connection,
           parents_end: Connection, parent: int) -> None:
    """The child: decode, send batches of records, then the file's new warnings and the time it took."""
    die_with_parent(parent)
    parents_end.close()  # else a write to a full pipe would wait for this process itself to read it
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides what Ctrl-C stops
    interrupts.clear()  # only a signal to this process counts here
    clock = time.perf_counter_ns
    batch: list[Record] = []

    def flush() -> None:
        send.send_bytes(pickle.dumps(("records", batch), protocol=pickle.HIGHEST_PROTOCOL))
        batch.clear()

    source = recording
    try:
        source = recording.independent()
        already = len(source.warnings)
        spent = count = 0
        start = clock()
        for record in selected_records(source, selection, topics):
            batch.append(record)
            if len(batch) == BATCH:
                spent += clock() - start
                count += len(batch)
                flush()
                start = clock()
        spent += clock() - start
        count += len(batch)
        if batch:
            flush()
        send.send_bytes(pickle.dumps(("end", (source.warnings[already:], spent, count))))
    except BrokenPipeError:
        pass  # the parent stopped reading
    except BaseException as e:  # handed to the parent, raised after the records read before it
        if interrupts.is_interrupt(e):
            # A SIGTERM of its own (`timeout` signals the whole group), maybe turned by a reader into a corrupt
            # file's error: the parent must read it as an interrupt.
            e = KeyboardInterrupt()
        try:
            message = pickle.dumps(("error", e))
            pickle.loads(message)  # an exception with its own constructor may pickle and not unpickle
        except Exception:
            message = pickle.dumps(("error", CartoError(f"{type(e).__name__}: {e}", source.path)))
        try:
            if batch:
                flush()
            send.send_bytes(message)
        except OSError:
            pass
    finally:
        send.close()
        os._exit(0)  # the parent's exit handlers and threads are not this process's
