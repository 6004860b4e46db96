"""CarmenRecording: fixtures written here, plus the real Radish and bench logs."""
from __future__ import annotations

import gzip
import itertools
import math
import zlib
from pathlib import Path

import numpy as np
import pytest
from support import SHARED as DATA

from carto_cli.core.errors import CartoError, FormatError, TopicError
from carto_cli.core.records import Odometry, Scan
from carto_cli.io.sources.carmen import CarmenRecording
from carto_cli.io.sources.carmen_lines import carmen_beam_geometry

needs_data = pytest.mark.skipif(not DATA.is_dir(), reason="shared data not available")

# Scan counts from `zcat FILE | grep -c '^FLASER'` (or '^ROBOTLASER1').
RADISH_SCANS = {"aces": 440, "freiburg-079": 4791, "intel": 910}
DENSE_SCANS = {"aces": 7074, "freiburg-079": 11320, "intel": 12163}
DENSE_ODOM = {"aces": 35367, "freiburg-079": 56597, "intel": 60812}


# ---------------------------------------------------------------- line builders

def fmt(values) -> str:
    return " ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in values)


def flaser(t, ranges, laser=(0.0, 0.0, 0.0), odom=None, name="FLASER"):
    odom = laser if odom is None else odom
    return f"{name} {len(ranges)} {fmt(ranges)} {fmt(laser)} {fmt(odom)} {t:.6f} host {t:.6f}"


def robotlaser(t, ranges, start=-2.356194, res=0.01309, max_range=30.0, remissions=(),
               laser=(0.0, 0.0, 0.0), robot=(0.0, 0.0, 0.0), tv=0.0, rv=0.0, name="ROBOTLASER1"):
    fov = res * len(ranges)
    head = f"{name} 0 {start} {fov} {res} {max_range} 0.01 0 {len(ranges)} {fmt(ranges)}"
    rem = f"{len(remissions)}" + (f" {fmt(remissions)}" if len(remissions) else "")
    return f"{head} {rem} {fmt(laser)} {fmt(robot)} {tv} {rv} 0.5 0.5 0 {t:.6f} host {t:.6f}"


def rawlaser(t, ranges, k=1, start=-1.5, res=0.01, max_range=8.0):
    return (f"RAWLASER{k} 0 {start} {res * len(ranges)} {res} {max_range} 0.01 0 {len(ranges)} "
            f"{fmt(ranges)} 0 {t:.6f} host {t:.6f}")


def odom(t, x=0.0, y=0.0, th=0.0, tv=0.0, rv=0.0):
    return f"ODOM {x} {y} {th} {tv} {rv} 0 {t:.6f} host {t:.6f}"


def write(path: Path, lines, gz=False, newline_at_end=True) -> Path:
    text = "\n".join(lines) + ("\n" if newline_at_end else "")
    if gz:
        with gzip.open(path, "wt") as f:
            f.write(text)
    else:
        path.write_text(text)
    return path


def records(path, topics=None):
    with CarmenRecording(path) as rec:
        return list(rec.records(topics))


def ranges(n, base=1.0):
    return [round(base + 0.01 * i, 2) for i in range(n)]


HEADER = [
    "# message formats defined: PARAM SYNC ODOM FLASER RLASER TRUEPOS",
    "PARAM robot_frontlaser_offset 0.0 nohost 0",
    "",
    "SYNC 1.0 host 1.0",
    "TRUEPOS 1 2 3 4 5 6 0.5 host 0.5",
    "NEFF 30",
]


# ---------------------------------------------------------------- fixtures

