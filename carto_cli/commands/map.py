"""`carto map` as a library call: open, build, write every output. The CLI only parses arguments."""
from __future__ import annotations

import dataclasses
import json
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

from carto_cli.commands.common import check_algorithm, compiling_note
from carto_cli.core import kernels
from carto_cli.core.errors import CartoError
from carto_cli.gmapping import GMAPPING_PIPELINE
from carto_cli.io.atomic import existing_outputs, output_set, write_text_atomic
from carto_cli.io.map_image import render_png, write_map, write_png
from carto_cli.io.read_ahead import RecordStream
from carto_cli.io.trajectory import Trajectory, write_trajectory
from carto_cli.options import Options
from carto_cli.pipeline import Auto, Configured, MapResult, build_configured, configure, opened, read_options

__all__ = ["OUTPUT_NAMES", "MapOutputs", "check_outdir", "compile_note", "default_outdir", "run_map", "summary_line",
           "write_outputs"]

OUTPUT_NAMES = ("map.pgm", "map.yaml", "map.png", "trajectory.tum", "map.carto", "summary.json")
# What a recording's name ends with: cut off for the default output directory, the rest of the name kept
RECORDING_SUFFIXES = (".gz", ".bag", ".mcap", ".db3", ".clf", ".log")


@dataclass
class MapOutputs:
    pgm: Path
    yaml: Path
    png: Path
    trajectory: Path
    state: Path | None
    summary: Path | None = None


def write_outputs(result: MapResult, outdir: Path, options: Options | None = None, *, state: bool = True,
                  recordings=(), jobs: int | None = None) -> MapOutputs:
    """Every output of ``result`` in ``outdir``, as one set: written to a staging directory first and moved into
    place together, so an interrupted or failed write leaves the earlier set (or nothing) as it was. Whether
    an existing set may be replaced is :func:`check_outdir`'s question, asked before mapping."""
    outdir = Path(outdir)
    if 0 in result.image.shape:
        raise CartoError("the map is empty: no scan was inserted", outdir)
    with output_set(outdir, OUTPUT_NAMES) as staging:
        write_map(staging, result.image)
        write_png(staging / "map.png", render_png(result.image, result.poses, result.loop_closures))
        write_trajectory(staging / "trajectory.tum", Trajectory.from_poses(result.times, result.poses), fmt="tum")
        wrote_state = False
        if state and options is not None and result.graph is not None:
            from carto_cli.io.map_file import save_map

            save_map(staging / "map.carto", result, options, recordings=recordings, jobs=jobs)
            wrote_state = True
        write_text_atomic(staging / "summary.json", json.dumps(result.summary(), indent=1, default=float) + "\n")
    return MapOutputs(outdir / "map.pgm", outdir / "map.yaml", outdir / "map.png", outdir / "trajectory.tum",
                      outdir / "map.carto" if wrote_state else None, outdir / "summary.json")


def default_outdir(recording_path: Path) -> Path:
    """``NAME_map`` in the current directory, NAME the recording's whole name without its suffixes
    (robot.2024.05.01.bag -> robot.2024.05.01_map, scans.clf.gz -> scans_map). The current directory, as
    rosbag's and ros2 bag's tools write theirs: recordings often sit on a read-only share or a robot's disk."""
    recording_path = Path(recording_path)
    name = recording_path.name.rstrip("/")
    while True:
        cut = next((s for s in RECORDING_SUFFIXES if name.lower().endswith(s) and len(name) > len(s)), None)
        if cut is None:
            break
        name = name[:-len(cut)]
    return Path(f"{name}_map")


def check_outdir(outdir: Path, *, force: bool = False) -> None:
    """Refuse, before any work, an output directory that is a file, or that holds an earlier map unless
    ``force``."""
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise CartoError("exists and is not a directory; the outputs go into a directory (give another -o)",
                         outdir)
    taken = existing_outputs(outdir, OUTPUT_NAMES)
    if taken and not force:
        raise CartoError(f"already holds a map ({', '.join(taken)}); --force replaces it, or give another -o",
                         outdir)


