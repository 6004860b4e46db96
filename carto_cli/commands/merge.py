"""`carto merge` as a library call: saved maps (map.carto or Cartographer's .pbstream) made separately, by other
robots or on other days, into one map without their recordings, written as `carto map A B` writes its map."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from carto_cli.commands.map import MapOutputs, check_outdir, write_outputs
from carto_cli.core.errors import CartoError
from carto_cli.io.loaded_map import LoadedMap
from carto_cli.io.map_file import load_map
from carto_cli.pipeline import MapResult, merge_maps

__all__ = ["load_maps", "merged_line", "run_merge"]


def load_maps(paths: Sequence[str | Path]) -> list[LoadedMap]:
    """Every map of ``paths``, read and checked before any is merged: the first that is missing or not a map
    raises its one-line error naming it."""
    if len(paths) < 2:
        raise CartoError("give two maps or more to merge")
    for path in paths:  # all said at once, before the first (perhaps large) map is read
        if not Path(path).exists():
            raise CartoError("no such file or directory", Path(path))
    return [load_map(Path(path)) for path in paths]


def run_merge(paths: Sequence[str | Path], outdir: Path, *, force: bool = False, jobs: int | None = None,
              timer: Any = None, state: bool = True, on_total: Callable[[int], None] | None = None,
              on_nodes: Callable[[int], None] | None = None) -> tuple[MapResult, MapOutputs]:
    """Merge the maps of ``paths`` in order (the first fixes the map frame and gives the options; a .pbstream
    holds none: carto's defaults) and write every output of `carto map` into ``outdir`` as one set: map.pgm /
    .yaml / .png, trajectory.tum (the last map's), trajectory_N.tum per trajectory, map.carto with every
    trajectory (``state``), summary.json and sessions.json. An earlier map in ``outdir`` is replaced only with
    ``force`` (checked before anything is read); a missing or bad map writes nothing. ``on_total`` / ``on_nodes``:
    the searches' progress, in nodes."""
    outdir = Path(outdir)
    check_outdir(outdir, force=force)
    maps = load_maps(paths)
    result = merge_maps(maps, timer=timer, jobs=jobs, on_total=on_total, on_nodes=on_nodes)
    recordings = [x.name for x in result.sessions]
    outputs = write_outputs(result, outdir, result.options, state=state, recordings=recordings, jobs=jobs)
    if timer is not None:
        timer.stop()
    return result, outputs


def merged_line(result: MapResult) -> str:
    """The merge in one line."""
    s = result.stats
    peak = f", {s['peak_memory_mb']:.0f} MB peak memory" if s.get("peak_memory_mb") else ""
    return (f"{s['maps']} maps: {s['nodes']} nodes, {s['submaps']} submaps, {s['loop_closures']} loop closures, "
            f"{s['loop_closure_searches']} searches ({s['whole_map_searches']} whole-map), "
            f"{s['wall_time_s']:.1f} s wall{peak}")
