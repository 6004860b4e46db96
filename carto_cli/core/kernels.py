"""The one JIT warm-up: numba kernels loaded (or compiled) once per process, timed as a stage of their own.

The first call into numba costs about a second (runtime initialisation, then each kernel's on-disk
cache), whichever kernel it is. Each layer that owns kernels registers a function that runs them once
on toy data; :func:`warm_up` runs every registered one that has not run yet, so that cost shows as the
``jit warm-up`` stage instead of inflating the first scan, search or query.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager
from typing import Any

from carto_cli.core.timing import NullTimer

STAGE = "jit warm-up"
HELPER_ENV = "CARTO_KERNEL_HELPER"  # set in a helper process: it must not start helpers of its own

_registered: list[tuple[Callable[[], None], str | None]] = []
_done: set[Callable[[], None]] = set()
_compiled: list[str] = []  # the warm-ups that found their module's kernels not yet in the on-disk cache
_notice: list[Callable[[str], None]] = []  # told before a warm-up compiles (the command line prints it)


def on_compiling(fn: Callable[[str], None] | None) -> None:
    """``fn`` hears one sentence before a warm-up starts compiling (None: nobody): a first run is otherwise
    silent for up to a minute, which a CI log cannot tell from a hang."""
    _notice[:] = [] if fn is None else [fn]


def register_warm_up(fn: Callable[[], None] | None = None, *, system: str | None = None) -> Any:
    """Decorator (``@register_warm_up`` or ``@register_warm_up(system="gmapping")``): ``fn`` runs the kernels of its
    module once on toy data. ``system``: only a run of that mapping system needs them (None: every run). The first
    run after installing compiles what it warms up (GMapping's kernels alone take half a minute), so a
    Cartographer run must not pay for GMapping's."""
    if fn is None:
        return lambda f: register_warm_up(f, system=system)
    if all(fn is not g for g, _ in _registered):
        _registered.append((fn, system))
    return fn


def _wanted(systems: Collection[str] | None) -> list[Callable[[], None]]:
    return [fn for fn, s in _registered if fn not in _done and (systems is None or s is None or s in systems)]


def compiled_here() -> bool:
    """Whether a warm-up of this process found kernels not yet cached, so that its stage was mostly compiling
    (a warm stage loads them, 0.6-1.2 s here)."""
    return bool(_compiled)


def pending(systems: Collection[str] | None = None) -> bool:
    """Whether a registered warm-up (the shared ones and those of ``systems``; None: any) has not run here."""
    return bool(_wanted(systems))


def warm_up(timer: Any = None, systems: Collection[str] | None = None) -> None:
    """Run every registered warm-up not yet run (the shared ones and those of ``systems``; None: all), inside
    ``timer``'s ``jit warm-up`` stage. On a cold cache (the first run after installing) the kernels are compiled
    by this process and helper processes at once, one per further core, each writing its share to the on-disk
    cache this process then loads: compiling is single-threaded, and it is most of a first run's time."""
    wanted = _wanted(systems)
    if not wanted:
        return
    timer = timer or NullTimer()
    with timer.stage(STAGE):
        cold = [_name(fn) for fn in wanted if _cold(fn)]
        _compiled.extend(cold)
        if cold:
            for notice in _notice:
                notice(f"compiling kernels ({len(cold)} of {len(wanted)} groups), once after installing: later runs "
                       f"load them from {os.environ.get('NUMBA_CACHE_DIR') or 'the cache'}")
        claims = tempfile.mkdtemp(prefix="carto-jit-") if cold_cache(wanted) else None
        helpers = _start_helpers(wanted, claims) if claims is not None else []
        try:
            # Whoever claims a warm-up first compiles it (this process from the front of the list, helpers from
            # the back): the shares balance however unequal the warm-ups are (local SLAM's take 10 s, others 1 s).
            for fn in wanted:
                if claims is None or claim(claims, fn):
                    fn()
                    _done.add(fn)
            for helper in helpers:
                helper.wait()  # a helper that failed only means this process compiles its share below
        except BaseException:
            # Ctrl-C, SIGTERM or an error here: the helpers would compile on after this process is gone (they are
            # not its forks and do not die with it). Numba writes a cache entry to a temporary it then renames:
            # a killed helper leaves no entry half-written.
            for helper in helpers:
                helper.kill()
                helper.wait()
            raise
        finally:
            if claims is not None:
                shutil.rmtree(claims, ignore_errors=True)
        for fn in wanted:
            if fn not in _done:
                fn()  # compiled by a helper: loaded from the cache
                _done.add(fn)


def _name(fn: Callable[[], None]) -> str:
    return f"{fn.__module__}:{fn.__qualname__}"


def claim(claims: str, fn_or_name: str | Callable[[], None]) -> bool:
    """Whether this process is the first to take the warm-up (an exclusive file create is atomic)."""
    name = fn_or_name if isinstance(fn_or_name, str) else _name(fn_or_name)
    try:
        os.close(os.open(os.path.join(claims, name.replace(":", "-")), os.O_CREAT | os.O_EXCL | os.O_WRONLY))
    except FileExistsError:
        return False
    return True


def cold_cache(wanted: list[Callable[[], None]]) -> bool:
    """Whether helper processes would pay: a cold cache, two warm-ups or more, two cores or more, and this
    process is not itself a helper."""
    from carto_cli.core.parallel import available_cores

    return (not os.environ.get(HELPER_ENV) and len(wanted) >= 2 and available_cores() >= 2
            and any(_cold(fn) for fn in wanted))


def _cold(fn: Callable[[], None]) -> bool:
    """Whether no kernel of ``fn``'s module is in numba's on-disk cache yet (as after installing). Kernels only
    ever called from other kernels have no entry of their own, so one entry in the module means warm."""
    from numba.core.registry import CPUDispatcher

    module = sys.modules.get(fn.__module__)
    indexes = []
    for value in vars(module).values() if module is not None else ():
        if isinstance(value, CPUDispatcher) and value.__module__ == fn.__module__:
            try:
                cache = value._cache  # type: ignore[attr-defined]  # numba's own layout
                indexes.append(cache._cache_file._index_path)
            except AttributeError:
                return False  # unknown layout: never guess "cold"
    return bool(indexes) and not any(os.path.exists(i) for i in indexes)


def _start_helpers(wanted: list[Callable[[], None]], claims: str) -> list[subprocess.Popen]:
    from carto_cli.core.parallel import available_cores

    n = min(available_cores(), len(wanted)) - 1
    names = [_name(fn) for fn in wanted]
    helpers = []
    for k in range(1, n + 1):
        order = names[::-1] if k == 1 else names[k:] + names[:k]
        code = f"from carto_cli.core.kernels import _helper; _helper({order!r}, {claims!r})"
        try:
            helpers.append(subprocess.Popen([sys.executable, "-c", code], env={**os.environ, HELPER_ENV: "1"},
                                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL))
        except OSError:
            break
    return helpers


def _helper(names: list[str], claims: str) -> None:
    """In a helper process: run the named warm-ups nobody has claimed (compiling their kernels into the cache)."""
    import importlib

    for name in names:
        if claim(claims, name):
            module, qualname = name.split(":")
            getattr(importlib.import_module(module), qualname)()


@contextmanager
def compile_time() -> Iterator[Callable[[], float]]:
    """Seconds this process spends compiling kernels while the block runs (numba's own count of its cache misses:
    loading a cached kernel is not compiling), read through the callable it gives, during or after the block. For
    work whose kernels compile on first use rather than in a warm-up (relocalize): on a cold cache that is seconds a
    user should hear about. Kernels compile one at a time (numba's compiler lock), so nested and concurrent
    compiles are counted once."""
    from numba.core import event

    listener = event.TimingListener()
    with event.install_listener("numba:compile", listener):
        yield lambda: listener.duration if listener.done else 0.0
