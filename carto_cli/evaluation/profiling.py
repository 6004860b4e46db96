"""The timing report of `carto profile`: a StageTimer run as one versioned JSON report, its text form, the
reference-kernel calibration and the machine it ran on (commands/profile.py runs the pipeline).

Schema (``schema_version`` 1, see ``carto_cli/schemas/profile.schema.json``)::

    {
      "schema": "carto.profile", "schema_version": 1, "carto_version": "...",
      "recording": path, "algorithm": "cartographer" | "gmapping", "created": ISO time, "machine": {...},
      "options_changed": {dotted key: value},
      "counts": {"scans", "nodes", "submaps", "constraints", "loop_closures"},
      "gmapping": {"processed_scans", "particles", "resamplings", "mean_neff", "map_memory_peak_bytes"},
                                    # gmapping runs only
      "wall_s": float, "ms_per_scan": float, "scans_per_s": float,
      "repeats": int,               # runs merged (merge_repeats); each stage also has cpu_ms[_per_scan], cpu_spread
      "compile_ms": float,          # numba compilation / cache loading, reported apart
      "peak_memory_mb": float,      # max RSS of this process, plus what the graph's process added
      "calibration": null | {"kernel": name, "ms": float},
      "timing": <carto_cli.core.timing.report_json>
    }

All times are milliseconds unless the key says otherwise.
"""
from __future__ import annotations

import math
import os
import platform
import time
from collections.abc import Sequence
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from carto_cli import __version__
from carto_cli.core import kernels
from carto_cli.core.memory import peak_rss_mb
from carto_cli.core.timing import StageTimer, report_json
from carto_cli.gmapping import Algorithm
from carto_cli.options import Options, changed_options

SCHEMA = "carto.profile"
SCHEMA_VERSION = 1
SCHEMA_PATH = Path(__file__).resolve().parents[1] / "schemas" / "profile.schema.json"

# Stages whose share of a run is dominated by one-off work; not part of the steady state.
COMPILE_STAGE = kernels.STAGE
# What a gmapping run reports besides the counts: the filter's own size and behaviour.
GMAPPING_STATS = ("processed_scans", "particles", "resamplings", "mean_neff", "map_memory_peak_bytes")


