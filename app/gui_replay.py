"""Replay of a recorded session (``pelvislab gui S.h5``): steps, echoes, traces, re-tracking,
identification, gap diagnosis and modal analysis results.

Views only: tracking, identification, the gap diagnosis and the EMA are the acquisition/model
packages' functions, run in a worker thread so the window stays responsive.
"""

from __future__ import annotations

import html
import logging
import math
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from pathlib import Path
from typing import Any

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from pelvislab.app.gui_dialogs import GuiError, alert
from pelvislab.app.gui_plots import (
    AScanPanel,
    DisplacementPanel,
    FrfPanel,
    QualityTable,
    draw_ema,
    draw_step,
    echo_trace,
)

log = logging.getLogger(__name__)


class _FrfOnlyFile:
    """An FRF-only file (``/frf`` alone, design 4.2) seen through the few parts of
    :class:`~pelvislab.acquisition.session.SessionReader` the replay uses: no steps."""

    def __init__(self, path: Path) -> None:
        from pelvislab.acquisition.frfset import read_frf

        self.path = path
        self._frf = read_frf(path)  # checked now: a bad file is refused when opened
        self.status = ("FRF-only file", "")
        self.damaged: list[str] = []

    def steps(self, include_incomplete: bool = False, with_echoes: bool = True) -> list[Any]:
        return []

    def frf(self) -> Any:
        return self._frf

    def read_step(self, name: str, with_echoes: bool = True) -> None:
        return None

    def close(self) -> None:
        pass


def display_columns(frequency_hz: np.ndarray, max_columns: int = 4000
                    ) -> tuple[np.ndarray, float, float]:
    """Columns of an image over frequency for lines at ``frequency_hz`` (ascending, Hz):
    returns (index of the line shown in each display column, low Hz, high Hz). Each line
    owns the interval between the midpoints to its neighbours (half a spacing beyond the
    first and last); display columns are as wide as the closest lines' spacing (at most
    ``max_columns``), so a zoomed grid keeps its lines where they are."""
    f = np.asarray(frequency_hz, dtype=float)
    if f.size < 2:
        at = float(f[0]) if f.size else 0.0
        return np.arange(f.size), at, at
    gaps = np.diff(f)
    edges = np.concatenate([[f[0] - gaps[0] / 2], (f[:-1] + f[1:]) / 2,
                            [f[-1] + gaps[-1] / 2]])
    low, high = float(edges[0]), float(edges[-1])
    positive = gaps[gaps > 0]
    step = float(positive.min()) if positive.size else high - low
    n = int(min(max_columns, max(f.size, np.ceil((high - low) / step))))
    centres = low + (np.arange(n) + 0.5) * (high - low) / n
    index = np.clip(np.searchsorted(edges, centres, side="right") - 1, 0, f.size - 1)
    return index, low, high


class AnalysisCancelled(Exception):
    """Raised in the worker thread, at an analysis' next progress line, once Cancel was
    pressed (or the window closed)."""


class _Worker:
    """One daemon thread running the replay's jobs in turn (a ``ThreadPoolExecutor`` of one
    worker, but whose thread the interpreter does not wait for at exit: with one, a window
    closed during a gap diagnosis left the process running, windowless, for the rest of
    it). The jobs only read the session file and compute; nothing is lost by not waiting."""

    def __init__(self) -> None:
        self._jobs: queue.Queue = queue.Queue()
        threading.Thread(target=self._loop, name="pelvislab-replay", daemon=True).start()

    def submit(self, work: Callable[[], Any]) -> Future:
        future: Future = Future()
        self._jobs.put((future, work))
        return future

    def _loop(self) -> None:
        while True:
            future, work = self._jobs.get()
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(work())
            except BaseException as exc:  # handed to the UI thread, which says it
                future.set_exception(exc)


PARAM_TABLE_MIN_WIDTH_PX = 340
"""The identification pane's parameter table before a fit fills it (px); then as wide as
its contents."""


def candidate_rows(report: dict[str, Any]) -> list[tuple[str, str, str, str, str]]:
    """The gap pane's candidate table from a diagnosis report (design 4.4): per candidate
    (effect, status, gap after, shrink, evidence), the verdict's effect first and marked
    ``named``, the others by shrink. A candidate the verdict did not name has its shrink in
    parentheses and a status saying why, as far as the report tells: within the chain's
    tolerance (``within_tolerance``), parameter updating (a null extension such as one
    damping per dashpot: its verdict is ``none``), not needed beside ``none`` (the
    reason says why), not near the noise beside ``unexplained``. An aborted demo file
    showed "100 %" for an effect whose drop was not significant, beside the verdict
    ``none``. Where ``gap_before`` is 0 the shrink is undefined (the JSON holds 0.0) and
    shows as "—"."""
    from pelvislab.model.gap_effects import NULL_EXTENSIONS

    verdict = str(report.get("verdict", ""))
    gap_before = report.get("gap_before")  # None: not said (a report built by hand)
    updating_explains = str(report.get("verdict_reason", "")).startswith(
        "parameter updating explains the data")

    def status(cand: dict[str, Any]) -> str:
        effect = cand.get("effect")
        if effect == verdict:
            return "named"
        if cand.get("within_tolerance"):
            return "within the chain's tolerance"
        if effect in NULL_EXTENSIONS:
            return ("explains it: updating, so none" if verdict == "none" and updating_explains
                    else "updating, not an effect")
        return {"none": "not needed (see the reason)",
                "unexplained": "not near the noise"}.get(verdict, f"not named ({verdict} is)")

    def number(cand: dict[str, Any], key: str) -> float:
        # a report read back from its JSON has null where the value was NaN
        value = cand.get(key)
        return float("nan") if value is None else float(value)

    def rank(cand: dict[str, Any]) -> tuple[bool, bool, float]:
        shrink = number(cand, "shrink")
        return (cand.get("effect") != verdict, not math.isfinite(shrink),
                -shrink if math.isfinite(shrink) else 0.0)

    rows = []
    for cand in sorted(report.get("candidates") or [], key=rank):
        said = status(cand)
        # undefined where gap_before is 0 (design 4.4's ratio; the JSON holds 0.0 there,
        # null in reports of sessions 40-49)
        shrink = ("—" if cand.get("shrink") is None
                  or (gap_before is not None and not float(gap_before) > 0)
                  else f"{100 * number(cand, 'shrink'):.0f} %")
        rows.append((str(cand.get("effect", "")), said, f"{number(cand, 'gap_after'):.3g}",
                     shrink if said == "named" else f"({shrink})",
                     str(cand.get("evidence") or "")))
    return rows


