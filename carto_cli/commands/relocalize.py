"""`carto relocalize` as a library call: load the map, build the relocalizer, answer one scan or a queries file."""
from __future__ import annotations

import csv
import functools
import io
import itertools
import json
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path
from typing import Any, TypeVar, cast

import numpy as np

from carto_cli.core import kernels
from carto_cli.core.errors import CartoError
from carto_cli.core.progress import progress
from carto_cli.core.records import Scan
from carto_cli.io.atomic import existing_outputs, output_set, write_text_atomic
from carto_cli.io.loaded_map import LoadedMap
from carto_cli.io.map_file import load_map
from carto_cli.io.map_server import is_map_server_yaml, load_map_server
from carto_cli.io.recording import ReadOptions, Recording
from carto_cli.io.sources.open import open_recording
from carto_cli.io.topics import TopicSelection, select_topics, selected_records
from carto_cli.io.trajectory import Trajectory, write_trajectory
from carto_cli.options import Options, apply_overrides, load_options
from carto_cli.pipeline import TopicChoice, read_options, resolve_laser_pose
from carto_cli.relocalization import (
    BatchSummary,
    QueryResult,
    RelocalizationResult,
    Relocalizer,
    context_at,
    parse_pose,
    read_queries,
    relocalize_many,
    scan_at,
    write_results_csv,
)
from carto_cli.relocalization.auto import AutoRelocalization, choose_for_map, choose_for_scans
from carto_cli.relocalization.queries import CONTEXT_SECONDS
from carto_cli.relocalization.result import PoseVerdict
from carto_cli.relocalization.tracking import TRACK_COLUMNS, TrackedScan, Tracker, TrackSummary, summarize_track

__all__ = ["TRACK_OUTPUTS", "Prepared", "RelocalizeRequest", "RelocalizeRun", "RelocalizeScans", "TrackRun",
           "apply_map_auto", "default_track_dir", "load_relocalization_map", "prepare", "relocalization_options",
           "run_relocalize", "run_track"]


def load_relocalization_map(map_file: Path, profile: str | Path | None = None) -> LoadedMap:
    """map.carto, or a map_server YAML (its PGM/PNG as the grid: ``io.map_server``).

    ``profile``: for map.carto its ``relocalization`` section replaces the map's own (the scan filtering stays the
    map's, as the map was built with it); a map_server map takes the whole profile (default: carto's defaults).
    None or 'auto': the map's own options (for a map_server map, carto's defaults); ``apply_map_auto`` then
    scales a map.carto's score thresholds to the map, ``_from_scans`` fits a map_server map's range to the scans.
    """
    profile = None if profile == "auto" else profile
    if is_map_server_yaml(map_file):
        return load_map_server(map_file, load_options(profile))
    loaded = load_map(map_file)
    if profile is not None:
        loaded.options = relocalization_options(loaded.options, load_options(profile))
    return loaded


AUTO_SCANS = 50  # scans read to choose a map_server map's settings (regime.no_return_value needs a few hundred
# readings at the top of the range; 50 scans of 360 beams hold 18 000)


def apply_map_auto(loaded: LoadedMap, profile) -> AutoRelocalization | None:
    """The settings chosen from a map.carto itself when no profile was given (``loaded.options`` are replaced by
    them); None when the map's own stand, for a map_server map (its settings come from the scans: ``_from_scans``)
    or with a profile."""
    if profile not in (None, "auto") or _reads_scans(loaded):
        return None
    auto = choose_for_map(loaded.options, loaded)
    loaded.options = auto.options
    return auto if auto.settings else None


def _reads_scans(loaded: LoadedMap) -> bool:
    """Whether the relocalizer needs the recording first: a map that does not know the laser mount (a
    map_server image) takes it from the recording's static TF (and, without a profile, settings from its scans)."""
    return loaded.laser_pose is None


