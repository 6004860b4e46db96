"""Several lasers' scans as one scan of the tracking frame (sensor.merging): each placed by its mount, its own
limits applied in its own frame, every beam with its time; a window holds one scan of each laser at most."""
import math

import numpy as np
import pytest

from carto_cli.core.records import Odometry, Scan
from carto_cli.sensor.merging import Laser, ScanMerger, merge, merged_records
from carto_cli.sensor.range_filter import crop_scan

FRONT = Laser("/front", "laser_front", (0.2, 0.1, 0.0))
BACK = Laser("/back", "laser_back", (-0.2, -0.1, math.pi))


def _scan(laser: Laser, time: float, ranges, *, range_max: float = 30.0, range_min: float = 0.05,
          time_increment: float = 0.0) -> Scan:
    ranges = np.asarray(ranges, dtype=np.float32)
    angles = np.linspace(-1.0, 1.0, len(ranges)).astype(np.float32)
    return Scan(time, ranges, angles, laser.frame, laser.topic, range_min=range_min, range_max=range_max,
                angle_min=-1.0, angle_increment=2.0 / (len(ranges) - 1), time_increment=time_increment)


def _in_base(laser: Laser, scan: Scan) -> np.ndarray:
    """The scan's returns placed by its mount, a plain numpy reference."""
    x, y, yaw = laser.mount
    r = scan.ranges.astype(np.float64)
    a = scan.angles.astype(np.float64) + yaw
    return np.column_stack([x + r * np.cos(a), y + r * np.sin(a)])


def test_each_scan_is_placed_by_its_own_mount_and_keeps_its_time():
    front = _scan(FRONT, 10.0, [2.0, 3.0, 4.0, 5.0])
    back = _scan(BACK, 10.04, [1.5, 2.5, 3.5], time_increment=0.001)
    merged = merge([front, back], [FRONT.mount, BACK.mount], "base_link", "/front+/back")
    assert merged.time == 10.04 and merged.frame == "base_link" and merged.angle_increment is None
    np.testing.assert_allclose(merged.points(), np.concatenate([_in_base(FRONT, front), _in_base(BACK, back)]),
                               atol=1e-5)
    # The older scan's beams before the merged scan's time, the newer's after it by their own sweep
    np.testing.assert_allclose(merged.beam_times(), [-0.04] * 4 + [0.0, 0.001, 0.002], atol=1e-9)
    # Cropped at rest from the tracking frame's origin: the same points
    data = crop_scan(merged, mount=(0.0, 0.0, 0.0), max_range=30.0)
    np.testing.assert_allclose(data.returns, merged.points(), atol=1e-5)


def test_each_lasers_limits_apply_in_its_own_frame():
    # 31 m is past the front laser's range_max: a miss along its own beam, not a wall; 0.01 m is below its
    # range_min: dropped; NaN is no reading at all
    front = _scan(FRONT, 1.0, [31.0, np.inf, 0.01, np.nan, 2.0])
    back = _scan(BACK, 1.0, [1.0, 1.0, 1.0])
    merged = merge([front, back], [FRONT.mount, BACK.mount], "base_link", "x")
    assert merged.num_beams == 3 + 3
    assert np.isposinf(merged.ranges[:2]).all() and np.isfinite(merged.ranges[2:]).all()
    # A miss keeps its laser's bearing (to well under a beam): 1000 m out, a 0.22 m offset turns it 0.01 degrees
    np.testing.assert_allclose(merged.angles[:2], front.angles[:2] + FRONT.mount[2], atol=1e-3)