@pytest.mark.parametrize("n", [180, 181, 360, 361])
def test_flaser_beam_geometry_follows_carmen(tmp_path, n):
    p = write(tmp_path / "f.clf", HEADER + [flaser(1.0, ranges(n))])
    (scan,) = records(p, ["/scan"])
    step = math.pi / 180 if n in (180, 181) else math.pi / 360
    assert scan.num_beams == n
    assert scan.angle_min == pytest.approx(-math.pi / 2)
    assert scan.angle_increment == pytest.approx(step)
    last = -math.pi / 2 + (n - 1) * step
    # 181 / 361 beams cover exactly 180 deg; 180 / 360 stop one step short of +90 deg.
    assert last == pytest.approx(math.pi / 2 if n % 2 else math.pi / 2 - step)
    assert scan.angles[-1] == pytest.approx(last, abs=1e-6)
    assert scan.ranges.dtype == np.float32 and scan.angles.dtype == np.float32
    np.testing.assert_allclose(scan.ranges, np.array(ranges(n), np.float32))
    assert scan.frame == "laser" and scan.topic == "/scan"
    assert scan.range_max == 80.0 and scan.intensities is None
    assert scan.time == 1.0


def test_beam_geometry_other_counts():
    assert carmen_beam_geometry(401) == (pytest.approx(-math.pi / 2), pytest.approx(math.pi / 720))
    assert carmen_beam_geometry(91)[1] == pytest.approx(math.pi / 90)


def test_comments_params_and_unknown_messages_are_skipped(tmp_path):
    p = write(tmp_path / "f.log", HEADER + [odom(1.0), "SOMETHINGNEW 1 2 3", flaser(1.5, ranges(181))])
    with CarmenRecording(p) as rec:
        assert {(t.name, t.msgtype, t.count) for t in rec.topics()} == {
            ("/scan", "sensor_msgs/msg/LaserScan", 1),
            ("/odom", "nav_msgs/msg/Odometry", 1),
            ("/odom_laser", "nav_msgs/msg/Odometry", 1),
        }
        assert [type(r).__name__ for r in rec.records()] == ["Odometry", "Odometry", "Scan"]


def test_odom_fields(tmp_path):
    p = write(tmp_path / "o.log", [odom(2.5, 1.0, -2.0, 0.3, 0.4, -0.1)])
    (o,) = records(p)
    assert o == Odometry(2.5, 1.0, -2.0, 0.3, frame="odom", child_frame="base_link", topic="/odom", vx=0.4, wz=-0.1)


def test_flaser_odometry_comes_just_before_its_scan(tmp_path):
    p = write(tmp_path / "f.log", [
        odom(1.0, 0.1, 0, 0),
        flaser(1.0, ranges(180), laser=(0.5, 0.25, 0.1), odom=(0.5, 0.25, 0.1)),
        odom(1.2),
    ])
    out = records(p)
    assert [r.topic for r in out] == ["/odom", "/odom_laser", "/scan", "/odom"]
    pose = out[1]
    assert (pose.time, pose.x, pose.y, pose.yaw) == (1.0, 0.5, 0.25, 0.1)
    assert (pose.frame, pose.child_frame) == ("odom", "base_link")


def test_robotlaser_fields_pose_and_mount(tmp_path):
    mount = (0.2, -0.05, 0.1)
    lines = []
    for i in range(5):
        rx, ry, rth = 1.0 + i, 2.0, 0.3 * i
        c, s = math.cos(rth), math.sin(rth)
        laser = (rx + c * mount[0] - s * mount[1], ry + s * mount[0] + c * mount[1], rth + mount[2])
        lines.append(robotlaser(10.0 + i, ranges(8), remissions=[5.0] * 8, laser=laser,
                                robot=(rx, ry, rth), tv=0.5, rv=0.25))
    p = write(tmp_path / "r.clf", lines)
    with CarmenRecording(p) as rec:
        (tf,) = rec.static_transforms()
        assert (tf.parent, tf.child) == ("base_link", "laser")
        np.testing.assert_allclose(tf.pose2d(), mount, atol=1e-5)
        out = list(rec.records())
    scans = [r for r in out if isinstance(r, Scan)]
    poses = [r for r in out if isinstance(r, Odometry)]
    assert len(scans) == len(poses) == 5
    s0 = scans[0]
    assert s0.range_max == 30.0 and s0.angle_min == pytest.approx(-2.356194)
    assert s0.angle_increment == pytest.approx(0.01309)
    np.testing.assert_array_equal(s0.intensities, np.full(8, 5.0, np.float32))
    assert (poses[2].x, poses[2].y, poses[2].yaw, poses[2].vx, poses[2].wz) == (3.0, 2.0, 0.6, 0.5, 0.25)


