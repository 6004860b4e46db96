#!/usr/bin/env python3
"""A 3D lidar flattened to 2D (issue 47): its map beside an ideal 2D lidar's.

    python bench/cloud.py [--laps N] [--seed S] [--furniture K] [--format mcap|ros1|ros2-sqlite3] [--instant]
                          [--keep DIR]

The loop building (``sim.loop_building``) with a 2.6 m ceiling and ``K`` boxes of furniture up to 0.55 m tall in
its corridor (``sim.lidar3d.furnish``), driven round by the default loop. A 16-ring lidar (VLP-16-like: -15 to +15
degrees every 2, 900 columns, 10 Hz, per-point times in Ouster's ``t`` field) 0.8 m above the floor records it to a
file carto reads as a user's (PointCloud2, odometry, IMU, static TF). The same trajectory with the same seed (so
the very same odometry) is recorded by an ideal 2D lidar (900 beams over 360 degrees, the same noise) in the same
walls without the furniture, which stands below the band, as a 2D lidar at the band's height would see it.

Both recordings are mapped by `carto map` with its defaults and ``--align none`` (so both maps stay in the frame of
the first pose), and their occupancy images (map.pgm, map_server's trinary classes) are compared cell by cell over
the cells either map knows: the share whose class (occupied, free, unknown) differs, as the maps' origins place them
and at the best shift of up to two cells (each frame is its SLAM's estimate of the first pose). The same figures
for the 2D lidar against itself with other noise (seed + 1) are the measure's floor. ``beyond_a_cell``: the differing
cells (at the best shift) more than a cell from any occupied cell of either map: a wall where the other has none, or
free space the other does not have, not a wall's line drawn in the neighbouring cell. ``--instant``: every column
of a sweep fired at its stamp, so the figure is the flattening's alone, without de-skewing. Printed as JSON.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import cv2
import numpy as np
import yaml
from scipy import ndimage

from carto_cli.io.map_server import occupancy_from_pixels
from carto_cli.io.recording_writers import write_recording
from carto_cli.io.sources.open import open_recording
from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate
from carto_cli.sim.lidar3d import Lidar3D, furnish, simulate_3d

HEIGHT = 0.8  # m: the 3D lidar above the floor
SEARCH = 2  # cells: the largest shift between the two maps' frames tried
LIDAR_3D = Lidar3D(columns=900, noise=0.01)
LIDAR_2D = Lidar(beams=900, fov=2 * np.pi, max_range=30.0, noise=0.01, dropout=0.0)


def occupancy(outdir: Path) -> tuple[np.ndarray, float, np.ndarray]:
    """(classes (rows, cols) int8 with row 0 the lowest y: 1 occupied, 0 free, -1 unknown; resolution; origin)."""
    meta = yaml.safe_load((outdir / "map.yaml").read_text())
    pixels = cv2.imread(str(outdir / meta["image"]), cv2.IMREAD_UNCHANGED)
    occ = occupancy_from_pixels(pixels, mode=meta.get("mode", "trinary"), negate=bool(meta.get("negate", 0)),
                                occupied_thresh=float(meta["occupied_thresh"]), free_thresh=float(meta["free_thresh"]))
    classes = np.where(occ == 100, 1, np.where(occ == 0, 0, -1)).astype(np.int8)[::-1]
    return classes, float(meta["resolution"]), np.asarray(meta["origin"][:2], dtype=np.float64)


def aligned(a: Path, b: Path) -> tuple[np.ndarray, np.ndarray]:
    """Two maps of one resolution on one grid, placed by their origins (unknown where a map has no cell)."""
    ca, ra, oa = occupancy(a)
    cb, rb, ob = occupancy(b)
    if abs(ra - rb) > 1e-9:
        raise SystemExit("the two maps differ in resolution")
    shift = np.rint((ob - oa) / ra).astype(int)  # b's lower-left cell in a's cells (x, y)
    lo = np.minimum([0, 0], shift)
    hi = np.maximum([ca.shape[1], ca.shape[0]], shift + [cb.shape[1], cb.shape[0]])
    size = (hi - lo)[::-1]
    ga = np.full(size, -1, np.int8)
    gb = np.full(size, -1, np.int8)
    ga[-lo[1]:-lo[1] + ca.shape[0], -lo[0]:-lo[0] + ca.shape[1]] = ca
    sb = shift - lo
    gb[sb[1]:sb[1] + cb.shape[0], sb[0]:sb[0] + cb.shape[1]] = cb
    return ga, gb


def differ(ga: np.ndarray, gb: np.ndarray) -> tuple[int, int]:
    """(cells either map knows, cells whose class differs)."""
    known = (ga >= 0) | (gb >= 0)
    return int(known.sum()), int((known & (ga != gb)).sum())


def compare(a: Path, b: Path, search: int = SEARCH) -> dict:
    """Cell-by-cell comparison of two maps: the share of the cells either knows whose class differs, as placed by
    their origins and at the best whole-cell shift within ``search`` cells (each map's frame is its own first pose
    as its SLAM estimated it: a few centimetres apart, they put a wall's line in neighbouring cells)."""
    ga, gb = aligned(a, b)
    known, bad = differ(ga, gb)
    pad = search
    pa = np.pad(ga, pad, constant_values=-1)
    best = (bad / max(known, 1), 0, 0)
    for dy in range(-search, search + 1):
        for dx in range(-search, search + 1):
            pb = np.full_like(pa, -1)
            pb[pad + dy:pad + dy + gb.shape[0], pad + dx:pad + dx + gb.shape[1]] = gb
            k, d = differ(pa, pb)
            if d / max(k, 1) < best[0]:
                best = (d / max(k, 1), dx, dy)
    occupied = (ga == 1) | (gb == 1)
    pb = np.full_like(pa, -1)
    pb[pad + best[2]:pad + best[2] + gb.shape[0], pad + best[1]:pad + best[1] + gb.shape[1]] = gb
    near_wall = ndimage.binary_dilation((pa == 1) | (pb == 1), structure=np.ones((3, 3), bool))
    far = ((pa >= 0) | (pb >= 0)) & (pa != pb) & ~near_wall
    return {"cells_known": known, "cells_differ": bad, "differ_fraction": round(bad / max(known, 1), 5),
            "differ_fraction_best_shift": round(best[0], 5), "best_shift_cells": [best[1], best[2]],
            "beyond_a_cell_fraction": round(int(far.sum()) / max(known, 1), 5),
            "occupied_either": int(occupied.sum()), "occupied_differ": int((occupied & (ga != gb)).sum()),
            "known_first_only": int(((ga >= 0) & (gb < 0)).sum()), "known_second_only": int(((gb >= 0) & (ga < 0)).sum())}


def carto_map(recording: Path, out: Path) -> dict:
    t0 = time.monotonic()
    cmd = [sys.executable, "-m", "carto_cli", "--quiet", "map", str(recording), "-o", str(out), "--align", "none",
           "--force"]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode not in (0, 3):
        raise SystemExit(f"{' '.join(cmd)} failed:\n{done.stderr}")
    summary = json.loads((out / "summary.json").read_text())
    return {"command": " ".join(cmd[1:]), "wall_s": round(time.monotonic() - t0, 1),
            "algorithm": summary.get("algorithm"), "quality": (summary.get("quality") or {}).get("verdict")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--laps", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--furniture", type=int, default=14)
    ap.add_argument("--format", default="mcap")
    ap.add_argument("--instant", action="store_true",
                    help="every column of a sweep at its stamp (no motion within the sweep, nothing to de-skew)")
    ap.add_argument("--keep", type=Path, help="write the recordings and maps here (default: a temporary directory)")
    args = ap.parse_args(argv)

    world = loop_building()
    building = furnish(world, count=args.furniture, seed=args.seed)
    trajectory = loop_trajectory(world, laps=args.laps)
    suffix = {"mcap": ".mcap", "ros1": ".bag"}.get(args.format, "")
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        root.mkdir(parents=True, exist_ok=True)
        t0 = time.monotonic()
        lidar = dataclasses.replace(LIDAR_3D, instantaneous=args.instant)
        sim3d = simulate_3d(building, trajectory, lidar=lidar, height=HEIGHT, seed=args.seed)
        rec3d = sim3d.write(root / f"lidar3d{suffix}", args.format, overwrite=True)
        sim2d = simulate(world, trajectory, scan_rate=LIDAR_3D.rate, lidar=LIDAR_2D, seed=args.seed)
        rec2d = root / f"lidar2d{suffix}"
        write_recording(sim2d.records(), rec2d, args.format, static_transforms=sim2d.static_transforms,
                        overwrite=True)
        simulated_s = time.monotonic() - t0
        with open_recording(rec3d) as rec:
            next(iter(rec.records(["/points"])))
            band = rec.cloud_bands["/points"]
        # The floor of the measure: the same 2D lidar with other noise (and odometry noise) mapped again.
        other = simulate(world, trajectory, scan_rate=LIDAR_3D.rate, lidar=LIDAR_2D, seed=args.seed + 1)
        rec2d_other = root / f"lidar2d_other{suffix}"
        write_recording(other.records(), rec2d_other, args.format, static_transforms=other.static_transforms,
                        overwrite=True)
        runs = {"3d": carto_map(rec3d, root / "map3d"), "2d": carto_map(rec2d, root / "map2d"),
                "2d_other_seed": carto_map(rec2d_other, root / "map2d_other")}
        result = {
            "world": world.name, "laps": args.laps, "seed": args.seed, "instant": args.instant,
            "furniture": len(building.furniture),
            "furniture_max_height": round(building.furniture_height, 3), "lidar_height": HEIGHT,
            "sweeps": int(len(sim3d.sweep_times)), "simulate_and_write_s": round(simulated_s, 1),
            "band": band.describe(), "maps": runs, "3d_vs_2d": compare(root / "map3d", root / "map2d"),
            "2d_vs_2d_other_seed": compare(root / "map2d_other", root / "map2d"),

        }
    print(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
