"""Forked worker map (model/parallel.py) and the gap diagnosis' independence of it."""

from __future__ import annotations

import os
import textwrap
import threading

import pytest

from pelvislab.model.parallel import available_cores, can_fork_workers, parallel_map, resolve_jobs
from pelvislab.tests.fresh_process import json_from_fresh_process

needs_fork = pytest.mark.skipif(not can_fork_workers(), reason="cannot fork workers here")


def _in_fresh_process(code: str) -> dict:
    """Run ``code`` (which prints one JSON line) in a new interpreter: the test process
    may hold threads left by other tests (the GUI's executors), and then the map runs
    serially by design (can_fork_workers)."""
    return json_from_fresh_process(textwrap.dedent(code))


@needs_fork
def test_results_in_task_order_from_other_processes_with_a_closure():
    got = _in_fresh_process("""
        import json, os
        import numpy as np
        from pelvislab.model.parallel import can_fork_workers, parallel_map
        offset = np.arange(3.0)  # captured by the closure: nothing here is pickled going in
        out = parallel_map(lambda k: (k, (offset * k).tolist(), os.getpid()), list(range(12)), 2)
        print(json.dumps({"fork": can_fork_workers(), "parent": os.getpid(),
                          "k": [o[0] for o in out], "arr": [o[1] for o in out],
                          "pids": sorted({o[2] for o in out})}))
        """)
    assert got["fork"]
    assert got["k"] == list(range(12))
    assert got["arr"] == [[0.0, float(k), 2.0 * k] for k in range(12)]
    assert got["parent"] not in got["pids"]


@needs_fork
def test_done_reports_each_result_in_this_process_and_can_stop_the_map():
    """``done`` (progress: the gap diagnosis' joint-fit starts said nothing for 11 s, and
    the GUI's Cancel, raised from it, waited as long) sees every result in task order in
    the calling process; what it raises stops the map, workers and all."""
    got = _in_fresh_process("""
        import json, os
        from pelvislab.model.parallel import can_fork_workers, parallel_map
        seen = []
        out = parallel_map(lambda k: k * k, list(range(5)), 2,
                           done=lambda n, total: seen.append((n, total, os.getpid())))
        class Stop(Exception):
            pass
        def stop(n, total):
            if n == 2:
                raise Stop()
        try:
            parallel_map(lambda k: k, list(range(40)), 2, done=stop)
            stopped = False
        except Stop:
            stopped = True
        print(json.dumps({"fork": can_fork_workers(), "out": out, "stopped": stopped,
                          "seen": [s[:2] for s in seen],
                          "here": all(s[2] == os.getpid() for s in seen)}))
        """)
    assert got["fork"] and got["out"] == [0, 1, 4, 9, 16]
    assert got["seen"] == [[n, 5] for n in range(1, 6)] and got["here"]
    assert got["stopped"]
    serial = []
    assert parallel_map(lambda k: -k, [1, 2], 1, done=lambda n, t: serial.append((n, t))) \
        == [-1, -2]
    assert serial == [(1, 2), (2, 2)]


def test_task_error_is_raised_in_the_caller():
    def task(k: int) -> int:
        if k == 3:
            raise ValueError("task 3 failed")
        return k

    with pytest.raises(ValueError, match="task 3 failed"):
        parallel_map(task, list(range(6)), jobs=2)


@needs_fork
def test_a_dead_worker_stops_the_map_instead_of_hanging():
    # the subprocess' timeout (600 s) would fail the test if the map waited for the
    # killed worker's result (what multiprocessing.Pool.map does)
    got = _in_fresh_process("""
        import json, os, signal
        from pelvislab.model.parallel import WorkerDied, parallel_map
        def task(k):
            if k == 1:
                os.kill(os.getpid(), signal.SIGKILL)
            return k
        try:
            parallel_map(task, list(range(4)), 2)
            print(json.dumps({"raised": None}))
        except WorkerDied as exc:
            print(json.dumps({"raised": "WorkerDied", "text": str(exc)}))
        """)
    assert got["raised"] == "WorkerDied"
    assert "--jobs 1" in got["text"]


@needs_fork
def test_first_failure_in_task_order_is_raised_without_waiting_for_running_tasks():
    got = _in_fresh_process("""
        import json, time
        from pelvislab.model.parallel import parallel_map
        def task(k):
            if k == 0:
                time.sleep(0.5)
                raise ValueError("task 0 failed")
            if k == 1:
                time.sleep(3600)  # terminated, not waited for
            raise KeyError("later task")
        try:
            parallel_map(task, list(range(3)), 2)
        except Exception as exc:
            print(json.dumps({"type": type(exc).__name__, "text": str(exc)}))
        """)
    assert got == {"type": "ValueError", "text": "task 0 failed"}


def test_serial_when_jobs_is_one_or_another_thread_runs():
    assert {pid for pid in parallel_map(lambda _k: os.getpid(), [0, 1, 2], jobs=1)} == {
        os.getpid()}
    pids: list[int] = []
    started, release = threading.Event(), threading.Event()

    def other() -> None:
        started.set()
        release.wait(10)

    t = threading.Thread(target=other)
    t.start()
    started.wait(10)
    try:
        assert not can_fork_workers()
        pids = parallel_map(lambda _k: os.getpid(), [0, 1, 2], jobs=2)
    finally:
        release.set()
        t.join()
    assert set(pids) == {os.getpid()}


def test_jobs_validation():
    cores = available_cores()
    assert resolve_jobs(0) == cores
    assert resolve_jobs(1) == 1
    assert resolve_jobs(cores + 5) == cores  # more workers than cores only add contention
    with pytest.raises(ValueError, match="jobs"):
        resolve_jobs(-1)


@needs_fork
def test_gap_report_does_not_depend_on_the_number_of_workers():
    got = _in_fresh_process("""
        import json
        import numpy as np
        from pelvislab.acquisition.frfset import Channels
        from pelvislab.model.frf import frf
        from pelvislab.model.gap import GapOptions, diagnose, prepare_data
        from pelvislab.model.parallel import can_fork_workers
        from pelvislab.model.pelvis import default_model
        from pelvislab.tests.test_gap_diagnosis import F_HZ, IN, OUT, noisy, true_model
        rng = np.random.default_rng(5)
        d = OUT.direction.copy()
        t = np.radians(20.0)
        d[1] = np.array([np.cos(t), 0.0, np.sin(t)])
        tilted = Channels(OUT.name, OUT.bone, OUT.position_m, d)
        Hn, sigma = noisy(frf(true_model(), F_HZ, tilted, IN), rng)
        data = prepare_data(F_HZ, Hn, sigma, OUT, IN)
        opts = dict(effects=("sensor_misorientation", "added_mass"), base_starts=1,
                    max_nfev_joint=20, max_nfev_short=8, finish_jobs=2)
        reports = []
        for jobs in (1, 2):
            rep = dict(diagnose(data, default_model(), GapOptions(jobs=jobs, **opts)).report)
            rep.pop("timing_s")
            reports.append(json.dumps(rep, sort_keys=True))
        print(json.dumps({"fork": can_fork_workers(), "same": reports[0] == reports[1],
                          "verdict": json.loads(reports[0])["verdict"]}))
        """)
    assert got["fork"]
    assert got["same"]
    assert got["verdict"] == "sensor_misorientation"
