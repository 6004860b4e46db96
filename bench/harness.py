"""The SLAM benchmark harness behind ``bench/run``.

Runs every benchmark case in a fresh subprocess of its own (one at a time), so
that each case's peak memory (``ru_maxrss`` of that process, from ``wait4``) and
numba start-up are measured on their own, then writes ``docs/benchmarks.md``.

Cases (``--list`` prints them):

* ``bench/<case>``: every directory of ``$DATA/bench`` — sparse real key scans of
  the Radish logs with drifting odometry; named by the directory (``intel``).
* ``bench-dense/<case>``: every directory of ``$DATA/bench-dense`` — dense 10 Hz
  scans simulated in the same buildings; named ``dense-<case>``.
* ``ccny``: the real CCNY bag (``data/ccny_laser_scan_matcher_demo.bag``), no
  reference: speed and loop closures only.
* ``sim-loop``: ``carto_cli.sim``'s loop building driven for 10 minutes (several
  laps) at 10 Hz; relations are built here from the exact ground truth.

Per case: relation error (mean ± std, translational m and rotational deg), ATE
where there is ground truth, the odometry's own relation error on the same
relations, wall time split into local SLAM / constraint search / optimization
from the StageTimer, scans/s, loop closures and the share of them that agree
with the reference, peak memory. What exactly is computed is written into the
generated document (``METHOD`` below). ``--algorithm gmapping`` maps every case with the
particle filter instead (``carto_cli.gmapping``); the document then says so in its header and
adds the filter's own figures (particles, resamplings, processed scans, time, memory).

    bench/run [--cases intel,aces,dense,...] [--quick] [--set k=v ...] [--profile NAME] [--algorithm NAME]
              [--peers lama]

``--peers lama`` also runs IRIS LaMa's Slam2D and PF-SLAM on every CARMEN case, each right after carto's
case and in a process of its own (built once by ``bench/lama.sh``), scores their trajectories with carto's
relation error and adds a table of error, CPU time and peak RSS side by side.

A case that fails (an exception, a crash, the per-case timeout) shows as
"failed: <reason>" and the others go on. Raw results (one JSON per case, the
stage trees, maps and trajectories) go to ``--results`` (default a fresh
directory under ``$TMPDIR/carto-bench``). The cases run a copy of ``carto_cli``
taken when the run starts (``--no-snapshot``: the working tree), so that a long
run in a tree others edit measures one version of the code; the document names
the commit, whether the tree was dirty and a fingerprint of the sources.
"""
from __future__ import annotations

import argparse
import collections
import datetime as _dt
import hashlib
import json
import math
import os
import platform
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("CARTO_BENCH_DATA", "/work/shared/data"))
CCNY_BAG = REPO / "data" / "ccny_laser_scan_matcher_demo.bag"
DEFAULT_DOC = REPO / "docs" / "benchmarks.md"

QUICK_SCANS = 1500          # --quick: the first scans of every case (intel, aces and ccny have fewer: in full)
SIM_DURATION = 600.0        # s of the simulated loop-building recording
SIM_SEED = 0
LC_TOLERANCE_M = 0.2        # a loop closure is correct within these of the reference
LC_TOLERANCE_DEG = 1.0
DEFAULT_TIMEOUT = 6 * 3600  # s per case

FAMILIES = {
    "bench": "bench/ — sparse real key scans (Radish logs), drifting odometry",
    "bench-dense": "bench-dense/ — dense 10 Hz scans simulated in the same buildings",
    "sim": "Simulated loop building (carto_cli.sim), exact ground truth",
    "ccny": "Real ROS bag without reference (CCNY Hokuyo demo)",
}
def profile_for(case: Case, profile: str | None) -> str | None:
    """The --profile a case's worker gets: 'auto' (what `carto map` does with no profile) is passed on."""
    if profile in (None, "auto"):
        return "auto"
    return None if profile == "default" else profile


FAMILY_ALIASES = {"bench": "bench", "sparse": "bench", "bench-dense": "bench-dense", "dense": "bench-dense",
                  "sim": "sim", "ccny": "ccny", "real": "ccny"}


# --------------------------------------------------------------------------- cases


@dataclass(frozen=True)
class Case:
    name: str                     # what --cases takes
    family: str                   # key of FAMILIES
    building: str                 # row label in the family's table
    path: str | None              # recording (None: simulated)
    relations: str | None = None
    groundtruth: str | None = None
    quick_scans: int | None = None  # scans in --quick mode (None: all)


def discover_cases() -> list[Case]:
    cases: list[Case] = []
    for family, prefix in (("bench", ""), ("bench-dense", "dense-")):
        root = DATA / family
        if not root.is_dir():
            continue
        order = {"intel": 0, "aces": 1, "freiburg-079": 2}  # PEERS.md's order, then the rest by name
        for d in sorted((p for p in root.iterdir() if p.is_dir()), key=lambda p: (order.get(p.name, 9), p.name)):
            rel, gt = d / "relations.txt", d / "groundtruth.txt"
            cases.append(Case(prefix + d.name, family, d.name, str(d / "scans.clf.gz"),
                              str(rel) if rel.is_file() else None, str(gt) if gt.is_file() else None,
                              QUICK_SCANS))
    cases.append(Case("ccny", "ccny", "ccny demo bag", str(CCNY_BAG), quick_scans=QUICK_SCANS))
    cases.append(Case("sim-loop", "sim", f"loop building, {SIM_DURATION / 60:g} min", None, quick_scans=QUICK_SCANS))
    return cases


def select_cases(spec: str | None, cases: list[Case]) -> list[Case]:
    """``--cases``: names (intel, dense-intel), bench/intel, bench-dense/intel, family names, 'all'."""
    if not spec or spec.strip() == "all":
        return cases
    by_name = {c.name: c for c in cases}
    chosen: list[Case] = []
    for token in (t.strip() for t in spec.split(",")):
        if not token:
            continue
        if token == "all":
            found = cases
        elif token in FAMILY_ALIASES:
            found = [c for c in cases if c.family == FAMILY_ALIASES[token]]
        elif token in by_name:
            found = [by_name[token]]
        elif "/" in token:
            fam, _, building = token.partition("/")
            fam = FAMILY_ALIASES.get(fam, fam)
            found = [c for c in cases if c.family == fam and c.building == building]
        else:
            found = []
        if not found:
            raise SystemExit(f"bench/run: unknown case '{token}' (cases: {', '.join(by_name)}; "
                             f"families: {', '.join(FAMILY_ALIASES)}; or 'all')")
        chosen += [c for c in found if c not in chosen]
    return chosen


# --------------------------------------------------------------------------- worker (one case, own process)


def _progress(case: Case, total: int | None):
    state = {"n": 0, "t0": time.perf_counter(), "last": time.perf_counter()}

    def on_scan(k: int) -> None:
        state["n"] += k
        now = time.perf_counter()
        if now - state["last"] >= 30.0:
            state["last"] = now
            of = f"/{total}" if total else ""
            print(f"[{case.name}] {state['n']}{of} scans, {now - state['t0']:.0f} s", file=sys.stderr, flush=True)

    return on_scan


def simulation_case(duration: float = SIM_DURATION, seed: int = SIM_SEED):
    from carto_cli.sim import loop_building, loop_trajectory, simulate

    world = loop_building()
    one_lap = loop_trajectory(world, laps=1).duration
    laps = int(math.ceil(duration / one_lap))
    trajectory = loop_trajectory(world, laps=laps)
    sim = simulate(world, trajectory, duration=duration, seed=seed)
    return sim, laps, one_lap


def relations_from_groundtruth(gt, *, step: int = 10, revisit_every: int = 5, min_dt: float = 30.0,
                               max_dist: float = 3.0, max_angle_deg: float = 60.0, max_revisits: int = 3000,
                               seed: int = 0):
    """Relations in the recipe of bench-dense/README: (i, i+step) every step-th pose, plus revisits.

    Revisits: poses subsampled every ``revisit_every`` (2 Hz at 10 Hz), every pair at least
    ``min_dt`` apart whose poses are within ``max_dist`` and ``max_angle_deg``; a seeded
    random ``max_revisits`` of them when there are more.
    """
    import numpy as np

    from carto_cli.core import transform
    from carto_cli.evaluation.metrics import Relations

    t, xy, th = gt.t, gt.xy, gt.theta

    def rel(i, j):
        d = xy[j] - xy[i]
        c, s = np.cos(th[i]), np.sin(th[i])
        dth = transform.wrap_angle(th[j] - th[i])
        return np.column_stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], dth])

    i1 = np.arange(0, len(t) - step, step)
    j1 = i1 + step
    sub = np.arange(0, len(t), revisit_every)
    a, b = np.triu_indices(len(sub), k=1)
    a, b = sub[a], sub[b]
    dyaw = np.abs(transform.wrap_angle(th[b] - th[a]))
    ok = (t[b] - t[a] >= min_dt) & (np.hypot(*(xy[b] - xy[a]).T) <= max_dist) & (dyaw <= math.radians(max_angle_deg))
    a, b = a[ok], b[ok]
    candidates = len(a)
    if len(a) > max_revisits:
        keep = np.sort(np.random.default_rng(seed).choice(len(a), max_revisits, replace=False))
        a, b = a[keep], b[keep]
    i = np.concatenate([i1, a])
    j = np.concatenate([j1, b])
    return Relations(t[i].copy(), t[j].copy(), rel(i, j)), {"consecutive": int(len(i1)), "revisits": int(len(a)),
                                                             "revisit_candidates": int(candidates)}


