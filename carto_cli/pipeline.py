"""The one place a recording meets the SLAM core. A :class:`MapRequest` (what is asked: a recording and how to
map it) is resolved once, against the opened recording, into a :class:`Plan` (topics, the laser's mount, the
options and system auto or the caller chose, the map continued), and :func:`execute` maps by the plan, feeding
the chosen system in time order and judging its map. ``carto map``, ``carto profile``, the Python API and the
benchmarks all go this way.

    with planned(MapRequest(path)) as plan:      # open, read ahead, survey, configure: once
        result = execute(plan)                   # may run again (a profile's repeats: one pass each)
"""
from __future__ import annotations

import dataclasses
import functools
import math
import time as _time
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from carto_cli.core import kernels, transform
from carto_cli.core.errors import CartoError
from carto_cli.core.memory import peak_rss_mb
from carto_cli.core.records import Imu, Odometry, Scan, Transform
from carto_cli.core.timing import NullTimer
from carto_cli.gmapping import ALGORITHMS, GMAPPING_PIPELINE, Algorithm
from carto_cli.grid.occupancy_image import EAGER_CELLS, AssembledImage
from carto_cli.io.content import ContentCheck
from carto_cli.io.read_ahead import RecordStream
from carto_cli.io.recording import ReadOptions, Recording, first_scan_frame
from carto_cli.io.sources.open import open_recording
from carto_cli.io.topics import TopicSelection, laser_mount, select_topics, selected_records
from carto_cli.mapping import alignment
from carto_cli.mapping.alignment import Align, Squaring
from carto_cli.mapping.cleaning import Transients, cleaned_image, find_transients, flat_points
from carto_cli.mapping.closure_confirmation import CONFIRM_MAX_ROTATION
from carto_cli.mapping.lifelong import SessionPolicy, Trimmed, last_seen
from carto_cli.mapping.merging import merge_states
from carto_cli.mapping.pose_graph import PoseGraph
from carto_cli.mapping.pose_graph_state import PoseGraphState
from carto_cli.mapping.quality import LEVELS, MapQuality, QualityCheck, assess
from carto_cli.mapping.sessions import Session, SessionLink, SessionScans, linked_to, session_links, trajectories
from carto_cli.mapping.slam import MappingSystem, RunStats, Slam, SlamResult
from carto_cli.mapping.submaps import Submap
from carto_cli.options import Options, load_options
from carto_cli.regime import AutoChoice, Regime, choose, survey

if TYPE_CHECKING:
    from carto_cli.io.loaded_map import LoadedMap

__all__ = ["Auto", "Configured", "Continued", "MapRequest", "MapResult", "Plan", "TopicChoice", "build", "execute",
           "map_sessions", "merge_maps", "planned", "read_options", "resolve_laser_pose", "survey_mount",
           "with_sessions"]


@dataclass(frozen=True)
class MapResult(SlamResult):
    """A map as :func:`execute` made it: the core's result, with how it was made and the verdict on it."""

    laser_pose_source: str = ""
    selection: TopicSelection | None = None
    regime: Regime | None = None  # what --profile auto measured (None for a named profile)
    auto: AutoChoice | None = None  # and what it chose
    quality: MapQuality | None = None  # carto's own verdict on the map (mapping.quality)
    warnings: tuple[str, ...] = ()  # what the recording held that mapping dropped (io.content)
    options: Options | None = None  # the options the map was built with (auto's choice)
    # A map of several recordings (sessions): each one's trajectory after the joint optimization, and the links
    sessions: tuple[Session, ...] = ()
    links: tuple[SessionLink, ...] = ()
    trimmed: tuple[Trimmed, ...] = ()  # what later sessions superseded, trimmed from the graph (mapping.lifelong)
    # What cleaning drew free (mapping.cleaning): None when the map was not cleaned (--no-clean, or too large)
    transients: Transients | None = None
    alignment: Squaring | None = None  # how --align turned the map frame (None: not asked)

    @property
    def configured(self) -> Configured:
        """The options and system that made this map (after auto's fallback, not what it chose first)."""
        assert self.options is not None  # execute records them
        return Configured(self.options, self.regime, self.auto, self.stats.get("algorithm", Algorithm.CARTOGRAPHER))

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
            "cleaning": None if self.transients is None else {
                "removed_cells": len(self.transients), "occupied_cells": self.transients.candidates},
        } | ({"sessions": self.sessions_report()} if self.sessions else {}) | (
            {"align": self.alignment.to_dict()} if self.alignment is not None else {})

    def sessions_report(self) -> dict:
        """What sessions.json holds: every recording's trajectory and whether it is in the map, and the links."""
        trimmed = {x.trajectory: x.to_dict() for x in self.trimmed}
        return {"schema": "carto.sessions v1",
                "sessions": [{"trajectory": x.trajectory, "recording": x.name, "scans": len(x.times),
                              "linked": x.linked} | ({"trimmed": trimmed[x.trajectory]}
                                                     if x.trajectory in trimmed else {})
                             for x in self.sessions],
                "links": [link.to_dict() for link in self.links],
                # placements the closures agreed on that would have put a session in another's free space
                "refused_placements": self.graph.stats.refused_links if self.graph is not None else 0}


@dataclass(frozen=True)
class Auto:
    """Options chosen from the recording itself (``--profile auto``, what ``carto map`` does with no
    profile), then the user's ``--set`` overrides on top."""

    overrides: tuple[str, ...] = ()

    @functools.cached_property
    def base(self) -> Options:
        """The defaults with the overrides, loaded once: what the recording is read with and auto chooses from
        (a bad ``--set`` fails here)."""
        return load_options(None, list(self.overrides))


