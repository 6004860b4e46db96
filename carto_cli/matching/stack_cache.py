"""Precomputation stacks of a map's submaps, built on first use and kept under a memory budget (LRU).

The one cache of stacks: relocalization's over a saved map, and the loop-closure search's over the finished
submaps of a map being built (the seed's submap cache). A dropped stack is rebuilt identically from its grid.
"""
from __future__ import annotations

import threading
import time
from collections import OrderedDict

from carto_cli.core.memory import give_back
from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.matching.precomputation import PrecomputationGridStack

__all__ = ["StackCache"]

# Freed memory is given back each time 1/TRIM_SHARE of the budget was evicted (16 MB of the default 256): on the
# 2-hour campus 72 calls, 0.5 s, peak 935 MB, against 359 calls, 1.5 s, 912 MB at every eviction and 980 MB never.
TRIM_SHARE = 16


_COUNTERS = ("hits", "misses", "evictions", "build_ms", "peak_bytes")


class StackCache:
    """Precomputation stacks by submap id, least recently used dropped beyond ``budget_bytes``.

    The stack just built or used is always kept, even alone above the budget. Safe to share between threads
    (two threads missing the same submap at once may both build it; either copy is the same).
    """

    def __init__(self, budget_bytes: int, depth: int):
        self.budget_bytes = int(budget_bytes)
        self.depth = int(depth)
        self._stacks: OrderedDict[int, PrecomputationGridStack] = OrderedDict()
        self.bytes = 0
        self.hits = 0
        self.misses = 0
        self.evictions = 0
        self.build_ms = 0.0
        self.peak_bytes = 0
        self._dropped_bytes = 0  # evicted since memory was last given back
        self._lock = threading.Lock()

    def get(self, index: int, grid: ProbabilityGrid) -> PrecomputationGridStack:
        with self._lock:
            stack = self._stacks.get(index)
            if stack is not None:
                self._stacks.move_to_end(index)
                self.hits += 1
                return stack
            self.misses += 1
        t0 = time.perf_counter()
        stack = PrecomputationGridStack(grid, self.depth)
        with self._lock:
            self.build_ms += (time.perf_counter() - t0) * 1e3
            old = self._stacks.pop(index, None)
            if old is not None:
                self.bytes -= old.memory_bytes
            self._stacks[index] = stack
            self.bytes += stack.memory_bytes
            while self.bytes > self.budget_bytes and len(self._stacks) > 1:
                dropped = self._stacks.popitem(last=False)[1].memory_bytes
                self.bytes -= dropped
                self._dropped_bytes += dropped
                self.evictions += 1
            self.peak_bytes = max(self.peak_bytes, self.bytes)
            # The budget holds for the process only if what is dropped leaves it (core.memory); a share of the
            # budget at a time, since handing pages back walks the whole heap (up to 11 ms).
            trim = self._dropped_bytes >= self.budget_bytes // TRIM_SHARE
            if trim:
                self._dropped_bytes = 0
        if trim:
            give_back()
        return stack

    def counters(self) -> dict:
        """The statistics (hits, misses, evictions, build_ms, peak_bytes) as one value."""
        with self._lock:
            return {name: getattr(self, name) for name in _COUNTERS}

    def add_counters(self, counters: dict) -> None:
        """Count another cache's work as this one's (the pose graph's process): sums, and the larger peak."""
        with self._lock:
            for name in _COUNTERS:
                mine, theirs = getattr(self, name), counters[name]
                setattr(self, name, max(mine, theirs) if name == "peak_bytes" else mine + theirs)

    def clear(self) -> None:
        """Drop every stack (statistics kept): when no search will follow, their memory is better given back."""
        with self._lock:
            self._stacks.clear()
            self.bytes = 0

    def __contains__(self, index: int) -> bool:
        return index in self._stacks

    def __len__(self) -> int:
        return len(self._stacks)

    def stats(self) -> dict:
        return {"stacks": len(self._stacks), "bytes": self.bytes, "budget_bytes": self.budget_bytes,
                "hits": self.hits, "misses": self.misses, "evictions": self.evictions,
                "build_ms": round(self.build_ms, 3)}