def _pose_errors(a, b):
    """Translational (m) and rotational (deg) differences of (n, 3) relative poses."""
    import numpy as np

    from carto_cli.core import transform

    return (np.hypot(a[:, 0] - b[:, 0], a[:, 1] - b[:, 1]),
            np.degrees(np.abs(transform.wrap_angle(a[:, 2] - b[:, 2]))))


def loop_closure_check(graph, reference) -> dict:
    """Compare every loop closure with the reference (see METHOD in the document).

    anchor: node i relative to the first node of submap j (the node whose scan started it);
    nearest: node i relative to the node of submap j nearest to it in the reference, which
    leaves out local SLAM's drift inside the submap between its first node and the place
    where the scan matched. Also the submaps' own drift: each submap's nodes relative to its
    first node, local SLAM against the reference.
    """
    import numpy as np

    from carto_cli.core import transform
    from carto_cli.evaluation.metrics import interpolate_poses

    cs = graph.constraints
    mask = np.asarray(cs.is_loop_closure, dtype=bool)
    nodes = np.asarray(cs.node)[mask]
    subs = np.asarray(cs.submap)[mask]
    out: dict = {"total": int(mask.sum()), "correct": None, "checked": 0}
    if reference is None:
        return out
    local = np.asarray(graph.local_poses)
    node_times = np.asarray(graph.node_times, dtype=np.float64)
    xy, th, valid = interpolate_poses(reference, node_times)
    ref = np.column_stack([xy, th])                                 # reference pose of every node
    members = [np.asarray(e.nodes, dtype=np.int64) for e in graph.submaps]

    # Local SLAM's drift inside each submap, relative to its first node.
    drift_m, drift_deg = [], []
    for ns in members:
        ns = ns[valid[ns]]
        if len(ns) < 2:
            continue
        et, er = _pose_errors(transform.relative(local[ns[0]], local[ns]), transform.relative(ref[ns[0]], ref[ns]))
        drift_m.append(float(et.max()))
        drift_deg.append(float(er.max()))
    if drift_m:
        out.update(submap_drift_median_m=float(np.median(drift_m)), submap_drift_median_deg=float(np.median(drift_deg)),
                   submap_drift_max_m=float(np.max(drift_m)), submap_drift_max_deg=float(np.max(drift_deg)))
    if out["total"] == 0:
        return out

    rel = np.asarray(cs.relative)[mask]
    implied_node = transform.compose(np.array([graph.submaps[j].local_pose for j in subs]), rel)  # local frame
    first = np.array([members[j][0] for j in subs], dtype=np.int64)
    nearest = np.empty_like(first)
    for k, (i, j) in enumerate(zip(nodes, subs)):
        ns = members[j][valid[members[j]]]
        nearest[k] = ns[np.argmin(np.hypot(*(ref[ns, :2] - ref[i, :2]).T))] if len(ns) else members[j][0]
    ok = valid[nodes] & valid[first] & valid[nearest]
    out["checked"] = int(ok.sum())
    if not ok.any():
        return out
    for label, anchor in (("anchor", first), ("nearest", nearest)):
        et, er = _pose_errors(transform.relative(local[anchor], implied_node), transform.relative(ref[anchor], ref[nodes]))
        et, er = et[ok], er[ok]
        good = (et <= LC_TOLERANCE_M) & (er <= LC_TOLERANCE_DEG)
        out[f"{label}_correct"] = int(good.sum())
        out[f"{label}_share"] = float(good.mean())
        out[f"{label}_median_m"] = float(np.median(et))
        out[f"{label}_median_deg"] = float(np.median(er))
        out[f"{label}_p90_m"] = float(np.percentile(et, 90))
        out[f"{label}_p90_deg"] = float(np.percentile(er, 90))
        out[f"{label}_over_1m"] = int((et > 1.0).sum())
    out["correct"] = out["anchor_correct"]
    out["share_correct"] = out["anchor_share"]
    return out


def _relation_dict(r) -> dict:
    return {"trans_mean": r.translation.mean, "trans_std": r.translation.std, "rot_mean": r.rotation.mean,
            "rot_std": r.rotation.std, "used": r.used, "skipped": r.skipped,
            "trans_max": r.translation.max, "trans_median": r.translation.median}


def _odometry_trajectory(recording, topic):
    import numpy as np

    from carto_cli.core.records import Odometry
    from carto_cli.io.trajectory import Trajectory

    rows = [(r.time, r.x, r.y, r.yaw) for r in recording.records([topic]) if isinstance(r, Odometry)]
    if len(rows) < 2:
        return None
    a = np.array(rows, dtype=np.float64)
    keep = np.concatenate([[True], np.diff(a[:, 0]) > 0])  # strictly increasing times
    a = a[keep]
    return Trajectory.from_arrays(a[:, 0], a[:, 1], a[:, 2], a[:, 3])


# Stage names of the StageTimer tree (carto_cli.core.timing). They are found by name wherever they sit, so
# that moving a stage (e.g. the pose graph's work into or out of the per-scan stage) keeps the split right.
JIT_STAGE, SCAN_STAGE, GLOBAL_STAGE = "jit warm-up", "scan", "global"
CONSTRAINT_STAGE, OPTIMIZATION_STAGE = "loop closure", "optimization"
SEARCH_THREADS_STAGE = "search threads"  # the searches' thread time with more than one job (a concurrent branch)
LOCAL_DETAIL = ("preprocess", "extrapolate", "match", "motion filter", "insert")
CONSTRAINT_DETAIL = ("candidate selection", "precomputation", "branch and bound", "refinement")
GMAPPING_DETAIL = ("motion model", "scan matching", "weighting", "resampling", "map update")  # under "scan"
GMAPPING_FINAL = ("refine",)  # once, after the last scan


def split_wall_time(snap) -> dict:
    """Seconds of build's wall time: JIT, local SLAM, constraint search, optimization, other.

    ``jit warm-up``, ``loop closure`` and ``optimization`` stages count wherever they are;
    local SLAM is the rest of the ``scan`` stage except what runs inside a ``global``
    stage there (the pose graph's bookkeeping, which goes to *other* with reading the
    recording and map assembly).
    """
    b = {"jit_warmup_s": 0, "local_slam_s": 0, "constraint_search_s": 0, "optimization_s": 0}
    special = {JIT_STAGE: "jit_warmup_s", CONSTRAINT_STAGE: "constraint_search_s",
               OPTIMIZATION_STAGE: "optimization_s"}

    def visit(node, in_scan: bool):
        key = special.get(node.name)
        if key is not None and node.path:
            b[key] += node.total_ns
            return
        if node.path and node.name == GLOBAL_STAGE:
            in_scan = False
        elif node.path == SCAN_STAGE:
            in_scan = True
        if in_scan:
            b["local_slam_s"] += node.self_ns
        for c in node.children:
            visit(c, in_scan)

    visit(snap.root, False)
    out = {k: v / 1e9 for k, v in b.items()}
    out["other_s"] = snap.wall_ns / 1e9 - sum(out.values())
    return out


def stage_detail(snap) -> dict:
    """Seconds in the sub-stages of local SLAM (children of ``scan``) and of the constraint search."""
    out = {f"local/{n}": 0.0 for n in LOCAL_DETAIL}
    out.update({f"constraint/{n}": 0.0 for n in CONSTRAINT_DETAIL})

    def visit(node, parent: str, under_constraint: bool):
        if parent == SCAN_STAGE and node.name in LOCAL_DETAIL:
            out[f"local/{node.name}"] += node.total_ns / 1e9
        if under_constraint and node.name in CONSTRAINT_DETAIL:
            out[f"constraint/{node.name}"] += node.total_ns / 1e9
            return
        for c in node.children:
            visit(c, node.path, under_constraint or node.name in (CONSTRAINT_STAGE, SEARCH_THREADS_STAGE))

    visit(snap.root, "", False)
    return out


def gmapping_detail(snap) -> dict:
    """Seconds in the particle filter's stages (children of ``scan``) and in the final refinement, for
    ``--algorithm gmapping``."""
    out = dict.fromkeys(GMAPPING_DETAIL + GMAPPING_FINAL, 0.0)

    def visit(node, parent: str):
        if (parent == SCAN_STAGE and node.name in GMAPPING_DETAIL) or (parent == "" and node.name in GMAPPING_FINAL):
            out[node.name] += node.total_ns / 1e9
        for c in node.children:
            visit(c, node.path)

    visit(snap.root, "")
    return out


