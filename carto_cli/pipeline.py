"""The one place a recording meets the SLAM core: open it, choose its topics, place the laser, feed
:class:`~carto_cli.mapping.slam.Slam` in time order. Every subcommand that maps goes through here."""
from __future__ import annotations

import dataclasses
import time as _time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.core.memory import peak_rss_mb
from carto_cli.core.records import Imu, Odometry, Scan, Transform
from carto_cli.gmapping import ALGORITHMS, GMAPPING_PIPELINE, Algorithm
from carto_cli.io.content import ContentCheck
from carto_cli.io.read_ahead import RecordStream
from carto_cli.io.recording import ReadOptions, Recording, first_scan_frame
from carto_cli.io.sources.open import open_recording
from carto_cli.io.tf_tree import laser_pose_from_tf
from carto_cli.io.topics import TopicSelection, select_topics, selected_records
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.quality import LEVELS, MapQuality, assess
from carto_cli.mapping.slam import MappingSystem, Slam, SlamResult
from carto_cli.options import Options, load_options
from carto_cli.regime import AutoChoice, Regime, choose, survey

if TYPE_CHECKING:
    pass


@dataclass
class MapResult(SlamResult):
    laser_pose_source: str = ""
    selection: TopicSelection | None = None
    regime: Regime | None = None  # what --profile auto measured (None for a named profile)
    auto: AutoChoice | None = None  # and what it chose
    quality: MapQuality | None = None  # carto's own verdict on the map (mapping.quality)
    warnings: list[str] = field(default_factory=list)  # what the recording held that mapping dropped (io.content)
    options: Options | None = None  # the options the map was built with (auto's choice), once known

    def summary(self) -> dict:
        """What summary.json holds: the mapping system, the verdict, the statistics, and what auto detected and
        chose."""
        return {
            "schema": "carto.map-summary v1",
            "algorithm": self.stats.get("algorithm", Algorithm.CARTOGRAPHER),  # Slam's stats do not name it
            "quality": self.quality.to_dict() if self.quality is not None else None,
            "stats": {k: (v.item() if isinstance(v, np.generic) else v) for k, v in self.stats.items()},
            "auto": None if self.auto is None or self.regime is None else {
                "detected": self.regime.to_dict(), "algorithm": self.auto.algorithm, "profile": self.auto.profile,
                "settings": self.auto.settings,
                "reasons": self.auto.reasons},
            "laser_pose_source": self.laser_pose_source,
            "odometry": None if self.selection is None else self.selection.describe_odometry(),
            "warnings": list(self.warnings),
        }


@dataclass(frozen=True)
class Auto:
    """Options chosen from the recording itself (``--profile auto``, what ``carto map`` does with no
    profile), then the user's ``--set`` overrides on top."""

    overrides: tuple[str, ...] = ()


@dataclass(frozen=True)
class Configured:
    options: Options
    regime: Regime | None = None
    auto: AutoChoice | None = None
    algorithm: str = Algorithm.CARTOGRAPHER  # what maps: the caller's choice, else auto's, else Cartographer


def configure(spec: Options | Auto, recording: Recording, selection: TopicSelection,
              algorithm: str | None = None, laser_pose=None, timer=None,
              stream: RecordStream | None = None) -> Configured:
    """The options and mapping system for ``recording``: ``spec`` itself (Cartographer unless ``algorithm``
    says otherwise), or for :class:`Auto` the survey's choice (``algorithm``, when given, wins). ``laser_pose``:
    the user's mount (None: the recording's), for the survey's odometry check; ``timer``: its kernels' warm-up;
    ``stream``: the records mapping will read (the survey looks at their start)."""
    if isinstance(spec, Options):
        return Configured(spec, algorithm=algorithm or Algorithm.CARTOGRAPHER)
    # The odometry check sizes the particle filter's motion model: a Cartographer run does not need it
    check = algorithm in (None, Algorithm.GMAPPING)
    mount = survey_mount(recording, selection, laser_pose) if check else None
    return configure_regime(survey(recording, selection, check_odometry=check, laser_pose=mount, timer=timer,
                                   stream=stream), spec, algorithm)


def survey_mount(recording: Recording, selection: TopicSelection, laser_pose=None) -> np.ndarray | None:
    """The laser's mount as mapping will resolve it (None without scans)."""
    scan_frame = first_scan_frame(recording, selection.scan)
    if scan_frame is None:
        return None
    return resolve_laser_pose(recording, scan_frame, laser_pose,
                              selection.tf_odometry.fixed if selection.tf_odometry else ())[0]


def configure_regime(regime: Regime, spec: Auto, algorithm: str | None = None) -> Configured:
    """:func:`configure` for a regime already surveyed."""
    base = load_options(None, list(spec.overrides))
    g = base.gmapping
    choice = choose(regime, base_max_range=base.trajectory_builder_2d.max_range, algorithm=algorithm,
                    gmapping_max_range=g.maxRange, gmapping_noise=(g.srr, g.srt, g.str, g.stt))
    return Configured(load_options(choice.profile, choice.settings + list(spec.overrides)), regime, choice,
                      choice.algorithm)


