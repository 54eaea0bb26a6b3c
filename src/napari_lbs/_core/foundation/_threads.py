"""How many threads this process's numerical work uses.

One count sizes torch's intra-op pool, the BLAS and OpenMP libraries, scipy.fft's workers and
this package's thread pools: the cores the process may run on (``os.sched_getaffinity``: what
``taskset``, a container or a batch system's CPU set allow, not the machine's core count), or
the ``NAPARI_LBS_THREADS`` environment variable when set. The console script sizes them at
start-up; the long functions (back-propagation, calibration, training, prediction) on first
use; `size_threads` re-sizes them from Python.

Two jobs started side by side each see every core the machine gives them, so together they
run twice as many threads as there are cores. OpenMP's waiting threads sleep after a short
spin (``OMP_WAIT_POLICY=PASSIVE`` and ``GOMP_SPINCOUNT=1000`` unless either is set), which
keeps that from being far slower than sharing the cores, but each job still does best with its
own share, by cores (``taskset -c 0 napari-lbs ... & taskset -c 1 napari-lbs ...``) or by count
(``NAPARI_LBS_THREADS=1``).
"""

from __future__ import annotations

import os
import sys
from concurrent.futures import ThreadPoolExecutor

from napari_lbs._core.foundation._errors import InputError

__all__ = ["THREADS_ENV", "available_threads", "process_threads", "size_threads", "thread_pool"]

THREADS_ENV = "NAPARI_LBS_THREADS"
# Read by OpenMP (torch), OpenBLAS and MKL when they load: libraries loaded after the sizing,
# and child processes, start with the count.
_LIBRARY_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# GNU OpenMP's busy-wait iterations before a waiting thread sleeps (about 100 000 a millisecond)
_SPIN_COUNT = "1000"
_count: int | None = None
_pools: dict[tuple[str, int], tuple[int, ThreadPoolExecutor]] = {}


def available_threads() -> int:
    """``NAPARI_LBS_THREADS`` if set, else the number of cores this process may run on."""
    text = os.environ.get(THREADS_ENV, "").strip()
    if text:
        if not text.isdigit() or int(text) < 1:
            raise InputError(f"{THREADS_ENV}: expected a positive integer (threads), got {text!r}")
        return int(text)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def size_threads(threads: int | None = None) -> int:
    """Size torch, BLAS, OpenMP, scipy.fft and this package's pools to ``threads`` threads.

    Parameters
    ----------
    threads : int, optional
        Default: `available_threads`.

    Returns
    -------
    int
        The count now in use.
    """
    global _count
    count = available_threads() if threads is None else int(threads)
    if count < 1:
        raise InputError(f"threads: expected a positive integer, got {threads!r}")
    _count = count
    for name in _LIBRARY_ENV:
        os.environ[name] = str(count)
    # OpenMP threads waiting for work spin by default (about 3 ms), taking the cores from the
    # threads doing it whenever anything else runs on them (another job, a viewer): beside other
    # work a training step ran 9x slower spinning than sleeping. Sleeping at once costs a wake-up
    # per parallel region instead: a short spin first (about 10 µs) keeps the many small
    # regions of a fit awake (docs/benchmarks.md: threads).
    if "OMP_WAIT_POLICY" not in os.environ:
        os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        os.environ.setdefault("GOMP_SPINCOUNT", _SPIN_COUNT)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(count)
    if "numpy" in sys.modules:  # a BLAS already loaded has read its environment
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=count, user_api="blas")
    return count


def process_threads() -> int:
    """The count in use (scipy.fft's ``workers``); the first call sizes everything (`size_threads`)."""
    return _count if _count is not None else size_threads()


def thread_pool(name: str) -> ThreadPoolExecutor:
    """This process's pool of `process_threads` threads for one use.

    One pool per ``name``, so that a task of one pool may wait on another's without
    deadlocking; a new one after a fork (a pool's threads do not survive it) or a re-sizing.
    """
    count, key = process_threads(), (name, os.getpid())
    size, pool = _pools.get(key, (0, None))
    if pool is None or size != count:
        if pool is not None:
            pool.shutdown(wait=False)
        pool = ThreadPoolExecutor(max_workers=count, thread_name_prefix=f"napari-lbs-{name}")
        _pools[key] = (count, pool)
    return pool
