"""carto tune against a real PostgreSQL server (started here: initdb and pg_ctl on a unix socket in a temporary
directory): two worker processes share one study, a third process resumes it; a missing driver is named."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

from carto_cli.core.errors import CartoError

SCRIPT = """
import sys
from pathlib import Path
from carto_cli.sim.lidar import Lidar
from carto_cli.sim.recording import simulate
from carto_cli.sim.trajectory import loop_trajectory
from carto_cli.sim.world import loop_building
from carto_cli.tuning.study import StudyRequest, tune

world = loop_building()
sim = simulate(world, loop_trajectory(world), duration=20.0, scan_rate=5.0, lidar=Lidar(beams=180))
space = {"trajectory_builder_2d.ceres_scan_matcher.translation_weight": {"low": 0.1, "high": 1.0e4, "log": True}}
seen = []
request = StudyRequest([sim.recording()], Path(sys.argv[1]), space=space, trials=int(sys.argv[3]),
                       n_jobs=int(sys.argv[4]), ground_truth=[sim.ground_truth], seed=0, max_scans=40,
                       storage=sys.argv[2], study_name="shared")
result = tune(request, on_trial=lambda n, v, b: seen.append(n))
print(result.n_trials, result.n_complete, len(seen))
"""


@pytest.fixture(scope="module")
def postgres():
    """The URL of a fresh PostgreSQL server on a unix socket; stopped after the module."""
    pytest.importorskip("psycopg", reason="the test extra installs psycopg (the postgres extra's driver)")
    initdb, pg_ctl = shutil.which("initdb"), shutil.which("pg_ctl")
    if initdb is None or pg_ctl is None:
        pytest.skip("PostgreSQL's initdb / pg_ctl are not on PATH")
    # PostgreSQL refuses to run as root: as root, run it as 'nobody', in a directory it can reach and write
    # (pytest's own temporary directories are private to their owner).
    as_user = ["runuser", "-u", "nobody", "--"] if os.geteuid() == 0 else []
    base = Path(tempfile.mkdtemp(prefix="carto-pg-"))
    data, sock = base / "data", base / "sock"
    sock.mkdir()
    if as_user:
        for d in (base, sock):
            d.chmod(0o777)
    subprocess.run([*as_user, initdb, "-D", str(data), "-U", "carto", "--auth=trust", "-E", "UTF8"],
                   check=True, capture_output=True)
    subprocess.run([*as_user, pg_ctl, "-D", str(data), "-o", f"-k {sock} -c listen_addresses=''",
                    "-l", str(base / "pg.log"), "-w", "start"], check=True, capture_output=True)
    try:
        yield f"postgresql://carto@/postgres?host={sock}"
    finally:
        subprocess.run([*as_user, pg_ctl, "-D", str(data), "-m", "immediate", "stop"], capture_output=True)
        shutil.rmtree(base, ignore_errors=True)


def _tune(out, url, trials, jobs):
    done = subprocess.run([sys.executable, "-c", SCRIPT, str(out), url, str(trials), str(jobs)],
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr
    return tuple(map(int, done.stdout.split()[-3:]))


def test_workers_share_a_postgres_study_and_a_third_process_resumes_it(postgres, tmp_path):
    n_trials, n_complete, seen = _tune(tmp_path / "p.yaml", postgres, 4, 2)
    assert (n_trials, n_complete) == (4, 4) and 1 <= seen < 4  # the worker process ran the rest
    n_trials, n_complete, seen = _tune(tmp_path / "p.yaml", postgres, 2, 1)
    assert (n_trials, n_complete, seen) == (6, 6, 2)


def test_a_missing_database_driver_is_named(sim, tmp_path, monkeypatch):
    import optuna

    from carto_cli.tuning.study import StudyRequest, tune

    def no_driver(*args, **kwargs):
        raise ModuleNotFoundError("No module named 'psycopg'", name="psycopg")

    monkeypatch.setattr(optuna, "create_study", no_driver)
    with pytest.raises(CartoError, match=r"the database driver 'psycopg' is not installed .*carto-slam\[postgres\]"):
        tune(StudyRequest([sim.recording()], tmp_path / "x.yaml",
                          space={"pose_graph.constraint_builder.min_score": {"low": 0.5, "high": 0.7}}, trials=1,
                          storage="postgresql://u@/db?host=/nowhere"))
