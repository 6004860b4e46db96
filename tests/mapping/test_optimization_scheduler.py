"""optimization_scheduler: the periodic optimization solved inline or beside the caller gives the same poses."""
import numpy as np

from carto_cli.core.timing import StageTimer
from carto_cli.mapping.constraints import ConstraintKind, ConstraintSet
from carto_cli.mapping.optimization_scheduler import OPTIMIZER_THREAD, OptimizationProblem, OptimizationScheduler
from carto_cli.options import load_options


def _problem():
    """Four nodes in one submap, the last pulled 0.3 m sideways by a loop closure."""
    local = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    cs = ConstraintSet()
    for i, pose in enumerate(local):
        cs.add(0, i, pose, 1e5, 1e5, ConstraintKind.INTRA_SUBMAP)
    cs.add(0, 3, (3.0, 0.3, 0.0), 1e5, 1e5, ConstraintKind.INTER_SUBMAP)
    return OptimizationProblem.of(load_options(None).pose_graph, local_poses=local, global_poses=local,
                                  trajectories=np.zeros(4, np.int64), odometry=np.full((4, 3), np.nan),
                                  submap_poses=np.zeros((1, 3)), constraints=cs, final=True)


def test_a_problem_is_a_copy_and_without_odometry_has_no_odometry_terms():
    problem = _problem()
    assert problem.odometry is None
    assert problem.max_num_iterations == load_options(None).pose_graph.max_num_final_iterations
    result, ns = problem.solve()
    assert ns > 0 and result.node_poses.shape == (4, 3) and result.node_poses[3, 1] > 0.0


def test_beside_the_caller_or_inline_the_result_is_the_same():
    inline, beside = OptimizationScheduler(), OptimizationScheduler()
    assert inline.take(StageTimer()) is None  # nothing started
    t1, t2 = StageTimer(), StageTimer()
    inline.start(_problem(), 4, 1, jobs=1, timer=t1)
    beside.start(_problem(), 4, 1, jobs=2, timer=t2)
    (r1, n1, m1), (r2, n2, m2) = inline.take(t1), beside.take(t2)
    beside.close()
    np.testing.assert_array_equal(r1.node_poses, r2.node_poses)
    assert (n1, m1) == (n2, m2) == (4, 1)
    assert t1.snapshot().find("optimization") is not None  # solved where it was started
    assert t2.snapshot().find(f"{OPTIMIZER_THREAD}/optimization") is not None  # on the solver's thread
    assert inline.running is None and beside.running is None
