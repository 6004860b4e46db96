"""`carto eval` as a library call: score a trajectory, and gate the score when limits are given."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from carto_cli.core.errors import CartoError
from carto_cli.evaluation.gates import GateResult, accuracy_gates
from carto_cli.evaluation.metrics import AteResult, Evaluation, ate_sessions, evaluate, to_json
from carto_cli.io.trajectory import read_trajectory

__all__ = ["EvalRun", "SessionsEvalRun", "run_eval", "run_eval_sessions"]


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


@dataclass
class SessionsEvalRun:
    results: list[AteResult]  # per trajectory, under one alignment
    data: dict
    gates: list[GateResult] | None

    def lines(self) -> list[str]:
        """One line per trajectory: its ATE in the common frame."""
        out = []
        for entry, r in zip(self.data["sessions"], self.results):
            out.append(f"{entry['trajectory']}: ATE {r.translation.rmse:.4f} m RMSE (max {r.translation.max:.4f}), "
                       f"{r.rotation.rmse:.3f} deg RMSE, {r.used} poses")
        return out


def run_eval_sessions(trajectories: list[Path], ground_truths: list[Path], *, max_trans_error: float | None = None,
                      max_rot_error: float | None = None) -> SessionsEvalRun:
    """ATE of several trajectories of one map (``carto map A B ...``'s trajectory_N.tum) in their common frame: one
    alignment over all, then each one's errors; ``ground_truths`` one for all or one per trajectory. Gated on the
    worst trajectory's ATE RMSE."""
    if not ground_truths:
        raise CartoError("several trajectories are scored by ATE in their common frame: give --ground-truth FILE")
    results = ate_sessions([read_trajectory(t) for t in trajectories], [read_trajectory(g) for g in ground_truths])
    worst = max(range(len(results)), key=lambda k: results[k].translation.rmse)
    data = {"schema_version": 1, "trajectory": None, "relations": None, "rpe": None,
            "ate": to_json(results[worst]),  # the worst one: what the gates read
            "sessions": [{"trajectory": str(t), "ate": to_json(r)} for t, r in zip(trajectories, results)]}
    gates = None
    if max_trans_error is not None or max_rot_error is not None:
        gates = accuracy_gates(data, max_trans_error, max_rot_error)
    return SessionsEvalRun(results, data, gates)
