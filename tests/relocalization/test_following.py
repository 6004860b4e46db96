"""The scans around a query check an answer no prior's window confirmed (relocalization/following.py)."""
import numpy as np
import pytest
from reloc_map import pose_error

from carto_cli.core.records import Odometry, Scan
from carto_cli.relocalization import ScanContext
from carto_cli.relocalization.following import check_context
from carto_cli.relocalization.queries import CONTEXT_SECONDS

QUERY_T = 1022.0  # on the bottom stretch
ELSEWHERE_T = 1040.0  # 18 s later, near the corner


def _around(records, t, odometry=True) -> tuple[Scan, ScanContext]:
    """The scan nearest ``t`` and the records within CONTEXT_SECONDS of it (scans only without ``odometry``)."""
    k = min((k for k, r in enumerate(records) if isinstance(r, Scan)), key=lambda k: abs(records[k].time - t))
    scan = records[k]
    keep = (Scan, Odometry) if odometry else (Scan,)
    before = [r for r in records[:k] if isinstance(r, keep) and r.time >= scan.time - CONTEXT_SECONDS]
    after = [r for r in records[k + 1:] if isinstance(r, keep) and r.time <= scan.time + CONTEXT_SECONDS]
    return scan, ScanContext(before, after)


@pytest.mark.parametrize("odometry", [True, False], ids=["odometry", "scans only"])
def test_the_scans_around_a_right_answer_fit_and_a_path_from_elsewhere_does_not(relocalizer, second_pass_records,
                                                                                 odometry):
    records, ref = second_pass_records
    scan, own = _around(records, QUERY_T, odometry)
    _, elsewhere = _around(records, ELSEWHERE_T, odometry)
    plain = relocalizer.relocalize(scan)
    assert plain.verdict == "ok" and plain.path == "global" and plain.context_checked == 0
    assert pose_error(plain.pose, ref[round(scan.time, 6)])[0] < 0.1

    right = relocalizer.relocalize(scan, context=own)
    assert right.verdict == "ok" and right.context_checked >= 10 and right.context_through_walls == 0
    np.testing.assert_array_equal(right.pose, plain.pose)

    # The same scan, but the robot's path around it is the one it drove half a minute later: the answer fits, the
    # path placed at it runs through the map's walls. Without the check this answer is 'ok'.
    wrong = relocalizer.relocalize(scan, context=elsewhere)
    assert wrong.verdict == "lost" and not wrong.success
    assert wrong.context_through_walls >= 3 and "see through walls" in wrong.reason
    assert wrong.to_dict()["context_through_walls"] == wrong.context_through_walls


def test_an_answer_a_window_around_the_prior_confirmed_is_not_checked(relocalizer, second_pass_records):
    """The prior is evidence of its own; the check would cost a windowed answer several times its search."""
    records, ref = second_pass_records
    scan, _ = _around(records, QUERY_T)
    _, elsewhere = _around(records, ELSEWHERE_T)
    res = relocalizer.relocalize(scan, np.asarray(ref[round(scan.time, 6)]) + [0.2, -0.1, 0.03], context=elsewhere)
    assert res.path == "windowed" and res.verdict == "ok" and res.context_checked == 0


def test_neighbours_where_the_map_never_saw_say_nothing(relocalizer, second_pass_records):
    """A robot that came from a part of the building the map leaves out: those scans are not counted."""
    records, _ = second_pass_records
    scan, own = _around(records, QUERY_T)
    far = [Odometry(r.time, r.x + 500.0, r.y, r.yaw) if isinstance(r, Odometry) else r for r in own.after]
    res = relocalizer.relocalize(scan, context=ScanContext(own.before, far))
    before_only = relocalizer.relocalize(scan, context=ScanContext(own.before, ()))
    assert res.verdict == "ok" and res.context_through_walls == 0
    assert res.context_checked == before_only.context_checked >= 3


def test_the_check_alone(relocalizer, second_pass_records):
    records, ref = second_pass_records
    scan, own = _around(records, QUERY_T)
    pose = np.asarray(ref[round(scan.time, 6)])
    mount, min_score = relocalizer.laser_pose, relocalizer.ro.min_score
    right = check_context(relocalizer.judge, own, pose, mount, min_score, 4, 2)
    # Stopped once the neighbours left (8 - checked) could no longer make more than 2 see through walls: after 6
    assert right.checked == 6 and right.through_walls == 0 and not right.vetoes(2)
    turned = check_context(relocalizer.judge, own, pose + [0.0, 0.0, 0.35], mount, min_score, 4, 2)
    assert turned.through_walls == 3 and turned.vetoes(2) and turned.lost >= 3  # stopped at the third
    assert check_context(relocalizer.judge, ScanContext(), pose, mount, min_score, 4, 2).checked == 0
