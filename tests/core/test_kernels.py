import pytest

from carto_cli.core import kernels
from carto_cli.core.timing import StageTimer


@pytest.fixture
def empty_registry(monkeypatch):
    """No warm-up registered or run: each test registers its own toys."""
    monkeypatch.setattr(kernels, "_registered", [])
    monkeypatch.setattr(kernels, "_done", set())
    monkeypatch.setattr(kernels, "_compiled", [])


def test_each_registered_warm_up_runs_once_inside_the_stage(empty_registry):
    calls = []

    @kernels.register_warm_up
    def toy():
        calls.append("toy")

    kernels.register_warm_up(toy)  # registering twice is harmless
    assert kernels.pending()
    timer = StageTimer()
    kernels.warm_up(timer)
    kernels.warm_up(timer)
    assert calls == ["toy"] and not kernels.pending()
    assert timer.snapshot().find(kernels.STAGE) is not None


def test_nothing_pending_opens_no_stage(empty_registry):
    timer = StageTimer()
    kernels.warm_up(timer)
    assert timer.snapshot().find(kernels.STAGE) is None


def test_a_systems_warm_up_runs_only_for_that_system(empty_registry):
    calls = []

    @kernels.register_warm_up
    def shared():
        calls.append("shared")

    @kernels.register_warm_up(system="gmapping")
    def particles():
        calls.append("gmapping")

    kernels.warm_up(systems=("cartographer",))
    assert calls == ["shared"] and not kernels.pending(("cartographer",)) and kernels.pending(("gmapping",))
    kernels.warm_up(systems=("gmapping",))
    assert calls == ["shared", "gmapping"] and not kernels.pending()


def test_a_warm_up_is_claimed_by_one_process_only(tmp_path):
    """On a cold cache this process and its helpers take warm-ups by an exclusive file create: one each."""
    assert kernels.claim(str(tmp_path), "carto_cli.mapping.local_slam:warm_up")
    assert not kernels.claim(str(tmp_path), "carto_cli.mapping.local_slam:warm_up")
    assert kernels.claim(str(tmp_path), "carto_cli.matching.branch_and_bound:warm_up")


def test_a_warm_cache_starts_no_helper(monkeypatch):
    monkeypatch.setattr(kernels, "_cold", lambda fn: False)
    assert not kernels.cold_cache([lambda: None, lambda: None])
    monkeypatch.setattr(kernels, "_cold", lambda fn: True)
    monkeypatch.setenv(kernels.HELPER_ENV, "1")  # a helper never starts helpers of its own
    assert not kernels.cold_cache([lambda: None, lambda: None])


def test_a_warm_up_that_finds_its_kernels_uncached_counts_as_compiling(empty_registry, monkeypatch):
    """What the summary line's compile note asks: a warm-up of this process met a module whose kernels were not
    in the cache yet; one that loaded them all from it is no compiling however long it took."""
    cold = {"warm": False, "fresh": True}

    @kernels.register_warm_up
    def warm():
        pass

    @kernels.register_warm_up(system="gmapping")
    def fresh():
        pass

    monkeypatch.setattr(kernels, "_cold", lambda fn: cold[fn.__name__])
    monkeypatch.setattr(kernels, "cold_cache", lambda wanted: False)  # no helper processes for toys
    kernels.warm_up(systems=("cartographer",))
    assert not kernels.compiled_here()
    kernels.warm_up(systems=("gmapping",))
    assert kernels.compiled_here()


def test_compile_time_counts_compiling_not_calling():
    """What relocalize's compile note reads: the seconds numba spent compiling inside the block, none for a kernel
    it has already compiled."""
    import numba
    import numpy as np

    @numba.njit(cache=False)
    def toy(x):
        return np.sum(x * 2.0)

    with kernels.compile_time() as compiling:
        toy(np.ones(3))
    assert compiling() > 0.0
    with kernels.compile_time() as again:
        toy(np.ones(4))
    assert again() == 0.0


def test_an_interrupted_warm_up_leaves_no_helper_compiling(empty_registry, monkeypatch):
    """Ctrl-C while the kernels compile on a cold cache: the helper processes (not forks of this one, so they do
    not die with it) are stopped, not left compiling after carto has gone (issue 42, item 2)."""
    import subprocess
    import sys

    helpers = []

    def start(wanted, claims):
        helpers.append(subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"]))
        return helpers

    @kernels.register_warm_up
    def first():
        raise KeyboardInterrupt

    @kernels.register_warm_up
    def second():
        pass

    monkeypatch.setattr(kernels, "cold_cache", lambda wanted: True)
    monkeypatch.setattr(kernels, "_start_helpers", start)
    with pytest.raises(KeyboardInterrupt):
        kernels.warm_up()
    assert helpers and all(h.poll() is not None for h in helpers)


def test_a_first_run_says_it_is_compiling_before_it_does(monkeypatch):
    """Issue 42, item 6: a first run compiled for up to a minute without a word, which a CI log cannot tell from a
    hang; the command line now hears one sentence before (and nothing when the kernels are cached, or with -q)."""
    heard, ran = [], []

    def warm():
        ran.append(len(heard))

    monkeypatch.setattr(kernels, "_registered", [(warm, None)])
    monkeypatch.setattr(kernels, "_done", set())
    monkeypatch.setattr(kernels, "_compiled", [])
    monkeypatch.setattr(kernels, "cold_cache", lambda wanted: False)  # no helper processes here
    kernels.on_compiling(heard.append)
    try:
        monkeypatch.setattr(kernels, "_cold", lambda fn: False)
        kernels.warm_up()
        assert ran == [0] and heard == []
        monkeypatch.setattr(kernels, "_done", set())
        monkeypatch.setattr(kernels, "_cold", lambda fn: True)
        kernels.warm_up()
        assert ran == [0, 1] and "compiling kernels (1 of 1 groups)" in heard[0]
        kernels.on_compiling(None)
        monkeypatch.setattr(kernels, "_done", set())
        kernels.warm_up()
        assert len(heard) == 1
    finally:
        kernels.on_compiling(None)
