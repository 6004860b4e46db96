"""`carto info`: what is in a recording: topics, rates, scan geometry, TF, and the problems worth a warning."""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from carto_cli.core.records import Scan, Transform
from carto_cli.io.content import ContentCheck
from carto_cli.io.recording import ReadOptions, Recording
from carto_cli.io.sources.open import open_recording

GAP_FACTOR = 3.0  # a gap is a period longer than this many median periods


@dataclass
class ScanStats:
    beams_min: int = 0
    beams_max: int = 0
    angle_min: float = math.inf
    angle_max: float = -math.inf
    range_min: float = math.inf
    range_max: float = -math.inf
    frames: list[str] = field(default_factory=list)
    source_types: list[str] = field(default_factory=list)
    returns: int = 0
    nan: int = 0
    inf: int = 0
    out_of_limits: int = 0
    # Where each frame's laser sits on the robot, as `carto map` would place it: x, y (m), yaw (deg) and from what
    mounts: list[dict] = field(default_factory=list)
    # A point cloud topic: the height band its clouds are sliced in (``sensor.height_band.HeightBand.to_dict``), with
    # ``described``, the line `carto info` prints
    band: dict | None = None


@dataclass
class TopicReport:
    name: str
    msgtype: str
    kind: str
    count: int
    start: float | None = None
    end: float | None = None
    rate_hz: float | None = None
    median_period: float | None = None
    backwards: int = 0
    gaps: int = 0
    max_gap: float | None = None
    scan: ScanStats | None = None


@dataclass
class RecordingInfo:
    path: str
    format: str
    start: float | None
    end: float | None
    duration: float | None
    topics: list[TopicReport]
    static_transforms: list[dict]
    has_odometry: bool
    has_imu: bool
    warnings: list[str]
    auto: dict | None = None  # what `carto map` with no profile would detect and choose
    auto_unavailable: str | None = None  # why ``auto`` is None: what `carto map` with no flags would stop with
    odometry_source: str | None = None  # where `carto map` takes odometry from: a topic, or TF (odom -> base)
    tf_transforms: list[dict] | None = None  # dynamic TF: the odometry edge and the /tf transforms that never moved

    def to_dict(self) -> dict:
        return _finite(asdict(self))


