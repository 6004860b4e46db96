"""Calibration of the reference-free map verdict (carto_cli/mapping/quality.py) against relation error.

Maps good and bad runs of the shared bench cases (one at a time), keeps each result in a cache
directory (so signals can be re-scored without re-mapping), then prints one row per run: relation
error, the odometry's own relation error, ATE RMSE against the ground truth, every quality signal,
the verdict, and the time the assessment took as a share of the mapping time (the mapping time is
measured after a 30-scan warm-up map, so without numba's compilation).

    python bench/quality_calibration.py [--cache DIR] [--only NAME,...] [--remap] [--markdown]
    python bench/quality_calibration.py --loo [--only NAME,...] [--regrid]

``--loo`` chooses the see-through check's solid share and own radius over ``GRID``, leaving one building out
at a time, on the cached maps (see ``leave_one_building_out``).

``$CARTO_SHARED_DATA`` (default ../shared/data next to the checkout, else /work/shared/data) holds bench/
and bench-dense/. Cases ``sim/<builder>`` are simulated instead (``carto_cli.sim.world``: buildings with
walls one line thick, glass, hedges, parked cars), 10 Hz, 360 beams, driven twice round at up to 1 m/s,
relations built from the exact ground truth as bench/harness.py does for ``sim-loop``. A run with
``misplace`` is another run's map with every node from halfway on moved by (x m, y m, yaw deg) about the
map's origin: a revisit placed wrong on purpose, a map a person would reject.
"""
from __future__ import annotations

import argparse
import math
import os
import pickle
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carto_cli.evaluation.metrics import ate, read_relations, relation_error
from carto_cli.io.sources.open import open_recording
from carto_cli.io.topics import select_topics
from carto_cli.io.trajectory import Trajectory, read_trajectory
from carto_cli.mapping.constraint_builder import ConstraintBuilder
from carto_cli.mapping.quality import assess
from carto_cli.options import load_options
from carto_cli.pipeline import build, read_options
from carto_cli.sim.lidar import Lidar
from carto_cli.sim.world import Material

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
    misplace: tuple[float, float, float] | None = None  # (x m, y m, deg): ``base``'s map, second half moved
    base: str | None = None


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
    # Issue 43, item 4: simulated buildings (SIM below) with walls one line thick seen from both sides, doors,
    # glass, plants, hedges, bushes and parked cars; good maps and wrong ones.
    Run("sim-office wheeled", "sim/office", "wheeled"),
    Run("sim-office-specular wheeled", "sim/office-specular", "wheeled"),
    Run("sim-courtyard wheeled", "sim/courtyard", "wheeled"),
    Run("sim-courtyard-r10 wheeled", "sim/courtyard-r10", "wheeled"),
    Run("sim-courtyard-keyscans sparse", "sim/courtyard-keyscans", "sparse"),
    Run("sim-office wheeled no-lc", "sim/office", "wheeled", loop_closure=False),
    Run("sim-courtyard wheeled no-lc", "sim/courtyard", "wheeled", loop_closure=False),
    Run("sim-courtyard-keyscans sparse no-lc", "sim/courtyard-keyscans", "sparse", loop_closure=False),
    Run("sim-office default", "sim/office", None),
    Run("sim-courtyard default", "sim/courtyard", None),
    Run("sim-office misplaced 0.5 m", "sim/office", "wheeled", misplace=(0.5, 0.0, 0.0), base="sim-office wheeled"),
    Run("sim-office misplaced 3 deg", "sim/office", "wheeled", misplace=(0.0, 0.0, 3.0), base="sim-office wheeled"),
    Run("sim-office-specular misplaced 0.5 m", "sim/office-specular", "wheeled", misplace=(0.0, 0.5, 0.0),
        base="sim-office-specular wheeled"),
    Run("sim-office-specular misplaced 0.3 m 2 deg", "sim/office-specular", "wheeled", misplace=(0.3, 0.0, 2.0),
        base="sim-office-specular wheeled"),
    Run("sim-courtyard misplaced 0.5 m", "sim/courtyard", "wheeled", misplace=(0.0, 0.5, 0.0),
        base="sim-courtyard wheeled"),
    Run("sim-courtyard misplaced 3 deg", "sim/courtyard", "wheeled", misplace=(0.0, 0.0, 3.0),
        base="sim-courtyard wheeled"),
    Run("sim-courtyard-r10 misplaced 0.3 m 2 deg", "sim/courtyard-r10", "wheeled", misplace=(0.3, 0.0, 2.0),
        base="sim-courtyard-r10 wheeled"),
    Run("sim-courtyard-keyscans misplaced 1 m 5 deg", "sim/courtyard-keyscans", "sparse", misplace=(1.0, 0.0, 5.0),
        base="sim-courtyard-keyscans sparse"),
]


