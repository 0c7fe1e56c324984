"""Ctrl-C during a long C call of the run still turns the outputs off at once.

CPython runs a Python signal handler in the main thread only between bytecodes; the CLI's run
is in the main thread, so an HDF5 flush or an FFT (50-230 ms measured under load) used to
delay the abort, and test_runner_kill's Ctrl-C test failed now and then (142 ms). Here the
run is one C call that releases the GIL and never looks at signals (PBKDF2): the abort must
come from the signal watcher thread while it lasts, not from the handler after it.
"""

from __future__ import annotations

import hashlib
import os
import signal
import sys
import time

import pytest

from pelvislab.app.commands.run import _run_with_signals


def _calibrated_iterations(seconds: float) -> int:
    n = 20_000
    t0 = time.perf_counter()
    hashlib.pbkdf2_hmac("sha256", b"pelvislab", b"salt", n)
    return max(n, int(n * seconds / max(time.perf_counter() - t0, 1e-6)))


class _Runner:
    def __init__(self) -> None:
        self.calls: list[tuple[str, float, str, str]] = []

    def abort(self, reason: str = "", status: str = "aborted") -> None:
        self.calls.append(("abort", time.monotonic(), reason, status))

    def interrupt(self, reason: str = "", safe_state: bool = True) -> None:
        # the real one raises RunInterrupted (and, with safe_state, puts outputs off)
        self.calls.append(("interrupt", time.monotonic(), reason, "interrupted"))


class _Prepared:
    def __init__(self, iterations: int, signum: int = signal.SIGINT) -> None:
        self.runner = _Runner()
        self.iterations = iterations
        self.signum = signum

    def run(self) -> str:
        self.t_signal = time.monotonic()
        os.kill(os.getpid(), self.signum)
        hashlib.pbkdf2_hmac("sha256", b"pelvislab", b"salt", self.iterations)  # ~0.4 s
        self.t_end = time.monotonic()
        return "final"


def test_sigint_during_a_long_c_call_aborts_within_100_ms():
    before = signal.getsignal(signal.SIGINT)
    prepared = _Prepared(_calibrated_iterations(0.4))
    assert _run_with_signals(prepared) == "final"
    aborts = [c for c in prepared.runner.calls if c[0] == "abort"]
    assert aborts, prepared.runner.calls
    _, t_abort, reason, status = aborts[0]
    assert t_abort < prepared.t_end, "abort only after the C call: no watcher"
    assert t_abort - prepared.t_signal < 0.1
    assert reason == "interrupted by Ctrl-C (SIGINT)" and status == "interrupted"
    assert any(c[0] == "interrupt" for c in prepared.runner.calls)  # the handler still runs
    # everything is put back: handler, wake-up fd
    assert signal.getsignal(signal.SIGINT) is before
    assert signal.set_wakeup_fd(-1) == -1


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signal")
@pytest.mark.parametrize("name", ["SIGHUP", "SIGQUIT"])
def test_closed_terminal_or_ctrl_backslash_aborts_like_ctrl_c(name):
    # before, SIGHUP (terminal closed, ssh dropped) and SIGQUIT killed the process with the
    # shaker still driving: no handler, default action
    signum = getattr(signal, name)
    # under nohup (e.g. `nohup make test`) SIGHUP is inherited as ignored, which the run
    # rightly keeps (next test): here the handling of a SIGHUP that is not ignored is checked
    inherited = signal.signal(signum, signal.SIG_DFL)
    try:
        before = signal.getsignal(signum)
        prepared = _Prepared(_calibrated_iterations(0.1), signum)
        assert _run_with_signals(prepared) == "final"
        aborts = [c for c in prepared.runner.calls if c[0] == "abort"]
        assert aborts and aborts[0][3] == "interrupted" and name in aborts[0][2]
        assert signal.getsignal(signum) is before
    finally:
        signal.signal(signum, inherited)


@pytest.mark.skipif(not hasattr(signal, "SIGHUP"), reason="POSIX signal")
def test_nohup_keeps_the_run_going_when_the_terminal_closes():
    # nohup sets SIGHUP to "ignore": the run must outlive the terminal, not abort on it
    before = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        prepared = _Prepared(_calibrated_iterations(0.05), signal.SIGHUP)
        assert _run_with_signals(prepared) == "final"
        assert prepared.runner.calls == []
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, before)


def test_exit_code_survives_a_terminal_that_hung_up(monkeypatch):
    # writing to a hung-up tty raises EIO (not EPIPE): the summary line is lost, the
    # exit code must still say how the run ended
    import argparse
    import errno
    import sys

    from pelvislab.app.commands.run import EXIT_INTERRUPTED, _report

    class HungUp:
        def write(self, text):
            raise OSError(errno.EIO, "Input/output error")

        def flush(self):
            raise OSError(errno.EIO, "Input/output error")

    class Final:
        status, reason, n_done, n_steps = "interrupted", "SIGHUP", 3, 8

    class Prepared:
        unsafe = ()

    monkeypatch.setattr(sys, "stderr", HungUp())
    args = argparse.Namespace(out="s.h5")
    assert _report(args, Prepared(), Final(), 1.0) == EXIT_INTERRUPTED


def test_an_interrupt_that_cannot_propagate_is_not_printed(monkeypatch):
    # clean-clone run, session 35: Ctrl-C landed in a weakref callback of the import
    # machinery; CPython printed the handler's RunInterrupted as "Exception ignored ...
    # Traceback" on stderr (the abort itself had been done)
    import gc
    from types import SimpleNamespace

    from pelvislab.acquisition.runner import RunInterrupted

    seen = []
    monkeypatch.setattr(sys, "unraisablehook", lambda args: seen.append(args.exc_type))

    class Raises:
        def __init__(self, exc):
            self.exc = exc

        def __del__(self):
            raise self.exc

    def run():
        Raises(RunInterrupted("interrupted by Ctrl-C (SIGINT)"))  # dropped at once
        Raises(ValueError("a real problem"))
        gc.collect()
        return "finished"

    prepared = SimpleNamespace(runner=SimpleNamespace(interrupt=lambda reason: None), run=run)
    hook = sys.unraisablehook
    assert _run_with_signals(prepared) == "finished"
    assert seen == [ValueError]  # others still reported
    assert sys.unraisablehook is hook  # put back
