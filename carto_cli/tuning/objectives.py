"""The scores ``carto tune`` minimises: cases (a recording and its references), objective
resolution and scoring.

One trial = one set of option values (the base profile, ``overrides`` and what the
sampler drew from the search space), mapped on every recording through the same
``pipeline.build`` every other command runs (by the study's algorithm, Cartographer or
GMapping), scored by an objective, averaged over the recordings (lower is better):

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

Sessions (``carto tune --sessions``): the recordings are sessions of one building, and a trial maps them
together into one map, a trajectory each (``pipeline.map_sessions``), scored in that map's one frame:
relations averaged over the sessions; ground-truth as the ATE RMSE over every session's poses under ONE SE(2)
alignment (a session misplaced against the others counts); map-quality with the endpoint spread of all the
sessions' returns in one grid (sessions placed alike put their returns on the same walls). A session linked to
nothing adds ``UNLINKED_PENALTY`` (as a 1 m error): such a map is failed whatever its other scores. Relocalization
has no multi-session form.

``time_weight`` adds ``time_weight × wall seconds per scan`` of the mapping (numba
compilation excluded by a warm-up run) to every recording's score: with
``time_weight=10``, 10 ms per scan costs as much as 10 cm of relation error.
"""
from __future__ import annotations

import math
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from carto_cli.core.errors import CartoError
from carto_cli.evaluation.metrics import (
    Relations,
    align_se2,
    ate,
    ate_sessions,
    interpolate_poses,
    read_relations,
    relation_error,
)
from carto_cli.gmapping import GMAPPING_PIPELINE
from carto_cli.io.trajectory import Trajectory, read_trajectory
from carto_cli.options import Options

__all__ = ["OBJECTIVES", "OBJECTIVE_TEXT", "ROTATION_LEVER_M", "UNLINKED_PENALTY", "Case", "SessionsCase",
           "check_space", "endpoint_spread",
           "evaluate_options", "make_cases", "map_quality", "prepare", "resolve_objective", "score_case"]

OBJECTIVES = ("auto", "relations", "ground-truth", "relocalization", "map-quality")
ROTATION_LEVER_M = 1.0  # relations objective: metres per radian of rotational error
UNLINKED_PENALTY = 1.0  # sessions: what a session linked to nothing adds to any objective

RELOC_MAP_FRACTION = 0.7
RELOC_QUERIES = 20
RELOC_PRIOR_NOISE = (0.3, math.radians(3.0))
RELOC_SIGMAS = (0.5, math.radians(6.0))
RELOC_TOLERANCE = (0.3, math.radians(3.0))
RELOC_ALIGN_RADIUS = 4.0

GMAPPING_PREFIX = "gmapping."  # the options only --algorithm gmapping reads

# Options a map-quality score would reward for themselves rather than for a better map.
GRID_OPTIONS = ("trajectory_builder_2d.submaps.grid_options_2d.resolution",
                "trajectory_builder_2d.submaps.range_data_inserter.")

OBJECTIVE_TEXT = {
    "relations": "mean translational relation error (m) + 1 m x mean rotational relation error (rad)",
    "ground-truth": "ATE RMSE (m) after SE(2) alignment",
    "relocalization": "(1 - relocalization success rate) + mean latency (s) on held-out scans",
    "map-quality": "endpoint spread (distinct 5 cm cells hit per return) + mean loop-closure residual (m)",
}


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


@dataclass(eq=False)
class SessionsCase:
    """Recordings of one building mapped together into one map, a trajectory each (``--sessions``), with one
    reference per recording."""

    parts: tuple[Case, ...]

    @property
    def name(self) -> str:
        return " + ".join(p.name for p in self.parts)


def _parts(cases: Sequence[Case | SessionsCase]) -> list[Case]:
    """Every recording's case, those of sessions included."""
    return [p for c in cases for p in (c.parts if isinstance(c, SessionsCase) else (c,))]


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
               ground_truth: Sequence | None = None, *, sessions: bool = False) -> list[Case | SessionsCase]:
    """Cases from recordings (paths or Recording objects) and one relations / ground-truth per recording;
    ``sessions``: the recordings are sessions of one building, one case mapped together."""
    if not recordings:
        raise CartoError("tune needs at least one recording")
    if sessions and len(recordings) < 2:
        raise CartoError("--sessions maps several recordings into one map: give at least two")
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
    return [SessionsCase(tuple(cases))] if sessions else list(cases)


def resolve_objective(objective: str, cases: Sequence[Case | SessionsCase]) -> str:
    if objective not in OBJECTIVES:
        raise CartoError(f"unknown objective '{objective}' (one of {', '.join(OBJECTIVES)})")
    if objective == "relocalization" and any(isinstance(c, SessionsCase) for c in cases):
        raise CartoError("the relocalization objective scores one recording's map: drop --sessions, or choose "
                         "relations, ground-truth or map-quality")
    cases = _parts(cases)
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