def identification_summary(document: dict[str, Any]) -> str:
    """One line (HTML) on an identification's JSON: converged or not and why, the misfit;
    its notes (if any) below."""
    rms = document.get("rms_residual")
    misfit = "" if rms is None else (
        f"rms residual {rms:.3g}" + (" (in noise σ)" if document.get("residual") == "std"
                                     else " (relative)"))
    if document.get("converged"):
        head = "<b>converged</b>"
    else:
        head = "<b style='color:#b71c1c'>NOT converged</b>: " + html.escape(
            str(document.get("message", "")).strip("; "))
    gain_std = document.get("gain_std") or 0.0
    calibration_std = document.get("calibration_std") or 0.0
    terms = [f"an FRF gain std of {100 * gain_std:.3g} %"] if gain_std else []
    if calibration_std:
        source = (" (bench file)" if document.get("calibration_std_source") == "bench"
                  else "")
        terms.append(f"the drive calibration's {100 * calibration_std:.3g} %{source}")
    std = ("" if document.get("method") != "frf" else
           f"; std include {' and '.join(terms)}" if terms
           else "; std: the noise's share only")
    # the command's notes (an infinite value read as not measured, no calibration
    # uncertainty stated, ...) were printed by the CLI only
    notes = "".join(f"<br>note: {html.escape(str(n))}" for n in document.get("notes", []))
    return head + (f" — {misfit}" if misfit else "") + std + notes


def _profile_cell(profiles: dict[str, Any], name: str,
                  on_bound: list[str] | tuple[str, ...] = ()) -> QtWidgets.QTableWidgetItem:
    """The identification table's profile cell of ``name``: its profile's 95 % interval
    (or what else it found, in red when it went below the fit) with the whole finding as a
    tooltip; empty for a parameter not profiled (well determined, or on the bound of its
    range: ``on_bound``, the JSON's)."""
    from pelvislab.app.commands.identify import profile_said

    if name not in profiles:
        cell = QtWidgets.QTableWidgetItem("")
        cell.setToolTip("not profiled: on the bound of its range (std null), no minimum to "
                        "walk from" if name in on_bound else
                        "not profiled: its std is under 10 % of its value")
        return cell
    prof = profiles[name]
    whole = profile_said(prof)
    if prof is None:
        text = "not run"
    elif prof["lower_minimum"] is not None:
        text = f"LOWER minimum at {prof['lower_minimum']['value']:.3g}"
    else:
        text = whole.removeprefix("95 % ").split(";")[0]
    cell = QtWidgets.QTableWidgetItem(text)
    cell.setToolTip(f"profile likelihood, the chain's gains held: {whole}"
                    + ("" if prof is None else f" ({prof['fits']} fits)"))
    if prof is not None and prof["lower_minimum"] is not None:
        cell.setForeground(QtGui.QColor("#b71c1c"))
    return cell


def _summary_page(text: str) -> tuple[QtWidgets.QWidget, QtWidgets.QVBoxLayout,
                                      QtWidgets.QLabel]:
    """A result page: a vertical layout that starts with a word-wrapped summary line."""
    page = QtWidgets.QWidget()
    layout = QtWidgets.QVBoxLayout(page)
    summary = QtWidgets.QLabel(text)
    summary.setWordWrap(True)
    layout.addWidget(summary)
    return page, layout, summary


