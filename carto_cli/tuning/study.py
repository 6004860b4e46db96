"""``carto tune``: search option values that map given recordings best (Optuna).

One trial = one set of option values (the base profile, ``overrides`` and what the
sampler drew from the search space), mapped on every recording through the same
``map_builder.build`` every other command runs, scored by an objective, averaged over
the recordings (lower is better):

``relations``
    mean translational relation error (m) + 1 m × mean rotational relation error (rad),
    i.e. a 1° rotation error weighs like 1.75 cm (the Kümmerle relations of the bench cases).
``ground-truth``
    ATE RMSE (m) after the SE(2) alignment that minimises it.
``relocalization``
    the map is built from the first 70 % of the scans; up to 20 scans evenly spread over
    the last 30 % are relocalized from priors perturbed by N(0, 0.3 m) per axis and
    N(0, 3°) (given to the relocalizer as sigma 0.5 m / 6°; the perturbation is seeded,
    so every trial sees the same queries). A query succeeds when the relocalizer reports
    success and its pose is within 0.3 m and 3° of the reference: the ground truth when
    given, else the trajectory of the whole recording mapped once with the base options,
    brought into the trial's map frame by the SE(2) alignment of the mapped scans within
    4 m of the query (the whole mapped part when fewer than 5 are), so a relocalization
    consistent with the map it was given counts even where that map drifted.
    Value = (1 − success rate) + mean latency per query (s).
``map-quality`` (no reference needed)
    endpoint spread + mean loop-closure residual (m). The endpoint spread is the number of
    distinct 5 cm cells hit by all scan returns placed at their mapped poses, divided by
    the number of returns: sharp, consistent walls collect the returns of many scans in
    few cells, a blurred or doubled wall spreads them (a point-cloud analogue of the mean
    map entropy). The residual is the mean translation residual of the loop closures after
    the final optimization (0 when there are none): a wrong loop closure leaves one. The
    grid's crispness (share of known cells with p ≤ 0.3 or ≥ 0.7) and occupied-cell
    entropy are recorded too, but not scored: they depend on the submap size and the
    hit/miss probabilities themselves (docs/tuning.md has the comparison). The space may
    not vary the grid's resolution or hit/miss probabilities under this objective.
``auto``
    relations when relation files are given, else ground-truth when ground truths are
    given, else map-quality.

``time_weight`` adds ``time_weight × wall seconds per scan`` of the mapping (numba
compilation excluded by a warm-up run) to every recording's score: with
``time_weight=10``, 10 ms per scan costs as much as 10 cm of relation error.

Engine: TPE sampler (seeded), median pruner fed the running mean after each recording
(so with several recordings a hopeless trial stops early; with one there is nothing to
prune on), SQLite storage next to the output by default so that rerunning the same
command resumes the study. ``n_jobs`` > 1 starts ``n_jobs − 1`` worker processes that
share the storage with this one (numba-heavy Python does not parallelise in threads).
A trial whose pipeline raises is recorded as failed and the study goes on. Ctrl-C stops
after the running trial; the outputs are still written.
"""
from __future__ import annotations

import csv
import datetime as _dt
import math
import multiprocessing as mp
import signal
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import yaml

from carto_cli.core.errors import CartoError
from carto_cli.evaluation.metrics import Relations, align_se2, ate, interpolate_poses, read_relations, relation_error
from carto_cli.io.atomic import atomic_output
from carto_cli.io.map_image import write_png
from carto_cli.io.trajectory import Trajectory, read_trajectory
from carto_cli.options import Options, apply_overrides, changed_options, load_options
from carto_cli.tuning.space import Param, base_values, load_space, suggest_params

__all__ = ["tune", "TuneResult", "Case", "make_cases", "evaluate_options", "map_quality", "OBJECTIVES",
           "ROTATION_LEVER_M", "write_profile", "write_trials_csv", "draw_report"]

OBJECTIVES = ("auto", "relations", "ground-truth", "relocalization", "map-quality")
ROTATION_LEVER_M = 1.0  # relations objective: metres per radian of rotational error

RELOC_MAP_FRACTION = 0.7
RELOC_QUERIES = 20
RELOC_PRIOR_NOISE = (0.3, math.radians(3.0))
RELOC_SIGMAS = (0.5, math.radians(6.0))
RELOC_TOLERANCE = (0.3, math.radians(3.0))
RELOC_ALIGN_RADIUS = 4.0

# Options a map-quality score would reward for themselves rather than for a better map.
_GRID_OPTIONS = ("trajectory_builder_2d.submaps.grid_options_2d.resolution",
                 "trajectory_builder_2d.submaps.range_data_inserter.")


