#!/usr/bin/env python3
"""Clean maps (issue 46): figures for docs/benchmarks.md.

    python bench/clean.py [--part crowds|static|all] [--cases DIR...] [--out FILE]

* ``crowds``: simulated buildings driven twice with people walking, standing and a cart parked for a minute
  (gone before the second time round), and a door opened halfway (``sim.movers.crowd``): the loop building (seeds
  0-2, 5 / 15 / 30 walkers) and the glass office (walls one line thick, glass fronts the laser partly sees through;
  seeds 0-1, 15 / 30 walkers). Each mapped as `carto map` does but uncleaned (``MapRequest(clean=False)``), then
  cleaned (``pipeline.finished``) and scored against the simulator's truth (``evaluation.cleaning.score_cleaning``):
  of the cells the movers left in today's map, how many cleaning removed; of the walls' cells, how many it kept.
  Beside it the same recording without the movers (same seed, so the same noise): the trajectory's relation error
  (``bench/harness.py`` relations from the truth) and ATE with and without them.
* ``static``: the shared key-scan and dense cases (static buildings): each mapped as `carto map` does, then cleaned:
  the share of occupied cells removed, and of the cells of structures at least 0.5 m long (walls; not a chair's
  legs, which real offices move), and the relation error (cleaning moves no pose: the same with and without).

CPU is this process's user + sys (the pose graph's own process, with --jobs > 1, not counted); the cleaning stage's
CPU is measured around it alone.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import resource
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numpy as np
from scipy import ndimage

from carto_cli.evaluation.cleaning import score_cleaning
from carto_cli.evaluation.metrics import align_se2, ate, read_relations, relation_error
from carto_cli.io.trajectory import Trajectory
from carto_cli.mapping.alignment import Align
from carto_cli.pipeline import Auto, MapRequest, finished, map_sessions
from carto_cli.sim import glass_office, loop_building, loop_trajectory, simulate
from carto_cli.sim.movers import crowd

SHARED = Path(os.environ.get("CARTO_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
WALL_LENGTH = 0.5  # m: an occupied structure at least this long (its bounding box's diagonal) counts as a wall
SCENES = [("loop", seed, walkers) for seed in (0, 1, 2) for walkers in (5, 15, 30)] + [
    ("glass", seed, walkers) for seed in (0, 1) for walkers in (15, 30)]


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def scene(name: str, seed: int, walkers: int, movers: bool = True):
    """(world, simulation, movers): the building driven twice at 10 Hz, with its crowd unless ``movers`` False."""
    if name == "loop":
        world = loop_building()
        doors = [((4.78, 0.0), 1.0, 0.0, math.pi)]  # the bottom wall's first door, opened flat against the wall
    else:
        world = glass_office()
        doors = []
    trajectory = loop_trajectory(world, laps=2)
    t = np.arange(0.0, trajectory.duration, 0.1)
    robot = np.column_stack([t, trajectory.poses(t)])
    people = crowd(world, robot, walkers=walkers, standing_people=3, carts=1, doors=doors, seed=seed) if movers else []
    return world, simulate(world, trajectory, seed=seed, movers=tuple(people)), people


def _clean(result, request: MapRequest):
    """``result`` (of ``request``, uncleaned) cleaned as `carto map` cleans, and the CPU it took."""
    cpu = _cpu()
    out = finished(result, dataclasses.replace(request, clean=True))
    return out, _cpu() - cpu


def _errors(result, truth: np.ndarray, relations) -> dict:
    traj = Trajectory.from_poses(result.times, result.poses)
    return {"relation_m": relation_error(traj, relations).translation.mean,
            "ate_m": ate(traj, Trajectory.from_poses(truth[:, 0], truth[:, 1:])).translation.rmse}


def crowds() -> list[dict]:
    from harness import relations_from_groundtruth

    rows = []
    for name, seed, walkers in SCENES:
        world, sim, people = scene(name, seed, walkers)
        truth = sim.ground_truth
        relations, _ = relations_from_groundtruth(Trajectory.from_poses(truth[:, 0], truth[:, 1:]))
        cpu = _cpu()
        request = MapRequest(sim.recording(), Auto(), clean=False, align=Align.NONE)
        raw = map_sessions(request)
        map_cpu = _cpu() - cpu
        clean, clean_cpu = _clean(raw, request)
        alignment = np.array(align_se2(raw.poses[:, :2], truth[:, 1:3]))
        score = score_cleaning(raw.image, clean.image, world, people, sim.scan_times - sim.start_time, alignment)
        _, bare, _ = scene(name, seed, walkers, movers=False)
        alone = map_sessions(MapRequest(bare.recording(), Auto(), clean=False, align=Align.NONE))
        row = {"scene": name, "seed": seed, "walkers": walkers, **score.to_dict(),
               "with": _errors(raw, truth, relations), "without": _errors(alone, truth, relations),
               "verdict": raw.quality.verdict if raw.quality else None, "map_cpu_s": round(map_cpu, 1),
               "clean_cpu_s": round(clean_cpu, 2)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def _wall_cells(prob: np.ndarray, resolution: float) -> np.ndarray:
    """Occupied cells of structures (8-connected) whose bounding box's diagonal is at least WALL_LENGTH."""
    occupied = np.nan_to_num(prob, nan=0.0) > 0.5
    labels, n = ndimage.label(occupied, structure=np.ones((3, 3), bool))
    extent = np.zeros(n + 1)
    for k, box in enumerate(ndimage.find_objects(labels), 1):
        extent[k] = math.hypot(box[0].stop - box[0].start, box[1].stop - box[1].start) * resolution
    return occupied & (extent[labels] >= WALL_LENGTH)