def _slug(name: str) -> str:
    return name.replace(" ", "_")


def _slim(res, opts) -> None:
    """Drop the constraint builder's precomputation grids: most of the result's memory, read by no signal."""
    if res.graph is not None:
        fresh = ConstraintBuilder(opts)
        fresh.stats = res.graph.builder.stats
        fresh.connected = res.graph.builder.connected
        fresh.stacks = None  # it holds a lock, which does not pickle
        res.graph.builder = fresh


def _store(out: dict, path: Path) -> None:
    """Pickle ``out`` to ``path`` whole or not at all (a failed dump leaves no empty file behind)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with tmp.open("wb") as f:
        pickle.dump(out, f, protocol=pickle.HIGHEST_PROTOCOL)
    tmp.replace(path)


def _with_ate(out: dict, run: Run) -> dict:
    if "ate" not in out:
        out["ate"] = _ate(out["result"], SHARED / run.case)
    return out


def _ate(result, case: Path) -> float:
    """ATE RMSE (m) against the case's ground truth, after the best SE(2) alignment."""
    truth = read_trajectory(case / "groundtruth.txt")
    return float(ate(Trajectory.from_poses(result.times, result.poses), truth).translation.rmse)


# Simulated cases: (world builder, its arguments, simulate's arguments). office: glass returning 30 % of the
# rays at any angle, plants 50 %; office-specular: glass returning 60 % within 25 degrees of its normal, none
# beyond; courtyard: hedges and bushes returning 70 % within 6 m, car bodies 70 % within 8 m, none from
# further, glass as office-specular; courtyard-r10: hedges 50 % and car bodies 60 % within 10 m, glass 30 %;
# courtyard-keyscans: the courtyard (another seed) as a key-scan log: 2 scans/s at 1 m/s, 181 beams over 180
# degrees, 80 m range.
SIM = {
    "sim/office": ("glass_office", {}, {}),
    "sim/office-specular": ("glass_office", {"seed": 1, "glass": Material(0.6, incidence=25.0)}, {}),
    "sim/courtyard": ("courtyard", {}, {}),
    "sim/courtyard-r10": ("courtyard", {"seed": 1, "hedges": Material(0.5, reach=10.0),
                                        "cars": Material(0.6, reach=10.0), "glass": Material(0.3)}, {}),
    "sim/courtyard-keyscans": ("courtyard", {"seed": 2},
                               {"scan_rate": 2.0, "lidar": Lidar(beams=181, fov=3.141592653589793, max_range=80.0)}),
}


def simulation(case: str):
    """A ``SIM`` case driven twice round its route (closed routes; an open one once), as a Simulation."""
    from carto_cli.sim import Limits, follow_route, simulate
    from carto_cli.sim import world as worlds

    builder, kwargs, sim_kwargs = SIM[case]
    world = getattr(worlds, builder)(**kwargs)
    trajectory = follow_route(world, laps=2 if world.closed else 1, limits=Limits(v_max=1.0))
    return simulate(world, trajectory, seed=kwargs.get("seed", 0), **sim_kwargs)


