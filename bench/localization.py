#!/usr/bin/env python3
"""Localization in a plain map_server map: the building's ground-truth occupancy image as the map.

    python bench/localization.py [--cases aces,intel,freiburg-079] [--queries 200] [--global-queries 100]
                                 [--foreign-queries 50] [--foreign-track 300] [--seed 0] [--no-track]
                                 [--results DIR]
                                 [--doc docs/benchmarks.md | --no-doc]

For each case of ``$DATA/bench-dense`` (``map.yaml`` + ``map.pgm``: the occupancy grid the simulator drew the
building from, in the frame of ``groundtruth.txt``, so the reference needs no fitting):

1. **Map**: ``carto relocalize``'s own path: ``io.map_server.load_map_server`` with the settings ``auto`` chooses
   from the recording's first scans (``relocalization.auto``), a ``Relocalizer`` with its stacks built first.
2. **With a prior**: ``--queries`` scans drawn uniformly (seeded), each with a prior = the reference moved
   uniformly within a disc of 1.5 m and ±15°, given with sigma 0.5 m / 5°. Right = verdict ``ok`` and within
   0.2 m / 2° of the reference. Latency = ``total_ms`` (numba compiled, stacks built).
3. **Global**: the first ``--global-queries`` of them without a prior.
4. **Another building**: ``--foreign-queries`` scans of each other case's recording, with priors on this map's
   route (the reference poses of its own recording) and without; every answer with verdict ``ok`` is counted:
   there should be none. From each such answer a ``Tracker`` follows the next ``--foreign-track`` scans of that
   recording: how many scans it believes the wrong pose, and how many it answers ``ok`` in all.
5. **Tracking**: ``commands.relocalize.run_track`` over the whole recording (reading, tracking and writing the
   outputs, as ``carto relocalize MAP REC --track`` does), no initial pose (a global first fix): share of scans
   ``ok`` and within 0.1 m / 1°, scans per second over the whole call, time to the first fix.

Targets (issue 14): prior >= 99 % right, p50 <= 10 ms, p99 <= 50 ms; global >= 95 %, p50 <= 200 ms; another
building: 0 answers ``ok``; tracking >= 99 % within 0.1 m / 1°, >= 500 scans/s, first fix <= 1 s.

Writes one JSON per case under ``--results`` and the section between ``<!-- localization:begin -->`` and
``<!-- localization:end -->`` of ``docs/benchmarks.md``.
"""
from __future__ import annotations

import argparse
import datetime as _dt
import json
import math
import os
import platform
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
BEGIN, END = "<!-- localization:begin -->", "<!-- localization:end -->"


def _data() -> Path:
    for cand in (os.environ.get("CARTO_SHARED_DATA"), REPO.parent / "shared" / "data"):
        if cand and (Path(cand) / "bench-dense").is_dir():
            return Path(cand)
    raise SystemExit("no shared data (set CARTO_SHARED_DATA)")


class _Recording:
    """A recording's scans, and each one's records around it as ``carto relocalize`` gathers them."""

    def __init__(self, path: Path):
        from carto_cli.core.records import Odometry, Scan
        from carto_cli.io.sources.open import open_recording

        with open_recording(path) as rec:
            self.records = [r for r in rec.records() if isinstance(r, (Scan, Odometry))]
        self.at = [k for k, r in enumerate(self.records) if isinstance(r, Scan)]
        self.scans = [self.records[k] for k in self.at]
        self.times = np.array([r.time for r in self.records])

    def context(self, i: int):
        from carto_cli.relocalization import ScanContext
        from carto_cli.relocalization.queries import CONTEXT_SECONDS

        k, t = self.at[i], self.scans[i].time
        lo = int(np.searchsorted(self.times, t - CONTEXT_SECONDS, side="left"))
        hi = int(np.searchsorted(self.times, t + CONTEXT_SECONDS, side="right"))
        return ScanContext(self.records[lo:k], self.records[k + 1:hi])


def _err(pose, ref) -> tuple[float, float]:
    from carto_cli.core.transform import wrap_angle_scalar

    d = np.asarray(pose, float) - np.asarray(ref, float)
    return math.hypot(d[0], d[1]), abs(math.degrees(wrap_angle_scalar(float(d[2]))))


def _lat(ms) -> dict:
    v = np.asarray(ms, float)
    return {"p50_ms": float(np.percentile(v, 50)), "p99_ms": float(np.percentile(v, 99)), "max_ms": float(v.max())}