@dataclass(frozen=True, slots=True)
class TopicChoice:
    """The ``--scan-topic`` family: what the user named; None leaves a choice to ``io.topics.select_topics``."""

    scan: str | tuple[str, ...] | None = None  # several: lasers mapped together (merged, io.topics)
    odometry: str | None = None
    imu: str | None = None
    odom_frame: str | None = None
    base_frame: str | None = None


@dataclass(frozen=True, slots=True)
class MapRequest:
    """One mapping run as asked, before the recording is looked at. ``source``: a recording file, or a recording
    already open (in memory, simulated). ``algorithm`` None: auto's choice for :class:`Auto` options, else
    Cartographer (also when continuing ``load_state``, whose pose graph is Cartographer's). ``laser_pose``: the
    laser on the robot (x, y, yaw), or each laser's by topic; None: the recording's TF. ``max_scans``: map only
    the first scans. ``jobs``: threads where the work is independent (None: every core); the map does not depend
    on it."""

    source: str | Path | Recording
    options: Options | Auto = Auto()
    algorithm: str | None = None
    topics: TopicChoice = TopicChoice()
    laser_pose: Sequence[float] | Mapping[str, Sequence[float]] | None = None
    use_odometry: bool = True
    loop_closure: bool = True
    load_state: Path | None = None
    max_scans: int | None = None
    jobs: int | None = None
    # Recordings of the same building mapped after ``source``, each a trajectory of its own placed by whole-map
    # loop-closure search (their odometry may restart anywhere)
    later: tuple[str | Path | Recording, ...] = ()
    # How a map of several sessions weighs them: the newest sure evidence drawn, also trimming what later sessions
    # superseded, or all fused alike (mapping.lifelong)
    sessions: SessionPolicy = SessionPolicy.LAST_SEEN
    # After the final optimization, draw free what the whole recording saw through after it was last hit
    # (people, carts, a door that opened: mapping.cleaning)
    clean: bool = True
    # A new map's frame turned square to its building once mapped (mapping.alignment); a continued map keeps its own
    align: Align = Align.AUTO

    def __post_init__(self) -> None:
        # Refused before any recording is read or state loaded: mapping would refuse only after both.
        if self.algorithm is not None and self.algorithm not in ALGORITHMS:
            raise CartoError(f"--algorithm: unknown algorithm '{self.algorithm}' (choose from "
                             f"{', '.join(ALGORITHMS)})")
        if self.load_state is not None and self.algorithm in GMAPPING_PIPELINE:
            raise CartoError(f"--load-state continues a Cartographer pose graph; {self.algorithm} starts every map "
                             "afresh (drop --load-state or use --algorithm cartographer)", self.load_state)
        if self.later and self.algorithm in GMAPPING_PIPELINE:
            raise CartoError(f"several recordings make one Cartographer pose graph; {self.algorithm} maps one "
                             "recording (give one, or use --algorithm cartographer)")

    @property
    def system(self) -> str | None:
        """The mapping system asked for; None: auto chooses."""
        if self.algorithm is None and (self.load_state is not None or self.later):
            return Algorithm.CARTOGRAPHER
        return self.algorithm

    @property
    def name(self) -> str:
        """The recording's name, as map.carto lists it."""
        return Path(self.source).name if isinstance(self.source, (str, Path)) else self.source.path.name


@dataclass(frozen=True)
class Configured:
    options: Options
    regime: Regime | None = None
    auto: AutoChoice | None = None
    algorithm: str = Algorithm.CARTOGRAPHER  # what maps: the caller's choice, else auto's, else Cartographer


@dataclass(frozen=True, eq=False)
class Continued:
    """The map a run extends: its pose graph's state, the recordings it was made of, and each earlier session's
    scans (whose poses the joint optimization will move)."""

    state: PoseGraphState
    recordings: tuple[str, ...]
    sessions: tuple[SessionScans, ...]
    # What a saved map's cleaning removed, with its nodes' times and poses as saved (carried into the new map)
    removed: Removed | None = None

    @property
    def next_trajectory(self) -> int:
        """The id the run's trajectory takes."""
        ids = [int(t) for t in self.state.node_trajectories] + [e.trajectory for e in self.state.submaps]
        return max(ids) + 1 if ids else 0

    @classmethod
    def of_loaded(cls, loaded: LoadedMap) -> Continued:
        """A saved map (--load-state): its earlier sessions are known by their nodes."""
        _finish(loaded.submaps)
        recordings = tuple(loaded.metadata.recordings)
        sessions = []
        for t in sorted({int(v) for v in loaded.node_trajectories}):
            nodes = np.flatnonzero(loaded.node_trajectories == t)
            name = recordings[t] if t < len(recordings) else f"trajectory {t}"
            sessions.append(SessionScans(t, name, loaded.node_times[nodes], loaded.node_local_poses[nodes], nodes))
        removed = None if loaded.transients is None or not len(loaded.transients) else Removed(
            loaded.transients, np.asarray(loaded.node_times), np.asarray(loaded.node_global_poses))
        return cls(loaded.to_state(), recordings, tuple(sessions), removed)

    @classmethod
    def of_result(cls, result: MapResult, plan: Plan, trajectory: int) -> Continued:
        """The map just made by ``plan`` (its trajectory ``trajectory``), to be extended in memory."""
        assert result.graph is not None  # Cartographer's
        earlier = plan.continued.sessions if plan.continued is not None else ()
        return cls(result.graph.to_state(), plan.recordings, earlier + (_own_scans(result, plan, trajectory),),
                   plan.continued.removed if plan.continued is not None else None)


