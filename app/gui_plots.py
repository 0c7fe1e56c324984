"""Plot panels of the operator GUI (pyqtgraph): A-scans, displacement, FRF, quality.

Views only: each panel takes arrays already computed by ``pelvislab.acquisition`` or
``pelvislab.model`` and draws them. No numerics beyond unit scaling for display.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

CHANNEL_PENS = ("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2",
                "#17becf", "#7f7f7f", "#bcbd22")
MODEL_PEN = pg.mkPen("#444444", width=1.5, style=QtCore.Qt.PenStyle.DashLine)

# Antialiasing costs several ms per 2000-point trace; the live view must redraw at >= 10 fps.
pg.setConfigOptions(antialias=False, background="w", foreground="k")


def channel_pen(index: int, width: float = 1.5) -> QtGui.QPen:
    """The pen of channel ``index`` (0-based), the same colour in every panel."""
    return pg.mkPen(CHANNEL_PENS[index % len(CHANNEL_PENS)], width=width)


def log_tick_labels(values_log10: Sequence[float], visible_log10: tuple[float, float],
                    scale: float = 1.0) -> list[str]:
    """Labels of the ticks at ``values_log10`` (log10 of the plotted value) on a log axis
    showing ``visible_log10`` (low, high), the values shown times ``scale`` (the axis' SI
    prefix). Only decades when two or more are in view, else the 1-2-5 ticks, else every
    tick; the others get an empty label. pyqtgraph labels every minor tick of a short
    log axis, and under a decade of span they overlap into an unreadable column."""
    shift = math.log10(scale) if scale > 0 else 0.0
    low, high = sorted(visible_log10)
    low, high = low + shift, high + shift
    decades = math.floor(high) - math.ceil(low) + 1
    if decades >= 2:
        kept = {1}
    else:
        in_view = [k + math.log10(m) for k in range(math.floor(low), math.ceil(high) + 1)
                   for m in (1, 2, 5)]
        kept = {1, 2, 5} if sum(low <= v <= high for v in in_view) >= 2 else set(range(1, 10))
    labels = []
    for v in values_log10:
        shown = v + shift
        mantissa = round(10 ** (shown - math.floor(shown + 1e-9)), 6)
        labels.append(f"{10 ** shown:g}" if round(mantissa) in kept
                      and abs(mantissa - round(mantissa)) < 1e-3 else "")
    return labels


def displacement_title(title: str, names: Sequence[str]) -> str:
    """``title`` and, under it, each channel's name in its pen's colour (HTML)."""
    coloured = "&nbsp;&nbsp;".join(
        f'<span style="color:{CHANNEL_PENS[i % len(CHANNEL_PENS)]}">&#9632; {html.escape(n)}</span>'
        for i, n in enumerate(names))
    return f"{html.escape(title)}<br><span style='font-size:9pt'>{coloured}</span>"


class LogLabelAxis(pg.AxisItem):
    """A log axis labelled by :func:`log_tick_labels` (ticks as pyqtgraph places them)."""

    def logTickStrings(self, values: list[float], scale: float, spacing: float) -> list[str]:
        return log_tick_labels(values, tuple(self.range), scale)


AUTO_GATE_BRUSH = (255, 200, 0, 50)
"""The gate the tracker chose (amber)."""
OPERATOR_GATE_BRUSH = (0, 170, 80, 60)
"""A gate the operator set (green)."""


class AScanPanel(pg.GraphicsLayoutWidget):
    """The latest echo of each channel (volts against depth-time in µs) with its gate.

    While :meth:`set_gates_editable` is on, the operator drags a gate (or its edges) onto
    the bone echo; :attr:`gate_edited` then gives the channel's row and the new edges (s)."""

    gate_edited = QtCore.Signal(int, float, float)
    """(row, start s, stop s) when the operator has moved a gate."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self._plots: list[pg.PlotItem] = []
        self._curves: list[pg.PlotDataItem] = []
        self._gates: list[pg.LinearRegionItem] = []
        self._rivals: list[pg.InfiniteLine] = []
        self._drawn: dict[int, tuple[float, float]] = {}  # row -> the region last drawn
        self._editable = False
        self._drawing = False  # our own setRegion also emits sigRegionChangeFinished

    def set_channels(self, names: Sequence[str]) -> None:
        """One row per channel, titled by its name (e.g. ``ch1 → PSIS_R``). Plots are reused
        between setups: building a pyqtgraph plot costs ~50 ms, too long for the UI thread."""
        while len(self._plots) < len(names):
            i = len(self._plots)
            plot = self.addPlot(row=i, col=0)
            plot.setLabel("bottom", "time after trigger", units="s")
            plot.setLabel("left", "echo", units="V")
            plot.showGrid(x=True, y=True, alpha=0.2)
            curve = plot.plot(pen=channel_pen(i, 1.0))
            gate = pg.LinearRegionItem(movable=self._editable,
                                       brush=pg.mkBrush(*AUTO_GATE_BRUSH))
            gate.setVisible(False)
            gate.sigRegionChangeFinished.connect(
                lambda region, row=i: self._gate_moved(row, region))
            plot.addItem(gate)
            rival = pg.InfiniteLine(angle=90, movable=False, pen=pg.mkPen(
                "#e65100", width=2, style=QtCore.Qt.PenStyle.DashLine),
                label="other echo", labelOpts={"position": 0.92, "color": "#e65100"})
            rival.setVisible(False)
            plot.addItem(rival)
            self._plots.append(plot)
            self._curves.append(curve)
            self._gates.append(gate)
            self._rivals.append(rival)
        for i, plot in enumerate(self._plots):
            visible = i < len(names)
            plot.setVisible(visible)
            if visible:
                plot.setTitle(f"A-scan {names[i]}")
                # the previous setup's echo is not shown under the new landmark's name
                self._curves[i].setData([], [])
                self._gates[i].setVisible(False)
                self._rivals[i].setVisible(False)

    def set_gates_editable(self, editable: bool) -> None:
        """Let the operator move the gates (at a prompt, over live echoes) or not."""
        self._editable = bool(editable)
        for gate in self._gates:
            gate.setMovable(self._editable)
            if not self._editable:
                # a drag cut short (STOP pressed mid-drag) never finishes: its "moving"
                # flags would keep show_echo from drawing this gate again
                gate.moving = False
                for line in gate.lines:
                    line.moving = False

    @property
    def gates_editable(self) -> bool:
        """True while the operator may move the gates."""
        return self._editable

    def show_rival(self, index: int, time_s: float | None) -> None:
        """Mark another echo within 10 dB of the gated one (the tracker's rival-echo note)
        on channel ``index``'s A-scan at ``time_s``; None hides the mark."""
        if index >= len(self._rivals):
            return
        line = self._rivals[index]
        if time_s is None:
            line.setVisible(False)
        else:
            line.setValue(time_s)
            line.setVisible(True)

    def _gate_moved(self, row: int, region: pg.LinearRegionItem) -> None:
        if self._drawing or not self._editable:
            return
        start_s, stop_s = region.getRegion()
        # a drag cancelled (right click) or let go where it began ends here too, with the
        # region unchanged: that is no gate set by the operator (helper review, session 38)
        drawn = self._drawn.get(row)
        if drawn is not None and abs(start_s - drawn[0]) <= 1e-12 and \
                abs(stop_s - drawn[1]) <= 1e-12:
            return
        self._drawn[row] = (float(start_s), float(stop_s))
        self.gate_edited.emit(row, float(start_s), float(stop_s))

    def show_echo(self, index: int, time_s: np.ndarray, volts: np.ndarray,
                  gate_s: tuple[float, float] | None, operator: bool = False) -> None:
        """Draw one echo of channel ``index``; ``gate_s`` is the tracking gate (start, stop),
        green when the operator set it (``operator``)."""
        if index >= len(self._curves):
            return
        self._curves[index].setData(time_s, volts)
        gate = self._gates[index]
        if gate_s is None:
            gate.setVisible(False)
            return
        gate.setBrush(pg.mkBrush(*(OPERATOR_GATE_BRUSH if operator else AUTO_GATE_BRUSH)))
        # a gate the operator is dragging is not pulled back by the next live echo
        if not (gate.moving or any(line.moving for line in gate.lines)):
            self._drawing = True
            try:
                gate.setRegion(gate_s)
                start_s, stop_s = gate.getRegion()
                self._drawn[index] = (float(start_s), float(stop_s))
            finally:
                self._drawing = False
        gate.setVisible(True)


class DisplacementPanel(pg.PlotWidget):
    """Displacement (µm) of each channel over the pulses of the current step. The
    channels are named in the title in their colours: a legend inside the plot hid the
    traces it named (they fill the whole box)."""

    TITLE = "Displacement, current step"

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent, title=self.TITLE)
        self.setLabel("bottom", "time", units="s")
        self.setLabel("left", "displacement", units="m")
        self.showGrid(x=True, y=True, alpha=0.2)
        self.setDownsampling(auto=True, mode="peak")
        self.setClipToView(True)
        self._curves: list[pg.PlotDataItem] = []

    def set_channels(self, names: Sequence[str]) -> None:
        """One curve per channel; curves are reused and renamed between setups."""
        while len(self._curves) < len(names):
            self._curves.append(self.plot(pen=channel_pen(len(self._curves))))
        for i, curve in enumerate(self._curves):
            curve.setVisible(i < len(names))
            curve.setData([], [])
        self.setTitle(displacement_title(self.TITLE, names))

    def show_trace(self, index: int, time_s: np.ndarray, displacement_m: np.ndarray) -> None:
        """Draw channel ``index``'s displacement trace (metres; pyqtgraph scales the units)."""
        if index < len(self._curves):
            self._curves[index].setData(time_s, displacement_m)


