"""The gap fits' forked workers end with their parent (helper review of session 34: a
``gap diagnose`` sent SIGTERM left its two workers blocked on their task pipe forever,
holding the caller's stdout open).

Each test runs a parent process that maps slow tasks over two workers, as the CLI does,
then stops the parent from outside and checks that the workers are gone.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from pelvislab.model.parallel import can_fork_workers

pytestmark = pytest.mark.skipif(
    not sys.platform.startswith("linux") or not can_fork_workers(),
    reason="forked workers and /proc (Linux)")

PARENT = textwrap.dedent("""
    import os, sys, time
    from pelvislab.app.cli import Terminated, _stop_on_termination_signals
    from pelvislab.model.parallel import parallel_map
    _stop_on_termination_signals()
    folder = sys.argv[1]
    def task(k):
        open(os.path.join(folder, str(os.getpid())), "w").close()
        time.sleep(300)
        return k
    try:
        parallel_map(task, list(range(4)), 2)
    except Terminated as exc:
        print(f"stopped: {exc}", flush=True)
        sys.exit(130)
    """)


def _alive(pid: int) -> bool:
    """Running (not gone, not a zombie nobody has reaped yet)."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state != "Z"


def _start(tmp_path: Path) -> tuple[subprocess.Popen, list[int]]:
    parent = subprocess.Popen([sys.executable, "-c", PARENT, str(tmp_path)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while len(list(tmp_path.iterdir())) < 2:
        assert parent.poll() is None, parent.communicate()
        assert time.monotonic() < deadline, "workers did not start"
        time.sleep(0.05)
    return parent, [int(p.name) for p in tmp_path.iterdir()]


def _gone_soon(pids: list[int], seconds: float = 20.0) -> bool:
    deadline = time.monotonic() + seconds
    while any(_alive(p) for p in pids):
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def _kill_leftovers(pids: list[int]) -> None:
    for p in pids:
        if _alive(p):
            os.kill(p, signal.SIGKILL)


def test_sigterm_stops_the_parent_cleanly_and_ends_its_workers(tmp_path):
    parent, workers = _start(tmp_path)
    try:
        assert os.getpid() not in workers and parent.pid not in workers
        parent.send_signal(signal.SIGTERM)
        out, err = parent.communicate(timeout=60)
        assert parent.returncode == 130, (out, err)
        assert "stopped: interrupted by SIGTERM" in out
        assert _gone_soon(workers), "workers outlived the parent"
    finally:
        _kill_leftovers(workers)
        parent.kill()


def test_workers_end_when_their_parent_is_killed_outright(tmp_path):
    parent, workers = _start(tmp_path)
    try:
        parent.kill()  # SIGKILL: no cleanup runs in the parent
        parent.communicate(timeout=60)
        assert _gone_soon(workers), "workers outlived the parent"
    finally:
        _kill_leftovers(workers)
