"""Operator window responsiveness during a run (issue 11: UI blocked <= 50 ms, >= 10 fps).

The figures include contention with the runner thread (simulation + tracking share the GIL
and the 2 cores), so they depend on machine load: compare them with the idle baseline.
Runs the demo protocol on the simulated bench from the window (offscreen), with the runner
in its own thread, and records the duration of every UI refresh (event drain + plot update)
and the frame rate. Baseline in the same run: the refresh of the idle window (no events).
Run: ``make bench`` or ``.venv/bin/python -m pelvislab.tests.benchmarks gui``.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path

import numpy as np

from pelvislab.tests.benchmarks.harness import Result


def run() -> list[Result]:
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6 import QtWidgets

    from pelvislab.app.gui_main import OperatorWindow

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(["bench"])
    window = OperatorWindow()
    window.resize(1366, 768)
    window.show()
    durations: list[float] = []
    original = window.refresh

    def timed_refresh() -> None:
        start = time.perf_counter()
        original()
        durations.append(time.perf_counter() - start)

    window.timer.timeout.disconnect()
    window.timer.timeout.connect(timed_refresh)
    idle_start = time.perf_counter()
    while time.perf_counter() - idle_start < 1.0:
        app.processEvents()
        time.sleep(0.005)
    idle = float(np.median(durations)) if durations else float("nan")
    durations.clear()
    with tempfile.TemporaryDirectory() as folder:
        window.subject_edit.setText("BENCH")
        window.protocol_combo.setCurrentIndex(window.protocol_combo.findText("demo"))
        window.out_edit.setText(str(Path(folder) / "bench.h5"))
        window.start_run()
        started = time.perf_counter()
        while not window.control.finished.is_set() and time.perf_counter() - started < 300:
            app.processEvents()
            if window.confirm_button.isVisible():
                window.confirm_prompt()
            time.sleep(0.002)
        app.processEvents()
        wall = time.perf_counter() - started
        steps = sum(len(v) for v in window._frf_lines.values())
        window.close()
        window.deleteLater()
        app.processEvents()
    d = np.array(durations)
    return [
        Result("UI refresh, idle window (baseline)", idle * 1e3, "ms"),
        Result("UI refresh during a run, median", float(np.median(d)) * 1e3, "ms"),
        Result("UI refresh during a run, 99th percentile", float(np.percentile(d, 99)) * 1e3,
               "ms", target="<= 50 ms"),
        Result("UI refresh during a run, maximum", float(d.max()) * 1e3, "ms",
               target="<= 50 ms"),
        Result("plot refresh rate during a run", d.size / wall, "fps", target=">= 10 fps"),
        Result("FRF lines shown live", float(steps), "lines"),
    ]