def _from_scans(loaded: LoadedMap, rec, selection: TopicSelection,
                profile) -> tuple[np.ndarray, AutoRelocalization | None]:
    """(the laser mount from the recording's static TF, the settings chosen from its first scans when no profile
    was given: ``loaded.options`` are replaced by them). Several lasers' scans come merged in the tracking frame,
    their mount its origin."""
    records = selected_records(rec, selection, list(selection.scan_topics))
    scans = [r for r in itertools.islice(records, AUTO_SCANS) if isinstance(r, Scan)]
    mount = np.zeros(3) if selection.lasers else resolve_laser_pose(rec, scans[0].frame if scans else None,
                                                                      None)[0]
    auto = None
    if profile in (None, "auto"):
        auto = choose_for_scans(loaded.options, scans)
        loaded.options = auto.options
    return mount, auto


def _relocalizer(loaded: LoadedMap, overrides, warnings: list[str],
                 on_warning: Callable[[str], None] | None, jobs: int | None = None) -> Relocalizer:
    relocalizer = Relocalizer(loaded, apply_overrides(loaded.options, overrides) if overrides else None, jobs=jobs)
    _tell(relocalizer.warnings, warnings, on_warning)
    return relocalizer


def _tell(new: list[str], warnings: list[str], on_warning: Callable[[str], None] | None) -> None:
    """Add ``new`` warnings to the run's and tell them at once (the map's, or what reading a damaged recording
    had to work around)."""
    warnings.extend(new)
    if on_warning is not None:
        for w in new:
            on_warning(w)


def relocalization_options(map_options: Options, profile_options: Options) -> Options:
    """The map's options with the profile's ``relocalization`` section."""
    import dataclasses

    return dataclasses.replace(map_options, relocalization=profile_options.relocalization)


@dataclass(frozen=True, slots=True)
class RelocalizeRequest:
    """A map, a recording and the prior the scans are searched from: what a relocalization (``run_relocalize``,
    through :class:`RelocalizeScans`) and a track (``run_track``) both ask. Built once (by the CLI, or a library
    caller).

    ``map_file`` is a map.carto or a map_server YAML (``load_relocalization_map``, with ``profile``); a map that
    does not know where the laser sits (a map_server image) takes it from the recording's static TF.
    ``initial_pose``: 'x,y,yaw' text or a pose (None: a global search); text is parsed only when it is used, so
    that a bad one is reported after the map and the scan, as the command always has. ``sigma_yaw`` is in radians.
    ``max_jump`` (m): an answer farther than this from its prior is 'lost'. ``overrides`` are ``--set`` items over
    the map's own options. ``read``: how point clouds are sliced (io.recording.ReadOptions; None: as the map's options
    slice them). ``topics``: the scan
    topic, and the odometry (``odometry``, or TF: ``odom_frame`` / ``base_frame``; default the recording's) that
    moves a track's predictions and the scans that check an answer no window around its prior confirmed (``imu``
    is not read). ``jobs``: threads for a batch, or for one query's whole-map search (None: every core); the
    answers are the same for any number.

    ``max_jump`` is checked here (CartoError), so a bad request fails before the map is loaded.
    """

    map_file: Path
    recording: Path
    _: KW_ONLY
    initial_pose: str | Sequence[float] | None = None
    sigma_xy: float | None = None
    sigma_yaw: float | None = None
    max_jump: float | None = None
    profile: str | Path | None = None
    overrides: Sequence[str] = ()
    read: ReadOptions | None = None
    topics: TopicChoice = TopicChoice()
    jobs: int | None = 1

    def __post_init__(self) -> None:
        if self.max_jump is not None and not self.max_jump > 0:
            raise CartoError(f"--max-jump must be > 0 m, got {self.max_jump:g}")