def map_simulated(run: Run) -> dict:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from harness import relations_from_groundtruth

    sim = simulation(run.case)
    opts = load_options(run.profile, run.overrides)
    with sim.recording() as rec:
        build(rec, opts, loop_closure=run.loop_closure, max_scans=30)
        t0 = time.perf_counter()
        res = build(rec, opts, loop_closure=run.loop_closure, max_scans=run.max_scans)
        seconds = time.perf_counter() - t0
    gt = sim.ground_truth
    truth = Trajectory.from_arrays(gt[:, 0], gt[:, 1], gt[:, 2], gt[:, 3])
    rate = 1.0 / float(np.median(np.diff(sim.scan_times)))
    # As bench/harness.py at 10 Hz: pairs a second apart every second, revisits sampled twice a second.
    relations, _ = relations_from_groundtruth(truth, step=max(1, round(rate)), revisit_every=max(1, round(rate / 2)))
    odo = sim.odometry[:, :4].copy()
    return {"result": res, "odometry": odo, "truth": truth, "relations": relations, "map_s": seconds}


class _Moved:
    """A pose graph with other global poses (what the verdict reads), the rest the graph's own."""

    def __init__(self, graph, poses: np.ndarray):
        self._graph = graph
        self.global_poses = poses

    def __getattr__(self, name):
        return getattr(self._graph, name)


def misplaced(base: dict, dx: float, dy: float, dyaw_deg: float) -> dict:
    """``base``'s map with every node (and scan pose) from the middle node's time on moved by (dx, dy, dyaw)
    about the map's origin: the result is a copy, the base's arrays are not touched."""
    import copy

    from carto_cli.core import transform

    res = copy.copy(base["result"])
    offset = np.array([dx, dy, math.radians(dyaw_deg)])
    poses = np.array(res.graph.global_poses, np.float64, copy=True)
    half = len(poses) // 2
    poses[half:] = transform.compose(offset, poses[half:])
    graph = _Moved(res.graph, poses)
    t_half = float(np.asarray(res.times)[np.asarray(res.node_scans)[half]])
    scan_poses = np.array(res.poses, np.float64, copy=True)
    later = np.asarray(res.times) >= t_half
    scan_poses[later] = transform.compose(offset, scan_poses[later])
    res.graph, res.poses, res.unrefined_node_poses = graph, scan_poses, None
    return {**base, "result": res}


def map_run(run: Run, cache: Path, remap: bool) -> dict:
    if run.misplace is not None:
        base = map_run(next(r for r in RUNS if r.name == run.base), cache, remap=False)
        out = misplaced(base, *run.misplace)
        rel = base["relations"] if "relations" in base else read_relations(SHARED / run.case / "relations.txt")
        out["error"] = float(relation_error(Trajectory.from_poses(out["result"].times, out["result"].poses),
                                            rel).translation.mean)
        if "truth" in base:
            out["ate"] = float(ate(Trajectory.from_poses(out["result"].times, out["result"].poses),
                                   base["truth"]).translation.rmse)
        return out
    path = cache / f"{_slug(run.name)}.pkl"
    if path.exists() and not remap:
        with path.open("rb") as f:
            return _with_ate(pickle.load(f), run)
    if run.case.startswith("sim/"):
        out = map_simulated(run)
        res, odo, relations = out["result"], out["odometry"], out["relations"]
        out["ate"] = float(ate(Trajectory.from_poses(res.times, res.poses), out["truth"]).translation.rmse)
        out["error"] = float(relation_error(Trajectory.from_poses(res.times, res.poses), relations).translation.mean)
        out["odometry_error"] = float(relation_error(Trajectory.from_poses(odo[:, 0], odo[:, 1:]),
                                                     relations).translation.mean)
        _slim(res, load_options(run.profile, run.overrides))
        _store(out, path)
        return out
    d = SHARED / run.case
    opts = load_options(run.profile, run.overrides)
    with open_recording(d / "scans.clf.gz", read_options(opts)) as recording:
        # A short map first, so that numba's compilation is not timed as mapping.
        build(recording, opts, loop_closure=run.loop_closure, max_scans=30)
        t0 = time.perf_counter()
        res = build(recording, opts, loop_closure=run.loop_closure, max_scans=run.max_scans)
        seconds = time.perf_counter() - t0
        odo = np.array([(r.time, r.x, r.y, r.yaw) for r in recording.records([select_topics(recording).odometry])])
    relations = read_relations(d / "relations.txt")
    error = relation_error(Trajectory.from_poses(res.times, res.poses), relations).translation.mean
    odo_error = relation_error(Trajectory.from_poses(odo[:, 0], odo[:, 1:]), relations).translation.mean
    _slim(res, opts)
    out = {"result": res, "odometry": odo, "error": float(error), "odometry_error": float(odo_error),
           "ate": _ate(res, d), "map_s": seconds}
    _store(out, path)
    return out


