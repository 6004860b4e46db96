"""Checks that run beside the other tests (importable as `background`: pytest puts tests/ on sys.path).

mypy over the package and the kernel tests with numba off take a minute or more each and need nothing the other
tests make, while the rest of the suite keeps one of two cores busy most of the time. A test module registers
such a check by name and marks its test ``@pytest.mark.background(name)``; conftest.py starts every marked check
as soon as the session has collected its tests, and the test waits for the result where it stands in the order.
Whatever is still running when the session ends is stopped.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
from collections.abc import Callable
from pathlib import Path


class Check:
    """Commands run at once, each with its output in a file. ``commands`` makes them from ``scratch``, a
    directory of the check's own (for what they write)."""

    def __init__(self, commands: Callable[[Path], list[list[str]]], cwd: Path, env: dict[str, str] | None = None):
        self.scratch = Path(tempfile.mkdtemp(prefix="carto-check-"))
        commands_ = commands(self.scratch)
        self._logs = [open(self.scratch / f"output-{k}.txt", "w+") for k in range(len(commands_))]
        self._procs = [subprocess.Popen(cmd, cwd=cwd, stdout=log, stderr=subprocess.STDOUT, text=True,
                                        env={**os.environ, **(env or {})})
                       for cmd, log in zip(commands_, self._logs)]

    def results(self, timeout: float) -> list[tuple[int, str]]:
        """(exit code, output) of each command, in order, once all have ended."""
        out = []
        for proc, log in zip(self._procs, self._logs):
            code = proc.wait(timeout=timeout)
            log.seek(0)
            out.append((code, log.read()))
        return out

    def stop(self) -> None:
        for proc in self._procs:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        for log in self._logs:
            log.close()
        shutil.rmtree(self.scratch, ignore_errors=True)


_factories: dict[str, Callable[[], Check]] = {}
_started: dict[str, Check] = {}


def register(name: str, factory: Callable[[], Check]) -> None:
    _factories[name] = factory


def start(name: str) -> None:
    """Start the check ``name`` unless it runs already (conftest.py, once the session has collected it)."""
    if name not in _started:
        _started[name] = _factories[name]()


def take(name: str) -> Check:
    """The check ``name``, started now if nothing started it; stopped at the end of the session."""
    start(name)
    return _started[name]


def stop_all() -> None:
    while _started:
        _started.popitem()[1].stop()