def check_space(objective: str, names: Sequence[str], algorithm: str = "cartographer") -> None:
    """CartoError when the objective cannot judge some of the options a space varies, or the algorithm
    does not use them (a study over them would only measure noise)."""
    if algorithm in GMAPPING_PIPELINE and objective != "relocalization":
        # Relocalization searches map.carto's submaps, built with Cartographer's submap and relocalization
        # options; every other objective scores only the particle filter's trajectory and map.
        unused = [name for name in names if not name.startswith(GMAPPING_PREFIX)]
        if unused:
            raise CartoError(f"{algorithm} does not use {', '.join(unused)}: vary gmapping.* options "
                             "(e.g. the packaged spaces/gmapping.yaml, the default with --algorithm gmapping)")
    elif algorithm not in GMAPPING_PIPELINE:
        unused = [name for name in names if name.startswith(GMAPPING_PREFIX)]
        if unused:
            raise CartoError(f"{algorithm} does not use {', '.join(unused)}: tune them with --algorithm gmapping")
    if objective == "map-quality":
        bad = [name for name in names if name.startswith(GRID_OPTIONS)]
        if bad:
            raise CartoError(f"the map-quality objective scores the grid itself, so it cannot tune {', '.join(bad)} "
                             "(they would be tuned for sharper-looking cells, not a better map); "
                             "use relations or ground truth, or drop them from the space")


def _scans(recording, limit: int | None = None):
    from carto_cli.core.records import Scan
    from carto_cli.io.topics import select_topics, selected_records

    selection = select_topics(recording)  # several lasers' scans merged, as mapping reads them
    n = 0
    for rec in selected_records(recording, selection, list(selection.scan_topics)):
        if isinstance(rec, Scan):
            if limit is not None and n >= limit:
                return
            yield rec
            n += 1


def prepare(cases: Sequence[Case | SessionsCase], objective: str, base: Options, max_scans: int | None,
            algorithm: str = "cartographer") -> None:
    """What an objective computes once per recording, before any trial (relocalization reference, mapped
    by ``algorithm`` like the trials)."""
    if objective != "relocalization":
        return
    from carto_cli.pipeline import build

    for case in _parts(cases):
        case.n_scans = sum(1 for _ in _scans(case.recording(), max_scans))
        if case.n_scans < 10:
            raise CartoError(f"relocalization needs at least 10 scans, the recording has {case.n_scans}", case.name)
        if case.ground_truth is not None:
            case.reference = case.ground_truth
        else:
            full = build(case.recording(), base, max_scans=max_scans, algorithm=algorithm)
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
    keys, n_points = _endpoint_cells(result.times, result.poses, result.laser_pose, recording, max_scans)
    return _spread(keys, n_points)


def _spread(keys: list[np.ndarray], n_points: int) -> float:
    if n_points == 0:
        raise CartoError("no scan endpoint to score the map with")
    return float(np.unique(np.concatenate(keys)).size / n_points)


