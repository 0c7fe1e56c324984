"""Run independent numeric tasks on the machine's cores (forked worker processes).

The gap diagnosis fits a hundred or so candidate models that do not depend on each other
(issue 10: <= 60 s per data set on a 2-core machine). Their candidates hold closures, which
cannot be pickled, so the workers are *forked*: they inherit the task function and its
data, and only the task index goes in and the (small, picklable) result comes back.

Results are returned in task order and are bit-identical to a serial run (same code, same
single-threaded BLAS in every process). The map runs serially when

* ``jobs`` is 1 or there is only one task,
* the platform cannot fork (Windows, macOS' default),
* the calling process already runs other Python threads (the GUI runs the diagnosis in a
  worker thread; forking a multi-threaded process can deadlock the child), or
* the caller is itself a daemonic worker (which may not have children).
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from collections.abc import Callable, Sequence
from typing import Any

# set in the parent just before the workers are forked; the children read it
_FORKED_TASK: tuple[Callable[[Any], Any], Sequence[Any]] | None = None


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS reports one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # no affinity API (macOS, Windows)
        return max(1, os.cpu_count() or 1)


def resolve_jobs(jobs: int) -> int:
    """``jobs`` as a worker count: 0 means every available core."""
    if jobs < 0:
        raise ValueError(f"jobs must be >= 0 (0 = every core), got {jobs}")
    return available_cores() if jobs == 0 else jobs


def can_fork_workers() -> bool:
    """Whether forking workers from this process is safe (see the module docstring)."""
    return ("fork" in multiprocessing.get_all_start_methods()
            and threading.active_count() == 1
            and not multiprocessing.current_process().daemon)


def _run_forked(index: int) -> Any:
    assert _FORKED_TASK is not None, "worker started without a task"
    fn, items = _FORKED_TASK
    return fn(items[index])


def parallel_map(fn: Callable[[Any], Any], items: Sequence[Any], jobs: int) -> list[Any]:
    """``[fn(item) for item in items]``, spread over up to ``jobs`` forked processes.

    ``fn`` and ``items`` need not be picklable (the workers inherit them); each result
    must be. Tasks go to whichever worker is free (one at a time: their costs differ by
    10x). An exception in a task is raised here, as in the serial loop.
    """
    global _FORKED_TASK
    n_workers = min(resolve_jobs(jobs), len(items))
    if n_workers <= 1 or not can_fork_workers():
        return [fn(item) for item in items]
    _FORKED_TASK = (fn, items)
    try:
        with multiprocessing.get_context("fork").Pool(n_workers) as pool:
            return pool.map(_run_forked, range(len(items)), chunksize=1)
    finally:
        _FORKED_TASK = None