class FrfPanel(pg.GraphicsLayoutWidget):
    """Receptance magnitude (log) and phase, measured lines building up, model curves dashed."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.magnitude = self.addPlot(row=0, col=0, title="FRF magnitude",
                                      axisItems={"left": LogLabelAxis("left")})
        self.magnitude.setLogMode(x=False, y=True)
        self.magnitude.setLabel("left", "|H|", units="m/N")
        self.magnitude.showGrid(x=True, y=True, alpha=0.2)
        self.phase = self.addPlot(row=1, col=0, title="FRF phase")
        self.phase.setLabel("left", "phase", units="deg")
        self.phase.setLabel("bottom", "frequency", units="Hz")
        self.phase.setXLink(self.magnitude)
        self.phase.setYRange(-180, 180)
        self.phase.showGrid(x=True, y=True, alpha=0.2)
        # The legend gets its own column: inside the plot it hides the lines it names.
        self.legend = pg.LegendItem(labelTextSize="8pt")
        self.addItem(self.legend, row=0, col=1, rowspan=2)
        self.ci.layout.setColumnFixedWidth(1, 190)
        # at its own height, at the top: stretched over both plots its rows drifted apart,
        # each line's sample far below its name
        self.legend.setSizePolicy(QtWidgets.QSizePolicy.Policy.Preferred,
                                  QtWidgets.QSizePolicy.Policy.Fixed)
        self.ci.layout.setAlignment(self.legend, QtCore.Qt.AlignmentFlag.AlignTop)
        self._measured: dict[str, tuple[pg.PlotDataItem, pg.PlotDataItem]] = {}
        self._model: dict[str, tuple[pg.PlotDataItem, pg.PlotDataItem]] = {}

    def clear_curves(self) -> None:
        """Remove every curve (a new session or a new file)."""
        for store in (self._measured, self._model):
            for mag, ph in store.values():
                self.magnitude.removeItem(mag)
                self.phase.removeItem(ph)
            store.clear()
        self.legend.clear()

    def _curve_pair(self, store: dict, label: str, pen: QtGui.QPen, symbol: str | None,
                    legend: bool) -> tuple[pg.PlotDataItem, pg.PlotDataItem]:
        if label not in store:
            kwargs = {"pen": pen}
            if symbol:
                kwargs.update(symbol=symbol, symbolSize=5, symbolBrush=pen.color())
            mag = self.magnitude.plot(**kwargs)
            ph = self.phase.plot(**kwargs)
            if legend:
                self.legend.addItem(mag, label)
            store[label] = (mag, ph)
        return store[label]

    def show_measured(self, label: str, index: int, frequency_hz: np.ndarray,
                      H: np.ndarray) -> None:
        """Draw measured lines of one FRF (NaN lines are skipped)."""
        ok = np.isfinite(H) & (np.abs(H) > 0)
        mag, ph = self._curve_pair(self._measured, label, channel_pen(index), "o", True)
        mag.setData(frequency_hz[ok], np.abs(H[ok]))
        ph.setData(frequency_hz[ok], np.degrees(np.angle(H[ok])))

    def show_model(self, label: str, frequency_hz: np.ndarray, H: np.ndarray) -> None:
        """Draw a model FRF as a dashed line."""
        ok = np.isfinite(H) & (np.abs(H) > 0)
        mag, ph = self._curve_pair(self._model, label, MODEL_PEN, None, False)
        mag.setData(frequency_hz[ok], np.abs(H[ok]))
        ph.setData(frequency_hz[ok], np.degrees(np.angle(H[ok])))


class QualityTable(QtWidgets.QTableWidget):
    """Per-channel tracking quality of the latest step, with warnings highlighted."""

    COLUMNS = ("channel", "landmark", "correlation", "SNR (dB)", "peak hops", "lost", "status")
    MIN_CORRELATION = 0.9
    MIN_SNR_DB = 15.0

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(0, len(self.COLUMNS), parent)
        self.setHorizontalHeaderLabels(self.COLUMNS)
        self.verticalHeader().setVisible(False)
        self.horizontalHeader().setSectionResizeMode(QtWidgets.QHeaderView.ResizeMode.Stretch)
        self.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.setMaximumHeight(110)

    def show_quality(self, rows: Sequence[dict[str, object]]) -> list[str]:
        """Fill the table; returns warning texts for channels that degraded."""
        self.setRowCount(len(rows))
        warnings: list[str] = []
        for r, row in enumerate(rows):
            corr = _as_float(row.get("correlation"))
            snr = _as_float(row.get("snr_db"))
            hops = int(_as_float(row.get("peak_hops")) or 0)
            lost = int(_as_float(row.get("lost")) or 0)
            problems = []
            if corr is not None and corr < self.MIN_CORRELATION:
                problems.append(f"correlation {corr:.2f}")
            if snr is not None and snr < self.MIN_SNR_DB:
                problems.append(f"SNR {snr:.0f} dB")
            if hops:
                problems.append(f"{hops} peak hops")
            if lost:
                problems.append(f"{lost} echoes lost")
            if corr is None and snr is None:  # nothing to judge by is not "OK"
                problems.append("no tracking figures")
            status = "OK" if not problems else "CHECK: " + ", ".join(problems)
            # what the tracker said it found or corrected (an echo cut by the record's
            # edge, a reference rebuilt along the record, a clipped gate): stored with the
            # step but, on a channel that passed, shown nowhere (session 37)
            notes = str(row.get("notes") or "")
            if notes:
                status += " (tracker note: hover)"
            if problems:
                warnings.append(f"{row.get('channel', '?')}: {', '.join(problems)}")
            values = (
                str(row.get("channel", "")), str(row.get("landmark", "")),
                "" if corr is None else f"{corr:.3f}", "" if snr is None else f"{snr:.1f}",
                str(hops), str(lost), status,
            )
            for c, text in enumerate(values):
                item = QtWidgets.QTableWidgetItem(text)
                if problems:
                    item.setBackground(QtGui.QColor("#ffe0b2"))
                if notes:
                    item.setToolTip(notes)
                self.setItem(r, c, item)
        return warnings


def _as_float(value: object) -> float | None:
    """``value`` as a finite float; None when missing, not a number, NaN or infinite."""
    try:
        number = None if value is None else float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return None
    return number if number is not None and math.isfinite(number) else None


def gate_seconds(channel: Any) -> tuple[float, float] | None:
    """The tracking gate of a step's channel as times after the trigger (s), if recorded."""
    quality = channel.quality if isinstance(channel.quality, dict) else {}
    if "gate_start" not in quality or "gate_stop" not in quality:
        return None
    return (channel.delay_s + float(quality["gate_start"]) / channel.sample_rate_hz,
            channel.delay_s + float(quality["gate_stop"]) / channel.sample_rate_hz)


