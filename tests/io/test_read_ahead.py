"""io.read_ahead: the records a child decodes are the records read here, in the same order, once."""
from __future__ import annotations

import multiprocessing
from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np
import pytest

from carto_cli.core.errors import CartoError, FormatError
from carto_cli.core.records import Imu, Odometry, Record, Scan
from carto_cli.core.timing import StageTimer
from carto_cli.io.read_ahead import BATCH, STAGE, RecordStream
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.sources.memory import MemoryRecording
from carto_cli.io.sources.open import open_recording
from carto_cli.io.topics import select_topics, selected_records

pytestmark = pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="reading ahead forks")

SCANS = 3 * BATCH + 5  # batches and a remainder


def carmen_log(path: Path, scans: int = SCANS, bad_line_after: int | None = None) -> Path:
    lines = []
    for k in range(scans):
        t = 100.0 + 0.1 * k
        lines.append(f"ODOM {0.01 * k} 0 0 0.1 0 0 {t - 0.05:.6f} host {t - 0.05:.6f}")
        ranges = " ".join(f"{1.0 + 0.01 * ((i + k) % 50):.2f}" for i in range(90))
        pose = f"{0.01 * k} 0 0"
        lines.append(f"FLASER 90 {ranges} {pose} {pose} {t:.6f} host {t:.6f}")
        if bad_line_after is not None and k == bad_line_after:
            lines.append(f"FLASER 90 1.0 2.0 {t + 0.01:.6f} host {t + 0.01:.6f}")  # 2 of 90 ranges
    path.write_text("\n".join(lines) + "\n")
    return path


def memory_records(n: int = SCANS) -> list[Record]:
    out: list[Record] = []
    for k in range(n):
        t = 10.0 + 0.1 * k
        angles = np.linspace(-1.0, 1.0, 30, dtype=np.float32)
        out.append(Scan(t, np.full(30, 1.0 + 0.01 * k, dtype=np.float32), angles, frame="laser", topic="/scan"))
        out.append(Odometry(t - 0.03, 0.01 * k, 0.0, 0.0, topic="/odom"))
        out.append(Imu(t - 0.01, np.zeros(3), np.array([0.0, 0.0, 9.81]), topic="/imu"))
    return out


def key(record: Record) -> tuple:
    """What tells two records apart (their type, topic, time and values)."""
    values = [record.ranges.tobytes()] if isinstance(record, Scan) else []
    if isinstance(record, Odometry):
        values = [record.x, record.y, record.yaw]
    return (type(record).__name__, record.topic, record.time, *values)


def keys(records: Iterable[Record]) -> list[tuple]:
    return [key(r) for r in records]


def plain(path: Path, topics) -> list[tuple]:
    with open_recording(path) as rec:
        return keys(selected_records(rec, select_topics(rec), topics))


def children() -> list:
    return [p for p in multiprocessing.active_children() if p.name == "carto-read"]


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_pass_is_the_plain_reading(tmp_path, jobs):
    log = carmen_log(tmp_path / "log.clf")
    timer = StageTimer()
    with open_recording(log) as rec:
        selection = select_topics(rec)
        with RecordStream(rec, selection, selection.topics, jobs=jobs) as stream:
            got = keys(stream.records(selection.topics, timer))
    assert got == plain(log, selection.topics)
    assert len(got) == 2 * SCANS
    # Two jobs: decoded in the child, whose time shows as a concurrent stage; one job: here, no child.
    assert (timer.snapshot().find(STAGE) is not None) == (jobs == 2)
    assert children() == []


