#!/usr/bin/env python3
"""Multi-session mapping: several recordings of one building into one map (``carto map A B ...``), issue 45.

    python bench/sessions.py [--cases sim,dense-aces,dense-intel,dense-freiburg-079] [--sessions 2 5]
                             [--no-foreign] [--doc docs/benchmarks.md | --no-doc] [--results DIR]

Cases:

* ``sim``: ``carto_cli.sim``'s loop building driven once per session, each session starting at another point of
  the route (evenly spread) and every other one driving it the other way round, each recording's odometry starting
  at zero. Its baseline: each session mapped alone.
* ``dense-NAME``: ``$DATA/bench-dense/NAME`` cut into equal parts by time (``carto_cli.sim.sessions.cut_sessions``:
  each part's odometry restarted at zero, as after a reboot). Its baseline: the uncut recording mapped.

Per case and number of sessions, in a process of its own (CPU = user + sys of it and its children; peak memory =
the map's own figure, this process and the pose graph's together):

* links: sessions linked to the first; loop closures between sessions;
* ATE in the common frame: every session's poses against the reference under ONE SE(2) alignment over all of them,
  per session, and its ratio to the baseline's ATE over the same scans (the baseline under its own alignment:
  the uncut map's over all its scans, a sim session's alone);
* relative pose error: each later session's own SE(2) alignment against the first one's (how far the session is
  misplaced relative to the first as a whole), translation and rotation.

``--merge DIR``: the same parts each mapped alone (``carto map PART``, its map.carto kept under DIR), then merged
(``carto merge``, ``pipeline.merge_maps``); scored as above, CPU and peak memory of the merge alone (a process of
its own reading the saved maps).

``--foreign``: every pair of dense cases given together (the first 40 % of each): a building must not link to
another; counted links and the verdict.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("CARTO_SHARED_DATA", ROOT.parent / "shared" / "data"))
FOREIGN_SHARE = 0.4


def _ate(trajectories, references) -> list:
    """``evaluation.metrics.ate_sessions``: one SE(2) alignment over all of ``trajectories``, each one's errors."""
    from carto_cli.evaluation.metrics import ate_sessions

    return ate_sessions(trajectories, references)


def _sim_sessions(n: int):
    from carto_cli.io.trajectory import Trajectory as Tum
    from carto_cli.sim import Lidar
    from carto_cli.sim.sessions import route_sessions
    from carto_cli.sim.world import loop_building

    recordings, references = route_sessions(loop_building(), n, lidar=Lidar(beams=360))
    return recordings, [Tum.from_arrays(g[:, 0], g[:, 1], g[:, 2], g[:, 3]) for g in references]


def _dense_sessions(name: str, n: int, share: float = 1.0):
    from carto_cli.io.sources.open import open_recording
    from carto_cli.io.trajectory import read_trajectory
    from carto_cli.pipeline import Auto, read_options
    from carto_cli.sim.sessions import cut_sessions

    path = DATA / "bench-dense" / name / "scans.clf.gz"
    reference = read_trajectory(path.parent / "groundtruth.txt")
    with open_recording(path, read_options(Auto())) as rec:
        scan = next(t.name for t in rec.topics() if t.kind == "scan")
        times = np.array([r.time for r in rec.records([scan])])
        end = times[0] + share * (times[-1] - times[0])
        cuts = [times[0] + (end - times[0]) * k / n for k in range(1, n)] + ([end] if share < 1.0 else [])
        parts = cut_sessions(rec, cuts)
    return parts[:n], [reference] * n, path


def _map(first, later=()):
    from carto_cli.pipeline import Auto, MapRequest, map_sessions

    return map_sessions(MapRequest(first, Auto(), later=tuple(later)))