# ------------------------------------------------------------------ choosing the see-through constants

# (SOLID_SHARE, OWN_RADIUS_M) pairs tried; a share of 0 is the check without the solidity test (before issue 43).
GRID = [(share, radius) for share in (0.0, 0.5, 0.6, 0.7, 0.8, 0.9) for radius in (0.2, 0.3, 0.4, 0.6, 1.0)]
GOOD_M = 0.05  # a map within this relation error must not be failed (issue 43's target)
FAIR_M = 0.1  # ... and as few as can be within this one (docs/benchmarks.md counts those)


def building(run: Run) -> str:
    """What a run maps: the shared case's building (bench-dense/aces is aces), or the simulated one."""
    if run.case.startswith("sim/"):
        return "sim-office" if "office" in run.case else "sim-courtyard"
    return run.case.split("/")[1]


def requirement(run: Run, m: dict) -> str | None:
    """'failed' for a map worse than its odometry or a revisit misplaced on purpose by 0.5 m or 3 degrees or
    more (the issue's wrong map: walls doubled, a person rejects it), 'not failed' for a map within ``GOOD_M``,
    'rather not failed' within ``FAIR_M``, None (free) beyond. Smaller misplacements (0.3 m and 2 degrees) are
    free: they show where the check's resolution ends."""
    moved = run.misplace is not None and (math.hypot(*run.misplace[:2]) >= 0.5 or abs(run.misplace[2]) >= 3.0)
    if moved or m["error"] > m["odometry_error"]:
        return "failed"
    if m["error"] <= GOOD_M:
        return "not failed"
    return "rather not failed" if m["error"] <= FAIR_M else None


def grid_values(run: Run, m: dict, cache: Path, regrid: bool) -> dict:
    """see_through (the larger of refined and unrefined) per ``GRID`` pair, and the worst level of the other
    checks; cached per run and version of quality.py and see_through.py."""
    import hashlib
    import json

    from carto_cli.mapping import quality, see_through

    code = b"".join(Path(m.__file__).read_bytes() for m in (quality, see_through))
    version = hashlib.sha256(code).hexdigest()[:12]
    path = cache / f"grid-{_slug(run.name)}-{version}.json"
    if path.exists() and not regrid:
        return json.loads(path.read_text())
    res = m["result"]
    values = {}
    for share, radius in GRID:
        worst = 0.0
        for poses in (None, res.unrefined_node_poses):
            if poses is None and worst:
                continue
            _, f = see_through.node_see_through(res.graph, res.laser_pose, poses=poses, solid_share=share, radius=radius)
            f = f[np.isfinite(f)]
            worst = max(worst, 100.0 * float(np.mean(f > quality.NODE_SHARE)) if f.size else 0.0)
        values[f"{share}/{radius}"] = worst
    others = [c for c in assess(res, m["odometry"]).checks if not c.name.startswith("see_through")]
    out = {"see_through": values, "others": max((quality.LEVELS.index(c.level) for c in others), default=0)}
    path.write_text(json.dumps(out))
    return out


def _level(value: float) -> int:
    from carto_cli.mapping.quality import SEE_THROUGH_FAILED, SEE_THROUGH_SUSPECT

    return 2 if value > SEE_THROUGH_FAILED else 1 if value > SEE_THROUGH_SUSPECT else 0