@dataclass(frozen=True, slots=True)
class RelocalizeScans:
    """Which scans of a request's recording ``run_relocalize`` answers: one (``at`` a time or ``scan_index``,
    default the first) from the request's ``initial_pose`` or, with ``global_search``, from none; or every line of
    ``queries`` (each with its own prior; results to ``csv_out``, default QUERIES.results.csv). ``corridor``: search
    only the submaps along the prior's heading (``Relocalizer.relocalize``).

    The choices that exclude each other are checked here (CartoError), after the request's own, in the order the
    command has always reported them.
    """

    request: RelocalizeRequest
    _: KW_ONLY
    at: float | None = None
    scan_index: int | None = None
    global_search: bool = False
    corridor: bool = False
    queries: Path | None = None
    csv_out: Path | None = None

    def __post_init__(self) -> None:
        initial_pose = self.request.initial_pose
        if self.queries is None and not self.global_search and initial_pose is None:
            raise CartoError("give --initial-pose x,y,yaw, or --global, or --queries FILE")
        if self.global_search and initial_pose is not None:
            raise CartoError("--global and --initial-pose exclude each other")
        if self.at is not None and self.scan_index is not None:
            raise CartoError("--at and --scan-index exclude each other")

    @property
    def results_csv(self) -> Path | None:
        """Where a batch's results go; None for one scan."""
        if self.queries is None:
            return None
        return self.csv_out or self.queries.with_suffix(".results.csv")


@dataclass(frozen=True, slots=True)
class Prepared:
    """What a relocalization and a track both start from (``prepare``)."""

    relocalizer: Relocalizer
    recording: Recording  # open while ``prepare``'s context lasts
    selection: TopicSelection  # the scan topic, and the odometry (a topic or TF) that moves a scan's neighbours
    mount: np.ndarray | None  # the laser mount read from the recording (a map that does not know it), else None
    auto: AutoRelocalization | None  # what auto chose from the map (map.carto) or the scans (map_server)
    warnings: list[str]  # the map's and the recording's, each already told to ``on_warning``


@contextmanager
def prepare(request: RelocalizeRequest, on_warning: Callable[[str], None] | None = None) -> Iterator[Prepared]:
    """The request's map loaded (``load_relocalization_map``, with its ``profile``) and its settings chosen
    (``apply_map_auto``), the recording opened and its topics chosen, the relocalizer built (``overrides`` over
    the map's options; ``jobs`` its threads), for as long as the context lasts (the recording stays open). A map
    that knows the laser mount gets its relocalizer before the recording is read, so that its warnings come first;
    one that does not (a map_server image) takes the mount, and without a profile its settings, from the recording
    (``_from_scans``)."""
    profile, overrides, jobs, topics = request.profile, request.overrides, request.jobs, request.topics
    loaded = load_relocalization_map(request.map_file, None if profile == "auto" else profile)
    auto = apply_map_auto(loaded, profile)
    warnings: list[str] = []
    relocalizer = None if _reads_scans(loaded) else _relocalizer(loaded, overrides, warnings, on_warning, jobs)
    # Clouds sliced as the map's were (its cloud_band, min_z, max_z, with the overrides), unless a slice was given.
    read = request.read if request.read is not None else read_options(
        apply_overrides(loaded.options, overrides) if overrides else loaded.options)
    with open_recording(request.recording, read) as rec:
        _tell(rec.warnings, warnings, on_warning)
        selection = select_topics(rec, topics.scan, topics.odometry, odom_frame=topics.odom_frame,
                                  base_frame=topics.base_frame)
        # Several lasers' scans are merged in the tracking frame (io.topics): the laser relocalization sees is at
        # its origin, whatever mount the map was made with
        mount = np.zeros(3) if selection.lasers else None
        if relocalizer is None:
            mount, auto = _from_scans(loaded, rec, selection, profile)
            relocalizer = _relocalizer(loaded, overrides, warnings, on_warning, jobs)
        yield Prepared(relocalizer, rec, selection, mount, auto, warnings)


