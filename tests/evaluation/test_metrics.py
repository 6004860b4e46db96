import gzip
import json
import math

import numpy as np
import pytest
from support import shared_path

from carto_cli.core.errors import CartoError, FormatError
from carto_cli.evaluation.metrics import (
    Relations,
    align_se2,
    ate,
    evaluate,
    format_table,
    interpolate_poses,
    read_relations,
    relation_error,
    rpe,
    to_json,
)
from carto_cli.io.trajectory import Trajectory, write_trajectory


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def reference(n=200, seed=3) -> Trajectory:
    """A wandering planar path at 10 Hz, yaw crossing ±π several times."""
    rng = np.random.default_rng(seed)
    t = 100.0 + 0.1 * np.arange(n)
    theta = np.cumsum(rng.uniform(-0.3, 0.5, n))
    step = 0.1 * np.stack([np.cos(theta), np.sin(theta)], axis=1)
    return Trajectory(t, np.cumsum(step, axis=0), wrap(theta))


def transformed(traj: Trajectory, tx, ty, phi) -> Trajectory:
    c, s = math.cos(phi), math.sin(phi)
    xy = traj.xy @ np.array([[c, s], [-s, c]]) + [tx, ty]
    return Trajectory(traj.t.copy(), xy, wrap(traj.theta + phi))


def relations_of(traj: Trajectory, pairs) -> Relations:
    i, j = np.asarray(pairs).T
    c, s = np.cos(traj.theta[i]), np.sin(traj.theta[i])
    d = traj.xy[j] - traj.xy[i]
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)
    return Relations(traj.t[i], traj.t[j], np.column_stack([local, wrap(traj.theta[j] - traj.theta[i])]))


# --------------------------------------------------------------------------- interpolation


def test_interpolation_linear_and_shortest_arc():
    traj = Trajectory.from_poses([0.0, 1.0, 3.0], [[0, 0, 3.0], [1, 2, -3.0], [3, 2, -3.0]])
    xy, th, ok = interpolate_poses(traj, [0.0, 0.5, 2.0, 3.0])
    assert ok.all()
    np.testing.assert_allclose(xy, [[0, 0], [0.5, 1.0], [2, 2], [3, 2]])
    # 3.0 -> -3.0 is a 0.283 rad turn across π, not 6 rad the other way.
    assert wrap(th[1] - math.pi) == pytest.approx(0.0, abs=1e-12)
    assert wrap(th[2] + 3.0) == pytest.approx(0.0, abs=1e-12)


def test_interpolation_outside_span_gaps_and_tolerance():
    traj = Trajectory.from_poses([0.0, 1.0, 10.0], [[0, 0, 0], [1, 0, 0], [2, 0, 0]])
    _, _, ok = interpolate_poses(traj, [-0.1, -1e-9, 10.0 + 1e-9, 10.1])
    assert ok.tolist() == [False, True, True, False]
    _, _, ok = interpolate_poses(traj, [0.5, 1.0, 5.0, 10.0], max_gap=2.0)
    assert ok.tolist() == [True, True, False, True]


# --------------------------------------------------------------------------- relation error


def test_relation_error_is_zero_for_a_rigidly_moved_trajectory():
    gt = reference()
    rel = relations_of(gt, [(i, i + 1) for i in range(len(gt) - 1)] + [(5, 150), (20, 199)])
    r = relation_error(transformed(gt, 4.0, -2.0, 2.5), rel)
    assert r.used == len(rel) and r.skipped == 0
    assert r.translation.max < 1e-9 and r.rotation.max < 1e-9