def one(case: str, n: int, mode: str) -> dict:
    """One measurement (run in a process of its own)."""
    from carto_cli.core import transform
    from carto_cli.io.trajectory import Trajectory

    if case == "sim":
        recordings, references, whole = *_sim_sessions(n), None
    else:
        recordings, references, whole = _dense_sessions(case.removeprefix("dense-"), n)
    out: dict = {"case": case, "sessions": n, "mode": mode}
    if mode == "baseline":
        if whole is not None:
            # The uncut map under one alignment, scored over each session's stretch of it
            result = _map(whole)
            pieces = []
            for rec in recordings:
                span = np.array([r.time for r in rec.records([next(t.name for t in rec.topics() if t.kind == "scan")])])
                inside = (result.times >= span[0]) & (result.times <= span[-1])
                pieces.append(Trajectory.from_poses(result.times[inside], result.poses[inside]))
            out["ate"] = [r.translation.rmse for r in _ate(pieces, references[:1])]
            out["peak_memory_mb"] = result.stats.get("peak_memory_mb")
        else:
            per = []
            for rec, reference in zip(recordings, references):
                result = _map(rec)
                (alone,) = _ate([Trajectory.from_poses(result.times, result.poses)], [reference])
                per.append(alone.translation.rmse)
                out["peak_memory_mb"] = max(out.get("peak_memory_mb") or 0, result.stats.get("peak_memory_mb") or 0)
            out["ate"] = per
        return out
    if mode == "parts":
        # Each part mapped alone, as `carto map PART -o DIR/partK` writes it, for the merge row
        from carto_cli.commands.map import write_outputs

        for k, rec in enumerate(recordings):
            result = _map(rec)
            write_outputs(result, _parts_dir(case, n) / f"part{k}", result.options, recordings=[rec.path.name])
        return out
    if mode == "merge":
        from carto_cli.io.map_file import load_map
        from carto_cli.pipeline import merge_maps

        result = merge_maps([load_map(_parts_dir(case, n) / f"part{k}" / "map.carto") for k in range(n)])
        out["whole_map_searches"] = result.stats.get("whole_map_searches")
        out["searches"] = result.stats.get("loop_closure_searches")
    else:
        result = _map(recordings[0], recordings[1:])
    out["peak_memory_mb"] = result.stats.get("peak_memory_mb")
    out["verdict"] = str(result.quality.verdict) if result.quality is not None else None
    out["linked"] = sum(s.linked for s in result.sessions)
    out["links"] = [link.to_dict() for link in result.links]
    trajectories = [Trajectory.from_poses(s.times, s.poses) for s in result.sessions]
    linked = [s.linked for s in result.sessions]
    # One alignment over the linked sessions (an unlinked one is in no common frame: not scored)
    common = iter(_ate([t for t, k in zip(trajectories, linked) if k], [r for r, k in zip(references, linked) if k]))
    out["ate"] = [next(common).translation.rmse if k else None for k in linked]
    # Each session aligned alone: how far a later one is misplaced against the first as a whole
    fits = [np.array(_ate([t], [r])[0].alignment) for t, r in zip(trajectories, references)]
    misplaced = []
    for fit, k in zip(fits[1:], linked[1:]):
        d = transform.compose(transform.inverse(fits[0]), fit)
        misplaced.append([float(math.hypot(d[0], d[1])), float(abs(math.degrees(d[2])))] if k else None)
    out["misplaced"] = misplaced
    return out


def _parts_dir(case: str, n: int) -> Path:
    return Path(os.environ["CARTO_BENCH_PARTS"]) / f"{case}-{n}"


def foreign(a: str, b: str) -> dict:
    first, _, _ = _dense_sessions(a, 1, FOREIGN_SHARE)
    second, _, _ = _dense_sessions(b, 1, FOREIGN_SHARE)
    result = _map(first[0], second)
    return {"pair": [a, b], "links": len(result.links), "verdict": str(result.quality.verdict),
            "linked": sum(s.linked for s in result.sessions)}


def _child(args: list[str]) -> dict:
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    out = subprocess.run([sys.executable, __file__, "--child", *args], capture_output=True, text=True, cwd=ROOT)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(args)} failed:\n{out.stderr[-3000:]}")
    got = json.loads(out.stdout.strip().splitlines()[-1])
    got["cpu_s"] = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    got["wall_s"] = time.perf_counter() - t
    return got


def _row(r: dict, base: dict, last_cpu_s: float) -> str:
    ratio = max((a / b if b > 0 else float("inf") for a, b in zip(r["ate"], base["ate"]) if a is not None),
                default=float("nan"))
    placed = [m for m in r["misplaced"] if m is not None]
    worst = max((m[0] for m in placed), default=0.0)
    worst_deg = max((m[1] for m in placed), default=0.0)
    ates = ", ".join("unlinked" if a is None else f"{a:.3f}" for a in r["ate"])
    return (f"| {r['case']} | {r['sessions']} | {r['linked']}/{r['sessions']} | {r['verdict']} | "
            f"{ates} | {ratio:.2f} | {worst:.3f} / {worst_deg:.2f} | "
            f"{r['cpu_s']:.1f} | {r['peak_memory_mb']:.0f} | {last_cpu_s:.1f} |")