# ----------------------------------------------------------------------------------------- cases


@dataclass(eq=False)
class Case:
    """One recording to score on, with what its objective needs."""

    source: Any  # a path, or a Recording object (simulated recordings in tests)
    relations: Relations | None = None
    ground_truth: Trajectory | None = None
    reference: Trajectory | None = None  # relocalization reference (set up by ``prepare``)
    n_scans: int | None = None  # scans used (after max_scans), relocalization only
    _recording: Any = field(default=None, repr=False)

    @property
    def name(self) -> str:
        return str(self.source) if isinstance(self.source, (str, Path)) else type(self.source).__name__

    def recording(self):
        if self._recording is None:
            if isinstance(self.source, (str, Path)):
                from carto_cli.io.sources.open import open_recording

                self._recording = open_recording(Path(self.source))
            else:
                self._recording = self.source
        return self._recording


def _as_trajectory(gt) -> Trajectory:
    if isinstance(gt, Trajectory):
        return gt
    if isinstance(gt, (str, Path)):
        return read_trajectory(gt)
    arr = np.asarray(gt, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 4:
        raise CartoError(f"ground truth must be (m, 4) t x y yaw, got shape {arr.shape}")
    return Trajectory.from_arrays(arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3])


def make_cases(recordings: Sequence, relations: Sequence | None = None,
               ground_truth: Sequence | None = None) -> list[Case]:
    """Cases from recordings (paths or Recording objects) and one relations / ground-truth per recording."""
    if not recordings:
        raise CartoError("tune needs at least one recording")
    n = len(recordings)
    for what, extra in (("relations", relations), ("ground-truth", ground_truth)):
        if extra and len(extra) != n:
            raise CartoError(f"give one --{what} file per recording: {n} recording(s), {len(extra)} {what} file(s)")
    cases = []
    for i, rec in enumerate(recordings):
        rel = relations[i] if relations else None
        gt = ground_truth[i] if ground_truth else None
        cases.append(Case(rec, read_relations(rel) if isinstance(rel, (str, Path)) else rel,
                          None if gt is None else _as_trajectory(gt)))
    return cases


def resolve_objective(objective: str, cases: Sequence[Case]) -> str:
    if objective not in OBJECTIVES:
        raise CartoError(f"unknown objective '{objective}' (one of {', '.join(OBJECTIVES)})")
    if objective == "auto":
        if all(c.relations is not None for c in cases):
            return "relations"
        if all(c.ground_truth is not None for c in cases):
            return "ground-truth"
        return "map-quality"
    if objective == "relations" and any(c.relations is None for c in cases):
        raise CartoError("the relations objective needs a --relations file for every recording")
    if objective == "ground-truth" and any(c.ground_truth is None for c in cases):
        raise CartoError("the ground-truth objective needs a --ground-truth file for every recording")
    return objective


def _scans(recording, limit: int | None = None):
    from carto_cli.io.topics import select_topics
    from carto_cli.core.records import Scan

    topic = select_topics(recording).scan
    n = 0
    for rec in recording.records([topic]):
        if isinstance(rec, Scan):
            if limit is not None and n >= limit:
                return
            yield rec
            n += 1


def prepare(cases: Sequence[Case], objective: str, base: Options, max_scans: int | None) -> None:
    """What an objective computes once per recording, before any trial (relocalization reference)."""
    if objective != "relocalization":
        return
    from carto_cli.pipeline import build

    for case in cases:
        case.n_scans = sum(1 for _ in _scans(case.recording(), max_scans))
        if case.n_scans < 10:
            raise CartoError(f"relocalization needs at least 10 scans, the recording has {case.n_scans}", case.name)
        if case.ground_truth is not None:
            case.reference = case.ground_truth
        else:
            full = build(case.recording(), base, max_scans=max_scans)
            case.reference = Trajectory.from_poses(full.times, full.poses)


# ----------------------------------------------------------------------------------------- scoring


SPREAD_CELL_M = 0.05  # map-quality: cell size of the endpoint-spread grid