@dataclass(frozen=True, eq=False)
class Removed:
    """What a saved map's cleaning removed (in its frame), and its nodes' times and global poses as saved: enough
    to carry each cell wherever the node that first saw it has moved since (:meth:`centres_in`)."""

    transients: Transients
    node_times: np.ndarray
    node_poses: np.ndarray

    def centres_in(self, moved: np.ndarray) -> np.ndarray:
        """(n, 2) the cells' centres carried by ``moved`` (the same nodes' global poses now)."""
        order = np.argsort(self.node_times, kind="stable")
        at = np.clip(np.searchsorted(self.node_times[order], self.transients.spans[:, 0]), 0, len(order) - 1)
        node = order[at]
        move = transform.compose(moved[node], transform.inverse(self.node_poses[node]))
        centres = self.transients.centres()
        return transform.compose(move, np.column_stack([centres, np.zeros(len(centres))]))[:, :2]


def _finish(submaps: Sequence[Submap]) -> None:
    """A session that is over takes no more scans: its last submaps are finished, as Cartographer's
    FinishTrajectory does, so that a later session's whole-map searches can match against them too."""
    for submap in submaps:
        if not submap.finished:
            submap.finish()


def _own_scans(result: MapResult, plan: Plan, trajectory: int) -> SessionScans:
    """The scans ``plan`` mapped as trajectory ``trajectory`` of ``result``'s graph."""
    assert result.graph is not None
    own = np.flatnonzero(np.asarray(result.graph.node_trajectory) == trajectory)
    # The node at or before each scan: the one whose correction carries it, as Slam poses its scans
    at = np.clip(np.searchsorted(result.node_scans, np.arange(len(result.times)), side="right") - 1, 0, None)
    return SessionScans(trajectory, plan.request.name, result.times, result.local_poses, own[at])


@dataclass(frozen=True)
class Plan:
    """A :class:`MapRequest` resolved against its opened recording: everything mapping needs, decided once before
    the first scan. It may be executed more than once (each execution reads the recording again)."""

    request: MapRequest
    recording: Recording
    selection: TopicSelection
    mount: np.ndarray  # the laser on the robot (x, y, yaw)
    mount_source: str  # where that came from, in words
    configured: Configured
    continued: Continued | None = None  # the map this run extends (--load-state, or the sessions before)
    stream: RecordStream | None = None  # the recording's records, read ahead (None: read them here)

    @property
    def recordings(self) -> tuple[str, ...]:
        """The recordings the map will have been built from, in order."""
        earlier = self.continued.recordings if self.continued is not None else ()
        return earlier + (self.request.name,)

    @property
    def may_fall_back(self) -> bool:
        """Auto chose GMapping by itself: a map it judges less than ``ok`` is made again with Cartographer
        (:func:`execute`)."""
        auto = self.configured.auto
        return (isinstance(self.request.options, Auto) and auto is not None and auto.chose_algorithm
                and auto.algorithm == Algorithm.GMAPPING and self.configured.regime is not None)

    @property
    def scan_count(self) -> int:
        """Scans mapping will be fed (what a progress bar counts to): the scan topic's messages; with several
        lasers merged, about as many as the fastest laser's (a window holds one scan of each at most)."""
        counts = {t.name: t.count for t in self.recording.topics()}
        return max(counts.get(topic, 0) for topic in self.selection.scan_topics)


def read_options(options: Options | Auto) -> ReadOptions:
    """How to read a recording for these options (the 3D point-cloud slice)."""
    tb = (options.base if isinstance(options, Auto) else options).trajectory_builder_2d
    return ReadOptions(min_z=tb.min_z, max_z=tb.max_z, cloud_band=tb.cloud_band)


@contextmanager
def planned(request: MapRequest, timer: Any = None, *, continued: Continued | None = None) -> Iterator[Plan]:
    """Open ``request``'s recording (unless it came open), choose its topics, start reading ahead, load or compile
    the kernels, survey and configure: the :class:`Plan`, for as long as the recording stays open. ``continued``:
    the map to extend (else ``request.load_state``'s, if any)."""
    with _opened(request) as recording:
        t = request.topics
        selection = select_topics(recording, t.scan, t.odometry, t.imu, odom_frame=t.odom_frame,
                                  base_frame=t.base_frame, laser_poses=_laser_poses(request.laser_pose))
        # --no-odometry: the survey must not count on odometry local SLAM will not get.
        surveyed = selection if request.use_odometry else dataclasses.replace(selection, odometry=None)
        # Started first: with two jobs or more the records are decoded in a child while this process loads its
        # kernels, surveys and maps (io.read_ahead).
        with RecordStream(recording, surveyed, surveyed.topics, jobs=request.jobs) as stream:
            # Before the survey, which needs the matchers: on a cold cache every kernel the run will use is
            # compiled here at once, on every core (GMapping's only if it was asked for: auto rarely picks it).
            kernels.warm_up(timer, systems=(request.system or Algorithm.CARTOGRAPHER,))
            yield resolve(request, recording, selection, stream=stream, timer=timer, continued=continued)


@contextmanager
def _opened(request: MapRequest) -> Iterator[Recording]:
    if isinstance(request.source, (str, Path)):
        with open_recording(request.source, read_options(request.options)) as recording:
            yield recording
    else:
        yield request.source


def _laser_poses(laser_pose: Sequence[float] | Mapping[str, Sequence[float]] | None
                 ) -> dict[str | None, Sequence[float]] | None:
    """``MapRequest.laser_pose`` by topic (None: the one laser's, unnamed)."""
    if laser_pose is None:
        return None
    if isinstance(laser_pose, Mapping):
        return {str(k): v for k, v in laser_pose.items()}
    return {None: laser_pose}