@dataclass
class RelocalizeRun:
    """What `carto relocalize` answered: one scan (``result``) or a batch (``results``, ``summary``, ``csv``)."""

    warnings: list[str] = field(default_factory=list)
    scan_index: int | None = None
    scan: Scan | None = None
    result: RelocalizationResult | None = None
    results: list[QueryResult] | None = None
    summary: BatchSummary | None = None
    csv: Path | None = None
    auto: AutoRelocalization | None = None  # what auto chose from the map (map.carto) or the scans (map_server)
    compile_s: float = 0.0  # of the run's time, compiling kernels (a first run after installing)

    @property
    def batch(self) -> bool:
        return self.summary is not None

    def to_dict(self) -> dict:
        """JSON-ready: the batch summary, or the one result with its scan's index and time."""
        if self.summary is not None:
            return {**self.summary.to_dict(), **({} if self.auto is None else {"auto": self.auto.describe()})}
        assert self.result is not None and self.scan is not None
        data = self.result.to_dict()
        data["scan_index"] = self.scan_index
        data["scan_time"] = self.scan.time
        if self.auto is not None:
            data["auto"] = self.auto.describe()
        return data


_Run = TypeVar("_Run", bound=Callable[..., Any])


def _noting_compiles(run: _Run) -> _Run:
    """``run``'s result with ``compile_s``: the seconds it spent compiling kernels. Relocalization compiles its
    kernels on first use, not in a warm-up as mapping does, so only numba can say how long that took."""
    @functools.wraps(run)
    def timed(*args, **kwargs):
        with kernels.compile_time() as compiling:
            done = run(*args, **kwargs)
        done.compile_s = compiling()
        return done

    return cast(_Run, timed)


@_noting_compiles
def run_relocalize(scans: RelocalizeScans, *, on_warning: Callable[[str], None] | None = None, quiet: bool = True,
                   force: bool = False) -> RelocalizeRun:
    """Relocalize the scans ``scans`` chooses of its request's recording in the request's map (one scan, or a
    queries file whose results go to ``scans.results_csv``).

    The relocalizer's warnings go to ``on_warning`` as soon as it is built (before any scan is relocalized), and
    into the result. ``quiet=False`` shows a progress bar over a batch (on a terminal). An existing results CSV is
    replaced only with ``force`` (refused before any work). An answer no window around its prior confirmed is
    checked by the scans around its own in the recording, moved by the request's odometry.
    """
    request = scans.request
    csv_out = scans.results_csv
    if csv_out is not None and csv_out.exists() and not force:
        raise CartoError("exists; --force replaces it, or give another --csv", csv_out)

    max_jump = request.max_jump
    with prepare(request, on_warning) as p:
        relocalizer, rec, selection, mount = p.relocalizer, p.recording, p.selection, p.mount
        run = RelocalizeRun(warnings=p.warnings, auto=p.auto)
        if scans.queries is not None:
            qs = read_queries(scans.queries)
            with progress("relocalizing", len(qs), quiet, unit="queries") as bar:
                run.results, run.summary = relocalize_many(relocalizer, rec, qs, corridor=scans.corridor,
                                                           on_query=bar.advance, laser_pose=mount, max_jump=max_jump,
                                                           jobs=request.jobs, selection=selection)
            assert csv_out is not None
            run.csv = write_results_csv(csv_out, run.results)
            return run
        context = None
        if relocalizer.ro.context_scans > 0:
            run.scan_index, run.scan, context = context_at(rec, time=scans.at, index=scans.scan_index,
                                                           context_seconds=CONTEXT_SECONDS,
                                                           selection=selection)
        else:
            run.scan_index, run.scan = scan_at(rec, time=scans.at, index=scans.scan_index, selection=selection)
    # Parsed only now, as the command always has: a bad --initial-pose is reported after the map and the scan.
    initial_pose = request.initial_pose
    prior = (None if scans.global_search
             else parse_pose(initial_pose) if isinstance(initial_pose, str) else initial_pose)
    run.result = relocalizer.relocalize(run.scan, prior, sigma_xy=request.sigma_xy, sigma_yaw=request.sigma_yaw,
                                        corridor=scans.corridor, laser_pose=mount, max_jump=max_jump,
                                        context=context)
    return run


TRACK_OUTPUTS = ("trajectory.tum", "track.csv", "track.json")


