"""Scale: a 2-hour, 10 Hz recording through a simulated 1 km² campus, mapped up to 15, 30, 60 and 120 minutes.

``carto_cli.sim.campus`` (corridors with random features, halls, two open plazas, several loops; ≈ 7.5 km
of route at up to 1 m/s) and a 360-beam, 270°, 30 m scanner with drifting wheel odometry and an IMU. Each prefix
is mapped in a fresh process, as ``carto map`` would map the recording (``--profile auto``, every core unless
``--jobs``), and gives: wall time of mapping, mean time per scan over the whole prefix and over its last
15 minutes (the growth shows there first), peak resident memory of the process and how much of it the
simulator holds before mapping starts, and the relation error against the exact ground truth (relations in
bench-dense's recipe: every 10th scan to the 10th after it, plus revisits ≥ 30 s apart within 3 m / 60°).

    python bench/scale.py [--minutes 15 30 60 120] [--jobs N] [--memory-budget MB] [--out docs/scale.md]
                          [--svg docs/scale.svg]

A run of all four prefixes takes about as long as mapping 225 minutes of recording.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SCAN_RATE = 10.0
DURATION_S = 7200.0


def rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20


def revisit_relations(gt: np.ndarray, *, step: int = 10, every: int = 5, min_dt: float = 30.0, max_dist: float = 3.0,
                      max_angle_deg: float = 60.0, max_revisits: int = 3000, seed: int = 0):
    """bench-dense's relation recipe for a long recording: revisit pairs from a k-d tree, not all pairs."""
    from scipy.spatial import cKDTree

    from carto_cli.core import transform
    from carto_cli.evaluation.metrics import Relations

    t, xy, th = gt[:, 0], gt[:, 1:3], gt[:, 3]
    i1 = np.arange(0, len(t) - step, step)
    sub = np.arange(0, len(t), every)
    pairs = cKDTree(xy[sub]).query_pairs(max_dist, output_type="ndarray")
    a, b = sub[pairs[:, 0]], sub[pairs[:, 1]]
    a, b = np.minimum(a, b), np.maximum(a, b)
    ok = (t[b] - t[a] >= min_dt) & (np.abs(transform.wrap_angle(th[b] - th[a])) <= math.radians(max_angle_deg))
    a, b = a[ok], b[ok]
    if len(a) > max_revisits:
        keep = np.sort(np.random.default_rng(seed).choice(len(a), max_revisits, replace=False))
        a, b = a[keep], b[keep]
    i, j = np.concatenate([i1, a]), np.concatenate([i1 + step, b])
    d = xy[j] - xy[i]
    c, s = np.cos(th[i]), np.sin(th[i])
    rel = np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], transform.wrap_angle(th[j] - th[i])])
    return Relations(t[i].copy(), t[j].copy(), rel), len(a), len(i1)


