"""A kill during session creation leaves ``.S.h5.<pid>.partial``; the next create removes
it when that process is gone (and says so in the new session's log), never a live one's."""

from __future__ import annotations

import subprocess
import sys

from pelvislab.acquisition.session import SessionReader, SessionWriter, remove_stale_partials
from tests.test_session_format import BENCH, protocol  # noqa: F401  (fixture)


def dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_stale_partial_of_a_dead_process_removed_live_one_kept(tmp_path, protocol):  # noqa: F811
    path = tmp_path / "S.h5"
    dead = tmp_path / f".S.h5.{dead_pid()}.partial"
    dead.write_bytes(b"\x89HDF half a file")
    live_proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        live = tmp_path / f".S.h5.{live_proc.pid}.partial"
        live.write_bytes(b"being written")
        other = tmp_path / f".T.h5.{dead_pid()}.partial"  # another session's: not ours
        other.write_bytes(b"x")
        with SessionWriter.create(path, protocol, BENCH, "test"):
            pass
        assert not dead.exists()
        assert live.exists() and other.exists()
    finally:
        live_proc.kill()
        live_proc.wait()
    with SessionReader(path) as reader:
        lines = reader.log_lines()
    assert any("WARNING" in line and dead.name in line for line in lines), lines
    # the live process is gone now: the next call removes its file too
    assert remove_stale_partials(path) == [live.name]