def test_inconsistent_laser_offset_gives_identity_mount(tmp_path):
    # laser pose = a corrected pose drifting away from odometry: no fixed mount
    lines = [flaser(float(i), ranges(180), laser=(0.1 * i * i, 0.0, 0.0), odom=(0.0, 0.0, 0.0)) for i in range(5)]
    with CarmenRecording(write(tmp_path / "f.log", lines)) as rec:
        (tf,) = rec.static_transforms()
        assert tf.pose2d() == (0.0, 0.0, 0.0)


def test_rawlaser_and_rear_lasers(tmp_path):
    lines = [
        rawlaser(1.0, ranges(10), k=1),
        rawlaser(1.1, ranges(12), k=2, start=-1.0, res=0.02, max_range=5.0),
        flaser(1.2, ranges(180), name="RLASER"),
    ]
    with CarmenRecording(write(tmp_path / "f.log", lines)) as rec:
        assert {t.name: t.count for t in rec.topics()} == {"/scan": 1, "/scan2": 1, "/scan_rear": 1, "/odom_laser": 1}
        tfs = {t.child: t.pose2d() for t in rec.static_transforms()}
        assert tfs["laser"] == (0.0, 0.0, 0.0)
        assert tfs["laser_rear"][2] == pytest.approx(math.pi)
        by_topic = {r.topic: r for r in rec.records()}
    assert by_topic["/scan"].frame == "laser" and by_topic["/scan"].range_max == 8.0
    s2 = by_topic["/scan2"]
    assert (s2.frame, s2.num_beams, s2.range_max) == ("laser2", 12, 5.0)
    assert s2.angles[1] == pytest.approx(-0.98)
    assert by_topic["/scan_rear"].frame == "laser_rear"


def test_one_source_per_topic(tmp_path):
    # Newer loggers write the same laser twice; /scan must not see it twice.
    lines = [robotlaser(1.0, ranges(4)), rawlaser(1.0, ranges(4)), flaser(1.0, ranges(180)),
             robotlaser(2.0, ranges(4)), rawlaser(2.0, ranges(4))]
    with CarmenRecording(write(tmp_path / "f.clf", lines)) as rec:
        assert {t.name: t.count for t in rec.topics()}["/scan"] == 2
        assert [r.num_beams for r in rec.records(["/scan"])] == [4, 4]


def test_plain_and_gzip_are_detected_by_content(tmp_path):
    lines = HEADER + [odom(0.5, 1, 2, 3), flaser(1.0, ranges(361), odom=(1.0, 2.0, 0.5))]
    plain = write(tmp_path / "looks.gz", lines)  # plain text despite the suffix
    packed = write(tmp_path / "looks.log", lines, gz=True)  # gzip despite the suffix
    a, b = records(plain), records(packed)
    assert len(a) == len(b) == 3
    for x, y in zip(a, b):
        assert x.same_as(y) if isinstance(x, Scan) else x == y


def test_topic_selection(tmp_path):
    p = write(tmp_path / "f.log", [odom(1.0), flaser(1.1, ranges(180)), odom(1.2)])
    assert [r.topic for r in records(p, ["/odom"])] == ["/odom", "/odom"]
    assert [r.topic for r in records(p, ["/odom_laser"])] == ["/odom_laser"]
    assert [r.topic for r in records(p, ["/scan"])] == ["/scan"]
    with pytest.raises(TopicError, match="/imu"):
        records(p, ["/imu"])


def test_out_of_order_lines_are_reordered_or_dropped(tmp_path):
    lines = [
        odom(10.0), flaser(10.5, ranges(180)), odom(10.2),  # 0.3 s late: reordered
        odom(11.0), odom(14.0), odom(0.0),  # stamped 0 long after: dropped
        flaser(14.5, ranges(180)), odom(14.5),
    ]
    with CarmenRecording(write(tmp_path / "f.log", lines)) as rec:
        out = list(rec.records())
        assert rec.dropped == {"ODOM": 1}
        counts = {t.name: t.count for t in rec.topics()}
    times = [r.time for r in out]
    assert times == sorted(times)
    assert [r.time for r in out if r.topic == "/odom"] == [10.0, 10.2, 11.0, 14.0, 14.5]
    for name, count in counts.items():
        assert sum(r.topic == name for r in out) == count