def one(minutes: float, jobs: int | None, budget: float | None) -> dict:
    from carto_cli.core.memory import peak_rss_mb
    from carto_cli.evaluation.metrics import Relations, relation_error
    from carto_cli.io.trajectory import Trajectory as Tum
    from carto_cli.pipeline import Auto, MapRequest, execute, planned
    from carto_cli.sim import Lidar, Limits, Trajectory, simulate
    from carto_cli.sim.world import campus

    world = campus()
    route = Trajectory.follow(world.route, limits=Limits(v_max=1.0), dt=0.02)
    lidar = Lidar(beams=360, fov=1.5 * math.pi, max_range=30.0, noise=0.01, dropout=0.01)
    sim = simulate(world, route, duration=DURATION_S, scan_rate=SCAN_RATE, lidar=lidar, seed=0)
    scans = int(round(minutes * 60 * SCAN_RATE))
    overrides = () if budget is None else (f"pose_graph.constraint_builder.precomputation_memory={budget!r}",)
    spec = Auto(overrides)
    rec = sim.recording()
    rss_before = rss_mb()
    marks: list[float] = []
    t0 = time.perf_counter()

    def tick(n: int) -> None:
        marks.append(time.perf_counter())

    with planned(MapRequest(rec, spec, max_scans=scans, jobs=jobs)) as plan:
        result = execute(plan, on_scan=tick)
    wall = time.perf_counter() - t0
    marks_a = np.array(marks)
    last = marks_a[-min(len(marks_a), int(15 * 60 * SCAN_RATE)):]
    gt = sim.ground_truth[:scans]
    relations, revisits, consecutive = revisit_relations(gt)
    traj = Tum.from_arrays(result.times, result.poses[:, 0], result.poses[:, 1], result.poses[:, 2])
    err = relation_error(traj, relations)
    # Consecutive relations alone (1 s apart) compare prefixes like with like: the first has no revisit to measure.
    local = relation_error(traj, Relations(relations.t1[:consecutive], relations.t2[:consecutive],
                                           relations.d[:consecutive]))
    per_minute = [float(1000 * np.mean(np.diff(marks_a[k:k + 600]))) for k in range(0, len(marks_a) - 600, 600)]
    return {
        "minutes": minutes, "scans": int(result.stats["scans"]), "nodes": int(result.stats["nodes"]),
        "submaps": int(result.stats["submaps"]), "loop_closures": int(result.stats.get("loop_closures", 0)),
        "wall_s": wall, "ms_per_scan": 1000 * wall / max(1, result.stats["scans"]),
        "ms_per_scan_last_15min": float(1000 * (last[-1] - last[0]) / max(1, len(last) - 1)),
        "ms_per_scan_by_minute": per_minute,
        # since mapping, or as mapping reported it (both processes, with the pose graph's own)
        "peak_rss_mb": max(peak_rss_mb() or 0.0, result.stats.get("peak_memory_mb") or 0.0),
        "rss_before_mapping_mb": rss_before,
        "precomputation_mb": result.stats.get("precomputation_bytes", 0) / 2**20,
        "precomputation_evictions": int(result.stats.get("precomputation_evictions", 0)),
        "relation_error_m": float(err.translation.mean), "relation_error_deg": float(err.rotation.mean),
        "consecutive_error_m": float(local.translation.mean),
        "relations": int(len(relations.t1)), "revisits": int(revisits),
        "quality": result.quality.verdict if result.quality is not None else None,
        "profile": result.auto.profile if result.auto is not None else None,
    }


def svg(rows: list[dict]) -> str:
    """Time per scan (by minute of the recording) and peak memory against the prefix length, as a small SVG."""
    w, h, pad = 640, 300, 50
    longest = max(rows, key=lambda r: r["minutes"])
    series = longest["ms_per_scan_by_minute"]
    xmax = max(r["minutes"] for r in rows)
    ymax = max(max(series, default=1.0), 1e-3) * 1.2
    mmax = max(r["peak_rss_mb"] for r in rows) * 1.2

    def x(m):
        return pad + (w - 2 * pad) * m / xmax

    def y(v, top):
        return h - pad - (h - 2 * pad) * v / top

    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" font-family="sans-serif" '
             f'font-size="11"><rect width="{w}" height="{h}" fill="white"/>',
             f'<line x1="{pad}" y1="{h - pad}" x2="{w - pad}" y2="{h - pad}" stroke="black"/>',
             f'<line x1="{pad}" y1="{pad}" x2="{pad}" y2="{h - pad}" stroke="black"/>',
             f'<line x1="{w - pad}" y1="{pad}" x2="{w - pad}" y2="{h - pad}" stroke="black"/>']
    pts = " ".join(f"{x(i + 0.5):.1f},{y(v, ymax):.1f}" for i, v in enumerate(series))
    parts.append(f'<polyline points="{pts}" fill="none" stroke="#1f77b4" stroke-width="1.5"/>')
    mem = " ".join(f"{x(r['minutes']):.1f},{y(r['peak_rss_mb'], mmax):.1f}" for r in sorted(rows, key=lambda r: r["minutes"]))
    parts.append(f'<polyline points="{mem}" fill="none" stroke="#d62728" stroke-width="1.5" stroke-dasharray="4 3"/>')
    for r in rows:
        parts.append(f'<circle cx="{x(r["minutes"]):.1f}" cy="{y(r["peak_rss_mb"], mmax):.1f}" r="3" fill="#d62728"/>')
    for m in sorted({0} | {int(r["minutes"]) for r in rows}):
        parts.append(f'<text x="{x(m):.1f}" y="{h - pad + 15}" text-anchor="middle">{m}</text>')
    for k in range(5):
        v, mv = ymax * k / 4, mmax * k / 4
        parts.append(f'<text x="{pad - 5}" y="{y(v, ymax) + 4:.1f}" text-anchor="end" fill="#1f77b4">{v:.2f}</text>')
        parts.append(f'<text x="{w - pad + 5}" y="{y(mv, mmax) + 4:.1f}" fill="#d62728">{mv:.0f}</text>')
    parts += [f'<text x="{w / 2}" y="{h - 12}" text-anchor="middle">minutes of recording</text>',
              f'<text x="{pad}" y="{pad - 12}" fill="#1f77b4">ms per scan, each minute of the '
              f'{longest["minutes"]:g}-minute run</text>',
              f'<text x="{w - pad}" y="{pad - 12}" text-anchor="end" fill="#d62728">peak memory MB (per prefix)</text>',
              "</svg>"]
    return "\n".join(parts) + "\n"