def run_case(case: Case, quick: bool, profile: str | None, overrides: list[str], outdir: Path,
             algorithm: str | None = None) -> dict:
    """Build the map of one case with ``algorithm`` (None: auto's choice, Cartographer for a named profile)
    and measure it. Runs in the case's own process."""
    t_import = time.perf_counter()
    import numpy as np

    from carto_cli.core.timing import StageTimer, report_json, report_tree_text
    from carto_cli.evaluation.metrics import Relations, ate, read_relations, relation_error
    from carto_cli.io.map_image import render_png, write_png
    from carto_cli.io.sources.open import open_recording
    from carto_cli.io.trajectory import Trajectory, read_trajectory, write_trajectory
    from carto_cli.options import load_options
    from carto_cli.pipeline import Auto, MapRequest, execute, finished, planned, read_options

    import_s = time.perf_counter() - t_import
    import carto_cli

    package_dir = Path(carto_cli.__file__).resolve().parent
    spec = Auto(tuple(overrides)) if profile == "auto" else load_options(profile, overrides)
    max_scans = case.quick_scans if quick else None
    info: dict = {"import_s": import_s, "package": str(package_dir), "fingerprint": source_fingerprint(package_dir)}

    t0 = time.perf_counter()
    sim = None
    if case.family == "sim":
        sim, laps, lap_s = simulation_case()
        recording = sim.recording()
        info.update(sim_laps=laps, sim_lap_s=lap_s, sim_duration_s=SIM_DURATION, sim_seed=SIM_SEED)
    else:
        recording = open_recording(case.path, read_options(spec))
    info["setup_s"] = time.perf_counter() - t0

    # Read as `carto map` reads (io.read_ahead): decoded beside mapping, the survey's look replayed.
    t_survey = time.perf_counter()
    with recording as rec, planned(request := MapRequest(rec, spec, algorithm, max_scans=max_scans)) as plan:
        info["survey_s"] = time.perf_counter() - t_survey  # with loading the kernels
        selection = plan.selection
        timer = StageTimer()
        # The map's last steps too (turned square, cleaned), as `carto map` pays for them
        result = finished(execute(plan, timer=timer, on_scan=_progress(case, plan.scan_count)), request, timer)
        algorithm = result.configured.algorithm
        if result.auto is not None and result.regime is not None:
            info["auto"] = {"regime": result.regime.to_dict(), "describe": result.regime.describe(),
                            "profile": result.auto.profile, "settings": result.auto.settings,
                            "algorithm": result.auto.algorithm, "note": result.auto.note}
        timer.stop()
        t_eval = time.perf_counter()
        odometry = None
        if sim is not None:
            odometry = Trajectory.from_arrays(sim.odometry[:, 0], sim.odometry[:, 1], sim.odometry[:, 2],
                                              sim.odometry[:, 3])
        elif selection.odometry:
            odometry = _odometry_trajectory(rec, selection.odometry)

    snap = timer.snapshot()
    wall = snap.wall_ns / 1e9
    stages = split_wall_time(snap)
    detail = stage_detail(snap)
    if algorithm == "gmapping":
        info["gmapping_detail"] = gmapping_detail(snap)

    # ---- accuracy
    traj = Trajectory.from_poses(result.times, result.poses)
    reference = None
    relations = None
    rel_info = None
    if sim is not None:
        gt = sim.ground_truth
        reference = Trajectory.from_arrays(gt[:, 0], gt[:, 1], gt[:, 2], gt[:, 3])
        relations, rel_info = relations_from_groundtruth(reference)
    else:
        if case.groundtruth:
            reference = read_trajectory(case.groundtruth)
        if case.relations:
            relations = read_relations(case.relations)
    accuracy: dict = {}
    if relations is not None:
        r = relation_error(traj, relations)
        accuracy["relations"] = _relation_dict(r)
        if rel_info:
            accuracy["relations_built"] = rel_info
        if odometry is not None:
            m = r.used_mask
            sub = Relations(relations.t1[m], relations.t2[m], relations.d[m])
            try:
                accuracy["odometry_relations"] = _relation_dict(relation_error(odometry, sub))
            except Exception as e:  # the odometry is a baseline, never a reason to fail the case
                accuracy["odometry_relations_error"] = str(e)
    if reference is not None:
        a = ate(traj, reference, associate="trajectory")
        accuracy["ate"] = {"trans_mean": a.translation.mean, "trans_rmse": a.translation.rmse,
                           "rot_mean": a.rotation.mean, "used": a.used}
    lc = loop_closure_check(result.graph, reference)
    eval_s = time.perf_counter() - t_eval

    # ---- artefacts for eyeballing (outside every timed figure)
    outdir.mkdir(parents=True, exist_ok=True)
    try:
        write_png(outdir / f"{case.name}.png", render_png(result.image, result.poses, result.loop_closures))
        write_trajectory(outdir / f"{case.name}.tum", traj, fmt="tum")
        (outdir / f"{case.name}.timing.txt").write_text(report_tree_text(snap))
        (outdir / f"{case.name}.timing.json").write_text(json.dumps(report_json(snap), indent=1))
    except Exception as e:  # artefacts are a convenience
        print(f"[{case.name}] could not write artefacts: {e}", file=sys.stderr)

    bstats = result.graph.builder.stats if result.graph is not None else None
    stats = {k: (float(v) if isinstance(v, (np.floating,)) else v) for k, v in result.stats.items()}
    import resource

    return {
        "status": "ok",
        "case": asdict(case),
        "algorithm": algorithm,
        "quick": quick,
        "max_scans": max_scans,
        "selection": {"scan": selection.scan, "odometry": selection.odometry, "imu": selection.imu},
        "laser_pose_source": result.laser_pose_source,
        "stats": stats,
        "build_wall_s": wall,
        "scans_per_s": stats["scans"] / wall if wall > 0 else None,
        "stages": stages,
        "stage_detail": detail,
        "constraint_builder": asdict(bstats) if bstats is not None else None,
        "accuracy": accuracy,
        "loop_closures": lc,
        "quality": result.quality.to_dict() if getattr(result, "quality", None) is not None else None,
        "eval_s": eval_s,
        "self_maxrss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
        **info,
    }


def worker_main(args) -> int:
    cases = {c.name: c for c in discover_cases()}
    case = cases[args.worker]
    out = Path(args.out)
    try:
        res = run_case(case, args.quick, profile_for(case, args.profile), args.set or [], out.parent,
                       algorithm=args.algorithm)
        code = 0
    except BaseException as e:  # report every failure, KeyboardInterrupt included
        traceback.print_exc()
        msg = str(e).strip().splitlines()[0] if str(e).strip() else ""
        res = {"status": "failed", "case": asdict(case), "algorithm": args.algorithm or "auto",
               "error": f"{type(e).__name__}: {msg}"[:300]}
        code = 1
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(res, indent=1, default=_json_default))
    os.replace(tmp, out)
    return code


def _json_default(v):
    try:
        import numpy as np

        if isinstance(v, np.generic):
            return v.item()
        if isinstance(v, np.ndarray):
            return v.tolist()
    except ImportError:
        pass
    if isinstance(v, Path):
        return str(v)
    return repr(v)


# --------------------------------------------------------------------------- source snapshot


def source_fingerprint(package_dir: Path) -> str:
    """A short hash of the package's sources (.py and .yaml), to tell which code a case ran."""
    h = hashlib.sha1()
    for f in sorted(package_dir.rglob("*")):
        if f.suffix in (".py", ".yaml") and "__pycache__" not in f.parts:
            h.update(str(f.relative_to(package_dir)).encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:12]


def snapshot_package(dest: Path) -> Path:
    """Copy carto_cli (with numba's on-disk cache, mtimes kept so it stays valid) to ``dest``.

    Workers put ``dest`` first on PYTHONPATH: a run of several hours in a tree that other
    people edit then measures one version of the code throughout.
    """
    target = dest / "carto_cli"
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(REPO / "carto_cli", target, copy_function=shutil.copy2,
                    ignore=shutil.ignore_patterns("*.tmp", "*.swp"))
    return dest


# --------------------------------------------------------------------------- driver


