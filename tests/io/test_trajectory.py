import math
import os

import numpy as np
import pytest
from support import shared_path

from carto_cli.core.errors import CartoError, FormatError
from carto_cli.io.trajectory import Trajectory, read_trajectory, write_trajectory


def sample(n=50, seed=1) -> Trajectory:
    rng = np.random.default_rng(seed)
    t = 1.6e9 + np.cumsum(rng.uniform(0.05, 0.2, n))     # large epoch times keep their nanoseconds
    theta = np.cumsum(rng.uniform(-0.6, 0.6, n))
    theta = (theta + np.pi) % (2 * np.pi) - np.pi
    xy = np.cumsum(rng.normal(0, 0.3, (n, 2)), axis=0)
    return Trajectory(t, xy, theta)


def assert_same(a: Trajectory, b: Trajectory):
    np.testing.assert_allclose(a.t, b.t, rtol=0, atol=2e-9)
    np.testing.assert_allclose(a.xy, b.xy, rtol=0, atol=1e-6)
    dth = (a.theta - b.theta + np.pi) % (2 * np.pi) - np.pi
    np.testing.assert_allclose(dth, 0, atol=1e-9)


@pytest.mark.parametrize("fmt, columns", [("tum", 8), ("xyt", 4)])
def test_round_trip(tmp_path, fmt, columns):
    traj = sample()
    p = write_trajectory(tmp_path / f"traj.{fmt}", traj, fmt)
    lines = p.read_text().splitlines()
    assert lines[0].startswith("#") and len(lines) == len(traj) + 1
    assert all(len(line.split()) == columns for line in lines[1:])
    assert_same(read_trajectory(p), traj)


def test_tum_writes_planar_poses(tmp_path):
    traj = Trajectory.from_poses([1.0, 2.0], [[1.0, 2.0, math.pi / 2], [3.0, 4.0, -math.pi]])
    p = write_trajectory(tmp_path / "t.txt", traj)
    rows = [line.split() for line in p.read_text().splitlines()[1:]]
    assert [float(v) for v in rows[0][3:6]] == [0.0, 0.0, 0.0]
    qz, qw = float(rows[0][6]), float(rows[0][7])
    assert (qz, qw) == pytest.approx((math.sin(math.pi / 4), math.cos(math.pi / 4)))


def test_reads_tum_with_unnormalised_and_tilted_quaternions(tmp_path):
    yaw = 0.7
    q = np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)]) * 3.0
    # A small roll on top of the yaw: the yaw is what a planar pose keeps.
    roll = 0.05
    qr = np.array([math.sin(roll / 2), 0, 0, math.cos(roll / 2)])
    x1, y1, z1, w1 = q / 3.0
    x2, y2, z2, w2 = qr
    tilted = [w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2, w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
              w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2, w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2]
    p = tmp_path / "t.tum"
    p.write_text(f"0 1 2 0.5 {' '.join(map(str, q))}\n1 1 2 0.5 {' '.join(map(str, tilted))}\n")
    traj = read_trajectory(p)
    assert traj.theta == pytest.approx([yaw, yaw], abs=1e-12)
    assert traj.xy.tolist() == [[1.0, 2.0], [1.0, 2.0]]


def test_autodetect_comments_blank_lines_and_commas(tmp_path):
    p = tmp_path / "t.txt"
    p.write_text("# t x y theta\n\n1.0, 0.0, 0.0, 0.1  # first\n   \n2.0 1.0 0.0 0.2\n")
    traj = read_trajectory(p)
    assert traj.t.tolist() == [1.0, 2.0] and traj.theta.tolist() == [0.1, 0.2]
    assert traj.poses.shape == (2, 3) and len(traj) == 2 and traj.span == (1.0, 2.0)


def test_reads_the_bench_ground_truth():
    traj = read_trajectory(shared_path("bench", "intel", "groundtruth.txt"))
    assert len(traj) == 910
    assert traj.t[0] == 32.9068 and traj.xy[0].tolist() == [0.600266, -0.032033]


@pytest.mark.parametrize("text, message", [
    ("1 2 3\n", "line 1: expected 8 or 4 columns in a trajectory file, got 3"),
    ("# c\n1 2 3 4\n2 2 3 4 5 6 7 8\n", "line 3: expected 4 columns like the lines before, got 8"),
    ("1 2 3 4\n2 2 x 4\n", "line 2: not a number: 'x'"),
    ("1 2 3 4\n2 2 nan 4\n", "line 2: values must be finite"),
    ("1 0 0 0\n2 0 0 0\n2 0 0 0\n", "line 3: time 2.000000000 does not come after 2.000000000"),
    ("1 0 0 0\n\n0.5 0 0 0\n", "line 3: time 0.500000000 does not come after"),
    ("1 0 0 0 0 0 0 0\n", "line 1: zero quaternion"),
    ("# only a comment\n", "no data"),
])
def test_malformed_names_file_and_line(tmp_path, text, message):
    p = tmp_path / "bad.txt"
    p.write_text(text)
    with pytest.raises(FormatError) as e:
        read_trajectory(p)
    assert message in str(e.value)
    assert e.value.path == str(p)


def test_missing_file(tmp_path):
    with pytest.raises(CartoError, match="no such trajectory file"):
        read_trajectory(tmp_path / "nope.txt")


def test_write_replaces_atomically_and_leaves_no_temp(tmp_path):
    p = tmp_path / "traj.txt"
    p.write_text("old\n")
    write_trajectory(p, sample(5), "xyt")
    assert os.listdir(tmp_path) == ["traj.txt"]
    assert len(read_trajectory(p)) == 5


def test_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    p = tmp_path / "traj.txt"
    p.write_text("old\n")

    def broken_replace(src, dst):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", broken_replace)
    with pytest.raises(CartoError, match="No space left on device"):
        write_trajectory(p, sample(5))
    assert p.read_text() == "old\n"
    assert os.listdir(tmp_path) == ["traj.txt"]


def test_write_creates_directories_and_ordinary_permissions(tmp_path):
    p = write_trajectory(tmp_path / "run" / "1" / "t.txt", sample(3))
    assert len(read_trajectory(p)) == 3
    umask = os.umask(0)
    os.umask(umask)
    assert p.stat().st_mode & 0o777 == 0o666 & ~umask


def test_write_errors(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(CartoError, match="cannot write trajectory"):
        write_trajectory(tmp_path / "file" / "t.txt", sample(3))
    with pytest.raises(CartoError, match="unknown trajectory format 'kitti'"):
        write_trajectory(tmp_path / "t.txt", sample(3), "kitti")
