#!/usr/bin/env python3
"""Maps square to the building (``carto map --align auto``, issue 46 item 3): figures for docs/benchmarks.md.

    python bench/align.py MAPDIR_OR_MAP.carto... [--angles 0,17,30,45,60,75,90] [--out FILE]

Each map (a map.carto written with ``--align none``) is turned by each known angle in code: its submaps' global
poses turned about the map origin and the image assembled again from them, as ``--align auto`` assembles a turned
map. ``mapping.alignment.wall_axes`` reads the walls' direction off each assembled image; the error of a turn is
how far that lies, modulo 90°, from the unturned map's direction plus the turn. Prints one row per map: the
walls' direction, the peak's contrast, the worst error over the angles and at which, and the CPU time (user +
sys of this process) of one estimate and of one turn of the image (the align stage's two parts).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np

from carto_cli.core import transform
from carto_cli.grid.occupancy_image import AssembledImage
from carto_cli.io.map_file import load_map
from carto_cli.mapping.alignment import turned_image, turned_poses, wall_axes


def _image(loaded, turn: float) -> AssembledImage:
    """The map's image with its frame turned by ``turn``: submaps at their turned global poses."""
    poses = turned_poses(np.asarray(loaded.submap_global_poses), turn)
    corrections = [transform.compose(g, transform.inverse(s.local_pose)) for s, g in zip(loaded.submaps, poses)]
    return AssembledImage([s.grid for s in loaded.submaps], corrections)


def _cpu() -> float:
    return time.process_time()


def measure(path: Path, angles: list[float]) -> dict:
    loaded = load_map(path)
    base = _image(loaded, 0.0)
    base.probability  # noqa: B018 - assembled before the clock starts, as mapping leaves it
    started = _cpu()
    axes = wall_axes(base)
    estimate_s = _cpu() - started
    started = _cpu()
    turned = turned_image(base, math.radians(17.0))
    turn_s = _cpu() - started
    errors = {}
    for deg in angles:
        found = wall_axes(_image(loaded, math.radians(deg))).angle
        errors[deg] = abs(math.degrees(transform.wrap_angle_scalar(4 * (found - axes.angle - math.radians(deg))) / 4))
    worst = max(errors, key=lambda d: errors[d])
    return {"map": str(path), "cells": base.shape[0] * base.shape[1], "turned_cells": turned.shape[0] * turned.shape[1],
            "walls_deg": math.degrees(axes.angle), "contrast": axes.contrast, "errors_deg": errors,
            "worst_deg": errors[worst], "worst_at": worst, "estimate_cpu_s": estimate_s, "turn_cpu_s": turn_s}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("maps", nargs="+", type=Path, help="map.carto files, or the directories carto map wrote")
    ap.add_argument("--angles", default="0,17,30,45,60,75,90", help="turns to apply, degrees")
    ap.add_argument("--out", type=Path, help="the rows as JSON too")
    args = ap.parse_args()
    angles = [float(a) for a in args.angles.split(",")]
    rows = []
    print(f"{'map':40} {'walls':>7} {'contrast':>8} {'worst':>6} {'at':>4} {'est CPU':>8} {'turn CPU':>8}")
    for given in args.maps:
        path = given / "map.carto" if given.is_dir() else given
        row = measure(path, angles)
        rows.append(row)
        print(f"{given!s:40} {row['walls_deg']:+7.2f} {row['contrast']:8.2f} {row['worst_deg']:6.3f} "
              f"{row['worst_at']:4.0f} {row['estimate_cpu_s']:7.2f}s {row['turn_cpu_s']:7.2f}s", flush=True)
    if args.out:
        args.out.write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main()
