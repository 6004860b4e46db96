import math

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from reference.optimization import block_matrix_to_sparse, huber_rho, jacobian_blocks, sparse_jacobian

from carto_cli.core.transform import compose, relative
from carto_cli.mapping.constraints import Constraint, ConstraintKind, ConstraintSet
from carto_cli.mapping.optimization import NodePairs, optimize, residuals
from carto_cli.mapping.optimization.block_cholesky import BlockSystem
from carto_cli.mapping.optimization.problem import Edges, build_edges, cost_kernel, free_columns, model_kernel

# Cartographer's default weights (pose_graph.lua).
MATCHER = (5e2, 1.6e3)
LOOP = (1.1e4, 1e5)
LOCAL_SLAM = (1e5, 1e5)


def rms(a, b) -> float:
    return float(np.sqrt(np.mean(np.sum((a[:, :2] - b[:, :2]) ** 2, axis=1))))


def two_lap_graph(seed=0, n=200, per_submap=20, radius=4.0, noise=(0.005, 0.001)):
    """Two laps of a circle; submap j starts at node 20j and holds 40 nodes (two active submaps).

    Intra-submap constraints, loop closures (second lap against first-lap submaps)
    and the local SLAM chain are ground truth plus noise; the initial guess is an
    odometry chain with 1 % scale and 4 mrad/step heading bias.
    """
    rng = np.random.default_rng(seed)
    sigma = np.array([noise[0], noise[0], noise[1]])
    phi = 2 * 2 * math.pi * np.arange(n) / n
    gt = np.stack([radius * np.sin(phi), radius * (1 - np.cos(phi)), phi], axis=1)
    gt[:, 2] = (gt[:, 2] + math.pi) % (2 * math.pi) - math.pi
    m = n // per_submap
    sub_gt = gt[::per_submap].copy()
    sub_gt[:, 2] = 0.0  # Cartographer's submap frames are axis-aligned in the local frame
    centres = np.array([gt[j * per_submap:(j + 2) * per_submap, :2].mean(axis=0) for j in range(m)])
    cs = ConstraintSet()
    for i in range(n):
        own = {i // per_submap, i // per_submap - 1}
        for j in range(m):
            if j in own:
                cs.add(j, i, relative(sub_gt[j], gt[i]) + rng.normal(0, sigma), *MATCHER, False)
            elif (abs(j - i // per_submap) >= 3 and np.linalg.norm(centres[j] - gt[i, :2]) < 4.0
                  and rng.random() < 0.3):
                cs.add(j, i, relative(sub_gt[j], gt[i]) + rng.normal(0, sigma), *LOOP, True)
    rel_gt = relative(gt[:-1], gt[1:])
    local = NodePairs(np.arange(n - 1), np.arange(1, n), rel_gt + rng.normal(0, sigma, rel_gt.shape), *LOCAL_SLAM)
    steps = rel_gt * [1.01, 1.01, 1.0] + [0.0, 0.0, 0.004]
    init = [gt[0]]
    for step in steps:
        init.append(compose(init[-1], step))
    init = np.array(init)
    sub_init = init[::per_submap].copy()
    sub_init[:, 2] = 0.0
    return gt, sub_gt, init, sub_init, cs, local


def random_problem(seed=1, n=30, m=4, k=120):
    """Poses all over the circle (angles on both sides of ±π) and constraints near the truth."""
    rng = np.random.default_rng(seed)
    nodes = np.column_stack([rng.uniform(-5, 5, (n, 2)), rng.uniform(-math.pi, math.pi, n)])
    submaps = np.column_stack([rng.uniform(-5, 5, (m, 2)), rng.uniform(-math.pi, math.pi, m)])
    s = rng.integers(0, m, k)
    i = rng.integers(0, n, k)
    rel = relative(submaps[s], nodes[i]) + rng.normal(0, 0.3, (k, 3))
    cs = ConstraintSet.from_arrays(s, i, rel, rng.uniform(1, 5, k), rng.uniform(1, 5, k), rng.random(k) < 0.5)
    pairs = NodePairs.consecutive(nodes + rng.normal(0, 0.3, nodes.shape), translation_weight=3.0,
                                  rotation_weight=2.0)
    return nodes, submaps, cs, pairs


# --------------------------------------------------------------------------- derivatives


def test_jacobian_matches_finite_differences():
    nodes, submaps, cs, pairs = random_problem()
    edges = build_edges(len(nodes), len(submaps), cs, [pairs])
    x = np.concatenate([submaps, nodes])
    r0, ja, jb = jacobian_blocks(x, edges)
    assert np.abs(r0).max() > 0.1  # not trivially at a minimum
    eps = 1e-6
    for blocks, of_start in ((ja, True), (jb, False)):
        for d in range(3):
            numeric = (_perturbed_residual(x, edges, of_start, d, eps)
                       - _perturbed_residual(x, edges, of_start, d, -eps)) / (2 * eps)
            np.testing.assert_allclose(blocks[:, :, d], numeric, rtol=1e-6, atol=1e-6)


def _perturbed_residual(x, edges, of_start, d, eps):
    """Weighted residuals with each block's start (or end) pose shifted by eps along d.

    Every block gets private copies of its two poses, so all blocks can be
    perturbed at once without a pose shared by several blocks moving twice.
    """
    k = len(edges)
    poses = np.concatenate([x[edges.start], x[edges.end]])
    private = Edges(np.arange(k), np.arange(k) + k, edges.measured, edges.translation_weight,
                         edges.rotation_weight, edges.robust)
    poses[np.arange(k) if of_start else np.arange(k) + k, d] += eps
    return jacobian_blocks(poses, private)[0]


def test_kernels_assemble_the_robust_normal_equations_and_solve_them():
    nodes, submaps, cs, pairs = random_problem(seed=2)
    edges = build_edges(len(nodes), len(submaps), cs, [pairs])
    x = np.concatenate([submaps, nodes])
    column = free_columns(edges, len(x), np.array([0, 7]))
    huber = 1.0
    system = BlockSystem(edges, column, int(column.max() + 1))
    cost, h_blocks, rhs = system.linearize(x, edges, huber)

    u, ja, jb = jacobian_blocks(x, edges)
    rho, rho1 = huber_rho(np.sum(u * u, axis=1), edges.robust, huber)
    assert np.count_nonzero(rho1 < 1) > 10  # the Huber tail is exercised
    scale = np.sqrt(rho1)
    jac = sparse_jacobian(ja * scale[:, None, None], jb * scale[:, None, None], edges, column)
    r = (u * scale[:, None]).ravel()

    h = block_matrix_to_sparse(system, h_blocks).toarray()
    jtj = (jac.T @ jac).toarray()
    np.testing.assert_allclose(h, jtj, atol=1e-9 * np.abs(jtj).max())
    g = np.empty_like(rhs)
    g[system.perm] = -rhs
    np.testing.assert_allclose(g.ravel(), jac.T @ r, atol=1e-9 * np.abs(g).max())
    assert cost == pytest.approx(0.5 * rho.sum(), rel=1e-12)
    args = (*edges.kernel_args, huber)
    assert cost_kernel(x, *args) == pytest.approx(cost, rel=1e-12)

    radius = 10.0
    step = system.solve(h_blocks, rhs, radius)
    reference = jtj + np.diag(np.clip(np.diag(jtj), 1e-6, 1e32) / radius)
    expected = spla.spsolve(sp.csc_matrix(reference), -g.ravel())
    unpermuted = np.empty_like(step)
    unpermuted[system.perm] = step
    np.testing.assert_allclose(unpermuted.ravel(), expected, rtol=1e-8, atol=1e-10)
    model = model_kernel(x, *args, system.rs, system.re, step)
    assert model == pytest.approx(float(np.sum((jac @ unpermuted.ravel()) ** 2)), rel=1e-10)


def test_block_cholesky_reports_an_indefinite_system():
    nodes, submaps, cs, pairs = random_problem(seed=3)
    edges = build_edges(len(nodes), len(submaps), cs, [pairs])
    x = np.concatenate([submaps, nodes])
    column = free_columns(edges, len(x), np.array([0]))
    system = BlockSystem(edges, column, int(column.max() + 1))
    _, h_blocks, rhs = system.linearize(x, edges, math.inf)
    assert system.solve(-h_blocks, rhs, 1e4) is None
    assert system.solve(h_blocks, rhs, 1e4) is not None  # the workspace was left clean


# --------------------------------------------------------------------------- optimisation


def test_recovers_ground_truth_from_a_drifting_chain():
    gt, sub_gt, init, sub_init, cs, local = two_lap_graph()
    assert cs.num_loop_closures > 50
    before = rms(init, gt)
    result = optimize(init, sub_init, cs, None, local)
    after = rms(result.node_poses, gt)
    # ~1.8 m of drift comes down to ~2 cm, about what the constraint noise allows.
    assert before > 1.0
    assert after < 0.05
    assert rms(result.submap_poses, sub_gt) < 0.05
    angle_error = np.abs((result.node_poses[:, 2] - gt[:, 2] + math.pi) % (2 * math.pi) - math.pi)
    assert angle_error.max() < 0.02
    s = result.summary
    assert s.converged and s.termination == "function_tolerance"
    assert s.final_cost < 1e-2 * s.initial_cost
    assert s.num_residual_blocks == len(cs) + len(local)
    assert s.num_parameters == 3 * (len(init) + len(sub_init) - 1)
    np.testing.assert_array_equal(result.submap_poses[0], sub_init[0])  # the gauge
    assert np.all((result.node_poses[:, 2] >= -math.pi) & (result.node_poses[:, 2] < math.pi))
    # After optimisation the loop closures agree with the poses to about the noise.
    err = residuals(result.node_poses, result.submap_poses, cs)
    assert np.median(np.hypot(err[:, 0], err[:, 1])) < 0.02


def test_huber_loss_rejects_a_false_loop_closure():
    gt, sub_gt, init, sub_init, cs, local = two_lap_graph()
    clean = rms(optimize(init, sub_init, cs, None, local).node_poses, gt)
    bad = cs.add(1, 150, relative(sub_gt[1], gt[150]) + [5.0, 0.0, 0.0], *LOOP, True)  # 5 m off

    robust = optimize(init, sub_init, cs, None, local, huber_scale=10.0)
    plain = optimize(init, sub_init, cs, None, local, huber_scale=None)
    robust_err = rms(robust.node_poses, gt)
    plain_err = rms(plain.node_poses, gt)
    # ~2 cm with or without the outlier under Huber; ~15 cm when it is a plain square.
    assert robust_err < 0.05
    assert robust_err < 1.2 * clean
    assert plain_err > 0.1
    assert plain_err > 3 * robust_err
    no_huber = optimize(init, sub_init, cs, None, local, huber_scale=math.inf)
    assert rms(no_huber.node_poses, gt) == pytest.approx(plain_err)
    # The residuals single the outlier out after the robust optimisation.
    err = np.hypot(*residuals(robust.node_poses, robust.submap_poses, cs)[:, :2].T)
    assert err[bad] > 4.5
    assert np.delete(err, bad).max() < 0.3
    assert robust.summary.num_loop_closures_in_huber_tail >= 1
    assert plain.summary.num_loop_closures_in_huber_tail == 0


def test_consecutive_pairs_are_weighted_against_each_other():
    # Two nodes, one submap pinning the first: local SLAM says 1.0 m, odometry 1.2 m.
    cs = ConstraintSet()
    cs.add(0, 0, (0.0, 0.0, 0.0), 1e3, 1e3)
    local = NodePairs.consecutive([(0, 0, 0), (1.0, 0, 0)], translation_weight=1.0, rotation_weight=1.0)
    odometry = NodePairs.consecutive([(5, 5, 1.0), compose((5, 5, 1.0), (1.2, 0, 0))],
                                     translation_weight=2.0, rotation_weight=1.0)
    result = optimize([(0, 0, 0), (0.5, 0.3, 0.2)], [(0, 0, 0)], cs, odometry, local)
    expected = (1.0 * 1.0 + 4.0 * 1.2) / 5.0  # weights enter squared
    np.testing.assert_allclose(result.node_poses[1], (expected, 0.0, 0.0), atol=1e-7)
    np.testing.assert_allclose(result.node_poses[0], (0, 0, 0), atol=1e-9)


def test_consecutive_pairs_respect_trajectories_gaps_and_missing_odometry():
    poses = np.array([(0, 0, 0), (1, 0, 0), (2, 0, 0), (3, 0, 0), (4, 0, 0), (5, 0, 0)], dtype=float)
    pairs = NodePairs.consecutive(poses, [0, 0, 0, 1, 1, 1], translation_weight=1.0, rotation_weight=2.0)
    assert pairs.first.tolist() == [0, 1, 3, 4]
    np.testing.assert_allclose(pairs.relative, [(1, 0, 0)] * 4)
    assert pairs.rotation_weight.tolist() == [2.0] * 4
    trimmed = NodePairs.consecutive(poses, [0] * 6, node_indices=[0, 1, 2, 4, 5, 6],
                                    translation_weight=1.0, rotation_weight=1.0)
    assert trimmed.first.tolist() == [0, 1, 3, 4]
    poses[2] = np.nan  # no odometry at that node's time
    odo = NodePairs.consecutive(poses, translation_weight=1.0, rotation_weight=1.0)
    assert odo.first.tolist() == [0, 3, 4]
    assert len(NodePairs.consecutive(np.empty((0, 3)), translation_weight=1, rotation_weight=1)) == 0


def test_gauge_fixed_poses_and_a_disconnected_trajectory():
    gt, sub_gt, init, sub_init, cs, local = two_lap_graph(seed=1)
    n, m = len(init), len(sub_init)
    # A second trajectory, shifted and rotated, with no loop closure to the first.
    shift = np.array([30.0, -10.0, 0.7])
    gt2 = compose(shift, gt)
    init2 = compose(shift, init) + [0.3, -0.2, 0.0]
    cs2 = ConstraintSet.from_arrays(cs.submap + m, cs.node + n, cs.relative, cs.translation_weight,
                                    cs.rotation_weight, cs.is_loop_closure)
    both = ConstraintSet.from_arrays(np.r_[cs.submap, cs2.submap], np.r_[cs.node, cs2.node],
                                     np.r_[cs.relative, cs2.relative],
                                     np.r_[cs.translation_weight, cs2.translation_weight],
                                     np.r_[cs.rotation_weight, cs2.rotation_weight],
                                     np.r_[cs.is_loop_closure, cs2.is_loop_closure])
    sub_init2 = init2[::20].copy()
    local2 = NodePairs(np.r_[local.first, local.first + n], np.r_[local.second, local.second + n],
                       np.r_[local.relative, local.relative], *LOCAL_SLAM)
    result = optimize(np.r_[init, init2], np.r_[sub_init, sub_init2], both, None, local2,
                      fixed_nodes=[5])
    assert np.isfinite(result.node_poses).all()
    np.testing.assert_array_equal(result.submap_poses[0], sub_init[0])
    np.testing.assert_allclose(result.node_poses[5], init[5])  # held, angle only re-wrapped
    # The second trajectory's gauge is its first submap, which therefore stays put.
    np.testing.assert_allclose(result.submap_poses[m], sub_init2[0])
    # Its shape is still recovered relative to that anchor.
    rel_est = relative(result.submap_poses[m], result.node_poses[n:])
    rel_gt = relative(compose(shift, sub_gt[0]), gt2)
    assert rms(rel_est, rel_gt) < 0.1
    assert result.summary.num_parameters == 3 * (2 * n + 2 * m - 3)


def test_iteration_limit_and_degenerate_inputs():
    _, _, init, sub_init, cs, local = two_lap_graph()
    one = optimize(init, sub_init, cs, None, local, max_num_iterations=1)
    assert one.summary.iterations == 1 and one.summary.termination == "max_iterations"
    assert not one.summary.converged
    assert one.summary.final_cost < one.summary.initial_cost
    none = optimize(init, sub_init, cs, None, local, max_num_iterations=0)
    np.testing.assert_allclose(none.node_poses, init)
    empty = optimize(init[:3], sub_init[:1], ConstraintSet())
    assert empty.summary.termination == "no_residuals"
    np.testing.assert_allclose(empty.node_poses, init[:3])
    with pytest.raises(ValueError, match="node index out of range"):
        optimize(init[:3], sub_init[:1], ConstraintSet.from_arrays([0], [3], [(0, 0, 0)], 1, 1))
    with pytest.raises(ValueError, match="submap index out of range"):
        optimize(init[:3], sub_init[:1], ConstraintSet.from_arrays([1], [0], [(0, 0, 0)], 1, 1))
    with pytest.raises(ValueError, match="huber_scale"):
        optimize(init, sub_init, cs, huber_scale=0.0)


# --------------------------------------------------------------------------- ConstraintSet


def test_constraint_set_grows_selects_and_removes():
    cs = ConstraintSet(capacity=2)
    for k in range(5):
        assert cs.add(k % 2, k, (k, 0.0, 0.1), 1.0, 2.0, k == 3) == k
    span = cs.extend([2, 3], [7, 8], [(1, 1, 1), (2, 2, 2)], [3.0, 4.0], 5.0, True)
    assert span == slice(5, 7)
    assert len(cs) == 7 and cs.num_loop_closures == 3
    assert cs.node.tolist() == [0, 1, 2, 3, 4, 7, 8]
    assert cs.translation_weight.tolist() == [1, 1, 1, 1, 1, 3, 4]
    assert cs.rotation_weight.tolist()[-2:] == [5.0, 5.0]
    c = cs[3]
    assert isinstance(c, Constraint) and c.kind is ConstraintKind.INTER_SUBMAP and c.is_loop_closure
    assert cs[-1].node == 8
    with pytest.raises(IndexError):
        cs[7]
    loops = cs.select(cs.is_loop_closure)
    assert loops.node.tolist() == [3, 7, 8]
    assert ConstraintSet.from_constraints(list(cs)).relative.tolist() == cs.relative.tolist()
    copy = cs.copy()
    assert cs.remove(cs.node >= 7) == 2
    assert len(cs) == 5 and len(copy) == 7
    assert cs.add(0, 9, (0, 0, 0), 1, 1) == 5 and cs.node[-1] == 9
    with pytest.raises(ValueError):
        cs.remove([True])


def _pose_graph_pattern(rng, n: int, closures: int) -> tuple[np.ndarray, np.ndarray]:
    """A chain of n blocks with ``closures`` random links between distant ones, both directions."""
    a = np.concatenate([np.arange(n - 1), rng.integers(0, n, closures)])
    b = np.concatenate([np.arange(1, n), rng.integers(0, n, closures)])
    keep = a != b
    return np.concatenate([a[keep], b[keep]]), np.concatenate([b[keep], a[keep]])


def _fill(rows: np.ndarray, cols: np.ndarray, iperm: np.ndarray, n: int) -> int:
    """Off-diagonal blocks of the Cholesky factor after the symmetric permutation ``iperm`` (old -> new)."""
    dense = np.zeros((n, n))
    dense[iperm[rows], iperm[cols]] = -1.0
    dense += np.diag(np.abs(dense).sum(axis=1) + 1.0)
    return int(np.count_nonzero(np.abs(np.tril(np.linalg.cholesky(dense), -1)) > 0))


def test_the_ordering_is_a_permutation_with_no_fill_on_trees_and_near_mmd_on_pose_graphs():
    from carto_cli.mapping.optimization.block_cholesky import block_ordering

    rng = np.random.default_rng(3)
    # a star: eliminating the hub first would fill every pair of leaves; minimum degree takes it last
    n = 12
    rows = np.concatenate([np.zeros(n - 1, int), np.arange(1, n)])
    cols = np.concatenate([np.arange(1, n), np.zeros(n - 1, int)])
    iperm = block_ordering(rows, cols, n)
    assert sorted(iperm) == list(range(n)) and iperm[0] >= n - 2
    assert _fill(rows, cols, iperm, n) == n - 1
    # random trees: no fill at all
    for _ in range(5):
        n = int(rng.integers(2, 60))
        parent = np.array([int(rng.integers(0, v)) for v in range(1, n)])
        rows = np.concatenate([np.arange(1, n), parent])
        cols = np.concatenate([parent, np.arange(1, n)])
        iperm = block_ordering(rows, cols, n)
        assert sorted(iperm) == list(range(n))
        assert _fill(rows, cols, iperm, n) == n - 1
    # pose graphs: as little fill as SuperLU's multiple minimum degree, give or take a tenth
    for n, closures in ((60, 5), (150, 20), (300, 60)):
        rows, cols = _pose_graph_pattern(rng, n, closures)
        iperm = block_ordering(rows, cols, n)
        assert sorted(iperm) == list(range(n))
        off = rows != cols
        values = np.where(off, -1.0, 1.0)
        stand_in = sp.csc_matrix((values, (rows, cols)), shape=(n, n)) + sp.identity(n, format="csc") * n
        mmd = spla.splu(stand_in.tocsc(), permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                        options={"SymmetricMode": True}).perm_c
        assert _fill(rows, cols, iperm, n) <= 1.1 * _fill(rows, cols, np.asarray(mmd), n) + 2
    # no links at all, and nothing to order
    assert sorted(block_ordering(np.arange(4), np.arange(4), 4)) == [0, 1, 2, 3]
    assert len(block_ordering(np.zeros(0, int), np.zeros(0, int), 0)) == 0


def test_the_ordering_of_sorted_pairs_is_the_general_ones():
    """BlockSystem's pairs are unique and sorted already: pair_ordering builds the same rows without the sort."""
    from carto_cli.mapping.optimization.block_cholesky import block_ordering, pair_ordering

    rng = np.random.default_rng(5)
    patterns = [_pose_graph_pattern(rng, n, closures) for n, closures in ((60, 5), (150, 20), (300, 60))]
    for _ in range(40):
        n = int(rng.integers(1, 80))
        a, b = rng.integers(0, n, (2, int(rng.integers(0, 300))))
        patterns.append((np.concatenate([a, b]), np.concatenate([b, a])))  # with self-pairs and repeats
    for rows, cols in patterns:
        n = int(max(rows.max(initial=-1), cols.max(initial=-1))) + 1
        keys = np.unique(np.minimum(rows, cols) * n + np.maximum(rows, cols))
        lo, hi = keys // n, keys % n
        np.testing.assert_array_equal(pair_ordering(lo, hi, n), block_ordering(rows, cols, n))
    assert len(pair_ordering(np.zeros(0, int), np.zeros(0, int), 0)) == 0


def test_connected_parts_match_scipys():
    import scipy.sparse.csgraph as csgraph

    from carto_cli.mapping.optimization.problem import connected_parts

    rng = np.random.default_rng(5)
    for _ in range(20):
        n = int(rng.integers(1, 80))
        k = int(rng.integers(0, n + 1))
        a, b = rng.integers(0, n, k), rng.integers(0, n, k)
        label = connected_parts(a, b, n)
        _, expected = csgraph.connected_components(sp.coo_matrix((np.ones(k), (a, b)), shape=(n, n)), directed=False)
        # the same parts, numbered by their lowest pose
        assert np.array_equal(label, expected)
