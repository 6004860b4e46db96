"""``carto tune``: search option values that map given recordings best (Optuna).

The objectives (what a trial scores) are in ``tuning.objectives``, the outputs (profile,
trials CSV, report PNG) in ``tuning.report``; this module runs the study.

Engine: TPE sampler (seeded), median pruner fed the running mean after each recording
(so with several recordings a hopeless trial stops early; with one there is nothing to
prune on), SQLite storage next to the output by default so that rerunning the same
command resumes the study. ``n_jobs`` > 1 starts ``n_jobs − 1`` worker processes that
share the storage with this one (numba-heavy Python does not parallelise in threads).
A trial whose pipeline raises is recorded as failed and the study goes on. Ctrl-C (or SIGTERM)
stops after the running trial and the outputs are written from the trials so far
(``TuneResult.interrupted``); a second one stops the running trial at once, recorded as pruned,
never as failed.
"""
from __future__ import annotations

import math
import multiprocessing as mp
import os
import signal
from collections.abc import Callable, Sequence
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path
from typing import Any

import carto_cli.pipeline  # noqa: F401  (imports every mapping kernel, registering its warm-up)
from carto_cli.core import interrupts, kernels
from carto_cli.core.errors import CartoError
from carto_cli.gmapping import ALGORITHMS, GMAPPING_PIPELINE
from carto_cli.io.atomic import output_set
from carto_cli.options import Options, apply_overrides, load_options
from carto_cli.tuning.objectives import (
    Case,
    SessionsCase,
    check_space,
    evaluate_options,
    make_cases,
    prepare,
    resolve_objective,
)
from carto_cli.tuning.report import draw_report, write_profile, write_trials_csv
from carto_cli.tuning.space import Param, base_values, load_space, suggest_params

__all__ = ["StudyRequest", "TuneResult", "tune"]


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
    interrupted: bool = False  # Ctrl-C or SIGTERM stopped the study early; the profile is the best so far


_STOP = {"requested": False, "announce": True}
_STOP_SIGNALS = interrupts.STOP_SIGNALS


def _on_stop_signal(signum, frame):
    """First Ctrl-C (or SIGTERM): finish the running trial, then stop and write the best profile so far. A
    second one interrupts the running trial at once; it is recorded as pruned (user attribute ``interrupted``),
    never as failed."""
    if _STOP["requested"]:
        interrupts.record()  # what this raises may surface as another error (numba's SystemError around it)
        raise KeyboardInterrupt
    _STOP["requested"] = True
    if _STOP["announce"]:
        os.write(2, b"carto: tune: interrupted; finishing the running trial, then writing the best profile so far "
                    b"(Ctrl-C again to stop now)\n")


@dataclass
class _Job:
    storage: str
    study_name: str
    params: list[Param]
    base: Options
    cases: list[Case | SessionsCase]
    objective: str
    time_weight: float
    max_scans: int | None
    seed: int | None
    startup: int
    algorithm: str = "cartographer"


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
                                              time_weight=job.time_weight, report=report, algorithm=job.algorithm)
        except optuna.TrialPruned:
            raise
        except (KeyboardInterrupt, Exception) as e:
            if not interrupts.is_interrupt(e):  # recorded on the failed trial, the study goes on
                trial.set_user_attr("error", f"{type(e).__name__}: {e}"[:500])
                raise
            # Stopped from outside (the second Ctrl-C may land in compiled code and come out as a SystemError),
            # not a failure of these options: pruned, so the sampler does not learn from it and the study shows
            # no failed trial.
            _STOP["requested"] = True
            trial.set_user_attr("interrupted", True)
            raise optuna.TrialPruned("interrupted") from None
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
    except KeyboardInterrupt:  # between trials (sampling, storage): no trial is running
        _STOP["requested"] = True


def _worker_main(job: _Job, worker: int, n_trials: int) -> None:  # pragma: no cover - runs in a child
    _STOP["requested"] = False
    _STOP["announce"] = False  # the parent says it once
    interrupts.clear()
    for sig in _STOP_SIGNALS:
        signal.signal(sig, _on_stop_signal)
    _run(job, worker, n_trials)


def _default_storage(out: Path) -> str:
    return "sqlite:///" + str(out.resolve().with_name(out.stem + ".optuna.db"))