def _endpoint_cells(times, poses, laser_pose, recording, max_scans: int | None) -> tuple[list[np.ndarray], int]:
    """The 5 cm cell of every return of ``recording``'s scans placed at ``poses`` (per scan, matched by time),
    and how many returns there were."""
    times = np.asarray(times, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    mount = np.asarray(laser_pose, dtype=np.float64).reshape(3)
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
    return keys, n_points


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
    if graph is not None and graph.constraints.num_loop_closures:
        res = graph.loop_closure_residuals()
        residual = float(np.mean(res)) if res.size else 0.0
    out = {"crispness": crisp, "occupied_entropy": entropy, "loop_closure_residual_m": residual}
    if recording is not None:
        out["endpoint_spread"] = endpoint_spread(result, recording, max_scans)
        out["map_quality"] = out["endpoint_spread"] + residual
    return out


def _relocalization_score(case: Case, options: Options, max_scans: int | None, time_weight: float,
                          algorithm: str = "cartographer") -> tuple[float, dict]:
    from carto_cli.evaluation.relocalization import Probe, run_probes, scans_with_context, summarize_outcomes
    from carto_cli.io.map_file import load_map, save_map
    from carto_cli.pipeline import build
    from carto_cli.relocalization import Relocalizer

    reference, n_scans = case.reference, case.n_scans
    if reference is None or n_scans is None:
        raise CartoError("relocalization case not prepared (call tune.prepare first)")
    rec = case.recording()
    n_map = max(5, int(round(RELOC_MAP_FRACTION * n_scans)))
    result = build(rec, options, max_scans=n_map, algorithm=algorithm)
    with tempfile.TemporaryDirectory(prefix="carto-tune-") as tmp:
        loaded = load_map(save_map(Path(tmp) / "part.carto", result, options))
    reloc = Relocalizer(loaded, options)
    # The reference in this trial's map frame, aligned locally: over the mapped scans within
    # RELOC_ALIGN_RADIUS of the query (those built the submaps it is matched against), so that
    # drift elsewhere in the map does not count against a relocalization consistent with it.
    rxy, _, ok = interpolate_poses(reference, result.times)
    if ok.sum() < 2:
        raise CartoError("the relocalization reference does not cover the mapped scans", case.name)
    rxy, mxy = rxy[ok], result.poses[ok, :2]
    global_fit = align_se2(rxy, mxy)
    held = np.arange(n_map, n_scans)
    pick = set(np.unique(np.linspace(0, len(held) - 1, min(RELOC_QUERIES, len(held))).round().astype(int)).tolist())
    wanted = sorted(int(held[i]) for i in pick)
    rng = np.random.default_rng(20240611)

    def probes():
        """The held-out scans the reference covers, each from its reference perturbed (seeded, in scan order), with
        the recording around it as `carto relocalize` reads it."""
        for index, scan, context in scans_with_context(rec, wanted):
            qxy, qth, qok = interpolate_poses(reference, [scan.time])
            if not qok[0]:
                continue
            near = np.hypot(*(rxy - qxy[0]).T) <= RELOC_ALIGN_RADIUS
            tx, ty, phi = align_se2(rxy[near], mxy[near]) if near.sum() >= 5 else global_fit
            c, s = math.cos(phi), math.sin(phi)
            truth = np.array([c * qxy[0, 0] - s * qxy[0, 1] + tx, s * qxy[0, 0] + c * qxy[0, 1] + ty, qth[0] + phi])
            noise = rng.normal(0.0, 1.0, 3) * [RELOC_PRIOR_NOISE[0], RELOC_PRIOR_NOISE[0], RELOC_PRIOR_NOISE[1]]
            yield Probe(index, scan, truth + noise, truth, RELOC_SIGMAS[0], RELOC_SIGMAS[1], context)

    # A query the relocalizer refuses counts as a failure without a latency.
    outcomes = run_probes(reloc, probes(), tolerance=RELOC_TOLERANCE, record_refusals=True)
    if not outcomes:
        raise CartoError("no held-out scan to relocalize", case.name)
    n = len(outcomes)
    rate = summarize_outcomes(outcomes).success_rate
    latencies = [o.ms / 1000.0 for o in outcomes if o.ms is not None]
    latency = float(np.mean(latencies)) if latencies else 0.0
    value = (1.0 - rate) + latency
    metrics = {"success_rate": rate, "latency_s": latency, "queries": n}
    return value, _with_time(value, metrics, result, time_weight)


def _with_time(value: float, metrics: dict, result, time_weight: float, s_per_scan: float | None = None) -> dict:
    if s_per_scan is None:
        s_per_scan = result.stats["wall_time_s"] / max(1, result.stats["scans"])
    metrics.update({"s_per_scan": s_per_scan, "loop_closures": result.stats.get("loop_closures", 0),
                    "score": value + time_weight * s_per_scan})
    return metrics


def _sessions_score(case: SessionsCase, options: Options, objective: str, max_scans: int | None,
                    time_weight: float) -> tuple[float, dict]:
    """(score, metrics) of ``options`` on recordings mapped together (module doc: Sessions)."""
    from carto_cli.mapping.alignment import Align
    from carto_cli.pipeline import MapRequest, map_sessions

    first, *later = (p.recording() for p in case.parts)
    mounts: list[np.ndarray] = []  # each recording's laser on its robot, as its plan resolved it
    started = time.perf_counter()  # every session's mapping, reading included (the result's stats are the last one's)
    # A trial is scored on its trajectories, in one frame with one alignment: turning the map square costs time
    # and changes no score
    result = map_sessions(MapRequest(first, options, max_scans=max_scans, later=tuple(later), align=Align.NONE),
                          on_plan=lambda plan: mounts.append(plan.mount))
    wall = time.perf_counter() - started
    sessions = result.sessions
    trajectories = [Trajectory.from_poses(x.times, x.poses) for x in sessions]
    metrics: dict[str, float] = {}
    if objective == "relations":
        errors = []
        for trajectory, part in zip(trajectories, case.parts):
            if part.relations is None:
                raise CartoError("the relations objective needs a --relations file for every recording", part.name)
            errors.append(relation_error(trajectory, part.relations))
        translation = float(np.mean([r.translation.mean for r in errors]))
        rotation = float(np.mean([r.rotation.mean for r in errors]))
        value = translation + ROTATION_LEVER_M * math.radians(rotation)
        metrics = {"relation_trans_m": translation, "relation_rot_deg": rotation,
                   "relations_used": float(sum(r.used for r in errors))}
    elif objective == "ground-truth":
        truths = [p.ground_truth for p in case.parts]
        if any(t is None for t in truths):
            raise CartoError("the ground-truth objective needs a --ground-truth file for every recording", case.name)
        results = ate_sessions(trajectories, [t for t in truths if t is not None])
        used = np.array([r.used for r in results], dtype=np.float64)

        def pooled(rmse: list[float]) -> float:  # the RMSE over every session's poses together
            return float(np.sqrt(np.sum(used * np.square(rmse)) / max(1.0, used.sum())))

        value = pooled([r.translation.rmse for r in results])
        metrics = {"ate_rmse_m": value, "ate_rot_rmse_deg": pooled([r.rotation.rmse for r in results]),
                   "worst_session_ate_m": max(r.translation.rmse for r in results)}
    elif objective == "map-quality":
        metrics = map_quality(result)
        keys: list[np.ndarray] = []
        n_points = 0
        for x, mount, part in zip(sessions, mounts, case.parts):
            more, n = _endpoint_cells(x.times, x.poses, mount, part.recording(), max_scans)
            keys += more
            n_points += n
        metrics["endpoint_spread"] = _spread(keys, n_points)
        value = metrics["map_quality"] = metrics["endpoint_spread"] + metrics["loop_closure_residual_m"]
    else:
        raise CartoError(f"the {objective} objective has no multi-session form")
    unlinked = sum(not x.linked for x in sessions)
    metrics["unlinked_sessions"] = float(unlinked)
    value += UNLINKED_PENALTY * unlinked
    return value, _with_time(value, metrics, result, time_weight, wall / max(1, sum(len(x.times) for x in sessions)))


def score_case(case: Case | SessionsCase, options: Options, objective: str, *, max_scans: int | None = None,
               time_weight: float = 0.0, algorithm: str = "cartographer") -> tuple[float, dict]:
    """(score, metrics) of ``options`` mapped by ``algorithm`` on one recording (or several together: a
    :class:`SessionsCase`, always Cartographer's pose graph); score includes the time term."""
    if isinstance(case, SessionsCase):
        if algorithm in GMAPPING_PIPELINE:
            raise CartoError(f"several recordings make one Cartographer pose graph; {algorithm} maps one "
                             "recording (drop --sessions, or use --algorithm cartographer)")
        value, metrics = _sessions_score(case, options, objective, max_scans, time_weight)
        return metrics["score"], metrics
    if objective == "relocalization":
        if case.reference is None:
            raise CartoError("relocalization case not prepared (call tune.prepare first)")
        _, metrics = _relocalization_score(case, options, max_scans, time_weight, algorithm)
        return metrics["score"], metrics
    from carto_cli.pipeline import build

    result = build(case.recording(), options, max_scans=max_scans, algorithm=algorithm)
    traj = Trajectory.from_poses(result.times, result.poses)
    if objective == "relations":
        if case.relations is None:
            raise CartoError("the relations objective needs a --relations file for every recording", case.name)
        r = relation_error(traj, case.relations)
        value = r.translation.mean + ROTATION_LEVER_M * math.radians(r.rotation.mean)
        metrics = {"relation_trans_m": r.translation.mean, "relation_rot_deg": r.rotation.mean,
                   "relations_used": r.used}
    elif objective == "ground-truth":
        if case.ground_truth is None:
            raise CartoError("the ground-truth objective needs a --ground-truth file for every recording", case.name)
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


def evaluate_options(options: Options, cases: Sequence[Case | SessionsCase], objective: str, *,
                     max_scans: int | None = None, time_weight: float = 0.0,
                     report: Callable[[int, float], None] | None = None,
                     algorithm: str = "cartographer") -> tuple[float, dict]:
    """Mean score of ``options`` (mapped by ``algorithm``) over ``cases`` and the mean of each metric;
    ``report(i, running_mean)`` is called after each recording (the tuner prunes from it)."""
    scores, metrics_all = [], []
    for i, case in enumerate(cases):
        score, metrics = score_case(case, options, objective, max_scans=max_scans, time_weight=time_weight,
                                    algorithm=algorithm)
        if not math.isfinite(score):
            raise CartoError(f"non-finite score on {case.name}")
        scores.append(score)
        metrics_all.append(metrics)
        if report is not None:
            report(i, float(np.mean(scores)))
    keys = metrics_all[0].keys()
    return float(np.mean(scores)), {k: float(np.mean([m[k] for m in metrics_all])) for k in keys}