def quality_row(channel: Any) -> dict[str, object]:
    """One row of the quality table from a step channel's recorded quality figures."""
    quality = channel.quality if isinstance(channel.quality, dict) else {}
    n_pulses = channel.codes.shape[0] if getattr(channel, "codes", None) is not None else 0
    lost_fraction = quality.get("lost_fraction")
    return {
        "channel": channel.name, "landmark": channel.output.name,
        "correlation": quality.get("correlation_median"),
        "snr_db": quality.get("snr_db_median"),
        "peak_hops": quality.get("peak_hops", 0),
        "lost": None if lost_fraction is None else round(float(lost_fraction) * n_pulses),
        # why a channel failed ("tracking failed: ...", stored since session 38), then
        # what the tracker said
        "notes": "; ".join(str(text) for text in (
            quality.get("message") if str(quality.get("message", "ok")).startswith(
                "tracking failed") else "",
            quality.get("tracking_warnings", "")) if text),
    }


def echo_trace(channel: Any, echo_index: int) -> tuple[np.ndarray, np.ndarray]:
    """(time after trigger in s, volts) of one echo of a step channel's raw record; volts
    as the digitizer defines them (``SegmentedRecord``: codes x V/count minus the offset)."""
    time_s = channel.delay_s + np.arange(channel.codes.shape[1]) / channel.sample_rate_hz
    volts = channel.codes[echo_index].astype(float) * channel.volts_per_count
    return time_s, volts - channel.volts_offset


