"""Giving freed memory back to the operating system.

glibc's malloc keeps what a program frees for later allocations: large blocks are mapped and unmapped, but after
the first is freed it raises its threshold for mapping to that size, and blocks freed in a thread's arena stay
with the arena. A long run that frees hundreds of MB of precomputation grids (``mapping.slam``) would go on
holding them, and the arrays allocated next would come on top. ``malloc_trim`` hands the free pages back.
"""
from __future__ import annotations

import ctypes
import functools
import sys

__all__ = ["give_back", "peak_kb", "peak_rss_mb", "reset_peak", "status_kb"]


@functools.lru_cache(maxsize=1)
def _trim():
    try:
        # The process's own symbols hold the C library's (no ldconfig lookup, as ctypes.util would run).
        return getattr(ctypes.CDLL(None), "malloc_trim", None)  # glibc only (not musl, not macOS)
    except OSError:
        return None


def give_back() -> bool:
    """Return the process's free heap pages to the system where the C library can (True when it could)."""
    trim = _trim()
    if trim is None:
        return False
    trim(0)
    return True


def status_kb(field: str) -> int:
    """A memory field of /proc/self/status (VmRSS, VmHWM) in kB; 0 where there is none (not Linux)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def peak_kb() -> int:
    """The process's peak resident memory since it started or since ``reset_peak`` (kB; 0 where unknown)."""
    return status_kb("VmHWM")


def reset_peak() -> bool:
    """Start measuring the peak resident memory afresh (Linux's clear_refs; True when it could). What a process
    and a child of its reach together is the sum of their peaks over the child's life, not over the whole run."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def peak_rss_mb() -> float | None:
    """The process's peak resident memory (MB; None where the platform does not say), since it started or since
    ``reset_peak``. Linux's VmHWM where there is one: getrusage's ru_maxrss also counts the footprint of the
    process this one was started from, at the moment it was (a `carto map` run by a 600 MB test process read
    600 MB), and ``reset_peak`` does not clear that part."""
    kb = peak_kb()
    if kb > 0:
        return kb / 1024
    try:
        import resource
    except ImportError:  # not on a POSIX system
        return None
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return peak / (2**20 if sys.platform == "darwin" else 2**10)  # bytes on macOS, kilobytes elsewhere
