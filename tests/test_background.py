"""The checks that run beside the tests (tests/background.py) start only when tests will run."""
import os
import subprocess
import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent

# A plugin for the inner pytest: before conftest.py's hook starts the marked checks, background.start is wrapped
# so that every check started is written to a file.
PLUGIN = '''
import pytest


@pytest.hookimpl(tryfirst=True)
def pytest_collection_finish(session):
    import background

    started = background.start

    def recorded(name):
        with open({path!r}, "a") as f:
            f.write(name + "\\n")
        started(name)

    background.start = recorded
'''


def _started_checks(tmp_path, *pytest_args) -> list[str]:
    log = tmp_path / "started.txt"
    (tmp_path / "record_background.py").write_text(PLUGIN.format(path=str(log)))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), os.environ.get("PYTHONPATH", "")])}
    out = subprocess.run([sys.executable, "-m", "pytest", "-p", "record_background", "-p", "no:cacheprovider",
                          "-q", *pytest_args], cwd=TESTS.parent, env=env, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    return log.read_text().split() if log.exists() else []


def test_listing_the_tests_starts_no_background_check(tmp_path):
    assert _started_checks(tmp_path, "--collect-only", str(TESTS / "test_static_checks.py")) == []


def test_planning_to_run_a_marked_test_starts_its_check(tmp_path):
    # The same plugin sees the check start once the marked test is chosen to run (so the test above can fail);
    # --setup-plan runs no test, and the session's end stops the check at once.
    started = _started_checks(tmp_path, "--setup-plan", str(TESTS / "test_static_checks.py") + "::test_mypy_finds_nothing")
    assert set(started) == {"mypy"}
