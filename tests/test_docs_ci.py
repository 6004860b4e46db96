"""docs/ci.md's jobs run here as far as they can: the GitHub Actions and GitLab CI YAML parse, and every carto
command in them (and the baseline command before them) runs, in a directory laid out as the doc assumes, with
the exit status and artifacts the doc promises. What needs a CI service (checkout, caches, artifact upload,
pip from the index) is the runner's part and is not run."""
import math
import re
import shlex
from pathlib import Path

import numpy as np
import pytest
import yaml
from support import REPO
from typer.testing import CliRunner

from carto_cli.cli import app

DOC = REPO / "docs" / "ci.md"


def blocks(language: str) -> list[tuple[str, str]]:
    """(heading, code) of each fenced block in the given language, under the nearest '## ' or '### ' heading."""
    out, heading = [], ""
    for part in re.split(r"(^#{2,3} .*$)", DOC.read_text(), flags=re.M):
        if part.startswith("#"):
            heading = part.lstrip("# ").strip()
            continue
        out += [(heading, code) for code in re.findall(rf"```{language}\n(.*?)```", part, flags=re.S)]
    return out


def github_commands(doc: dict) -> list[str]:
    (job,) = doc["jobs"].values()
    return [" ".join(step["run"].split()) for step in job["steps"] if "run" in step]


def gitlab_commands(doc: dict) -> list[str]:
    (job,) = doc.values()
    return list(job["script"])


@pytest.fixture(scope="module")
def workspace(tmp_path_factory):
    """recordings/lap.bag (a simulated lap with odometry) and recordings/lap.relations from its ground truth."""
    from carto_cli.io.recording_writers import write_recording
    from carto_cli.sim import loop_building, loop_trajectory, simulate

    root = tmp_path_factory.mktemp("ci")
    (root / "recordings").mkdir()
    (root / "ci").mkdir()
    world = loop_building()
    sim = simulate(world, loop_trajectory(world), duration=40.0, scan_rate=10.0)
    write_recording(iter(list(sim.records(["/scan", "/odom"]))), root / "recordings" / "lap.bag", "ros1")
    gt = sim.ground_truth  # (t, x, y, yaw)
    lines = []
    for i in range(0, len(gt) - 20, 10):
        (t1, x1, y1, a1), (t2, x2, y2, a2) = gt[i], gt[i + 20]
        c, s = math.cos(a1), math.sin(a1)
        dx, dy = c * (x2 - x1) + s * (y2 - y1), -s * (x2 - x1) + c * (y2 - y1)
        dyaw = math.atan2(math.sin(a2 - a1), math.cos(a2 - a1))
        lines.append(f"{t1:.9f} {t2:.9f} {dx:.6f} {dy:.6f} 0 0 0 {dyaw:.6f}")
    (root / "recordings" / "lap.relations").write_text("\n".join(lines) + "\n")
    return root


def untimed(argv: list[str]) -> list[str]:
    """The command with its speed gate's limit lifted. Whether this machine is as fast a minute later is not
    this test's question (a shared machine made the gate flap here: `scan/preprocess` +42 % between two runs
    of the same code); the gate's arithmetic is tested with set timings in tests/commands/test_profile.py and
    its false-alarm rate measured by bench/gate_stability.py."""
    if "--max-regression" not in argv:
        return argv
    i = argv.index("--max-regression") + 1
    return argv[:i] + ["1000"] + argv[i + 1 :]


def run_commands(commands: list[str], cwd: Path, monkeypatch) -> None:
    monkeypatch.chdir(cwd)
    runner = CliRunner()
    for command in commands:
        argv = untimed(shlex.split(command))
        if argv[0] == "pip":
            continue  # the runner's install step
        assert argv[0] == "carto", command
        result = runner.invoke(app, argv[1:])
        assert result.exit_code == 0, f"{command}\n{result.output}"


def test_the_jobs_parse_and_name_the_same_commands():
    (baseline,) = [code for heading, code in blocks("sh") if "baseline" in heading]
    github = [yaml.safe_load(code) for heading, code in blocks("yaml") if heading == "GitHub Actions"]
    gitlab = [yaml.safe_load(code) for heading, code in blocks("yaml") if heading == "GitLab CI"]
    assert len(github) == len(gitlab) == 1
    gh, gl = github_commands(github[0]), gitlab_commands(gitlab[0])
    assert [c for c in gh if c.startswith("carto")] == [c for c in gl if c.startswith("carto")]
    assert any(c.startswith("pip install carto-slam") for c in gh + gl)  # our distribution, not PyPI's "carto"
    # numba's cache directory is an absolute path each service expands ("~" is not expanded in env values).
    assert "NUMBA_CACHE_DIR" in github[0]["jobs"]["slam-regression"]["env"]
    assert not any("~" in v for v in github[0]["jobs"]["slam-regression"]["env"].values())
    assert "carto profile" in baseline


def test_the_gitlab_job_runs_here(workspace, monkeypatch):
    """The baseline, then the job's script, in a checkout laid out as the doc's: the accuracy gate passes, the
    speed gate runs against the baseline (its limit lifted, see `untimed`), and the artifacts it reports exist."""
    (baseline,) = [code for heading, code in blocks("sh") if "baseline" in heading]
    first = [line for line in baseline.splitlines() if line.startswith("carto ")]
    (gitlab,) = [yaml.safe_load(code) for heading, code in blocks("yaml") if heading == "GitLab CI"]
    run_commands(first + gitlab_commands(gitlab), workspace, monkeypatch)
    out = workspace / "out"
    for name in ("map.pgm", "map.yaml", "trajectory.tum", "profile.json", "accuracy.xml", "speed.xml"):
        assert (out / name).is_file(), name
    assert (workspace / "ci" / "profile-baseline.json").is_file()
    tum = np.loadtxt(out / "trajectory.tum")
    assert tum.shape[1] == 8 and len(tum) > 300