def build_configured(recording: Recording, configured: Configured, spec: Options | Auto,
                     **kwargs) -> tuple[MapResult, Configured]:
    """:func:`build` with ``configured``'s options and system. When auto chose GMapping and judges its map
    less than ``ok``, the recording is mapped again with Cartographer's key-scan settings and the map the
    verdict prefers is kept: the particle filter's outcome varies from run to run (aces: 0.05 m with 30
    particles, 0.33 m with 50, judged suspect) where Cartographer's does not. On a tie GMapping's stays, the
    system auto chose for the regime (key scans: better on four of five buildings left out one at a time,
    docs/gmapping.md; fhw: both judged suspect, GMapping's 0.053 m against Cartographer's 0.114 m).
    Returns the map and the configuration that made it; after a second mapping its ``wall_time_s`` and
    ``scans_per_s`` cover both, and ``first_pass_wall_time_s`` the first."""
    started = _time.perf_counter()
    result = build(recording, configured.options, algorithm=configured.algorithm, **kwargs)
    auto = configured.auto
    if (not isinstance(spec, Auto) or auto is None or not auto.chose_algorithm or auto.algorithm != Algorithm.GMAPPING
            or configured.regime is None or result.quality is None or result.quality.ok):
        return result, configured
    other = configure_regime(configured.regime, spec, Algorithm.CARTOGRAPHER)
    assert other.auto is not None
    first_wall = float(result.stats.get("wall_time_s", float("nan")))
    again = build(recording, other.options, algorithm=Algorithm.CARTOGRAPHER, **kwargs)
    wall = _time.perf_counter() - started
    for r in (result, again):
        r.stats.update(wall_time_s=wall, first_pass_wall_time_s=first_wall,
                       scans_per_s=r.stats["scans"] / wall if wall > 0 else float("nan"))
    if again.quality is None or LEVELS.index(again.quality.verdict) < LEVELS.index(result.quality.verdict):
        note = (f"gmapping's map judged {result.quality.verdict}; mapped again with cartographer, judged "
                f"{again.quality.verdict if again.quality else 'not'}")
        return again, dataclasses.replace(other, auto=dataclasses.replace(other.auto, note=note))
    note = f"cartographer's map judged {again.quality.verdict}: kept gmapping's, judged {result.quality.verdict}"
    return result, dataclasses.replace(configured, auto=dataclasses.replace(auto, note=note))


@dataclass
class OpenedRecording:
    recording: Recording
    selection: TopicSelection

    @property
    def scan_count(self) -> int:
        """Messages on the scan topic (what a progress bar counts to)."""
        return next(t.count for t in self.recording.topics() if t.name == self.selection.scan)


def read_options(options: Options | Auto) -> ReadOptions:
    """How to read a recording for these options (the 3D point-cloud slice)."""
    if isinstance(options, Auto):
        options = load_options(None, list(options.overrides))
    tb = options.trajectory_builder_2d
    return ReadOptions(min_z=tb.min_z, max_z=tb.max_z)


@contextmanager
def opened(path: str | Path, read: ReadOptions | None = None, *, scan_topic: str | None = None,
           odom_topic: str | None = None, imu_topic: str | None = None, odom_frame: str | None = None,
           base_frame: str | None = None) -> Iterator[OpenedRecording]:
    """Open a recording and choose its topics (the ``--scan-topic`` family of choices), closing it after."""
    with open_recording(path, read) as rec:
        yield OpenedRecording(rec, select_topics(rec, scan_topic, odom_topic, imu_topic, odom_frame=odom_frame,
                                                 base_frame=base_frame))


def resolve_laser_pose(recording: Recording, scan_frame: str | None, explicit,
                       fixed_tf: Sequence[Transform] = ()) -> tuple[np.ndarray, str]:
    """--laser-pose wins; else static TF; else transforms of /tf that never moved (``fixed_tf``: a mount broadcast
    on /tf); else the laser is at the tracking frame."""
    if explicit is not None:
        return transform.as_pose(explicit), "--laser-pose"
    if scan_frame:
        found = laser_pose_from_tf(recording.static_transforms(), scan_frame)
        if found is not None:
            pose, root = found
            return np.asarray(pose, dtype=np.float64), f"static TF {root} -> {scan_frame}"
        found = laser_pose_from_tf(list(recording.static_transforms()) + list(fixed_tf), scan_frame)
        if found is not None:
            pose, root = found
            return np.asarray(pose, dtype=np.float64), f"TF {root} -> {scan_frame} (fixed transforms on /tf)"
    return np.zeros(3), "identity (no static TF for the laser)"


