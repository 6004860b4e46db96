"""Tracking a recording through a fixed map: every scan posed, first fix, and recovery after a kidnap."""
import math

import numpy as np
from reloc_map import pose_error

from carto_cli.core import transform
from carto_cli.core.records import Odometry, Scan
from carto_cli.relocalization.tracking import Tracker, summarize_track


def _errors(out, ref, shift=0.0):
    return [(o, pose_error(o.pose, ref[round(o.time + shift, 6)])) for o in out
            if o.pose is not None and round(o.time + shift, 6) in ref]


def test_tracks_every_scan_from_an_initial_pose(relocalizer, second_pass_records):
    records, ref = second_pass_records
    first = next(r for r in records if isinstance(r, Scan))
    tracker = Tracker(relocalizer)
    out = list(tracker.track(records, initial_pose=np.asarray(ref[round(first.time, 6)]) + [0.3, -0.2, 0.05]))
    assert len(out) == sum(isinstance(r, Scan) for r in records)
    assert [o.index for o in out] == list(range(len(out)))
    late = [(o, e) for o, e in _errors(out, ref) if o.time >= 1015.0]  # the map's own first poses are no reference
    assert sum(o.verdict == "ok" and e[0] < 0.1 and e[1] < 1.0 for o, e in late) >= 0.97 * len(late)
    assert all(e[0] < 0.3 for o, e in late if o.verdict == "ok")
    s = summarize_track(out, 1.0, tracker.relocalizations, tracker.timings)
    assert s.first_fix_index == 0 and s.relocalizations == 1 and s.verdicts["ok"] >= 0.97 * len(out)
    assert out[0].source.startswith("relocalize:") and out[1].source == "track"


def test_without_odometry_and_without_a_prior(relocalizer, second_pass_records):
    records, ref = second_pass_records
    scans = [r for r in records if isinstance(r, Scan) and r.time >= 1015.0]
    out = list(Tracker(relocalizer).track(scans))  # global first fix, then constant velocity
    assert out[0].verdict == "ok" and out[0].source == "relocalize:global"
    errs = _errors(out, ref)
    assert sum(o.verdict == "ok" and e[0] < 0.1 for o, e in errs) >= 0.95 * len(out)


def test_recovers_after_a_kidnap(relocalizer, second_pass_records):
    """At t = 1030 s the robot is carried 20 s down the route; its odometry goes on as if it had not moved."""
    records, ref = second_pass_records
    t_kidnap, skip = 1030.0, 20.0
    before = [r for r in records if r.time < t_kidnap]
    last_odom = next(r for r in reversed(before) if isinstance(r, Odometry))
    later = [r for r in records if r.time >= t_kidnap + skip]
    odom0 = next(r for r in later if isinstance(r, Odometry))
    spliced = list(before)
    for r in later:
        if isinstance(r, Odometry):
            # Odometry continues smoothly from where it stopped: the wheels did not see the carry.
            moved = transform.relative(np.array([odom0.x, odom0.y, odom0.yaw]), np.array([r.x, r.y, r.yaw]))
            x, y, yaw = transform.compose(np.array([last_odom.x, last_odom.y, last_odom.yaw]), moved)
            spliced.append(Odometry(r.time - skip, float(x), float(y), float(yaw)))
        else:
            spliced.append(Scan(r.time - skip, r.ranges, r.angles, r.frame, r.topic, r.range_min, r.range_max,
                                r.angle_min, r.angle_increment))
    first = next(r for r in spliced if isinstance(r, Scan))
    tracker = Tracker(relocalizer)
    out = list(tracker.track(spliced, initial_pose=ref[round(first.time, 6)]))
    after = [o for o in out if o.time >= t_kidnap]
    # Right after the carry: never a confident wrong pose ...
    for o in after:
        if o.verdict == "ok":
            assert pose_error(o.pose, ref[round(o.time + skip, 6)])[0] < 0.3, o
    # ... lost for a few scans, found again by a search, then tracked
    assert after[0].verdict == "lost"
    recovered = next(k for k, o in enumerate(after) if o.verdict == "ok")
    assert recovered <= 10 and after[recovered].source.startswith("relocalize:")
    tail = after[recovered:]
    assert sum(o.verdict == "ok" for o in tail) >= 0.95 * len(tail)
    assert tracker.relocalizations >= 2
    assert math.isfinite(summarize_track(out, 1.0, tracker.relocalizations, tracker.timings).scans_per_second)
