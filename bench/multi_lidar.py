#!/usr/bin/env python3
"""Several 2D lidars on one robot (issue 47): a robot with two 180 degree lidars, front and back, 0.3 m apart, at
10 and 7 Hz, mapped with both (merged, `carto map`'s default for such a recording), with either alone, and beside
it the same robot with one 360 degree lidar at its centre at 10 Hz (and at 7 Hz, and the pair both at 10 Hz): the
relation error of each trajectory against the truth, its verdict, and the CPU it took.

    python bench/multi_lidar.py [--seeds 0 1 2] [--worlds loop 'glass office'] [--variants ...] [--laps 2]
                                [--no-odometry] [--json FILE]

Relations are those of ``bench/harness.py`` (every 10th pose and revisits) from the true trajectory at 10 Hz, the
same for every variant. Each variant maps through ``pipeline.map_sessions`` with auto options, as `carto map`
does, without alignment (so the frames agree) and without cleaning (it moves no pose).
"""
from __future__ import annotations

import argparse
import json
import math
import resource
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np

from carto_cli.evaluation.metrics import relation_error
from carto_cli.io.trajectory import Trajectory
from carto_cli.mapping.alignment import Align
from carto_cli.pipeline import Auto, MapRequest, TopicChoice, map_sessions
from carto_cli.sim import Lidar, glass_office, loop_building, loop_trajectory
from carto_cli.sim.multi_lidar import MountedLidar, several_lidars

HALF = Lidar(beams=361, fov=math.pi)  # 0.5 degree beams, as a 270 degree scanner's over half of it
FULL = Lidar(beams=720, fov=2 * math.pi)
FRONT = MountedLidar(HALF, (0.15, 0.0, 0.0), "/scan_front", "laser_front", rate=10.0)
BACK = MountedLidar(HALF, (-0.15, 0.0, math.pi), "/scan_back", "laser_back", rate=7.0)
CENTRE = MountedLidar(FULL, (0.0, 0.0, 0.0), "/scan", "laser", rate=10.0)
# Beside the pair (10 and 7 Hz): one 360 degree lidar at the slower rate, and the pair both at 10 Hz, as
# many returns a second as the 360 degree lidar (the pair at 10 and 7 Hz has 15 % fewer)
VARIANTS = {"one 360": ([CENTRE], None),
            "one 360 at 7 Hz": ([MountedLidar(FULL, (0.0, 0.0, 0.0), "/scan", "laser", rate=7.0)], None),
            "both": ([FRONT, BACK], None),
            "both at 10 Hz": ([FRONT, MountedLidar(HALF, BACK.pose, BACK.topic, BACK.frame, rate=10.0)], None),
            "front alone": ([FRONT, BACK], "/scan_front"), "back alone": ([FRONT, BACK], "/scan_back")}
WORLDS = {"loop": loop_building, "glass office": glass_office}


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run(world_name: str, seed: int, laps: int, use_odometry: bool = True,
        variants: list[str] | None = None) -> list[dict]:
    from harness import relations_from_groundtruth

    world = WORLDS[world_name]()
    trajectory = loop_trajectory(world, laps=laps)
    rows, relations = [], None
    for name in variants or list(VARIANTS):
        mounts, topic = VARIANTS[name]
        recording, sims = several_lidars(world, trajectory, mounts, seed=seed)
        if relations is None:
            t = np.arange(0.0, trajectory.duration, 0.1)
            truth = Trajectory.from_poses(t + sims[0].start_time, trajectory.poses(t))
            relations, _ = relations_from_groundtruth(truth)
        cpu = _cpu()
        result = map_sessions(MapRequest(recording, Auto(), topics=TopicChoice(scan=topic), align=Align.NONE,
                                         clean=False, use_odometry=use_odometry))
        cpu = _cpu() - cpu
        error = relation_error(Trajectory.from_poses(result.times, result.poses), relations)
        row = {"world": world_name, "seed": seed, "variant": name, "relation_m": round(error.translation.mean, 4),
               "relation_deg": round(error.rotation.mean, 4),
               "verdict": result.quality.verdict if result.quality else None, "scans": len(result.times),
               "loop_closures": int(result.stats.get("loop_closures", 0)), "cpu_s": round(cpu, 1),
               "mount": result.laser_pose_source}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--worlds", nargs="+", default=list(WORLDS), choices=list(WORLDS))
    parser.add_argument("--laps", type=int, default=2)
    parser.add_argument("--json", type=Path)
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--no-odometry", action="store_true", help="map as `carto map --no-odometry` does")
    args = parser.parse_args()
    variants = [v for v in VARIANTS if v in args.variants]
    rows = [row for w in args.worlds for seed in args.seeds
            for row in run(w, seed, args.laps, use_odometry=not args.no_odometry, variants=variants)]
    print("\n| world | seed | " + " | ".join(variants) + " |")
    print("|---|---|" + "---|" * len(variants))
    for w in args.worlds:
        for seed in args.seeds:
            cells = [next(f"{r['relation_m']:.4f} m ({r['verdict']})" for r in rows
                          if r["world"] == w and r["seed"] == seed and r["variant"] == v) for v in variants]
            print(f"| {w} | {seed} | " + " | ".join(cells) + " |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
