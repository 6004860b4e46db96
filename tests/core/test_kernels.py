from carto_cli.core import kernels
from carto_cli.core.timing import StageTimer


def test_each_registered_warm_up_runs_once_inside_the_stage(monkeypatch):
    monkeypatch.setattr(kernels, "_registered", [])
    monkeypatch.setattr(kernels, "_done", set())
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


def test_nothing_pending_opens_no_stage(monkeypatch):
    monkeypatch.setattr(kernels, "_registered", [])
    monkeypatch.setattr(kernels, "_done", set())
    timer = StageTimer()
    kernels.warm_up(timer)
    assert timer.snapshot().find(kernels.STAGE) is None


def test_a_systems_warm_up_runs_only_for_that_system(monkeypatch):
    monkeypatch.setattr(kernels, "_registered", [])
    monkeypatch.setattr(kernels, "_done", set())
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