def test_records_stream_lazily(tmp_path):
    # A broken line near the end must not stop the records before it from coming out.
    lines = [odom(float(i)) for i in range(100)] + ["ODOM 1 2 3 oops 0 0 200 host 200"]
    with CarmenRecording(write(tmp_path / "f.log", lines)) as rec:
        it = rec.records()
        first = list(itertools.islice(it, 50))
        assert len(first) == 50
        with pytest.raises(FormatError, match="line 101"):
            list(it)


# ---------------------------------------------------------------- malformed input

@pytest.mark.parametrize("line, message", [
    (flaser(1.0, ranges(180)).replace(" 1.5 ", " ", 1), r"line 3: FLASER with 180 beams has 189 fields after its name, expected 190"),
    (flaser(1.0, ranges(180)).replace(" 1.5 ", " abc ", 1), r"line 3: FLASER field \d+ is not a number \('abc'\)"),
    ("FLASER 18x0 1 2 3", r"line 3: FLASER has no valid beam or remission count"),
    (flaser(1.0, ranges(180)).replace("FLASER 180", "FLASER 180.5"), r"line 3: FLASER has no valid beam"),
    (flaser(1.0, ranges(180)).replace("1.000000 host", "nan host"), r"line 3: FLASER timestamp 'nan' is not a finite number"),
    (robotlaser(1.0, ranges(8), remissions=[1.0] * 8)[:-40] + " 0 1.0 host 1.0", r"line 3: ROBOTLASER1 with 8 beams and 8 remissions has \d+ fields"),
    (rawlaser(1.0, ranges(10)).replace(" 0 1.000000", " 3 1.000000"), r"line 3: RAWLASER1 with 10 beams and 3 remissions has 22 fields after its name, expected 25"),
    ("ODOM 1 2 3 4 5 1.0 host 1.0", r"line 3: ODOM has 8 fields after its name, expected 9"),
    ("ODOM 1 2 3 4 5 6 x host 1.0", r"line 3: ODOM field 7 is not a number"),
], ids=["count", "non-numeric", "bad-n", "fractional-n", "nan-time", "robotlaser-count", "rawlaser-count",
        "odom-count", "odom-time"])
def test_malformed_lines(tmp_path, line, message):
    p = write(tmp_path / "bad.log", [odom(0.0), odom(0.5), line, odom(2.0)])
    with pytest.raises(FormatError, match=message) as err:
        records(p)
    assert err.value.path == str(p) and str(p) in str(err.value)


def test_a_cut_anywhere_in_the_last_line_is_detected_and_left_out(tmp_path):
    kinds = [
        odom(0.5, 1, 2, 3),
        flaser(1.5, ranges(180)),
        robotlaser(1.0, ranges(6), remissions=[2.0] * 6, laser=(1, 2, 3), robot=(1, 2, 3)),
        rawlaser(1.0, ranges(5)),
    ]
    for last in kinds:
        # A cut inside the final logger timestamp loses nothing carto reads, so it is not tried.
        end = last.rindex(" ")
        cuts = sorted(set(range(1, end, 7)) | set(range(max(1, end - 40), end)))
        for cut in cuts:
            p = write(tmp_path / "cut.log", [odom(0.1), last[:cut]], newline_at_end=False)
            with CarmenRecording(p) as rec:
                assert rec.warnings == ["cut.log: cut short (line 2 ends mid-message): read up to the cut, 1 "
                                        "message recovered"], last[:cut]
                assert [r.time for r in rec.records()] == [0.1]
    whole = write(tmp_path / "whole.log", kinds, newline_at_end=False)
    assert len(records(whole)) == 3  # ODOM, plus ROBOTLASER1 (pose + scan) which outranks FLASER and RAWLASER1
    assert CarmenRecording(whole).warnings == []  # a last line without its end of line, but whole


