#!/usr/bin/env python3
"""A map that stays current (lifelong mapping), issue 45 item 4: figures for docs/benchmarks.md.

    python bench/lifelong.py [--case changes|repeat|all] [--sessions 10] [--policy lifelong|last-seen|fuse] [--out FILE]

* ``changes``: ``sim.world.rearranged_loop_building``: the loop building driven once, then driven again after a
  door was closed, a room's back wall moved and a cabinet taken away (two sessions, ``carto map A B``). Scored by
  ``evaluation.changes.score_changes`` on the changed cells the last session saw surely (a moved wall hides the
  old one behind it: no session can say it is gone), and on the walls both sessions found. Under each
  ``mapping.lifelong.SessionPolicy``: last seen (the default), lifelong (``--lifelong``: also trimmed), fused.
* ``repeat``: the loop building driven ``--sessions`` times (``sim.sessions.route_sessions``: each session from
  another point of the route, every other one the other way round), each session mapped onto the map the one
  before saved (``carto map S_k --load-state prev/map.carto [--lifelong]``, through ``commands.map.run_map``, under
  ``--policy``, lifelong by default): map.carto's size
  after every session against its size after the first, every session's CPU (user + sys of this process) and
  the peak memory of the run so far, and how far the new session lies from where it belongs in the FIRST session's
  map frame (RMSE of its poses against its truth carried by the first session's alignment): a link made half a turn
  round the ring turns the map frame with it, and stays invisible to the verdict once the sessions it contradicted
  are trimmed.
"""
from __future__ import annotations

import argparse
import json
import resource
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from carto_cli.commands.map import run_map
from carto_cli.core import transform
from carto_cli.evaluation.changes import score_changes
from carto_cli.evaluation.metrics import align_se2
from carto_cli.grid.occupancy_image import AssembledImage
from carto_cli.mapping import lifelong
from carto_cli.mapping.lifelong import SURE, SessionPolicy
from carto_cli.pipeline import Auto, MapRequest, map_sessions
from carto_cli.sim.sessions import route_sessions
from carto_cli.sim.world import loop_building, rearranged_loop_building


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    c = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime + c.ru_utime + c.ru_stime


def changes() -> dict:
    before, after = rearranged_loop_building()
    recordings, references = route_sessions([before, after], 2)
    start = references[0][0, 1:]
    out = {}
    for policy in SessionPolicy:
        cpu = _cpu()
        result = map_sessions(MapRequest(recordings[0], Auto(), later=(recordings[1],), sessions=policy))
        assert result.graph is not None
        last = [e for e in result.graph.submaps if e.trajectory == 1]
        seen = AssembledImage([e.submap.grid for e in last], [e.local_to_global() for e in last])
        score = score_changes(result.image, before, after, alignment=start, observed=seen, sure=SURE)
        out[str(policy)] = {
            **score.to_dict(), "cpu_s": round(_cpu() - cpu, 1), "verdict": result.quality.verdict
            if result.quality else None, "trimmed": [x.describe() for x in result.trimmed],
            "submaps": len(result.graph.submaps), "nodes": result.graph.num_nodes}
    return out


def repeat(sessions: int, policy: SessionPolicy) -> dict:
    recordings, references = route_sessions(loop_building(), sessions)
    rows = []
    first_fit = None  # the first session's map frame in the world: where every later session must land
    with tempfile.TemporaryDirectory() as tmp:
        previous = None
        for k, recording in enumerate(recordings):
            cpu, wall = _cpu(), time.perf_counter()
            outdir = Path(tmp) / f"s{k}"
            result, outputs = run_map(MapRequest(recording, Auto(), load_state=previous, sessions=policy),
                                      outdir)
            assert outputs.state is not None
            previous = outputs.state
            rows.append({"session": k + 1, "superseded": lifelong.SUPERSEDED, "map_carto_bytes": previous.stat().st_size,
                         "cpu_s": round(_cpu() - cpu, 1), "wall_s": round(time.perf_counter() - wall, 1),
                         "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
                         "submaps": len(result.graph.submaps) if result.graph else None,
                         "nodes": result.graph.num_nodes if result.graph else None,
                         "verdict": result.quality.verdict if result.quality else None,
                         "linked": [x.linked for x in result.sessions],
                         "trimmed": [x.describe() for x in result.trimmed]})
            rows[-1]["size_ratio"] = round(rows[-1]["map_carto_bytes"] / rows[0]["map_carto_bytes"], 3)
            # The new session's poses against its truth carried into the FIRST session's map frame: a link half a
            # turn round shows here even after the sessions it contradicted were trimmed
            own = result.sessions[-1] if result.sessions else None
            poses = own.poses if own is not None else result.poses
            times = own.times if own is not None else result.times
            truth = np.column_stack([np.interp(times, references[k][:, 0], references[k][:, i]) for i in (1, 2)])
            if first_fit is None:
                first_fit = align_se2(truth, poses[:, :2])
            placed = transform.apply(first_fit, truth)
            rows[-1]["error_in_first_frame_m"] = round(float(np.sqrt(np.mean(np.sum((placed - poses[:, :2]) ** 2,
                                                                                      axis=1)))), 3)
            print(json.dumps(rows[-1]), flush=True)
    return {"policy": str(policy), "sessions": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", choices=("changes", "repeat", "all"), default="all")
    parser.add_argument("--sessions", type=int, default=10)
    parser.add_argument("--policy", type=SessionPolicy, default=SessionPolicy.LIFELONG,
                        help="repeat: how the sessions are weighed (default lifelong)")
    parser.add_argument("--superseded", type=float, help="the share of a submap later sessions must know for it to "
                        "be trimmed (default: mapping.lifelong.SUPERSEDED)")
    parser.add_argument("--out", type=Path, help="write the figures as JSON here too")
    args = parser.parse_args()
    if args.superseded is not None:
        lifelong.SUPERSEDED = args.superseded
    figures = {}
    if args.case in ("changes", "all"):
        figures["changes"] = changes()
        print(json.dumps(figures["changes"], indent=1), flush=True)
    if args.case in ("repeat", "all"):
        figures["repeat"] = repeat(args.sessions, args.policy)
    if args.out:
        args.out.write_text(json.dumps(figures, indent=1) + "\n")


if __name__ == "__main__":
    main()