def table(rows: list[dict], header: str) -> str:
    lines = [header, "",
             "| minutes | scans | nodes / submaps | loop closures | wall s | ms/scan (whole) | ms/scan (last 15 min) "
             "| peak memory MB (simulator before mapping) | precomputation MB (evicted) | relation error "
             "| consecutive only | verdict |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(
            f"| {r['minutes']:g} | {r['scans']} | {r['nodes']} / {r['submaps']} | {r['loop_closures']} | "
            f"{r['wall_s']:.0f} | {r['ms_per_scan']:.2f} | {r['ms_per_scan_last_15min']:.2f} | "
            f"{r['peak_rss_mb']:.0f} ({r['rss_before_mapping_mb']:.0f}) | {r['precomputation_mb']:.0f} "
            f"({r['precomputation_evictions']}) | {r['relation_error_m']:.3f} m / {r['relation_error_deg']:.2f}° "
            f"({r['relations']} relations, {r['revisits']} revisits) | {r['consecutive_error_m']:.3f} m | "
            f"{r['quality']} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, nargs="+", default=[15, 30, 60, 120])
    ap.add_argument("--jobs", type=int)
    ap.add_argument("--memory-budget", type=float, help="MB for precomputation grids (default: the option's)")
    ap.add_argument("--one", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--json", type=Path, help=argparse.SUPPRESS)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--svg", type=Path)
    args = ap.parse_args(argv)
    if args.one is not None:
        args.json.write_text(json.dumps(one(args.one, args.jobs, args.memory_budget)))
        return 0
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    header = (f"Measured at commit `{commit}`, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
              f"{len(os.sched_getaffinity(0))} cores, load average {os.getloadavg()[0]:.2f} at start; "
              f"`python bench/scale.py --minutes {' '.join(f'{m:g}' for m in args.minutes)}"
              f"{f' --jobs {args.jobs}' if args.jobs else ''}"
              f"{f' --memory-budget {args.memory_budget:g}' if args.memory_budget else ''}`, each prefix in a "
              "fresh process.")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for m in args.minutes:
            out = Path(tmp) / f"{m:g}.json"
            cmd = [sys.executable, __file__, "--one", str(m), "--json", str(out)]
            if args.jobs:
                cmd += ["--jobs", str(args.jobs)]
            if args.memory_budget:
                cmd += ["--memory-budget", str(args.memory_budget)]
            subprocess.run(cmd, check=True)
            rows.append(json.loads(out.read_text()))
            print(table(rows[-1:], f"{m:g} min"), flush=True)
    text = table(rows, header)
    print(text)
    if args.out:
        args.out.write_text(text)
        (args.out.with_suffix(".json")).write_text(json.dumps(rows, indent=1))
    if args.svg:
        args.svg.write_text(svg(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
