"""`carto map` as a library call: open, build, write every output. The CLI only parses arguments."""
from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from carto_cli.commands.common import compiling_note
from carto_cli.core import kernels
from carto_cli.core.errors import CartoError
from carto_cli.io.atomic import existing_outputs, output_set, write_text_atomic
from carto_cli.io.map_image import render_png, write_map, write_png
from carto_cli.io.trajectory import Trajectory, write_trajectory
from carto_cli.options import Options
from carto_cli.pipeline import Configured, MapRequest, MapResult, Plan, map_sessions

__all__ = ["OUTPUT_NAMES", "MapOutputs", "check_outdir", "cleaning_lines", "compile_note", "default_outdir",
           "run_map", "sessions_lines", "summary_line", "write_outputs"]

OUTPUT_NAMES = ("map.pgm", "map.yaml", "map.png", "trajectory.tum", "map.carto", "summary.json")
# A map of several recordings also gets one trajectory file per recording (its trajectory id in the name) and the
# report of how they are linked
SESSION_NAMES = ("sessions.json",)
SESSION_GLOB = "trajectory_*.tum"
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
                  recordings=(), jobs: int | None = None, show_removed: bool = False) -> MapOutputs:
    """Every output of ``result`` in ``outdir``, as one set: written to a staging directory first and moved into
    place together, so an interrupted or failed write leaves the earlier set (or nothing) as it was. Whether
    an existing set may be replaced is :func:`check_outdir`'s question, asked before mapping. ``show_removed``:
    map.png marks what cleaning drew free."""
    outdir = Path(outdir)
    if 0 in result.image.shape:
        raise CartoError("the map is empty: no scan was inserted", outdir)
    # One trajectory file per recording of a map of several; those of an earlier set go with it
    sessions = {f"trajectory_{x.trajectory}.tum": x for x in result.sessions}
    names = OUTPUT_NAMES + SESSION_NAMES + tuple(sorted(set(sessions) | {p.name for p in outdir.glob(SESSION_GLOB)}))
    with output_set(outdir, names) as staging:
        write_map(staging, result.image)
        removed = result.transients.centres() if show_removed and result.transients is not None else None
        write_png(staging / "map.png", render_png(result.image, result.poses, result.loop_closures,
                                                  removed_xy=removed))
        write_trajectory(staging / "trajectory.tum", Trajectory.from_poses(result.times, result.poses), fmt="tum")
        wrote_state = False
        if state and options is not None and result.graph is not None:
            from carto_cli.io.map_file import save_map

            save_map(staging / "map.carto", result, options, recordings=recordings, jobs=jobs)
            wrote_state = True
        write_text_atomic(staging / "summary.json", json.dumps(result.summary(), indent=1, default=float) + "\n")
        for name, session in sessions.items():
            write_trajectory(staging / name, Trajectory.from_poses(session.times, session.poses), fmt="tum")
        if sessions:
            write_text_atomic(staging / "sessions.json",
                              json.dumps(result.sessions_report(), indent=1, default=float) + "\n")
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
    request: MapRequest,
    outdir: Path | None = None,
    *,
    timer: Any = None,
    on_scan: Callable[[int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
    on_configured: Callable[[Configured], None] | None = None,
    state: bool = True,
    force: bool = False,
    show_removed: bool = False,
) -> tuple[MapResult, MapOutputs]:
    """Map as ``request`` asks and write every output (to ``default_outdir`` of the recording when ``outdir`` is
    None); ``state``: map.carto too. ``on_configured`` hears the options and system chosen (again when auto fell
    back to another system), ``on_total`` the scans to come, ``on_scan`` each scan fed. ``timer`` is stopped once
    the outputs are written. An earlier map in the output directory is replaced only with ``force`` (checked
    before mapping). ``show_removed``: map.png marks what cleaning drew free."""
    if outdir is None:
        if not isinstance(request.source, (str, Path)):
            raise CartoError("a recording in memory has no name to make an output directory of: give outdir")
        outdir = default_outdir(Path(request.source))
    check_outdir(outdir, force=force)  # before mapping: not after the whole recording was mapped
    plans: list[Plan] = []
    scans = 0

    def on_plan(plan: Plan) -> None:
        nonlocal scans
        if on_configured is not None and not plans:  # the later recordings are mapped with the first's options
            on_configured(plan.configured)
        plans.append(plan)
        scans += plan.scan_count
        if on_total is not None:
            on_total(scans)  # every recording's scans so far: one bar over the whole run

    result = map_sessions(request, timer=timer, on_scan=on_scan, on_plan=on_plan)
    if result.auto is not plans[0].configured.auto and on_configured is not None:
        on_configured(result.configured)  # auto tried another system (execute): say what came of it
    recordings = plans[-1].recordings
    outputs = write_outputs(result, outdir, result.options, state=state, recordings=recordings, jobs=request.jobs,
                            show_removed=show_removed)
    if timer is not None:
        timer.stop()
    return result, outputs


def sessions_lines(result: MapResult) -> list[str]:
    """A map of several recordings in a few lines: each link, each recording linked to none, then what later
    sessions superseded and trimming took from each earlier one."""
    lines = [f"sessions: {link.describe()}" for link in result.links]
    lines += [f"sessions: trajectory {x.trajectory} ({x.name}) is linked to no other: left out of the map"
              for x in result.sessions if not x.linked]
    lines += [f"trimmed: {x.describe()}" for x in result.trimmed]
    refused = result.graph.stats.refused_links if result.graph is not None else 0
    if refused:
        lines.append(f"sessions: {refused} placement(s) refused: they put a session's scans in another's free space")
    return lines


def cleaning_lines(result: MapResult) -> list[str]:
    """What cleaning drew free, in one line (none when it found nothing or did not run)."""
    found = result.transients
    if found is None or not len(found):
        return []
    return [f"cleaned: {len(found)} of {found.candidates} occupied cells drawn free, seen through after they were "
            "last hit (people, carts, doors; kept in map.carto; --no-clean keeps them)"]


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
