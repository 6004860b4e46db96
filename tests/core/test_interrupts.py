"""core.interrupts: a stop signal is remembered, so the error it turns into still reads as an interrupt."""
import signal

import pytest

from carto_cli.core import interrupts


@pytest.fixture
def handler():
    """install()'s handler on SIGINT for one test (pytest's own put back after)."""
    before = signal.getsignal(signal.SIGINT)
    interrupts.clear()
    signal.signal(signal.SIGINT, interrupts.interrupt)
    yield
    signal.signal(signal.SIGINT, before)
    interrupts.clear()


def _wrapped(error: BaseException, cause: BaseException) -> BaseException:
    try:
        try:
            raise cause
        except BaseException as inner:
            raise error from inner
    except BaseException as outer:
        return outer


def test_an_error_caused_by_a_keyboard_interrupt_is_an_interrupt():
    interrupts.clear()
    # As numba reports a KeyboardInterrupt raised in Python code its compiled code called.
    numba_like = _wrapped(SystemError("CPUDispatcher(<function _climb>) returned a result with an exception set"),
                          KeyboardInterrupt())
    assert interrupts.is_interrupt(numba_like)
    assert interrupts.is_interrupt(_wrapped(RuntimeError("outer"), numba_like))
    assert interrupts.is_interrupt(KeyboardInterrupt())
    assert not interrupts.is_interrupt(_wrapped(SystemError("x"), ValueError("y")))
    assert not interrupts.is_interrupt(RuntimeError("boom"))


def test_after_a_signal_every_error_is_an_interrupt(handler):
    with pytest.raises(KeyboardInterrupt):
        signal.raise_signal(signal.SIGINT)  # to this thread, the main one: handled before the call returns
    assert interrupts.requested()
    assert interrupts.is_interrupt(RuntimeError("the pose graph's process ended unexpectedly"))
    interrupts.clear()
    assert not interrupts.is_interrupt(RuntimeError("boom"))


def test_a_signal_inside_a_deferred_block_raises_at_its_end(handler):
    done = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts.deferred():
            signal.raise_signal(signal.SIGINT)
            done.append("first")
            done.append("second")  # what the block must not be cut between (two outputs moved into place)
    assert done == ["first", "second"] and interrupts.requested()


def test_a_signal_while_a_deferred_block_fails_makes_its_error_an_interrupt(handler):
    with pytest.raises(OSError) as failed:
        with interrupts.deferred():
            signal.raise_signal(signal.SIGINT)
            raise OSError("disk full")
    assert interrupts.is_interrupt(failed.value)


def test_once_held_a_signal_changes_nothing(handler):
    interrupts.hold()
    signal.raise_signal(signal.SIGINT)  # leaving: nothing may cut the report short
    assert not interrupts.requested()


def test_install_keeps_an_ignored_signal_ignored():
    before = {sig: signal.getsignal(sig) for sig in interrupts.STOP_SIGNALS}
    try:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a background job of a shell without job control
        interrupts.install()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) == interrupts.interrupt
    finally:
        for sig, h in before.items():
            signal.signal(sig, h)
