"""Precomputation stacks of a map's submaps, built on first use and kept under a memory budget (LRU)."""
from __future__ import annotations

import time
from collections import OrderedDict

from carto_cli.matching.precomputation import PrecomputationGridStack

__all__ = ["StackCache"]


class StackCache:
    """Precomputation stacks by submap id, least recently used dropped beyond ``budget_bytes``.

    The stack just built or used is always kept, even alone above the budget.
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

    def get(self, index: int, grid) -> PrecomputationGridStack:
        stack = self._stacks.get(index)
        if stack is not None:
            self._stacks.move_to_end(index)
            self.hits += 1
            return stack
        self.misses += 1
        t0 = time.perf_counter()
        stack = PrecomputationGridStack(grid, self.depth)
        self.build_ms += (time.perf_counter() - t0) * 1e3
        self._stacks[index] = stack
        self.bytes += stack.memory_bytes
        while self.bytes > self.budget_bytes and len(self._stacks) > 1:
            _, old = self._stacks.popitem(last=False)
            self.bytes -= old.memory_bytes
            self.evictions += 1
        return stack

    def __contains__(self, index: int) -> bool:
        return index in self._stacks

    def __len__(self) -> int:
        return len(self._stacks)

    def stats(self) -> dict:
        return {"stacks": len(self._stacks), "bytes": self.bytes, "budget_bytes": self.budget_bytes,
                "hits": self.hits, "misses": self.misses, "evictions": self.evictions,
                "build_ms": round(self.build_ms, 3)}