def _vetoed(res) -> bool:
    """Judged ok on its own, lost by the scans around it (``Relocalizer.relocalize``'s context)."""
    return res.verdict == "lost" and res.context_checked > 0


def _row(res, ref) -> tuple:
    e = _err(res.pose, ref)
    return res.verdict, e[0] < 0.2 and e[1] < 2.0, res.total_ms, _vetoed(res), res.context_checked > 0


def _answers(rows) -> dict:
    """Counts over (verdict, within 0.2 m / 2 deg, ms, vetoed by the context, context checked) rows."""
    return {"n": len(rows), "right": sum(r[0] == "ok" and r[1] for r in rows),
            "false_ok": sum(r[0] == "ok" and not r[1] for r in rows),
            "verdicts": {v: sum(r[0] == v for r in rows) for v in ("ok", "ambiguous", "lost")},
            "context_checked": sum(r[4] for r in rows), "context_vetoed": sum(r[3] for r in rows),
            "context_vetoed_right": sum(r[3] and r[1] for r in rows), **_lat([r[2] for r in rows])}


def _track_from(reloc, building: Path, first: int, pose, n: int) -> dict:
    """Track ``n`` scans of ``building`` from its scan ``first`` on, starting at ``pose`` (a wrong answer in
    another building's map): how long the tracker believes it, and how often its searches answer ``ok`` again."""
    from carto_cli.core.records import Scan
    from carto_cli.io.sources.open import open_recording
    from carto_cli.relocalization.tracking import Tracker

    if n <= 0:
        return {}
    records, k = [], -1
    with open_recording(building / "scans.clf.gz") as rec:
        for r in rec.records():
            k += isinstance(r, Scan)
            if k >= first + n:
                break
            if k >= first:
                records.append(r)
    verdicts = [t.verdict for t in Tracker(reloc).track(records, initial_pose=pose, sigma_xy=0.1, sigma_yaw=0.05)]
    return {"tracked": len(verdicts), "first_not_ok": next((j for j, v in enumerate(verdicts) if v != "ok"), None),
            "tracked_ok": verdicts.count("ok")}


