#!/usr/bin/env python3
"""GMapping's memory on a 100 m x 100 m building: how much the particles' copy-on-write maps hold.

A simulated ring corridor around a 100 m x 100 m block (carto_cli.sim.loop_building), one lap at 10 Hz with
a 30 m, 360-beam scanner and drifting odometry, mapped by ``GMappingSlam`` with N particles (default 100) at
0.05 m. Prints the peak map memory (tiles held by the pool at its fullest), what a full copy of the map per
particle would take, the process's peak RSS, the wall time and the relation-free end error.

    python bench/gmapping_memory.py [--particles 100] [--linear-update 1.0]

``--linear-update`` defaults to slam_gmapping's 1.0 m to keep the run to minutes; memory follows the area the
particles saw since their last common ancestor, not how often they update.
"""
from __future__ import annotations

import argparse
import resource
import time

import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--size", type=float, default=100.0, help="building side (m)")
    ap.add_argument("--linear-update", type=float, default=1.0)
    ap.add_argument("--delta", type=float, default=0.05)
    args = ap.parse_args()

    from carto_cli.core.records import Odometry, Scan
    from carto_cli.gmapping.filter import GMappingSlam
    from carto_cli.gmapping.maps import TILE
    from carto_cli.options import load_options
    from carto_cli.sim import loop_building, loop_trajectory, simulate

    world = loop_building(width=args.size, height=args.size, corridor_width=3.0, room_depth=4.0)
    trajectory = loop_trajectory(world, laps=1)
    sim = simulate(world, trajectory, duration=trajectory.duration, seed=1)
    options = load_options(None, [f"gmapping.particles={args.particles}", f"gmapping.delta={args.delta}",
                                  f"gmapping.linearUpdate={args.linear_update}", "gmapping.angularUpdate=0.5"])
    slam = GMappingSlam(options)
    t0 = time.perf_counter()
    for record in sim.recording().records():
        if isinstance(record, Scan):
            slam.add_scan(record)
        elif isinstance(record, Odometry):
            slam.add_odometry(record)
    result = slam.finish()
    wall = time.perf_counter() - t0
    s = result.stats
    xmin, ymin, xmax, ymax = world.bounds
    cells = (xmax - xmin) * (ymax - ymin) / args.delta ** 2
    full_copy = cells * 16 * args.particles  # bytes a full map per particle would take (16 B per cell)
    print(f"building {xmax - xmin:.0f} m x {ymax - ymin:.0f} m, {s['scans']} scans ({s['processed_scans']} "
          f"processed), {args.particles} particles, delta {args.delta} m")
    print(f"peak map memory {s['map_memory_peak_bytes'] / 2**20:.0f} MB ({s['map_tiles_peak']} tiles of "
          f"{TILE}x{TILE} cells); a full copy per particle would be {full_copy / 2**30:.1f} GB")
    print(f"peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MB, wall {wall:.0f} s, "
          f"{s['resamplings']} resamplings")
    print(f"trajectory: {len(result.poses)} poses, path {np.sum(np.hypot(*np.diff(result.poses[:, :2], axis=0).T)):.0f} m")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
