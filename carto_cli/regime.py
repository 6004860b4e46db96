"""What kind of recording this is, read before mapping, and the settings chosen from it (``--profile auto``).

A user who runs ``carto map REC`` should not have to know which profile their robot needs. The survey
reads the start of the recording (scans and odometry only, no mapping) and measures what decides the
settings:

* how far and how much the robot moves between consecutive scans: from odometry interpolated at the
  scan times, or, without odometry, from a quick scan-to-scan match of a sample of consecutive pairs.
  Timestamps are not trusted for this: logs with key scans only (CARMEN/Radish) may carry synthetic
  times 1 ms apart, so a "1000 Hz" scan rate would mislead; the motion per scan does not;
* the sensor: beams, field of view, range limit, and whether "no return" is reported as one fixed
  reading at the top of the range (a spike in the range histogram), which must become a miss rather
  than a wall;
* whether odometry and an IMU are present.

:func:`choose` turns that into a base profile plus a few derived settings, each with its reason.
Named profiles and ``--set`` still override everything here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from carto_cli.core import transform
from carto_cli.core.errors import CartoError
from carto_cli.core.records import Odometry, Scan
from carto_cli.gmapping import GMAPPING_PIPELINE, Algorithm
from carto_cli.io.content import ContentCheck
from carto_cli.io.read_ahead import RecordStream
from carto_cli.io.recording import Recording
from carto_cli.io.topics import TopicSelection, selected_records

__all__ = ["AutoChoice", "Regime", "choose", "no_return_value", "survey"]

SURVEY_SCANS = 1500  # enough for the statistics below, a fraction of a second to read
MATCH_PAIRS = 40  # scan-to-scan matches when there is no odometry
# Key scans: a node per scan is what Cartographer's motion filter keeps at 0.2 m / 1 deg;
# above these medians local SLAM sees a new piece of the building with every scan.
SPARSE_STEP = 0.25  # m
SPARSE_TURN = math.radians(5.0)
# The particle filter's motion noise from the measured odometry error (m per m): GMapping's srr is a standard
# deviation per metre, the measure a median of |2-D error| per metre, which for a Gaussian is 1.177 of it
# (Rayleigh); a margin over that keeps room for the match's own error and for a rougher stretch later on.
RAYLEIGH_MEDIAN = math.sqrt(2.0 * math.log(2.0))
MOTION_NOISE_MARGIN = 1.5
# Odometry is never trusted more than a fifth of GMapping's defaults (a climb must still be able to leave it) nor
# distrusted beyond twice them (the proposal's lattice is sized for a match, not for a search)
MOTION_NOISE_SCALE = (0.2, 2.0)
# Seconds of local SLAM's poses its velocity is read from when several lasers' windows are merged (unevenly spaced)
MERGED_POSE_QUEUE = 0.2
NO_RETURN_SHARE = 0.002  # a single range value this common at the top of the range is a "no return" marker


@dataclass(frozen=True)
class Regime:
    scans: int  # scans surveyed
    beams: int  # median beams per scan
    fov: float  # rad
    range_max: float  # the sensor's stated maximum (finite), or the largest reading
    no_return: float | None  # the fixed reading that means "no return", if any
    odometry: bool
    imu: bool
    motion_source: str  # "odometry" | "scan matching" | "none"
    step_median: float  # m between consecutive scans
    step_p90: float
    turn_median: float  # rad between consecutive scans
    turn_p90: float
    scan_rate: float | None  # Hz from timestamps (None when fewer than two scans)
    # How far odometry can be trusted (key scans with odometry): its median translation error per metre
    # travelled against the scans matched on their own map (gmapping.odometry_check; None: not measured)
    odometry_error: float | None = None
    # Several lasers' scans merged into one a window (io.topics): their topics; () for one laser
    lasers: tuple[str, ...] = ()

    @property
    def sparse(self) -> bool:
        return self.step_median >= SPARSE_STEP or self.turn_median >= SPARSE_TURN

    @property
    def kind(self) -> str:
        return "key scans" if self.sparse else "dense scans"

    def describe(self) -> str:
        rate = f"{self.scan_rate:.3g} Hz, " if self.scan_rate else ""
        moves = (f"{self.step_median:.2f} m / {math.degrees(self.turn_median):.1f} deg per scan "
                 f"(p90 {self.step_p90:.2f} m / {math.degrees(self.turn_p90):.0f} deg, {self.motion_source})")
        sensor = f"{self.beams} beams / {math.degrees(self.fov):.0f} deg, range {self.range_max:.3g} m"
        if self.no_return is not None:
            sensor += f", no return = {self.no_return:.4g} m"
        inputs = ("odometry" if self.odometry else "no odometry") + (", IMU" if self.imu else "")
        if self.odometry_error is not None:
            inputs += f" (off the scans by {100 * self.odometry_error:.1f} % of the travel)"
        if self.lasers:
            sensor = f"{len(self.lasers)} lasers merged ({', '.join(self.lasers)}), {sensor}"
        return f"{self.kind}: {rate}{moves}; {sensor}; {inputs}"

    def to_dict(self) -> dict:
        return {
            "kind": self.kind, "scans_surveyed": self.scans, "beams": self.beams, "fov_rad": self.fov,
            "range_max_m": self.range_max, "no_return_m": self.no_return, "odometry": self.odometry,
            "imu": self.imu, "motion_source": self.motion_source, "step_median_m": self.step_median,
            "step_p90_m": self.step_p90, "turn_median_rad": self.turn_median, "turn_p90_rad": self.turn_p90,
            "scan_rate_hz": self.scan_rate, "odometry_error_m_per_m": self.odometry_error,
            "lasers": list(self.lasers),
        }


@dataclass(frozen=True)
class AutoChoice:
    profile: str  # packaged base profile
    settings: list[str] = field(default_factory=list)  # "key=value", applied before the user's --set
    reasons: list[str] = field(default_factory=list)
    algorithm: str = Algorithm.CARTOGRAPHER  # the mapping system (an Algorithm, or its name)
    chose_algorithm: bool = False  # auto chose it (not the user's --algorithm): it may fall back
    note: str = ""  # what happened after the choice (a fallback)

    def describe(self) -> str:
        extra = f" + {len(self.settings)} derived settings" if self.settings else ""
        system = "" if self.algorithm == Algorithm.CARTOGRAPHER else f", algorithm {self.algorithm}"
        note = f" ({self.note})" if self.note else ""
        return f"profile {self.profile}{extra}{system}{note}"


def no_return_value(ranges: np.ndarray) -> float | None:
    """The top-of-range reading that repeats far more often than a real distance can (e.g. 81.83, 50.0)."""
    finite = ranges[np.isfinite(ranges) & (ranges > 0)]
    if finite.size == 0:
        return None
    top = float(finite.max())
    if np.count_nonzero(finite >= top - 0.01) < NO_RETURN_SHARE * finite.size:
        return None
    return top


def _scan_to_scan(scans: list[Scan]) -> np.ndarray:
    """(k, 3) relative motions of a sample of consecutive scan pairs, each matched by correlative search
    in a one-scan grid: the motion estimate of a recording without odometry."""
    from carto_cli.core.parallel import map_ordered
    from carto_cli.mapping.submaps import ActiveSubmaps
    from carto_cli.matching import correlative, least_squares
    from carto_cli.sensor.range_filter import crop_scan
    from carto_cli.sensor.voxel_filter import adaptive_voxel_filter, voxel_filter

    if len(scans) < 2:
        return np.zeros((0, 3))
    picks = np.unique(np.linspace(0, len(scans) - 2, min(MATCH_PAIRS, len(scans) - 1)).astype(int))
    crop: dict[str, Any] = dict(min_range=0.0, max_range=30.0, missing_data_ray_length=1.0)
    mount = (0.0, 0.0, 0.0)

    def match(i: int) -> np.ndarray | None:
        a, b = crop_scan(scans[i], mount=mount, **crop), crop_scan(scans[i + 1], mount=mount, **crop)
        if len(a.returns) < 10 or len(b.returns) < 10:
            return None
        # A coarse grid keeps a window as wide as a key scan's motion (1 m, 45 deg) cheap.
        active = ActiveSubmaps(num_range_data=1, resolution=0.1)
        active.insert(a)
        submap = active.matching_submap
        assert submap is not None
        grid = submap.grid
        points = adaptive_voxel_filter(voxel_filter(b.returns, 0.025), max_length=0.5, min_num_points=200)
        guess = correlative.match(grid, points, np.zeros(3), linear_search_window=1.0,
                                  angular_search_window=math.radians(45.0))
        return least_squares.match(grid, points, guess.pose, target_translation=guess.pose[:2],
                                   translation_weight=1.0, rotation_weight=1.0).pose

    # On threads (the matchers' kernels release the GIL): the survey is a tenth of a short run's time
    out = [pose for pose in map_ordered(match, picks) if pose is not None]
    return np.array(out).reshape(-1, 3)


def survey(recording: Recording, selection: TopicSelection, *, max_scans: int = SURVEY_SCANS,
           check_odometry: bool = True, laser_pose=None, timer=None, stream: RecordStream | None = None) -> Regime:
    """Read up to ``max_scans`` scans (and the odometry alongside) and measure the recording's regime. With
    ``check_odometry``, key scans with odometry are also matched to measure the odometry's error (the particle
    filter's motion model is sized from it; about a second); ``laser_pose``: the laser's mount on the robot, as
    mapping resolves it (``pipeline.resolve_laser_pose``; None: at the robot's origin); ``timer``: where the
    check's kernels are warmed up (compiled on a fresh install: the ``jit warm-up`` stage); ``stream``: the
    recording's records as mapping will read them (what the survey reads is then not decoded twice)."""
    topics = list(selection.scan_topics) + ([selection.odometry] if selection.odometry else [])
    scans: list[Scan] = []
    odometry: list[Odometry] = []
    # What mapping will not use (io.content) must not shape the settings either; mapping reports it.
    records = stream.prefix(topics) if stream is not None else selected_records(recording, selection, topics)
    for record in ContentCheck().filter(records):
        if isinstance(record, Scan):
            if len(scans) >= max_scans:
                break
            scans.append(record)
        elif isinstance(record, Odometry):
            odometry.append(record)
    if not scans:
        raise CartoError(f"no scans on {selection.scan}", recording.path)
    times = np.array([s.time for s in scans])
    beams = int(np.median([s.num_beams for s in scans]))
    fov = float(np.median([float(np.ptp(s.angles)) if s.num_beams > 1 else 0.0 for s in scans]))
    stated = [s.range_max for s in scans if math.isfinite(s.range_max) and s.range_max > 0]
    ranges = np.concatenate([s.ranges for s in scans]).astype(np.float64)
    finite = ranges[np.isfinite(ranges)]
    range_max = float(np.median(stated)) if stated else (float(finite.max()) if finite.size else 0.0)
    dt = np.diff(times)
    scan_rate = 1.0 / float(np.median(dt)) if dt.size and np.median(dt) > 0 else None

    motions = np.zeros((0, 3))
    source = "none"
    odo = np.array([(o.time, o.x, o.y, o.yaw) for o in odometry]).reshape(-1, 4)
    if len(odo) >= 2:
        inside = (times >= odo[0, 0]) & (times <= odo[-1, 0])
        t = times[inside]
        if t.size >= 2:
            yaw = np.unwrap(odo[:, 3])
            at = np.stack([np.interp(t, odo[:, 0], odo[:, 1]), np.interp(t, odo[:, 0], odo[:, 2]),
                           np.interp(t, odo[:, 0], yaw)], axis=1)
            motions = transform.relative(at[:-1], at[1:])
            source = "odometry"
    if source == "none":
        motions = _scan_to_scan(scans)
        source = "scan matching" if len(motions) else "none"
    step = np.hypot(motions[:, 0], motions[:, 1]) if len(motions) else np.zeros(1)
    turn = np.abs(transform.wrap_angle(motions[:, 2])) if len(motions) else np.zeros(1)
    no_return = no_return_value(ranges)
    odometry_error = None
    if check_odometry and source == "odometry" and (np.median(step) >= SPARSE_STEP
                                                    or np.median(turn) >= SPARSE_TURN):
        from carto_cli.gmapping.odometry_check import odometry_error as measure
        from carto_cli.options import Options

        odometry_error = measure(scans, odometry, Options(),
                                 laser_pose=(0.0, 0.0, 0.0) if laser_pose is None else laser_pose,
                                 max_range=None if no_return is None else no_return - 0.1, timer=timer)
    return Regime(
        scans=len(scans), beams=beams, fov=fov, range_max=range_max, no_return=no_return,
        odometry=bool(selection.odometry), imu=bool(selection.imu), motion_source=source,
        step_median=float(np.median(step)), step_p90=float(np.percentile(step, 90)),
        turn_median=float(np.median(turn)), turn_p90=float(np.percentile(turn, 90)), scan_rate=scan_rate,
        odometry_error=odometry_error, lasers=tuple(x.topic for x in selection.lasers),
    )


def _system(regime: Regime, reasons: list[str]) -> str:
    """The mapping system for ``regime``, the reason appended to ``reasons``."""
    if len(regime.lasers) > 1:
        reasons.append(f"{len(regime.lasers)} lasers merged into one scan a window: Cartographer (GMapping maps one "
                       "laser's scans)")
        return Algorithm.CARTOGRAPHER
    if regime.sparse and regime.odometry:
        reasons.append("key scans with odometry: GMapping's particle filter (measured better than Cartographer on "
                       "such recordings)")
        return Algorithm.GMAPPING
    return Algorithm.CARTOGRAPHER


def _merged_lasers(regime: Regime, settings: list[str], reasons: list[str]) -> None:
    """What several lasers merged need (appended to ``settings`` and ``reasons``). Their windows come 14 to 100 ms
    apart (two lasers at 10 and 7 Hz): a velocity read off the last two poses 14 ms apart threw maps without
    odometry off by 10-64 m; read over 0.2 s, 4-7 mm (bench/multi_lidar.py). With odometry the velocity is
    odometry's, and this changes nothing."""
    if len(regime.lasers) > 1:
        settings.append("trajectory_builder_2d.pose_extrapolator.constant_velocity.pose_queue_duration="
                        f"{MERGED_POSE_QUEUE:g}")
        reasons.append(f"several lasers' windows come unevenly: velocity from the poses of the last "
                       f"{MERGED_POSE_QUEUE:g} s")


def choose(regime: Regime, base_max_range: float = 30.0, algorithm: str | None = None,
           gmapping_max_range: float = 80.0,
           gmapping_noise: tuple[float, float, float, float] = (0.1, 0.2, 0.1, 0.2)) -> AutoChoice:
    """The mapping system, base profile and derived settings for ``regime`` (see docs/profiles.md, 'auto').

    ``algorithm`` None lets the regime choose: GMapping for key scans with odometry, where it was measured
    better than Cartographer on four of the five key-scan buildings (intel 0.063 vs 0.127 m, edmonton 0.056
    vs 0.077, fhw 0.062 vs 0.114, orebro 0.051 vs 0.167) and worse on one (aces 0.33 vs 0.048, which the
    verdict reports as suspect; docs/gmapping.md), Cartographer otherwise. With GMapping the particle filter's
    range is also set, its default (80 m) being far beyond Cartographer's, and its motion noise (``gmapping_noise``:
    the base srr, srt, str, stt) scaled to the odometry error the survey measured."""
    settings: list[str] = []
    reasons: list[str] = []
    chose = algorithm is None
    if algorithm is None:
        algorithm = _system(regime, reasons)
    rt = "trajectory_builder_2d.real_time_correlative_scan_matcher"
    if regime.sparse and algorithm in GMAPPING_PIPELINE:
        # The sparse profile still sets the submaps map.carto is written with; its matcher settings do nothing.
        profile = "sparse"
    elif regime.sparse:
        profile = "sparse"
        reasons.append("key scans far apart: the sparse profile (wide loop-closure windows, 35-scan submaps)")
        if regime.odometry:
            settings.append(f"{rt}.motion_scaled_prior=true")
            reasons.append("scan-matching window and prior sized to the odometry's error over each scan's motion")
            # Without the odometry prior a scan lying mostly in unknown space would score as well as a match.
            settings.append(f"{rt}.unknown_probability=0.5")
            reasons.append("each key scan sees new space: never-observed cells count as no evidence, not as free")
        # Partial overlap keeps right matches of key scans below the stock 0.55 (orebro: none found). A lower
        # threshold lets false matches in too (intel 0.11 -> 0.63 m at 0.45), so a closure must be confirmed by a
        # neighbouring node's closure to the same submap (Karto's chain rule) and its rays must not cross the
        # submap's walls; with those, 0.40 won the leave-one-building-out comparison (docs/measurements.md).
        settings.append("pose_graph.constraint_builder.min_score=0.4")
        settings.append("pose_graph.constraint_builder.confirm_loop_closures=true")
        settings.append("pose_graph.constraint_builder.max_see_through=0.15")
        reasons.append("a key scan overlaps a submap only partly: loop-closure score threshold 0.4, a closure "
                       "counts once a neighbouring node's closure agrees, and none whose rays cross walls")
    elif regime.odometry:
        profile = "wheeled"
        reasons.append("dense scans with odometry: the wheeled profile (scan decides the heading)")
    else:
        profile = "office"
        reasons.append("dense scans without odometry: the correlative matcher on, a weak constant-velocity prior")
    _merged_lasers(regime, settings, reasons)
    if regime.no_return is not None and regime.no_return <= base_max_range + 0.05:
        settings.append(f"trajectory_builder_2d.max_range={max(regime.no_return - 0.1, 0.1):.3f}")
        reasons.append(f"'no return' is reported as {regime.no_return:.4g} m: readings there become misses")
    if (algorithm in GMAPPING_PIPELINE and regime.no_return is not None
            and regime.no_return <= gmapping_max_range + 0.05):
        # GMapping skips beams beyond maxRange; a fixed 'no return' reading inside it would draw phantom walls
        # on a circle around every pose (aces: 50 m readings, 0.36 m error before this).
        settings.append(f"gmapping.maxRange={max(regime.no_return - 0.1, 0.1):.3f}")
        reasons.append(f"'no return' is reported as {regime.no_return:.4g} m: gmapping skips those beams")
    if algorithm == Algorithm.GMAPPING and regime.odometry_error is not None and gmapping_noise[0] > 0:
        lo, hi = MOTION_NOISE_SCALE
        scale = MOTION_NOISE_MARGIN * regime.odometry_error / RAYLEIGH_MEDIAN / gmapping_noise[0]
        scale = min(max(scale, lo), hi)
        for name, value in zip(("srr", "srt", "str", "stt"), gmapping_noise):
            settings.append(f"gmapping.{name}={value * scale:.4g}")
        reasons.append(f"odometry off the scans by {100 * regime.odometry_error:.1f} % of the travel: the motion "
                       f"model's noise x {scale:.2f} (particles spread where odometry leaves doubt, not beyond)")
    return AutoChoice(profile, settings, reasons, algorithm, chose)
