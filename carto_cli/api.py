"""carto's Python API: what the command line does, as functions, for scripts and notebooks.

This module is the stable surface: its names and their parameters change only with a new major version;
modules below it may change in any release. Units are metres, seconds and radians throughout.

    from carto_cli import api

    run = api.map_recording("run.bag")           # `carto map run.bag`, nothing written yet
    run.write("run_map")                         # map.pgm/.yaml/.png, trajectory.tum, map.carto, summary.json
    scans = [api.scan(t, ranges, angle_min=-2.0, angle_increment=0.01, range_max=30.0) for t, ranges in data]
    run = api.map_records(scans + [api.odometry(t, x, y, yaw) for t, x, y, yaw in odo])   # from arrays
    answer = api.relocalize("run_map/map.carto", scans[10], prior=(1.0, 2.0, 0.3))        # .verdict, .pose
    report = api.evaluate("run_map/trajectory.tum", relations="run.relations")            # .relations.mean_translation
    ates = api.evaluate_sessions(["ab/trajectory_0.tum", "ab/trajectory_1.tum"], ["a.tum", "b.tum"])  # one frame

Scans are de-skewed by the robot's motion during the sweep only when they say how long it took
(``time_increment`` per beam, or ``scan_time``); with both 0 (the default of :func:`scan`) a scan is taken as
instantaneous, as a LaserScan with those fields at 0 is by the command line.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from carto_cli.commands.eval import run_eval, run_eval_sessions
from carto_cli.commands.map import MapOutputs, check_outdir, run_map, write_outputs
from carto_cli.commands.merge import load_maps, run_merge
from carto_cli.commands.relocalize import apply_map_auto, load_relocalization_map
from carto_cli.core.errors import CartoError
from carto_cli.core.records import Odometry, Record, Scan, Transform, beam_angles, yaw_quaternion
from carto_cli.evaluation.metrics import AteResult, Evaluation
from carto_cli.io.sources.memory import MemoryRecording
from carto_cli.mapping.alignment import Align
from carto_cli.options import Options, load_options
from carto_cli.pipeline import Auto, MapRequest, MapResult, map_sessions
from carto_cli.pipeline import merge_maps as _merge_maps
from carto_cli.relocalization import RelocalizationResult, Relocalizer, ScanContext

__all__ = [
    "CartoError",
    "MapRun",
    "ScanContext",
    "evaluate",
    "evaluate_sessions",
    "map_recording",
    "map_recordings",
    "map_records",
    "merge_maps",
    "odometry",
    "options",
    "relocalize",
    "scan",
]


@dataclasses.dataclass
class MapRun:
    """A map in memory: ``result`` (poses, the occupancy image, the verdict, statistics) and the options it was
    built with (what map.carto records)."""

    result: MapResult
    options: Options
    recordings: tuple[str, ...] = ()

    @property
    def poses(self) -> np.ndarray:
        """(n, 3) x, y, yaw of every scan in the map frame."""
        return self.result.poses

    @property
    def quality(self) -> str | None:
        """'ok', 'suspect' or 'failed' (the map's own verdict: a ``MapVerdict``, which is that string)."""
        return None if self.result.quality is None else self.result.quality.verdict

    @property
    def sessions(self) -> tuple:
        """A map of several recordings: each one's trajectory in the map frame after the joint optimization
        (``.name``, ``.times``, ``.poses``, ``.linked``); empty for one recording."""
        return self.result.sessions

    def write(self, outdir: str | Path, *, force: bool = False, state: bool = True) -> MapOutputs:
        """Every output `carto map` writes, into ``outdir`` as one set; an earlier map there only with ``force``."""
        check_outdir(Path(outdir), force=force)
        return write_outputs(self.result, Path(outdir), self.options, state=state, recordings=list(self.recordings))


def options(profile: str | Path | None = None, overrides: Sequence[str] = ()) -> Options | Auto:
    """The options a command would use: ``profile`` None or 'auto' chooses them from each recording (what
    `carto map` does with no profile), else a profile name or YAML path; ``overrides`` as ``--set`` items."""
    if profile in (None, "auto"):
        auto = Auto(tuple(overrides))
        auto.base  # noqa: B018 - a bad override fails here, not once a recording is read
        return auto
    return load_options(profile, overrides)


def map_recording(recording: str | Path, *, profile: str | Path | None = None, overrides: Sequence[str] = (),
                  algorithm: str | None = None, jobs: int | None = None, outdir: str | Path | None = None,
                  force: bool = False, clean: bool = True, align: str = "auto") -> MapRun:
    """Map a recording file as `carto map` does; with ``outdir`` the outputs are written there too. ``clean``
    False: as `carto map --no-clean`. ``align``: "auto" turns the map square to its walls, "none" keeps the
    frame of the first scan (``carto map --align``)."""
    request = MapRequest(Path(recording), options(profile, overrides), algorithm, jobs=jobs, clean=clean,
                         align=Align.named(align))
    if outdir is not None:
        result, _ = run_map(request, Path(outdir), force=force)
    else:
        result = map_sessions(request)  # nothing written: the caller wants the result only
    return MapRun(result, result.configured.options, (Path(recording).name,))


def map_recordings(recordings: Sequence[str | Path], *, profile: str | Path | None = None,
                   overrides: Sequence[str] = (), jobs: int | None = None, outdir: str | Path | None = None,
                   force: bool = False, clean: bool = True) -> MapRun:
    """Several recordings of one building into one map, as `carto map A B ...`: each a trajectory, placed by
    loop closures; ``MapRun.sessions`` says where each is and whether it is linked (``result.links``: how)."""
    if not recordings:
        raise CartoError("no recording to map")
    first, *later = (Path(r) for r in recordings)
    request = MapRequest(first, options(profile, overrides), jobs=jobs, later=tuple(later), clean=clean)
    if outdir is not None:
        result, _ = run_map(request, Path(outdir), force=force)
    else:
        result = map_sessions(request)
    return MapRun(result, result.configured.options, tuple(Path(r).name for r in recordings))


def merge_maps(maps: Sequence[str | Path], *, jobs: int | None = None, outdir: str | Path | None = None,
               force: bool = False) -> MapRun:
    """Saved maps (map.carto or .pbstream) made separately into one, as `carto merge`: the first fixes the frame
    and the options, each later one is placed by loop closures; ``MapRun.sessions`` says where each trajectory is
    and whether it is linked. With ``outdir`` the outputs are written there too."""
    if outdir is not None:
        result, _ = run_merge(maps, Path(outdir), force=force, jobs=jobs)
    else:
        result = _merge_maps(load_maps(maps), jobs=jobs)
    assert result.options is not None  # merge_maps records the first map's
    return MapRun(result, result.options, tuple(x.name for x in result.sessions))


def map_records(records: Iterable[Record], *, laser_pose: Sequence[float] | None = None,
                profile: str | Path | None = None, overrides: Sequence[str] = (), algorithm: str | None = None,
                jobs: int | None = None, clean: bool = True) -> MapRun:
    """Map scans (and odometry / IMU) a program holds, with no file: :func:`scan`, :func:`odometry` or
    ``carto_cli.core.records`` objects, in any order (sorted by time here). ``laser_pose`` (x, y, yaw): the
    laser on the robot (default: at the robot's origin). ``clean`` False: as `carto map --no-clean`."""
    statics: list[Transform] = []
    if laser_pose is not None:
        x, y, yaw = (float(v) for v in laser_pose)
        statics.append(Transform("base_link", "laser", (x, y, 0.0), yaw_quaternion(yaw)))
    recording = MemoryRecording(records, statics)
    if not any(t.kind == "scan" for t in recording.topics()):
        raise CartoError("no scans to map")
    request = MapRequest(recording, options(profile, overrides), algorithm, laser_pose=laser_pose, jobs=jobs,
                         clean=clean)
    result = map_sessions(request)
    return MapRun(result, result.configured.options, ("memory",))


def scan(time: float, ranges, *, angle_min: float, angle_increment: float, range_min: float = 0.0,
         range_max: float = math.inf, frame: str = "laser", time_increment: float = 0.0, scan_time: float = 0.0,
         intensities=None) -> Scan:
    """A LaserScan: ``ranges`` (m) of beams at ``angle_min + i * angle_increment`` (rad). A return outside
    [range_min, range_max] (or inf / NaN) is no return. See the module doc for de-skewing."""
    # Every field as a LaserScan message holds it (float32), so a scan made here maps exactly as the same scan
    # recorded in a bag and read back (tests/test_api.py).
    r = np.asarray(ranges, dtype=np.float32).reshape(-1)

    def f32(v: float) -> float:
        return float(np.float32(v))

    return Scan(float(time), r, beam_angles(f32(angle_min), f32(angle_increment), r.size), frame, "", f32(range_min),
                f32(range_max), f32(angle_min), f32(angle_increment), f32(time_increment), f32(scan_time),
                None if intensities is None else np.asarray(intensities, dtype=np.float32).reshape(-1))


def odometry(time: float, x: float, y: float, yaw: float) -> Odometry:
    """The robot's pose by wheel odometry in its odometry frame at ``time``."""
    return Odometry(float(time), float(x), float(y), float(yaw))


def relocalize(map_file: str | Path, query: Scan, prior: Sequence[float] | None = None, *,
               sigma_xy: float | None = None, sigma_yaw: float | None = None, max_jump: float | None = None,
               laser_pose: Sequence[float] | None = None, profile: str | Path | None = None,
               context: ScanContext | None = None) -> RelocalizationResult:
    """Where ``query`` is in the map (map.carto or a map_server YAML): from ``prior`` (x, y, yaw) or, without,
    by a global search. The answer carries ``pose``, ``verdict`` ('ok' | 'ambiguous' | 'lost') and ``reason``,
    ``covariance``, ``ambiguity`` and ``inlier_fraction`` (docs/localization.md). A map_server map takes carto's
    defaults or ``profile`` (the command line also fits the range to the recording's first scans, which one query
    cannot do); a map.carto without ``profile`` gets its score thresholds scaled to the map, as on the command
    line (``relocalization.auto.choose_for_map``). ``context``: the records of the recording around ``query``
    (``carto_cli.relocalization.ScanContext``), which check an answer no window around the prior confirmed, as
    on the command line. For many queries against one map, build a
    ``carto_cli.relocalization.Relocalizer`` once instead."""
    loaded = load_relocalization_map(Path(map_file), profile)
    apply_map_auto(loaded, profile)
    return Relocalizer(loaded).relocalize(query, prior, sigma_xy=sigma_xy, sigma_yaw=sigma_yaw,
                                          laser_pose=laser_pose, max_jump=max_jump, context=context)


def evaluate(trajectory: str | Path, *, relations: str | Path | None = None,
             ground_truth: str | Path | None = None) -> Evaluation:
    """`carto eval`: relation error (Kümmerle et al.) with ``relations``, ATE and RPE with ``ground_truth``."""
    return run_eval(Path(trajectory), relations=None if relations is None else Path(relations),
                    ground_truth=None if ground_truth is None else Path(ground_truth)).result


def evaluate_sessions(trajectories: Sequence[str | Path], ground_truths: Sequence[str | Path]) -> list[AteResult]:
    """`carto eval T0 T1 ... --ground-truth G...`: the ATE of each trajectory of one map of several recordings
    (``map_recordings``' trajectory_N.tum) in their common frame, under ONE alignment for all (a session placed
    wrongly against the others shows); ``ground_truths`` one for all, or one per trajectory."""
    return run_eval_sessions([Path(t) for t in trajectories], [Path(g) for g in ground_truths]).results