def run_in_subprocess(case: Case, args, results: Path) -> dict:
    out = results / f"{case.name}.json"
    out.unlink(missing_ok=True)
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", case.name, "--out", str(out)]
    if args.quick:
        cmd.append("--quick")
    cmd += ["--profile", profile_for(case, args.profile) or "default"]
    if args.algorithm:
        cmd += ["--algorithm", args.algorithm]
    for s in args.set or []:
        cmd += ["--set", s]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    if args.snapshot_dir:
        env["PYTHONPATH"] = os.pathsep.join(p for p in (args.snapshot_dir, os.environ.get("PYTHONPATH")) if p)
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, cwd=str(REPO),
                            text=True, errors="replace")
    tail: collections.deque[str] = collections.deque(maxlen=20)
    log = open(results / f"{case.name}.log", "w")

    def pump():
        for line in proc.stderr:
            tail.append(line.rstrip())
            log.write(line)
            log.flush()
            sys.stderr.write(line)
            sys.stderr.flush()

    reader = threading.Thread(target=pump, daemon=True)
    reader.start()
    timed_out = threading.Event()

    def kill():
        timed_out.set()
        try:
            os.kill(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass

    killer = threading.Timer(args.timeout, kill) if args.timeout and args.timeout > 0 else None
    if killer:
        killer.start()
    try:
        _, status, usage = os.wait4(proc.pid, 0)  # this child's own rusage: its peak RSS
    except KeyboardInterrupt:
        os.kill(proc.pid, signal.SIGKILL)
        os.wait4(proc.pid, 0)
        raise
    finally:
        if killer:
            killer.cancel()
    proc.returncode = os.waitstatus_to_exitcode(status)
    wall = time.perf_counter() - t0
    reader.join(timeout=5)
    log.close()

    res = None
    if out.is_file():
        try:
            res = json.loads(out.read_text())
        except ValueError:
            res = None
    if res is None:
        if timed_out.is_set():
            reason = f"timeout after {args.timeout:g} s"
        elif proc.returncode < 0:
            sig = -proc.returncode
            name = signal.Signals(sig).name if sig in signal.Signals._value2member_map_ else str(sig)
            reason = f"killed by {name}" + (" (out of memory?)" if sig == signal.SIGKILL else "")
        else:
            last = next((l for l in reversed(tail) if l.strip()), "")
            reason = f"exit status {proc.returncode}" + (f": {last[:200]}" if last else "")
        res = {"status": "failed", "case": asdict(case), "algorithm": args.algorithm or "auto", "error": reason}
    res["process_wall_s"] = wall
    # wait4 reports the child with its reaped children (RUSAGE_BOTH): the pose graph's process and every thread count
    res["cpu_s"] = usage.ru_utime + usage.ru_stime
    # wait4's maxrss is the larger of the worker's and its pose graph process's (which counts the pages they share):
    # with a graph process, the worker's own peak or both together while the graph's ran (mapping.slam)
    res["peak_rss_mb"] = usage.ru_maxrss / 1024.0
    together = (res.get("stats") or {}).get("graph_process_peak_memory_mb", 0.0)
    if together and res.get("self_maxrss_kb"):
        res["peak_rss_mb"] = max(res["self_maxrss_kb"] / 1024.0, together)
    res["returncode"] = proc.returncode
    out.write_text(json.dumps(res, indent=1, default=_json_default))
    return res


# --------------------------------------------------------------------------- peer systems run beside carto


LAMA_SCRIPT = REPO / "bench" / "lama.sh"
# (key, label, driver arguments, trajectory file): iris_lama_ros's defaults; PF-SLAM's seed fixed because its
# error changes up to 2x between seeds (../shared/peers/lama/README.md), its threads as measured in PEERS.md.
LAMA_RUNS = (("lama-slam2d", "LaMa Slam2D", ("slam2d",), ".scans.txt"),
             ("lama-pf", "LaMa PF-SLAM", ("pf", "threads=2", "seed=1"), ".final_scans.txt"))
PEER_SYSTEMS = {"lama": LAMA_RUNS}
LASER_LINES = ("FLASER", "ROBOTLASER1")  # what the driver maps: one scan each


def build_lama(log: Path) -> dict:
    """``{"driver", "source"}`` from ``bench/lama.sh`` (a cached build after the first), or ``{"error"}``."""
    with open(log, "w") as err:
        p = subprocess.run(["bash", str(LAMA_SCRIPT)], stdout=subprocess.PIPE, stderr=err, text=True,
                           cwd=str(REPO))
    driver = p.stdout.strip().splitlines()[-1] if p.stdout.strip() else ""
    if p.returncode != 0 or not os.access(driver, os.X_OK):
        lines = [l.strip() for l in Path(log).read_text(errors="replace").splitlines() if l.strip()]
        return {"error": f"bench/lama.sh failed ({lines[-1][:200] if lines else f'exit status {p.returncode}'})"}
    source = Path(driver).with_name("source.txt")
    return {"driver": driver, "source": source.read_text().strip() if source.is_file() else "iris_lama"}


def first_scans(log: str, n: int, dest: Path) -> Path:
    """The CARMEN log cut after its ``n``-th scan, so that with --quick a peer maps the scans carto mapped."""
    import gzip

    with gzip.open(log, "rt", errors="replace") as f:
        lines = f.readlines()
    laser = [i for i, l in enumerate(lines) if l.startswith(LASER_LINES)]
    end = laser[n - 1] + 1 if len(laser) > n else len(lines)
    with gzip.open(dest, "wt") as f:
        f.writelines(lines[:end])
    return dest


def score_peer_trajectory(path: Path, case: Case) -> dict:
    """The accuracy figures run_case computes for carto, on a peer's ``t x y theta`` file."""
    import numpy as np

    from carto_cli.evaluation.metrics import ate, read_relations, relation_error
    from carto_cli.io.trajectory import Trajectory, parse_table, read_trajectory

    data, _ = parse_table(path, (4,), "trajectory")
    # A log's repeated timestamps give repeated poses: keep the first, as for carto's odometry baseline.
    t = data[:, 0]
    keep = np.concatenate([[True], t[1:] > np.maximum.accumulate(t)[:-1]])
    data = data[keep]
    traj = Trajectory.from_arrays(data[:, 0], data[:, 1], data[:, 2], data[:, 3])
    acc: dict = {"poses": len(traj), "dropped_poses": int((~keep).sum())}
    if case.relations:
        acc["relations"] = _relation_dict(relation_error(traj, read_relations(case.relations)))
    if case.groundtruth:
        a = ate(traj, read_trajectory(case.groundtruth), associate="trajectory")
        acc["ate"] = {"trans_mean": a.translation.mean, "trans_rmse": a.translation.rmse,
                      "rot_mean": a.rotation.mean, "used": a.used}
    return acc


# ru_maxrss also counts the memory a process had before its exec, and a child of this harness starts as a copy of
# it (100+ MB with numpy and carto_cli loaded), more than LaMa's whole peak: the peer is started from a bare
# interpreter (5 MB) instead, which writes the peer's own wait4 figures: exit code, user s, sys s, peak RSS KB.
RUSAGE_LAUNCHER = """\
import os, sys
pid = os.fork()
if pid == 0:
    try:
        os.execv(sys.argv[2], sys.argv[2:])
    finally:
        os._exit(127)
_, status, ru = os.wait4(pid, 0)
with open(sys.argv[1], "w") as f:
    f.write(f"{os.waitstatus_to_exitcode(status)} {ru.ru_utime} {ru.ru_stime} {ru.ru_maxrss}")
"""


def run_peer(case: Case, run: tuple, driver: str, log: str, results: Path, timeout: float | None) -> dict:
    """One peer run in its own process (CPU and peak RSS from its ``os.wait4``, as for carto), then its trajectory
    scored as carto's is."""
    key, label, argv, suffix = run
    prefix = results / f"{case.name}.{key}"
    traj, usage = Path(f"{prefix}{suffix}"), Path(f"{prefix}.rusage")
    for stale in (traj, usage):  # an earlier run's files must not be read as this one's
        stale.unlink(missing_ok=True)
    cmd = [driver, argv[0], log, str(prefix), *argv[1:]]
    res: dict = {"peer": key, "label": label, "command": shlex.join(cmd), "status": "ok"}
    t0 = time.perf_counter()
    with open(f"{prefix}.log", "w") as out:
        proc = subprocess.Popen([sys.executable, "-I", "-S", "-c", RUSAGE_LAUNCHER, str(usage), *cmd], stdout=out,
                                stderr=subprocess.STDOUT, cwd=str(results), start_new_session=True)
    try:
        proc.wait(timeout=timeout if timeout and timeout > 0 else None)
    except BaseException as e:  # the timeout, or an interrupt: the peer goes too
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        if not isinstance(e, subprocess.TimeoutExpired):
            raise
        return {**res, "status": "failed", "error": f"timeout after {timeout:g} s"}
    res["process_wall_s"] = time.perf_counter() - t0
    try:
        code, user, system, maxrss = usage.read_text().split()
    except (OSError, ValueError):
        return {**res, "status": "failed", "error": f"no figures from the launcher (exit status {proc.returncode})"}
    res.update(returncode=int(code), cpu_s=float(user) + float(system), peak_rss_mb=int(maxrss) / 1024.0)
    if res["returncode"] != 0:
        lines = [l.strip() for l in Path(f"{prefix}.log").read_text(errors="replace").splitlines() if l.strip()]
        return {**res, "status": "failed",
                "error": f"exit status {res['returncode']}" + (f": {lines[-1][:200]}" if lines else "")}
    try:
        res["accuracy"] = score_peer_trajectory(traj, case)
    except Exception as e:  # a peer's bad output is that peer's failure, not the run's
        return {**res, "status": "failed", "error": f"{type(e).__name__}: {str(e).strip()[:200]}"}
    return res


def run_peers(case: Case, builds: dict, args, results: Path) -> dict:
    """Every built peer system's runs on ``case``, keyed by run (``lama-slam2d``, ...)."""
    out: dict = {}
    for system, runs in PEER_SYSTEMS.items():
        build = builds.get(system)
        if build is None:
            continue
        if build.get("error"):
            out.update({key: {"status": "skipped", "error": "not built"} for key, *_ in runs})
            continue
        if not (case.path or "").endswith((".clf", ".clf.gz")):
            out.update({key: {"status": "skipped", "error": "its driver reads CARMEN logs only"} for key, *_ in runs})
            continue
        log = case.path
        if args.quick and case.quick_scans:
            log = str(first_scans(case.path, case.quick_scans, results / f"{case.name}.first-scans.clf.gz"))
        for run in runs:
            print(f"== {case.name}: {run[1]}", file=sys.stderr, flush=True)
            out[run[0]] = r = run_peer(case, run, build["driver"], log, results, args.timeout)
            rel = ((r.get("accuracy") or {}).get("relations") or {})
            what = f"relation error {_rel_cell(rel)}, " if rel else ""
            print(f"== {case.name}: {run[1]}: " + (f"{what}CPU {r['cpu_s']:.1f} s, {r['peak_rss_mb']:.0f} MB"
                                                   if r["status"] == "ok" else _failed(r)), file=sys.stderr, flush=True)
    return out


# --------------------------------------------------------------------------- environment


def _run(cmd: list[str]) -> str:
    try:
        return subprocess.run(cmd, cwd=str(REPO), capture_output=True, text=True, timeout=30).stdout.strip()
    except Exception:
        return ""


def environment() -> dict:
    from carto_cli.evaluation.profiling import cpu_model

    cpu = cpu_model()
    mem_gb = None
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemTotal:"):
                mem_gb = int(line.split()[1]) / 1024 / 1024
    except OSError:
        pass
    versions = {"python": platform.python_version()}
    for mod in ("numpy", "numba", "scipy", "cv2"):
        try:
            versions[mod] = __import__(mod).__version__
        except Exception:
            versions[mod] = "not installed"
    status = _run(["git", "status", "--porcelain"]).splitlines()
    modified = [l for l in status if not l.startswith("??")]
    untracked = [l for l in status if l.startswith("??")]
    return {
        "cpu": cpu or platform.processor() or "unknown",
        "cores": os.cpu_count(),
        "memory_gb": mem_gb,
        "kernel": platform.release(),
        "loadavg_start": os.getloadavg(),
        "versions": versions,
        "commit": _run(["git", "rev-parse", "--short", "HEAD"]) or "unknown",
        "dirty": bool(status),
        "modified": [l[3:] for l in modified],
        "untracked": [l[3:] for l in untracked],
    }


# --------------------------------------------------------------------------- peers


def parse_peers(path: Path) -> dict:
    """{family: {case: {odometry, cartographer, best}}} from PEERS.md; empty when unreadable."""
    try:
        text = path.read_text()
    except OSError:
        return {}
    out: dict = {}
    sections = re.split(r"^## ", text, flags=re.M)[1:]
    for sec in sections:
        head, _, body = sec.partition("\n")
        family = head.split()[0].rstrip("/") if head.split() else ""
        rows = [l for l in body.splitlines() if l.strip().startswith("|")]
        if len(rows) < 3:
            continue
        cells = lambda l: [c.strip().replace("**", "") for c in l.strip().strip("|").split("|")]  # noqa: E731
        header = cells(rows[0])
        fam: dict = {}
        for l in rows[2:]:
            c = cells(l)
            if not c or not c[0]:
                continue
            entry = {"odometry": None, "cartographer": None, "best": None}
            best_val, best_txt = math.inf, None
            for h, v in zip(header[1:], c[1:]):
                hl = h.lower()
                if hl.startswith("odometry"):
                    entry["odometry"] = v
                    continue
                if hl.startswith("cartographer") and entry["cartographer"] is None:
                    entry["cartographer"] = v
                m = re.match(r"\s*(\d+(?:\.\d+)?)(?: ± \d+(?:\.\d+)?)? m\b", v)  # "0.047 m" or "0.047 ± 0.045 m"
                if m and float(m.group(1)) < best_val:
                    best_val, best_txt = float(m.group(1)), f"{m.group(1)} m ({h.split(' (')[0]})"
            entry["best"] = best_txt
            fam[c[0]] = entry
        best_line = re.search(r"Best figure per case[^:]*:(.*)", body)
        if best_line:
            # "intel 0.041 m, aces 0.059 m, fhw 0.065 m (all GMapping), freiburg-079 0.018 m (Cartographer)": a
            # name in parentheses covers the cases listed since the previous one.
            pending: list[tuple[str, str]] = []
            for case, val, who in re.findall(r"([\w.-]+) (\d+(?:\.\d+)?) m(?: \(([^)]*)\))?", best_line.group(1)):
                pending.append((case, val))
                if who:
                    who = who.removeprefix("all ")
                    for c, v in pending:
                        fam.setdefault(c, {"odometry": None, "cartographer": None, "best": None})["best"] = \
                            f"{v} m ({who})"
                    pending = []
        out[family] = fam
    return out


# --------------------------------------------------------------------------- report


METHOD = f"""\
## What is measured

* **Relation error** — `carto_cli.evaluation.metrics.relation_error` on the case's `relations.txt` (Kümmerle et al.):
  for every relation `t1 t2 dx dy dyaw`, the SLAM trajectory's pose at `t2` expressed in its pose at `t1`
  (poses at every scan, interpolated linearly in x, y and along the shorter arc in yaw) is compared with
  the relation; the translational error is the norm of the difference of the translations (m), the
  rotational one the wrapped yaw difference (deg). Shown as mean ± std (population std) over the relations
  whose two times fall within the trajectory (with `--quick`, only the processed part).
  *odometry (here)* is the same metric on the recording's own odometry (the topic SLAM used), on exactly the
  relations used for carto; *odometry / Cartographer / best peer* are copied from `PEERS.md`.
* **ATE** — after the SE(2) alignment that minimises it (`carto_cli.evaluation.metrics.ate`, at the trajectory's
  timestamps), mean translational error in m.
* **Simulated loop building** — `carto_cli.sim.loop_building()` driven round its ring corridor by
  `loop_trajectory` (as many laps as needed, cut at {SIM_DURATION:g} s), scans at 10 Hz (360 beams over 270°,
  30 m, 1 cm noise, 1% dropouts), odometry at 50 Hz with the default drift model, seed {SIM_SEED}. The relations are
  built here from the exact ground truth with the bench-dense recipe: (i, i+10) for every 10th scan (1 s
  apart), plus revisits — scans subsampled at 2 Hz, every pair ≥ 30 s apart within 3 m and 60°, a seeded
  random 3000 of them when there are more.
* **Wall time** — `build` under a `StageTimer`, stages found by name wherever they sit in the tree:
  *constraint search* = every `loop closure` stage (candidate selection, precomputation grids, branch and
  bound, refinement); *optimization* = every `optimization` stage (the periodic ones and the final one);
  *JIT* = the `jit warm-up` stage (numba loading its on-disk cache, or compiling when the cache is stale;
  kernels used only later — branch and bound, optimization — load inside their own stages); *local SLAM* =
  the rest of the `scan` stage (preprocess, extrapolate, match, motion filter, insert) except what runs in a
  `global` stage inside it; *other* = the rest of `build`'s wall time (reading and decoding the recording,
  or ray casting the simulated scans; pose-graph bookkeeping; map assembly). *scans/s* = scans read /
  `build` wall time. *process* = the whole case process from start to exit (interpreter start, imports,
  reading, SLAM, evaluation, writing the map) — comparable to the peers' "whole-process wall clock".
* **Peak RSS** — `ru_maxrss` of the case's own process (`os.wait4`), or, if higher, of it and its pose graph's
  process together while that one ran (each one's peak over that time, the graph's beyond the pages they
  share), one fresh process per case, run one at a time.
* **Loop closures** — the pose graph's inter-submap constraints. One says node *i* sits at relative pose
  *r* in submap *j*'s frame (the local SLAM frame translated to the submap's `local_pose` *S_j*), so it puts
  node *i* at `S_j ∘ r` in the local frame. With *f* the first node inserted into submap *j* (the node whose
  scan started it) and *L_f* its local-SLAM pose, the loop closure implies the pose of node *i* relative to
  node *f*: `inverse(L_f) ∘ S_j ∘ r`. The reference is `inverse(G(t_f)) ∘ G(t_i)`, G being the reference
  trajectory (`groundtruth.txt`, or the simulator's exact poses) interpolated at the two nodes' times. A loop
  closure is **correct** when the two agree within {LC_TOLERANCE_M:g} m (norm of the translation difference)
  and {LC_TOLERANCE_DEG:g}° (wrapped yaw difference): *correct vs anchor*, the figure of the family tables.
  The submap's grid is drawn by all its nodes, so local SLAM's drift between node *f* and the part of the
  submap where the scan matched counts against the loop closure there; *correct vs nearest node* repeats the
  test with, instead of *f*, the node of submap *j* nearest to node *i* in the reference (its local pose
  *L_k*, reference `G(t_k)`), which isolates the loop closure's own error. *off by > 1 m* counts the
  loop closures more than 1 m wrong even then: false matches. *submap drift* is local SLAM's own error
  inside each submap — for every submap, the largest error of its nodes' local poses relative to its first
  node against the reference (m, deg) — as the median over submaps / the worst submap. *B&B searches* is
  how many node–submap pairs went through branch and bound.
"""


def _f(x, spec=".3f", unit=""):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "—"
    return f"{format(x, spec)}{unit}"


def _failed(res: dict) -> str:
    return f"failed: {res.get('error', 'unknown error')}".replace("|", "/").replace("\n", " ")


def _rel_cell(r: dict | None) -> str:
    if not r:
        return "—"
    return f"{_f(r['trans_mean'])} ± {_f(r['trans_std'])} m / {_f(r['rot_mean'], '.2f')} ± {_f(r['rot_std'], '.2f')}°"


def _lc_cell(res: dict) -> str:
    lc = res.get("loop_closures") or {}
    total = lc.get("total")
    if total is None:
        return "—"
    if lc.get("correct") is None:
        return f"{total}" if total else "none"
    share = lc.get("share_correct")
    return f"{lc['correct']} / {total}" + (f" ({100 * share:.0f}%)" if share is not None else "")


def _table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in rows]
    return "\n".join(lines) + "\n"