@pytest.mark.parametrize("jobs", [1, 2])
def test_the_survey_s_prefix_is_replayed_not_read_twice(tmp_path, jobs):
    log = carmen_log(tmp_path / "log.clf")
    with open_recording(log) as rec:
        selection = select_topics(rec)
        with RecordStream(rec, selection, selection.topics, jobs=jobs) as stream:
            looked = []
            for record in stream.prefix([selection.scan]):  # the survey: scans only, then it stops
                looked.append(key(record))
                if len(looked) == BATCH + 3:
                    break
            again = keys(stream.prefix([selection.scan]))[:5]  # a second look starts at the start again
            whole = keys(stream.records(selection.topics))
            scans_only = keys(stream.records([selection.scan]))  # a second pass reads the recording again
    assert looked == plain(log, [selection.scan])[:BATCH + 3]
    assert again == looked[:5]
    assert whole == plain(log, selection.topics)
    assert scans_only == plain(log, [selection.scan])


@pytest.mark.parametrize("fmt, name", [("ros1", "rec.bag"), ("ros2-sqlite3", "rec_db3"), ("ros2-mcap", "rec_mcap"),
                                       ("mcap", "rec.mcap")])
def test_each_topic_keeps_its_place_among_the_others(tmp_path, fmt, name):
    """Every file format is read by a child, through a reader of its own; a pass filters the stream of every
    topic: the same order as reading the topics asked for alone."""
    bag = tmp_path / name
    write_recording(memory_records(), bag, fmt)
    with open_recording(bag) as rec:
        selection = select_topics(rec, imu_topic="/imu")
        assert selection.imu == "/imu"
        timer = StageTimer()
        with RecordStream(rec, selection, selection.topics, jobs=2) as stream:
            records = stream.records([selection.scan, "/odom"], timer)
            first = [key(next(records))]
            assert rec.static_transforms() == rec.static_transforms()  # this process's reader is its own still
            without_imu = first + keys(records)
    assert timer.snapshot().find(STAGE) is not None  # decoded by a child
    assert without_imu == plain(bag, ["/scan", "/odom"])
    assert {k[1] for k in without_imu} == {"/scan", "/odom"}


@pytest.mark.parametrize("jobs", [1, 2])
def test_a_bad_line_raises_where_it_is_after_the_records_before_it(tmp_path, jobs):
    log = carmen_log(tmp_path / "log.clf", bad_line_after=BATCH + 10)
    got = []
    with open_recording(log) as rec:
        selection = select_topics(rec)
        with RecordStream(rec, selection, selection.topics, jobs=jobs) as stream:
            with pytest.raises(FormatError) as raised:
                for record in stream.records(selection.topics):
                    got.append(key(record))
    with open_recording(log) as rec:
        inline = []
        with pytest.raises(FormatError) as expected:
            for record in selected_records(rec, select_topics(rec), selection.topics):
                inline.append(key(record))
    assert got == inline and len(got) > BATCH
    assert str(raised.value) == str(expected.value) and str(raised.value.path) == str(log)
    assert children() == []


def test_stopping_early_stops_the_child(tmp_path):
    log = carmen_log(tmp_path / "log.clf", scans=2000)  # more than the pipe holds
    with open_recording(log) as rec:
        selection = select_topics(rec)
        with RecordStream(rec, selection, selection.topics, jobs=2) as stream:
            records = stream.records(selection.topics)
            first = next(records)
            assert isinstance(first, (Scan, Odometry))
            assert len(children()) == 1
            records.close()  # --max-scans reached
            assert children() == []
        with RecordStream(rec, selection, selection.topics, jobs=2):
            assert len(children()) == 1  # started, never read
        assert children() == []


class WarnsWhileReading(MemoryRecording):
    """A reader that works around something in the middle of the file (as a damaged bag's reader might)."""

    read_ahead = True  # in memory, but read in a child all the same

    def independent(self) -> WarnsWhileReading:
        return self

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        for i, record in enumerate(super().records(topics)):
            if i == 7:
                self.warnings.append("skipped a damaged chunk")
            yield record


@pytest.mark.parametrize("jobs", [1, 2])
def test_what_the_reader_worked_around_reaches_this_process(jobs):
    rec = WarnsWhileReading(memory_records(20))
    selection = select_topics(rec)
    with RecordStream(rec, selection, selection.topics, jobs=jobs) as stream:
        n = sum(1 for _ in stream.records(selection.topics))
    assert n == 60  # scans, odometry and IMU
    assert rec.warnings == ["skipped a damaged chunk"]


