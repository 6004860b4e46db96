"""`carto eval` as a library call: the scores, their JSON form, and gates only when limits are given."""
import pytest

from carto_cli.commands.eval import run_eval
from carto_cli.core.errors import CartoError


@pytest.fixture
def files(tmp_path):
    traj = tmp_path / "t.txt"
    traj.write_text("0 0 0 0\n1 1 0 0\n2 2 0 0\n")
    rel = tmp_path / "r.txt"
    rel.write_text("0 1 1.0 0 0 0 0 0\n1 2 1.3 0 0 0 0 0\n")
    gt = tmp_path / "gt.txt"
    gt.write_text("0 0 0 0\n1 1.1 0 0\n2 2.05 0.1 0\n")
    return traj, rel, gt


def test_relations_only(files):
    traj, rel, _ = files
    run = run_eval(traj, relations=rel)
    assert run.gates is None
    assert run.data["relations"]["translation_m"]["mean"] == pytest.approx(0.15)
    assert run.data["ate"] is None and run.result.relations is not None


def test_ground_truth_adds_ate_and_rpe(files):
    traj, rel, gt = files
    run = run_eval(traj, relations=rel, ground_truth=gt, rpe_delta=1.0)
    assert run.data["ate"] is not None and run.data["rpe"] is not None


def test_gates(files):
    traj, rel, _ = files
    passed = run_eval(traj, relations=rel, max_trans_error=0.5)
    assert [g.passed for g in passed.gates] == [True]
    failed = run_eval(traj, relations=rel, max_trans_error=0.1, max_rot_error=1.0)
    assert [(g.name, g.passed) for g in failed.gates] == [("relations/translation_m/mean", False),
                                                          ("relations/rotation_deg/mean", True)]


def test_needs_a_reference(files):
    traj, _, _ = files
    with pytest.raises(CartoError, match="give --relations FILE and/or --ground-truth FILE"):
        run_eval(traj)


def test_several_trajectories_are_scored_in_their_common_frame(tmp_path):
    from carto_cli.commands.eval import run_eval_sessions

    gt = tmp_path / "gt.txt"
    gt.write_text("".join(f"{t} {0.5 * t} {0.1 * t * t} 0\n" for t in range(20)))
    first, second, shifted = tmp_path / "a.txt", tmp_path / "b.txt", tmp_path / "c.txt"
    first.write_text("".join(f"{t} {0.5 * t} {0.1 * t * t} 0\n" for t in range(10)))
    second.write_text("".join(f"{t} {0.5 * t} {0.1 * t * t} 0\n" for t in range(10, 20)))
    # The second session placed 1 m off: alone it would align perfectly, in the common frame it cannot
    shifted.write_text("".join(f"{t} {0.5 * t + 1.0} {0.1 * t * t} 0\n" for t in range(10, 20)))
    right = run_eval_sessions([first, second], [gt])
    assert [r.translation.rmse for r in right.results] == pytest.approx([0.0, 0.0], abs=1e-9)
    wrong = run_eval_sessions([first, shifted], [gt], max_trans_error=0.1)
    assert max(r.translation.rmse for r in wrong.results) > 0.3  # the common alignment splits the shift
    assert [g.passed for g in wrong.gates] == [False]
    assert [s["trajectory"] for s in wrong.data["sessions"]] == [str(first), str(shifted)]
    with pytest.raises(CartoError, match="ground truth"):
        run_eval_sessions([first, second], [gt, gt, gt])
    with pytest.raises(CartoError, match="--ground-truth"):
        run_eval_sessions([first, second], [])