def accuracy_table(family: str, results: list[dict], peers: dict) -> str:
    fam_peers = peers.get(family, {})
    if family in ("bench", "bench-dense"):
        header = ["case", "scans", "carto: relation error", "odometry (here)", "odometry (PEERS)",
                  "Cartographer (PEERS, stock)", "best peer (PEERS)", "loop closures correct", "ATE m"]
    elif family == "sim":
        header = ["case", "scans", "carto: relation error", "odometry (here)", "loop closures correct",
                  "ATE m", "relations"]
    else:
        header = ["case", "scans", "loop closures", "searches"]
    rows = []
    for res in results:
        case = res["case"]
        p = fam_peers.get(case["building"], {})
        label = case["name"]
        if res.get("status") != "ok":
            cells = [label, "—", _failed(res)]
            cells += ["—"] * (len(header) - len(cells))
            if family in ("bench", "bench-dense"):
                cells[4:7] = [p.get("odometry") or "—", p.get("cartographer") or "—", p.get("best") or "—"]
            rows.append(cells)
            continue
        acc = res.get("accuracy", {})
        scans = str(res["stats"]["scans"])
        ate_cell = _f((acc.get("ate") or {}).get("trans_mean"))
        odo = acc.get("odometry_relations")
        odo_cell = f"{_f(odo['trans_mean'], '.2f')} m / {_f(odo['rot_mean'], '.1f')}°" if odo else "—"
        if family in ("bench", "bench-dense"):
            rows.append([label, scans, _rel_cell(acc.get("relations")), odo_cell, p.get("odometry") or "—",
                         p.get("cartographer") or "—", p.get("best") or "—", _lc_cell(res), ate_cell])
        elif family == "sim":
            rb = acc.get("relations_built") or {}
            used = (acc.get("relations") or {}).get("used", "?")
            rows.append([label, scans, _rel_cell(acc.get("relations")), odo_cell, _lc_cell(res), ate_cell,
                         f"{used} used of {rb.get('consecutive', '?')} consecutive + {rb.get('revisits', '?')} "
                         "revisits"])
        else:
            cb = res.get("constraint_builder") or {}
            rows.append([label, scans, _lc_cell(res), str(cb.get("searched", "—"))])
    return _table(header, rows)