class ReplayView(QtWidgets.QWidget):
    """Browse a session file; re-track a step with other settings; show analysis results."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.reader: Any = None
        self.path: Path | None = None
        self.steps: list[Any] = []
        self._executor = _Worker()
        # set by Cancel (or closing the window): the analyses whose progress callback was
        # made before it raise AnalysisCancelled at their next progress line; Cancel puts
        # a fresh one here for those started after it
        self._cancel = threading.Event()
        self._cancellable: set[Future] = set()  # pending jobs that Cancel stops
        # (job, done, what, button, the file it works on)
        self._pending: list[tuple[Future, Callable[[Any], None], str,
                                  QtWidgets.QPushButton | None, Path | None]] = []
        # the running job's latest progress line, set from the worker thread and shown
        # by the poll timer (a str assignment: no lock needed)
        self._progress_note = ""
        # offscreen, what an analysis' failure dialog would have said (the command ends
        # with it as its error after the screenshot)
        self.headless_failures: list[str] = []
        self._build()
        self._poll = QtCore.QTimer(self)
        self._poll.setInterval(100)
        self._poll.timeout.connect(self._collect)
        self._poll.start()

    # ------------------------------------------------------------------ layout
    def _build(self) -> None:
        layout = QtWidgets.QHBoxLayout(self)
        layout.setContentsMargins(2, 2, 2, 2)
        left = QtWidgets.QVBoxLayout()
        self.file_label = QtWidgets.QLabel("no session open")
        self.file_label.setWordWrap(True)
        left.addWidget(self.file_label)
        open_button = QtWidgets.QPushButton("Open session…")
        open_button.clicked.connect(self._browse)
        left.addWidget(open_button)
        self.step_list = QtWidgets.QListWidget()
        self.step_list.currentRowChanged.connect(self.show_step)
        left.addWidget(self.step_list, 1)

        retrack = QtWidgets.QGroupBox("Re-track selected step")
        form = QtWidgets.QFormLayout(retrack)
        from pelvislab.acquisition.tracking import ESTIMATORS, TrackingOptions

        self.estimator_combo = QtWidgets.QComboBox()
        self.estimator_combo.addItems(list(ESTIMATORS))
        self.estimator_combo.setCurrentText(TrackingOptions().estimator)
        form.addRow("estimator", self.estimator_combo)
        self.gate_start = QtWidgets.QSpinBox()
        self.gate_stop = QtWidgets.QSpinBox()
        for box in (self.gate_start, self.gate_stop):
            box.setRange(0, 100_000)
            box.setSpecialValueText("auto")
        form.addRow("gate start (sample)", self.gate_start)
        form.addRow("gate stop (sample)", self.gate_stop)
        self.retrack_button = QtWidgets.QPushButton("Re-track")
        self.retrack_button.setToolTip(
            "a channel's gate: the one dragged on its A-scan, else the sample boxes, else "
            "the one set at acquisition (operator or protocol), else the strongest echo")
        self.retrack_button.clicked.connect(self.retrack_step)
        form.addRow(self.retrack_button)
        self.dragged_gates_label = QtWidgets.QLabel("")
        self.dragged_gates_label.setWordWrap(True)
        form.addRow(self.dragged_gates_label)
        left.addWidget(retrack)

        analysis = QtWidgets.QGroupBox("Analysis")
        analysis_layout = QtWidgets.QVBoxLayout(analysis)
        self.identify_button = QtWidgets.QPushButton("Identify parameters")
        self.identify_button.clicked.connect(self.run_identification)
        self.gap_button = QtWidgets.QPushButton("Diagnose sim-to-real gap")
        self.gap_button.clicked.connect(self.run_gap)
        self.ema_button = QtWidgets.QPushButton("Modal analysis (EMA)")
        self.ema_button.clicked.connect(self.run_ema)
        analysis_layout.addWidget(self.identify_button)
        # identify --gain-std: without it the std are the noise's share only (1.9-13x too
        # small on the simulated chain's sessions, docs/identification.md)
        gain_row = QtWidgets.QHBoxLayout()
        gain_label = QtWidgets.QLabel("FRF gain std")
        self.gain_std_box = QtWidgets.QDoubleSpinBox()
        self.gain_std_box.setRange(0.0, 49.9)
        self.gain_std_box.setDecimals(2)
        self.gain_std_box.setSingleStep(0.1)
        self.gain_std_box.setSuffix(" %")
        from pelvislab.app.commands.identify import DEFAULT_GAIN_STD

        self.gain_std_box.setValue(100.0 * DEFAULT_GAIN_STD)
        tip = ("Standard uncertainty of each FRF's gain (a chain error common to its lines: "
               "speed of sound, transducer angle), in the fit's weights and the identified "
               "parameters' std; 0: the std are the noise's share only (identify --gain-std; "
               "default the chain's ±0.5 % tolerance)")
        gain_label.setToolTip(tip)
        self.gain_std_box.setToolTip(tip)
        gain_row.addWidget(gain_label)
        gain_row.addWidget(self.gain_std_box, 1)
        analysis_layout.addLayout(gain_row)
        # identify --profile weak: the linearised std is least trusted where it is wide
        # (the thesis' untrusted optimiser; docs/identification.md)
        self.profile_box = QtWidgets.QCheckBox("profile weak parameters")
        self.profile_box.setToolTip(
            "also walk each weak parameter (std at least 10 % of its value) out from the "
            "fit, refitting the others: its 95 % interval without the linearisation, and "
            "any second or lower minimum (a lower one is fitted again from); seconds to a "
            "minute more (identify --profile weak)")
        analysis_layout.addWidget(self.profile_box)
        analysis_layout.addWidget(self.gap_button)
        analysis_layout.addWidget(self.ema_button)
        self.analysis_status = QtWidgets.QLabel("")
        self.analysis_status.setWordWrap(True)
        analysis_layout.addWidget(self.analysis_status)
        # an identification or a gap diagnosis takes seconds to a minute: it can be
        # stopped (at its next progress line: a stage of the diagnosis, a start of the fit)
        self.cancel_button = QtWidgets.QPushButton("Cancel analysis")
        self.cancel_button.setToolTip(
            "stop the running identification or gap diagnosis at its next stage; "
            "nothing is shown of it")
        self.cancel_button.setVisible(False)
        self.cancel_button.clicked.connect(self.cancel_analysis)
        analysis_layout.addWidget(self.cancel_button)
        left.addWidget(analysis)
        left_widget = QtWidgets.QWidget()
        left_widget.setLayout(left)
        left_widget.setFixedWidth(250)
        layout.addWidget(left_widget)

        self.tabs = QtWidgets.QTabWidget()
        layout.addWidget(self.tabs, 1)
        # what the file holds (`pelvislab session info`), read when the tab is first shown
        # for a file: runs and how they ended, steps against the plan, tracking per channel
        self.file_info = QtWidgets.QPlainTextEdit()
        self.file_info.setReadOnly(True)
        self.file_info.setLineWrapMode(QtWidgets.QPlainTextEdit.LineWrapMode.WidgetWidth)
        self._file_info_for: Path | None = None
        step_page = QtWidgets.QWidget()
        grid = QtWidgets.QGridLayout(step_page)
        grid.setContentsMargins(2, 2, 2, 2)
        self.ascan = AScanPanel()
        # drag a channel's gate, then Re-track: per channel, kept for the steps of its setup
        self.ascan.set_gates_editable(True)
        self.ascan.gate_edited.connect(self._gate_dragged)
        self._dragged_gates: dict[tuple[str, str], tuple[int, int]] = {}
        self.displacement = DisplacementPanel()
        self.quality = QualityTable()
        self.step_info = QtWidgets.QLabel()
        grid.addWidget(self.step_info, 0, 0, 1, 2)
        grid.addWidget(self.ascan, 1, 0)
        grid.addWidget(self.displacement, 1, 1)
        grid.addWidget(self.quality, 2, 0, 1, 2)
        self.tabs.addTab(step_page, "Step")
        self.frf = FrfPanel()
        self.tabs.addTab(self.frf, "FRFs")

        # the verdict on the fit first: the thesis' optimiser could not be trusted, and a
        # table of values alone reads as a result (review of session 36: the pane never
        # said "not converged")
        ident_page, ident_outer, self.ident_summary = _summary_page(
            "run the identification to see the parameters")
        self.ident_summary.setTextFormat(QtCore.Qt.TextFormat.RichText)
        ident_layout = QtWidgets.QHBoxLayout()
        ident_outer.addLayout(ident_layout, 1)
        self.param_table = QtWidgets.QTableWidget(0, 3)
        self.param_table.setHorizontalHeaderLabels(("parameter", "value", "std"))
        self.param_table.verticalHeader().setVisible(False)
        self.param_table.setFixedWidth(PARAM_TABLE_MIN_WIDTH_PX)
        self.param_table.horizontalHeader().setSectionResizeMode(
            0, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        self.ident_frf = FrfPanel()
        ident_layout.addWidget(self.param_table)
        ident_layout.addWidget(self.ident_frf, 1)
        self.tabs.addTab(ident_page, "Identification")

        gap_page, gap_layout, self.gap_summary = _summary_page(
            "run the diagnosis to see where model and data differ")
        self.residual_plot = pg.PlotWidget(title="Normalised residual: channel x frequency")
        self.residual_plot.setLabel("bottom", "frequency", units="Hz")
        self.residual_plot.setLabel("left", "channel (output/input)")
        self.residual_image = pg.ImageItem()
        self.residual_image.setColorMap(pg.colormap.get("viridis"))
        self.residual_plot.addItem(self.residual_image)
        self.residual_bar = pg.ColorBarItem(colorMap=pg.colormap.get("viridis"),
                                            label="|residual| / σ", interactive=False)
        self.residual_bar.setImageItem(self.residual_image,
                                       insert_in=self.residual_plot.getPlotItem())
        gap_layout.addWidget(self.residual_plot, 2)
        self.candidate_table = QtWidgets.QTableWidget(0, 5)
        self.candidate_table.setHorizontalHeaderLabels(
            ("effect", "verdict", "gap after", "shrink", "evidence"))
        self.candidate_table.horizontalHeader().setStretchLastSection(True)
        for column in (0, 1):
            self.candidate_table.horizontalHeader().setSectionResizeMode(
                column, QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        self.candidate_table.verticalHeader().setVisible(False)
        gap_layout.addWidget(self.candidate_table, 1)
        self.tabs.addTab(gap_page, "Gap diagnosis")
        self._build_modes_page()

    def _build_modes_page(self) -> None:
        """EMA results: summed FRF over the stabilisation diagram, and the modes table."""
        page, layout, self.ema_summary = _summary_page("run the modal analysis to see the modes")
        self.ema_sum_plot = pg.PlotWidget(title="Sum of |H| over the FRFs")
        # in dB: pyqtgraph's log axis labels its minor ticks, which overlap over the one or
        # two decades a summed FRF spans
        self.ema_sum_plot.setLabel("left", "Σ|H| (dB re 1 m/N)")
        self.ema_sum_plot.showGrid(x=True, y=True, alpha=0.3)
        self.stab_plot = pg.PlotWidget(
            title="Stabilisation diagram (grey new, blue stable frequency, green + damping, "
            "red all)")
        self.stab_plot.setLabel("bottom", "frequency", units="Hz")
        self.stab_plot.setLabel("left", "model order")
        self.stab_plot.setXLink(self.ema_sum_plot)
        layout.addWidget(self.ema_sum_plot, 3)
        layout.addWidget(self.stab_plot, 4)
        self.mode_table = QtWidgets.QTableWidget(0, 6)
        self.mode_table.setHorizontalHeaderLabels(
            ("mode", "frequency (Hz)", "± std (Hz)", "damping ratio (%)", "± std (%)",
             "complexity"))
        self.mode_table.horizontalHeader().setStretchLastSection(True)
        self.mode_table.horizontalHeader().setSectionResizeMode(
            QtWidgets.QHeaderView.ResizeMode.ResizeToContents)
        self.mode_table.verticalHeader().setVisible(False)
        self.mode_table.setMaximumHeight(150)
        # manual selection, as in the stabilisation diagrams of ME'scope or SDT: click the
        # stable poles of a column, then fit those (pelvislab ema --frequencies)
        picks = QtWidgets.QHBoxLayout()
        self.pick_label = QtWidgets.QLabel("click poles in the diagram to pick modes by hand")
        self.pick_label.setWordWrap(True)  # the row fits the 1366 px of the operator window
        self.fit_picks_button = QtWidgets.QPushButton("Fit picked poles")
        self.fit_picks_button.clicked.connect(self.fit_picked_poles)
        self.fit_picks_button.setEnabled(False)
        self.clear_picks_button = QtWidgets.QPushButton("Clear picks")
        self.clear_picks_button.clicked.connect(self.clear_picks)
        self.refine_picks = QtWidgets.QCheckBox("refine poles (every mode selected)")
        self.refine_picks.setToolTip(
            "polish the poles (automatic or picked) by the pole/residue fit, which removes "
            "p-LSCF's damping bias and gives their uncertainties; only when every mode of "
            "the band is selected (a mode left out pulls the refined poles)")
        picks.addWidget(self.pick_label, 1)
        picks.addWidget(self.refine_picks)
        picks.addWidget(self.fit_picks_button)
        picks.addWidget(self.clear_picks_button)
        layout.addLayout(picks)
        layout.addWidget(self.mode_table)
        self.picked_hz: list[float] = []
        self._pick_lines: list[Any] = []
        self.modes_page = page
        self.tabs.addTab(page, "Modes")
        self.tabs.addTab(self.file_info, "File")
        self.tabs.currentChanged.connect(self._tab_shown)

    # ------------------------------------------------------------------ file
    def _browse(self) -> None:
        path, _ = QtWidgets.QFileDialog.getOpenFileName(self, "Session file", "",
                                                        "Session (*.h5)")
        if not path:
            return
        try:
            self.open_session(Path(path))
        except Exception as exc:
            alert(self, "Cannot open session", str(exc))

    def open_session(self, path: Path) -> None:
        """Open ``path``, a session or an FRF-only file (design 4.2; its FRFs and the
        analyses, no steps); raises with a one-line reason for a bad file."""
        from pelvislab.acquisition.session import SessionFileError, SessionReader

        try:
            reader: Any = SessionReader(path)
        except SessionFileError as exc:
            if exc.schema is None:  # unreadable, in use, another version
                raise
            # not a session: an FRF-only file, which identify, ema and gap read too; design
            # 4.2 puts its schema on /frf, so another tool's file may have none at the root
            if exc.schema == "pelvislab-frf":
                reader = _FrfOnlyFile(Path(path))  # a bad one: its own reason
            else:
                try:
                    reader = _FrfOnlyFile(Path(path))
                except Exception:
                    raise exc from None  # neither: the session reader's reason
        try:
            steps = list(reader.steps(include_incomplete=True, with_echoes=False))
        except Exception:
            reader.close()
            raise
        self.close_session()
        self.reader, self.path, self.steps = reader, Path(path), steps
        self._file_info_for = None
        self.file_info.setPlainText("")
        self._tab_shown(self.tabs.currentIndex())  # the File tab may be the one shown
        self._dragged_gates = {}
        self._show_dragged_gates()
        status, reason = reader.status
        # "running" in a file nobody writes: the process ended without closing it; one that
        # opens while its writer lives (HDF5 file locking off) is still being written
        shown = status
        if status == "running":
            from pelvislab.acquisition.session_info import last_run_writer_alive

            alive = last_run_writer_alive(reader.handle, path) \
                if hasattr(reader, "handle") else None
            shown = ("still being written (its process is running: these are the steps so "
                     "far)" if alive else "did not end (the process was killed?)")
        text = f"{Path(path).name}: {len(steps)} steps, run {shown}"
        if isinstance(reader, _FrfOnlyFile):
            text = f"{Path(path).name}: FRF-only file (no steps to replay)"
        if reason:
            text += f" ({reason})"
        if getattr(reader, "outputs_confirmed_off", None) is False:
            text += "; outputs NOT CONFIRMED OFF at the end of a run"
        if reader.damaged:
            text += f"; {len(reader.damaged)} damaged step(s) skipped"
        unstated = self._bone_unstated(reader, steps)
        if unstated:
            # a session written from design 4.2 alone: reprocess would write these points
            # on no modelled bone, and identify and gap leave such points out (reprocess
            # said so; the replay did not: session 41's note)
            named = ", ".join(f"{prefix} {name}" for prefix, name in unstated)
            text += (f"; bone unknown for {named} (not in the landmark catalogue, no "
                     f"output_bone/input_bone in the steps): reprocess writes them on no "
                     f"modelled bone, which identify and gap leave out")
        self.file_label.setText(text)
        self.step_list.clear()
        for step in steps:
            flag = "" if step.status == "complete" else f"  [{step.status}]"
            self.step_list.addItem(
                f"{step.index:4d}  {step.setup}  {step.frequency_hz:g} Hz{flag}")
        self._show_frf()
        self._clear_results()  # the analyses shown were the previous file's
        self.clear_picks()  # picks belong to the previous file's diagram
        if steps:
            self.step_list.setCurrentRow(0)
        else:
            self.tabs.setCurrentWidget(self.frf)

    def _tab_shown(self, index: int) -> None:
        """Fill the File tab the first time it is shown for the open file."""
        if self.tabs.widget(index) is not self.file_info or self.path is None \
                or self._file_info_for == self.path:
            return
        from pelvislab.acquisition.session_info import session_info
        from pelvislab.app.commands.session import info_text

        self._file_info_for = self.path
        try:
            text = info_text(session_info(self.path))
        except Exception as exc:  # a summary only: the file's own errors show elsewhere
            text = f"no summary of {self.path}: {exc}"
        self.file_info.setPlainText(text)

    @staticmethod
    def _bone_unstated(reader: Any, steps: list[Any]) -> list[tuple[str, str]]:
        """The points reprocess would write on no modelled bone because nothing gave their
        bone (its note's points: the complete steps' FRF layout), none when the file
        stores /frf (its bones are the file's word) or is FRF-only."""
        if not getattr(reader, "bone_unstated", None) or reader.frf_layout() is not None:
            return []
        from pelvislab.acquisition.runner import bone_unstated_points
        from pelvislab.acquisition.session import frf_from_steps

        done = [s for s in steps if s.status == "complete"]
        if not done:
            return []
        try:
            return bone_unstated_points(frf_from_steps(done), reader.bone_unstated)
        except Exception:  # the label is a courtesy: a file reprocess would refuse says so there
            return []

    def _clear_results(self) -> None:
        """Empty the identification, gap and modes panes."""
        self.param_table.setRowCount(0)
        self.ident_frf.clear_curves()
        self.ident_summary.setText("run the identification to see the parameters")
        self.gap_summary.setText("run the diagnosis to see where model and data differ")
        self.residual_image.clear()
        self.candidate_table.setRowCount(0)
        self.ema_summary.setText("run the modal analysis to see the modes")
        self.ema_sum_plot.clear()
        self.stab_plot.clear()
        self._pick_lines = []
        self.mode_table.setRowCount(0)

    def close_session(self) -> None:
        """Close the open file, if any."""
        if self.reader is not None:
            self.reader.close()
        self.reader, self.path, self.steps = None, None, []

    def _show_frf(self) -> None:
        self.frf.clear_curves()
        try:
            frf = self.reader.frf()
        except Exception as exc:
            self.file_label.setText(self.file_label.text() + f"; no FRFs ({exc})")
            return
        k = 0
        for i, out in enumerate(frf.outputs.name):
            for j, inp in enumerate(frf.inputs.name):
                column = frf.H[:, i, j]
                if np.isfinite(column).any():
                    self.frf.show_measured(f"{out} / {inp}", k, frf.frequency_hz, column)
                    k += 1

    # ------------------------------------------------------------------ steps
    def current_step(self, with_echoes: bool = True) -> Any:
        """The selected step, read from the file (with its raw echoes)."""
        row = self.step_list.currentRow()
        if self.reader is None or not 0 <= row < len(self.steps):
            return None
        name = f"{self.steps[row].index:06d}"
        return self.reader.read_step(name, with_echoes=with_echoes)

    def show_step(self, row: int) -> None:
        """Draw the selected step's last echo, displacement trace and quality."""
        try:
            step = self.current_step()
        except Exception as exc:
            self.step_info.setText(f"step unreadable: {exc}")
            return
        if step is None:
            return
        labels = [f"{ch.name} → {ch.output.name}" for ch in step.channels]
        self.ascan.set_channels(labels)
        self.displacement.set_channels(labels)
        self.step_info.setText(
            f"step {step.index}: setup {step.setup}, {step.frequency_hz:g} Hz, input "
            f"{step.input.name}, status {step.status}, force phasor "
            f"{abs(step.force_phasor_n):.3g} N")
        draw_step(self.ascan, self.displacement, self.quality, step, 0)

    def tracking_options(self) -> Any:
        """Tracking options from the re-track controls."""
        from pelvislab.acquisition.tracking import TrackingOptions

        gate = None
        if self.gate_start.value() and self.gate_stop.value() > self.gate_start.value():
            gate = (self.gate_start.value(), self.gate_stop.value())
        return TrackingOptions(gate=gate, estimator=self.estimator_combo.currentText())

    def channel_gate(self, step: Any, channel: Any) -> tuple[tuple[int, int] | None, str]:
        """The gate a re-track uses for ``channel`` of ``step`` and where it comes from:
        dragged on its A-scan, the sample boxes (every channel), the one set at acquisition
        by the operator or the protocol (as ``pelvislab reprocess`` keeps it), else
        automatic (None)."""
        dragged = self._dragged_gates.get((step.setup, channel.name))
        if dragged is not None:
            return dragged, "dragged"
        boxes = self.tracking_options().gate
        if boxes is not None:
            return boxes, "boxes"
        q = channel.quality or {}
        source = q.get("gate_source")
        if source in ("operator", "protocol") and "gate_start" in q and "gate_stop" in q:
            return (int(q["gate_start"]), int(q["gate_stop"])), f"{source}'s"
        return None, "auto"

    def _gate_dragged(self, row: int, start_s: float, stop_s: float) -> None:
        try:
            step = self.current_step(with_echoes=False)
        except Exception:
            return
        if step is None or row >= len(step.channels):
            return
        ch = step.channels[row]
        gate = (int(round((start_s - ch.delay_s) * ch.sample_rate_hz)),
                int(round((stop_s - ch.delay_s) * ch.sample_rate_hz)))
        self._dragged_gates[(step.setup, ch.name)] = gate
        self._show_dragged_gates()

    def clear_dragged_gates(self) -> None:
        """Forget the gates dragged on the A-scans."""
        self._dragged_gates = {}
        self._show_dragged_gates()

    def _show_dragged_gates(self) -> None:
        self.dragged_gates_label.setText(
            "dragged (Re-track to apply): " + ", ".join(
                f"{setup} {name} {a}-{b}" for (setup, name), (a, b)
                in sorted(self._dragged_gates.items())) if self._dragged_gates else
            "drag a gate on an A-scan to re-track that channel in it")

    def retrack_step(self) -> None:
        """Re-run echo tracking on the selected step with the chosen options (worker thread)."""
        step = self.current_step()
        if step is None:
            return
        options = self.tracking_options()
        gates = [self.channel_gate(step, ch) for ch in step.channels]

        def work() -> list[Any]:
            from dataclasses import replace

            from pelvislab.acquisition.tracking import track_echoes

            return [track_echoes(ch.codes, ch.trigger_offset_s, ch.sample_rate_hz,
                                 ch.speed_of_sound_m_s, ch.volts_per_count,
                                 replace(options, gate=gate))
                    for ch, (gate, _) in zip(step.channels, gates, strict=True)]

        def done(results: list[Any]) -> None:
            rows = []
            for i, (ch, res) in enumerate(zip(step.channels, results, strict=True)):
                self.displacement.show_trace(
                    i, np.arange(res.displacement_m.size) / ch.prf_hz, res.displacement_m)
                gate = (ch.delay_s + res.gate[0] / ch.sample_rate_hz,
                        ch.delay_s + res.gate[1] / ch.sample_rate_hz)
                self.ascan.show_echo(i, *echo_trace(ch, 0), gate,
                                     operator=gates[i][1] != "auto")
                rows.append({
                    "channel": ch.name, "landmark": ch.output.name,
                    "correlation": float(np.median(res.correlation)),
                    "snr_db": float(np.median(res.snr_db)),
                    "peak_hops": int(np.sum(res.peak_hops)), "lost": int(np.sum(res.lost)),
                })
            self.quality.show_quality(rows)
            base = self.step_info.text().split(" [re-tracked")[0]
            used = ", ".join(
                f"{ch.name} {'auto' if gate is None else f'{gate[0]}-{gate[1]}'}"
                + ("" if source == "auto" else f" ({source})")
                for ch, (gate, source) in zip(step.channels, gates, strict=True))
            self.step_info.setText(f"{base} [re-tracked: {options.estimator}, gates {used}]")

        self.submit(work, done, "re-tracking")

    # ------------------------------------------------------------------ analysis
    def run_identification(self) -> None:
        """Identify the model parameters from the session's /frf (worker thread)."""
        if self.path is None:
            return
        path = self.path
        gain_std = self.gain_std_box.value() / 100.0
        profile = ["weak"] if self.profile_box.isChecked() else None
        note = self._progress_for("identification")

        def work() -> Any:
            from pelvislab.app.commands.identify import identify_file

            return identify_file(path, gain_std=gain_std, progress=note, profile=profile)

        self.submit(work, self.show_identification, "identification", self.identify_button,
                    cancellable=True)

    def show_identification(self, report: Any) -> None:
        """Parameters with their standard errors; measured vs model FRFs."""
        from pelvislab.app.commands.identify import parameter_unit, undetermined

        document = report.to_json()
        self.ident_summary.setText(identification_summary(document))
        params = document.get("parameters", {})
        profiles = document.get("profile")
        self.param_table.setColumnCount(3 if profiles is None else 4)
        self.param_table.setHorizontalHeaderLabels(("parameter", "value", "std",
                                                    "profile 95 %"))
        self.param_table.setRowCount(len(params))
        units = document.get("units", {})  # by prefix: m_ kg, k_ N/m, c_ N s/m, f_ 1
        for r, (name, entry) in enumerate(sorted(params.items())):
            unit = parameter_unit(name, units)
            label = f"{name} ({unit})" if unit and unit != "1" else name
            self.param_table.setItem(r, 0, QtWidgets.QTableWidgetItem(label))
            self.param_table.setItem(r, 1, QtWidgets.QTableWidgetItem(f"{entry['value']:.4g}"))
            std = entry.get("std")
            cell = QtWidgets.QTableWidgetItem("" if std is None else f"{std:.2g}")
            interval = entry.get("interval_95")
            if undetermined(entry):
                cell.setToolTip("undetermined: std above the value (the data do not "
                                "determine it)")
            elif interval:  # a weak parameter's is a factor, not value +- 2 std
                cell.setToolTip(f"95 % interval {interval[0]:.3g} to {interval[1]:.3g}"
                                + ("" if name.startswith("f_") else
                                   " (a factor either way: the fit runs in log p)"))
            self.param_table.setItem(r, 2, cell)
            if profiles is not None:
                self.param_table.setItem(r, 3, _profile_cell(
                    profiles, name, document.get("on_bound") or ()))
        # as wide as its contents (the std column sat behind a horizontal scrollbar)
        table = self.param_table
        table.resizeColumnsToContents()
        width = sum(table.columnWidth(c) for c in range(table.columnCount()))
        width += 2 * table.frameWidth() + table.verticalScrollBar().sizeHint().width()
        table.setFixedWidth(width)
        self.ident_frf.clear_curves()
        frf = getattr(report, "frf", None)
        model_H = getattr(report, "model_H", None)
        if frf is not None and model_H is not None:
            k = 0
            for i, out in enumerate(frf.outputs.name):
                for j, inp in enumerate(frf.inputs.name):
                    if np.isfinite(frf.H[:, i, j]).any():
                        self.ident_frf.show_measured(f"{out} / {inp}", k, frf.frequency_hz,
                                                     frf.H[:, i, j])
                        self.ident_frf.show_model(f"model {out} / {inp}", frf.frequency_hz,
                                                  model_H[:, i, j])
                        k += 1
        self.tabs.setCurrentIndex(2)

    def run_gap(self) -> None:
        """Run the sim-to-real gap diagnosis on the session's /frf (worker thread)."""
        if self.path is None:
            return
        path = self.path
        note = self._progress_for("gap diagnosis")

        def work() -> Any:
            from pelvislab.app.commands.gap import diagnose_file

            return diagnose_file(path, progress=note)

        # a diagnosis takes about a minute here (serial in the worker thread): the
        # stages' progress lines show where it is
        self.submit(work, self.show_gap, "gap diagnosis", self.gap_button, cancellable=True)

    def _progress_for(self, what: str) -> Callable[[str], None]:
        """The progress callback of an analysis (worker thread): its line shown under the
        buttons, and the point where Cancel stops it."""

        # this analysis' own flag: a Cancel pressed for an earlier one stopped an analysis
        # started after it, at its first progress line (review, session 43)
        cancel = self._cancel

        def note(message: str) -> None:
            if cancel.is_set():
                raise AnalysisCancelled(what)
            self._progress_note = f"{what}: {message}"

        return note

    def cancel_analysis(self) -> None:
        """Stop the identification or gap diagnosis under way (and one queued behind it) at
        its next progress line; an analysis started after this runs."""
        running = [what for future, _, what, *_ in self._pending
                   if future in self._cancellable]
        if not running:
            return
        self._cancel.set()
        self._cancel = threading.Event()  # for the analyses started from now on
        self._cancellable.clear()
        self.cancel_button.setEnabled(False)
        self.analysis_status.setText(
            f"cancelling the {' and the '.join(running)} "
            f"({'it stops' if len(running) == 1 else 'each stops'} at its next stage)…")

    def shutdown(self) -> None:
        """The window closes: the running analysis stops at its next progress line, the
        queued ones never start (the worker thread is not waited for)."""
        self._cancel.set()
        for future, *_ in self._pending:
            future.cancel()
        self._pending.clear()

    def show_gap(self, result: Any) -> None:
        """Residual map, verdict and candidate effects ranked by shrink (design 4.4)."""
        report = result.to_json()
        verdict = report.get("verdict", "?")
        where = report.get("where", {})
        bands = ", ".join(f"{b['lo_hz']:g}–{b['hi_hz']:g} Hz ({100 * b['share']:.0f} %)"
                          for b in where.get("bands", [])[:3])
        outputs = ", ".join(f"{o['name']} ({100 * o['share']:.0f} %)"
                            for o in where.get("outputs", [])[:3])
        # the reason says why (a verdict 'none' after a large base gap needs it: the
        # calibration null fitted as a whole can explain it)
        bones = ", ".join(f"{b['bone'] or '(no bone)'} ({100 * b['share']:.0f} %)"
                          for b in where.get("bones", [])[:3])
        reason = html.escape(str(report.get("verdict_reason", "")))
        # what the data cannot exclude (a `none` means "not needed", not "absent":
        # parameter updating can absorb an effect)
        ranges = "; ".join(
            f"{html.escape(str(r['effect']))} {html.escape(str(r['parameter']))} "
            f"{r['low']:.3g} … {r['high']:.3g}" + (" (0 inside)" if r["null_inside"] else "")
            for r in report.get("not_excluded") or [])
        # e.g. a pick-up on the bed frame (bone ""): left out of the shares, said here
        notes = "; ".join(html.escape(str(n)) for n in report.get("notes") or [])
        gap_before = report.get("gap_before")
        gap_text = "?" if gap_before is None else f"{gap_before:.3g}"
        if gap_before == 0:
            gap_text += " (at the noise level: no shrink can be measured)"
        self.gap_summary.setText(
            f"<b>verdict: {verdict}</b> — gap before {gap_text}."
            f" Largest residual in {bands or '—'}; outputs {outputs or '—'};"
            f" bones {bones or '—'}."
            + (f"<br><small>{reason}</small>" if reason else "")
            + (f"<br><small>not excluded by the data: {ranges}</small>" if ranges else "")
            + (f"<br><small>note: {notes}</small>" if notes else ""))
        residual = getattr(result, "residual_map", None)
        if residual is not None:
            # NaN (not measured) stays NaN: drawn blank, not as a residual of 0
            image = np.asarray(residual, dtype=float)
            finite = image[np.isfinite(image)]
            top = float(np.percentile(finite, 99)) if finite.size else 1.0
            frequency = np.asarray(result.frequency_hz, dtype=float)
            # each line's column over its own frequency interval: spread evenly, a zoomed
            # grid's 173.75 Hz column sat at 109 Hz (replay review, session 36)
            columns, low_hz, high_hz = display_columns(frequency)
            # ImageItem's first axis is x: transpose rows x frequency to frequency x rows.
            self.residual_image.setImage(image[:, columns].T, autoLevels=False)
            self.residual_bar.setLevels((0.0, max(top, 1e-12)))
            if high_hz > low_hz:
                self.residual_image.setRect(QtCore.QRectF(
                    low_hz, 0, high_hz - low_hz, image.shape[0]))
            labels = list(getattr(result, "row_labels", []))
            axis = self.residual_plot.getAxis("left")
            axis.setTicks([[(i + 0.5, text) for i, text in enumerate(labels)]])
        rows = candidate_rows(report)
        self.candidate_table.setRowCount(len(rows))
        for r, values in enumerate(rows):
            for c, text in enumerate(values):
                item = QtWidgets.QTableWidgetItem(text)
                item.setToolTip(text)  # the evidence is cut at two lines a row
                if values[1] != "named":  # not the verdict: greyed, its shrink in ( )
                    item.setForeground(QtCore.Qt.GlobalColor.gray)
                self.candidate_table.setItem(r, c, item)
        self.tabs.setCurrentIndex(3)

    def run_ema(self) -> None:
        """Experimental modal analysis of the session's /frf (worker thread), as
        ``pelvislab ema`` does it (``--refine`` when the box is ticked)."""
        if self.path is None:
            return
        path = self.path

        refine = self.refine_picks.isChecked()

        def work() -> Any:
            from pelvislab.app.commands.ema import ema_file

            return ema_file(path, refine=refine)

        self.submit(work, self.show_ema, "modal analysis", self.ema_button)

    def show_ema(self, outcome: Any) -> None:
        """Modes (frequency and damping with their uncertainties), the stabilisation diagram
        over the summed FRF, a line at each mode."""
        from pelvislab.model.ema import pole_frequency_damping

        frf, result = outcome
        self.ema_sum_plot.clear()
        self.stab_plot.clear()
        f = np.asarray(result.fit_frequency_hz, dtype=float)
        self._pick_lines = []  # the plots were cleared
        self._show_picks()
        for item in draw_ema(self.ema_sum_plot.getPlotItem(), self.stab_plot.getPlotItem(),
                             result):
            item.sigPointsClicked.connect(self._pole_clicked)
        rows = [(str(r + 1), result.frequency_hz[r], result.frequency_std_hz[r],
                 result.damping_ratio[r], result.damping_ratio_std[r], result.complexity[r])
                for r in range(result.frequency_hz.size)]
        f_res, z_res = pole_frequency_damping(result.residual_poles)
        rows += [("residual", fr, np.nan, zr, np.nan, np.nan)
                 for fr, zr in zip(f_res, z_res, strict=True)]

        def text(value: float, fmt: str) -> str:
            return format(value, fmt) if np.isfinite(value) else "—"

        self.mode_table.setRowCount(len(rows))
        for r, (name, fr, f_sd, zr, z_sd, complexity) in enumerate(rows):
            values = (name, text(fr, ".3f"), text(f_sd, ".2g"), text(100 * zr, ".4g"),
                      text(100 * z_sd, ".2g"), text(complexity, ".3f"))
            for c, value in enumerate(values):
                self.mode_table.setItem(r, c, QtWidgets.QTableWidgetItem(value))
        notes = "; ".join(html.escape(n) for n in result.notes)
        self.ema_summary.setText(
            f"<b>{result.frequency_hz.size} mode(s)</b> in {f.min():g}–{f.max():g} Hz "
            f"({f.size} lines, {len(frf.outputs)} x {len(frf.inputs)} FRFs), relative fit "
            f"error {result.fit_error():.3g}."
            + (" Poles refined; their uncertainties assume noise independent between lines "
               "and FRFs." if np.isfinite(result.damping_ratio_std).any() else
               " Poles from p-LSCF (tick <i>refine poles</i> for the pole/residue fit and "
               "uncertainties).")
            + (f"<br><small>{notes}</small>" if notes else ""))
        self.tabs.setCurrentWidget(self.modes_page)

    def _pole_clicked(self, _item: Any, points: Any, *_: Any) -> None:
        if len(points):
            self.pick_pole(float(points[0].pos().x()))

    def pick_pole(self, frequency_hz: float) -> None:
        """Add a mode at ``frequency_hz`` to the manual selection, or remove the pick within
        0.2 % of it (a second click on the same column; the poles of one column lie closer,
        while two modes 0.5 % apart must both be pickable)."""
        for k, f in enumerate(self.picked_hz):
            if abs(f / frequency_hz - 1) < 0.002:
                del self.picked_hz[k]
                break
        else:
            self.picked_hz.append(frequency_hz)
            self.picked_hz.sort()
        self._show_picks()

    def clear_picks(self) -> None:
        """Forget the manual selection."""
        self.picked_hz = []
        self._show_picks()

    def _show_picks(self) -> None:
        for line in self._pick_lines:
            self.stab_plot.removeItem(line)
        self._pick_lines = []
        for f in self.picked_hz:
            line = pg.InfiniteLine(f, angle=90, pen=pg.mkPen((40, 170, 80), width=2))
            self.stab_plot.addItem(line)
            self._pick_lines.append(line)
        self.fit_picks_button.setEnabled(bool(self.picked_hz) and self.path is not None)
        self.pick_label.setText(
            "picked: " + ", ".join(f"{f:.4g} Hz" for f in self.picked_hz) if self.picked_hz
            else "click poles in the diagram to pick modes by hand")

    def fit_picked_poles(self) -> None:
        """The EMA with the picked modes (``pelvislab ema --frequencies``; refined only when
        the box says every mode is selected)."""
        if self.path is None or not self.picked_hz:
            return
        path, picked = self.path, list(self.picked_hz)
        refine = self.refine_picks.isChecked()

        def work() -> Any:
            from pelvislab.app.commands.ema import ema_file

            return ema_file(path, frequencies_hz=picked, refine=refine)

        self.submit(work, self.show_ema, "modal analysis (picked poles)",
                    self.fit_picks_button)

    # ------------------------------------------------------------------ worker plumbing
    def submit(self, work: Callable[[], Any], done: Callable[[Any], None], what: str,
               button: QtWidgets.QPushButton | None = None,
               cancellable: bool = False) -> Future:
        """Run ``work`` off the UI thread; ``done(result)`` runs on the UI thread.
        ``button`` (the one that started it) is disabled until the job ends, so that a
        second click does not queue the same minute-long job again. ``cancellable``: its
        progress callback (:meth:`_progress_for`) honours *Cancel analysis*."""
        self._progress_note = ""
        future = self._executor.submit(work)
        self._pending.append((future, done, what, button, self.path))
        if button is not None:
            button.setEnabled(False)
        if cancellable:
            self._cancellable.add(future)
            self.cancel_button.setVisible(True)
            self.cancel_button.setEnabled(True)
        self.file_label.setToolTip(f"{what} running…")
        self.analysis_status.setText(f"{what} running…")
        return future

    def _collect(self) -> None:
        for item in list(self._pending):
            future, done, what, button, path = item
            if not future.done():
                if self._progress_note:
                    self.analysis_status.setText(self._progress_note)
                continue
            self._pending.remove(item)
            if button is not None:
                button.setEnabled(True)
            self._cancellable.discard(future)
            if not self._cancellable:  # a Cancel pressed now is for nothing that runs
                self.cancel_button.setVisible(False)
            self.analysis_status.setText("" if self._pending else f"{what} done")
            if path != self.path:  # another file was opened meanwhile: not its result
                self.analysis_status.setText(
                    f"{what} of {path.name if path else 'the previous file'} discarded: "
                    "another file is open")
                continue
            try:
                result = future.result()
            except AnalysisCancelled:
                self.analysis_status.setText(f"{what} cancelled")
                continue
            except Exception as exc:
                self.analysis_status.setText(f"{what} failed")
                try:
                    alert(self, f"{what} failed", str(exc), critical=False)
                except GuiError as error:  # offscreen: the screenshot shows the status
                    self.headless_failures.append(str(error))
                continue
            done(result)

    def busy(self) -> bool:
        """True while background work is pending."""
        return bool(self._pending)
