"""Calibration of the reference-free map verdict (carto_cli/mapping/quality.py) against relation error.

Maps good and bad runs of the shared bench cases (one at a time), keeps each result in a cache
directory (so signals can be re-scored without re-mapping), then prints one row per run: relation
error, the odometry's own relation error, ATE RMSE against the ground truth, every quality signal,
the verdict, and the time the assessment took as a share of the mapping time (the mapping time is
measured after a 30-scan warm-up map, so without numba's compilation).

    python bench/quality_calibration.py [--cache DIR] [--only NAME,...] [--remap] [--markdown]

``$CARTO_SHARED_DATA`` (default ../shared/data next to the checkout, else /work/shared/data) holds bench/
and bench-dense/.
"""
from __future__ import annotations

import argparse
import os
import pickle
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carto_cli.evaluation.metrics import ate, read_relations, relation_error
from carto_cli.io.trajectory import Trajectory, read_trajectory
from carto_cli.mapping.constraint_builder import ConstraintBuilder
from carto_cli.mapping.quality import assess
from carto_cli.options import load_options
from carto_cli.pipeline import build, opened, read_options

SHARED = Path(os.environ.get("CARTO_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
if not SHARED.is_dir():
    SHARED = Path("/work/shared/data")


@dataclass(frozen=True)
class Run:
    name: str
    case: str  # under SHARED
    profile: str | None
    loop_closure: bool = True
    max_scans: int | None = None
    overrides: list[str] = field(default_factory=list)


# Good maps first (relation error a few cm, intel sparse 0.38 m), then the bad ones (metres).
RUNS = [
    Run("aces sparse", "bench/aces", "sparse"),
    Run("intel sparse", "bench/intel", "sparse"),
    Run("freiburg sparse", "bench/freiburg-079", "sparse"),
    Run("dense-aces wheeled 3000", "bench-dense/aces", "wheeled", max_scans=3000),
    Run("dense-intel wheeled 3000", "bench-dense/intel", "wheeled", max_scans=3000),
    Run("dense-freiburg wheeled 3000", "bench-dense/freiburg-079", "wheeled", max_scans=3000),
    Run("aces sparse nrd20", "bench/aces", "sparse", overrides=["trajectory_builder_2d.submaps.num_range_data=20"]),
    Run("orebro sparse", "bench/orebro", "sparse"),
    Run("edmonton sparse", "bench/edmonton", "sparse"),
    Run("fhw sparse", "bench/fhw", "sparse"),
    Run("intel sparse no-lc", "bench/intel", "sparse", loop_closure=False),
    Run("aces sparse no-lc", "bench/aces", "sparse", loop_closure=False),
    Run("aces default", "bench/aces", None),
    Run("intel default", "bench/intel", None),
    Run("orebro default", "bench/orebro", None),
    Run("edmonton default", "bench/edmonton", None),
    Run("fhw default", "bench/fhw", None),
    Run("dense-aces default 3000", "bench-dense/aces", None, max_scans=3000),
    Run("dense-intel wheeled no-lc 3000", "bench-dense/intel", "wheeled", loop_closure=False, max_scans=3000),
    Run("freiburg sparse no-lc", "bench/freiburg-079", "sparse", loop_closure=False),
    Run("freiburg default", "bench/freiburg-079", None),
    Run("dense-intel default 3000", "bench-dense/intel", None, max_scans=3000),
    Run("dense-aces wheeled", "bench-dense/aces", "wheeled"),
    Run("dense-aces wheeled no-lc", "bench-dense/aces", "wheeled", loop_closure=False),
    # Mapped after the thresholds were chosen, to check them.
    Run("intel sparse nrd20", "bench/intel", "sparse", overrides=["trajectory_builder_2d.submaps.num_range_data=20"]),
    Run("aces sparse odometry-weight 1e5", "bench/aces", "sparse",
        overrides=["pose_graph.optimization_problem.odometry_translation_weight=1e5",
                   "pose_graph.optimization_problem.odometry_rotation_weight=1e5"]),
    Run("intel sparse no-online-csm", "bench/intel", "sparse",
        overrides=["trajectory_builder_2d.use_online_correlative_scan_matching=false"]),
    Run("edmonton sparse no-lc", "bench/edmonton", "sparse", loop_closure=False),
    Run("dense-freiburg default 3000", "bench-dense/freiburg-079", None, max_scans=3000),  # ~20 min
    Run("dense-intel wheeled", "bench-dense/intel", "wheeled"),
]


def _slug(name: str) -> str:
    return name.replace(" ", "_")


def _ate(result, case: Path) -> float:
    """ATE RMSE (m) against the case's ground truth, after the best SE(2) alignment."""
    truth = read_trajectory(case / "groundtruth.txt")
    return float(ate(Trajectory.from_poses(result.times, result.poses), truth).translation.rmse)


def map_run(run: Run, cache: Path, remap: bool) -> dict:
    path = cache / f"{_slug(run.name)}.pkl"
    d = SHARED / run.case
    if path.exists() and not remap:
        with path.open("rb") as f:
            out = pickle.load(f)
        out.setdefault("ate", _ate(out["result"], d))
        return out
    opts = load_options(run.profile, run.overrides)
    with opened(d / "scans.clf.gz", read_options(opts)) as src:
        # A short map first, so that numba's compilation is not timed as mapping.
        build(src.recording, opts, selection=src.selection, loop_closure=run.loop_closure, max_scans=30)
        t0 = time.perf_counter()
        res = build(src.recording, opts, selection=src.selection, loop_closure=run.loop_closure,
                    max_scans=run.max_scans)
        seconds = time.perf_counter() - t0
        odo = np.array([(r.time, r.x, r.y, r.yaw) for r in src.recording.records([src.selection.odometry])])
    relations = read_relations(d / "relations.txt")
    error = relation_error(Trajectory.from_poses(res.times, res.poses), relations).translation.mean
    odo_error = relation_error(Trajectory.from_poses(odo[:, 0], odo[:, 1:]), relations).translation.mean
    if res.graph is not None:
        # The precomputation grids are most of the result's memory and no signal reads them.
        fresh = ConstraintBuilder(opts)
        fresh.stats = res.graph.builder.stats
        fresh.connected = res.graph.builder.connected
        res.graph.builder = fresh
    out = {"result": res, "odometry": odo, "error": float(error), "odometry_error": float(odo_error),
           "ate": _ate(res, d), "map_s": seconds}
    cache.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        pickle.dump(out, f, protocol=pickle.HIGHEST_PROTOCOL)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "carto-quality-cal")
    ap.add_argument("--only", default="", help="comma-separated run names")
    ap.add_argument("--remap", action="store_true", help="map again even when cached")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args(argv)
    wanted = {w.strip() for w in args.only.split(",") if w.strip()}
    unknown = wanted - {r.name for r in RUNS}
    if unknown:
        ap.error(f"no run named {', '.join(sorted(unknown))}")
    runs = [r for r in RUNS if not wanted or r.name in wanted]
    assess(map_run(runs[0], args.cache, False)["result"])  # compile the kernels outside the timing
    rows = []
    for run in runs:
        m = map_run(run, args.cache, args.remap)
        t0 = time.perf_counter()
        q = assess(m["result"], m["odometry"])
        share = (time.perf_counter() - t0) / m["map_s"]
        values = {c.name: c.value for c in q.checks}
        rows.append((run.name, m["error"], m["odometry_error"], m["ate"], values, q.verdict, share))
        print(f"{run.name:32s} err {m['error']:7.3f} odo {m['odometry_error']:6.2f} ate {m['ate']:6.2f} "
              + " ".join(f"{k} {v:7.3f}" for k, v in values.items())
              + f"  {q.verdict:8s} {100 * share:4.1f}% of {m['map_s']:.0f} s", flush=True)
    if args.markdown:
        names = list(dict.fromkeys(k for r in rows for k in r[4]))
        print("\n| run | relation error m | odometry m | ATE m | " + " | ".join(f"{k} %" for k in names)
              + " | verdict | cost |")
        print("|---" * (len(names) + 6) + "|")
        for name, err, odo, ate_m, values, verdict, share in rows:
            cells = " | ".join(f"{values[k]:.1f}" if k in values else "-" for k in names)
            print(f"| {name} | {err:.3f} | {odo:.2f} | {ate_m:.2f} | {cells} | {verdict} | {100 * share:.1f} % |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