def run_map(
    recording_path: Path,
    outdir: Path | None,
    options: Options | Auto,
    *,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    imu_topic: str | None = None,
    laser_pose=None,
    use_odometry: bool = True,
    odom_frame: str | None = None,
    base_frame: str | None = None,
    timer=None,
    on_scan: Callable[[int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
    loop_closure: bool = True,
    state: bool = True,
    load_state: Path | None = None,
    on_configured: Callable[[Configured], None] | None = None,
    algorithm: str | None = None,
    force: bool = False,
    jobs: int | None = None,
) -> tuple[MapResult, MapOutputs]:
    """Map a recording and write every output (to ``default_outdir`` when ``outdir`` is None); with
    ``load_state`` continue an existing map.carto; with :class:`~carto_cli.pipeline.Auto` options chosen
    from the recording; ``algorithm`` "gmapping" maps with the particle filter (``options.gmapping``), None
    leaves the choice to auto (Cartographer for a named profile). ``timer`` is stopped once the outputs are
    written. An earlier map in the output directory is replaced only with ``force`` (checked before mapping).
    ``jobs``: threads where the work is independent (None: every core); the outputs do not depend on it."""
    if algorithm is not None:
        check_algorithm(algorithm)
    elif load_state is not None:
        algorithm = "cartographer"  # continuing a map.carto's pose graph is Cartographer's
    if load_state is not None and algorithm in GMAPPING_PIPELINE:
        # Before the recording is surveyed and the state loaded: build would refuse only after both.
        raise CartoError(f"--load-state continues a Cartographer pose graph; {algorithm} starts every map afresh "
                         "(drop --load-state or use --algorithm cartographer)", load_state)
    if outdir is None:
        outdir = default_outdir(recording_path)
    check_outdir(outdir, force=force)  # before mapping: not after the whole recording was mapped
    graph = None
    trajectory_id = 0
    recordings = [Path(recording_path).name]
    with opened(recording_path, read_options(options), scan_topic=scan_topic, odom_topic=odom_topic,
                imu_topic=imu_topic, odom_frame=odom_frame, base_frame=base_frame) as source, ExitStack() as stack:
        # --no-odometry: the survey must not count on odometry local SLAM will not get.
        surveyed = source.selection if use_odometry else dataclasses.replace(source.selection, odometry=None)
        # Started first: with two jobs or more the records are decoded in a child while this process loads its
        # kernels, surveys and maps (io.read_ahead).
        stream = stack.enter_context(RecordStream(source.recording, surveyed, surveyed.topics, jobs=jobs))
        # Before the survey, which needs the matchers: on a cold cache every kernel the run will use is compiled
        # here at once, on every core (GMapping's only if it was asked for: auto rarely picks it).
        kernels.warm_up(timer, systems=(algorithm or "cartographer",))
        configured = configure(options, source.recording, surveyed, algorithm, laser_pose, timer=timer,
                               stream=stream)
        if on_configured is not None:
            on_configured(configured)
        if load_state is not None:
            from carto_cli.io.map_file import load_map

            loaded = load_map(load_state)
            graph = loaded.to_pose_graph(configured.options, timer=timer, loop_closure=loop_closure)
            trajectory_id = loaded.next_trajectory_id
            recordings = list(loaded.metadata.recordings) + recordings
        if on_total is not None:
            on_total(source.scan_count)
        chosen = configured
        result, configured = build_configured(
            source.recording, configured, options, selection=source.selection, laser_pose=laser_pose, timer=timer,
            on_scan=on_scan, use_odometry=use_odometry, loop_closure=loop_closure, graph=graph,
            trajectory_id=trajectory_id, jobs=jobs, stream=stream)
        if configured is not chosen and on_configured is not None:
            on_configured(configured)  # auto fell back to another system: say so
        result.regime, result.auto, result.options = configured.regime, configured.auto, configured.options
    outputs = write_outputs(result, outdir, configured.options, state=state, recordings=recordings, jobs=jobs)
    if timer is not None:
        timer.stop()
    return result, outputs


def summary_line(result: MapResult, timer=None, compiled: bool | None = None) -> str:
    """The run in one line. With the run's ``timer`` its wall time is the whole run's (reading, surveying, loading
    or compiling kernels, mapping, writing), and a first run says how much of it went to compiling (``compiled``:
    see :func:`compile_note`); without, the mapping's alone (summary.json's ``wall_time_s``). The rate is the
    mapping's either way, and says so: the whole run's wall divided into the scans would not give it."""
    s = result.stats
    if timer is None:
        wall = f"{s['wall_time_s']:.1f} s wall"
    else:
        # The kernels compile before mapping starts: a wall that left them out would not include what the note
        # says it does.
        wall = f"{timer.snapshot().wall_ns / 1e9:.1f} s wall{compile_note(timer, compiled)}"
    peak = f", {s['peak_memory_mb']:.0f} MB peak memory" if s.get("peak_memory_mb") else ""
    if s.get("algorithm") == "scan-to-map":
        return (f"scan-to-map: {s['scans']} scans ({s['processed_scans']} processed), "
                f"{s.get('loop_closures', 0)} loop closures between passes, "
                f"{s['map_memory_peak_bytes'] / 2**20:.0f} MB distance map, {wall}, {s['scans_per_s']:.0f} scans/s "
                f"mapping{peak}")
    if s.get("algorithm") == "gmapping":
        return (f"gmapping: {s['scans']} scans ({s['processed_scans']} processed), {s['particles']} particles, "
                f"{s['resamplings']} resamplings, {s['map_memory_peak_bytes'] / 2**20:.0f} MB peak map, "
                f"{wall}, {s['scans_per_s']:.0f} scans/s mapping{peak}")
    return (f"{s['scans']} scans, {s['nodes']} nodes, {s['submaps']} submaps, "
            f"{s.get('loop_closures', 0)} loop closures, "
            f"{wall}, {s['scans_per_s']:.0f} scans/s mapping{peak}")


def compile_note(timer, compiled: bool | None = None) -> str:
    """' (incl. N s compiling kernels: later runs ...)' when the run compiled kernels (``compiled``; None: whether
    this process did) and paid noticeably for it, else ''. N is every ``jit warm-up`` stage of the run, wherever
    it ran (a warm-up inside the survey too). Loading cached kernels can take a second too, and is no news."""
    if compiled is None:
        compiled = kernels.compiled_here()
    if not compiled:
        return ""
    return compiling_note(_warm_up_ns(timer.snapshot().root) / 1e9)


def _warm_up_ns(stage) -> int:
    """The time of the warm-up stages under ``stage`` (not counting one inside another twice, nor a concurrent
    branch: work on another thread or process that the wall time does not add up)."""
    if stage.name == kernels.STAGE:
        return stage.total_ns
    return sum(_warm_up_ns(child) for child in stage.children if not child.concurrent)