def resolve(request: MapRequest, recording: Recording, selection: TopicSelection, *,
            stream: RecordStream | None = None, timer: Any = None, continued: Continued | None = None) -> Plan:
    """The :class:`Plan` for ``request`` on an opened ``recording`` whose topics are ``selection``: the laser's
    mount, the options and system (for :class:`Auto` the survey's choice; ``request.algorithm`` wins), the saved
    map to continue. ``stream``: the records mapping will read (the survey looks at their start). Several lasers
    reach mapping merged in the tracking frame (``selection.lasers``): the laser mapping sees is at its origin."""
    scan_frame = first_scan_frame(recording, selection.scan)
    if scan_frame is None:
        raise CartoError(f"no scans on {selection.scan}", recording.path)
    if selection.lasers:
        if request.system in GMAPPING_PIPELINE:
            raise CartoError(f"{request.system} maps one laser's scans; {len(selection.lasers)} lasers are merged "
                             f"({', '.join(selection.scan_topics)}): choose one with --scan-topic, or use "
                             "--algorithm cartographer")
        mount, mount_source = np.zeros(3), selection.describe_lasers()
    else:
        poses = _laser_poses(request.laser_pose) or {}
        explicit = next(iter(poses.values()), None)
        mount, mount_source = resolve_laser_pose(recording, scan_frame, None if explicit is None else
                                                 transform.as_pose(explicit).reshape(3),
                                                 selection.tf_odometry.fixed if selection.tf_odometry else ())
    spec = request.options
    if isinstance(spec, Options):
        configured = Configured(spec, algorithm=request.system or Algorithm.CARTOGRAPHER)
    else:
        # The odometry check sizes the particle filter's motion model: a Cartographer run does not need it
        check = request.system in (None, Algorithm.GMAPPING)
        surveyed = selection if request.use_odometry else dataclasses.replace(selection, odometry=None)
        regime = survey(recording, surveyed, check_odometry=check, laser_pose=mount if check else None, timer=timer,
                        stream=stream)
        configured = configure_regime(regime, spec, request.system)
    if continued is None and request.load_state is not None:
        from carto_cli.io.map_file import load_map  # reads pose graphs: only a run that continues one needs it

        continued = Continued.of_loaded(load_map(request.load_state))
    return Plan(request, recording, selection, mount, mount_source, configured, continued, stream)


def survey_mount(recording: Recording, selection: TopicSelection, laser_pose: Any = None) -> np.ndarray | None:
    """The laser's mount as mapping will resolve it (None without scans): several lasers' scans come merged in the
    tracking frame, at its origin."""
    if selection.lasers:
        return np.zeros(3)
    scan_frame = first_scan_frame(recording, selection.scan)
    if scan_frame is None:
        return None
    return resolve_laser_pose(recording, scan_frame, laser_pose,
                              selection.tf_odometry.fixed if selection.tf_odometry else ())[0]


def configure_regime(regime: Regime, spec: Auto, algorithm: str | None = None) -> Configured:
    """The options and system auto chooses for a surveyed ``regime`` (``algorithm``, when given, wins), the
    user's ``--set`` on top."""
    base = spec.base
    g = base.gmapping
    choice = choose(regime, base_max_range=base.trajectory_builder_2d.max_range, algorithm=algorithm,
                    gmapping_max_range=g.maxRange, gmapping_noise=(g.srr, g.srt, g.str, g.stt))
    return Configured(load_options(choice.profile, choice.settings + list(spec.overrides)), regime, choice,
                      choice.algorithm)


def execute(plan: Plan, *, timer: Any = None, on_scan: Callable[[int], None] | None = None) -> MapResult:
    """Map by ``plan``. When auto chose GMapping and judges its map less than ``ok``, the recording is mapped
    again with Cartographer's key-scan settings and the map the verdict prefers is kept: the particle filter's
    outcome varies from run to run (aces: 0.05 m with 30 particles, 0.33 m with 50, judged suspect) where
    Cartographer's does not. On a tie GMapping's stays, the system auto chose for the regime (key scans: better
    on four of five buildings left out one at a time, docs/gmapping.md; fhw: both judged suspect, GMapping's
    0.053 m against Cartographer's 0.114 m). After a second mapping the result's ``wall_time_s`` and
    ``scans_per_s`` cover both, and ``first_pass_wall_time_s`` the first. ``timer``: the stages' times;
    ``on_scan``: called with 1 for every scan fed (a progress bar)."""
    started = _time.perf_counter()
    result = _map_once(plan, plan.configured, timer, on_scan)
    if not plan.may_fall_back or result.quality is None or result.quality.ok:
        return result
    assert plan.configured.regime is not None and isinstance(plan.request.options, Auto)  # may_fall_back's
    other = configure_regime(plan.configured.regime, plan.request.options, Algorithm.CARTOGRAPHER)
    assert other.auto is not None
    first_wall = float(result.stats.get("wall_time_s", float("nan")))
    again = _map_once(plan, other, timer, on_scan)
    wall = _time.perf_counter() - started

    def both(r: MapResult) -> RunStats:
        stats = r.stats.copy()
        stats["wall_time_s"] = wall
        stats["first_pass_wall_time_s"] = first_wall
        stats["scans_per_s"] = r.stats["scans"] / wall if wall > 0 else float("nan")
        return stats

    if again.quality is None or LEVELS.index(again.quality.verdict) < LEVELS.index(result.quality.verdict):
        note = (f"gmapping's map judged {result.quality.verdict}; mapped again with cartographer, judged "
                f"{again.quality.verdict if again.quality else 'not'}")
        return dataclasses.replace(again, stats=both(again), auto=dataclasses.replace(other.auto, note=note))
    assert result.auto is not None  # auto chose GMapping
    note = f"cartographer's map judged {again.quality.verdict}: kept gmapping's, judged {result.quality.verdict}"
    return dataclasses.replace(result, stats=both(result), auto=dataclasses.replace(result.auto, note=note))


