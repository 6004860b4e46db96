"""Ctrl-C and SIGTERM as one request to stop, remembered, so that whatever error it turns into still reads as it.

Python runs a signal's handler in the main thread, between two bytecodes, wherever they are. Numba's compiled
code calls back into Python now and then (its helpers unpickle constants there): a KeyboardInterrupt raised in
such a call comes out of the compiled function as a ``SystemError`` ("returned a result with an exception set").
One raised while a reader decodes becomes that reader's "corrupt file" error; a clean-up on its way out may fail
and raise in its place; a child process that got the signal too ends, and the caller sees it gone. So the
handler records the request before it raises, and whoever reports errors (the command line) asks
``is_interrupt`` and reports any error that follows the request as the interrupt.

``install`` is for a process's entry point (the command line); a library caller keeps its own handlers, and
its KeyboardInterrupt is still recognised in an error's chain.
"""
from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager

_state = {
    "requested": False,  # a handler raised KeyboardInterrupt since the last clear()
    "held": False,  # the command has ended: a signal changes nothing, so that leaving is never cut short
    "deferring": 0,  # inside deferred(): a signal waits for the block's end
    "pending": False,  # a signal came while deferring
}

STOP_SIGNALS = tuple(getattr(signal, name) for name in ("SIGINT", "SIGTERM") if hasattr(signal, name))


def clear() -> None:
    """Forget earlier requests (a command starting in a process that ran another, as tests and tune do)."""
    _state.update(requested=False, held=False, deferring=0, pending=False)


def requested() -> bool:
    """Whether a stop signal raised KeyboardInterrupt since the last ``clear``."""
    return bool(_state["requested"])


def is_interrupt(error: BaseException) -> bool:
    """Whether ``error`` is a stop signal's doing: a KeyboardInterrupt in its chain of causes, or any error at
    all once a stop was requested (an error after it is an echo of it, not a fault of its own)."""
    if _state["requested"]:
        return True
    seen: set[int] = set()
    e: BaseException | None = error
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def record() -> None:
    """Note a stop request that the caller itself turns into KeyboardInterrupt (tune's second Ctrl-C)."""
    _state["requested"] = True


def interrupt(signum: int | None = None, frame: object = None) -> None:
    """The handler: record the request, then raise KeyboardInterrupt, unless the command has ended (``hold``) or
    is inside ``deferred``."""
    if _state["held"]:
        return
    if _state["deferring"]:
        _state["pending"] = True
        return
    _state["requested"] = True
    raise KeyboardInterrupt


def install() -> None:
    """Ctrl-C and SIGTERM (a CI job cancelled, ``timeout``, ``docker stop``) both stop the process through
    ``interrupt``. A signal its parent had set to be ignored stays ignored: a shell without job control starts
    background jobs with SIGINT ignored, and Python itself keeps it so."""
    for sig in STOP_SIGNALS:
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, interrupt)


def hold() -> None:
    """From now on a stop signal changes nothing: the command is over (its outputs written or abandoned) and the
    process only reports and leaves; an interrupt there would cut the report short or end in a traceback."""
    _state["held"] = True


@contextmanager
def deferred() -> Iterator[None]:
    """A block a stop signal may not cut in two (moving a set of outputs into place): a signal that comes inside
    it raises at its end. Only with ``install``'s handler; under Python's default one a Ctrl-C raises at once."""
    _state["deferring"] += 1
    try:
        yield
    except BaseException:
        _end_deferring()  # the block's own error goes on; a signal that came meanwhile makes it an interrupt
        raise
    if _end_deferring() and not _state["held"]:
        raise KeyboardInterrupt


def _end_deferring() -> bool:
    """Leave one ``deferred`` block; whether a signal came while deferring (now recorded as requested)."""
    _state["deferring"] -= 1
    if _state["deferring"] or not _state["pending"]:
        return False
    _state["pending"] = False
    _state["requested"] = True
    return True
