"""Fuzzing every format carto reads: over 1,000 mutated inputs per run (truncations, byte flips, insertions,
duplicated and removed chunks, and well-formed text with nan / inf / huge numbers), each through the library
call its command makes, in a child process limited to 2 GB of memory and 20 s per input. An input may be
refused (CartoError: one line, exit 2) but never raise anything else, hang or crash the process.

Formats: ROS1 bag, ROS2 bag (sqlite3 and mcap storage), standalone MCAP, CARMEN plain and gzip, profile YAML,
map.carto, trajectory, relations and relocalization query files. (map_server YAML/PGM maps are not read by
carto yet: issue 14.)
"""
import gzip
import json
import math
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

from carto_cli.io.recording_writers import FORMATS, write_recording
from carto_cli.sim import Lidar, loop_building, loop_trajectory, simulate

PER_SEED = 100  # x 11 seeds
MEMORY_LIMIT = 2 * 2**30
WORKER = Path(__file__).with_name("fuzz_worker.py")


def _seeds(root: Path) -> list[dict]:
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=3.0, scan_rate=5.0, lidar=Lidar(beams=90))
    rec = sim.recording()
    topics = {t.name: t.msgtype for t in rec.topics()}
    entries = []
    for fmt in FORMATS:
        name = {"ros1": "drive.bag", "ros2-sqlite3": "drive_sqlite", "ros2-mcap": "drive_mcap",
                "mcap": "drive.mcap"}[fmt]
        write_recording(rec.records(), root / name, fmt, static_transforms=rec.static_transforms(), topics=topics)
        entries.append({"name": fmt, "path": name, "kind": "recording"})
    lines = []
    for k in range(12):
        t = 0.5 * k
        odom = f"{0.1 * k:.3f} 0.000 0.000"
        ranges = " ".join(f"{2.0 + 0.01 * j:.3f}" for j in range(31))
        lines.append(f"ODOM {odom} 0 0 0 {t:.3f} fuzz {t:.3f}")
        lines.append(f"FLASER 31 {ranges} {odom} {odom} {t + 0.01:.3f} fuzz {t + 0.01:.3f}")
    log = "\n".join(lines) + "\n"
    (root / "drive.clf").write_text(log)
    (root / "drive.clf.gz").write_bytes(gzip.compress(log.encode()))
    entries += [{"name": "carmen", "path": "drive.clf", "kind": "recording", "text": True},
                {"name": "carmen-gzip", "path": "drive.clf.gz", "kind": "recording"}]
    (root / "profile.yaml").write_text(
        "trajectory_builder_2d:\n  min_range: 0.2\n  max_range: 25.0\n  submaps:\n    num_range_data: 40\n"
        "pose_graph:\n  optimize_every_n_nodes: 30\n  constraint_builder:\n    min_score: 0.6\n"
        "gmapping:\n  particles: 20\n")
    shutil.copy(Path(__file__).with_name("data") / "hand_graph_v1.carto", root / "map.carto")
    (root / "trajectory.tum").write_text("".join(
        f"{0.1 * k:.3f} {0.1 * k:.3f} 0.5 0 0 0 {math.sin(0.05 * k):.6f} {math.cos(0.05 * k):.6f}\n"
        for k in range(30)))
    (root / "relations.txt").write_text("".join(f"{k:.1f} {k + 1:.1f} 1.0 0.1 0 0 0 0.05\n" for k in range(20)))
    (root / "queries.txt").write_text("t x y yaw sigma_xy sigma_yaw\n" + "".join(
        f"{1.0 + k:.2f} {0.5 * k:.2f} 0.3 10deg 0.5 5deg\n" for k in range(8)) + "12.0 - - -\n")
    entries += [{"name": "profile-yaml", "path": "profile.yaml", "kind": "profile", "text": True},
                {"name": "map.carto", "path": "map.carto", "kind": "carto"},
                {"name": "trajectory", "path": "trajectory.tum", "kind": "trajectory", "text": True},
                {"name": "relations", "path": "relations.txt", "kind": "relations", "text": True},
                {"name": "queries", "path": "queries.txt", "kind": "queries", "text": True}]
    (root / "seeds.json").write_text(json.dumps(entries))
    return entries


def _limit_memory():
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_LIMIT, MEMORY_LIMIT))


def test_every_format_survives_a_thousand_mutants(tmp_path, capsys):
    seeds_dir, work = tmp_path / "seeds", tmp_path / "mutants"
    seeds_dir.mkdir()
    work.mkdir()
    entries = _seeds(seeds_dir)
    # The seeds themselves are read without complaint: a mutant's refusal is about the mutation.
    r = subprocess.run([sys.executable, str(WORKER), str(seeds_dir), str(work), "0", "0"], capture_output=True,
                       text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout.strip().splitlines()[-1])["findings"] == []
    r = subprocess.run([sys.executable, str(WORKER), str(seeds_dir), str(work), str(PER_SEED), "1"],
                       capture_output=True, text=True, timeout=1800, preexec_fn=_limit_memory)
    assert r.returncode == 0, f"the fuzz worker died (signal or memory): {r.returncode}\n{r.stderr[-2000:]}"
    report = json.loads(r.stdout.strip().splitlines()[-1])
    total = sum(report["counts"].values())
    with capsys.disabled():
        print(f"\nfuzz: {total} inputs, {len(report['findings'])} findings: "
              + ", ".join(f"{k} {v}" for k, v in sorted(report["counts"].items())))
    assert total >= 1000 and len(report["counts"]) == len(entries)
    assert report["findings"] == [], json.dumps(report["findings"][:5], indent=1)


def test_the_mutations_change_the_input():
    import random

    sys.path.insert(0, str(WORKER.parent))
    from fuzz_worker import mutate

    rng = random.Random(0)
    data = np.arange(200, dtype=np.uint8).tobytes()
    mutants = [mutate(data, rng, False) for _ in range(50)]
    assert sum(m != data for m in mutants) >= 45
    assert any(len(m) < len(data) for m in mutants) and any(len(m) > len(data) for m in mutants)
    text = b"1.0 2.0 3.0 4.0"
    assert any(b"nan" in m or b"inf" in m or b"e308" in m for m in (mutate(text, rng, True) for _ in range(60)))