def _finite(value):
    """``value`` with every infinite float as None: JSON has no infinity, and a point cloud's scans have no range
    limits (``range_max`` inf)."""
    if isinstance(value, float) and math.isinf(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


class _TopicAccumulator:
    def __init__(self):
        self.times: list[float] = []
        self.scan: ScanStats | None = None

    def add(self, record) -> None:
        self.times.append(record.time)
        if isinstance(record, Scan):
            s = self.scan or ScanStats(beams_min=record.num_beams, beams_max=record.num_beams)
            self.scan = s
            r = record.ranges
            n = r.shape[0]
            s.beams_min = min(s.beams_min, n)
            s.beams_max = max(s.beams_max, n)
            if n:
                s.angle_min = min(s.angle_min, float(record.angles.min()))
                s.angle_max = max(s.angle_max, float(record.angles.max()))
            s.range_min = min(s.range_min, float(record.range_min))
            s.range_max = max(s.range_max, float(record.range_max))
            if record.frame not in s.frames:
                s.frames.append(record.frame)
            if record.source_type not in s.source_types:
                s.source_types.append(record.source_type)
            s.returns += n
            nan = np.isnan(r)
            inf = np.isinf(r)
            finite = ~(nan | inf)
            s.nan += int(nan.sum())
            s.inf += int(inf.sum())
            s.out_of_limits += int(((r < record.range_min) | (r > record.range_max))[finite].sum())


def _time_stats(report: TopicReport, times: list[float]) -> None:
    if not times:
        return
    t = np.asarray(times, dtype=np.float64)
    report.start, report.end = float(t.min()), float(t.max())
    if t.size < 2:
        return
    dt = np.diff(t)
    report.backwards = int((dt < 0).sum())
    forward = dt[dt > 0]
    if forward.size:
        median = float(np.median(forward))
        report.median_period = median
        gaps = forward[forward > GAP_FACTOR * median]
        report.gaps = int(gaps.size)
        report.max_gap = float(gaps.max()) if gaps.size else None
    span = report.end - report.start
    if span > 0:
        report.rate_hz = (t.size - 1) / span


def _transform_dict(tf: Transform) -> dict:
    return {
        "parent": tf.parent,
        "child": tf.child,
        "translation": list(tf.translation),
        "rotation": list(tf.rotation),
        "yaw": tf.yaw,
    }


def inspect_recording(recording: Recording, on_record: Callable[[], None] | None = None) -> RecordingInfo:
    """Read the whole recording once and summarise it."""
    infos = recording.topics()
    accumulators = {t.name: _TopicAccumulator() for t in infos}
    supported = [t.name for t in infos if t.kind in ("scan", "odometry", "imu")]
    content = ContentCheck()  # what mapping will drop, reported before mapping; the tables count the file
    for record in recording.records(supported):
        content.accept(record)
        if isinstance(record, Transform):  # static transforms are read apart, by static_transforms()
            continue
        acc = accumulators.get(record.topic)
        if acc is None:  # a reader that names topics differently from topics(); keep it visible
            acc = accumulators[record.topic] = _TopicAccumulator()
        acc.add(record)
        if on_record is not None:
            on_record()

    reports = []
    warnings = list(recording.warnings) + content.warnings()
    kinds = {t.name: t for t in infos}
    for name, acc in accumulators.items():
        info = kinds.get(name)
        report = TopicReport(
            name=name,
            msgtype=info.msgtype if info else "unknown",
            kind=info.kind if info else "unknown",
            count=len(acc.times) if acc.times else (info.count if info else 0),
            scan=acc.scan,
        )
        _time_stats(report, acc.times)
        reports.append(report)
        if report.gaps:
            warnings.append(
                f"{name}: {report.gaps} gap(s) over {GAP_FACTOR:g}x the median period "
                f"({(report.median_period or 0.0) * 1e3:.1f} ms), longest {report.max_gap:.3f} s"
            )
        s = acc.scan
        if s is not None and s.returns:
            for label, n in (("NaN", s.nan), ("Inf", s.inf), ("out-of-limit", s.out_of_limits)):
                share = n / s.returns
                if share > 0.0:
                    warnings.append(f"{name}: {100 * share:.1f}% of ranges are {label}")
            if len(s.frames) > 1:
                warnings.append(f"{name}: scans in several frames: {', '.join(s.frames)}")

    starts = [r.start for r in reports if r.start is not None]
    ends = [r.end for r in reports if r.end is not None]
    start = min(starts) if starts else None
    end = max(ends) if ends else None
    if not any(r.kind == "scan" and r.count for r in reports):
        warnings.append("no laser scans: carto cannot map this recording")
    return RecordingInfo(
        path=str(recording.path),
        format=recording.format,
        start=start,
        end=end,
        duration=(end - start) if start is not None and end is not None else None,
        topics=reports,
        static_transforms=[_transform_dict(tf) for tf in recording.static_transforms()],
        has_odometry=any(r.kind == "odometry" and r.count for r in reports),
        has_imu=any(r.kind == "imu" and r.count for r in reports),
        warnings=warnings,
    )


def run_info(path: str | Path, read: ReadOptions | None = None, *,
             on_total: Callable[[int], None] | None = None,
             on_record: Callable[[], None] | None = None) -> RecordingInfo:
    """Open the recording at ``path`` and summarise it; ``on_total`` hears how many messages will be read."""
    with open_recording(path, read) as rec:
        auto, selection, why_not = _auto(rec)
        if on_total is not None:
            on_total(sum(t.count for t in rec.topics() if t.kind in ("scan", "odometry", "imu")))
        info = inspect_recording(rec, on_record=on_record)
        info.auto = auto
        info.auto_unavailable = why_not
        _place_lasers(rec, info, selection.tf_odometry.fixed if selection is not None and selection.tf_odometry
                      else ())
        for report in info.topics:
            band = rec.cloud_bands.get(report.name)
            if band is not None and report.scan is not None:
                report.scan.band = {**band.to_dict(), "described": band.describe()}
        if selection is not None:
            info.odometry_source = selection.describe_odometry()
            tf = selection.tf_odometry
            if tf is not None:
                info.has_odometry = True
                info.tf_transforms = [{"parent": tf.odom_frame, "child": tf.base_frame, "moving": True}] + [
                    {**_transform_dict(t), "moving": False} for t in tf.fixed]
        return info


def _place_lasers(recording: Recording, info: RecordingInfo, fixed_tf) -> None:
    """Every scan topic's lasers placed as `carto map` places its one (``pipeline.resolve_laser_pose``: static TF,
    else transforms on /tf that never move, else the robot's origin), so that a recording with several lasers
    shows each one's mount."""
    from carto_cli.pipeline import resolve_laser_pose

    for report in info.topics:
        if report.scan is None:
            continue
        for frame in report.scan.frames:
            pose, source = resolve_laser_pose(recording, frame, None, fixed_tf)
            report.scan.mounts.append({"frame": frame, "x": float(pose[0]), "y": float(pose[1]),
                                       "yaw_deg": math.degrees(float(pose[2])), "source": source})


def _auto(recording: Recording):
    """(the regime `carto map` would detect and the settings it would choose, the topics it would read, None);
    (None, None, why) when `carto map` with no flags would stop."""
    from carto_cli.core.errors import CartoError
    from carto_cli.io.topics import select_topics
    from carto_cli.pipeline import survey_mount
    from carto_cli.regime import choose, survey

    try:
        selection = select_topics(recording)
        regime = survey(recording, selection, laser_pose=survey_mount(recording, selection))
    except CartoError as e:
        return None, None, e.message
    choice = choose(regime)
    return ({"detected": regime.describe(), "regime": regime.to_dict(), "profile": choice.profile,
             "settings": choice.settings, "reasons": choice.reasons}, selection, None)


def _fmt_time(t: float | None) -> str:
    if t is None:
        return "-"
    from datetime import datetime, timezone

    # Simulated and CARMEN clocks start near zero; only show a date for wall-clock stamps.
    if t > 1e8:
        return f"{t:.3f} ({datetime.fromtimestamp(t, timezone.utc).strftime('%Y-%m-%d %H:%M:%S')} UTC)"
    return f"{t:.3f}"


def format_info(info: RecordingInfo) -> str:
    lines = [
        f"recording  {info.path}",
        f"format     {info.format}",
        f"start      {_fmt_time(info.start)}",
        f"end        {_fmt_time(info.end)}",
        f"duration   {info.duration:.3f} s" if info.duration is not None else "duration   -",
        "",
        "topics",
    ]
    width = max([len(t.name) for t in info.topics] + [5])
    for t in info.topics:
        rate = f"{t.rate_hz:.2f} Hz" if t.rate_hz else "-"
        lines.append(f"  {t.name:<{width}}  {t.msgtype:<32} {t.count:>7} msgs  {rate}")
        s = t.scan
        if s is not None:
            beams = f"{s.beams_min}" if s.beams_min == s.beams_max else f"{s.beams_min}-{s.beams_max}"
            lines.append(
                f"  {'':<{width}}  beams {beams}, angles {math.degrees(s.angle_min):.1f}° to "
                f"{math.degrees(s.angle_max):.1f}°, ranges {s.range_min:g}-{s.range_max:g} m, "
                f"frame {', '.join(s.frames)}"
            )
            lines.extend(f"  {'':<{width}}  mount {m['frame']}: x {m['x']:.3f} m, y {m['y']:.3f} m, yaw "
                         f"{m['yaw_deg']:.1f}°: {m['source']}" for m in s.mounts)
            if s.band is not None:
                lines.append(f"  {'':<{width}}  cloud band {s.band['described']}")
    lines.append("")
    lines.append(f"odometry   {'yes' if info.has_odometry else 'no'}"
                 + (f" ({info.odometry_source})" if info.odometry_source and info.has_odometry else ""))
    lines.append(f"imu        {'yes' if info.has_imu else 'no'}")
    if info.static_transforms:
        from carto_cli.io.tf_tree import format_tree

        lines.append("static tf")
        tfs = [Transform(t["parent"], t["child"], tuple(t["translation"]), tuple(t["rotation"]))
               for t in info.static_transforms]
        lines.extend(f"  {line}" for line in format_tree(tfs))
    else:
        lines.append("static tf  none")
    if info.tf_transforms:
        lines.append("tf (dynamic)")
        lines.extend(f"  {t['parent']} -> {t['child']}" + ("  (odometry: what map uses)" if t["moving"] else
                                                          "  (never moves: a mount)") for t in info.tf_transforms)
    if info.auto is not None:
        lines.append("")
        lines.append(f"auto       {info.auto['detected']}")
        lines.append(f"           -> profile {info.auto['profile']}" + "".join(
            f"\n              {setting}" for setting in info.auto["settings"]))
    elif info.auto_unavailable is not None:
        lines.append("")
        lines.append(f"auto       none: {info.auto_unavailable}")
    if info.warnings:
        lines.append("")
        lines.append("warnings")
        lines.extend(f"  {w}" for w in info.warnings)
    return "\n".join(lines)