def _table(rows: list[dict], foreign_rows: list[dict], commit: str) -> str:
    lines = [f"Multi-session mapping (`python bench/sessions.py`, commit {commit}): ATE in m in the common frame (one "
             "alignment for every session), per session, and its ratio to the baseline's over the same scans "
             "(the uncut recording's map; a sim session mapped alone); how far each later session is misplaced "
             "relative to the first (its own alignment against the first's); CPU s user+sys, peak MB.", "",
             "| case | sessions | linked | verdict | ATE per session (m) | worst ratio | misplaced (m / deg, worst) "
             "| CPU s | peak MB | baseline CPU s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [_row(r, r["baseline"], r["baseline"]["cpu_s"]) for r in rows]
    merged = [r for r in rows if "merge" in r]
    if merged:
        lines += ["", "The same parts each mapped alone, then merged (`--merge`, `carto merge`): the same scores; CPU s "
                  "and peak MB of the merge alone (reading the saved maps), and the parts' mapping CPU s.", "",
                  "| case | sessions | linked | verdict | ATE per session (m) | worst ratio | misplaced (m / deg, worst) "
                  "| merge CPU s | peak MB | parts CPU s |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        lines += [_row(r["merge"], r["baseline"], r["merge"]["parts_cpu_s"]) for r in merged]
    if foreign_rows:
        lines += ["", "Two buildings given together (the first 40 % of each): links found and the verdict.", "",
                  "| recordings | links | verdict |", "|---|---|---|"]
        for f in foreign_rows:
            lines.append(f"| {f['pair'][0]} + {f['pair'][1]} | {f['links']} | {f['verdict']} |")
    return "\n".join(lines)


def _rows(args: argparse.Namespace) -> list[dict]:
    rows = []
    for case in args.cases.split(","):
        for n in args.sessions:
            print(f"[{case}] {n} sessions ...", file=sys.stderr, flush=True)
            row = _child(["sessions", case, str(n)])
            row["baseline"] = _child(["baseline", case, str(n)])
            if args.merge is not None:
                os.environ["CARTO_BENCH_PARTS"] = str(args.merge.resolve())
                parts = _child(["parts", case, str(n)])
                row["merge"] = _child(["merge", case, str(n)]) | {"parts_cpu_s": parts["cpu_s"]}
            rows.append(row)
            print(json.dumps(row), file=sys.stderr, flush=True)
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", default="sim,dense-aces,dense-intel,dense-freiburg-079")
    p.add_argument("--sessions", type=int, nargs="+", default=[2, 5])
    p.add_argument("--no-foreign", action="store_true")
    p.add_argument("--doc", type=Path, default=ROOT / "docs" / "benchmarks.md")
    p.add_argument("--no-doc", action="store_true")
    p.add_argument("--results", type=Path, default=None)
    p.add_argument("--merge", type=Path, default=None, metavar="DIR",
                   help="also map the parts alone (their maps kept in DIR) and merge them (`carto merge`)")
    p.add_argument("--child", nargs="+", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.child:
        kind, *rest = args.child
        out = foreign(*rest) if kind == "foreign" else one(rest[0], int(rest[1]), kind)
        print(json.dumps(out))
        return
    rows, foreign_rows = _rows(args), []
    if not args.no_foreign:
        dense = [c.removeprefix("dense-") for c in args.cases.split(",") if c.startswith("dense-")]
        for i, a in enumerate(dense):
            for b in dense[i + 1:]:
                foreign_rows.append(_child(["foreign", a, b]))
                print(json.dumps(foreign_rows[-1]), file=sys.stderr, flush=True)
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                            cwd=ROOT).stdout.strip()
    table = _table(rows, foreign_rows, commit)
    print(table)
    if args.results is not None:
        args.results.mkdir(parents=True, exist_ok=True)
        (args.results / "sessions.json").write_text(json.dumps({"rows": rows, "foreign": foreign_rows}, indent=1))
    if not args.no_doc:
        text = args.doc.read_text(encoding="utf-8")
        begin, end = "<!-- sessions:begin -->", "<!-- sessions:end -->"
        block = f"{begin}\n{table}\n{end}"
        if begin in text:
            text = text[:text.index(begin)] + block + text[text.index(end) + len(end):]
        else:
            text = text.rstrip() + "\n\n## Multi-session mapping\n\n" + block + "\n"
        args.doc.write_text(text, encoding="utf-8")


if __name__ == "__main__":
    main()
