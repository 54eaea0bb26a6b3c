"""Worker processes: tasks run in a pool of one-thread processes, with progress and stop, results in task order.

The one scheme for process pools (synthetic data generation, refinement's batches;
recordings use dask). `run_in_workers` runs one list of tasks;
`WorkerPool` keeps its processes for several lists (refinement's rounds), so they start once.

- **Workers**: at most `available_threads` (the cores this process may use) and at most one
  per task; each is sized to one thread (`size_threads`), so together they use the cores once.
  They are spawned, not forked: a forked child inherits torch's, the BLAS's and the FFT's
  thread pools (and, under napari, Qt's threads) mid-use and can hang. A script that uses
  more than one worker therefore needs an ``if __name__ == "__main__":`` guard.
- **One worker** (or a single task before any process started): the tasks run in this
  process, through the same function, so the serial and the pooled results are the same code's.
- **Progress and stop**: one step per finished task (in the order they finish); the stop is
  checked at least every `CHECK_S` seconds. A stop ends every worker at once: a running task
  is unwound (its ``finally`` blocks remove what it half wrote) and its process ended within
  `END_S` seconds, so no process is left and no partial result returned; `Stopped` is raised.
- **Failures**: a worker's exception is raised again here, with its message (and the worker's
  traceback as its cause); the other workers are ended as for a stop.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os
import signal
import time
from collections.abc import Callable, Iterable
from concurrent.futures.process import BrokenProcessPool
from typing import Self

from napari_lbs._core.foundation._interrupts import _RETRY_S, _inside_import
from napari_lbs._core.foundation._progress import Steps
from napari_lbs._core.foundation._threads import available_threads, size_threads

__all__ = ["CHECK_S", "END_S", "WorkerPool", "run_in_workers"]

# How often (s) the stop is checked, and progress repeated (`Steps`' heartbeat), while workers run.
CHECK_S = 0.5
# How long (s) an ended worker may take to unwind its task before it is killed.
END_S = 1.0


class WorkerPool:
    """Processes that run tasks; the processes start with the first list of tasks that needs them.

    Parameters
    ----------
    workers : int
        Processes wanted; capped at `available_threads` (and, when they start, at the number
        of tasks). 1: every task runs in this process.

    Use as a context manager (or call `close`): the processes are ended on the way out.
    """

    def __init__(self, workers: int) -> None:
        self.workers = max(1, min(int(workers), available_threads()))
        self._executor: concurrent.futures.ProcessPoolExecutor | None = None

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def run(self, function: Callable, tasks: Iterable, *, steps: Steps, share_steps: bool = False) -> list:
        """``[function(task) for task in tasks]``, in task order, one ``steps`` step per task.

        Parameters
        ----------
        function : callable
            A module-level function (workers receive it by name), called with one task.
        tasks : iterable
            Picklable tasks.
        steps : Steps
            Advanced once per finished task; its stop is checked before each task in this
            process, and at least every `CHECK_S` seconds while workers run.
        share_steps : bool
            In this process, call ``function(task, steps)`` so that a long task can check for a
            stop and report a heartbeat itself (workers cannot reach the caller's callbacks).

        Returns
        -------
        list
            The results, in task order.

        Raises
        ------
        Stopped
            The caller asked to stop; every worker has been ended.
        """
        tasks = list(tasks)
        if self.workers == 1 or (len(tasks) <= 1 and self._executor is None):
            results = []
            for task in tasks:
                steps.check()
                results.append(function(task, steps) if share_steps else function(task))
                steps.advance()
            return results
        if self._executor is None:
            count, spawn = min(self.workers, len(tasks)), multiprocessing.get_context("spawn")
            self._executor = concurrent.futures.ProcessPoolExecutor(max_workers=count, mp_context=spawn, initializer=_start_worker)
        results = [None] * len(tasks)
        try:
            order = {self._executor.submit(_run_task, function, task): index for index, task in enumerate(tasks)}
            pending = set(order)
            while pending:
                steps.check()
                done, pending = concurrent.futures.wait(pending, timeout=CHECK_S, return_when=concurrent.futures.FIRST_COMPLETED)
                for future in done:
                    results[order[future]] = future.result()  # a worker's exception is raised here
                    steps.advance()
        except BrokenProcessPool as error:
            self._end()
            why = 'killed, out of memory, or a script without an `if __name__ == "__main__":` guard'
            raise BrokenProcessPool(f"a worker process ended abruptly ({why}): {error}") from error
        except BaseException:
            self._end()
            raise
        return results

    def close(self) -> None:
        """Let the (idle) processes exit; after a stop or a failure they are already ended."""
        executor, self._executor = self._executor, None
        if executor is not None:
            executor.shutdown(wait=True)

    def _end(self) -> None:
        """End every worker now: cancel what has not started, unwind what runs (SIGTERM), kill what is left after `END_S`."""
        executor, self._executor = self._executor, None
        if executor is None:
            return
        processes = list((getattr(executor, "_processes", None) or {}).values())
        executor.shutdown(wait=False, cancel_futures=True)
        for process in processes:
            process.terminate()
        deadline = time.monotonic() + END_S
        for process in processes:
            process.join(max(0.0, deadline - time.monotonic()))
        for process in processes:
            if process.is_alive():
                process.kill()
                process.join()
        executor.shutdown(wait=True)  # the executor's own threads, now that no worker is left


def run_in_workers(function: Callable, tasks: Iterable, *, workers: int, steps: Steps, share_steps: bool = False) -> list:
    """``[function(task) for task in tasks]`` in task order, on up to ``workers`` processes (`WorkerPool.run`)."""
    with WorkerPool(workers) as pool:
        return pool.run(function, tasks, steps=steps, share_steps=share_steps)


class _Ended(BaseException):
    """Raised in a worker's task when the pool ends it (a BaseException, so that a task's ``except Exception`` lets it pass)."""


_in_task = False


def _start_worker() -> None:
    # one thread per worker: the processes share the cores between them
    size_threads(1)
    # Ctrl-C reaches the whole process group: the parent decides, and ends the workers itself
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, _on_terminate)


def _on_terminate(signum, frame) -> None:
    if not _in_task:
        os._exit(1)
    # an exception crossing an extension's initialisation aborts the process instead of unwinding
    # it, and a task's first file write imports its encoding: asked again once the import is done
    # (`END_S` still bounds the wait), so that the task unwinds and removes what it half wrote
    if _inside_import(frame) and hasattr(signal, "setitimer"):
        signal.signal(signal.SIGALRM, _on_terminate)
        signal.setitimer(signal.ITIMER_REAL, _RETRY_S)
        return
    raise _Ended


def _run_task(function: Callable, task):
    """A worker's call of ``function(task)``; ended (SIGTERM), it unwinds the task and exits."""
    global _in_task
    _in_task = True
    try:
        return function(task)
    except _Ended:
        os._exit(1)
    finally:
        _in_task = False
