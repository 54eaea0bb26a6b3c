"""SIGTERM and Ctrl-C as `KeyboardInterrupt`, raised where unwinding is safe.

A command interrupted by either unwinds like Ctrl-C, so every temporary file is removed on
the way out. An exception raised in a module's top level can cross an extension's
initialisation (torch's pybind11 modules), which aborts the whole process instead of
unwinding it: a signal that lands inside an import is looked at again every 50 ms (SIGALRM)
until the import is over.

CPython runs signal handlers in the main thread, between bytecodes. A signal the kernel hands
to another thread while the main thread waits on a lock is handled only when that wait ends
(dask waits 10 s at a time while a cluster starts): `run_interruptibly` waits in short slices.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Callable, Iterator
from typing import TypeVar

T = TypeVar("T")

__all__ = ["deferred_interrupts", "interruptible", "run_interruptibly"]

_RETRY_S = 0.05
# per thread: how deep in `deferred_interrupts` blocks, and whether an interrupt waits for their end
# (the handler runs in the main thread, so it reads the main thread's)
_deferral = threading.local()


def _inside_import(frame) -> bool:
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _interrupt(signum, frame) -> None:
    if getattr(_deferral, "depth", 0):
        _deferral.pending = True
        return
    if _inside_import(frame) and hasattr(signal, "setitimer"):
        signal.signal(signal.SIGALRM, _interrupt)
        signal.setitimer(signal.ITIMER_REAL, _RETRY_S)
        return
    raise KeyboardInterrupt


@contextlib.contextmanager
def deferred_interrupts() -> Iterator[None]:
    """Within the block an interrupt (SIGTERM or Ctrl-C, under `interruptible`) waits, and is raised where the block ends.

    For the few steps that must not be cut in two: a temporary file created and its name
    kept, or removed (`atomic_path`); an interrupt between the two would leave the file behind.
    """
    _deferral.depth = getattr(_deferral, "depth", 0) + 1
    try:
        yield
    finally:
        _deferral.depth -= 1
        if not _deferral.depth and getattr(_deferral, "pending", False):
            _deferral.pending = False
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


def run_interruptibly(work: Callable[[], T], *, abandoned: Callable[[T], None]) -> T:
    """``work()``, run in a helper thread while the main thread waits for it in slices of 50 ms, so that Ctrl-C and SIGTERM are heard at once.

    Interrupted, the caller unwinds immediately; ``work`` goes on in its thread and what it
    makes is handed to ``abandoned`` (to close it) once it is done; its error, if any, is
    dropped. Outside the main thread ``work`` runs in place (no handler runs there).
    """
    if threading.current_thread() is not threading.main_thread():
        return work()
    outcome: dict = {}
    lock = threading.Lock()

    def run() -> None:
        try:
            value = work()
        except BaseException as error:  # noqa: BLE001 - handed to the waiting caller
            with lock:
                outcome["error"] = error
            return
        with lock:
            outcome["value"] = value
            late = outcome.get("abandoned", False)
        if late:
            abandoned(value)

    helper = threading.Thread(target=run, name="napari-lbs-interruptible", daemon=True)
    helper.start()
    try:
        while helper.is_alive():
            helper.join(_RETRY_S)
    except BaseException:
        with lock:
            outcome["abandoned"] = True
            made = "value" in outcome
        if made:
            abandoned(outcome["value"])
        raise
    if "error" in outcome:
        raise outcome["error"]
    return outcome["value"]