def build(recording: Recording, options: Options, *, laser_pose: Sequence[float] | None = None, timer: Any = None,
          on_scan: Callable[[int], None] | None = None, use_odometry: bool = True, max_scans: int | None = None,
          loop_closure: bool = True, algorithm: str = Algorithm.CARTOGRAPHER, jobs: int | None = None) -> MapResult:
    """Map an opened ``recording`` with fixed ``options`` (tests, tuning trials, benchmarks that hold a recording
    and its options already): :func:`execute` of the request, its records read here."""
    request = MapRequest(recording, options, algorithm, laser_pose=laser_pose, use_odometry=use_odometry,
                         loop_closure=loop_closure, max_scans=max_scans, jobs=jobs)
    return execute(resolve(request, recording, select_topics(recording), timer=timer), timer=timer, on_scan=on_scan)


def resolve_laser_pose(recording: Recording, scan_frame: str | None, explicit,
                       fixed_tf: Sequence[Transform] = ()) -> tuple[np.ndarray, str]:
    """--laser-pose wins; else static TF; else transforms of /tf that never moved (``fixed_tf``: a mount broadcast
    on /tf); else the laser is at the tracking frame (``io.topics.laser_mount``)."""
    return laser_mount(recording, scan_frame, explicit, fixed_tf)


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


def _map_once(plan: Plan, configured: Configured, timer: Any,
              on_scan: Callable[[int], None] | None) -> MapResult:
    """One pass of the recording through the system ``configured`` names, and the verdict on its map."""
    slam, trajectory_id = _start_system(plan, configured, timer)
    content = ContentCheck()
    try:
        _feed(plan, configured, slam, content, on_scan)
    except BaseException:
        try:
            slam.close(abandon=True)  # Ctrl-C or a bad recording: do not make the user wait for the graph
        except Exception:
            pass
        raise
    core = slam.finish()
    stats = core.stats.copy()
    peak = peak_rss_mb()
    # or of this process and the pose graph's together while that one ran (mapping.slam), if higher
    together = stats.get("graph_process_peak_memory_mb", 0.0)
    stats["peak_memory_mb"] = None if peak is None else max(peak, together)
    quality = None
    if core.graph is not None:
        with slam.timer.stage("quality"):
            quality = assess(core, core.graph.odometry.samples(trajectory_id))
    fields = {f.name: getattr(core, f.name) for f in dataclasses.fields(SlamResult)}
    result = MapResult(**(fields | {"stats": stats}), laser_pose_source=plan.mount_source, selection=plan.selection,
                       regime=configured.regime, auto=configured.auto, quality=quality,
                       warnings=tuple(plan.recording.warnings) + tuple(content.warnings()), options=configured.options)
    if plan.continued is not None:
        with slam.timer.stage("sessions"):
            result = _with_sessions(result, plan, trajectory_id)
    return result


def _with_sessions(result: MapResult, plan: Plan, trajectory: int) -> MapResult:
    """``with_sessions`` of a map that continued ``plan.continued``'s, its own trajectory ``trajectory``."""
    assert plan.continued is not None
    return with_sessions(result, plan.continued.sessions + (_own_scans(result, plan, trajectory),))


def with_sessions(result: MapResult, scans: Sequence[SessionScans]) -> MapResult:
    """A map of several sessions (``scans``: each one's, in trajectory order): every session's trajectory after the
    joint optimization, the links between them, and a verdict that fails when one is linked to none. An unlinked
    session's submaps are left out of the map image: they lie in a frame of their own, which drawn at the map's
    origin would overlay unrelated walls. ``carto map A B`` and ``carto merge`` both report through it."""
    graph = result.graph
    assert graph is not None
    links = session_links(graph)
    first = min(trajectories(graph))
    linked = linked_to(first, links)
    sessions = tuple(Session(x.trajectory, x.name, x.times, x.poses(graph), x.trajectory in linked) for x in scans)
    unlinked = [x for x in sessions if not x.linked]
    checks = list(result.quality.checks) if result.quality is not None else []
    if links:
        # The closures of one link place the session alike when it is right; a look-alike place mixed in splits
        # them (within the link rule's own tolerance: suspect at twice it, failed at five times)
        worst = max(links, key=lambda link: float(link.spread[2]))
        tolerance = math.degrees(CONFIRM_MAX_ROTATION)
        checks.append(QualityCheck("session_links", math.degrees(float(worst.spread[2])), 2 * tolerance,
                                   5 * tolerance, "deg", f"spread of the headings the closures between trajectories "
                                   f"{worst.a} and {worst.b} give the one in the other"))
    image = result.image
    if unlinked:
        kept = [e for e in graph.submaps if e.trajectory in linked]
        image = AssembledImage([e.submap.grid for e in kept], [e.local_to_global() for e in kept])
        checks.append(QualityCheck("unlinked_sessions", float(len(unlinked)), 0.0, 0.0, "",
                                   "recording(s) linked by no loop closure to the first, left out of the map: "
                                   + ", ".join(x.name for x in unlinked)))
    return dataclasses.replace(result, sessions=sessions, links=tuple(links), image=image,
                               quality=MapQuality.of(checks))


