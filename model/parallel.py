"""Run independent numeric tasks on the machine's cores (forked worker processes).

The gap diagnosis fits a hundred or so candidate models that do not depend on each other
(issue 10: <= 60 s per data set on a 2-core machine). Their candidates hold closures, which
cannot be pickled, so the workers are *forked*: they inherit the task function and its
data, and only the task index goes in and the (small, picklable) result comes back.

Results are returned in task order and are identical to a serial run: the same code runs
on the same data. (Bit-identity also needs the same BLAS threading in every process: the
command line sets single-threaded BLAS before numpy loads, see ``pelvislab.app``; a library
caller that does not gets whatever its BLAS does in the parent, inherited by the workers.)

The map runs serially when

* ``jobs`` is 1 or there is only one task,
* the platform cannot fork safely: Windows has no fork, and on macOS forking a process
  that has used Accelerate/Objective-C libraries is a known crash (Python's default there
  is spawn, which cannot carry the closures),
* the calling process already runs other Python threads (the GUI runs the diagnosis in a
  worker thread; forking a multi-threaded process can deadlock the child), or
* the caller is itself a daemonic worker (which may not have children).

A worker that dies (killed, out of memory) stops the map with :class:`WorkerDied` instead
of waiting for it forever; Ctrl-C reaches the parent only (workers ignore SIGINT and are
terminated when the parent unwinds, as on SIGTERM or SIGHUP, which the command line turns
into the same interruption). On Linux a worker also ends when its parent dies without
unwinding (SIGKILL): ``PR_SET_PDEATHSIG``.
"""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any

# set in the parent just before the workers are forked; the children read it
_FORKED_TASK: tuple[Callable[[Any], Any], Sequence[Any]] | None = None


class WorkerDied(RuntimeError):
    """A worker process ended without returning its result (killed, out of memory)."""


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the OS reports one)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # no affinity API (macOS, Windows)
        return max(1, os.cpu_count() or 1)


def resolve_jobs(jobs: int) -> int:
    """``jobs`` as a worker count: 0 means every available core; more workers than
    available cores only add contention, so the count is capped there."""
    if jobs < 0:
        raise ValueError(f"jobs must be >= 0 (0 = every core), got {jobs}")
    cores = available_cores()
    return cores if jobs == 0 else min(jobs, cores)


def can_fork_workers() -> bool:
    """Whether forking workers from this process is safe (see the module docstring)."""
    return (sys.platform != "darwin"
            and "fork" in multiprocessing.get_all_start_methods()
            and threading.active_count() == 1
            and not multiprocessing.current_process().daemon)


def _worker_signals(parent_pid: int) -> None:
    """Signal set-up of a forked worker (its initializer)."""
    # Ctrl-C is the parent's to handle (one "interrupted" line, not a traceback per worker)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # the parent's handlers for these (the CLI turns them into KeyboardInterrupt) would
    # make a worker survive the parent's terminate(): a worker just ends
    for name in ("SIGTERM", "SIGHUP"):
        if hasattr(signal, name):
            signal.signal(getattr(signal, name), signal.SIG_DFL)
    if sys.platform.startswith("linux"):
        # a parent killed outright (SIGKILL, OOM killer) runs no cleanup: without this its
        # workers waited on their task pipe forever, holding its stdout open
        import ctypes

        try:
            ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
        except (OSError, AttributeError):
            pass
        if os.getppid() != parent_pid:  # the parent died before prctl took effect
            os._exit(1)


def _run_forked(index: int) -> Any:
    assert _FORKED_TASK is not None, "worker started without a task"
    fn, items = _FORKED_TASK
    return fn(items[index])


def parallel_map(fn: Callable[[Any], Any], items: Sequence[Any], jobs: int,
                 done: Callable[[int, int], None] | None = None) -> list[Any]:
    """``[fn(item) for item in items]``, spread over up to ``jobs`` forked processes.

    ``fn`` and ``items`` need not be picklable (the workers inherit them); each result
    must be. Tasks go to whichever worker is free (one at a time: their costs differ by
    10x). A task's exception is raised here: the first failing task in task order, as in
    the serial loop (tasks not yet started are cancelled). A worker that dies raises
    :class:`WorkerDied`. ``done(n, total)``, if given, is called in this process as the
    results arrive in task order (progress; an exception it raises stops the map as a
    task's would).
    """
    global _FORKED_TASK
    n_workers = min(resolve_jobs(jobs), len(items))
    if n_workers <= 1 or not can_fork_workers():
        results = []
        for item in items:
            results.append(fn(item))
            if done:
                done(len(results), len(items))
        return results
    _FORKED_TASK = (fn, items)
    # with the fork start method, the executor forks every worker before it starts its own
    # management thread, so no child is forked from a multi-threaded parent
    pool = ProcessPoolExecutor(n_workers, mp_context=multiprocessing.get_context("fork"),
                               initializer=_worker_signals, initargs=(os.getpid(),))
    try:
        results = []
        for result in pool.map(_run_forked, range(len(items)), chunksize=1):
            results.append(result)
            if done:
                done(len(results), len(items))
        return results
    except BrokenProcessPool as exc:
        raise WorkerDied("a worker process of the parallel fit ended without a result "
                         "(killed or out of memory?); run again, or with --jobs 1 to fit "
                         "in this process") from exc
    except BaseException:
        # interrupted (Ctrl-C) or a task failed: running tasks are not waited for (a fit
        # may take many seconds); the executor has no public terminate, hence _processes
        for proc in list((getattr(pool, "_processes", None) or {}).values()):
            proc.terminate()
        raise
    finally:
        pool.shutdown(wait=True, cancel_futures=True)
        _FORKED_TASK = None
