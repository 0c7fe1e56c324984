"""Files derived from others (``model frf --out``, ``import-uff``, ``reprocess``) when the
disk or the file-size limit (``ulimit -f``) cannot take them: one line, no crash, nothing
left behind, never a wrong file under the real name (session 51: ``model frf --out`` at an
8 kB limit ended in a segmentation fault, exit 139, and left its hidden temporary file;
``reprocess`` said "Can't decrement id ref count"; a helper's review found a write HDF5
dropped while it freed an object, and the file published with zeros for data). Each case
runs in its own process: a refused HDF5 write leaves a handle that this process must not
close."""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from pelvislab.app.cli import main
from pelvislab.tests.test_session_kill_windows import PROTOCOL  # three steps, two channels

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="RLIMIT_FSIZE as on Linux")

MODEL_FRF = ["model", "frf", "--points", "sacrum_x,SIAS_R_x"]

def _cli_under_limit(limit_bytes: int, *argv: str, cwd: Path) -> subprocess.CompletedProcess:
    def limit_file_size() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, resource.RLIM_INFINITY))

    return subprocess.run([sys.executable, "-m", "pelvislab.app", *argv],
                          preexec_fn=limit_file_size, capture_output=True, text=True,
                          timeout=300, cwd=cwd)


def _one_line_error(done: subprocess.CompletedProcess) -> str:
    assert done.returncode == 1, (done.returncode, done.stderr[-2000:])
    assert "Traceback" not in done.stderr, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr[-2000:]
    return lines[0]


@pytest.mark.parametrize("limit_kb", [8, 20])  # 8: HDF5 crashed; 20: its error record
def test_an_frf_file_the_limit_cannot_hold_is_one_line_and_leaves_nothing(tmp_path, limit_kb):
    done = _cli_under_limit(limit_kb * 1024, *MODEL_FRF, "--out", "m.h5", cwd=tmp_path)
    line = _one_line_error(done)
    assert line == ("pelvislab model frf: error: writing m.h5 failed: File too large; "
                    "nothing was written under that name"), line
    assert list(tmp_path.iterdir()) == []  # no file, no hidden temporary one
    # with room, the same command writes it (22 kB)
    assert main([*MODEL_FRF, "--out", str(tmp_path / "m.h5")]) == 0


def test_a_reprocessed_session_the_limit_cannot_hold_is_refused(tmp_path):
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    source = tmp_path / "s.h5"
    assert main(["run", str(protocol), "--out", str(source), "--quiet"]) == 0
    size = source.stat().st_size  # about 2.6 MB, as its copy
    done = _cli_under_limit(size // 2, "reprocess", str(source), "--out", "r.h5",
                            cwd=tmp_path)
    line = _one_line_error(done)
    assert line.startswith("pelvislab reprocess: error: cannot write r.h5: the file-size "
                           "limit (ulimit -f) is "), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.toml", "s.h5"]
    # 20 % above the copy's size is room enough (the first check asked for 2x + 1 MB and
    # refused 2.9 MB for this 2.6 MB copy; review, session 51)
    done = _cli_under_limit(int(1.2 * size), "reprocess", str(source), "--out", "r.h5",
                            cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "r.h5").stat().st_size < 1.2 * size


@pytest.mark.skipif(shutil.which("strace") is None, reason="needs strace's fault injection")
def test_a_write_hdf5_drops_while_freeing_an_object_fails_the_reprocess(tmp_path):
    """One refused write (EIO) among the copy's: HDF5 reported it only as an error while it
    freed a dataset (Python's "unraisable" hook) and reprocess published the file, its
    step's force phasor 0j, then crashed at exit (exit 139; helper review, session 51).
    Every write of the copy (the 4th to the 124th of this session's) was checked by hand
    the same way: one line, nothing left."""
    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    source = tmp_path / "s.h5"
    assert main(["run", str(protocol), "--out", str(source), "--quiet"]) == 0
    done = subprocess.run(["strace", "-f", "-qq", "-o", os.devnull, "-e", "trace=pwrite64",
                           "-e", "inject=pwrite64:error=EIO:when=33", sys.executable, "-m",
                           "pelvislab.app", "reprocess", str(source), "--out", "r.h5"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    if "PTRACE" in done.stderr or "ptrace" in done.stderr:
        pytest.skip(f"strace cannot trace here: {done.stderr.strip()[:200]}")
    line = _one_line_error(done)
    assert line == ("pelvislab reprocess: error: writing r.h5 failed: Input/output error; "
                    "nothing was written under that name"), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.toml", "s.h5"]


def test_a_uff_export_the_limit_cannot_hold_names_the_systems_reason(tmp_path):
    # pyuff said "Error writing data-set #58" over "File too large" (session 51)
    assert main([*MODEL_FRF, "--out", str(tmp_path / "m.h5")]) == 0
    done = _cli_under_limit(4 * 1024, "export-uff", "m.h5", "e.uff", cwd=tmp_path)
    line = _one_line_error(done)
    assert line == ("pelvislab export-uff: error: writing e.uff failed: File too large; "
                    "nothing was written under that name"), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.h5"]
