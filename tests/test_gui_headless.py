"""``pelvislab gui`` never waits for a click nobody can give; Ctrl-C or SIGTERM closes it
(a running session ends safely first)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

ENV = dict(os.environ, QT_QPA_PLATFORM="offscreen")


def _default_sighup() -> None:
    """In a child before exec: SIGHUP back to its default action."""
    signal.signal(signal.SIGHUP, signal.SIG_DFL)


def _signal_and_wait(proc: subprocess.Popen, signum: str, what: str) -> None:
    """Send ``signum`` to ``proc`` and wait up to 20 s for it to end; kill it and fail
    the test if it does not."""
    try:
        proc.send_signal(getattr(signal, signum))
        proc.wait(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            pytest.fail(f"{what} still open 20 s after {signum}")


def _gui(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pelvislab.app", "gui", *args], env=ENV,
                          capture_output=True, text=True, timeout=timeout)


def test_screenshot_of_a_bad_file_fails_with_one_line_instead_of_a_dialog(tmp_path):
    # before: a modal "Cannot open session" box that nobody could answer, forever
    bad = tmp_path / "bad.h5"
    bad.write_text("not a session")
    done = _gui(str(bad), "--screenshot", str(tmp_path / "x.png"))
    assert done.returncode == 1
    assert "Cannot open session" in done.stderr and "not a readable HDF5" in done.stderr
    assert not (tmp_path / "x.png").exists()
    done = _gui(str(bad), "--screenshot", str(tmp_path / "x.png"), "--after", "inf")
    assert done.returncode == 1 and "--after" in done.stderr
    # options that mean nothing alone are refused, not ignored with the window left open
    # (helper review, session 34)
    done = _gui("--after", "5")
    assert done.returncode == 1 and "--after goes with --screenshot" in done.stderr
    done = _gui("--out", str(tmp_path / "s.h5"))
    assert done.returncode == 1 and "--out goes with --start" in done.stderr


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signal")
@pytest.mark.parametrize("signum", ["SIGINT", "SIGTERM"])
def test_ctrl_c_or_sigterm_closes_the_window(tmp_path, signum):
    proc = subprocess.Popen([sys.executable, "-m", "pelvislab.app", "gui"], env=ENV,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(3.0)  # the GUI has started (its handler is installed before the window)
    # before: Qt's loop never let Python run its handler; the window stayed open
    _signal_and_wait(proc, signum, "pelvislab gui")
    # closed by the handler, not by a KeyboardInterrupt ("pelvislab: interrupted", 130)
    assert proc.returncode == 0, proc.stderr.read()[-500:]


@pytest.mark.skipif(sys.platform == "win32", reason="POSIX signal")
@pytest.mark.parametrize("signum", ["SIGTERM", "SIGHUP"])
def test_a_signal_closes_the_window_over_a_bad_files_dialog(tmp_path, signum):
    # audit: `pelvislab gui bad.h5` showed its "Cannot open session" box while the window
    # was being built; SIGTERM then did nothing (no timer woke Python's handler, and the
    # box's own loop waited for a click): it needed SIGKILL. The terminal got no reason.
    import threading

    bad = tmp_path / "bad.h5"
    bad.write_text("not a session")
    # the GUI keeps an ignored SIGHUP ignored (nohup): the child gets the default
    # disposition whatever this test run inherited (a suite started under nohup failed)
    proc = subprocess.Popen([sys.executable, "-m", "pelvislab.app", "gui", str(bad)],
                            env=ENV, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=_default_sighup)
    lines: list[str] = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stderr), daemon=True)
    reader.start()
    deadline = time.monotonic() + 20  # the reason is printed as the box opens
    while (not any("cannot open session" in line for line in lines)
           and proc.poll() is None and time.monotonic() < deadline):
        time.sleep(0.1)
    time.sleep(1.0)  # the box is up (a signal before it is handled as well)
    _signal_and_wait(proc, signum, "pelvislab gui bad.h5")
    reader.join(5)
    assert proc.returncode == 0, lines
    reason = [line for line in lines if "cannot open session" in line]
    assert len(reason) == 1 and "not a readable HDF5" in reason[0], lines
    assert reason[0].startswith("pelvislab gui: ") and "Traceback" not in "".join(lines)


def test_a_failed_analysis_in_a_screenshot_fails_the_command(tmp_path):
    # replay review, session 36: the failure was logged, the picture saved, exit 0
    import h5py
    import numpy as np

    from pelvislab.app.cli import main

    path = tmp_path / "f.h5"
    assert main(["model", "frf", "--points", "sacrum_x,SIAS_R_x", "--out", str(path)]) == 0
    with h5py.File(path, "r+") as f:
        f["frf/H"][...] = np.nan  # nothing measured: identify refuses it
    png = tmp_path / "x.png"
    done = _gui(str(path), "--analyse", "identify", "--screenshot", str(png))
    assert done.returncode == 1, done.stderr
    assert "identification failed" in done.stderr and "no measured line" in done.stderr
    assert png.exists()  # the picture still shows the failed analysis' status


def test_a_run_failed_in_a_screenshot_fails_the_command(tmp_path):
    # session 51: a session file refusing a write made its writer refuse the Fault and the
    # run's end too, and the window never heard of them: "RUNNING — OUTPUTS ON" in the
    # picture with the outputs off, exit 0. The "Run failed" box is a dialog nobody
    # answers offscreen: the command's error, the picture still written
    from pelvislab.acquisition.session import SessionReader
    from pelvislab.app.cli import main
    from pelvislab.tests.test_session_kill_windows import INJECT_WRITE_FAILURE, PROTOCOL

    protocol = tmp_path / "p.toml"
    protocol.write_text(PROTOCOL)  # three steps; the second one's write is refused
    out, png = tmp_path / "s.h5", tmp_path / "x.png"
    argv = ["gui", "--start", str(protocol), "--out", str(out), "--after", "8",
            "--screenshot", str(png)]
    done = subprocess.run([sys.executable, "-c", INJECT_WRITE_FAILURE.format(argv=argv)],
                          env=ENV, capture_output=True, text=True, timeout=120)
    assert done.returncode == 1, (done.returncode, done.stderr[-2000:])
    last = done.stderr.strip().splitlines()[-1]
    assert last.startswith("pelvislab gui: error: run failed: 1/3 steps") and (
        "Input/output error" in last and f"(screenshot written to {png})" in last), last
    assert png.exists()
    # the step written before the failure is kept and the run resumes to the plan
    assert main(["run", str(protocol), "--out", str(out), "--resume", "--quiet"]) == 0
    with SessionReader(out) as reader:
        assert reader.status[0] == "completed"
        assert len({s.key for s in reader.steps(with_echoes=False)}) == 3
