"""io.content: what a readable recording holds that carto cannot use is dropped and reported once per kind;
`carto info` reports it before mapping, `carto map` maps the rest and says what it dropped."""
import math

import numpy as np
from room_sim import cast
from typer.testing import CliRunner

from carto_cli.cli import app
from carto_cli.core.records import Imu, Odometry, Scan
from carto_cli.io.content import MAX_BEAMS, ContentCheck


def _scan(t, n=5, frame="laser", increment=0.1, topic="/scan"):
    angles = (np.arange(n) * increment).astype(np.float32)
    return Scan(time=t, ranges=np.ones(n, np.float32), angles=angles, frame=frame, topic=topic,
                angle_increment=increment)


def _odom(t, x=0.0):
    return Odometry(time=t, x=x, y=0.0, yaw=0.0, topic="/odom")


def test_what_cannot_be_used_is_dropped_and_counted_once_per_kind():
    records = [
        _scan(1.0), _odom(1.0),
        _scan(0.5),                                   # time goes backwards on /scan
        _scan(1.0),                                   # the same stamp again
        _odom(1.5, x=math.nan),                       # NaN odometry
        _scan(2.0, n=0),                              # no beams
        _scan(2.1, increment=0.0),                    # every beam on one bearing
        _scan(2.2, n=MAX_BEAMS + 1, increment=1e-5),  # a corrupt length
        _scan(2.3, frame="laser_rear"),               # a second laser on the topic
        _scan(2.4, frame="laser_rear"),
        _scan(math.inf),                              # a time that is not finite
        Imu(time=2.5, angular_velocity=np.array([0.0, 0.0, math.inf]), linear_acceleration=np.zeros(3),
            topic="/imu"),
        _scan(3.0, increment=-0.1),                   # clockwise beams: kept, mentioned
        _scan(3.1), _odom(3.1),
    ]
    check = ContentCheck()
    kept = list(check.filter(records))
    assert [(type(r).__name__, r.time) for r in kept] == [
        ("Scan", 1.0), ("Odometry", 1.0), ("Scan", 3.0), ("Scan", 3.1), ("Odometry", 3.1)]
    assert check.dropped == 10
    text = "\n".join(check.warnings())
    for line in ("/scan: 1 message(s) older than the one before on the topic dropped (time goes backwards)",
                 "/scan: 1 message(s) with the same stamp as the one before dropped (duplicated)",
                 "/odom: 1 odometry message(s) with a NaN or infinite value dropped",
                 "/scan: 1 scan(s) with no beams dropped",
                 "/scan: 1 scan(s) with angle_increment 0 dropped",
                 f"/scan: 1 scan(s) with over {MAX_BEAMS:,} beams dropped",
                 "/scan: 2 scan(s) from frame(s) laser_rear dropped: two lasers on one topic, the first one (laser)",
                 "/scan: 1 message(s) with a time that is not finite dropped",
                 "/imu: 1 IMU message(s) with a NaN or infinite value dropped",
                 "/scan: 1 scan(s) with a negative angle_increment"):
        assert line in text, line
    assert len(check.warnings()) == 10  # one line per topic and kind


def test_a_clean_stream_passes_untouched():
    records = [_scan(0.1 * i) for i in range(1, 20)] + [_odom(5.0)]
    check = ContentCheck()
    assert list(check.filter(records)) == records and check.warnings() == [] and check.dropped == 0


def _carmen(path, bad: bool):
    """A CARMEN log of a drive along the room of room_sim, 181 beams; with ``bad`` some of its lines broken."""
    angles = np.linspace(-math.pi / 2, math.pi / 2, 181)
    lines = []
    for i in range(60):
        t = 0.5 * i
        pose = (1.5 + 0.08 * i, 1.0 + 0.04 * i, 0.3)
        r = np.minimum(cast(pose, angles), 30.0)
        odom = f"{pose[0]:.4f} {pose[1]:.4f} {pose[2]:.4f}"
        lines.append(f"ODOM {odom} 0 0 0 {t:.3f} test {t:.3f}")
        lines.append(f"FLASER 181 {' '.join(f'{v:.3f}' for v in r)} {odom} {odom} {t + 0.01:.3f} test {t + 0.01:.3f}")
    if bad:
        p = lines[20].split()
        lines[20] = " ".join(["ODOM", "nan"] + p[2:])                 # NaN odometry
        lines.insert(41, lines[41])                                    # a duplicated scan
        p = lines[61].split()
        lines[61] = " ".join(["FLASER", "0"] + p[-9:])                 # a scan with no beams
    path.write_text("\n".join(lines) + "\n")
    return path


def test_info_reports_bad_content_and_map_maps_the_rest(tmp_path):
    runner = CliRunner()
    log = _carmen(tmp_path / "drive.clf", bad=True)
    info = runner.invoke(app, ["info", str(log)])
    assert info.exit_code == 0, info.output
    for words in ("odometry message(s) with a NaN", "same stamp as the one before", "scan(s) with no beams"):
        assert words in info.stdout, words
    out = tmp_path / "m"
    r = runner.invoke(app, ["map", str(log), "-o", str(out), "--algorithm", "cartographer"])
    assert r.exit_code in (0, 3), r.output  # mapped (its verdict is another matter), never a traceback
    assert "Traceback" not in r.output and (out / "map.pgm").exists()
    assert r.stderr.count("carto: warning: ") >= 3
    clean = runner.invoke(app, ["info", str(_carmen(tmp_path / "clean.clf", bad=False))])
    assert "dropped" not in clean.stdout