def _score(rows: list[tuple], key: str) -> tuple[int, int, float]:
    """(violations, maps within ``FAIR_M`` failed, margin) of one GRID pair over rows (run, requirement, grid
    values): margin is how far the failing threshold lies from the see_through of maps that must not fail (and
    of those within ``FAIR_M`` it does not fail) and from that of maps that must fail and fail by no other
    check, as the smaller of the two ratios."""
    from carto_cli.mapping.quality import SEE_THROUGH_FAILED

    violations, fair, good, bad = 0, 0, [0.5], [50.0]
    for _, need, g in rows:
        value = g["see_through"][key]
        failed = max(_level(value), g["others"]) == 2
        violations += (need == "failed" and not failed) + (need == "not failed" and failed)
        fair += need == "rather not failed" and failed
        if need == "not failed" or (need == "rather not failed" and not failed):
            good.append(value)
        elif need == "failed" and g["others"] < 2:
            bad.append(value)
    return violations, fair, min(SEE_THROUGH_FAILED / max(good), min(bad) / SEE_THROUGH_FAILED)


def choose(rows: list[tuple]) -> str:
    """The GRID pair with the fewest violations on ``rows``, then the fewest maps within ``FAIR_M`` failed,
    then the widest margin."""
    keys = [f"{share}/{radius}" for share, radius in GRID]
    return max(keys, key=lambda k: (-_score(rows, k)[0], -_score(rows, k)[1], _score(rows, k)[2]))


def leave_one_building_out(runs: list[Run], cache: Path, regrid: bool) -> None:
    """Print every cached run's see_through per ``GRID`` pair, then per building: the pair ``choose`` picks on
    the other buildings' runs and how the held-out building's runs fare with it, then the pair on all runs and
    every pair's score. Runs not mapped yet are left out (this never maps)."""
    rows = []
    for run in runs:
        if not (cache / f"{_slug(run.base or run.name)}.pkl").exists():
            print(f"{run.name:44s} not mapped yet: left out")
            continue
        m = map_run(run, cache, False)
        rows.append((run, requirement(run, m), grid_values(run, m, cache, regrid)))
        print(f"{run.name:44s} {m['error']:7.3f} {m['odometry_error']:6.2f} {rows[-1][1]!s:10s} "
              + " ".join(f"{v:5.1f}" for v in rows[-1][2]["see_through"].values()) + f"  others {rows[-1][2]['others']}",
              flush=True)
    print("\nheld out        chosen (share/radius)  on the others: violations, fair, margin   held out: violations, "
          "fair, of runs")
    for b in sorted({building(r) for r, _, _ in rows}):
        train = [row for row in rows if building(row[0]) != b]
        test = [row for row in rows if building(row[0]) == b]
        key = choose(train)
        v, fair, margin = _score(train, key)
        tv, tfair, _ = _score(test, key)
        print(f"{b:16s} {key:22s} {v}, {fair}, {margin:.2f}                      {tv}, {tfair} of {len(test)}")
    key = choose(rows)
    print(f"{'(all)':16s} {key:22s} " + ", ".join(f"{x:.3g}" for x in _score(rows, key)))
    for k in (f"{share}/{radius}" for share, radius in GRID):
        print(f"  {k:10s} violations {_score(rows, k)[0]}, within {FAIR_M:g} m failed {_score(rows, k)[1]}, "
              f"margin {_score(rows, k)[2]:.2f}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", type=Path, default=Path(tempfile.gettempdir()) / "carto-quality-cal")
    ap.add_argument("--only", default="", help="comma-separated run names")
    ap.add_argument("--remap", action="store_true", help="map again even when cached")
    ap.add_argument("--markdown", action="store_true")
    ap.add_argument("--loo", action="store_true", help="choose the see-through constants leaving one building out "
                    "at a time, over the cached runs (--only: those)")
    ap.add_argument("--regrid", action="store_true", help="with --loo: measure again even when cached")
    args = ap.parse_args(argv)
    wanted = {w.strip() for w in args.only.split(",") if w.strip()}
    unknown = wanted - {r.name for r in RUNS}
    if unknown:
        ap.error(f"no run named {', '.join(sorted(unknown))}")
    runs = [r for r in RUNS if not wanted or r.name in wanted]
    if args.loo:
        leave_one_building_out(runs, args.cache, args.regrid)
        return 0
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