def test_a_recording_in_memory_is_read_here():
    rec = MemoryRecording(memory_records(10))
    selection = select_topics(rec)
    timer = StageTimer()
    with RecordStream(rec, selection, selection.topics, jobs=2) as stream:
        assert children() == []
        assert len(list(stream.records(selection.topics, timer))) == 30
    assert timer.snapshot().find(STAGE) is None


class Unpicklable(Exception):
    """Pickles, but does not unpickle: its constructor wants two arguments and pickle passes one."""

    def __init__(self, what: str, where: int):
        super().__init__(f"{what} at {where}")


class FailsWhileReading(MemoryRecording):
    read_ahead = True  # read in a child

    def independent(self) -> FailsWhileReading:
        return self

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        for i, record in enumerate(super().records(topics)):
            if i == 5:
                raise Unpicklable("a reader's own error", i)
            yield record


def test_an_error_that_cannot_cross_is_named_not_lost():
    rec = FailsWhileReading(memory_records(20))
    selection = select_topics(rec)
    with RecordStream(rec, selection, selection.topics, jobs=2) as stream:
        got = []
        with pytest.raises(CartoError, match="Unpicklable: a reader's own error at 5"):
            for record in stream.records(selection.topics):
                got.append(record)
    assert len(got) == 5


def test_a_pass_may_not_ask_for_topics_the_stream_does_not_read(tmp_path):
    log = carmen_log(tmp_path / "log.clf")
    with open_recording(log) as rec:
        selection = select_topics(rec)
        with RecordStream(rec, selection, [selection.scan], jobs=1) as stream:
            with pytest.raises(ValueError, match="not read by this stream"):
                stream.records([selection.scan, selection.odometry])
            with pytest.raises(ValueError, match="not read by this stream"):
                stream.prefix([selection.odometry])


class InterruptedWhileReading(MemoryRecording):
    """A reader stopped by a SIGTERM of the child's own (`timeout` signals the whole group), which the file's
    reader turned into a "corrupt file" error, as io.sources' translate_errors turns anything."""

    read_ahead = True  # read in a child

    def independent(self) -> InterruptedWhileReading:
        return self

    def records(self, topics: Iterable[str] | None = None) -> Iterator[Record]:
        for i, record in enumerate(super().records(topics)):
            if i == 5:
                try:
                    raise KeyboardInterrupt
                except KeyboardInterrupt as e:
                    raise FormatError("corrupt or truncated log: KeyboardInterrupt") from e
            yield record


def test_an_interrupted_child_reads_as_an_interrupt_here():
    """Not as the damaged file it was reported as (the pickle that carries it over drops its cause)."""
    rec = InterruptedWhileReading(memory_records(20))
    selection = select_topics(rec)
    with RecordStream(rec, selection, selection.topics, jobs=2) as stream:
        with pytest.raises(KeyboardInterrupt):
            for _ in stream.records(selection.topics):
                pass


@pytest.mark.parametrize("fmt, name", [("ros1", "rec.bag"), ("ros1", "rec.bag.active"), ("ros2-sqlite3", "rec_db3"),
                                       ("ros2-mcap", "rec_mcap"), ("mcap", "rec.mcap")])
def test_a_reader_opened_again_is_the_same_reader_with_the_same_records(tmp_path, fmt, name):
    """What a forked child reads through: ``independent`` opens the file again with the reader's own class (a
    .bag.active is the salvaging reader's), the parent's reader left where it was."""
    bag = tmp_path / name
    write_recording(memory_records(8), bag, fmt)
    with open_recording(bag) as rec:
        first = key(next(rec.records()))
        with rec.independent() as again:
            assert type(again) is type(rec) and again is not rec and again.path == rec.path
            assert keys(again.records()) == keys(rec.records())
        assert key(next(rec.records())) == first