def test_motion_de_skews_the_older_scan_to_the_newer_ones_time():
    # A robot driving +x at 1 m/s sees a wall at x = 3 with its front laser at t = 0 and again at t = 0.1
    # with its back laser turned to face it (mount yaw 0 here): merged at t = 0.1 and de-skewed, both parts
    # put the wall where it is from the robot at t = 0.1
    ahead = Laser("/a", "a", (0.0, 0.0, 0.0))
    second = Laser("/b", "b", (0.0, 0.0, 0.0))
    angles = np.zeros(1, np.float32)
    first = Scan(0.0, np.array([3.0], np.float32), angles, "a", "/a", range_max=30.0)
    later = Scan(0.1, np.array([2.9], np.float32), angles, "b", "/b", range_max=30.0)
    merged = merge([first, later], [ahead.mount, second.mount], "base_link", "/a+/b")
    still = crop_scan(merged, mount=(0.0, 0.0, 0.0), max_range=30.0)
    moving = crop_scan(merged, mount=(0.0, 0.0, 0.0), motion=(1.0, 0.0, 0.0), max_range=30.0)
    assert still.returns[:, 0] == pytest.approx([3.0, 2.9])
    assert moving.returns[:, 0] == pytest.approx([2.9, 2.9])


def test_a_window_holds_one_scan_of_each_laser_at_most():
    merger = ScanMerger([FRONT, BACK])
    out = [merger.add(_scan(FRONT, 0.0, [1.0, 1.0])), merger.add(_scan(BACK, 0.05, [2.0, 2.0]))]
    assert out == [None, None]  # full, it goes out at the next scan
    pair = merger.add(_scan(FRONT, 0.1, [1.0, 1.0]))
    # stamped with its newest scan, the older one's beams before
    assert pair is not None and pair.num_beams == 4 and pair.time == 0.05
    assert pair.beam_times() == pytest.approx([-0.05, -0.05, 0.0, 0.0])
    # The front laser twice before the back one: its first scan goes out alone, the second waits for the back
    alone = merger.add(_scan(FRONT, 0.2, [1.0, 1.0]))
    assert alone is not None and alone.time == 0.1 and alone.num_beams == 2
    assert merger.add(_scan(BACK, 0.25, [2.0, 2.0])) is None
    # A laser that stopped does not stop the other
    outs = [merger.add(_scan(FRONT, 0.3 + 0.1 * k, [1.0, 1.0])) for k in range(4)]
    assert [o is not None and o.num_beams for o in outs] == [4, 2, 2, 2]
    last = merger.flush()
    assert last is not None and last.time == pytest.approx(0.6) and merger.flush() is None


@pytest.mark.parametrize("order", ["front first", "back first"])
def test_scans_stamped_alike_share_a_window_whatever_their_order(order):
    """Two lasers at 10 and 5 Hz fire together every 0.2 s; a bag may hold either first. No two windows share a
    stamp, and no scan is lost."""
    front = [_scan(FRONT, 0.1 * k, [1.0, 1.0]) for k in range(10)]
    back = [_scan(BACK, 0.2 * k, [2.0, 2.0]) for k in range(5)]
    rank = {"/front": 0, "/back": 1} if order == "front first" else {"/front": 1, "/back": 0}
    records = sorted(front + back, key=lambda s: (s.time, rank[s.topic]))
    out = list(merged_records(records, [FRONT, BACK]))
    times = [s.time for s in out]
    assert times == sorted(set(times)) and sum(s.num_beams for s in out) == 2 * 15
    assert [s.num_beams for s in out] == [4, 2] * 5


def test_other_records_pass_through_in_order():
    odometry = Odometry(0.07, 0.0, 0.0, 0.0, topic="/odom")
    records = [_scan(FRONT, 0.0, [1.0, 1.0]), odometry, _scan(BACK, 0.1, [2.0, 2.0]), _scan(FRONT, 0.2, [1.0, 1.0])]
    out = list(merged_records(records, [FRONT, BACK]))
    # A window goes out at the scan after it, after what came between: odometry then covers the whole window
    assert [type(r).__name__ for r in out] == ["Odometry", "Scan", "Scan"]
    assert [r.time for r in out] == [0.07, 0.1, 0.2]
    assert out[1].topic == "/front+/back" and out[1].frame == "base_link"


def test_lasers_must_be_two_or_more_with_topics_of_their_own():
    with pytest.raises(ValueError, match="two lasers"):
        ScanMerger([FRONT])
    with pytest.raises(ValueError, match="topic of its own"):
        ScanMerger([FRONT, FRONT])
    with pytest.raises(ValueError, match="not one of"):
        ScanMerger([FRONT, BACK]).add(_scan(Laser("/other", "o", (0.0, 0.0, 0.0)), 0.0, [1.0, 1.0]))