@dataclass(frozen=True, slots=True)
class StudyRequest:
    """One study, as ``carto tune`` asks for it: what to map, which options to vary (``space``), what to score
    them by and where the trials are kept. Built once (by the CLI, or a library caller) and handed to
    :func:`carto_cli.commands.tune.run_tune` / :func:`tune`.

    ``recordings`` are paths (or Recording objects); ``relations`` / ``ground_truth`` one per recording (paths;
    ground truths may also be (m, 4) t x y yaw arrays). ``space`` is a search-space file or dict (see
    ``tuning.space``); None lets ``run_tune`` take the base profile's (gmapping's with ``algorithm`` gmapping).
    ``storage`` defaults to ``sqlite:///<out dir>/<out stem>.optuna.db`` and ``study_name`` to the out stem, so
    the same request resumes. Every trial maps with ``algorithm`` (``carto_cli.gmapping.ALGORITHMS``);
    ``sessions``: the recordings are sessions of one building, mapped together and scored in the map's one frame
    (``tuning.objectives``).

    The values that can be judged without reading anything are checked here (CartoError), so a bad request
    fails before any recording is opened.
    """

    recordings: Sequence
    out: Path
    _: KW_ONLY
    space: Path | str | dict | None = None
    trials: int = 20
    objective: str = "auto"
    relations: Sequence | None = None
    ground_truth: Sequence | None = None
    profile: str | Path | None = None
    overrides: Sequence[str] | dict = ()
    time_weight: float = 0.0
    storage: str | None = None
    study_name: str | None = None
    n_jobs: int = 1
    seed: int | None = None
    max_scans: int | None = None
    algorithm: str = "cartographer"
    sessions: bool = False  # the recordings are sessions of one building: every trial maps them into one map

    def __post_init__(self) -> None:
        object.__setattr__(self, "out", Path(self.out))
        if self.trials < 1:
            raise CartoError(f"--trials must be at least 1, got {self.trials}")
        if self.n_jobs < 1:
            raise CartoError(f"--n-jobs must be at least 1, got {self.n_jobs}")
        if self.time_weight < 0 or not math.isfinite(self.time_weight):
            raise CartoError(f"--time-weight must be a non-negative number, got {self.time_weight}")
        if self.max_scans is not None and self.max_scans < 1:
            raise CartoError(f"--max-scans must be at least 1, got {self.max_scans}")
        if self.algorithm not in ALGORITHMS:
            raise CartoError(f"--algorithm: unknown algorithm '{self.algorithm}' "
                             f"(choose from {', '.join(ALGORITHMS)})")
        if self.sessions and self.algorithm in GMAPPING_PIPELINE:
            raise CartoError(f"--sessions maps the recordings into one Cartographer pose graph; {self.algorithm} "
                             "maps one recording (use --algorithm cartographer)")