def test_relation_error_of_a_known_perturbation():
    gt = reference()
    moved = Trajectory(gt.t, gt.xy.copy(), gt.theta.copy())
    moved.xy[50] += [0.3, 0.4]
    moved.theta[50] = wrap(moved.theta[50] + math.radians(2))
    rel = relations_of(gt, [(10, 20), (49, 50), (50, 51)])
    r = relation_error(moved, rel)
    # (49, 50): the end point moved 0.5 m; (50, 51): the frame moved and turned, so the
    # translation error is |R(-2°)(p51 - p50 - δ) - (p51 - p50)| — both rotate by 2°.
    assert r.translation_errors[0] == pytest.approx(0.0, abs=1e-12)
    assert r.translation_errors[1] == pytest.approx(0.5)
    assert r.rotation_errors.tolist() == pytest.approx([0.0, 2.0, 2.0])
    assert r.translation.mean == pytest.approx(np.mean(r.translation_errors))
    assert r.translation.std == pytest.approx(np.std(r.translation_errors))


def test_relations_outside_the_trajectory_are_skipped_and_counted():
    gt = reference()
    rel = relations_of(gt, [(i, i + 1) for i in range(len(gt) - 1)])
    part = Trajectory(gt.t[50:120], gt.xy[50:120], gt.theta[50:120])
    r = relation_error(part, rel)
    assert (r.used, r.skipped) == (69, len(rel) - 69)
    assert r.used_mask.sum() == 69 and r.translation.max < 1e-9
    with pytest.raises(CartoError, match="no relation falls within"):
        relation_error(Trajectory.from_poses([0.0, 1.0], [[0, 0, 0], [1, 0, 0]]), rel)


def test_read_relations_malformed(tmp_path):
    p = tmp_path / "rel.txt"
    p.write_text("1 2 0.1 0 0 0 0 0.2\n2 3 0.1 0 0 0 0\n")
    with pytest.raises(FormatError, match="line 2: expected 8 columns"):
        read_relations(p)


def test_eval_says_a_relations_file_not_a_relations(tmp_path):
    """Issue 42, item 10: a relations file with the wrong column count was "expected 8 columns for a relations"."""
    p = tmp_path / "rel.txt"
    p.write_text("1 2 0.1 0 0 0 0\n")
    with pytest.raises(FormatError) as e:
        read_relations(p)
    assert "line 1: expected 8 columns in a relations file, got 7" in str(e.value)


# --------------------------------------------------------------------------- ATE and RPE


def test_alignment_recovers_the_transform():
    gt = reference()
    est = transformed(gt, 4.0, -2.0, 2.5)
    tx, ty, phi = align_se2(est.xy, gt.xy)
    # est = R(2.5)·gt + t  =>  gt = R(-2.5)·(est - t)
    back = transformed(est, 0, 0, phi)
    np.testing.assert_allclose(back.xy + [tx, ty], gt.xy, atol=1e-9)
    assert wrap(phi + 2.5) == pytest.approx(0.0, abs=1e-12)


def test_ate_after_alignment_and_without():
    gt = reference()
    est = transformed(gt, 4.0, -2.0, 2.5)
    r = ate(est, gt)
    assert r.used == len(gt) and r.translation.rmse < 1e-9 and r.rotation.max < 1e-7
    raw = ate(est, gt, align=False)
    assert raw.translation.mean > 1.0 and raw.alignment == (0.0, 0.0, 0.0)


def test_ate_with_noise_and_association_by_interpolation():
    gt = reference()
    rng = np.random.default_rng(0)
    noisy = Trajectory(gt.t, gt.xy + rng.normal(0, 0.05, gt.xy.shape), gt.theta)
    # The estimate at other times (every 2nd pose, shifted by half a step): interpolating it
    # at the reference's times gives back a close approximation.
    half = Trajectory(gt.t[::2] + 0.05, (noisy.xy[::2] + noisy.xy[1::2]) / 2,
                      wrap(gt.theta[::2] + wrap(gt.theta[1::2] - gt.theta[::2]) / 2))
    r = ate(half, gt)
    assert r.skipped == 1 + 1   # the first reference pose precedes it, the last follows it
    assert r.translation.rmse < 0.1
    by_traj = ate(half, gt, associate="trajectory")
    assert (by_traj.used, by_traj.skipped, by_traj.associate) == (len(half), 0, "trajectory")
    with pytest.raises(CartoError, match="associate must be"):
        ate(half, gt, associate="nearest")
    with pytest.raises(CartoError, match="at least 2 poses"):
        ate(Trajectory.from_poses([0.0, 1.0], [[0, 0, 0], [1, 0, 0]]), gt)


