"""SIGTERM and Ctrl-C as `KeyboardInterrupt`, raised where unwinding is safe.

A command interrupted by either unwinds like Ctrl-C, so every temporary file is removed on
the way out. An exception raised in a module's top level can cross an extension's
initialisation (torch's pybind11 modules), which aborts the whole process instead of
unwinding it: a signal that lands inside an import is looked at again every 50 ms (SIGALRM)
until the import is over.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator

__all__ = ["interruptible"]

_RETRY_S = 0.05


def _inside_import(frame) -> bool:
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _interrupt(signum, frame) -> None:
    if _inside_import(frame) and hasattr(signal, "setitimer"):
        signal.signal(signal.SIGALRM, _interrupt)
        signal.setitimer(signal.ITIMER_REAL, _RETRY_S)
        return
    raise KeyboardInterrupt


@contextlib.contextmanager
def interruptible() -> Iterator[None]:
    """Within the block, SIGTERM and SIGINT raise `KeyboardInterrupt` (outside any import); the handlers are restored after.

    Only the main thread can install signal handlers; elsewhere the block runs unchanged.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {number: signal.signal(number, _interrupt) for number in (signal.SIGTERM, signal.SIGINT)}
    try:
        yield
    finally:
        if hasattr(signal, "setitimer"):
            signal.setitimer(signal.ITIMER_REAL, 0.0)
        for number, handler in previous.items():
            signal.signal(number, handler)