def tune(
    request: StudyRequest,
    *,
    on_trial: Callable[[int, float | None, float | None], None] | None = None,
    force: bool = False,
) -> TuneResult:
    """Run (or resume) the study ``request`` of ``request.trials`` more trials and write the tuned profile
    ``request.out``, ``<out stem>.trials.csv`` and ``<out stem>.report.png`` next to it; a study keeps the
    algorithm it was started with.

    ``on_trial(number, value or None, best value or None)`` is called after every trial this process runs.
    Raises CartoError for bad inputs and when no trial completed. An existing ``out`` is replaced when it belongs
    to the study being resumed, or with ``force``.
    """
    import optuna

    if request.space is None:
        raise ValueError("tune needs a search space (run_tune picks the base profile's)")
    out, trials, n_jobs, algorithm = request.out, request.trials, request.n_jobs, request.algorithm
    base_profile, overrides = request.profile, request.overrides
    params = load_space(request.space)
    base = load_options(base_profile, []) if isinstance(overrides, dict) else load_options(base_profile, overrides)
    if isinstance(overrides, dict):
        base = apply_overrides(base, overrides)
    cases = make_cases(request.recordings, request.relations, request.ground_truth, sessions=request.sessions)
    objective = resolve_objective(request.objective, cases)
    check_space(objective, [p.name for p in params], algorithm)
    prepare(cases, objective, base, request.max_scans, algorithm)
    if request.time_weight > 0:
        # Kernels load (or compile) before the first trial, so its time is not the compiler's.
        kernels.warm_up()

    storage = request.storage or _default_storage(out)
    study_name = request.study_name or out.stem
    out.parent.mkdir(parents=True, exist_ok=True)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    if out.exists() and not force and not _has_trials(storage, study_name):
        # A rerun of the same study (resuming it) rewrites its own profile; any other file is kept.
        raise CartoError(f"exists and is not the output of study '{study_name}' in {storage}; --force replaces it, "
                         "or give another -o", out)
    try:
        study = optuna.create_study(study_name=study_name, storage=_storage(storage), direction="minimize",
                                    load_if_exists=True)
    except ModuleNotFoundError as e:
        # SQLAlchemy imports the database driver only when it connects (psycopg for postgresql:// since 2.1).
        raise CartoError(f"cannot open the study storage {storage}: the database driver '{e.name}' is not "
                         f"installed (pip install \"carto-slam[postgres]\" installs psycopg for PostgreSQL)") from None
    except Exception as e:
        raise CartoError(f"cannot open the study storage {storage}: {e}") from None
    # Studies from before --algorithm carry no name: they mapped with Cartographer.
    started_with = study.user_attrs.get("algorithm", "cartographer" if study.trials else algorithm)
    if started_with != algorithm:
        raise CartoError(f"study '{study_name}' in {storage} maps with {started_with}, not {algorithm}: resume it "
                         "with the same --algorithm, or start another study (--study NAME or another -o)")
    if not study.trials:
        study.set_user_attr("algorithm", algorithm)
        baseline = base_values(base, params)
        if baseline:
            study.enqueue_trial(baseline, user_attrs={"baseline": True})
    job = _Job(storage, study_name, params, base, cases, objective, request.time_weight, request.max_scans,
               request.seed, startup=max(3, min(10, trials // 2)), algorithm=algorithm)

    _STOP["requested"] = False
    _STOP["announce"] = True
    interrupts.clear()  # an earlier run's interrupt (a library caller's) is not this study's
    in_main = _is_main_thread()
    previous = {sig: signal.getsignal(sig) for sig in _STOP_SIGNALS} if in_main else {}
    for sig in previous:
        signal.signal(sig, _on_stop_signal)
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
            ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else mp.get_context("spawn")
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
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    interrupted = _STOP["requested"]
    return _finish(study_name, storage, job, out, objective, base_profile, overrides, interrupted=interrupted)


def _has_trials(storage: str, study_name: str) -> bool:
    """Whether ``storage`` holds study ``study_name`` with at least one trial (without creating it)."""
    import optuna

    if storage.startswith("sqlite:///") and not Path(storage[len("sqlite:///"):]).is_file():
        return False  # asking would create the database file
    try:
        summaries = optuna.get_all_study_summaries(storage=_storage(storage), include_best_trial=False)
    except Exception:  # no database yet, or one that is not a study's: nothing to resume
        return False
    return any(s.study_name == study_name and s.n_trials > 0 for s in summaries)


def _is_main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


def _finish(study_name: str, storage: str, job: _Job, out: Path, objective: str, base_profile, overrides, *,
            interrupted: bool = False) -> TuneResult:
    import optuna

    study = optuna.load_study(study_name=study_name, storage=storage)
    trials = study.get_trials(deepcopy=False)
    complete = [t for t in trials if t.state == optuna.trial.TrialState.COMPLETE]
    if interrupted and not complete:
        raise KeyboardInterrupt  # nothing to write: stopped before any trial completed
    stem = out.with_suffix("") if out.suffix in (".yaml", ".yml") else out
    csv_path = stem.parent / (stem.name + ".trials.csv")
    png_path = stem.parent / (stem.name + ".report.png")
    if not complete:
        write_trials_csv(csv_path, trials)  # what went wrong, trial by trial
        errors = {t.user_attrs["error"] for t in trials if t.user_attrs.get("error")}
        hint = f" (e.g. {sorted(errors)[0]})" if errors else ""
        raise CartoError(f"no trial completed out of {len(trials)}{hint}; see {csv_path}")
    importances: dict[str, float] = {}
    if len(complete) >= 3:
        try:
            importances = dict(optuna.importance.get_param_importances(study))
        except Exception:
            importances = {}
    best = study.best_trial
    options = apply_overrides(job.base, {p.name: best.params[p.name] for p in job.params if p.name in best.params})
    baseline = next((t.value for t in complete if t.user_attrs.get("baseline")), None)
    # The profile, the CSV and the report move into place together: never a new profile beside an old report
    with output_set(out.parent, [out.name, csv_path.name, png_path.name]) as staging:
        write_trials_csv(staging / csv_path.name, trials)
        draw_report(staging / png_path.name, trials, importances, title=f"carto tune: {study_name} ({objective})")
        write_profile(staging / out.name, options, best=best, objective=objective, n_trials=len(trials),
                      base_profile=base_profile, overrides=overrides, tuned=[p.name for p in job.params],
                      baseline=baseline, time_weight=job.time_weight, max_scans=job.max_scans,
                      algorithm=job.algorithm)
    state = optuna.trial.TrialState
    return TuneResult(
        best_value=float(study.best_value), best_params=dict(best.params), n_trials=len(trials), profile_path=out,
        csv_path=csv_path, png_path=png_path, objective=objective, study_name=study_name, storage=storage,
        baseline_value=baseline, n_complete=len(complete),
        n_pruned=sum(t.state == state.PRUNED for t in trials), n_failed=sum(t.state == state.FAIL for t in trials),
        best_metrics={k: v for k, v in best.user_attrs.items() if k not in ("baseline",)},
        interrupted=interrupted,
    )