def endpoint_spread(result, recording, max_scans: int | None = None) -> float:
    """Distinct 5 cm cells hit by the scans' endpoints at their mapped poses, per endpoint.

    Every return within the scan's own range limits (not the options', so that the value
    compares option sets) is placed at its scan's pose; a consistent map puts the returns
    of many scans on the same thin walls, a blurred or doubled one spreads them over more
    cells. In (0, 1], lower is sharper.
    """
    times = np.asarray(result.times, dtype=np.float64)
    poses = np.asarray(result.poses, dtype=np.float64)
    mount = np.asarray(result.laser_pose, dtype=np.float64).reshape(3)
    keys, n_points = [], 0
    for scan in _scans(recording, max_scans):
        i = int(np.searchsorted(times, scan.time))
        if i >= len(times) or abs(times[i] - scan.time) > 1e-6:
            continue
        r = np.asarray(scan.ranges, dtype=np.float64)
        a = np.asarray(scan.angles, dtype=np.float64)
        ok = np.isfinite(r) & (r > max(scan.range_min, 0.0)) & (r < scan.range_max)
        if not ok.any():
            continue
        x, y, th = poses[i]
        lx = x + math.cos(th) * mount[0] - math.sin(th) * mount[1]
        ly = y + math.sin(th) * mount[0] + math.cos(th) * mount[1]
        ang = th + mount[2] + a[ok]
        px = np.floor((lx + r[ok] * np.cos(ang)) / SPREAD_CELL_M).astype(np.int64)
        py = np.floor((ly + r[ok] * np.sin(ang)) / SPREAD_CELL_M).astype(np.int64)
        keys.append(px * 4_000_003 + py)
        n_points += int(ok.sum())
    if n_points == 0:
        raise CartoError("no scan endpoint to score the map with")
    return float(np.unique(np.concatenate(keys)).size / n_points)


def map_quality(result, recording=None, max_scans: int | None = None) -> dict[str, float]:
    """Reference-free scores of a MapResult (see the module doc); ``map_quality`` is the objective.

    Needs ``recording`` (the one mapped) for the endpoint spread; without it the value is
    left out and only the grid scores (crispness, occupied entropy) and the residual are given.
    """
    p = np.asarray(result.image.probability, dtype=np.float64)
    known = p[np.isfinite(p)]
    if known.size == 0:
        raise CartoError("the map has no known cell")
    crisp = float(np.mean((known <= 0.3) | (known >= 0.7)))
    occ = np.clip(known[known > 0.5], 1e-6, 1 - 1e-6)
    entropy = float(np.mean(-(occ * np.log2(occ) + (1 - occ) * np.log2(1 - occ)))) if occ.size else 1.0
    residual = 0.0
    graph = getattr(result, "graph", None)
    if graph is not None and graph.num_loop_closures:
        res = graph.loop_closure_residuals()
        residual = float(np.mean(res)) if res.size else 0.0
    out = {"crispness": crisp, "occupied_entropy": entropy, "loop_closure_residual_m": residual}
    if recording is not None:
        out["endpoint_spread"] = endpoint_spread(result, recording, max_scans)
        out["map_quality"] = out["endpoint_spread"] + residual
    return out


def _relocalization_score(case: Case, options: Options, max_scans: int | None, time_weight: float
                          ) -> tuple[float, dict]:
    from carto_cli.io.map_file import load_map, save_map
    from carto_cli.pipeline import build
    from carto_cli.relocalization.relocalizer import Relocalizer

    rec = case.recording()
    n_map = max(5, int(round(RELOC_MAP_FRACTION * case.n_scans)))
    result = build(rec, options, max_scans=n_map)
    with tempfile.TemporaryDirectory(prefix="carto-tune-") as tmp:
        loaded = load_map(save_map(Path(tmp) / "part.carto", result, options))
    reloc = Relocalizer(loaded, options)
    # The reference in this trial's map frame, aligned locally: over the mapped scans within
    # RELOC_ALIGN_RADIUS of the query (those built the submaps it is matched against), so that
    # drift elsewhere in the map does not count against a relocalization consistent with it.
    rxy, rth, ok = interpolate_poses(case.reference, result.times)
    if ok.sum() < 2:
        raise CartoError("the relocalization reference does not cover the mapped scans", case.name)
    rxy, mxy = rxy[ok], result.poses[ok, :2]
    global_fit = align_se2(rxy, mxy)
    held = np.arange(n_map, case.n_scans)
    pick = set(np.unique(np.linspace(0, len(held) - 1, min(RELOC_QUERIES, len(held))).round().astype(int)).tolist())
    wanted = {int(held[i]) for i in pick}
    rng = np.random.default_rng(20240611)
    successes, latencies, n = 0, [], 0
    for index, scan in enumerate(_scans(rec, case.n_scans)):
        if index not in wanted:
            continue
        qxy, qth, qok = interpolate_poses(case.reference, [scan.time])
        if not qok[0]:
            continue
        near = np.hypot(*(rxy - qxy[0]).T) <= RELOC_ALIGN_RADIUS
        tx, ty, phi = align_se2(rxy[near], mxy[near]) if near.sum() >= 5 else global_fit
        c, s = math.cos(phi), math.sin(phi)
        truth = np.array([c * qxy[0, 0] - s * qxy[0, 1] + tx, s * qxy[0, 0] + c * qxy[0, 1] + ty, qth[0] + phi])
        noise = rng.normal(0.0, 1.0, 3) * [RELOC_PRIOR_NOISE[0], RELOC_PRIOR_NOISE[0], RELOC_PRIOR_NOISE[1]]
        n += 1
        try:
            r = reloc.relocalize(scan, truth + noise, sigma_xy=RELOC_SIGMAS[0], sigma_yaw=RELOC_SIGMAS[1])
        except CartoError:
            continue
        latencies.append(r.total_ms / 1000.0)
        dyaw = abs((r.pose[2] - truth[2] + math.pi) % (2 * math.pi) - math.pi)
        if r.success and np.hypot(*(r.pose[:2] - truth[:2])) <= RELOC_TOLERANCE[0] and dyaw <= RELOC_TOLERANCE[1]:
            successes += 1
    if n == 0:
        raise CartoError("no held-out scan to relocalize", case.name)
    rate = successes / n
    latency = float(np.mean(latencies)) if latencies else 0.0
    value = (1.0 - rate) + latency
    metrics = {"success_rate": rate, "latency_s": latency, "queries": n}
    return value, _with_time(value, metrics, result, time_weight)


