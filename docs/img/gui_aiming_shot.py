"""Screenshot of the live echoes at a prompt (docs/img/gui-aiming.png).

The demo protocol on the simulated bench with a stationary reflection 3.5 dB stronger than
ch1's bone echo, 0.3 us before it: the automatic gate holds both, the note and the dashed
mark name the other echo (the bone's), before the operator drags the gate onto it. The
simulated bench takes its effects only in Python, so the bench factory is replaced here.
Run from the repository:

    QT_QPA_PLATFORM=offscreen .venv/bin/python docs/img/gui_aiming_shot.py \\
        docs/img/gui-aiming.png /tmp/aimshot.h5
"""

from __future__ import annotations

import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from PySide6 import QtCore, QtWidgets

import pelvislab.drivers.bench as bench_module
from pelvislab.sim_instruments import bench as sim_bench
from pelvislab.sim_instruments.effects import StaticClutter

BONE_DEPTH_M = 8.2e-3  # the simulated bench's default
CLUTTER = StaticClutter(depth_m=(BONE_DEPTH_M - 0.3e-6 * 1540.0 / 2,), level_db=(3.5,),
                        channels=(1,))


def open_bench_with_clutter(config: Any = None, **_: Any) -> Any:
    """The simulated bench with :data:`CLUTTER`."""
    return sim_bench.open_simulated_bench(config, generators="python", effects=[CLUTTER])


def main(png: Path, session: Path) -> None:
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    bench_module.open_bench = open_bench_with_clutter
    from pelvislab.app.gui_main import OperatorWindow

    app = QtWidgets.QApplication(["pelvislab"])
    window = OperatorWindow()
    window.ask_before_closing_a_run = False
    window.resize(1366, 768)
    window.show()

    def pump(condition: Callable[[], bool], timeout_s: float = 30.0) -> None:
        end = time.monotonic() + timeout_s
        while not condition() and time.monotonic() < end:
            app.processEvents(QtCore.QEventLoop.ProcessEventsFlag.AllEvents, 50)
            time.sleep(0.01)

    window.subject_edit.setText("S007")
    window.protocol_combo.setCurrentIndex(window.protocol_combo.findText("demo"))
    session.unlink(missing_ok=True)
    window.out_edit.setText(str(session))
    window.start_run()
    pump(lambda: window.aim_label.isVisible() and "another echo" in window.aim_label.text())
    shown = time.monotonic()
    pump(lambda: time.monotonic() - shown > 0.8)
    window.grab().save(str(png))
    window.control.stop("screenshot taken")
    window.control.finished.wait(10.0)


if __name__ == "__main__":
    main(Path(sys.argv[1]), Path(sys.argv[2]))