def _timed(records: Iterator, timer, stage: str = "read recording") -> Iterator:
    """``records``, the time spent producing them added to ``timer`` as one top-level ``stage`` when the stream
    ends: decoding a recording happens between scans, where no other stage sees it (a quarter of a dense CARMEN
    log's run was "untimed"). Two clock reads a record, not a stage each."""
    clock = _time.perf_counter_ns
    total = count = 0
    it = iter(records)
    try:
        while True:
            start = clock()
            try:
                record = next(it)
            except StopIteration:
                total += clock() - start
                return
            total += clock() - start
            count += 1
            yield record
    finally:
        timer.add(stage, total, count)


def build(
    recording: Recording,
    options: Options,
    *,
    selection: TopicSelection | None = None,
    laser_pose=None,
    timer=None,
    on_scan: Callable[[int], None] | None = None,
    use_odometry: bool = True,
    use_imu: bool = True,
    max_scans: int | None = None,
    loop_closure: bool = True,
    graph: PoseGraph | None = None,
    trajectory_id: int = 0,
    judge: bool = True,
    algorithm: str = Algorithm.CARTOGRAPHER,
    jobs: int | None = None,
    stream: RecordStream | None = None,
) -> MapResult:
    """Map one recording. With ``graph`` (e.g. from a loaded map.carto) the recording becomes trajectory
    ``trajectory_id`` of that graph, linked to the earlier ones by loop closures, as Cartographer's
    offline node does with --load_state_filename. ``algorithm`` "gmapping" maps with the particle filter
    (``options.gmapping``) instead of Cartographer. ``jobs``: threads where work is independent (Cartographer's
    pose graph beside local SLAM and its loop-closure searches, GMapping's particles and final searches; None: every
    core); the map is the same for any number. ``stream``: the recording's records, read ahead (one pass of it
    is taken; by default the recording is read here)."""
    wall0 = _time.perf_counter()
    if algorithm not in ALGORITHMS:
        raise CartoError(f"unknown algorithm '{algorithm}' (choose from {', '.join(ALGORITHMS)})")
    if algorithm in GMAPPING_PIPELINE and graph is not None:
        raise CartoError(f"{algorithm} cannot continue a saved map (--load-state is for cartographer)", recording.path)
    selection = selection or select_topics(recording)
    scan_frame = first_scan_frame(recording, selection.scan)
    if scan_frame is None:
        raise CartoError(f"no scans on {selection.scan}", recording.path)
    mount, mount_source = resolve_laser_pose(recording, scan_frame, laser_pose,
                                             selection.tf_odometry.fixed if selection.tf_odometry else ())
    tb = options.trajectory_builder_2d
    slam: MappingSystem
    if algorithm == Algorithm.GMAPPING:
        from carto_cli.gmapping.filter import GMappingSlam  # a Cartographer run never loads it (0.4 s)

        slam = GMappingSlam(options, laser_pose=mount, timer=timer, started=wall0, jobs=jobs)
    elif algorithm == Algorithm.SCAN_TO_MAP:
        from carto_cli.gmapping.front_end import ScanToMapSlam

        slam = ScanToMapSlam(options, laser_pose=mount, timer=timer, started=wall0, jobs=jobs)
    else:
        slam = Slam(options, laser_pose=mount, timer=timer, loop_closure=loop_closure, graph=graph,
                    trajectory_id=trajectory_id, started=wall0, jobs=jobs)

    topics = [selection.scan]
    if use_odometry and selection.odometry:
        topics.append(selection.odometry)
    if use_imu and selection.imu and tb.use_imu_data and algorithm not in GMAPPING_PIPELINE:
        topics.append(selection.imu)

    content = ContentCheck()
    try:
        records = (stream.records(topics, slam.timer) if stream is not None
                   else selected_records(recording, selection, topics))
        for record in _timed(content.filter(records), slam.timer):
            if isinstance(record, Scan):
                if max_scans is not None and slam.num_scans >= max_scans:
                    break
                slam.add_scan(record)
                if on_scan is not None:
                    on_scan(1)
            elif isinstance(record, Odometry):
                slam.add_odometry(record)
            elif isinstance(record, Imu):
                slam.add_imu(record)
        if slam.num_poses == 0:
            raise CartoError("no scan could be matched (all scans empty after filtering?)", recording.path)
    except BaseException:
        try:
            slam.close(abandon=True)  # Ctrl-C or a bad recording: do not make the user wait for the graph
        except Exception:
            pass
        raise
    core = slam.finish()
    result = MapResult(**vars(core), laser_pose_source=mount_source, selection=selection,
                       warnings=list(recording.warnings) + content.warnings())
    peak = peak_rss_mb()
    # or of this process and the pose graph's together while that one ran (mapping.slam), if higher
    together = result.stats.get("graph_process_peak_memory_mb", 0.0)
    result.stats["peak_memory_mb"] = None if peak is None else max(peak, together)
    if judge and result.graph is not None:
        with slam.timer.stage("quality"):
            result.quality = assess(result, result.graph.odometry_samples(trajectory_id))
    return result