def _with_time(value: float, metrics: dict, result, time_weight: float) -> dict:
    s_per_scan = result.stats["wall_time_s"] / max(1, result.stats["scans"])
    metrics.update({"s_per_scan": s_per_scan, "loop_closures": result.stats.get("loop_closures", 0),
                    "score": value + time_weight * s_per_scan})
    return metrics


def score_case(case: Case, options: Options, objective: str, *, max_scans: int | None = None,
               time_weight: float = 0.0) -> tuple[float, dict]:
    """(score, metrics) of ``options`` on one recording; score includes the time term."""
    if objective == "relocalization":
        if case.reference is None:
            raise CartoError("relocalization case not prepared (call tune.prepare first)")
        _, metrics = _relocalization_score(case, options, max_scans, time_weight)
        return metrics["score"], metrics
    from carto_cli.pipeline import build

    result = build(case.recording(), options, max_scans=max_scans)
    traj = Trajectory.from_poses(result.times, result.poses)
    if objective == "relations":
        r = relation_error(traj, case.relations)
        value = r.translation.mean + ROTATION_LEVER_M * math.radians(r.rotation.mean)
        metrics = {"relation_trans_m": r.translation.mean, "relation_rot_deg": r.rotation.mean,
                   "relations_used": r.used}
    elif objective == "ground-truth":
        a = ate(traj, case.ground_truth)
        value = a.translation.rmse
        metrics = {"ate_rmse_m": value, "ate_rot_rmse_deg": a.rotation.rmse}
    elif objective == "map-quality":
        metrics = map_quality(result, case.recording(), max_scans)
        value = metrics["map_quality"]
    else:
        raise CartoError(f"unknown objective '{objective}'")
    metrics = _with_time(value, metrics, result, time_weight)
    return metrics["score"], metrics


def evaluate_options(options: Options, cases: Sequence[Case], objective: str, *, max_scans: int | None = None,
                     time_weight: float = 0.0, report: Callable[[int, float], None] | None = None
                     ) -> tuple[float, dict]:
    """Mean score of ``options`` over ``cases`` and the mean of each metric; ``report(i, running_mean)``
    is called after each recording (the tuner prunes from it)."""
    scores, metrics_all = [], []
    for i, case in enumerate(cases):
        score, metrics = score_case(case, options, objective, max_scans=max_scans, time_weight=time_weight)
        if not math.isfinite(score):
            raise CartoError(f"non-finite score on {case.name}")
        scores.append(score)
        metrics_all.append(metrics)
        if report is not None:
            report(i, float(np.mean(scores)))
    keys = metrics_all[0].keys()
    return float(np.mean(scores)), {k: float(np.mean([m[k] for m in metrics_all])) for k in keys}


# ----------------------------------------------------------------------------------------- study


@dataclass
class TuneResult:
    best_value: float
    best_params: dict[str, Any]
    n_trials: int  # trials in the study (all runs of it), whatever their state
    profile_path: Path
    csv_path: Path
    png_path: Path
    objective: str = ""
    study_name: str = ""
    storage: str = ""
    baseline_value: float | None = None  # the base options' score, when it was measured (first trial)
    n_complete: int = 0
    n_pruned: int = 0
    n_failed: int = 0
    best_metrics: dict = field(default_factory=dict)


