#!/usr/bin/env python3
"""A LaMa-Slam2D-like online SLAM from carto's distance map and distance matcher, on the bench's CARMEN logs.

    python bench/frontend.py [CASE ...] [--out DIR] [--d-thresh M] [--a-thresh RAD] [--multires] ...

CASE is ``family/case`` (``bench-dense/intel``, ``bench/fhw``); none: every case of bench-dense/ and bench/.
Each case runs in a child process of its own, one at a time (CPU = user + sys of that child, from wait4, as the
peers were measured; peak RSS likewise), then its trajectory is scored with ``carto eval --relations``.

The SLAM, as IRIS LaMa's ``Slam2D`` with iris_lama_ros's defaults (``../shared/peers/lama``): each scan's odometry
pose (the pose in its laser line, ``/odom_laser``) predicts the motion since the last processed scan; a scan is
processed only when that motion exceeds ``d_thresh`` (0.01 m) or ``a_thresh`` (0.25 rad): it is matched to the
distance map from the prediction (robust Gauss-Newton, Cauchy 0.15 m) and inserted at the matched pose (hits at
its returns, free space along its rays). Beams at or beyond ``mrange`` (16 m) are dropped. No submaps, no loop
closure. The trajectory has every scan, the skipped ones placed by odometry from the last processed one.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

DATA = Path(os.environ.get("CARTO_SHARED_DATA", "/work/shared/data"))
CASES = ["bench-dense/intel", "bench-dense/aces", "bench-dense/freiburg-079", "bench/intel", "bench/aces",
         "bench/orebro", "bench/edmonton", "bench/fhw", "bench/freiburg-079"]
# LaMa Slam2D and carto (no flags) from ../shared/data/PEERS.md: error (m), CPU (s), peak RSS (MB).
PEERS = {
    "bench-dense/intel": ((0.027, 3.9, 11), (0.016, 14.4, 484)),
    "bench-dense/aces": ((0.052, 2.3, 19), (0.016, 6.2, 487)),
    "bench-dense/freiburg-079": ((0.018, 2.8, 9), (0.012, 16.5, 499)),
    "bench/intel": ((0.038, 0.3, 10), (0.039, 116, 640)),
    "bench/aces": ((0.156, 0.2, 15), (0.040, 65, 942)),
    "bench/orebro": ((0.342, 0.2, 15), (0.038, 39, 979)),
    "bench/edmonton": ((0.045, 0.3, 31), (0.049, 59, 1813)),
    "bench/fhw": ((1.533, 0.3, 15), (0.048, 76, 1461)),
    "bench/freiburg-079": ((0.033, 1.5, None), (0.016, 6.4, None)),
}


def run_case(log: Path, out: Path, args) -> dict:
    """The SLAM on one log; writes ``out`` (TUM) and returns the in-process statistics."""
    from carto_cli.core import kernels, transform
    from carto_cli.core.records import Odometry, Scan
    from carto_cli.io.sources.open import open_recording
    from carto_cli.io.trajectory import Trajectory, write_trajectory
    from carto_cli.mapping.scan_to_map import Slam2D, Slam2DOptions

    t_start = time.process_time()
    kernels.warm_up()
    t_warm = time.process_time() - t_start
    recording = open_recording(log)
    mount = np.zeros(3)
    for tf in recording.static_transforms():
        if tf.child == "laser":
            mount = np.array(tf.pose2d())
    topics = {t.name for t in recording.topics()}
    odom_topic = "/odom_laser" if "/odom_laser" in topics else "/odom"
    slam = Slam2D(Slam2DOptions(
        resolution=args.resolution, max_distance=args.l2_max, d_thresh=args.d_thresh, a_thresh=args.a_thresh,
        loss_scale=args.loss, max_iterations=args.max_iterations, multires=args.multires,
        translation_weight=args.prior_t, rotation_weight=args.prior_r))
    times, poses = [], []
    odom = None
    unconverged = 0
    slam_cpu = 0.0
    for rec in recording.records(["/scan", odom_topic]):
        if isinstance(rec, Odometry):
            odom = np.array([rec.x, rec.y, rec.yaw])
            continue
        if not isinstance(rec, Scan) or odom is None:
            continue
        scan: Scan = rec
        r = scan.ranges.astype(np.float64)
        a = scan.angles.astype(np.float64)
        max_range = min(args.mrange, scan.range_max) if args.mrange > 0 else scan.range_max
        ok = np.isfinite(r) & (r < max_range) & (r > 0.0)
        points = transform.apply(mount, np.stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])], axis=1))
        t0 = time.process_time()
        result = slam.add_scan(odom, points, mount[:2])
        slam_cpu += time.process_time() - t0
        unconverged += result.match is not None and not result.match.converged
        times.append(scan.time)
        poses.append(result.pose)
    write_trajectory(out, Trajectory.from_poses(np.array(times), np.array(poses)))
    return {"scans": len(times), "processed": slam.processed, "iterations": slam.iterations,
            "unconverged": unconverged, "slam_cpu_s": slam_cpu, "warm_up_cpu_s": t_warm,
            "map_mb": slam.memory_bytes / 2**20, "patches": slam.distance_map.patches}


def evaluate(traj: Path, relations: Path) -> dict:
    out = subprocess.run(["carto", "eval", str(traj), "--relations", str(relations), "--json"], check=True,
                         capture_output=True, text=True).stdout
    return json.loads(out)


def _child(case: str, out: Path, args: argparse.Namespace, passthrough: list[str]) -> dict:
    stats = out.with_suffix(".stats.json")
    cmd = [sys.executable, __file__, "--child", str(DATA / case / "scans.clf.gz"), str(out), str(stats),
           *passthrough]
    proc = subprocess.Popen(cmd)
    _, status, usage = os.wait4(proc.pid, 0)
    if os.waitstatus_to_exitcode(status) != 0:
        raise RuntimeError(f"{case}: child failed ({status})")
    res = json.loads(stats.read_text())
    res["cpu_s"] = usage.ru_utime + usage.ru_stime
    res["peak_rss_mb"] = usage.ru_maxrss / 1024.0
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("cases", nargs="*", default=None)
    p.add_argument("--out", type=Path, default=None, help="directory for trajectories (default: a temporary one)")
    p.add_argument("--d-thresh", type=float, default=0.01)
    p.add_argument("--a-thresh", type=float, default=0.25)
    p.add_argument("--l2-max", type=float, default=0.5)
    p.add_argument("--resolution", type=float, default=0.05)
    p.add_argument("--mrange", type=float, default=16.0)
    p.add_argument("--loss", type=float, default=0.15)
    p.add_argument("--max-iterations", type=int, default=100)
    p.add_argument("--multires", action="store_true", help="match on a 4x coarser map first")
    p.add_argument("--prior-t", type=float, default=0.0, help="prior weight towards odometry's translation (1/m)")
    p.add_argument("--prior-r", type=float, default=0.0, help="prior weight towards odometry's heading (1/rad)")
    p.add_argument("--json", action="store_true")
    p.add_argument("--child", nargs=3, metavar=("LOG", "OUT", "STATS"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        log, out, stats = map(Path, args.child)
        res = run_case(log, out, args)
        stats.write_text(json.dumps(res))
        return 0
    passthrough = [f"--d-thresh={args.d_thresh}", f"--a-thresh={args.a_thresh}", f"--l2-max={args.l2_max}",
                   f"--resolution={args.resolution}", f"--mrange={args.mrange}", f"--loss={args.loss}",
                   f"--max-iterations={args.max_iterations}", f"--prior-t={args.prior_t}", f"--prior-r={args.prior_r}"] + (["--multires"] if args.multires else [])
    out_dir = args.out or Path(tempfile.mkdtemp(prefix="carto-frontend-"))
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in args.cases or CASES:
        traj = out_dir / (case.replace("/", "_") + ".tum")
        res = _child(case, traj, args, passthrough)
        score = evaluate(traj, DATA / case / "relations.txt")
        rel = score["relations"]
        res.update(case=case, error_m=rel["translation_m"]["mean"], error_std_m=rel["translation_m"].get("std"),
                   rot_deg=rel.get("rotation_deg", {}).get("mean"), trajectory=str(traj))
        rows.append(res)
        lama, carto = PEERS.get(case, ((None,) * 3,) * 2)
        print(f"{case:26s} err {res['error_m']:.3f} m  cpu {res['cpu_s']:6.1f} s (slam {res['slam_cpu_s']:5.1f}, "
              f"warm-up {res['warm_up_cpu_s']:4.1f})  rss {res['peak_rss_mb']:5.0f} MB  map {res['map_mb']:5.1f} MB  "
              f"processed {res['processed']}/{res['scans']}  | LaMa {lama[0]}  carto {carto[0]}", flush=True)
    if args.json:
        print(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
