"""`carto eval` as a library call: score a trajectory, and gate the score when limits are given."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from carto_cli.core.errors import CartoError
from carto_cli.evaluation.gates import GateResult, accuracy_gates
from carto_cli.evaluation.metrics import Evaluation, evaluate, to_json

__all__ = ["EvalRun", "run_eval"]


@dataclass
class EvalRun:
    result: Evaluation
    data: dict  # the JSON form of ``result``
    gates: list[GateResult] | None  # None when no limit was given


def run_eval(trajectory: Path, *, relations: Path | None = None, ground_truth: Path | None = None,
             rpe_delta: float = 1.0, max_trans_error: float | None = None,
             max_rot_error: float | None = None) -> EvalRun:
    """Relation error with ``relations``, ATE and RPE (every ``rpe_delta`` s) with ``ground_truth``;
    gated on the mean relation error, else the ATE RMSE (m), and the rotational error (degrees)."""
    if relations is None and ground_truth is None:
        raise CartoError("give --relations FILE and/or --ground-truth FILE")
    result = evaluate(trajectory, relations=relations, groundtruth=ground_truth,
                      rpe_delta=rpe_delta if ground_truth is not None else None)
    data = to_json(result)
    gates = None
    if max_trans_error is not None or max_rot_error is not None:
        gates = accuracy_gates(data, max_trans_error, max_rot_error)
    return EvalRun(result, data, gates)