_STOP = {"requested": False}


def _on_sigint(signum, frame):  # first Ctrl-C: finish the running trial; second: default behaviour
    _STOP["requested"] = True
    signal.signal(signal.SIGINT, signal.default_int_handler)


@dataclass
class _Job:
    storage: str
    study_name: str
    params: list[Param]
    base: Options
    cases: list[Case]
    objective: str
    time_weight: float
    max_scans: int | None
    seed: int | None
    startup: int


def _storage(url: str):
    """SQLite studies shared by several processes: wait for the file lock instead of failing a trial."""
    import optuna

    if url.startswith("sqlite:"):
        return optuna.storages.RDBStorage(url, engine_kwargs={"connect_args": {"timeout": 120}})
    return url


def _load_study(job: _Job, worker: int):
    import optuna

    seed = None if job.seed is None else job.seed + worker
    sampler = optuna.samplers.TPESampler(seed=seed, n_startup_trials=job.startup)
    pruner = optuna.pruners.MedianPruner(n_startup_trials=3, n_warmup_steps=0)
    return optuna.load_study(study_name=job.study_name, storage=_storage(job.storage), sampler=sampler, pruner=pruner)


def _objective(job: _Job):
    import optuna

    def objective(trial) -> float:
        values = suggest_params(trial, job.params)
        options = apply_overrides(job.base, values)

        def report(i: int, running: float) -> None:
            if len(job.cases) > 1:
                trial.report(running, i)
                if trial.should_prune():
                    raise optuna.TrialPruned()

        try:
            value, metrics = evaluate_options(options, job.cases, job.objective, max_scans=job.max_scans,
                                              time_weight=job.time_weight, report=report)
        except optuna.TrialPruned:
            raise
        except Exception as e:  # recorded on the failed trial, the study goes on
            trial.set_user_attr("error", f"{type(e).__name__}: {e}"[:500])
            raise
        for k, v in metrics.items():
            trial.set_user_attr(k, v)
        return value

    return objective


def _stop_callback(on_trial):
    import optuna

    def callback(study, frozen) -> None:
        if on_trial is not None:
            try:
                best = study.best_value
            except ValueError:
                best = None
            value = frozen.value if frozen.state == optuna.trial.TrialState.COMPLETE else None
            on_trial(frozen.number, value, best)
        if _STOP["requested"]:
            study.stop()

    return callback


def _run(job: _Job, worker: int, n_trials: int, on_trial=None) -> None:
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = _load_study(job, worker)
    try:
        study.optimize(_objective(job), n_trials=n_trials, catch=(Exception,),
                       callbacks=[_stop_callback(on_trial)], gc_after_trial=False)
    except KeyboardInterrupt:  # second Ctrl-C: the running trial is marked failed by optuna
        pass


def _worker_main(job: _Job, worker: int, n_trials: int) -> None:  # pragma: no cover - runs in a child
    _STOP["requested"] = False
    if hasattr(signal, "SIGINT"):
        signal.signal(signal.SIGINT, _on_sigint)
    _run(job, worker, n_trials)


def _default_storage(out: Path) -> str:
    return "sqlite:///" + str(out.resolve().with_name(out.stem + ".optuna.db"))


def _warm_up(cases: Sequence[Case], base: Options) -> None:
    """Compile the numba kernels before timed trials (a few scans of the first recording)."""
    from carto_cli.pipeline import build

    try:
        build(cases[0].recording(), base, max_scans=20)
    except Exception:
        pass