def verdict_table(results: list[dict]) -> str:
    """carto's own verdict (mapping/quality.py, no reference) against what the reference says: a map worse than
    its odometry should be 'failed', a map within 0.1 m should not be."""
    rows = []
    missed = false_alarms = better_failed = 0
    for res in results:
        q = res.get("quality")
        if res.get("status") != "ok" or not q:
            continue
        acc = res.get("accuracy", {})
        err = (acc.get("relations") or {}).get("trans_mean")
        odo = (acc.get("odometry_relations") or {}).get("trans_mean")
        worse = err is not None and odo is not None and err > odo
        good = err is not None and err < 0.1
        missed += worse and q["verdict"] != "failed"
        false_alarms += good and q["verdict"] == "failed"
        better_failed += (err is not None and odo is not None and err < odo and q["verdict"] == "failed")
        rows.append([res["case"]["name"], _f(err), _f(odo), f"**{q['verdict']}**",
                     "; ".join(q.get("reasons") or []) or "—"])
    if not rows:
        return ""
    return (_table(["case", "relation error m", "odometry m", "verdict", "reasons"], rows)
            + f"\nMaps worse than their odometry not reported `failed`: {missed}. Maps within 0.1 m reported "
              f"`failed`: {false_alarms}; maps better than their odometry reported `failed`: {better_failed}. "
              "(`carto_cli/mapping/quality.py` has the calibration on 24 runs, good and failed maps.)\n")


def performance_table(results: list[dict]) -> str:
    header = ["case", "scans", "nodes / submaps", "build wall s", "scans/s", "local SLAM s", "constraint search s",
              "optimization s", "JIT s", "other s", "process wall s", "peak RSS MB", "LC searches → accepted"]
    rows = []
    for res in results:
        name = res["case"]["name"]
        rss = _f(res.get("peak_rss_mb"), ".0f")
        pw = _f(res.get("process_wall_s"), ".1f")
        if res.get("status") != "ok":
            rows.append([name, "—", _failed(res)] + ["—"] * 7 + [pw, rss, "—"])
            continue
        st, sg = res["stats"], res["stages"]
        cb = res.get("constraint_builder") or {}
        rows.append([
            name, str(st["scans"]), f"{st['nodes']} / {st['submaps']}", _f(res["build_wall_s"], ".1f"),
            _f(res["scans_per_s"], ".0f"), _f(sg["local_slam_s"], ".1f"), _f(sg["constraint_search_s"], ".1f"),
            _f(sg["optimization_s"], ".1f"), _f(sg["jit_warmup_s"], ".2f"), _f(sg["other_s"], ".1f"), pw, rss,
            f"{cb.get('searched', '—')} → {cb.get('accepted', '—')}",
        ])
    return _table(header, rows)


def _peer_cell(r: dict | None, best: float | None) -> str:
    """``error · CPU s · peak MB`` of carto's result or a peer run's (the same keys), the lowest error in bold."""
    if not r:
        return "—"
    if r.get("status") != "ok":
        return _failed(r) if r.get("status") == "failed" else f"not run: {r.get('error', '?')}"
    err = ((r.get("accuracy") or {}).get("relations") or {}).get("trans_mean")
    cell = _f(err)
    if err is not None and err == best:
        cell = f"**{cell}**"
    return f"{cell} · {_f(r.get('cpu_s'), '.1f')} · {_f(r.get('peak_rss_mb'), '.0f')}"


def peers_table(results: list[dict], builds: dict) -> str:
    """carto beside each peer run of the same bench run, per case (``--peers``)."""
    # A peer that was not built has no column: the section says why once.
    runs = [run for system, runs in PEER_SYSTEMS.items() if "driver" in builds.get(system, {}) for run in runs]
    header = ["case", "carto: error m · CPU s · peak MB"] + [f"{label}: error · CPU · MB" for _, label, *_ in runs]
    rows = []
    for res in results:
        peers = res.get("peers") or {}
        row = [res] + [peers.get(key) for key, *_ in runs]
        errors = [((r.get("accuracy") or {}).get("relations") or {}).get("trans_mean")
                  for r in row if r and r.get("status") == "ok"]
        errors = [e for e in errors if e is not None]
        best = min(errors) if len(errors) > 1 else None
        rows.append([res["case"]["name"]] + [_peer_cell(r, best) for r in row])
    return _table(header, rows)


def peers_section(results: list[dict], builds: dict, quick: bool) -> str:
    out = ["\n## Peers run beside carto\n\n"]
    lama = builds.get("lama")
    if lama is not None:
        if lama.get("error"):
            out.append(f"IRIS LaMa was not run: {lama['error']}.\n")
        else:
            out.append(
                f"IRIS LaMa ({lama['source']}), built by `bench/lama.sh` with the driver of `../shared/peers/lama`, "
                "run on the same `scans.clf.gz` right after each carto case, each run in its own process, with "
                "iris_lama_ros's parameter defaults: *Slam2D* (scan-to-map matching, no loop closure; a pose at "
                "every scan, the last processed one's composed with the odometry since) and *PF-SLAM* (30 "
                "particles, 2 threads, seed 1; the final best particle's poses, scans between processed ones "
                "placed by odometry). "
                + ("With `--quick` they get the log cut after the scans carto mapped. " if quick else ""))
    out.append("*error*: carto's relation error (`carto_cli.evaluation.metrics.relation_error`, the translational "
               "mean in m, as in the tables above) of each system's trajectory, the lowest of the row in bold; "
               "*CPU*: user + sys seconds of the whole process from `os.wait4` (carto's with its pose graph "
               "process and every thread); *MB*: its peak RSS. The machine is shared, so compare CPU rather than "
               "wall time (each run's wall time is in the per-case JSON).\n\n")
    out.append(peers_table(results, builds))
    return "".join(out)


GMAPPING_METHOD = """\
* **GMapping** (`--algorithm gmapping`, `carto_cli/gmapping/`): every case mapped by the Rao-Blackwellized
  particle filter with the `gmapping.*` options instead of Cartographer; the trajectory is the best particle's
  (a pose for every scan, the scans between processed ones placed by odometry), so the relation error, ATE and
  verdict above are computed as for Cartographer. Its only loop closures and optimization come after the last
  scan, in the final refinement (*loop closures* counts them): *local SLAM* in the time table is the whole filter. In the table below *processed* counts the scans the filter
  processed (odometry moved `linearUpdate` or turned `angularUpdate` since the last one; every scan without
  odometry), *resamplings* how often the effective sample size fell below the threshold, *mean Neff* its
  mean over processed scans, *motion model* … *map update* the seconds in each of the filter's stages,
  *refine* the final refinement of the best particle's trajectory: loop closures between its passes in a pose
  graph (`gmapping.refineLoops`), then its scans re-matched against its whole map (`gmapping.refineIterations`),
  *map peak* the most memory all particles' copy-on-write map tiles held at once
  (`map_memory_peak_bytes`), *peak RSS* the case process's as above.
"""


