"""``carto tune`` as a library: objectives (what a trial scores), the Optuna study, its report, search spaces."""
from carto_cli.tuning.study import TuneResult, tune

__all__ = ["TuneResult", "tune"]