@dataclass
class TrackRun:
    """What `carto relocalize --track` wrote and measured."""

    outdir: Path
    summary: TrackSummary
    warnings: list[str] = field(default_factory=list)
    auto: AutoRelocalization | None = None
    compile_s: float = 0.0  # of the run's time, compiling kernels (a first run after installing)

    def to_dict(self) -> dict:
        return {"outdir": str(self.outdir), **self.summary.to_dict(),
                "auto": None if self.auto is None else self.auto.describe()}


def default_track_dir(recording: Path) -> Path:
    """``NAME_track`` in the current directory (NAME as for ``carto map``'s ``NAME_map``)."""
    from carto_cli.commands.map import default_outdir

    out = default_outdir(recording)
    return out.with_name(out.name[:-len("_map")] + "_track")


@_noting_compiles
def run_track(
    request: RelocalizeRequest,
    outdir: Path | None = None,
    *,
    force: bool = False,
    on_warning: Callable[[str], None] | None = None,
    on_scan: Callable[[TrackedScan], None] | None = None,
    on_total: Callable[[int], None] | None = None,
) -> TrackRun:
    """A pose and a verdict for every scan of the request's recording in its map (``relocalization.tracking``):
    the first from the request's ``initial_pose`` or a global search, then each from the previous one moved by
    odometry; writes ``trajectory.tum`` (the scans judged ok), ``track.csv`` (every scan: pose, verdict, source,
    score, sigmas) and ``track.json`` (the summary: verdict counts, time to first fix, scans per second) into
    ``outdir`` (default NAME_track in the current directory) as one set; an earlier set is replaced only with
    ``force``. ``on_total`` hears how many scans the recording holds (before the first ``on_scan``)."""
    recording = request.recording
    outdir = Path(outdir) if outdir is not None else default_track_dir(recording)
    if outdir.exists() and not outdir.is_dir():
        raise CartoError("exists and is not a directory; the outputs go into a directory (give another -o)", outdir)
    taken = existing_outputs(outdir, TRACK_OUTPUTS)
    if taken and not force:
        raise CartoError(f"already holds a track ({', '.join(taken)}); --force replaces it, or give another -o",
                         outdir)
    initial_pose = request.initial_pose
    prior = parse_pose(initial_pose) if isinstance(initial_pose, str) else initial_pose
    t0 = time.perf_counter()
    with prepare(request, on_warning) as p:
        selection = p.selection
        if on_total is not None:
            counts = {t.name: t.count for t in p.recording.topics()}
            on_total(max(counts.get(topic, 0) for topic in selection.scan_topics))
        tracker = Tracker(p.relocalizer, laser_pose=p.mount, max_jump=request.max_jump)
        topics = list(selection.scan_topics) + ([selection.odometry] if selection.odometry else [])
        scans = list(tracker.track(selected_records(p.recording, selection, topics), initial_pose=prior,
                                   sigma_xy=request.sigma_xy, sigma_yaw=request.sigma_yaw, on_scan=on_scan))
    if not scans:
        raise CartoError(f"no scans on {selection.scan}", recording)
    summary = summarize_track(scans, time.perf_counter() - t0, tracker.relocalizations, tracker.timings)
    ok = [s for s in scans if s.verdict == PoseVerdict.OK and s.pose is not None]
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(TRACK_COLUMNS), lineterminator="\n")
    writer.writeheader()
    for s in scans:
        writer.writerow(s.row())
    with output_set(outdir, TRACK_OUTPUTS) as staging:
        poses = np.array([s.pose for s in ok]).reshape(-1, 3)
        write_trajectory(staging / "trajectory.tum", Trajectory.from_poses(np.array([s.time for s in ok]), poses))
        write_text_atomic(staging / "track.csv", buf.getvalue())
        write_text_atomic(staging / "track.json", json.dumps(summary.to_dict(), indent=1) + "\n")
    return TrackRun(outdir, summary, p.warnings, p.auto)
