"""Trajectory accuracy: relation error, ATE after SE(2) alignment, RPE.

Relation error is the metric of the bench cases (Kümmerle et al. 2009, see
data/README.md): for each relation ``t1 t2 dx dy dz droll dpitch dyaw`` the
trajectory's own pose of t2 in the frame of t1, with poses interpolated at those
times (linear in x, y; shortest arc in yaw), is compared with the relation. The
translational error is the norm of the difference of the two translations, which
in 2D equals the translation of ``relation⁻¹ · estimate``; the rotational one the
wrapped yaw difference. Relations with a time outside the trajectory are skipped
and counted, never extrapolated.

Everything is vectorised over relations / poses; the only loops are over a handful
of metrics.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from carto_cli.core.errors import CartoError
from carto_cli.core.transform import wrap_angle
from carto_cli.io.trajectory import Trajectory, parse_table, read_trajectory

__all__ = [
    "TIME_TOLERANCE",
    "AteResult",
    "ErrorStats",
    "Evaluation",
    "RelationResult",
    "Relations",
    "RpeResult",
    "align_se2",
    "ate",
    "ate_sessions",
    "evaluate",
    "format_table",
    "interpolate_poses",
    "read_relations",
    "relation_error",
    "rpe",
    "to_json",
]

# Times written with 6-9 decimals and read back may land a rounding error outside
# the trajectory's span; that is not a reason to skip the first or last relation.
TIME_TOLERANCE = 1e-6


# --------------------------------------------------------------------------- statistics


@dataclass(frozen=True)
class ErrorStats:
    """Summary of error magnitudes. ``std`` is the population standard deviation."""

    n: int
    mean: float
    std: float
    rmse: float
    median: float
    max: float

    @classmethod
    def of(cls, errors: np.ndarray) -> ErrorStats:
        e = np.asarray(errors, dtype=np.float64)
        if e.size == 0:
            nan = math.nan
            return cls(0, nan, nan, nan, nan, nan)
        return cls(int(e.size), float(e.mean()), float(e.std()), float(np.sqrt(np.mean(e * e))),
                   float(np.median(e)), float(e.max()))

    def to_dict(self) -> dict:
        return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                for k, v in self.__dict__.items()}


# --------------------------------------------------------------------------- relations and interpolation


@dataclass(frozen=True, eq=False)
class Relations:
    """Relative poses ``d`` (m, 3: dx dy dyaw) of the pose at ``t2`` in the frame of the pose at ``t1``."""

    t1: np.ndarray
    t2: np.ndarray
    d: np.ndarray

    def __len__(self) -> int:
        return int(self.t1.shape[0])


def read_relations(path: str | Path) -> Relations:
    """A Kümmerle-style relations file: ``t1 t2 dx dy dz droll dpitch dyaw`` per line."""
    data, _ = parse_table(path, (8,), "relations")
    return Relations(data[:, 0].copy(), data[:, 1].copy(), data[:, [2, 3, 7]].copy())


def interpolate_poses(traj: Trajectory, times, tolerance: float = TIME_TOLERANCE,
                      max_gap: float | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poses of ``traj`` at ``times``: (xy (m, 2), theta (m,), valid (m,) bool).

    x, y are linear in time and yaw follows the shorter arc between neighbours.
    ``valid`` is false for times outside the trajectory (beyond ``tolerance``) and,
    with ``max_gap``, for times between poses more than ``max_gap`` seconds apart.
    """
    times = np.asarray(times, dtype=np.float64).reshape(-1)
    n = len(traj)
    m = times.shape[0]
    if n == 0:
        return np.full((m, 2), np.nan), np.full(m, np.nan), np.zeros(m, dtype=bool)
    t = traj.t
    valid = (times >= t[0] - tolerance) & (times <= t[-1] + tolerance)
    if n == 1:
        return np.repeat(traj.xy, m, axis=0), np.repeat(traj.theta, m), valid
    tc = np.clip(times, t[0], t[-1])
    i = np.clip(np.searchsorted(t, tc, side="right") - 1, 0, n - 2)
    dt = t[i + 1] - t[i]
    a = (tc - t[i]) / dt
    xy = traj.xy[i] + a[:, None] * (traj.xy[i + 1] - traj.xy[i])
    theta = traj.theta[i] + a * wrap_angle(traj.theta[i + 1] - traj.theta[i])
    if max_gap is not None:
        exact = (a == 0.0) | (a == 1.0)
        valid &= exact | (dt <= max_gap)
    return xy, theta, valid


def _relative(xy1, th1, xy2, th2) -> tuple[np.ndarray, np.ndarray]:
    """Pose 2 in the frame of pose 1: (dxy (m, 2), dtheta (m,))."""
    d = xy2 - xy1
    c, s = np.cos(th1), np.sin(th1)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
    return local, wrap_angle(th2 - th1)


