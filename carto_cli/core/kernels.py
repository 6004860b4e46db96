"""The one JIT warm-up: numba kernels loaded (or compiled) once per process, timed as a stage of their own.

The first call into numba costs about a second (runtime initialisation, then each kernel's on-disk
cache), whichever kernel it is. Each layer that owns kernels registers a function that runs them once
on toy data; :func:`warm_up` runs every registered one that has not run yet, so that cost shows as the
``jit warm-up`` stage instead of inflating the first scan, search or query.
"""
from __future__ import annotations

from collections.abc import Callable

from carto_cli.core.timing import NullTimer

STAGE = "jit warm-up"

_registered: list[Callable[[], None]] = []
_done: set[Callable[[], None]] = set()


def register_warm_up(fn: Callable[[], None]) -> Callable[[], None]:
    """Decorator: ``fn`` runs the kernels of its module once on toy data."""
    if fn not in _registered:
        _registered.append(fn)
    return fn


def pending() -> bool:
    """Whether a registered warm-up has not run in this process."""
    return any(fn not in _done for fn in _registered)


def warm_up(timer=None) -> None:
    """Run every registered warm-up not yet run, inside ``timer``'s ``jit warm-up`` stage."""
    if not pending():
        return
    timer = timer or NullTimer()
    with timer.stage(STAGE):
        for fn in list(_registered):
            if fn not in _done:
                fn()
                _done.add(fn)
