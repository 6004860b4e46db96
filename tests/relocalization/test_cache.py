"""The precomputation-stack LRU: kept under its byte budget, least recently used out first."""
from carto_cli.relocalization import StackCache


def test_stack_cache_is_lru_under_its_budget(mapped):
    grids = [s.grid for s in mapped.submaps[:4]]
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


def test_stack_cache_counts_hits_misses_and_build_time(mapped):
    grid = mapped.submaps[0].grid
    cache = StackCache(1 << 40, 7)
    first = cache.get(5, grid)
    assert cache.get(5, grid) is first
    stats = cache.stats()
    assert stats["misses"] == 1 and stats["hits"] == 1 and stats["stacks"] == 1 and stats["evictions"] == 0
    assert stats["bytes"] == first.memory_bytes and stats["build_ms"] > 0
    assert first.depth == 7 and 5 in cache and 4 not in cache
