"""`carto map` as a library call: open, build, write every output. The CLI only parses arguments."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from carto_cli.io.map_image import render_png, write_map, write_png
from carto_cli.io.sources.open import open_recording
from carto_cli.io.recording import ReadOptions
from carto_cli.io.topics import select_topics
from carto_cli.io.trajectory import Trajectory, write_trajectory
from carto_cli.pipeline import MapResult, build
from carto_cli.options import Options


@dataclass
class MapOutputs:
    pgm: Path
    yaml: Path
    png: Path
    trajectory: Path
    state: Path | None


def write_outputs(result: MapResult, outdir: Path, options: Options | None = None, *, state: bool = True,
                  recordings=()) -> MapOutputs:
    outdir = Path(outdir)
    pgm, yml = write_map(outdir, result.image)
    png = write_png(outdir / "map.png", render_png(result.image, result.poses, result.loop_closures))
    traj = write_trajectory(outdir / "trajectory.tum", Trajectory.from_poses(result.times, result.poses), fmt="tum")
    state_path = None
    if state and options is not None and result.graph is not None:
        from carto_cli.io.map_file import save_map

        state_path = save_map(outdir / "map.carto", result, options, recordings=recordings)
    return MapOutputs(pgm, yml, png, traj, state_path)


def run_map(
    recording_path: Path,
    outdir: Path,
    options: Options,
    *,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    imu_topic: str | None = None,
    laser_pose=None,
    use_odometry: bool = True,
    timer=None,
    on_scan: Callable[[int], None] | None = None,
    on_total: Callable[[int], None] | None = None,
    loop_closure: bool = True,
    state: bool = True,
    load_state: Path | None = None,
) -> tuple[MapResult, MapOutputs]:
    """Map a recording and write every output; with ``load_state`` continue an existing map.carto."""
    graph = None
    trajectory_id = 0
    recordings = [Path(recording_path).name]
    if load_state is not None:
        from carto_cli.io.map_file import load_map

        loaded = load_map(load_state)
        graph = loaded.to_pose_graph(options, timer=timer, loop_closure=loop_closure)
        trajectory_id = loaded.next_trajectory_id
        recordings = list(loaded.metadata.recordings) + recordings
    tb = options.trajectory_builder_2d
    with open_recording(recording_path, ReadOptions(min_z=tb.min_z, max_z=tb.max_z)) as rec:
        selection = select_topics(rec, scan_topic, odom_topic, imu_topic)
        if on_total is not None:
            on_total(next(t.count for t in rec.topics() if t.name == selection.scan))
        result = build(rec, options, selection=selection, laser_pose=laser_pose, timer=timer, on_scan=on_scan,
                       use_odometry=use_odometry, loop_closure=loop_closure, graph=graph,
                       trajectory_id=trajectory_id)
    return result, write_outputs(result, outdir, options, state=state, recordings=recordings)


def summary_line(result: MapResult) -> str:
    s = result.stats
    return (f"{s['scans']} scans, {s['nodes']} nodes, {s['submaps']} submaps, "
            f"{s.get('loop_closures', 0)} loop closures, "
            f"{s['wall_time_s']:.1f} s wall, {s['scans_per_s']:.0f} scans/s")
