"""Threads: the loop-closure search alone, and whole `carto map` runs, with 1 and with N jobs side by side.

Part 1 (constraint search): a map.carto made by `carto map` gives finished submaps and nodes; every pair a
mapping run would consider (node within ``max_constraint_distance`` of a finished submap it is not in) is
searched with Cartographer's loop-closure window through ``ConstraintBuilder.search_many`` with 1 and with N
worker threads (precomputation grids built beforehand, not timed). The outcomes must be identical.

Part 2 (whole mapping): ``carto map REC --jobs J`` in a fresh process for each J, alternating, ``--repeat`` times;
the median wall time per J, and whether every output file is byte-identical across J.

    python bench/parallel.py [--jobs 2] [--repeat 3] [--pairs 800] [--cases freiburg-079 dense-freiburg-079]
                             [--out docs/parallel.md]

Beside each pair of runs, the machine's own ceiling: how much more a compute-only kernel gets done on N threads at
once than on one (``machine ×``; N on an idle N-core machine, less when a shared host's other tenants take part of
its cores), and each run's CPU time (user + sys, ``cpu s``): what N jobs spend beyond one.

Figures depend on the machine and its load; run the two configurations together, as here.
"""
from __future__ import annotations

import argparse
import filecmp
import functools
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"
CASES = {
    "freiburg-079": DATA / "bench" / "freiburg-079" / "scans.clf.gz",
    "dense-freiburg-079": DATA / "bench-dense" / "freiburg-079" / "scans.clf.gz",
    "intel": DATA / "bench" / "intel" / "scans.clf.gz",
    "dense-aces": DATA / "bench-dense" / "aces" / "scans.clf.gz",
    "dense-intel": DATA / "bench-dense" / "intel" / "scans.clf.gz",
}
OUTPUTS = ("map.pgm", "map.yaml", "map.png", "trajectory.tum", "map.carto")


def carto_map(recording: Path, outdir: Path, jobs: int, extra=()) -> tuple[float, float]:
    """Wall time and CPU time (user + sys) of one ``carto map`` in a fresh process."""
    cmd = [sys.executable, "-m", "carto_cli", "-q", "map", str(recording), "-o", str(outdir), "--force",
           "--jobs", str(jobs), *extra]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


@functools.lru_cache(maxsize=1)
def _spin_kernel():
    import numba

    @numba.njit(nogil=True, cache=True)
    def spin(n):
        s = 0.0
        for i in range(n):
            s += (i * 1.0001) % 7.3
        return s

    return spin


