"""Time the pose-graph optimizer on a large synthetic graph.

10⁴ nodes driving ten laps of a 20 m circle, a submap every 100 nodes (each
holding 200, as Cartographer's two active submaps overlap by half), ~2·10⁴
intra-submap constraints, ~8·10⁴ loop closures between later laps and earlier
submaps, local SLAM and odometry chains; initial poses from an odometry chain
with a scale and heading bias. Prints setup and solver times and the pose error.

    python bench/optimization_scaling.py [--nodes 10000] [--loop-closures 80000]
"""
from __future__ import annotations

import argparse
import math
import time

import numpy as np

from carto_cli.core.transform import relative
from carto_cli.mapping.constraints import ConstraintSet
from carto_cli.mapping.optimization import NodePairs, optimize, residuals


def chain(start, steps):
    """Accumulate relative poses; a scan over angles so it stays vectorised."""
    theta = start[2] + np.concatenate([[0.0], np.cumsum(steps[:, 2])])
    c, s = np.cos(theta[:-1]), np.sin(theta[:-1])
    dxy = np.stack([c * steps[:, 0] - s * steps[:, 1], s * steps[:, 0] + c * steps[:, 1]], axis=1)
    xy = start[:2] + np.concatenate([[[0.0, 0.0]], np.cumsum(dxy, axis=0)])
    return np.column_stack([xy, theta])


def build(num_nodes: int, num_loop_closures: int, per_submap: int = 100, laps: int = 10,
          radius: float = 20.0, seed: int = 0):
    rng = np.random.default_rng(seed)
    noise = np.array([0.005, 0.005, 0.001])
    phi = laps * 2 * math.pi * np.arange(num_nodes) / num_nodes
    # A wobble so that laps do not retrace each other exactly.
    r = radius + 1.5 * np.sin(phi * 1.1)
    gt = np.stack([r * np.sin(phi), radius - r * np.cos(phi), phi], axis=1)
    num_submaps = num_nodes // per_submap
    submaps = gt[::per_submap][:num_submaps].copy()
    submaps[:, 2] = 0.0

    cs = ConstraintSet(capacity=3 * num_nodes + num_loop_closures)
    nodes = np.arange(num_nodes)
    for back in (0, 1):  # each node sits in its newest and the previous submap
        sub = nodes // per_submap - back
        ok = (sub >= 0) & (sub < num_submaps)
        rel = relative(submaps[sub[ok]], gt[nodes[ok]]) + rng.normal(0, noise, (ok.sum(), 3))
        cs.extend(sub[ok], nodes[ok], rel, 5e2, 1.6e3, False)

    centres = np.array([gt[j * per_submap:(j + 2) * per_submap, :2].mean(axis=0) for j in range(num_submaps)])
    dist = np.linalg.norm(gt[:, None, :2] - centres[None], axis=2)
    own = nodes[:, None] // per_submap - np.arange(num_submaps)[None]
    candidate = (dist < 10.0) & (own >= 10)  # earlier laps only
    ci, cj = np.nonzero(candidate)
    pick = rng.choice(len(ci), size=min(num_loop_closures, len(ci)), replace=False)
    ci, cj = ci[pick], cj[pick]
    rel = relative(submaps[cj], gt[ci]) + rng.normal(0, noise, (len(ci), 3))
    cs.extend(cj, ci, rel, 1.1e4, 1e5, True)

    rel_gt = relative(gt[:-1], gt[1:])
    local = NodePairs(nodes[:-1], nodes[1:], rel_gt + rng.normal(0, noise, rel_gt.shape), 1e5, 1e5)
    odometry_steps = rel_gt * [1.01, 1.01, 1.0] + [0.0, 0.0, 2e-4]
    odometry_poses = chain(gt[0], odometry_steps + rng.normal(0, noise, rel_gt.shape))
    odometry = NodePairs.consecutive(odometry_poses, translation_weight=1e2, rotation_weight=1e2)
    init_submaps = odometry_poses[::per_submap][:num_submaps].copy()
    init_submaps[:, 2] = 0.0
    return gt, submaps, odometry_poses, init_submaps, cs, odometry, local


def rms(a, b) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, default=10_000)
    parser.add_argument("--loop-closures", type=int, default=80_000)
    parser.add_argument("--max-iterations", type=int, default=50)
    args = parser.parse_args()

    t = time.perf_counter()
    gt, submaps, init, init_submaps, cs, odometry, local = build(args.nodes, args.loop_closures)
    build_time = time.perf_counter() - t
    print(f"graph: {len(gt)} nodes, {len(submaps)} submaps, {len(cs)} node-submap constraints "
          f"({cs.num_loop_closures} loop closures), {len(odometry)} odometry + {len(local)} local SLAM pairs "
          f"[built in {build_time:.2f} s]")
    # Load (or compile) the numba kernels outside the timings.
    small = cs.select(cs.node < 200)
    optimize(init[:200], init_submaps[:3], small.select(small.submap < 3), max_num_iterations=2)
    for huber in (1e1, None):
        result = optimize(init, init_submaps, cs, odometry, local, huber_scale=huber,
                          max_num_iterations=args.max_iterations)
        s = result.summary
        err = residuals(result.node_poses, result.submap_poses, cs)
        print(f"huber_scale={huber}: {s.time:.2f} s total, {s.linear_solver_time:.2f} s in the linear solver, "
              f"{s.iterations} iterations ({s.successful_steps} successful, "
              f"{1000 * s.time / max(s.iterations, 1):.0f} ms each), {s.termination}; "
              f"cost {s.initial_cost:.3g} -> {s.final_cost:.3g}; {s.num_parameters} parameters, "
              f"{s.num_residual_blocks} residual blocks, {s.factor_nnz} non-zeros in the factor")
        print(f"    node RMS error {rms(init, gt):.3f} m -> {rms(result.node_poses, gt):.3f} m; "
              f"median loop-closure error {np.median(np.hypot(*err[cs.is_loop_closure, :2].T)) * 1000:.1f} mm")


if __name__ == "__main__":
    main()