def run_case(case: Path, foreign: list[Path], args) -> dict:
    from carto_cli.commands.relocalize import RelocalizeRequest, run_track
    from carto_cli.io.map_server import load_map_server
    from carto_cli.relocalization import Relocalizer
    from carto_cli.relocalization.auto import choose_for_scans

    rng = np.random.default_rng(args.seed)
    gt = np.loadtxt(case / "groundtruth.txt")
    own = _Recording(case / "scans.clf.gz")
    scans = own.scans
    if len(scans) != len(gt):
        raise SystemExit(f"{case}: {len(scans)} scans, {len(gt)} reference poses")
    t = time.perf_counter()
    loaded = load_map_server(case / "map.yaml")
    auto = choose_for_scans(loaded.options, scans[:50])
    loaded.options = auto.options
    reloc = Relocalizer(loaded)
    for i in reloc.searchable:
        reloc.cache.get(i, reloc.grids[i])
    load_s = time.perf_counter() - t
    reloc.relocalize(scans[0], gt[0, 1:4])  # compile / load the kernels
    reloc.relocalize(scans[0])
    out: dict = {"case": case.name, "scans": len(scans), "auto": auto.describe(), "load_s": load_s,
                 "cells": int(loaded.occupancy.size), "tiles": len(loaded.submaps)}

    idx = rng.choice(len(scans), min(args.queries, len(scans)), replace=False)
    rows = []
    for i in idx:
        ref = gt[i, 1:4]
        r, a = 1.5 * math.sqrt(rng.uniform()), rng.uniform(0, 2 * math.pi)
        prior = ref + [r * math.cos(a), r * math.sin(a), math.radians(rng.uniform(-15, 15))]
        res = reloc.relocalize(scans[i], prior, sigma_xy=0.5, sigma_yaw=math.radians(5), context=own.context(i))
        rows.append(_row(res, ref))
    out["prior"] = _answers(rows)
    rows = []
    for i in idx[:args.global_queries]:
        res = reloc.relocalize(scans[i], context=own.context(i))
        rows.append(_row(res, gt[i, 1:4]))
    out["global"] = _answers(rows)

    ok_prior = ok_global = n_foreign = vetoed = 0
    wrong = []
    for building in foreign:
        rec = _Recording(building / "scans.clf.gz")
        other = rec.scans
        fidx = rng.choice(len(other), min(args.foreign_queries, len(other)), replace=False)
        n_foreign += len(fidx)
        for i in fidx:
            prior = gt[rng.integers(len(gt)), 1:4]
            ctx = rec.context(int(i))
            for kind, res in (("prior", reloc.relocalize(other[i], prior, sigma_xy=0.5, sigma_yaw=math.radians(5),
                                                         context=ctx)),
                              ("global", reloc.relocalize(other[i], context=ctx))):
                vetoed += _vetoed(res)
                if res.verdict == "ok":
                    ok_prior += kind == "prior"
                    ok_global += kind == "global"
                    wrong.append({"building": building.name, "scan": int(i), "kind": kind, "path": res.path,
                                  "score": res.score, "inliers": res.inlier_fraction, "see_through": res.see_through,
                                  "ambiguity": res.ambiguity,
                                  **_track_from(reloc, building, int(i), res.pose, args.foreign_track)})
    out["foreign"] = {"buildings": [b.name for b in foreign], "n": n_foreign, "ok_with_prior": ok_prior,
                      "ok_global": ok_global, "context_vetoed": vetoed, "ok_answers": wrong}

    if not args.no_track:
        with tempfile.TemporaryDirectory() as d:
            t = time.perf_counter()
            # Every core, as the command line's default: scans per second as a user would see them.
            run = run_track(RelocalizeRequest(case / "map.yaml", case / "scans.clf.gz", jobs=None), Path(d) / "track")
            wall = time.perf_counter() - t
            import csv

            with open(Path(d) / "track" / "track.csv", newline="") as f:
                tracked = list(csv.DictReader(f))
        right = 0
        for row in tracked:
            if row["verdict"] != "ok":
                continue
            e = _err([float(row["x"]), float(row["y"]), float(row["yaw"])], gt[int(row["scan_index"]), 1:4])
            right += e[0] < 0.1 and e[1] < 1.0
        s = run.summary
        out["track"] = {"scans": s.scans, "right": right, "verdicts": s.verdicts, "first_fix_index": s.first_fix_index,
                        "first_fix_s": s.first_fix_s, "scans_per_second": s.scans / wall, "wall_s": wall,
                        "searches": s.relocalizations, "timings_ms": s.timings_ms}
    return out


def _pct(a, b) -> str:
    return f"{a}/{b} = {100 * a / b:.1f} %" if b else "–"


