"""`carto tune` as a library call: the base profile's search space unless one is given (gmapping's with
``--algorithm gmapping``), then ``tuning.tune``."""
from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path

from carto_cli.gmapping import GMAPPING_PIPELINE
from carto_cli.tuning.space import default_space_path, spaces_dir
from carto_cli.tuning.study import TuneResult, tune

__all__ = ["run_tune", "summary_line"]


def run_tune(
    recordings: Sequence,
    out: Path,
    *,
    space: Path | None = None,
    trials: int = 20,
    objective: str = "auto",
    relations: Sequence | None = None,
    ground_truth: Sequence | None = None,
    profile: str | None = None,
    overrides: Sequence[str] = (),
    time_weight: float = 0.0,
    storage: str | None = None,
    study: str | None = None,
    n_jobs: int = 1,
    seed: int | None = None,
    max_scans: int | None = None,
    on_trial: Callable[[int, float | None, float | None], None] | None = None,
    algorithm: str = "cartographer",
    force: bool = False,
) -> TuneResult:
    """Run (or resume) the study and write the tuned profile ``out`` with its CSV and report PNG; every trial
    maps with ``algorithm``."""
    if space is not None:
        space_path = space
    elif algorithm in GMAPPING_PIPELINE:
        # A profile's space varies Cartographer's options, which a gmapping trial would not use.
        space_path = spaces_dir() / "gmapping.yaml"
    else:
        space_path = default_space_path(profile)
    return tune(recordings, space_path, trials=trials, out=out, objective=objective, relations=relations,
                ground_truth=ground_truth, base_profile=profile, overrides=list(overrides),
                time_weight=time_weight, storage=storage, study_name=study, n_jobs=n_jobs, seed=seed,
                max_scans=max_scans, on_trial=on_trial, algorithm=algorithm, force=force)


def summary_line(result: TuneResult) -> str:
    base = "" if result.baseline_value is None else f" (base profile {result.baseline_value:.4g})"
    return (f"{result.n_trials} trials ({result.n_complete} complete, {result.n_pruned} pruned, "
            f"{result.n_failed} failed); best {result.objective} {result.best_value:.4g}{base} -> "
            f"{result.profile_path}, {result.csv_path.name}, {result.png_path.name}")