def gmapping_table(results: list[dict]) -> str:
    """The particle filter's own figures per case (``--algorithm gmapping``)."""
    header = ["case", "scans", "processed", "particles", "resamplings", "mean Neff", "build wall s", "scans/s"]
    header += [f"{n} s" for n in GMAPPING_DETAIL + GMAPPING_FINAL] + ["process wall s", "peak RSS MB", "map peak MB"]
    rows = []
    for res in results:
        name = res["case"]["name"]
        rss = _f(res.get("peak_rss_mb"), ".0f")
        pw = _f(res.get("process_wall_s"), ".1f")
        if res.get("status") != "ok":
            rows.append([name, "—", _failed(res)] + ["—"] * (len(header) - 6) + [pw, rss, "—"])
            continue
        st = res["stats"]
        d = res.get("gmapping_detail") or {}
        mem = st.get("map_memory_peak_bytes")
        rows.append([name, str(st["scans"]), str(st.get("processed_scans", "—")), str(st.get("particles", "—")),
                     str(st.get("resamplings", "—")), _f(st.get("mean_neff"), ".1f"), _f(res["build_wall_s"], ".1f"),
                     _f(res["scans_per_s"], ".0f")]
                    + [_f(d.get(n), ".1f") for n in GMAPPING_DETAIL + GMAPPING_FINAL]
                    + [pw, rss, _f(None if mem is None else mem / 2**20, ".0f")])
    return _table(header, rows)


def loop_closure_table(results: list[dict]) -> str:
    header = ["case", "loop closures", "B&B searches", "correct vs anchor", "correct vs nearest node",
              "median error vs anchor", "median error vs nearest", "off by > 1 m (nearest)",
              "submap drift, median / worst submap"]
    rows = []
    for res in results:
        if res.get("status") != "ok":
            continue
        lc = res.get("loop_closures") or {}
        cb = res.get("constraint_builder") or {}
        total = lc.get("total", 0)

        def share(label, lc=lc):
            if lc.get(f"{label}_correct") is None:
                return "—"
            return f"{lc[f'{label}_correct']} ({100 * lc[f'{label}_share']:.0f}%)"

        def med(label, lc=lc):
            if lc.get(f"{label}_median_m") is None:
                return "—"
            return f"{lc[f'{label}_median_m']:.3f} m / {lc[f'{label}_median_deg']:.2f}°"

        drift = "—"
        if lc.get("submap_drift_median_m") is not None:
            drift = (f"{lc['submap_drift_median_m']:.2f} m {lc['submap_drift_median_deg']:.1f}° / "
                     f"{lc['submap_drift_max_m']:.2f} m {lc['submap_drift_max_deg']:.1f}°")
        rows.append([res["case"]["name"], str(total), str(cb.get("searched", "—")), share("anchor"), share("nearest"),
                     med("anchor"), med("nearest"), str(lc.get("nearest_over_1m", "—")), drift])
    return _table(header, rows) if rows else ""


def detail_table(results: list[dict]) -> str:
    cols = [("preprocess", "local/preprocess"), ("match", "local/match"), ("insert", "local/insert"),
            ("candidate sel.", "constraint/candidate selection"),
            ("precomputation", "constraint/precomputation"),
            ("branch and bound", "constraint/branch and bound"),
            ("refinement", "constraint/refinement")]
    header = ["case"] + [c for c, _ in cols] + ["ms per B&B search", "optimizations"]
    rows = []
    for res in results:
        if res.get("status") != "ok":
            continue
        d = res["stage_detail"]
        cb = res.get("constraint_builder") or {}
        bnb = d["constraint/branch and bound"]
        per = 1000 * bnb / cb["searched"] if cb.get("searched") else None
        rows.append([res["case"]["name"]] + [_f(d[p], ".1f") for _, p in cols]
                    + [_f(per, ".1f"), str(res["stats"].get("optimizations", "—"))])
    return _table(header, rows) if rows else ""


def _code_line(results: list[dict], env: dict) -> str:
    prints = {r.get("fingerprint") for r in results if r.get("fingerprint")}
    where = ("a copy of `carto_cli` taken when the run started" if env.get("snapshot")
             else "`carto_cli` of the working tree as it was when each case started (`--no-snapshot`)")
    line = f"* code: {where}, source fingerprint `{env.get('fingerprint')}`"
    if len(prints) > 1 or (prints and env.get("fingerprint") not in prints):
        per = ", ".join(f"{r['case']['name']} `{r.get('fingerprint', '?')}`" for r in results)
        line += f" — **the sources changed during the run**: {per}"
    return line


def render_doc(results: list[dict], env: dict, argv_line: str, args, started: str, finished: str,
               peers: dict, changed: dict | str) -> str:
    v = env["versions"]
    dirty = ""
    if env["dirty"]:
        dirty = f" + uncommitted changes ({len(env['modified'])} modified, {len(env['untracked'])} untracked files)"
    mode = f"quick (`--quick`: every case cut to its first {QUICK_SCANS} scans; sparse intel and aces and " \
           "the CCNY bag are shorter and run in full)" if args.quick else "every scan of every case run"
    algorithm = getattr(args, "algorithm", None)
    out = [
        "# Benchmarks\n",
        "Generated by `bench/run` (bench/harness.py); do not edit by hand — rerun it.\n",
        f"* command: `{argv_line}` (from the repository root)",
    ]
    if algorithm not in (None, "cartographer"):
        out.append(f"* algorithm: {algorithm} (every case mapped by `--algorithm {algorithm}` with the "
                   f"`{algorithm}.*` options)")
    out += [
        f"* mode: {mode}",
        f"* date: {started} → {finished}",
        f"* commit: `{env['commit']}`{dirty}",
        _code_line(results, env),
        f"* machine: {env['cpu']}, {env['cores']} cores, {_f(env['memory_gb'], '.0f')} GB RAM, Linux {env['kernel']}; "
        f"load average at start {', '.join(f'{x:.2f}' for x in env['loadavg_start'])} (a shared machine: wall "
        "times carry the noise of other people's jobs)",
        f"* software: Python {v['python']}, numpy {v['numpy']}, numba {v['numba']}, scipy {v['scipy']}, "
        f"opencv {v['cv2']}",
        "* profile: " + ("`auto` (what `carto map` does with no profile: each case's regime surveyed, a base "
                         "profile and derived settings chosen from it; the *auto* table below lists them)"
                         if args.profile in (None, "auto") else f"`{args.profile}` for every case")
        + "; cases run one at a time, each in a fresh process",
    ]
    if args.profile in (None, "auto"):
        out.append("* options: each base profile's values and the reason for each are in "
                   "`carto_cli/profiles/NAME.yaml` (`carto profiles show NAME --changed`); the derived settings "
                   "and their reasons are in `carto_cli/regime.py`\n")
    elif isinstance(changed, dict):
        if changed:
            out.append("* options that differ from the defaults (Cartographer's stock 2D configuration, "
                       "`carto options`):\n")
            out.append(_table(["option", "value"], [[f"`{k}`", f"`{val}`"] for k, val in changed.items()]))
        else:
            out.append("* options: all at their defaults (Cartographer's stock 2D configuration)\n")
    else:
        out.append(f"* options: could not be loaded: {changed}\n")
    by_family: dict[str, list[dict]] = {}
    for r in results:
        by_family.setdefault(r["case"]["family"], []).append(r)
    for family in FAMILIES:
        if family not in by_family:
            continue
        out.append(f"\n## {FAMILIES[family]}\n")
        out.append(accuracy_table(family, by_family[family], peers))
    autos = [r for r in results if r.get("auto")]
    if autos:
        out.append("\n## What `auto` chose\n")
        out.append(_table(["case", "detected", "algorithm", "base profile", "derived settings"],
                          [[r["case"]["name"], r["auto"]["describe"],
                            r["auto"].get("algorithm", "cartographer")
                            + (f" ({r['auto']['note']})" if r["auto"].get("note") else ""),
                            f"`{r['auto']['profile']}`",
                            "<br>".join(f"`{x}`" for x in r["auto"]["settings"]) or "-"] for r in autos]))
    vt = verdict_table(results)
    if vt:
        out.append("\n## Verdicts: does carto know when its map failed?\n")
        out.append(vt)
    gmapping = algorithm == "gmapping" or all(r.get("algorithm") == "gmapping" for r in results)
    some_gmapping = [r for r in results if r.get("algorithm") == "gmapping"]
    # Loop closures and the constraint search's sub-stages are Cartographer's machinery: all zero for gmapping.
    lct = "" if gmapping else loop_closure_table(results)
    if lct:
        out.append("\n## Loop closures\n")
        out.append(lct)
    out.append("\n## Time and memory\n")
    out.append("Each case on every core (`--jobs` default). One job against two side by side, the machine's own "
               "two-thread throughput beside them, and the 2-hour campus (time per scan and peak memory from 15 to "
               "120 minutes): docs/scaling.md (`bench/parallel.py`, `bench/scale.py`).\n\n")
    out.append(performance_table(results))
    if some_gmapping:
        out.append("\nThe particle filter (particles, resamplings, processed scans, its stages in s, memory):\n")
        out.append(gmapping_table(some_gmapping))
    det = "" if gmapping else detail_table(results)
    if det:
        out.append("\nWhere the time goes (s; the sub-stages of local SLAM and of the constraint search):\n")
        out.append(det)
    builds = env.get("peer_builds")
    if builds:
        out.append(peers_section(results, builds, args.quick))
    peers_note = ""
    if peers:
        peers_note = ("\nPeer figures are read from `PEERS.md` when this document is generated (translational "
                      "relation error, then rotational and the peer's whole-process wall time where given).\n")
    out.append(peers_note)
    out.append("\n" + METHOD)
    if gmapping:
        out.append(GMAPPING_METHOD)
    out.append(f"\nRaw results (per-case JSON, stage trees, maps, trajectories, logs) were written to "
               f"`{args.results}`.\n")
    return "\n".join(out)


