"""The precomputation-stack LRU: kept under its byte budget, least recently used out first."""
import threading

import numpy as np
import pytest

from carto_cli.grid.probability_grid import ProbabilityGrid
from carto_cli.matching.stack_cache import StackCache


def _grid(n: int, seed: int) -> ProbabilityGrid:
    grid = ProbabilityGrid(0.05, (0.0, 0.0), (n, n))
    cells = np.random.default_rng(seed).integers(0, n, size=(50, 2))
    grid.set_probability(cells, 0.8)
    return grid


@pytest.fixture(scope="module")
def grids():
    return [_grid(n, k) for k, n in enumerate((60, 80, 70, 90))]


def test_stack_cache_is_lru_under_its_budget(grids):
    size = [StackCache(1 << 40, 7).get(i, g).memory_bytes for i, g in enumerate(grids[:3])]
    cache = StackCache(size[0] + max(size[1], size[2]), 7)
    cache.get(0, grids[0])
    cache.get(1, grids[1])
    assert cache.get(0, grids[0]) is cache.get(0, grids[0])  # hits
    cache.get(2, grids[2])  # evicts 1, the least recently used
    assert 0 in cache and 2 in cache and 1 not in cache
    assert cache.evictions == 1 and cache.bytes <= cache.budget_bytes
    tiny = StackCache(1, 7)
    tiny.get(0, grids[0])
    tiny.get(1, grids[1])
    assert len(tiny) == 1 and 1 in tiny  # the one in use is always kept


def test_stack_cache_counts_hits_misses_and_build_time(grids):
    grid = grids[0]
    cache = StackCache(1 << 40, 7)
    first = cache.get(5, grid)
    assert cache.get(5, grid) is first
    stats = cache.stats()
    assert stats["misses"] == 1 and stats["hits"] == 1 and stats["stacks"] == 1 and stats["evictions"] == 0
    assert stats["bytes"] == first.memory_bytes and stats["build_ms"] > 0
    assert first.depth == 7 and 5 in cache and 4 not in cache


def test_stack_cache_shared_by_threads_stays_within_its_budget_and_counts_every_call(grids):
    one = StackCache(1 << 40, 7).get(0, grids[1]).memory_bytes
    cache = StackCache(2 * one + 1, 7)
    order = [k % 4 for k in range(200)]

    def work(offset):
        for k in order[offset::4]:
            stack = cache.get(k, grids[k])
            assert stack.depth == 7

    threads = [threading.Thread(target=work, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert cache.hits + cache.misses == len(order)
    assert cache.bytes <= cache.budget_bytes and 1 <= len(cache) <= 2
    assert cache.peak_bytes >= cache.bytes


def test_clear_drops_every_stack_and_keeps_the_statistics(grids):
    cache = StackCache(1 << 40, 7)
    first = cache.get(0, grids[0])
    cache.get(1, grids[1])
    peak = cache.peak_bytes
    cache.clear()
    assert len(cache) == 0 and cache.bytes == 0 and 0 not in cache
    assert cache.misses == 2 and cache.peak_bytes == peak
    again = cache.get(0, grids[0])  # rebuilt, the same
    assert again is not first and again.memory_bytes == first.memory_bytes