def map_sessions(request: MapRequest, *, timer: Any = None, on_scan: Callable[[int], None] | None = None,
                 on_plan: Callable[[Plan], None] | None = None) -> MapResult:
    """Every recording of ``request`` (``source``, then ``later``) into one map, one trajectory each, in order:
    the first (or ``load_state``'s map) fixes the map frame, each later one continues the pose graph the one
    before left, mapped with the first one's options. ``on_plan`` hears each plan before it is executed. One
    recording: :func:`execute` of its plan."""
    for source in request.later:  # a missing later recording is said before the first is mapped, not after
        if isinstance(source, (str, Path)) and not Path(source).exists():
            raise CartoError("no such file or directory", source)
    result: MapResult | None = None
    continued: Continued | None = None
    returns: dict[int, np.ndarray] = {}  # every session's nodes' returns, by node (cleaning's evidence)
    removed: Removed | None = None  # what --load-state's map had removed
    first = dataclasses.replace(request, later=(), algorithm=request.system)
    for source in (request.source,) + request.later:
        one = first if result is None else dataclasses.replace(
            first, source=source, options=result.configured.options, algorithm=Algorithm.CARTOGRAPHER,
            load_state=None)
        with planned(one, timer, continued=continued) as plan:
            if on_plan is not None:
                on_plan(plan)
            result = execute(plan, timer=timer, on_scan=on_scan)
            returns.update(enumerate(result.node_returns, start=result.first_node))
            removed = removed or (plan.continued.removed if plan.continued is not None else None)
            if request.later:
                trajectory = plan.continued.next_trajectory if plan.continued is not None else 0
                assert result.graph is not None  # Cartographer's
                _finish([e.submap for e in result.graph.submaps if e.trajectory == trajectory])
                continued = Continued.of_result(result, plan, trajectory)
    assert result is not None
    if result.sessions and request.sessions != SessionPolicy.FUSE:
        result = _as_last_seen(result, timer, trim=request.sessions == SessionPolicy.LIFELONG)
    # Trimming renumbered the nodes: what is left of them is judged by the returns the graph keeps, and what the
    # loaded map removed can no longer be carried by its nodes
    if result.trimmed:
        return finished(result, request, timer, {})
    return finished(result, request, timer, returns, removed)


def finished(result: MapResult, request: MapRequest, timer: Any = None,
             returns: dict[int, np.ndarray] | None = None, removed: Removed | None = None) -> MapResult:
    """The last steps of every map, once its poses are final: turned square to its building (``request.align``),
    then cleaned of what left during the recording (``request.clean``), judged by ``returns`` (by node; None: the
    result's own nodes'), with what a continued map's cleaning had ``removed`` carried over."""
    result = _aligned(result, request, timer)
    if not request.clean:
        return result
    if returns is None:
        returns = dict(enumerate(result.node_returns, start=result.first_node))
    return cleaned(result, timer, returns, removed)


def _aligned(result: MapResult, request: MapRequest, timer: Any) -> MapResult:
    """``result`` square to its building as ``request.align`` asks (``mapping.alignment``): every trajectory of a
    new map turned together, once; a map that continues a saved one keeps that one's frame, which its earlier
    trajectories, and whatever was placed in it since, are in."""
    if request.align == Align.NONE:
        return result
    with (timer or NullTimer()).stage("align"):
        if request.load_state is not None:
            found = Squaring(0.0, "frame of the loaded map kept")
        else:
            found = alignment.squaring(alignment.wall_axes(result.image))
        rotation = found.rotation
        if rotation:
            result = dataclasses.replace(
                alignment.turned(result, rotation),
                sessions=tuple(dataclasses.replace(x, poses=alignment.turned_poses(x.poses, rotation))
                               for x in result.sessions))
    # In the statistics (and so in map.carto's metadata) only when turned: a map square already is saved as before
    stats = result.stats | {"aligned_deg": math.degrees(rotation)} if rotation else result.stats
    return dataclasses.replace(result, alignment=found, stats=stats)


def cleaned(result: MapResult, timer: Any = None, returns: dict[int, np.ndarray] | None = None,
            removed: Removed | None = None) -> MapResult:
    """``result`` with its image cleaned of what stood only a while (``mapping.cleaning``), judged by every
    node's returns at its final pose (``returns``, by node; a node without: its loop-closure points, all a
    saved map keeps). What a continued map's cleaning had ``removed`` (its nodes first in the graph) stays removed
    unless a later node's return hit it again. A map too large to hold whole is left as it is (``transients``
    None)."""
    image, graph = result.image, result.graph
    if graph is None or graph.num_nodes == 0 or image.shape[0] * image.shape[1] > EAGER_CELLS:
        return result
    returns = returns or {}
    points = [returns.get(i, p) for i, p in enumerate(graph.node_points)]
    poses = np.asarray(graph.global_poses)
    with (timer or NullTimer()).stage("clean"):
        found = find_transients(image.probability, image.origin, image.resolution, points, poses,
                                np.asarray(graph.node_times), result.laser_pose)
        if removed is not None:
            found = _with_removed(found, removed, points, poses)
        if len(found):
            image = cleaned_image(image, found)
    return dataclasses.replace(result, image=image, transients=found)


def _as_last_seen(result: MapResult, timer: Any, *, trim: bool) -> MapResult:
    """The finished map of several sessions as last seen (``mapping.lifelong``): its image with the newest sure
    evidence winning, and with ``trim`` its graph trimmed of what later sessions superseded. The sessions'
    trajectories were taken before, so each stays whole."""
    assert result.graph is not None and result.options is not None
    with (timer or NullTimer()).stage("last seen"):
        seen = last_seen(result.graph.to_state(), [x.trajectory for x in result.sessions if x.linked], trim=trim)
        graph = PoseGraph.from_state(result.options, seen.state) if seen.trimmed else result.graph
    return dataclasses.replace(result, graph=graph, image=seen.image, trimmed=seen.trimmed)