def cpu_model() -> str:
    """The CPU's model name (Linux /proc/cpuinfo), else what platform knows."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict:
    cpu = cpu_model()
    import numba

    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "numba": numba.__version__,
        "platform": platform.platform(),
    }


def calibrate(repeats: int = 7) -> dict:
    """Time a fixed reference workload: insert and match one synthetic scan on one synthetic grid.

    It exercises the same kinds of kernels the pipeline runs (ray casting, odds updates,
    bicubic least squares), so the ratio of a stage to it transfers between machines
    better than a raw time does. The median of ``repeats`` runs, after one warm-up run.
    """
    from carto_cli.grid.probability_grid import ProbabilityGrid
    from carto_cli.grid.range_inserter import ProbabilityGridRangeDataInserter
    from carto_cli.matching import least_squares
    from carto_cli.sensor.range_filter import RangeData

    angles = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    # A 12 × 8 m room seen from inside: the ranges to its walls along each bearing.
    hx, hy = 6.0, 4.0
    with np.errstate(divide="ignore"):
        tx = np.where(np.cos(angles) != 0, np.abs(hx / np.cos(angles)), np.inf)
        ty = np.where(np.sin(angles) != 0, np.abs(hy / np.sin(angles)), np.inf)
    r = np.minimum(tx, ty)
    points = np.stack([r * np.cos(angles), r * np.sin(angles)], axis=1)
    inserter = ProbabilityGridRangeDataInserter()

    def once() -> float:  # CPU time, as the gates compare
        t0 = time.process_time()
        grid = ProbabilityGrid.centered((0.0, 0.0), 0.05, 300)
        for _ in range(5):
            inserter.insert(RangeData(np.zeros(2), points, np.empty((0, 2))), grid)
        for k in range(20):
            least_squares.match(grid, points[::2], np.array([0.05, -0.03, 0.01 * (k % 3)]))
        return (time.process_time() - t0) * 1e3

    once()
    samples = [once() for _ in range(repeats)]
    return {"kernel": "insert5+ls20/720beams/v1", "ms": float(np.median(samples))}


def build_report(result, timer: StageTimer, options: Options, recording: str | Path,
                 calibration: dict | None = None) -> dict:
    timing = report_json(timer)
    compile_stage = timing["stages"].get(COMPILE_STAGE)
    scans = int(result.stats["scans"])
    scan_stage = timing["stages"].get("scan")
    ms_per_scan = scan_stage["ms_per_scan"] if scan_stage and scan_stage.get("ms_per_scan") is not None else None
    algorithm = result.stats.get("algorithm", "cartographer")
    report = {
        "schema": SCHEMA,
        "schema_version": SCHEMA_VERSION,
        "carto_version": __version__,
        "recording": str(recording),
        "algorithm": algorithm,
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        "machine": machine_info(),
        "options_changed": dict(changed_options(options)),
        "counts": {
            "scans": scans,
            "nodes": int(result.stats["nodes"]),
            "submaps": int(result.stats["submaps"]),
            "constraints": int(result.stats.get("constraints", 0)),
            "loop_closures": int(result.stats.get("loop_closures", 0)),
        },
        "wall_s": timing["wall_ms"] / 1e3,
        "ms_per_scan": ms_per_scan,
        "scans_per_s": (1e3 / ms_per_scan) if ms_per_scan else None,
        "compile_ms": compile_stage["total_ms"] if compile_stage else 0.0,
        # since mapping (outputs written), or as mapping reported it (both processes, with the graph's own)
        "peak_memory_mb": max(peak_rss_mb() or 0.0, result.stats.get("peak_memory_mb") or 0.0),
        "calibration": calibration,
        "timing": timing,
    }
    if algorithm == Algorithm.GMAPPING:
        # mean_neff is NaN when only the first scan was processed: null keeps the report strict JSON.
        report["gmapping"] = {k: _finite_or_none(result.stats[k]) for k in GMAPPING_STATS}
    return report


def merge_repeats(runs: list[dict]) -> dict:
    """One report from several runs of the same recording: the last run's tree and figures, and for every stage
    the lowest CPU time over the runs (``cpu_ms_per_scan`` / ``cpu_ms``: the run least disturbed by other work
    on the machine) with ``cpu_spread``, (highest - lowest) / lowest, the noise the gates allow for."""
    report = runs[-1]
    report["repeats"] = len(runs)
    for path, stage in report["timing"]["stages"].items():
        spread = None
        for key in ("cpu_ms", "cpu_ms_per_scan"):  # the second, where a stage has it, is the one gated
            values = [r["timing"]["stages"][path].get(key) for r in runs if path in r["timing"]["stages"]]
            values = [v for v in values if v is not None]
            if values:
                low = min(values)
                stage[key] = low
                spread = (max(values) - low) / low if low > 0 else 0.0
        if spread is not None:
            stage["cpu_spread"] = spread
    return report


def _finite_or_none(value):
    return None if isinstance(value, float) and not math.isfinite(value) else value


def format_report(report: dict) -> str:
    c = report["counts"]
    lines = [f"recording   {report['recording']}"]
    g = report.get("gmapping")
    if g is not None:
        lines.append(f"algorithm   gmapping: {g['processed_scans']} of {c['scans']} scans processed, "
                     f"{g['particles']} particles, {g['resamplings']} resamplings, "
                     f"mean Neff {'-' if g['mean_neff'] is None else format(g['mean_neff'], '.1f')}, "
                     f"map peak {g['map_memory_peak_bytes'] / 2**20:.0f} MB")
    lines += [
        f"scans {c['scans']}, nodes {c['nodes']}, submaps {c['submaps']}, constraints {c['constraints']} "
        f"({c['loop_closures']} loop closures)",
        f"steady state {report['ms_per_scan']:.3f} ms/scan ({report['scans_per_s']:.0f} scans/s), "
        f"wall {report['wall_s']:.2f} s, numba compile/cache {report['compile_ms']:.0f} ms, "
        f"peak memory {report['peak_memory_mb']:.0f} MB"
        if report["ms_per_scan"] else f"wall {report['wall_s']:.2f} s",
    ]
    if report.get("calibration"):
        lines.append(f"calibration {report['calibration']['kernel']}: {report['calibration']['ms']:.2f} ms")
    lines.append("")
    lines.append(_tree_text(report["timing"]))
    return "\n".join(lines)


def _tree_text(timing: dict) -> str:
    rows = []

    def fmt(x, spec):
        return "" if x is None else format(x, spec)

    def visit(node: dict, prefix: str, last: bool, depth: int):
        name = "total (wall)" if depth == 0 else node["name"]
        if node.get("concurrent"):
            name += " (concurrent: not in the sum)"
        branch = "" if depth == 0 else ("└─ " if last else "├─ ")
        share = fmt(None if node["share"] is None else 100 * node["share"], ".1f")
        rows.append((prefix + branch + name, fmt(node["total_ms"], ".1f"), fmt(node["ms_per_scan"], ".3f"),
                     share + ("%" if share else ""), str(node["calls"]) if depth else "",
                     fmt(node["p50_ms"], ".3f"), fmt(node["p95_ms"], ".3f"), fmt(node["p99_ms"], ".3f")))
        kids = node["children"]
        child_prefix = prefix + ("" if depth == 0 else ("   " if last else "│  "))
        for k in kids:
            visit(k, child_prefix, False, depth + 1)
        if kids:
            self_share = node["self_share"]
            share = fmt(None if self_share is None else 100 * self_share, ".1f")
            per_scan = None
            if node["ms_per_scan"] is not None and node["total_ms"]:
                per_scan = node["ms_per_scan"] * node["self_ms"] / node["total_ms"]
            rows.append((child_prefix + "└─ " + ("(other)" if depth else "(other: untimed)"),
                         fmt(node["self_ms"], ".1f"), fmt(per_scan, ".3f"), share + ("%" if share else ""),
                         "", "", "", ""))

    visit(timing["tree"], "", True, 0)
    header = ("stage", "total ms", "ms/scan", "%total", "calls", "p50 ms", "p95 ms", "p99 ms")
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    out = []
    for r in [header] + rows:
        out.append("  ".join([r[0].ljust(widths[0])] + [r[i].rjust(widths[i]) for i in range(1, len(r))]).rstrip())
    return "\n".join(out)


def profile_relocalization(loaded_map, recording, *, every: int = 10, max_queries: int = 200,
                           perturb_xy: float = 0.5, perturb_yaw: float = math.radians(5.0), seed: int = 0,
                           scan_topic: str | Sequence[str] | None = None) -> dict:
    """Relocalize every ``every``-th scan of ``recording`` in ``loaded_map`` and time the buckets.

    Priors are the map's own trajectory at the scan's time, perturbed uniformly by up to
    ``perturb_xy`` / ``perturb_yaw``, so the recording should be (a drive through) the mapped
    one; scans outside the mapped time span get a global search. The first query pays for
    building precomputation grids and loading kernels; it is reported apart.
    """
    from carto_cli.core.errors import CartoError
    from carto_cli.evaluation.metrics import interpolate_poses
    from carto_cli.evaluation.relocalization import Probe, every_nth_scan, run_probes, summarize_outcomes
    from carto_cli.relocalization import TIMING_BUCKETS, Latency, Relocalizer

    relocalizer = Relocalizer(loaded_map)
    rng = np.random.default_rng(seed)
    traj = loaded_map.trajectory

    def probes():
        for i, record in every_nth_scan(recording, every, scan_topic):
            prior = None
            if traj is not None:
                xy, th, valid = interpolate_poses(traj, np.array([record.time]))
                if valid[0]:
                    dx, dy = rng.uniform(-perturb_xy, perturb_xy, 2)
                    prior = (xy[0, 0] + dx, xy[0, 1] + dy, th[0] + rng.uniform(-perturb_yaw, perturb_yaw))
            yield Probe(i, record, prior)

    outcomes = run_probes(relocalizer, probes(), max_queries=max_queries)
    if not outcomes:
        raise CartoError("no scans to relocalize", recording.path)
    summary = summarize_outcomes(outcomes)
    results = [o.result for o in outcomes if o.result is not None]
    first, rest = results[0], results[1:] or results[:1]

    def stats(values) -> dict:
        lat = Latency.of(values)
        return {"mean_ms": lat.mean_ms, "p50_ms": lat.p50_ms, "p95_ms": lat.p95_ms, "p99_ms": lat.p99_ms}

    total = stats([r.total_ms for r in rest])
    buckets = {b: stats([r.timings[b] for r in rest]) for b in TIMING_BUCKETS}
    for b in buckets.values():
        b["share"] = b["mean_ms"] / total["mean_ms"] if total["mean_ms"] > 0 else None
    return {
        "queries": summary.queries,
        "success_rate": summary.success_rate,
        "first_query_ms": first.total_ms,
        "total": total,
        "stages": buckets,
        "paths": summary.paths,
    }


def format_relocalization(rel: dict) -> str:
    t = rel["total"]
    lines = [f"relocalization: {rel['queries']} queries, {100 * rel['success_rate']:.1f}% reliable, "
             f"p50 {t['p50_ms']:.2f} ms, p95 {t['p95_ms']:.2f} ms, p99 {t['p99_ms']:.2f} ms "
             f"(first query {rel['first_query_ms']:.0f} ms: grids and kernels)",
             f"  {'stage':<20} {'mean ms':>8} {'share':>6} {'p50 ms':>8} {'p95 ms':>8} {'p99 ms':>8}"]
    for name, s in rel["stages"].items():
        share = "" if s["share"] is None else f"{100 * s['share']:.1f}%"
        lines.append(f"  {name:<20} {s['mean_ms']:>8.2f} {share:>6} {s['p50_ms']:>8.2f} {s['p95_ms']:>8.2f} "
                     f"{s['p99_ms']:>8.2f}")
    lines.append("  paths: " + ", ".join(f"{k} {v}" for k, v in rel["paths"].items()))
    return "\n".join(lines)
