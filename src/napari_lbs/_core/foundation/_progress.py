"""The one pattern for long work: ``progress(done, total)`` and ``should_stop()`` callbacks.

Every long-running `_core` function takes two keyword-only callables, both optional:

- ``progress(done, total)`` is called after each step (a z chunk, a GA generation, a batch);
- ``should_stop()`` is polled between steps; when it returns True the function stops at the
  next step boundary. Functions whose partial result is meaningful (calibration, data
  generation, training) return it marked as stopped; the others (back-propagation,
  prediction, diagnosis) raise `Stopped` and leave nothing half-written.

Training and calibration also take ``report(record)``, called with a dict after each batch
and epoch (training) or GA generation (calibration), for live plots.

A job made of several long functions in a row (a refined prediction: the network, the fit,
the second look) passes the same ``progress`` to each, whose counts start again; it names
each phase as it begins with `begin_phase`, so that a ``progress`` with a ``phase(name)``
method (napari's steps) shows one bar over the whole job. Other callbacks hear nothing of it.
"""

from __future__ import annotations

import time
from collections.abc import Callable

__all__ = ["ProgressCallback", "StopCallback", "ReportCallback", "Stopped", "Steps", "begin_phase"]

ProgressCallback = Callable[[int, int], None]
StopCallback = Callable[[], bool]
ReportCallback = Callable[[dict], None]


class Stopped(RuntimeError):
    """Raised by a long function whose caller asked it to stop and that has no partial result."""


class Steps:
    """Counts the steps of one long job and relays them to the callbacks.

    Parameters
    ----------
    total : int
        Number of steps the job will report.
    progress, should_stop : callable or None
        The caller's callbacks (see the module docstring).
    heartbeat_s : float, optional
        For steps longer than this: `check` also reports the count again once this many
        seconds have passed since the last report, so a caller hears from a long step as
        often as the work checks, but not more than once per ``heartbeat_s``.
    """

    def __init__(self, total: int, *, progress: ProgressCallback | None, should_stop: StopCallback | None, heartbeat_s: float | None = None) -> None:
        self.total = int(total)
        self.done = 0
        self._progress = progress
        self._should_stop = should_stop
        self._heartbeat_s = heartbeat_s
        self._reported = time.monotonic()

    def stop_requested(self) -> bool:
        """True once the caller asked to stop."""
        return bool(self._should_stop is not None and self._should_stop())

    def check(self) -> None:
        """Raise `Stopped` if the caller asked to stop (and report the count again when a heartbeat is due)."""
        if self.stop_requested():
            raise Stopped(f"stopped after {self.done} of {self.total} steps")
        if self._heartbeat_s is not None and time.monotonic() - self._reported >= self._heartbeat_s:
            self.advance(0)

    def advance(self, count: int = 1) -> None:
        """Record ``count`` finished steps and report them."""
        self.done += count
        self._reported = time.monotonic()
        if self._progress is not None:
            self._progress(self.done, self.total)


def begin_phase(progress: ProgressCallback | None, name: str) -> None:
    """Tell ``progress`` that the job's next phase, ``name`` (e.g. "fit 103 particles"), begins, where it has a ``phase(name)`` method."""
    phase = getattr(progress, "phase", None)
    if callable(phase):
        phase(name)