def test_rpe_frames_and_seconds():
    gt = reference()
    est = Trajectory(gt.t, gt.xy.copy(), gt.theta.copy())
    est.xy[100:] += [1.0, 0.0]     # one jump: only the pairs spanning it see it
    r = rpe(est, gt, 1, "frames")
    assert r.used == len(gt) - 1
    assert np.count_nonzero(r.translation_errors > 1e-9) == 1
    assert r.translation.max == pytest.approx(1.0)
    s = rpe(est, gt, 0.5, "s")
    assert s.unit == "s" and s.used == len(gt) - 5
    assert np.count_nonzero(s.translation_errors > 1e-9) == 5
    with pytest.raises(CartoError, match="positive integer"):
        rpe(est, gt, 1.5, "frames")
    with pytest.raises(CartoError, match="unit must be"):
        rpe(est, gt, 1, "m")


# --------------------------------------------------------------------------- whole evaluation and output


def test_evaluate_files_and_outputs(tmp_path):
    gt = reference()
    est = transformed(gt, 1.0, 1.0, 0.3)
    gt_path = write_trajectory(tmp_path / "gt.txt", gt, "xyt")
    est_path = write_trajectory(tmp_path / "est.tum", est, "tum")
    rel = relations_of(gt, [(i, i + 10) for i in range(0, len(gt) - 10, 5)])
    rel_path = tmp_path / "rel.txt"
    rel_path.write_text("".join(f"{a:.9f} {b:.9f} {d[0]:.9f} {d[1]:.9f} 0 0 0 {d[2]:.9f}\n"
                                for a, b, d in zip(rel.t1, rel.t2, rel.d)))
    ev = evaluate(est_path, rel_path, gt_path, rpe_delta=1.0)
    assert ev.relations.skipped == 0 and ev.relations.translation.max < 1e-5
    assert ev.ate.translation.max < 1e-5 and ev.rpe.translation.max < 1e-5
    j = to_json(ev)
    json.dumps(j)
    assert j["schema_version"] == 1 and j["trajectory"] == str(est_path)
    assert j["relations"]["used"] == len(rel) and j["ate"]["aligned"] is True
    assert set(j["relations"]["translation_m"]) == {"n", "mean", "std", "rmse", "median", "max"}
    table = format_table(ev)
    assert "relations trans [m]" in table and "ATE rot [deg]" in table and "RPE 1s trans [m]" in table
    with pytest.raises(CartoError, match="nothing to evaluate against"):
        evaluate(est_path)


# --------------------------------------------------------------------------- the real bench


def carmen_odometry(path) -> Trajectory:
    """The noisy odometry of a bench log: FLASER n r1..rn x y theta x y theta t ..."""
    rows = []
    with gzip.open(path, "rt") as f:
        for line in f:
            if line.startswith("FLASER"):
                fields = line.split()
                n = int(fields[1])
                rows.append(fields[2 + n:2 + n + 7])
    a = np.array(rows, dtype=np.float64)
    return Trajectory.from_arrays(a[:, 6], a[:, 0], a[:, 1], a[:, 2])


def test_bench_ground_truth_has_no_relation_error():
    ev = evaluate(shared_path("bench", "intel", "groundtruth.txt"), shared_path("bench", "intel", "relations.txt"))
    r = ev.relations
    assert (r.used, r.skipped) == (3909, 0)
    assert r.translation.max < 1e-5 and r.rotation.max < 1e-3


def test_bench_odometry_matches_the_peers_figure():
    odom = carmen_odometry(shared_path("bench", "intel", "scans.clf.gz"))
    assert len(odom) == 910
    r = relation_error(odom, read_relations(shared_path("bench", "intel", "relations.txt")))
    assert r.skipped == 0
    assert r.translation.mean == pytest.approx(11.29, abs=0.01)   # PEERS.md: odometry 11.29 m