def machine_scaling(jobs: int, n: int = 60_000_000) -> float:
    """Work done per second by ``jobs`` threads running a compute-only kernel at once, over one thread's."""
    import threading

    spin = _spin_kernel()
    spin(10)
    t0 = time.perf_counter()
    spin(n)
    one = time.perf_counter() - t0
    threads = [threading.Thread(target=spin, args=(n,)) for _ in range(jobs)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return jobs * one / (time.perf_counter() - t0)


def search_pairs(map_path: Path, limit: int):
    from carto_cli.io.map_file import load_map
    from carto_cli.mapping.constraint_builder import NodeData, SubmapData

    m = load_map(map_path)
    cb = m.options.pose_graph.constraint_builder
    pairs = []
    for s, submap in enumerate(m.submaps):
        members = set(m.submap_nodes[s].tolist())
        offsets = m.node_global_poses[:, :2] - m.submap_global_poses[s, :2]
        near = np.flatnonzero(np.hypot(offsets[:, 0], offsets[:, 1]) <= cb.max_constraint_distance)
        data = SubmapData(s, int(m.submap_trajectories[s]), submap.grid, submap.local_pose, m.submap_global_poses[s])
        for n in near.tolist():
            if n not in members and len(m.node_points[n]):
                pairs.append((NodeData(n, int(m.node_trajectories[n]), m.node_global_poses[n], m.node_points[n]),
                              data, False))
    rng = np.random.default_rng(0)
    keep = np.sort(rng.choice(len(pairs), size=min(limit, len(pairs)), replace=False))
    return m.options, [pairs[i] for i in keep]


def time_searches(options, pairs, jobs: int, repeat: int):
    from carto_cli.mapping.constraint_builder import ConstraintBuilder

    builder = ConstraintBuilder(options, jobs=jobs)
    for _, submap, _ in pairs:
        builder.stack(submap.index, submap.grid)
    times, found = [], None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = builder.search_many(pairs)
        times.append(time.perf_counter() - t0)
        found = [None if lc is None else (lc.node, lc.submap, lc.relative_pose.tobytes(), lc.score) for lc in out]
    builder.close()
    return min(times), found


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--pairs", type=int, default=800)
    ap.add_argument("--cases", nargs="+", default=["freiburg-079", "dense-freiburg-079"], choices=sorted(CASES))
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    import os

    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True,
                            text=True).stdout.strip()
    lines = [f"Measured at commit `{commit}`, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
             f"{len(os.sched_getaffinity(0))} cores, load average {os.getloadavg()[0]:.2f} at start; "
             f"`python bench/parallel.py --jobs {args.jobs} --repeat {args.repeat} --pairs {args.pairs} "
             f"--cases {' '.join(args.cases)}`.", ""]
    search_rows, map_rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for case in args.cases:
            rec = CASES[case]
            walls: dict[int, list[float]] = {1: [], args.jobs: []}
            cpus: dict[int, list[float]] = {1: [], args.jobs: []}
            ceiling = []
            for r in range(args.repeat):
                ceiling.append(machine_scaling(args.jobs))
                for j in (1, args.jobs) if r % 2 == 0 else (args.jobs, 1):
                    wall, cpu = carto_map(rec, Path(tmp) / f"{case}-j{j}", j)
                    walls[j].append(wall)
                    cpus[j].append(cpu)
            same = all(filecmp.cmp(Path(tmp) / f"{case}-j1" / f, Path(tmp) / f"{case}-j{args.jobs}" / f,
                                   shallow=False) for f in OUTPUTS)
            w1, wn = statistics.median(walls[1]), statistics.median(walls[args.jobs])
            c1, cn = statistics.median(cpus[1]), statistics.median(cpus[args.jobs])
            map_rows.append(f"| {case} | {w1:.2f} | {wn:.2f} | {w1 / wn:.2f}× | {c1:.1f} | {cn:.1f} | "
                            f"{min(ceiling):.2f}-{max(ceiling):.2f}× | {'yes' if same else '**no**'} |")
            print(map_rows[-1], flush=True)

            options, pairs = search_pairs(Path(tmp) / f"{case}-j1" / "map.carto", args.pairs)
            around = [machine_scaling(args.jobs)]
            t1, f1 = time_searches(options, pairs, 1, args.repeat)
            tn, fn = time_searches(options, pairs, args.jobs, args.repeat)
            around.append(machine_scaling(args.jobs))
            found = sum(x is not None for x in f1)
            search_rows.append(f"| {case} | {len(pairs)} | {found} | {1000 * t1 / len(pairs):.2f} | "
                               f"{1000 * tn / len(pairs):.2f} | {t1 / tn:.2f}× | {min(around):.2f}-{max(around):.2f}× | "
                               f"{'yes' if f1 == fn else '**no**'} |")
            print(search_rows[-1], flush=True)
    lines += ["Loop-closure search alone (`ConstraintBuilder.search_many`, Cartographer's window, pairs sampled from "
              "every node within `max_constraint_distance` of a finished submap; best of the repeats):", "",
              f"| case | pairs | closures | ms per search, 1 job | ms per search, {args.jobs} jobs | speed-up | "
              "machine × | same closures |", "|---|---|---|---|---|---|---|---|", *search_rows, "",
              f"Whole `carto map` (a fresh process each, median of {args.repeat}, alternating):", "",
              f"| case | 1 job s | {args.jobs} jobs s | speed-up | 1 job cpu s | {args.jobs} jobs cpu s | machine × "
              "| outputs byte-identical |", "|---|---|---|---|---|---|---|---|",
              *map_rows, ""]
    text = "\n".join(lines)
    print(text)
    if args.out:
        args.out.write_text(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