def merge_maps(maps: Sequence[LoadedMap], *, timer: Any = None, jobs: int | None = None,
               on_total: Callable[[int], None] | None = None,
               on_nodes: Callable[[int], None] | None = None) -> MapResult:
    """Saved maps (other robots, other days) into one, without their recordings, in order: the first fixes the map
    frame and gives the options, each later one is placed by loop-closure search against the ones before it
    (``mapping.merging``); reported as a map of several recordings (:func:`with_sessions`), drawn as last seen
    (a later map's sure cells over an earlier's). The maps' last submaps are finished in place. ``on_total`` and
    ``on_nodes``: the searches' progress in nodes (``mapping.merging.merge_states``)."""
    if len(maps) < 2:
        raise CartoError("give two maps or more to merge")
    started = _time.perf_counter()
    options = maps[0].options
    merged = merge_states(options, [m.to_state() for m in maps], timer=timer, jobs=jobs, on_total=on_total,
                          on_nodes=on_nodes)
    graph = merged.graph
    scans: list[SessionScans] = []
    first_node = 0
    for loaded, renumber in zip(maps, merged.trajectories):
        scans.extend(_saved_scans(loaded, renumber, first_node))
        first_node += loaded.num_nodes
    last = scans[-1]
    image = AssembledImage([e.submap.grid for e in graph.submaps], [e.local_to_global() for e in graph.submaps])
    loops = graph.constraints.is_loop_closure
    closures = np.concatenate([graph.global_poses[graph.constraints.node[loops], :2],
                               graph.submap_global_poses[graph.constraints.submap[loops], :2]], axis=1)
    wall = _time.perf_counter() - started
    count = sum(len(x.times) for x in scans)
    peak = peak_rss_mb()
    stats: RunStats = {
        "maps": len(maps), "scans": count, "poses": count, "nodes": graph.num_nodes, "submaps": len(graph.submaps),
        "wall_time_s": wall, "scans_per_s": count / wall if wall > 0 else float("nan"),
        "constraints": len(graph.constraints), "loop_closures": graph.constraints.num_loop_closures,
        "loop_closure_searches": graph.builder.stats.searched,
        "whole_map_searches": graph.builder.stats.global_searches,
        "optimizations": graph.stats.optimizations, "optimization_time_s": graph.stats.optimization_time_s,
        "precomputation_bytes": graph.builder.stacks.peak_bytes, "precomputations": graph.builder.stacks.misses,
        "precomputation_evictions": graph.builder.stacks.evictions, "peak_memory_mb": peak}
    # The scans of the last map as the map's own trajectory (trajectory.tum, map.png), as `carto map A B` has the
    # last recording's; every map's are in its trajectory_N.tum
    at = np.searchsorted(last.nodes, np.unique(last.nodes))
    core = SlamResult(times=last.times, poses=last.poses(graph), local_poses=last.local_poses, node_scans=at,
                      submaps=[e.submap for e in graph.submaps], submap_poses=graph.submap_global_poses, image=image,
                      laser_pose=maps[0].laser_pose if maps[0].laser_pose is not None else np.zeros(3), stats=stats,
                      loop_closures=closures, graph=graph)
    quality = assess(core)
    fields = {f.name: getattr(core, f.name) for f in dataclasses.fields(SlamResult)}
    result = MapResult(**fields, laser_pose_source=maps[0].metadata.laser_pose_source or "", quality=quality,
                       options=options)
    # As last seen: where a later map is sure of a cell it draws it (nothing is trimmed)
    return _with_carried(_as_last_seen(with_sessions(result, scans), timer, trim=False), maps)


def _with_removed(found: Transients, removed: Removed, points: Sequence[np.ndarray], poses: np.ndarray
                  ) -> Transients:
    """``found`` and what a continued map had ``removed``, carried to where its nodes (the graph's first) are
    now, but for the cells a later node's return hit: something stands there again."""
    n = len(removed.node_times)
    centres = removed.centres_in(poses[:n])
    res = found.resolution
    flat, offsets = flat_points(list(points[n:]))
    at = poses[n:][np.repeat(np.arange(len(offsets) - 1), np.diff(offsets))]
    c, s = np.cos(at[:, 2]), np.sin(at[:, 2])
    ends = np.column_stack([c * flat[:, 0] - s * flat[:, 1] + at[:, 0], s * flat[:, 0] + c * flat[:, 1] + at[:, 1]])
    keep = ~_rows_in(np.floor(centres / res).astype(np.int64), np.floor(ends / res).astype(np.int64))
    return Transients.of_centres(res, np.concatenate([found.centres(), centres[keep]]),
                                 np.concatenate([found.spans, removed.transients.spans[keep]]),
                                 np.concatenate([found.hits, removed.transients.hits[keep]]),
                                 np.concatenate([found.after, removed.transients.after[keep]]), found.candidates)


