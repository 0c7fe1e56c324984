"""Files derived from others (``model frf --out``, ``import-uff``, ``reprocess``) when the
disk or the file-size limit (``ulimit -f``) cannot take them: one line, no crash, nothing
left behind (session 51: ``model frf --out`` at an 8 kB limit ended in a segmentation fault,
exit 139, and left its hidden temporary file; ``reprocess`` said "Can't decrement id ref
count"). Each case runs in its own process: a refused HDF5 write leaves a handle that this
process must not close."""

from __future__ import annotations

import resource
import subprocess
import sys
from pathlib import Path

import pytest

from pelvislab.app.cli import main
from pelvislab.tests.test_runner_aiming import PROTOCOL as AIM_PROTOCOL

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"),
                                reason="RLIMIT_FSIZE as on Linux")

PROTOCOL = AIM_PROTOCOL.split("[[setups]]\nname = \"b\"")[0]  # three steps, two channels
MODEL_FRF = ["model", "frf", "--points", "sacrum_x,SIAS_R_x"]

# the command line as `pelvislab`, with the room check's margin set from argv[1]: at 0 the
# check lets a file start that the limit then cuts part way
RUN_CLI = """
import sys
from pelvislab.acquisition import session
session.NEW_FILE_MARGIN_BYTES = int(sys.argv.pop(1))
from pelvislab.app.cli import main
sys.exit(main())
"""


def _cli_under_limit(limit_bytes: int, margin_bytes: int, *argv: str,
                     cwd: Path) -> subprocess.CompletedProcess:
    def limit_file_size() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit_bytes, resource.RLIM_INFINITY))

    return subprocess.run([sys.executable, "-c", RUN_CLI, str(margin_bytes), *argv],
                          preexec_fn=limit_file_size, capture_output=True, text=True,
                          timeout=300, cwd=cwd)


def _one_line_error(done: subprocess.CompletedProcess) -> str:
    assert done.returncode == 1, (done.returncode, done.stderr[-2000:])
    assert "Traceback" not in done.stderr, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1, done.stderr[-2000:]
    return lines[0]


def test_an_frf_file_the_limit_cannot_hold_is_refused_before_it_starts(tmp_path):
    from pelvislab.acquisition.session import NEW_FILE_MARGIN_BYTES

    done = _cli_under_limit(8 * 1024, NEW_FILE_MARGIN_BYTES, *MODEL_FRF, "--out", "m.h5",
                            cwd=tmp_path)
    line = _one_line_error(done)
    assert "cannot write m.h5: the file-size limit (ulimit -f) is 0.01 MB" in line, line
    assert list(tmp_path.iterdir()) == []  # no file, no hidden temporary one


def test_an_frf_file_cut_part_way_by_the_limit_leaves_nothing(tmp_path):
    # margin 0: the check passes (about 17 kB estimated), the file (22 kB) does not fit
    done = _cli_under_limit(20 * 1024, 0, *MODEL_FRF, "--out", "m.h5", cwd=tmp_path)
    line = _one_line_error(done)
    assert line == ("pelvislab model frf: error: writing m.h5 failed: File too large; "
                    "nothing was written under that name"), line
    assert list(tmp_path.iterdir()) == []
    # with room, the same command writes it
    assert main([*MODEL_FRF, "--out", str(tmp_path / "m.h5")]) == 0


def test_a_reprocessed_session_the_limit_cannot_hold_is_refused(tmp_path):
    from pelvislab.acquisition.session import NEW_FILE_MARGIN_BYTES

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)
    source = tmp_path / "s.h5"
    assert main(["run", str(protocol), "--out", str(source), "--quiet"]) == 0
    size = source.stat().st_size
    # the echoes alone take about 1.5 MB: a limit above the session file's own size (it
    # applies per file) but under what the copy needs with its margin
    done = _cli_under_limit(size + 1024, NEW_FILE_MARGIN_BYTES, "reprocess", str(source),
                            "--out", "r.h5", cwd=tmp_path)
    line = _one_line_error(done)
    assert line.startswith("pelvislab reprocess: error: cannot write r.h5: the file-size "
                           "limit (ulimit -f) is "), line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.toml", "s.h5"]