def draw_step(ascan: AScanPanel, displacement: DisplacementPanel, quality: QualityTable,
              step: Any, echo_index: int = 0) -> list[str]:
    """Draw a step's echo (``echo_index``) with its gate, its displacement traces and its
    quality rows; returns the quality warnings."""
    rows = []
    for i, ch in enumerate(step.channels):
        time_s, volts = echo_trace(ch, echo_index)
        ascan.show_echo(i, time_s, volts, gate_seconds(ch),
                        operator=(ch.quality or {}).get("gate_source") in ("operator",
                                                                          "protocol"))
        if ch.displacement_m is not None:
            displacement.show_trace(i, np.arange(ch.displacement_m.size) / ch.prf_hz,
                                    ch.displacement_m)
        rows.append(quality_row(ch))
    return quality.show_quality(rows)


# stabilisation-diagram colours by pole status (model.ema NEW, STABLE_FREQUENCY,
# STABLE_DAMPING, STABLE_ALL), as the plots' titles name them
STATUS_COLOURS = {0: (170, 170, 170), 1: (60, 110, 220), 2: (40, 170, 80), 3: (220, 40, 40)}


def draw_ema(sum_plot: pg.PlotItem, stab_plot: pg.PlotItem, result: Any) -> list[Any]:
    """An :class:`~pelvislab.model.ema.EmaResult` in two plots: the sum of |H| over the
    FRFs in dB re 1 m/N (dots measured, line the fitted modal model) and the stabilisation
    diagram (model order over frequency, coloured by status), a dashed line at each mode
    and a dotted grey one at each residual mode within the lines.
    Returns the diagram's items of poles stable at least in frequency (the ones a user
    may pick)."""
    f = np.asarray(result.fit_frequency_hz, dtype=float)
    # in dB: pyqtgraph's log axis labels its minor ticks, which overlap over the one or
    # two decades a summed FRF spans
    for values, style in ((result.H_measured, {"pen": None, "symbol": "o", "symbolSize": 4,
                                               "symbolBrush": (120, 120, 120)}),
                          (result.H_fit, {"pen": pg.mkPen((200, 60, 60), width=1)})):
        # the fit summed over the measured values only: beyond where a run stopped it is
        # an extrapolation, drawn far above the data (replay review, session 36)
        values = np.where(np.isfinite(result.H_measured), values, np.nan)
        total = np.nansum(np.abs(values), axis=(1, 2))
        keep = total > 0
        sum_plot.plot(f[keep], 20 * np.log10(total[keep]), **style)
    pickable = []
    diagram = result.diagram
    if diagram is not None and f.size:
        for status, colour in STATUS_COLOURS.items():
            xs: list[float] = []
            ys: list[int] = []
            for k, order in enumerate(diagram.orders):
                fk = diagram.frequency_hz(k)
                chosen = (np.asarray(diagram.status[k]) == status) & (fk >= f.min()) & (
                    fk <= f.max())
                xs.extend(fk[chosen])
                ys.extend([int(order)] * int(chosen.sum()))
            if xs:
                item = stab_plot.plot(xs, ys, pen=None, symbol="o",
                                      symbolSize=4 if status < 3 else 6,
                                      symbolBrush=colour, symbolPen=None)
                if status >= 1:
                    pickable.append(item)
    for fn in result.frequency_hz:
        for plot in (sum_plot, stab_plot):
            plot.addItem(pg.InfiniteLine(float(fn), angle=90, pen=pg.mkPen(
                (0, 0, 0), width=1, style=QtCore.Qt.PenStyle.DashLine)))
    residual = np.abs(np.asarray(result.residual_poles)) / (2 * np.pi)
    for fr in residual[(residual >= f.min()) & (residual <= f.max())] if f.size else []:
        for plot in (sum_plot, stab_plot):  # residual modes inside the lines: dotted, grey
            plot.addItem(pg.InfiniteLine(float(fr), angle=90, pen=pg.mkPen(
                (140, 140, 140), width=1, style=QtCore.Qt.PenStyle.DotLine)))
    return pickable

