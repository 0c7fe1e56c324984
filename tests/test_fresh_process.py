"""The fresh-process helper of the gap tests ends everything it started on a timeout."""

import os
import subprocess
import time
from pathlib import Path

import pytest

from pelvislab.tests.fresh_process import json_from_fresh_process

# the interpreter forks a worker (as the diagnosis does), writes the worker's pid, and both
# wait far past the timeout
_FORK_AND_WAIT = """\
import os, sys, time
pid = os.fork()
if pid:
    with open(sys.argv[1], "w") as f:
        f.write(str(pid))
time.sleep(120)
"""


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs: a killed orphan that the container's init does not reap stays
    a zombie (state Z in /proc), which counts as ended."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    stat = Path(f"/proc/{pid}/stat")
    try:
        # the state follows the command name, which is in parentheses
        return stat.read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except (FileNotFoundError, IndexError):
        return not stat.parent.parent.exists()  # no /proc (macOS): os.kill decided


def test_timeout_kills_the_forked_workers_too(tmp_path):
    pid_file = tmp_path / "worker.pid"
    with pytest.raises(subprocess.TimeoutExpired):
        json_from_fresh_process(_FORK_AND_WAIT, str(pid_file), timeout_s=3.0)
    worker = int(pid_file.read_text())
    deadline = time.monotonic() + 10.0
    while _alive(worker) and time.monotonic() < deadline:
        time.sleep(0.1)  # the orphan is reaped by init once killed
    assert not _alive(worker)
