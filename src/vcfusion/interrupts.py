"""Ctrl-C that always stops the command.

Python turns SIGINT into a KeyboardInterrupt raised wherever the interpreter happens to be. When
that is inside numba (a compiled function being loaded from its cache, or LLVM calling back into
Python while compiling one on a cold cache), the interrupt comes out mangled: a SystemError whose
cause is the KeyboardInterrupt, a RuntimeError, or nothing at all ("Exception ignored on calling
ctypes callback function"), and the run would go on to its end. So the SIGINT handler also
records that the signal came: the co-simulation loop checks the record every V2C tick, and the
command-line entry point and the worker pool read any exception that follows it as the interrupt.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Iterator
from contextlib import contextmanager

_received = False
_terminated = False  # the signal was SIGTERM (a scheduler, `timeout`, `kill`): exit 143, not 130

STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM)


def record_and_raise(signum, frame) -> None:
    """SIGINT / SIGTERM handler: Python's own for SIGINT (raise KeyboardInterrupt), which also
    remembers the signal. SIGTERM is handled as Ctrl-C so that the command stops its workers and
    removes its partial outputs: by default it killed the command alone, and the worker pool's
    processes (children of the fork server, not of the command) ran on, writing run folders that
    nobody tracked."""
    global _received, _terminated
    _received = True
    _terminated = _terminated or signum == signal.SIGTERM
    raise KeyboardInterrupt


def terminated() -> bool:
    """Whether the stop that was received came as SIGTERM."""
    return _terminated


@contextmanager
def recorded() -> Iterator[None]:
    """Within: SIGINT is recorded as well as raised (unless SIGINT is ignored, as in a background
    job, or handled by an application embedding vcfusion). Afterwards the handler and the record
    are as before, so that a process calling several commands (a test session) starts each afresh."""
    global _received, _terminated
    previous = signal.getsignal(signal.SIGINT)
    ours = previous is signal.default_int_handler
    if ours:
        signal.signal(signal.SIGINT, record_and_raise)
    previous_term = signal.getsignal(signal.SIGTERM)
    ours_term = previous_term is signal.SIG_DFL
    if ours_term:
        signal.signal(signal.SIGTERM, record_and_raise)
    previous_hook = sys.unraisablehook

    def drop_swallowed_interrupt(unraisable) -> None:
        # ctypes' "Exception ignored on calling ctypes callback function" and its traceback: the
        # interrupt is recorded and acted on, so the user sees "interrupted" and no traceback
        if not (_received and issubclass(unraisable.exc_type, KeyboardInterrupt)):
            previous_hook(unraisable)

    sys.unraisablehook = drop_swallowed_interrupt
    _received = _terminated = False
    try:
        yield
    finally:
        if ours:
            signal.signal(signal.SIGINT, previous)
        if ours_term:
            signal.signal(signal.SIGTERM, previous_term)
        sys.unraisablehook = previous_hook
        _received = _terminated = False


def note_received() -> None:
    """For a handler of one's own (the worker pool's) that raises KeyboardInterrupt itself."""
    global _received
    _received = True


def raise_if_received() -> None:
    """Raise KeyboardInterrupt if SIGINT came but its KeyboardInterrupt was swallowed on the way."""
    if _received:
        raise KeyboardInterrupt


def is_interrupt(exc: BaseException) -> bool:
    """Whether `exc` is Ctrl-C on its way up: a KeyboardInterrupt, an exception with one among its
    causes (numba's SystemError), or any exception raised after SIGINT was received."""
    if _received:
        return True
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, KeyboardInterrupt):
            return True
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return False
