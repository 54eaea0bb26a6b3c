"""The worker pool (`napari_lbs._core.foundation.run_in_workers`): task order, progress, stop, a worker's failure, the worker cap.

The workers are spawned processes, so their tasks are this module's functions; each test
keeps its tasks short (the whole module runs in a few seconds on 2 cores).
"""

import itertools
import multiprocessing
import os
import time
from pathlib import Path

import pytest

from napari_lbs._core.foundation import Steps, Stopped, WorkerPool, run_in_workers


def _slow_square(task):
    """(value, seconds): sleeps, then returns value² and the process that computed it."""
    value, seconds = task
    time.sleep(seconds)
    return value * value, os.getpid()


def _hold_file(task):
    """Writes ``task`` (a path) and holds it until ended: a half-written result that unwinding removes."""
    path = Path(task)
    path.write_text("partial")
    try:
        time.sleep(60.0)
    finally:
        path.unlink()


def _fail_on_three(value):
    if value == 3:
        raise ValueError(f"task {value}: refused (a worker's own message)")
    time.sleep(0.2)
    return value


def _with_steps(task, steps):
    return task, steps.total


def _children() -> list:
    """This process's live child processes, but multiprocessing's resource tracker (one per process, from the first spawn on).

    psutil's view where installed: the operating system's, which also sees what
    multiprocessing lost track of. multiprocessing's own list can hold a worker that has
    exited: when the executor's thread and the pool both wait for it, the one that loses the
    race sees no exit status, and the worker stays listed until it is joined again.
    """
    from multiprocessing import resource_tracker

    tracker = getattr(resource_tracker._resource_tracker, "_pid", None)
    try:
        import psutil
    except ImportError:
        return multiprocessing.active_children()
    alive = []
    for child in psutil.Process().children(recursive=True):
        try:
            if child.pid != tracker and child.status() != psutil.STATUS_ZOMBIE:
                alive.append(child)
        except psutil.NoSuchProcess:
            pass  # exited since it was listed
    return alive


def test_results_come_in_task_order_with_one_step_per_task_however_they_finish():
    calls = []
    # the first task finishes last
    tasks = [(value, 0.6 if value == 0 else 0.05) for value in range(5)]
    steps = Steps(len(tasks), progress=lambda done, total: calls.append((done, total)), should_stop=None)
    results = run_in_workers(_slow_square, tasks, workers=2, steps=steps)
    assert [value for value, _ in results] == [0, 1, 4, 9, 16]
    assert calls == [(done, 5) for done in range(1, 6)]
    assert os.getpid() not in {pid for _, pid in results} and not _children()


def test_one_worker_runs_the_same_function_in_this_process_and_can_share_the_steps():
    steps = Steps(3, progress=None, should_stop=None)
    results = run_in_workers(_slow_square, [(2, 0.0), (3, 0.0), (4, 0.0)], workers=1, steps=steps)
    assert results == [(4, os.getpid()), (9, os.getpid()), (16, os.getpid())] and steps.done == 3
    shared = Steps(2, progress=None, should_stop=None)
    assert run_in_workers(_with_steps, ["a", "b"], workers=1, steps=shared, share_steps=True) == [("a", 2), ("b", 2)]


def test_a_stop_ends_every_worker_within_two_seconds_and_leaves_nothing_half_written(tmp_path):
    asked = []
    started = time.monotonic()

    def stop_after_a_second() -> bool:
        asked.append(time.monotonic())
        return asked[-1] - started > 1.5  # the workers are running their tasks by then

    paths = [str(tmp_path / f"part-{index}") for index in range(2)]
    with pytest.raises(Stopped):
        run_in_workers(_hold_file, paths, workers=2, steps=Steps(2, progress=None, should_stop=stop_after_a_second))
    stopped = next(t for t in asked if t - started > 1.5)
    assert max(b - a for a, b in itertools.pairwise(asked)) < 1.0  # checked at least every second
    assert time.monotonic() - stopped < 2.0 and not _children()
    assert not list(tmp_path.iterdir())  # each task unwound: its finally removed its file


def test_a_workers_exception_is_raised_here_with_its_message_and_the_other_workers_are_ended():
    with pytest.raises(ValueError, match=r"task 3: refused \(a worker's own message\)"):
        run_in_workers(_fail_on_three, range(8), workers=2, steps=Steps(8, progress=None, should_stop=None))
    assert not _children()
    with pytest.raises(ValueError, match="task 3"):  # the same in this process
        run_in_workers(_fail_on_three, [3], workers=1, steps=Steps(1, progress=None, should_stop=None))


def test_workers_are_capped_at_the_available_threads_and_a_pool_serves_several_lists(monkeypatch):
    monkeypatch.setenv("NAPARI_LBS_THREADS", "2")
    assert WorkerPool(16).workers == 2 and WorkerPool(0).workers == 1
    with WorkerPool(16) as pool:
        first = pool.run(_slow_square, [(value, 0.2) for value in range(6)], steps=Steps(6, progress=None, should_stop=None))
        second = pool.run(_slow_square, [(7, 0.0)], steps=Steps(1, progress=None, should_stop=None))  # the started processes, not this one
    assert len({pid for _, pid in first}) <= 2 and second[0][1] in {pid for _, pid in first}
    assert not _children()
