"""A kill during session creation leaves ``.S.h5.<pid>.partial``; the next create removes
it when that process is gone (and says so in the new session's log), never a live one's."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

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


def test_publish_without_hard_links_never_replaces_a_file_that_appears(tmp_path, monkeypatch):
    """On a file system without hard links the finished file is renamed into place. A file
    that appears under the target name after the check (another run finishing at that
    moment) must not be replaced: renameat2(RENAME_NOREPLACE) refuses atomically. Before,
    an exists-then-rename fallback replaced it."""
    import errno
    import sys

    from pelvislab.acquisition import session as session_mod

    if not sys.platform.startswith("linux"):
        pytest.skip("renameat2 is Linux-only")
    tmp, target = tmp_path / "s.h5.partial", tmp_path / "s.h5"
    tmp.write_bytes(b"new")

    calls = []

    def no_link(src, dst):
        if not calls:  # the first time another file appears in the window no check closes
            target.write_bytes(b"theirs")
        calls.append(dst)
        raise OSError(errno.EPERM, "hard links not supported")

    monkeypatch.setattr(session_mod.os, "link", no_link)
    monkeypatch.setattr(session_mod.Path, "exists", lambda self: False)
    with pytest.raises(FileExistsError, match="not overwriting"):
        session_mod.publish_new_file(tmp, target)
    assert target.read_bytes() == b"theirs" and tmp.read_bytes() == b"new"
    target.unlink()
    session_mod.publish_new_file(tmp, target)  # and with the name free it is renamed into place
    assert target.read_bytes() == b"new" and not tmp.exists()


def test_publish_syncs_the_new_name(tmp_path, monkeypatch):
    """The finished file is synced before it gets its name, and the name's folder entry
    after: a power cut must not leave the file without its name (reprocess output had no
    sync after the link)."""
    from pelvislab.acquisition import session as session_mod

    synced = []
    monkeypatch.setattr(session_mod, "fsync_path", lambda p: synced.append(Path(p)))
    tmp, target = tmp_path / "s.h5.partial", tmp_path / "s.h5"
    tmp.write_bytes(b"new")
    session_mod.publish_new_file(tmp, target)
    assert synced == [tmp, target]