def _motion_errors(est_dxy, est_dth, ref_dxy, ref_dth) -> tuple[np.ndarray, np.ndarray]:
    """Translational (m) and rotational (deg) error magnitudes of relative motions."""
    trans = np.linalg.norm(est_dxy - ref_dxy, axis=1)
    rot = np.degrees(np.abs(wrap_angle(est_dth - ref_dth)))
    return trans, rot


# --------------------------------------------------------------------------- results


@dataclass(frozen=True, eq=False)
class RelationResult:
    translation: ErrorStats          # metres
    rotation: ErrorStats             # degrees
    used: int
    skipped: int                     # relations with a time outside the trajectory
    translation_errors: np.ndarray = field(repr=False)   # per used relation, metres
    rotation_errors: np.ndarray = field(repr=False)      # degrees
    used_mask: np.ndarray = field(repr=False)            # over all relations


@dataclass(frozen=True, eq=False)
class AteResult:
    translation: ErrorStats          # metres, after alignment
    rotation: ErrorStats             # degrees, after alignment
    used: int
    skipped: int                     # reference poses with no trajectory pose to compare with
    aligned: bool
    associate: str                   # 'groundtruth' or 'trajectory': whose timestamps were used
    alignment: tuple[float, float, float]   # (tx, ty, theta) applied to the trajectory
    translation_errors: np.ndarray = field(repr=False)
    rotation_errors: np.ndarray = field(repr=False)


@dataclass(frozen=True, eq=False)
class RpeResult:
    translation: ErrorStats
    rotation: ErrorStats
    used: int
    delta: float
    unit: str                        # 's' or 'frames'
    translation_errors: np.ndarray = field(repr=False)
    rotation_errors: np.ndarray = field(repr=False)


@dataclass(frozen=True, eq=False)
class Evaluation:
    trajectory: str | None = None
    relations: RelationResult | None = None
    ate: AteResult | None = None
    rpe: RpeResult | None = None


# --------------------------------------------------------------------------- metrics


def relation_error(traj: Trajectory, relations: Relations, max_gap: float | None = None) -> RelationResult:
    """Relation error of ``traj``; relations outside its time span are skipped and counted."""
    xy1, th1, v1 = interpolate_poses(traj, relations.t1, max_gap=max_gap)
    xy2, th2, v2 = interpolate_poses(traj, relations.t2, max_gap=max_gap)
    used = v1 & v2
    n_used = int(used.sum())
    if n_used == 0:
        lo, hi = traj.span
        raise CartoError(f"no relation falls within the trajectory's time span {lo:.3f}..{hi:.3f} s "
                         f"({len(relations)} relations): is it the right relations file?")
    est_dxy, est_dth = _relative(xy1[used], th1[used], xy2[used], th2[used])
    trans, rot = _motion_errors(est_dxy, est_dth, relations.d[used, :2], relations.d[used, 2])
    return RelationResult(ErrorStats.of(trans), ErrorStats.of(rot), n_used, len(relations) - n_used,
                          trans, rot, used)


def _associate(traj: Trajectory, groundtruth: Trajectory, associate: str, max_gap: float | None):
    """(times, est xy, est theta, gt xy, gt theta, skipped) at the chosen side's timestamps."""
    if associate == "groundtruth":
        xy, th, ok = interpolate_poses(traj, groundtruth.t, max_gap=max_gap)
        return groundtruth.t[ok], xy[ok], th[ok], groundtruth.xy[ok], groundtruth.theta[ok], int((~ok).sum())
    if associate == "trajectory":
        xy, th, ok = interpolate_poses(groundtruth, traj.t, max_gap=max_gap)
        return traj.t[ok], traj.xy[ok], traj.theta[ok], xy[ok], th[ok], int((~ok).sum())
    raise CartoError(f"associate must be 'groundtruth' or 'trajectory', got {associate!r}")


def align_se2(source: np.ndarray, target: np.ndarray) -> tuple[float, float, float]:
    """(tx, ty, theta) minimising Σ|R·source + t − target|² (Horn/Umeyama in the plane, no scale)."""
    ms, mt = source.mean(axis=0), target.mean(axis=0)
    p, q = source - ms, target - mt
    theta = math.atan2(float(np.sum(p[:, 0] * q[:, 1] - p[:, 1] * q[:, 0])),
                       float(np.sum(p[:, 0] * q[:, 0] + p[:, 1] * q[:, 1])))
    c, s = math.cos(theta), math.sin(theta)
    tx = mt[0] - (c * ms[0] - s * ms[1])
    ty = mt[1] - (s * ms[0] + c * ms[1])
    return float(tx), float(ty), theta


