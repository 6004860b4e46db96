"""Helpers shared by the tests (importable as `support`: pytest puts tests/ on sys.path)."""
import math
import os
from pathlib import Path

import numpy as np
import pytest

from carto_cli.core.records import Imu, Odometry, Scan, Transform


def _find_shared() -> Path:
    """The project's shared data: $CARTO_SHARED_DATA, else ../shared/data next to the checkout, else /work/shared/data."""
    candidates = [os.environ.get("CARTO_SHARED_DATA"), Path(__file__).resolve().parents[2] / "shared" / "data",
                  "/work/shared/data"]
    for c in candidates:
        if c and Path(c).is_dir():
            return Path(c)
    return Path(__file__).resolve().parents[2] / "shared" / "data"


SHARED = _find_shared()
REPO = Path(__file__).resolve().parents[1]
SAMPLE_BAG = REPO / "data" / "ccny_laser_scan_matcher_demo.bag"

# tests/test_static_checks.py runs the kernel tests once more as plain Python (NUMBA_DISABLE_JIT, for coverage),
# where a kernel is about a hundred times slower: a randomized comparison takes fewer draws there, through the
# same code paths, and all of them with the kernels compiled.
JIT = os.environ.get("NUMBA_DISABLE_JIT", "0") in ("", "0")


def draws(compiled: int, plain: int) -> int:
    """How many random cases a comparison takes: ``compiled`` with numba on, ``plain`` without."""
    return compiled if JIT else plain


def shared_path(*parts) -> Path:
    """A file under ../shared/data; the test is skipped on machines without it."""
    p = SHARED.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"shared data not available: {p}")
    return p


def synthetic_records(n_scans: int = 20, beams: int = 90, seed: int = 0) -> list:
    """Interleaved scans (10 Hz), odometry (50 Hz) and IMU (100 Hz) with exact float values."""
    rng = np.random.default_rng(seed)
    records = []
    t0_ns = 1_000_000_000_000  # times built from whole nanoseconds: the resolution of every ROS format
    inc = np.float32(2 * math.pi / beams)
    for i in range(n_scans):
        t_ns = t0_ns + 100_000_000 * i
        t = t_ns / 1e9
        ranges = rng.uniform(0.5, 8.0, beams).astype(np.float32)
        ranges[rng.integers(0, beams, 3)] = np.nan
        ranges[rng.integers(0, beams, 2)] = np.inf
        angles = (np.float32(-math.pi) + np.arange(beams, dtype=np.float32) * inc).astype(np.float32)
        records.append(
            Scan(time=t, ranges=ranges, angles=angles, frame="laser", topic="/scan", range_min=0.1,
                 range_max=10.0, angle_min=float(np.float32(-math.pi)), angle_increment=float(inc),
                 time_increment=0.0, scan_time=0.1)
        )
        for k in range(5):
            tk = (t_ns + 20_000_000 * k + 1_000_000) / 1e9
            records.append(Odometry(time=tk, x=0.1 * i + 0.02 * k, y=0.01 * i, yaw=0.05 * i, topic="/odom",
                                    vx=0.2, vy=0.0, wz=0.05))
        for k in range(10):
            tk = (t_ns + 10_000_000 * k + 500_000) / 1e9
            records.append(Imu(time=tk, angular_velocity=np.array([0.0, 0.0, 0.05]),
                               linear_acceleration=np.array([0.1, 0.0, 9.81]),
                               orientation=np.array([0.0, 0.0, math.sin(0.025 * i), math.cos(0.025 * i)]),
                               frame="imu", topic="/imu"))
    records.sort(key=lambda r: r.time)
    return records


STATIC_TF = [Transform(parent="base_link", child="laser", translation=(0.2, 0.0, 0.3),
                       rotation=(0.0, 0.0, math.sin(0.05), math.cos(0.05)))]


def write_carmen_log(sim, path: Path, *, robotlaser: bool = False, no_return: float = 80.0, gz: bool = False) -> Path:
    """A simulation as a CARMEN log, one line per message in time order: ODOM, and each scan as FLASER (the
    robot's odometry pose at the scan) or, with ``robotlaser``, ROBOTLASER1 with the lidar's own fan, as
    bench-dense's logs are. A beam with no return reads ``no_return``."""
    import gzip

    lidar, odom = sim.lidar, sim.odometry
    lines = [(t, f"ODOM {x:.6f} {y:.6f} {yaw:.6f} {vx:.3f} {wz:.3f} 0 {t:.6f} host {t:.6f}")
             for t, x, y, yaw, vx, wz in odom]
    for t, ranges in zip(sim.scan_times, sim.scan_ranges()):
        pose = " ".join(f"{np.interp(t, odom[:, 0], odom[:, i]):.6f}" for i in (1, 2, 3))
        beams = " ".join(f"{r:.3f}" if np.isfinite(r) else f"{no_return:.3f}" for r in ranges)
        if robotlaser:
            head = (f"ROBOTLASER1 0 {-lidar.fov / 2:.6f} {lidar.fov:.6f} {lidar.angle_increment:.6f} "
                    f"{lidar.max_range:.1f} 0.01 0 {len(ranges)}")
            lines.append((t, f"{head} {beams} 0 {pose} {pose} 0 0 0.5 0.5 0 {t:.6f} host {t:.6f}"))
        else:
            lines.append((t, f"FLASER {len(ranges)} {beams} {pose} {pose} {t:.6f} host {t:.6f}"))
    text = "".join(line + "\n" for _, line in sorted(lines, key=lambda p: p[0]))
    if gz:
        path.write_bytes(gzip.compress(text.encode()))
    else:
        path.write_text(text)
    return path


def sim_carmen_log(path: Path, duration: float = 8.0, gz: bool = False) -> Path:
    """A CARMEN log of the simulated loop that maps in a second: ODOM at 10 Hz, FLASER (181 beams) at 5 Hz."""
    from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate

    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=duration, lidar=Lidar(beams=181, fov=math.pi, dropout=0.0),
                   scan_rate=5.0, odom_rate=10.0, imu_rate=0.0)
    return write_carmen_log(sim, path, gz=gz)


def _idl(name, body):
    pkg, _, struct = name.split("/")
    return (f"{'=' * 80}\nIDL: {name}\nmodule {pkg} {{\n  module msg {{\n    struct {struct} {{\n{body}"
            "    };\n  };\n};\n")


def laser_scan_idl(extra_member=""):
    """sensor_msgs/msg/LaserScan as rosbag2 writes a ros2idl definition: the type's IDL, then each type it uses,
    each after a separator and a header; ``extra_member`` is a line put first in LaserScan's struct (line 6)."""
    floats = "".join(f"      float {n};\n" for n in ("angle_min", "angle_max", "angle_increment", "time_increment",
                                                     "scan_time", "range_min", "range_max"))
    return (_idl("sensor_msgs/msg/LaserScan", extra_member + "      std_msgs::msg::Header header;\n" + floats
                 + "      sequence<float> ranges;\n      sequence<float> intensities;\n")
            + _idl("std_msgs/msg/Header", "      builtin_interfaces::msg::Time stamp;\n      string frame_id;\n")
            + _idl("builtin_interfaces/msg/Time", "      int32 sec;\n      uint32 nanosec;\n"))
