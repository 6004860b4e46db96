"""How far a recording's odometry can be trusted, measured before mapping: what the motion model's noise is sized to.

GMapping's motion model draws every particle around the odometry with noise ``srr``, ``srt``, ``str``, ``stt``;
slam_gmapping's defaults (0.1 m per m, 0.2 rad per m, ...) suit a robot whose odometry errs by about a tenth of
its travel. Where it errs far less, particles spread over poses odometry already rules out, and on a young map a
climb from one of them slides to a wrong local peak that the weights cannot tell from the right one: orebro,
seed 2, the filter's fifth step went 0.33 m further than a 2.9 m odometry increment that was right within 4 cm,
and the map kept the gap (0.096 m mean relation error against 0.039 m with the noise sized to the odometry).

The measurement is the filter itself with one particle and no noise: each key scan climbs from the odometry's
prediction on the map of the scans before it, and the median, over steps of at least ``MIN_STEP``, of
|climbed increment - odometry increment| / travel says how far odometry is off per metre. A climb that slid
lands in the upper half; the match's own error makes the figure an upper bound (on the five key-scan benchmark
buildings it reads 0.025-0.042 against the reference poses' 0.021-0.025).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from carto_cli.core import kernels, transform
from carto_cli.core.records import Odometry, Scan
from carto_cli.options import Options

__all__ = ["MIN_STEP", "MIN_STEPS", "odometry_error"]

MIN_STEP = 0.3  # m: a shorter increment says more about the match than about the odometry
MIN_STEPS = 10  # fewer such steps leave the error unmeasured
MAX_STEPS = 150  # processed scans looked at: enough for a median, a second on the benchmark logs


def odometry_error(scans: Sequence[Scan], odometry: Sequence[Odometry], options: Options, *,
                   laser_pose=(0.0, 0.0, 0.0), max_range: float | None = None, timer=None) -> float | None:
    """Median translation error of the odometry per metre travelled over the first ``MAX_STEPS`` processed key
    scans of ``scans`` (time order, ``odometry`` alongside), or None when fewer than ``MIN_STEPS`` steps moved
    ``MIN_STEP`` or more. ``options.gmapping`` gives the matcher's settings; ``max_range`` caps its range (a
    fixed "no return" reading below it would draw phantom walls). ``timer``: the caller's, for the ``jit
    warm-up`` stage: on a fresh install the filter's kernels are compiled here, before mapping needs them, and
    by :func:`kernels.warm_up` (shared with helper processes) rather than one by one on first use."""
    from carto_cli.gmapping.filter import GMappingSlam

    kernels.warm_up(timer, systems=("gmapping",))
    g = dataclasses.replace(options.gmapping, particles=1, srr=0.0, srt=0.0, str=0.0, stt=0.0,
                            refineIterations=0, refineLoops=False)
    if max_range is not None:
        g = dataclasses.replace(g, maxRange=min(g.maxRange, max_range))
    slam = GMappingSlam(dataclasses.replace(options, gmapping=g), laser_pose=laser_pose)
    records: list[Scan | Odometry] = [*scans, *odometry]
    records.sort(key=lambda r: (r.time, isinstance(r, Scan)))  # odometry first on a tie
    for record in records:
        if isinstance(record, Odometry):
            slam.add_odometry(record)
        elif slam.add_scan(record) and slam.num_steps >= MAX_STEPS:
            break
    if slam.num_steps < 2 or any(o is None for o in slam.step_odometry):
        return None
    climbed = slam.best_trajectory()
    odo = np.array(slam.step_odometry, dtype=np.float64)
    by_scans = transform.relative(climbed[:-1], climbed[1:])
    by_odometry = transform.relative(odo[:-1], odo[1:])
    step = np.hypot(by_odometry[:, 0], by_odometry[:, 1])
    keep = step >= MIN_STEP
    if np.count_nonzero(keep) < MIN_STEPS:
        return None
    gap = by_scans[keep, :2] - by_odometry[keep, :2]
    return float(np.median(np.hypot(gap[:, 0], gap[:, 1]) / step[keep]))