def static(cases: list[Path]) -> list[dict]:
    rows = []
    for case in cases:
        cpu, wall = _cpu(), time.perf_counter()
        request = MapRequest(case / "scans.clf.gz", Auto(), clean=False, align=Align.NONE)
        raw = map_sessions(request)
        map_cpu = _cpu() - cpu
        prob = np.asarray(raw.image.probability)
        clean, clean_cpu = _clean(raw, request)
        found = clean.transients
        removed = np.zeros(prob.shape, bool)
        if found is not None and len(found):
            removed[found.cells[:, 1], found.cells[:, 0]] = True
        walls = _wall_cells(prob, raw.image.resolution)
        occupied = int((np.nan_to_num(prob, nan=0.0) > 0.5).sum())
        relations = read_relations(case / "relations.txt")
        row = {"case": f"{case.parent.name}/{case.name}", "algorithm": str(raw.stats.get("algorithm", "cartographer")),
               "occupied": occupied, "removed": int(removed.sum()),
               "removed_share": removed.sum() / max(occupied, 1), "walls": int(walls.sum()),
               "walls_removed": int((removed & walls).sum()),
               "walls_removed_share": (removed & walls).sum() / max(int(walls.sum()), 1),
               "relation_m": relation_error(Trajectory.from_poses(raw.times, raw.poses), relations).translation.mean,
               "map_cpu_s": round(map_cpu, 1), "map_wall_s": round(time.perf_counter() - wall, 1),
               "clean_cpu_s": round(clean_cpu, 2), "nodes": raw.graph.num_nodes if raw.graph else None,
               "returns_mb": round(sum(r.nbytes for r in raw.node_returns) / 2**20, 1)}
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--part", choices=("crowds", "static", "all"), default="all")
    parser.add_argument("--cases", type=Path, nargs="*",
                        help="static: case directories (default: every one of bench/ and bench-dense/)")
    parser.add_argument("--out", type=Path, help="write the figures as JSON here too")
    args = parser.parse_args()
    figures: dict = {}
    if args.part in ("crowds", "all"):
        figures["crowds"] = crowds()
    if args.part in ("static", "all"):
        cases = args.cases or sorted((SHARED / "bench").iterdir()) + sorted((SHARED / "bench-dense").iterdir())
        figures["static"] = static([c for c in cases if (c / "scans.clf.gz").exists()])
    if args.out:
        args.out.write_text(json.dumps(figures, indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
