"""Suite-wide test settings: Qt offscreen, hypothesis profile for a 2-core CI machine."""

import os

import pytest
from hypothesis import HealthCheck, settings

# single-threaded BLAS before numpy is first imported, as the command line sets it:
# otherwise the fits run on BLAS threads (and forked workers on top of them) whenever a
# test module that imports numpy is collected before one that imports pelvislab.app (2-core
# machine: the whole suite 671.9 s against 274.7 s; test_gap_support_contacts'
# test_per_dashpot_damping_data_are_none alone 26-29 s against 3.2 s)
import pelvislab.app  # noqa: F401

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

# "ci" (default): the same examples on every run, so a submission never fails on a
# newly drawn example; HYPOTHESIS_PROFILE=explore draws new ones (run it now and then).
settings.register_profile(
    "ci", max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow],
    derandomize=True, database=None,
)
settings.register_profile(
    "explore", max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow]
)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture
def operator_window(qtbot):
    """A fresh operator window, deleted while Qt still runs (PySide6 crashes at interpreter
    exit when the window is left to the final garbage collection)."""
    from PySide6 import QtWidgets

    from pelvislab.app.gui_main import OperatorWindow

    windows = []

    def make(*args, **kwargs):
        window = OperatorWindow(*args, **kwargs)
        window.show()
        windows.append(window)
        return window

    yield make
    for window in windows:
        window.ask_before_closing_a_run = False  # nobody answers a question offscreen
        window.close()
        window.deleteLater()
    QtWidgets.QApplication.processEvents()


@pytest.fixture(scope="session", autouse=True)
def _delete_qt_widgets_before_exit():
    """Delete every remaining top-level Qt widget while Qt still runs (see operator_window)."""
    yield
    from PySide6 import QtWidgets

    app = QtWidgets.QApplication.instance()
    if app is None:
        return
    import gc

    gc.collect()
    for widget in app.topLevelWidgets():
        widget.close()
        widget.deleteLater()
    app.processEvents()