def tune(
    recordings: Sequence,
    space: Path | str | dict,
    *,
    trials: int,
    out: Path,
    objective: str = "auto",
    relations: Sequence | None = None,
    ground_truth: Sequence | None = None,
    base_profile: str | Path | None = None,
    overrides: Sequence[str] | dict = (),
    time_weight: float = 0.0,
    storage: str | None = None,
    study_name: str | None = None,
    n_jobs: int = 1,
    seed: int | None = None,
    max_scans: int | None = None,
    on_trial: Callable[[int, float | None, float | None], None] | None = None,
) -> TuneResult:
    """Run (or resume) a study of ``trials`` more trials and write the tuned profile ``out``,
    ``<out stem>.trials.csv`` and ``<out stem>.report.png`` next to it.

    ``recordings`` are paths (or Recording objects); ``relations`` / ``ground_truth`` one per
    recording (paths; ground truths may also be (m, 4) t x y yaw arrays). ``space`` is a
    search-space file or dict (see ``tune_space``). ``storage`` defaults to
    ``sqlite:///<out dir>/<out stem>.optuna.db`` and ``study_name`` to the out stem, so the same
    command resumes. ``on_trial(number, value or None, best value or None)`` is called after
    every trial this process runs. Raises CartoError for bad inputs and when no trial completed.
    """
    import optuna

    out = Path(out)
    if trials < 1:
        raise CartoError(f"--trials must be at least 1, got {trials}")
    if n_jobs < 1:
        raise CartoError(f"--n-jobs must be at least 1, got {n_jobs}")
    if time_weight < 0 or not math.isfinite(time_weight):
        raise CartoError(f"--time-weight must be a non-negative number, got {time_weight}")
    if max_scans is not None and max_scans < 1:
        raise CartoError(f"--max-scans must be at least 1, got {max_scans}")
    params = load_space(space)
    base = load_options(base_profile, []) if isinstance(overrides, dict) else load_options(base_profile, overrides)
    if isinstance(overrides, dict):
        base = apply_overrides(base, overrides)
    cases = make_cases(recordings, relations, ground_truth)
    objective = resolve_objective(objective, cases)
    if objective == "map-quality":
        bad = [p.name for p in params if p.name.startswith(_GRID_OPTIONS)]
        if bad:
            raise CartoError(f"the map-quality objective scores the grid itself, so it cannot tune {', '.join(bad)} "
                             "(they would be tuned for sharper-looking cells, not a better map); "
                             "use relations or ground truth, or drop them from the space")
    prepare(cases, objective, base, max_scans)
    if time_weight > 0:
        _warm_up(cases, base)

    storage = storage or _default_storage(out)
    study_name = study_name or out.stem
    out.parent.mkdir(parents=True, exist_ok=True)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        study = optuna.create_study(study_name=study_name, storage=_storage(storage), direction="minimize",
                                    load_if_exists=True)
    except Exception as e:
        raise CartoError(f"cannot open the study storage {storage}: {e}") from None
    if not study.trials:
        baseline = base_values(base, params)
        if baseline:
            study.enqueue_trial(baseline, user_attrs={"baseline": True})
    job = _Job(storage, study_name, params, base, cases, objective, time_weight, max_scans, seed,
               startup=max(3, min(10, trials // 2)))

    previous = signal.getsignal(signal.SIGINT)
    _STOP["requested"] = False
    in_main = _is_main_thread()
    if in_main:
        signal.signal(signal.SIGINT, _on_sigint)
    workers: list = []
    try:
        remaining = trials
        if n_jobs > 1 and remaining and any(t.state == optuna.trial.TrialState.WAITING for t in study.trials):
            # Optuna hands an enqueued trial to whichever process asks first, and two processes can
            # both take it ("Cannot tell a COMPLETE trial"): run the baseline here before forking.
            _run(job, 0, 1, on_trial)
            remaining -= 1
        shares = [remaining // n_jobs + (1 if i < remaining % n_jobs else 0) for i in range(n_jobs)]
        if n_jobs > 1:
            ctx = mp.get_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")
            for w in range(1, n_jobs):
                if shares[w]:
                    p = ctx.Process(target=_worker_main, args=(job, w, shares[w]), daemon=False)
                    p.start()
                    workers.append(p)
        _run(job, 0, shares[0], on_trial)
        for p in workers:
            p.join()
        failed = [p.exitcode for p in workers if p.exitcode]
        if failed:
            raise CartoError(f"{len(failed)} tuning worker process(es) failed (exit codes {failed}); "
                             "the study keeps every trial that finished")
    finally:
        for p in workers:
            if p.is_alive():
                p.join()
        if in_main:
            signal.signal(signal.SIGINT, previous)
    return _finish(study_name, storage, job, out, objective, base_profile, overrides)


def _is_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _finish(study_name: str, storage: str, job: _Job, out: Path, objective: str, base_profile, overrides
            ) -> TuneResult:
    import optuna

    study = optuna.load_study(study_name=study_name, storage=storage)
    trials = study.get_trials(deepcopy=False)
    stem = out.with_suffix("") if out.suffix in (".yaml", ".yml") else out
    csv_path = stem.parent / (stem.name + ".trials.csv")
    png_path = stem.parent / (stem.name + ".report.png")
    write_trials_csv(csv_path, trials)
    complete = [t for t in trials if t.state == optuna.trial.TrialState.COMPLETE]
    if not complete:
        errors = {t.user_attrs.get("error") for t in trials if t.user_attrs.get("error")}
        hint = f" (e.g. {sorted(errors)[0]})" if errors else ""
        raise CartoError(f"no trial completed out of {len(trials)}{hint}; see {csv_path}")
    importances: dict[str, float] = {}
    if len(complete) >= 3:
        try:
            importances = dict(optuna.importance.get_param_importances(study))
        except Exception:
            importances = {}
    draw_report(png_path, trials, importances, title=f"carto tune: {study_name} ({objective})")
    best = study.best_trial
    options = apply_overrides(job.base, {p.name: best.params[p.name] for p in job.params if p.name in best.params})
    baseline = next((t.value for t in complete if t.user_attrs.get("baseline")), None)
    write_profile(out, options, best=best, objective=objective, n_trials=len(trials), base_profile=base_profile,
                  overrides=overrides, tuned=[p.name for p in job.params], baseline=baseline,
                  time_weight=job.time_weight, max_scans=job.max_scans)
    state = optuna.trial.TrialState
    return TuneResult(
        best_value=float(best.value), best_params=dict(best.params), n_trials=len(trials), profile_path=out,
        csv_path=csv_path, png_path=png_path, objective=objective, study_name=study_name, storage=storage,
        baseline_value=baseline, n_complete=len(complete),
        n_pruned=sum(t.state == state.PRUNED for t in trials), n_failed=sum(t.state == state.FAIL for t in trials),
        best_metrics={k: v for k, v in best.user_attrs.items() if k not in ("baseline",)},
    )


# ----------------------------------------------------------------------------------------- outputs


_OBJECTIVE_TEXT = {
    "relations": "mean translational relation error (m) + 1 m x mean rotational relation error (rad)",
    "ground-truth": "ATE RMSE (m) after SE(2) alignment",
    "relocalization": "(1 - relocalization success rate) + mean latency (s) on held-out scans",
    "map-quality": "endpoint spread (distinct 5 cm cells hit per return) + mean loop-closure residual (m)",
}


def _nest(flat: dict[str, Any]) -> dict:
    out: dict = {}
    for key, value in flat.items():
        node = out
        parts = key.split(".")
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return out


def write_profile(path: Path, options: Options, *, best=None, objective: str = "", n_trials: int = 0,
                  base_profile=None, overrides=(), tuned: Sequence[str] = (), baseline: float | None = None,
                  time_weight: float = 0.0, max_scans: int | None = None) -> Path:
    """``options`` as a profile: the keys that differ from the packaged defaults (so the file stands
    alone under ``--profile``, base profile included), with a header saying where it came from."""

    path = Path(path)
    changed = changed_options(options, load_options())
    set_text = (", ".join(f"{k}={v}" for k, v in overrides.items()) if isinstance(overrides, dict)
                else " ".join(f"--set {o}" for o in overrides))
    lines = [
        "# carto tune result: load with --profile " + path.name,
        f"# date: {_dt.datetime.now().astimezone().isoformat(timespec='seconds')}",
        f"# base profile: {base_profile or 'default'}" + (f" ({set_text})" if set_text else ""),
        f"# objective: {objective} = {_OBJECTIVE_TEXT.get(objective, objective)}"
        + (f" + {time_weight:g} x s/scan" if time_weight else ""),
    ]
    if best is not None:
        lines.append(f"# best value: {best.value:.6g} (trial {best.number} of {n_trials})"
                     + (f"; base options scored {baseline:.6g}" if baseline is not None else ""))
    if max_scans:
        lines.append(f"# scored on the first {max_scans} scans of each recording")
    if tuned:
        lines.append("# tuned options: " + ", ".join(tuned))
    lines.append("# keys below: every option that differs from carto's defaults (base profile + tuned values)")
    body = yaml.safe_dump(_nest(changed), sort_keys=False, default_flow_style=False) if changed else "{}\n"
    with atomic_output(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n" + body, encoding="utf-8")
    return path


def write_trials_csv(path: Path, trials) -> Path:
    """number, state, value, duration_s, one column per parameter, then the trial's metrics."""
    names: list[str] = []
    attrs: list[str] = []
    for t in trials:
        names += [k for k in t.params if k not in names]
        attrs += [k for k in t.user_attrs if k not in attrs]
    with atomic_output(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["number", "state", "value", "duration_s"] + names + attrs)
        for t in trials:
            dur = t.duration.total_seconds() if t.duration is not None else ""
            value = "" if t.value is None else repr(float(t.value))
            w.writerow([t.number, t.state.name, value, dur if dur == "" else f"{dur:.3f}"]
                       + [t.params.get(k, "") for k in names] + [t.user_attrs.get(k, "") for k in attrs])
    return path


def _short(name: str) -> str:
    parts = name.split(".")
    return ".".join(parts[-2:]) if len(parts) > 1 else name


def draw_report(path: Path, trials, importances: dict[str, float], title: str = "carto tune") -> Path:
    """A PNG: objective per trial with the best-so-far line, and parameter importances (OpenCV)."""
    import cv2
    import optuna

    W, H = 1280, 520
    img = np.full((H, W, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    black, grey, blue, red = (0, 0, 0), (170, 170, 170), (200, 110, 30), (40, 40, 220)
    cv2.putText(img, title, (20, 28), font, 0.65, black, 1, cv2.LINE_AA)
    # ---- history
    x0, y0, x1, y1 = 80, 60, 620, H - 60
    cv2.rectangle(img, (x0, y0), (x1, y1), black, 1)
    cv2.putText(img, "objective per trial (lower is better); red: best so far", (x0, y0 - 10), font, 0.45, black, 1,
                cv2.LINE_AA)
    done = [(t.number, float(t.value)) for t in trials
            if t.state == optuna.trial.TrialState.COMPLETE and t.value is not None and math.isfinite(t.value)]
    n = max([t.number for t in trials], default=0) + 1
    if done:
        vals = np.array([v for _, v in done])
        lo, hi = float(vals.min()), float(np.percentile(vals, 95)) if len(vals) > 4 else float(vals.max())
        if hi <= lo:
            hi = lo + max(abs(lo) * 0.1, 1e-9)
        pad = 0.05 * (hi - lo)
        lo, hi = lo - pad, hi + pad

        def px(i, v):
            x = x0 + int(round((i + 0.5) / n * (x1 - x0)))
            y = y1 - int(round((min(max(v, lo), hi) - lo) / (hi - lo) * (y1 - y0)))
            return x, y

        for i, v in done:
            cv2.circle(img, px(i, v), 4, blue, -1, cv2.LINE_AA)
        for t in trials:
            if t.state != optuna.trial.TrialState.COMPLETE:
                x, _ = px(t.number, lo)
                cv2.drawMarker(img, (x, y1 - 6), grey, cv2.MARKER_TILTED_CROSS, 8, 1)
        best = math.inf
        pts = []
        for i, v in sorted(done):
            best = min(best, v)
            pts.append(px(i, best))
        pts.append((x1, pts[-1][1]))
        for a, b in zip(pts[:-1], pts[1:]):
            cv2.line(img, a, (b[0], a[1]), red, 2, cv2.LINE_AA)
            cv2.line(img, (b[0], a[1]), b, red, 2, cv2.LINE_AA)
        for k in range(5):
            v = lo + k / 4 * (hi - lo)
            y = y1 - int(round(k / 4 * (y1 - y0)))
            cv2.line(img, (x0 - 4, y), (x0, y), black, 1)
            cv2.putText(img, f"{v:.4g}", (8, y + 4), font, 0.4, black, 1, cv2.LINE_AA)
        cv2.putText(img, f"best {min(vals):.5g}", (x1 - 150, y0 + 20), font, 0.45, red, 1, cv2.LINE_AA)
    for k in range(0, n, max(1, n // 10)):
        x = x0 + int(round((k + 0.5) / n * (x1 - x0)))
        cv2.putText(img, str(k), (x - 5, y1 + 18), font, 0.4, black, 1, cv2.LINE_AA)
    cv2.putText(img, "trial", ((x0 + x1) // 2 - 15, y1 + 40), font, 0.45, black, 1, cv2.LINE_AA)
    # ---- importances
    bx0, by0, bx1 = 900, 60, W - 30
    cv2.putText(img, "parameter importance (fANOVA)", (680, by0 - 10), font, 0.45, black, 1, cv2.LINE_AA)
    if importances:
        items = sorted(importances.items(), key=lambda kv: -kv[1])[:12]
        row = min(34, (H - 100) // max(1, len(items)))
        top = max(v for _, v in items) or 1.0
        for k, (name, v) in enumerate(items):
            y = by0 + 10 + k * row
            cv2.putText(img, _short(name)[:34], (680, y + row // 2 + 4), font, 0.4, black, 1, cv2.LINE_AA)
            w = int(round(v / top * (bx1 - bx0 - 50)))
            cv2.rectangle(img, (bx0, y + 4), (bx0 + max(w, 1), y + row - 4), blue, -1)
            cv2.putText(img, f"{v:.2f}", (bx0 + w + 5, y + row // 2 + 4), font, 0.4, black, 1, cv2.LINE_AA)
    else:
        cv2.putText(img, "(needs at least 3 completed trials)", (680, by0 + 30), font, 0.45, grey, 1, cv2.LINE_AA)
    return write_png(path, img)
