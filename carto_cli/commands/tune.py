"""`carto tune` as a library call: the base profile's search space unless one is given (gmapping's with
``--algorithm gmapping``), then ``tuning.tune``."""
from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace

from carto_cli.gmapping import GMAPPING_PIPELINE
from carto_cli.tuning.space import default_space_path, spaces_dir
from carto_cli.tuning.study import StudyRequest, TuneResult, tune

__all__ = ["StudyRequest", "run_tune", "summary_line"]


def run_tune(
    request: StudyRequest,
    *,
    on_trial: Callable[[int, float | None, float | None], None] | None = None,
    force: bool = False,
) -> TuneResult:
    """Run (or resume) the study and write the tuned profile ``request.out`` with its CSV and report PNG; every
    trial maps with ``request.algorithm``."""
    if request.space is not None:
        space_path = request.space
    elif request.algorithm in GMAPPING_PIPELINE:
        # A profile's space varies Cartographer's options, which a gmapping trial would not use.
        space_path = spaces_dir() / "gmapping.yaml"
    else:
        space_path = default_space_path(request.profile)
    return tune(replace(request, space=space_path), on_trial=on_trial, force=force)


def summary_line(result: TuneResult) -> str:
    base = "" if result.baseline_value is None else f" (base profile {result.baseline_value:.4g})"
    return (f"{result.n_trials} trials ({result.n_complete} complete, {result.n_pruned} pruned, "
            f"{result.n_failed} failed); best {result.objective} {result.best_value:.4g}{base} -> "
            f"{result.profile_path}, {result.csv_path.name}, {result.png_path.name}")