def ate(traj: Trajectory, groundtruth: Trajectory, align: bool = True, associate: str = "groundtruth",
        max_gap: float | None = None) -> AteResult:
    """Absolute trajectory error, after the SE(2) alignment that minimises it (unless ``align`` is false)."""
    _, exy, eth, gxy, gth, skipped = _associate(traj, groundtruth, associate, max_gap)
    if exy.shape[0] < 2:
        raise CartoError(f"ATE needs at least 2 poses common to the trajectory and the ground truth, "
                         f"got {exy.shape[0]}: do their time spans overlap?")
    tx, ty, phi = align_se2(exy, gxy) if align else (0.0, 0.0, 0.0)
    c, s = math.cos(phi), math.sin(phi)
    axy = np.stack([c * exy[:, 0] - s * exy[:, 1] + tx, s * exy[:, 0] + c * exy[:, 1] + ty], axis=1)
    trans = np.linalg.norm(axy - gxy, axis=1)
    rot = np.degrees(np.abs(wrap_angle(eth + phi - gth)))
    return AteResult(ErrorStats.of(trans), ErrorStats.of(rot), int(trans.size), skipped, align, associate,
                     (tx, ty, phi), trans, rot)


def rpe(traj: Trajectory, groundtruth: Trajectory, delta: float = 1.0, unit: str = "s",
        max_gap: float | None = None) -> RpeResult:
    """Relative pose error over ``delta`` seconds or frames, at the ground truth's timestamps.

    With seconds, each reference pose is paired with the first one at least ``delta``
    later; with frames, with the one ``delta`` samples later.
    """
    times, exy, eth, gxy, gth, _ = _associate(traj, groundtruth, "groundtruth", max_gap)
    n = times.shape[0]
    if unit in ("frames", "frame", "f"):
        unit = "frames"
        step = int(delta)
        if step != delta or step < 1:
            raise CartoError(f"an RPE delta in frames must be a positive integer, got {delta}")
        i = np.arange(max(n - step, 0))
        j = i + step
    elif unit in ("s", "seconds", "sec"):
        unit = "s"
        if not delta > 0:
            raise CartoError(f"an RPE delta in seconds must be positive, got {delta}")
        j_all = np.searchsorted(times, times + delta - TIME_TOLERANCE, side="left")
        i = np.nonzero(j_all < n)[0]
        j = j_all[i]
    else:
        raise CartoError(f"RPE delta unit must be 's' or 'frames', got {unit!r}")
    if i.size == 0:
        raise CartoError(f"no pose pairs {delta:g} {unit} apart within the common time span")
    est_dxy, est_dth = _relative(exy[i], eth[i], exy[j], eth[j])
    ref_dxy, ref_dth = _relative(gxy[i], gth[i], gxy[j], gth[j])
    trans, rot = _motion_errors(est_dxy, est_dth, ref_dxy, ref_dth)
    return RpeResult(ErrorStats.of(trans), ErrorStats.of(rot), int(i.size), float(delta), unit, trans, rot)


def _load_traj(x: Trajectory | str | Path) -> Trajectory:
    return x if isinstance(x, Trajectory) else read_trajectory(x)


def evaluate(trajectory: Trajectory | str | Path, relations: Relations | str | Path | None = None,
             groundtruth: Trajectory | str | Path | None = None, *, align: bool = True,
             associate: str = "groundtruth", rpe_delta: float | None = None, rpe_unit: str = "s",
             max_gap: float | None = None) -> Evaluation:
    """Every metric the inputs allow: relation error with ``relations``; ATE and RPE with ``groundtruth``."""
    if relations is None and groundtruth is None:
        raise CartoError("nothing to evaluate against: give relations and/or a ground-truth trajectory")
    name = None if isinstance(trajectory, Trajectory) else str(trajectory)
    traj = _load_traj(trajectory)
    rel_result = None
    if relations is not None:
        rel = relations if isinstance(relations, Relations) else read_relations(relations)
        rel_result = relation_error(traj, rel, max_gap=max_gap)
    ate_result = rpe_result = None
    if groundtruth is not None:
        gt = _load_traj(groundtruth)
        ate_result = ate(traj, gt, align=align, associate=associate, max_gap=max_gap)
        if rpe_delta is not None:
            rpe_result = rpe(traj, gt, rpe_delta, rpe_unit, max_gap=max_gap)
    return Evaluation(name, rel_result, ate_result, rpe_result)


