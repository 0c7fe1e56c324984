"""SIGTERM, SIGHUP and Ctrl-C close ``pelvislab gui`` while a modal dialog is open, as the
close button does (a running session ends safely first). In-process: ``run_gui`` on the
test's offscreen QApplication, the signal sent to this process from a Qt timer."""

from __future__ import annotations

import os
import signal
import sys
from importlib import resources

import pytest
from PySide6 import QtCore, QtWidgets

from pelvislab.acquisition.session import SessionReader
from pelvislab.app import gui_main

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="POSIX signals")


def _guard(seen: dict, after_ms: int = 20_000) -> QtCore.QTimer:
    """Where the signal fails, end the dialogs and the loop so that the test fails rather
    than hangs."""
    def give_up() -> None:
        seen["gave_up"] = True
        while (widget := QtWidgets.QApplication.activeModalWidget()) is not None:
            widget.hide()
        for widget in QtWidgets.QApplication.topLevelWidgets():
            if isinstance(widget, gui_main.OperatorWindow):
                widget.ask_before_closing_a_run = False
                widget.close()
        QtWidgets.QApplication.quit()

    def keep_quitting() -> None:
        # QApplication.quit() before run_gui's loop has started does nothing (the guard
        # may fire while the window is still being built): ask until the loop ends
        give_up()
        timer.setSingleShot(False)
        timer.timeout.disconnect()
        timer.timeout.connect(QtWidgets.QApplication.quit)
        timer.start(100)

    timer = QtCore.QTimer()
    timer.setSingleShot(True)
    timer.timeout.connect(keep_quitting)
    timer.start(after_ms)
    return timer


@pytest.fixture(autouse=True)
def _sighup_default():
    """SIGHUP at its default action for the test: run_gui keeps an ignored SIGHUP ignored
    (nohup), and a suite started under nohup sent it to nobody (the test hung)."""
    previous = signal.signal(signal.SIGHUP, signal.SIG_DFL)
    try:
        yield
    finally:
        signal.signal(signal.SIGHUP, previous)


@pytest.mark.parametrize("signum", ["SIGTERM", "SIGHUP", "SIGINT"])
def test_a_signal_over_the_bad_files_dialog_closes_the_gui(qapp, tmp_path, capsys, signum):
    # audit: `pelvislab gui bad.h5`'s "Cannot open session" box opens while the window is
    # being built, before the application's loop: SIGTERM did nothing there (no timer woke
    # Python's handler, no window to close yet, the box waiting for a click): SIGKILL only
    bad = tmp_path / "bad.h5"
    bad.write_text("not a session")
    seen: dict = {}

    def signal_over_the_box() -> None:
        box = QtWidgets.QApplication.activeModalWidget()
        seen["box"] = None if box is None else box.windowTitle()
        os.kill(os.getpid(), getattr(signal, signum))

    guard = _guard(seen)
    # the first timer to fire runs in the box's own loop, the window still in construction
    QtCore.QTimer.singleShot(1000, signal_over_the_box)
    try:
        assert gui_main.run_gui(bad) == 0
    finally:
        guard.stop()
    assert seen["box"] == "Cannot open session"
    assert "gave_up" not in seen, f"{signum} left the dialog open"
    err = capsys.readouterr().err
    # the terminal learns why too (the box stays for the operator: one line, no traceback)
    assert "pelvislab gui: cannot open session" in err and "not a readable HDF5" in err
    assert not [w for w in QtWidgets.QApplication.topLevelWidgets()
                if isinstance(w, gui_main.OperatorWindow) and w.isVisible()]


def test_a_signal_during_the_close_question_stops_the_run_safely(qapp, tmp_path):
    # the close button asks "A run is going ..." (a modal question); SIGTERM while it is
    # open answers nothing: the run is stopped (outputs off, file closed) and the window
    # closes, as for a signal without a question
    out = tmp_path / "gui.h5"
    seen: dict = {}

    def poll() -> None:
        window = next((w for w in QtWidgets.QApplication.topLevelWidgets()
                       if isinstance(w, gui_main.OperatorWindow) and w.isVisible()), None)
        if window is None or "asked" in seen:
            return
        if window.confirm_button.isVisible():
            window.confirm_prompt()
        if window.state_banner.text() == "RUNNING — OUTPUTS ON":
            seen["asked"] = True
            QtCore.QTimer.singleShot(500, signal_over_the_question)
            window.close()  # the close button: the question's own loop runs here
            seen["run_left_running"] = window.control is not None and (
                not window.control.finished.is_set())

    def signal_over_the_question() -> None:
        box = QtWidgets.QApplication.activeModalWidget()
        seen["box"] = None if box is None else box.windowTitle()
        os.kill(os.getpid(), signal.SIGTERM)

    timer = QtCore.QTimer()
    timer.timeout.connect(poll)
    timer.start(100)
    guard = _guard(seen, 90_000)
    try:
        code = gui_main.run_gui(start_protocol=resources.files("pelvislab.protocols")
                                / "demo.toml", out_path=out)
    finally:
        timer.stop()
        guard.stop()
    assert "gave_up" not in seen, seen
    assert code == 0 and seen["box"] == "A run is going"
    assert seen["run_left_running"] is False  # the close waited for the run's end
    with SessionReader(out) as reader:
        # the signal, not the operator, ended it (it was recorded as the operator's)
        assert reader.status == ("aborted", "window closed by SIGTERM (shutdown, terminal "
                                 "closed or Ctrl-C)")
