"""Independent matches on threads: numba kernels compiled with ``nogil=True`` run side by side.

Results come back in the order of the inputs whatever the number of workers, so a caller that applies them
in that order produces the same output with one worker or many.
"""
from __future__ import annotations

import os
import sys
import threading
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from typing import Generic, TypeVar

T = TypeVar("T")
R = TypeVar("R")


class Done(Generic[R]):
    """A result computed at once (one job), with a future's ``result``: callers treat both the same."""

    __slots__ = ("_value",)

    def __init__(self, value: R):
        self._value = value

    def result(self) -> R:
        return self._value


def available_cores() -> int:
    """Cores this process may run on (a CI runner's CPU quota through affinity, else the machine's count)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def fork_safe() -> bool:
    """Whether a forked child can do Python work: fork copies only the calling thread, so a lock another thread
    of ours holds at that moment would stay held in the child for ever."""
    # Linux only: macOS has fork, but its system libraries are not safe to use in a forked child.
    return sys.platform.startswith("linux") and threading.active_count() == 1


def die_with_parent(parent: int) -> None:
    """In a forked child: be killed when ``parent`` (the process that forked this one) dies, even by SIGKILL,
    which runs no clean-up there; a child blocked on a pipe it shares with its dead parent would wait for ever.
    Linux only (prctl's PR_SET_PDEATHSIG); elsewhere nothing is forked."""
    import ctypes
    import signal

    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:  # the parent died before the request was made
        os._exit(1)


def map_ordered(fn: Callable[[T], R], items: Iterable[T], jobs: int | None = None) -> list[R]:
    """``[fn(x) for x in items]``, on ``jobs`` threads (None: every available core)."""
    items = list(items)
    jobs = available_cores() if jobs is None else max(1, int(jobs))
    if jobs == 1 or len(items) < 2:
        return [fn(x) for x in items]
    with ThreadPoolExecutor(max_workers=min(jobs, len(items))) as pool:
        return list(pool.map(fn, items))