def render(cases: list[dict], argv: list[str], wall_s: float) -> str:
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True, text=True,
                                check=True).stdout.strip()
        if subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO, capture_output=True,
                          text=True).stdout.strip():
            commit += " + uncommitted changes in the tree"
    except Exception:
        commit = "unknown"
    cmd = "python bench/localization.py" + ("" if not argv else " " + " ".join(shlex.quote(a) for a in argv))
    load = os.getloadavg()
    out = [BEGIN, "", "## Localization in a map_server map (the building's ground-truth image)", "",
           f"`{cmd}` — {_dt.date.today().isoformat()}, commit {commit}, {os.cpu_count()} cores, Python "
           f"{platform.python_version()}, load average at the end {load[0]:.2f}; shared machine, "
           f"{wall_s / 60:.1f} min in all.", "",
           "Map: `bench-dense/*/map.yaml` (the occupancy image the simulator drew the building from), read as "
           "`carto relocalize MAP.yaml` reads it, settings chosen by `auto` from the scans. Queries: scans of the "
           "recording; with a prior = reference moved uniformly within 1.5 m / ±15° (sigma 0.5 m / 5°); global: "
           "the first of them without a prior; right = verdict `ok` and within 0.2 m / 2°; *false ok* = verdict "
           "`ok` and not right. Another building: scans of each other case with priors on this map's route, and "
           "without (each `ok` among them listed below, with how a tracker started there fares). Tracking: "
           "`carto relocalize MAP REC --track` over the whole recording without an initial pose (global first "
           "fix), right = `ok` and within 0.1 m / 1°; scans/s over the whole call (reading, tracking, writing). "
           "Method in `bench/localization.py`.", "",
           "Targets (issue 14): prior ≥ 99 %, p50 ≤ 10 ms, p99 ≤ 50 ms; global ≥ 95 %, p50 ≤ 200 ms; another "
           "building 0 `ok`; tracking ≥ 99 %, ≥ 500 scans/s, first fix ≤ 1 s.", "",
           "| case | map | prior: right | false ok | p50 / p99 ms | global: right | false ok | p50 / p99 ms | "
           "another building: ok (prior / global) | track: right | scans/s | first fix |",
           "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in cases:
        p, g, f = c["prior"], c["global"], c["foreign"]
        tr = c.get("track")
        track = ("| – | – | – |" if tr is None else
                 f"| {_pct(tr['right'], tr['scans'])} | {tr['scans_per_second']:.0f} | scan {tr['first_fix_index']}, "
                 f"{tr['first_fix_s']:.2f} s |")
        out.append(f"| {c['case']} | {c['cells'] / 1e6:.2f} M cells, {c['tiles']} tile(s) | "
                   f"{_pct(p['right'], p['n'])} | {p['false_ok']} | {p['p50_ms']:.1f} / {p['p99_ms']:.1f} | "
                   f"{_pct(g['right'], g['n'])} | {g['false_ok']} | {g['p50_ms']:.0f} / {g['p99_ms']:.0f} | "
                   f"{f['ok_with_prior']} / {f['ok_global']} of {f['n']} ({', '.join(f['buildings'])}) " + track)
    out += ["", "The scans around each query (docs/localization.md, *The scans around an answer*) checked the answers "
            "no window around the prior confirmed; answers judged `ok` on their own and `lost` by them:", ""]
    for c in cases:
        p, g, f = c["prior"], c["global"], c["foreign"]
        out.append(f"- {c['case']}: with a prior {p['context_vetoed']} of {p['context_checked']} checked "
                   f"({p['context_vetoed_right']} of them right), global {g['context_vetoed']} of "
                   f"{g['context_checked']} ({g['context_vetoed_right']} right); scans of another building "
                   f"{f['context_vetoed']}")
    out += ["", "Verdicts and settings:", ""]
    for c in cases:
        line = (f"- {c['case']}: auto {c['auto']}; prior {c['prior']['verdicts']}, global {c['global']['verdicts']}")
        if "track" in c:
            t = c["track"]
            line += f"; track {t['verdicts']}, {t['searches']} searches, stage ms {t['timings_ms']}"
        out.append(line)
        for w in c["foreign"]["ok_answers"]:
            tracked = ("" if "tracked" not in w else
                       f"; tracked from there: first not `ok` after {w['first_not_ok']} scan(s), "
                       f"{w['tracked_ok']} of {w['tracked']} `ok`")
            out.append(f"  - `ok` on {w['building']} scan {w['scan']} ({w['kind']}, {w['path']}): score "
                       f"{w['score']:.3f}, {100 * w['inliers']:.0f} % of the points on walls, "
                       f"{100 * w['see_through']:.0f} % of the rays through walls, ambiguity {w['ambiguity']:.2f}"
                       + tracked)
    out += ["", END]
    return "\n".join(out) + "\n"


def write_section(doc: Path, section: str) -> None:
    text = doc.read_text(encoding="utf-8") if doc.exists() else ""
    b, e = text.find(BEGIN), text.find(END)
    text = (text[:b] + section.rstrip("\n") + text[e + len(END):]) if (b >= 0 and e > b) else \
        (text.rstrip("\n") + "\n\n" + section if text else section)
    tmp = doc.with_suffix(doc.suffix + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, doc)


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--cases", default="aces,intel,freiburg-079")
    p.add_argument("--queries", type=int, default=200)
    p.add_argument("--global-queries", type=int, default=100)
    p.add_argument("--foreign-queries", type=int, default=50)
    p.add_argument("--foreign-track", type=int, default=300)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-track", action="store_true")
    p.add_argument("--results", type=Path, default=None)
    p.add_argument("--doc", type=Path, default=REPO / "docs" / "benchmarks.md")
    p.add_argument("--no-doc", action="store_true")
    args = p.parse_args(argv)
    data = _data() / "bench-dense"
    names = args.cases.split(",")
    t0 = time.perf_counter()
    cases = []
    every = sorted(d.name for d in data.iterdir() if d.is_dir())
    for name in names:
        c = run_case(data / name, [data / other for other in every if other != name], args)
        cases.append(c)
        print(json.dumps(c), flush=True)
        if args.results:
            args.results.mkdir(parents=True, exist_ok=True)
            (args.results / f"{name}.json").write_text(json.dumps(c, indent=1))
    if not args.no_doc:
        write_section(args.doc, render(cases, argv, time.perf_counter() - t0))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