def _rows_in(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per row of ``a`` (n, 2 int): whether it is a row of ``b``."""
    if not len(a) or not len(b):
        return np.zeros(len(a), bool)
    return np.isin(_cell_key(a), _cell_key(b))


def _cell_key(cells: np.ndarray) -> np.ndarray:
    """One int64 per cell (ix, iy)."""
    return cells[:, 0].astype(np.int64) * (1 << 32) + (cells[:, 1].astype(np.int64) & 0xFFFFFFFF)


def _with_carried(result: MapResult, maps: Sequence[LoadedMap]) -> MapResult:
    """A merged map drawn without what each map's cleaning removed (``LoadedMap.transients``; their submaps still
    hold it): each cell carried by the move of the map's node that first saw it (:meth:`Removed.centres_in`), from
    the map's frame into the merged one."""
    assert result.graph is not None
    if result.image.shape[0] * result.image.shape[1] > EAGER_CELLS:
        return result  # as cleaning leaves a map too large to hold whole
    merged = np.asarray(result.graph.global_poses)
    parts, first, resolution = [], 0, None
    for loaded in maps:
        found, n = loaded.transients, loaded.num_nodes
        if found is not None and len(found) and n:
            removed = Removed(found, np.asarray(loaded.node_times), np.asarray(loaded.node_global_poses))
            parts.append((removed.centres_in(merged[first:first + n]), found))
            resolution = resolution or found.resolution
        first += n
    if not parts or resolution is None:
        return result
    carried = Transients.of_centres(resolution, np.concatenate([c for c, _ in parts]),
                                    np.concatenate([f.spans for _, f in parts]),
                                    np.concatenate([f.hits for _, f in parts]),
                                    np.concatenate([f.after for _, f in parts]))
    return dataclasses.replace(result, image=cleaned_image(result.image, carried), transients=carried)


def _saved_scans(loaded: LoadedMap, renumber: dict[int, int], first_node: int) -> list[SessionScans]:
    """A saved map's sessions as trajectories ``renumber`` of a merged graph whose node ids start at ``first_node``.
    A map of one recording keeps every posed scan and each node's scan: by every scan, each carried by the node at
    or before it as mapping posed it; else (several recordings, a .pbstream) by its nodes, as ``--load-state``."""
    recordings = loaded.metadata.recordings
    out = []
    for t, new in sorted(renumber.items()):
        nodes = np.flatnonzero(loaded.node_trajectories == t)
        if not len(nodes):
            continue
        name = recordings[t] if t < len(recordings) else f"{loaded.path.name} trajectory {t}"
        saved = loaded.trajectory
        if saved is not None and len(saved) and loaded.node_scans is not None and len(renumber) == 1:
            at = np.clip(np.searchsorted(loaded.node_scans, np.arange(len(saved)), side="right") - 1, 0, None)
            correction = transform.compose(loaded.node_global_poses[at],
                                           transform.inverse(loaded.node_local_poses[at]))
            local = transform.compose(transform.inverse(correction), saved.poses)
            out.append(SessionScans(new, name, saved.t, local, at + first_node))
        else:
            out.append(SessionScans(new, name, loaded.node_times[nodes], loaded.node_local_poses[nodes],
                                    nodes + first_node))
    return out


def _start_system(plan: Plan, configured: Configured, timer: Any) -> tuple[MappingSystem, int]:
    """The mapping system ``configured`` names, and the trajectory it maps. A run that continues a saved map
    becomes the next trajectory of that map's pose graph, linked to the earlier ones by loop closures, as
    Cartographer's offline node does with --load_state_filename."""
    wall0 = _time.perf_counter()
    request, options, algorithm = plan.request, configured.options, configured.algorithm
    if algorithm == Algorithm.GMAPPING:
        from carto_cli.gmapping.filter import GMappingSlam  # a Cartographer run never loads it (0.4 s)

        return GMappingSlam(options, laser_pose=plan.mount, timer=timer, started=wall0, jobs=request.jobs), 0
    if algorithm == Algorithm.SCAN_TO_MAP:
        from carto_cli.gmapping.front_end import ScanToMapSlam

        return ScanToMapSlam(options, laser_pose=plan.mount, timer=timer, started=wall0, jobs=request.jobs), 0
    graph = None
    trajectory_id = 0
    if plan.continued is not None:
        graph = PoseGraph.from_state(options, plan.continued.state, timer=timer, loop_closure=request.loop_closure)
        trajectory_id = plan.continued.next_trajectory
    return Slam(options, laser_pose=plan.mount, timer=timer, loop_closure=request.loop_closure, graph=graph,
                trajectory_id=trajectory_id, started=wall0, jobs=request.jobs), trajectory_id


def _feed(plan: Plan, configured: Configured, slam: MappingSystem, content: ContentCheck,
          on_scan: Callable[[int], None] | None) -> None:
    """The recording's records to ``slam`` in time order: the scans (up to ``max_scans``), the odometry unless
    turned off, the IMU where the system uses it; what mapping cannot use is dropped by ``content``."""
    request, selection = plan.request, plan.selection
    topics = list(selection.scan_topics)
    if request.use_odometry and selection.odometry:
        topics.append(selection.odometry)
    if (selection.imu and configured.options.trajectory_builder_2d.use_imu_data
            and configured.algorithm not in GMAPPING_PIPELINE):
        topics.append(selection.imu)
    records = (plan.stream.records(topics, slam.timer) if plan.stream is not None
               else selected_records(plan.recording, selection, topics))
    for record in _timed(content.filter(records), slam.timer):
        if isinstance(record, Scan):
            if request.max_scans is not None and slam.num_scans >= request.max_scans:
                break
            slam.add_scan(record)
            if on_scan is not None:
                on_scan(1)
        elif isinstance(record, Odometry):
            slam.add_odometry(record)
        elif isinstance(record, Imu):
            slam.add_imu(record)
    if slam.num_poses == 0:
        raise CartoError("no scan could be matched (all scans empty after filtering?)", plan.recording.path)