def record_keys(path, topics=None) -> list[tuple]:
    with CarmenRecording(path) as rec:
        return [(type(r).__name__, r.topic, r.time, r.ranges.tobytes() if isinstance(r, Scan) else (r.x, r.y, r.yaw))
                for r in rec.records(topics)]


def drive(n: int) -> list[str]:
    return [line for k in range(n) for line in (odom(0.1 * k, 0.01 * k), flaser(0.1 * k + 0.05, ranges(181)))]


@pytest.mark.parametrize("how", ["plain", "gzip", "gzip stream"])
def test_cut_short_carmen_log_is_read_up_to_the_cut_with_one_warning(tmp_path, how):
    lines = drive(300) + [odom(30.0, 3.0, 0.5, 0.25)]
    text = "\n".join(lines) + "\n"
    if how == "gzip stream":
        packed = gzip.compress(text.encode())
        cut = tmp_path / "cut.clf.gz"
        cut.write_bytes(packed[: len(packed) * 2 // 3])
        # What the cut stream still holds, up to its last whole line.
        head = zlib.decompressobj(wbits=31).decompress(cut.read_bytes()).decode()
        kept = head[: head.rindex("\n") + 1].splitlines()
        why = f"the compressed stream ends early, after line {len(kept)}"
    else:
        # The case: an ODOM cut to three fields, which a pass not reading /odom took for whole.
        kept = lines[:-1]
        cut = write(tmp_path / "cut.clf", kept + [" ".join(lines[-1].split()[:4])], gz=how == "gzip",
                    newline_at_end=False)
        why = f"line {len(lines)} ends mid-message"
    whole = write(tmp_path / "whole.clf", kept)
    with CarmenRecording(cut) as rec:
        # Known as soon as the log is open: relocalize tells the recording's warnings before reading a scan.
        assert rec.warnings == [f"{cut.name}: cut short ({why}): read up to the cut, {len(kept)} messages "
                                "recovered"]
        with CarmenRecording(whole) as reference:
            assert rec.topics() == reference.topics()
    for topics in (None, ["/scan", "/odom_laser"], ["/odom"]):  # what info, map and a pass over /odom read
        assert record_keys(cut, topics) == record_keys(whole, topics)


def test_a_corrupt_line_is_no_cut(tmp_path):
    # Bad content with its end of line is an error wherever it is; only the file's end can cut a line.
    lines = drive(5)
    for i, broken in ((3, lines[3][:30]), (9, lines[9][:30])):
        p = write(tmp_path / "bad.clf", lines[:i] + [broken] + lines[i + 1:])
        with pytest.raises(FormatError, match=f"line {i + 1}: "):
            records(p)


def test_truncated_and_corrupt_gzip(tmp_path):
    lines = [odom(i * 0.1, i, 0, 0) for i in range(3000)] + [flaser(301.0, ranges(360))]
    whole = write(tmp_path / "whole.clf.gz", lines, gz=True).read_bytes()
    for size in (len(whole) * 2 // 3, len(whole) - 4):  # in the data; in the trailer (CRC and length)
        cut = tmp_path / "cut.clf.gz"
        cut.write_bytes(whole[:size])
        with CarmenRecording(cut) as rec:
            (warning,) = rec.warnings
            assert "cut short (the compressed stream ends early" in warning
            assert sum(1 for _ in rec.records()) > 0
    with pytest.raises(FormatError, match="cut short .* before its first whole message"):
        cut.write_bytes(whole[:30])
        CarmenRecording(cut)
    bad = tmp_path / "bad.clf.gz"
    bad.write_bytes(whole[:100] + bytes(b ^ 0x55 for b in whole[100:200]) + whole[200:])
    with pytest.raises(FormatError, match="compressed data corrupt"):
        list(CarmenRecording(bad).records())


def test_missing_file_and_non_carmen_text(tmp_path):
    with pytest.raises(CartoError, match="no such file"):
        CarmenRecording(tmp_path / "nope.clf")
    other = tmp_path / "notes.log"
    other.write_text("hello world\nthis is not a robot log\n")
    with pytest.raises(FormatError, match="not a CARMEN log"):
        CarmenRecording(other).topics()
    assert not CarmenRecording.sniff(other)
    assert CarmenRecording.sniff(write(tmp_path / "f.log", HEADER, gz=True))


# ---------------------------------------------------------------- real data

def check_stream(rec, n_scans, beams):
    last = -math.inf
    scans = 0
    for r in rec.records(["/scan"]):
        assert r.time >= last
        last = r.time
        assert r.num_beams in beams and r.ranges.dtype == np.float32 and r.frame == "laser"
        scans += 1
    assert scans == n_scans


@needs_data
@pytest.mark.parametrize("name", sorted(RADISH_SCANS))
def test_radish_corrected_logs(name):
    with CarmenRecording(DATA / f"radish/corrected/{name}-corrected.log.gz") as rec:
        topics = {t.name: t.count for t in rec.topics()}
        assert topics["/scan"] == topics["/odom_laser"] == RADISH_SCANS[name]
        # one ODOM stamped 0 follows every scan in these logs; they cannot be placed in time
        assert rec.dropped["ODOM"] > 0.9 * RADISH_SCANS[name]
        check_stream(rec, RADISH_SCANS[name], (180, 360))
        (tf,) = rec.static_transforms()
        assert tf.pose2d() == (0.0, 0.0, 0.0)


@needs_data
@pytest.mark.parametrize("name", ["aces", "intel"])  # freiburg-079 is the same format, 5x larger
def test_bench_logs_match_their_ground_truth_times(name):
    case = DATA / "bench" / name
    truth = np.loadtxt(case / "groundtruth.txt")
    with CarmenRecording(case / "scans.clf.gz") as rec:
        out = list(rec.records())
    scans = [r for r in out if isinstance(r, Scan)]
    odo = [r for r in out if r.topic == "/odom"]
    assert len(scans) == len(odo) == RADISH_SCANS[name] == len(truth)
    np.testing.assert_allclose([s.time for s in scans], truth[:, 0])
    times = [r.time for r in out]
    assert times == sorted(times)
    # the noisy odometry rides both in ODOM and in the FLASER lines
    at_scan = [r for r in out if r.topic == "/odom_laser"]
    np.testing.assert_allclose([(o.x, o.y) for o in at_scan], [(o.x, o.y) for o in odo], atol=1e-6)


@needs_data
@pytest.mark.parametrize("name", ["freiburg-079", "intel"])  # aces is read in full below
def test_bench_dense_topics(name):
    with CarmenRecording(DATA / "bench-dense" / name / "scans.clf.gz") as rec:
        topics = {t.name: t.count for t in rec.topics()}
        assert topics == {"/scan": DENSE_SCANS[name], "/odom": DENSE_ODOM[name], "/odom_laser": DENSE_SCANS[name]}
        first = list(itertools.islice(rec.records(["/scan"]), 3))
    s = first[0]
    assert s.num_beams == 360 and s.range_max == 30.0
    assert s.angle_min == pytest.approx(-3 * math.pi / 4, abs=1e-6)
    assert s.angle_increment * 360 == pytest.approx(1.5 * math.pi, abs=1e-4)


@needs_data
def test_bench_dense_full_read():
    case = DATA / "bench-dense" / "aces"
    odo_at_scans = np.loadtxt(case / "odometry_at_scans.txt")
    with CarmenRecording(case / "scans.clf.gz") as rec:
        assert {t.name: t.count for t in rec.topics()} == {
            "/scan": DENSE_SCANS["aces"], "/odom": DENSE_ODOM["aces"], "/odom_laser": DENSE_SCANS["aces"]}
        last = -math.inf
        poses = []
        n = {"/scan": 0, "/odom": 0, "/odom_laser": 0}
        for r in rec.records():
            assert r.time >= last
            last = r.time
            n[r.topic] += 1
            if r.topic == "/odom_laser":
                poses.append((r.time, r.x, r.y, r.yaw))
    assert n == {"/scan": DENSE_SCANS["aces"], "/odom": DENSE_ODOM["aces"], "/odom_laser": DENSE_SCANS["aces"]}
    np.testing.assert_allclose(np.array(poses), odo_at_scans, atol=1e-6)