def ate_sessions(trajectories: Sequence[Trajectory], groundtruths: Sequence[Trajectory], *,
                 associate: str = "groundtruth", max_gap: float | None = None) -> list[AteResult]:
    """ATE of several trajectories of one map (sessions) in their common frame: ONE SE(2) alignment over all of them
    (a session misplaced against the others shows, which aligning each alone would hide), then each one's errors.
    ``groundtruths``: one per trajectory, or one for all (a recording cut into sessions)."""
    if len(groundtruths) not in (1, len(trajectories)):
        raise CartoError(f"give one ground truth, or one per trajectory ({len(trajectories)}), "
                         f"not {len(groundtruths)}")
    refs = list(groundtruths) * len(trajectories) if len(groundtruths) == 1 else list(groundtruths)
    pairs = [_associate(t, g, associate, max_gap) for t, g in zip(trajectories, refs)]
    if sum(p[1].shape[0] for p in pairs) < 2:
        raise CartoError("ATE needs at least 2 poses common to the trajectories and the ground truth")
    tx, ty, phi = align_se2(np.concatenate([p[1] for p in pairs]), np.concatenate([p[3] for p in pairs]))
    c, s = math.cos(phi), math.sin(phi)
    out = []
    for _, exy, eth, gxy, gth, skipped in pairs:
        axy = np.stack([c * exy[:, 0] - s * exy[:, 1] + tx, s * exy[:, 0] + c * exy[:, 1] + ty], axis=1)
        trans = np.linalg.norm(axy - gxy, axis=1)
        rot = np.degrees(np.abs(wrap_angle(eth + phi - gth)))
        out.append(AteResult(ErrorStats.of(trans), ErrorStats.of(rot), int(trans.size), skipped, True, associate,
                             (tx, ty, phi), trans, rot))
    return out


# --------------------------------------------------------------------------- formatting


def to_json(result: Evaluation | RelationResult | AteResult | RpeResult) -> dict:
    """JSON-ready dict (NaN as null, no per-pose arrays)."""
    if isinstance(result, Evaluation):
        return {
            "schema_version": 1,
            "trajectory": result.trajectory,
            "relations": None if result.relations is None else to_json(result.relations),
            "ate": None if result.ate is None else to_json(result.ate),
            "rpe": None if result.rpe is None else to_json(result.rpe),
        }
    out: dict = {"translation_m": result.translation.to_dict(), "rotation_deg": result.rotation.to_dict(),
                 "used": result.used}
    if isinstance(result, RelationResult):
        out["skipped"] = result.skipped
    elif isinstance(result, AteResult):
        tx, ty, th = result.alignment
        out.update(skipped=result.skipped, aligned=result.aligned, associate=result.associate,
                   alignment={"tx": tx, "ty": ty, "theta": th})
    elif isinstance(result, RpeResult):
        out.update(delta=result.delta, unit=result.unit)
    else:
        raise TypeError(f"cannot format {type(result).__name__}")
    return out


def _rows(label: str, r, extra: str) -> list[tuple[str, ...]]:
    rows: list[tuple[str, ...]] = []
    for kind, stats, unit, spec in (("trans", r.translation, "m", ".4f"), ("rot", r.rotation, "deg", ".3f")):
        rows.append((f"{label} {kind} [{unit}]", str(stats.n), format(stats.mean, spec), format(stats.std, spec),
                     format(stats.rmse, spec), format(stats.median, spec), format(stats.max, spec),
                     extra if kind == "trans" else ""))
    return rows


def format_table(result: Evaluation | RelationResult | AteResult | RpeResult) -> str:
    """An aligned text table: one line per metric, mean ± std and more."""
    ev = result if isinstance(result, Evaluation) else Evaluation(
        relations=result if isinstance(result, RelationResult) else None,
        ate=result if isinstance(result, AteResult) else None,
        rpe=result if isinstance(result, RpeResult) else None)
    rows: list[tuple[str, ...]] = []
    if ev.relations is not None:
        rows += _rows("relations", ev.relations, f"{ev.relations.skipped} skipped")
    if ev.ate is not None:
        note = "aligned" if ev.ate.aligned else "not aligned"
        if ev.ate.skipped:
            note += f", {ev.ate.skipped} skipped"
        rows += _rows("ATE", ev.ate, note)
    if ev.rpe is not None:
        rows += _rows(f"RPE {ev.rpe.delta:g}{'s' if ev.rpe.unit == 's' else ' frames'}", ev.rpe, "")
    header = ("metric", "n", "mean", "std", "rmse", "median", "max", "")
    widths = [max(len(r[i]) for r in rows + [header]) for i in range(len(header))]
    lines = [] if ev.trajectory is None else [f"trajectory: {ev.trajectory}"]
    for r in [header] + rows:
        cells = [r[0].ljust(widths[0])] + [r[i].rjust(widths[i]) for i in range(1, 7)] + [r[7]]
        lines.append("  ".join(cells).rstrip())
    return "\n".join(lines) + "\n"