# --------------------------------------------------------------------------- main


KEPT_SECTIONS = ("relocalization", "localization")  # written by bench/relocalization.py and bench/localization.py


def _kept_sections(doc: Path) -> str:
    """The marked sections other benchmark scripts own, carried over when this document is regenerated."""
    if not doc.exists():
        return ""
    old = doc.read_text()
    kept = []
    for name in KEPT_SECTIONS:
        begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
        if begin in old and end in old:
            kept.append(old[old.index(begin):old.index(end) + len(end)])
    return ("\n" + "\n\n".join(kept) + "\n") if kept else ""


def _changed_options(profile, overrides):
    try:
        from carto_cli.options import changed_options, load_options

        return dict(changed_options(load_options(profile, overrides)))
    except Exception as e:
        return f"{type(e).__name__}: {e}"


def _peer_list(text: str) -> list[str]:
    names = [n.strip() for n in text.split(",") if n.strip()]
    unknown = [n for n in names if n not in PEER_SYSTEMS]
    if unknown:
        raise argparse.ArgumentTypeError(f"unknown peer {', '.join(unknown)} (choose from {', '.join(PEER_SYSTEMS)})")
    return names


def parse_args(argv: list[str], prog: str) -> argparse.Namespace:
    from carto_cli.gmapping import ALGORITHMS

    p = argparse.ArgumentParser(
        prog=prog, description="Run the SLAM benchmark cases, one fresh process each, and write docs/benchmarks.md.",
        epilog="The document goes to docs/benchmarks.md only for a full run of every case; a --quick or "
               "--cases run writes it to the results directory unless --doc is given.")
    p.add_argument("--cases", help="comma-separated cases or families (bench, dense, sim, ccny, all); "
                                   "default: all. See --list.")
    p.add_argument("--quick", action="store_true",
                   help=f"only the first {QUICK_SCANS} scans of each case (sparse intel and aces run in full)")
    p.add_argument("--set", "-s", action="append", metavar="KEY=VALUE", help="option override (repeatable)")
    p.add_argument("--profile", "-p", default="auto",
                   help="options profile (name or .yaml path); 'auto' (default): what `carto map` does with no "
                        "profile, settings and system chosen from each recording's survey; 'default': "
                        "Cartographer's stock")
    p.add_argument("--algorithm", default=None, choices=ALGORITHMS,
                   help="mapping system for every case: cartographer or gmapping (options gmapping.*, e.g. --set "
                        "gmapping.particles=30); default: what auto chooses per case (cartographer for a named "
                        "profile)")
    p.add_argument("--peers", type=_peer_list, default=[],
                   help=f"also run these peer systems on every CARMEN case, after carto's, and compare CPU, memory "
                        f"and error ({', '.join(PEER_SYSTEMS)}; LaMa is built by bench/lama.sh from $LAMA_SRC once)")
    p.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT, help="seconds per case (0: none)")
    p.add_argument("--results", help="directory for raw results (default: a new one under $TMPDIR/carto-bench)")
    p.add_argument("--doc", help="where to write the Markdown report")
    p.add_argument("--no-doc", action="store_true", help="print the report only")
    p.add_argument("--no-snapshot", action="store_true",
                   help="run the tree's carto_cli as it is at each case's start instead of a copy taken at the start")
    p.add_argument("--list", action="store_true", help="list the cases and exit")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    return p.parse_args(argv)


def main(argv: list[str] | None = None, prog: str = "bench/run") -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = parse_args(argv, prog)
    if args.worker:
        return worker_main(args)
    cases = discover_cases()
    if args.list:
        for c in cases:
            print(f"{c.name:20s} {c.family:12s} {c.path or '(simulated)'}")
        return 0
    chosen = select_cases(args.cases, cases)
    # Fail early on bad options rather than once per case.
    if args.profile in (None, "auto"):
        changed = _changed_options(None, args.set or [])
    else:
        changed = _changed_options(None if args.profile == "default" else args.profile, args.set or [])
    if isinstance(changed, str):
        print(f"{prog}: {changed}", file=sys.stderr)
        return 2
    stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    results_dir = Path(args.results) if args.results else Path(tempfile.gettempdir()) / "carto-bench" / stamp
    results_dir.mkdir(parents=True, exist_ok=True)
    args.results = str(results_dir)
    args.snapshot_dir = None
    fingerprint = source_fingerprint(REPO / "carto_cli")
    if not args.no_snapshot:
        args.snapshot_dir = str(snapshot_package(results_dir / "src"))
        fingerprint = source_fingerprint(Path(args.snapshot_dir) / "carto_cli")
    full = not args.quick and len(chosen) == len(cases)
    doc = None if args.no_doc else Path(args.doc) if args.doc else DEFAULT_DOC if full else results_dir / "benchmarks.md"
    argv_line = shlex.join([prog] + argv)
    env = environment()
    env["fingerprint"] = fingerprint
    env["snapshot"] = args.snapshot_dir
    started = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    print(f"{argv_line}: {len(chosen)} case(s), results in {results_dir}", file=sys.stderr)
    builds: dict = {}
    if "lama" in args.peers:
        print("building IRIS LaMa (bench/lama.sh; cached after the first time)", file=sys.stderr, flush=True)
        builds["lama"] = build_lama(results_dir / "lama-build.log")
        if builds["lama"].get("error"):
            print(f"{prog}: going on without IRIS LaMa: {builds['lama']['error']} (log: {results_dir}/lama-build.log)",
                  file=sys.stderr, flush=True)
    if builds:
        env["peer_builds"] = builds

    results = []
    for case in chosen:
        print(f"== {case.name} ==", file=sys.stderr, flush=True)
        try:
            res = run_in_subprocess(case, args, results_dir)
        except KeyboardInterrupt:
            raise
        except Exception as e:  # the harness itself must not stop on one case
            res = {"status": "failed", "case": asdict(case), "error": f"harness: {type(e).__name__}: {e}"}
        results.append(res)
        if res.get("status") == "ok":
            acc = (res.get("accuracy") or {}).get("relations")
            err = f", relation error {_rel_cell(acc)}" if acc else ""
            st = res["stats"]
            what = (f"{st['particles']} particles, {st['resamplings']} resamplings, {st['processed_scans']} scans "
                    "processed" if st.get("algorithm") == "gmapping" else f"loop closures {_lc_cell(res)}")
            print(f"== {case.name}: {st['scans']} scans in {res['build_wall_s']:.1f} s "
                  f"(process {res['process_wall_s']:.1f} s, CPU {res['cpu_s']:.1f} s, {res['peak_rss_mb']:.0f} MB)"
                  f"{err}, {what}",
                  file=sys.stderr, flush=True)
        else:
            print(f"== {case.name}: {_failed(res)}", file=sys.stderr, flush=True)
        if builds:
            res["peers"] = run_peers(case, builds, args, results_dir)
            json_path = results_dir / f"{case.name}.json"
            if json_path.is_file():
                json_path.write_text(json.dumps(res, indent=1, default=_json_default))

    finished = _dt.datetime.now().astimezone().strftime("%Y-%m-%d %H:%M %Z")
    peers = parse_peers(DATA / "PEERS.md")
    text = render_doc(results, env, argv_line, args, started, finished, peers, changed)
    (results_dir / "summary.json").write_text(json.dumps(
        {"command": argv_line, "environment": env, "results": results}, indent=1, default=_json_default))
    if doc is not None:
        doc.parent.mkdir(parents=True, exist_ok=True)
        text = text.rstrip("\n") + "\n" + _kept_sections(doc)
        tmp = doc.with_name(doc.name + ".tmp")
        tmp.write_text(text)
        os.replace(tmp, doc)
        print(f"wrote {doc}", file=sys.stderr)
    print(text)
    return 0 if all(r.get("status") == "ok" for r in results) else 1


if __name__ == "__main__":
    sys.exit(main())
