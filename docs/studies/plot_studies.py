"""Draw the identification studies' PNGs from the committed result files.

``python docs/studies/plot_studies.py [--dir docs/studies]`` reads ``ch6_summary.csv`` and
``ch7_summary.csv`` (written by ``run_studies.py``) and writes ``ch6_success_mass.png``,
``ch6_stiffness.png`` and ``ch7_errors.png``, each with the thesis' ch. 6.2 / 7 figures
(as quoted in ``model/studies.py`` and README.md) drawn next to ours. matplotlib is not
installed here, so the plots are pyqtgraph scenes exported offscreen.
"""

from __future__ import annotations

import argparse
import csv
import math
import os
import sys
from pathlib import Path

FLOOR = 1e-12  # errors below this (exact recoveries) are drawn at the floor of the log axis

COLOURS = {"ours": (0, 90, 200), "ours2": (0, 160, 80), "ours3": (150, 0, 180),
           "ours4": (230, 140, 0), "eq610": (200, 0, 0), "thesis": (90, 90, 90)}


def _rows(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def _num(text: str) -> float:
    return float(text) if text not in ("", "None") else math.nan


def _series(rows: list[dict[str, str]], study: str, column: str) -> tuple[list, list]:
    sel = sorted((int(r["dp_pct"]), _num(r[column])) for r in rows if r["study"] == study)
    return [s[0] for s in sel], [max(s[1], FLOOR) for s in sel]


def main(argv: list[str] | None = None) -> int:
    """Write the three PNGs into ``--dir``."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--dir", default=str(Path(__file__).parent),
                   help="folder with the study files; PNGs are written there")
    args = p.parse_args(argv)
    folder = Path(args.dir)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    import pyqtgraph as pg
    import shiboken6
    from pyqtgraph.exporters import ImageExporter

    pg.mkQApp()
    # global options: restored afterwards so a GUI in the same process keeps its look
    saved = {k: pg.getConfigOption(k) for k in ("background", "foreground", "antialias")}
    pg.setConfigOptions(background="w", foreground="k", antialias=True)
    widgets: list[object] = []
    try:
        _draw(pg, ImageExporter, folder, widgets)
    finally:
        for w in widgets:  # PySide6 may crash at interpreter exit with live widgets
            shiboken6.delete(w)
        pg.setConfigOptions(**saved)
    return 0


def _draw(pg: object, ImageExporter: type, folder: Path,
          widgets: list[object]) -> None:
    """Build the three figures (pyqtgraph scenes) and export them as PNG into ``folder``."""

    def pen(key: str, style: object = None, width: float = 2) -> object:
        kw = {"style": style} if style is not None else {}
        return pg.mkPen(COLOURS[key], width=width, **kw)

    def curve(plot: object, x: list, y: list, key: str, name: str | None, symbol: str = "o",
              dashed: bool = False) -> None:
        plot.plot(x, y, name=name, symbol=symbol, symbolSize=9,  # type: ignore[attr-defined]
                  symbolBrush=COLOURS[key], symbolPen=COLOURS[key],
                  pen=pen(key, pg.QtCore.Qt.PenStyle.DashLine if dashed else None))

    def band(plot: object, lo: float, hi: float, text: str, x: float) -> None:
        """Shaded thesis range (log-y plots: view coordinates are log10)."""
        region = pg.LinearRegionItem((math.log10(lo), math.log10(hi)),
                                     orientation="horizontal", movable=False,
                                     brush=pg.mkBrush(120, 120, 120, 60))
        plot.addItem(region)  # type: ignore[attr-defined]
        label = pg.TextItem(text, color=COLOURS["thesis"], anchor=(0, 0))
        label.setPos(x, math.log10(lo))  # below the band: legends sit top right
        plot.addItem(label)  # type: ignore[attr-defined]

    def new_plot(layout: object, title: str, left: str, bottom: str, log_y: bool = True,
                 legend_at: tuple[int, int] = (-5, 5)) -> object:
        plot = layout.addPlot(title=title)  # type: ignore[attr-defined]
        plot.setLabel("left", left)
        plot.setLabel("bottom", bottom)
        plot.showGrid(x=True, y=True, alpha=0.25)
        if log_y:
            plot.setLogMode(y=True)
        plot.addLegend(offset=legend_at, labelTextColor="k", brush=pg.mkBrush(255, 255, 255, 220))
        return plot

    def export(layout: object, name: str, width: int) -> None:
        layout.show()  # type: ignore[attr-defined]  # lays the plots out at the widget size
        pg.QtWidgets.QApplication.processEvents()
        exporter = ImageExporter(layout.scene())  # type: ignore[attr-defined]
        exporter.parameters()["width"] = width
        exporter.export(str(folder / name))
        print(f"wrote {folder / name}", file=sys.stderr)

    bins = [10, 20, 30, 40]
    dp_ticks = [[(b, f"{b} %") for b in bins]]
    ch6 = _rows(folder / "ch6_summary.csv")

    # ---- ch. 6.2 (1): success per bin (noise-free) and mass errors with noise
    layout = pg.GraphicsLayoutWidget()
    widgets.append(layout)
    layout.resize(1400, 520)
    plot = new_plot(layout, "ch. 6.2 noise-free: success (all 18 parameters within 0.1 %)",
                    "runs successful (%)", "perturbation bin dp", log_y=False)
    x, y = _series(ch6, "ch6_ours_noisefree", "success_pct")
    plot.addItem(pg.BarGraphItem(x=x, height=y, width=6, brush=COLOURS["ours"],
                                 name="ours (continuation + multi-start)"))
    plot.setYRange(0, 115)
    plot.getAxis("bottom").setTicks(dp_ticks)
    cross = pg.ScatterPlotItem([40], [0], symbol="x", size=22, brush=COLOURS["eq610"],
                               pen=pg.mkPen(COLOURS["eq610"], width=2),
                               name="thesis: dp 40 % 'impairs the identification', "
                                    "discarded (no rate published)")
    plot.addItem(cross)
    plot = new_plot(layout, "ch. 6.2 median mass error, both noise types (2 mm, 10°)",
                    "median |error| of the 3 masses (%)", "perturbation bin dp")
    x, y = _series(ch6, "ch6_ours_noise", "mass_err_median_pct")
    curve(plot, x, y, "ours", "ours (median)")
    x, y = _series(ch6, "ch6_ours_noise", "mass_err_max_pct")
    curve(plot, x, y, "ours", "ours (max)", symbol="t", dashed=True)
    x, y = _series(ch6, "ch6_eq610_ab0.1", "mass_err_median_pct")
    curve(plot, x, y, "eq610", "eq. 6.10, a/b = 0.1, one run (median)", symbol="s")
    curve(plot, [10, 20, 30], [2.5, 5.0, 7.0], "thesis", "thesis (bound: below 2.5/5/7 %)",
          symbol="x", dashed=True)
    plot.getAxis("bottom").setTicks(dp_ticks)
    export(layout, "ch6_success_mass.png", 1400)

    # ---- ch. 6.2 (2): stiffness errors vs noise type, layout/df, and the a/b ratio
    layout = pg.GraphicsLayoutWidget()
    widgets.append(layout)
    layout.resize(1800, 560)
    plot = new_plot(layout, "stiffness error vs noise (face-up, df 2.5 Hz)",
                    "median |error| of the 12 stiffnesses (%)", "perturbation bin dp")
    band(plot, 30, 60, "thesis: 30-60 %", 10)
    for study, key, name, sym in (
            ("ch6_ours_noisefree", "ours2", "ours, noise-free (~1e-11 %, off scale)", "o"),
            ("ch6_ours_orientation_only", "ours4", "ours, tilt 0-10° only", "d"),
            ("ch6_ours_position_only", "ours3", "ours, position ±2 mm only", "t"),
            ("ch6_ours_noise", "ours", "ours, both", "s"),
            ("ch6_eq610_ab0.1", "eq610", "eq. 6.10 a/b 0.1 one run, both", "x")):
        x, y = _series(ch6, study, "stiffness_err_median_pct")
        curve(plot, x, y, key, name, symbol=sym)
    plot.getAxis("bottom").setTicks(dp_ticks)
    plot.setYRange(math.log10(0.2), math.log10(2000), padding=0)
    plot = new_plot(layout, "stiffness error: layout and df (both noise types)",
                    "median |error| (solid) / 90th pct (dashed) (%)", "perturbation bin dp")
    band(plot, 30, 60, "thesis: 30-60 %", 10)
    for study, key, name in (("ch6_ours_noise", "ours", "face-up df 2.5"),
                             ("ch6_ours_noise_face_down", "eq610", "face-down"),
                             ("ch6_ours_noise_full", "ours2", "full (28 pairs)"),
                             ("ch6_ours_noise_df5", "ours4", "face-up df 5")):
        x, y = _series(ch6, study, "stiffness_err_median_pct")
        curve(plot, x, y, key, name)
        x, y = _series(ch6, study, "stiffness_err_p90_pct")
        curve(plot, x, y, key, None, symbol="t", dashed=True)
    plot.getAxis("bottom").setTicks(dp_ticks)
    plot = new_plot(layout, "eq. 6.10, one least-squares run: the a/b ratio",
                    "median |stiffness error| (%)", "a/b (log)")
    plot.setLogMode(x=True, y=True)
    band(plot, 30, 60, "thesis: 30-60 %; chose a/b = 0.1", -2)
    ratios = [0.01, 0.1, 1.0, 10.0, 100.0]
    for dp, key in ((10, "ours2"), (20, "ours"), (30, "eq610")):
        y = [max(_num(r["stiffness_err_median_pct"]), FLOOR) for a in ratios for r in ch6
             if r["study"] == f"ch6_eq610_ab{a:g}" and int(r["dp_pct"]) == dp]
        curve(plot, ratios, y, key, f"dp {dp} % (2 sets)")
    ours = [_num(r["stiffness_err_median_pct"]) for r in ch6 if r["study"] == "ch6_ours_noise"
            and int(r["dp_pct"]) <= 30]
    line = pg.InfiniteLine(math.log10(max(ours)), angle=0,
                           pen=pen("ours", pg.QtCore.Qt.PenStyle.DashLine))
    plot.addItem(line)
    label = pg.TextItem(f"ours, same noise: <= {max(ours):.1f} %", color=COLOURS["ours"],
                        anchor=(0, 0))
    label.setPos(-2, math.log10(max(ours)))
    plot.addItem(label)
    export(layout, "ch6_stiffness.png", 1800)

    # ---- ch. 7: errors per case, versions A and B
    ch7 = _rows(folder / "ch7_summary.csv")
    cases = list(range(1, 8))
    case_ticks = [[(c, f"{c}") for c in cases]]

    def per_case(version: str, column: str, floor: float = FLOOR) -> list[float]:
        return [max(_num(r[column]), floor) for r in ch7 if r["version"] == version]

    layout = pg.GraphicsLayoutWidget()
    widgets.append(layout)
    layout.resize(1800, 560)
    panels = (("freq_err_max_pct", "max |frequency error| (%)", (3, 35),
               "thesis A: ±3 %, mode 10 up to 35 %"),
              ("zeta_err_max_pct", "max |damping-ratio error| (%)", (100, 400),
               "thesis A: -100 ... +400 %"),
              ("param_err_max_pct", "max |parameter error| (%)", (300, 500),
               "thesis A: c_sij +300...500 %,\nothers ±30 %"))
    for column, left, (lo, hi), text in panels:
        plot = new_plot(layout, left.replace("max |", "").replace("| (%)", ""), left,
                        "case of table 7.2", legend_at=(-5, 150))
        band(plot, lo, hi, text, 0.6)
        curve(plot, cases, per_case("A", column), "eq610", "ours version A", symbol="o")
        curve(plot, cases, per_case("B", column), "ours", "ours version B", symbol="t")
        plot.getAxis("bottom").setTicks(case_ticks)
        plot.setXRange(0.5, 7.5)
        if column == "param_err_max_pct":
            failed = pg.ScatterPlotItem([5, 7], [0.0, 0.0], symbol="x", size=22,
                                        pen=pg.mkPen(COLOURS["thesis"], width=3),
                                        name="thesis B: failed (2000 starts)")
            plot.addItem(failed)
    plot = new_plot(layout, "MAC of paired in-band modes", "min MAC", "case of table 7.2",
                    log_y=False, legend_at=(30, 150))
    curve(plot, cases, per_case("A", "mac_min", 0.0), "eq610", "ours version A")
    curve(plot, cases, per_case("B", "mac_min", 0.0), "ours", "ours version B", symbol="t")
    note = pg.TextItem("thesis A: mode switching 9/10, 15/16", color=COLOURS["thesis"],
                       anchor=(0, 1))
    note.setPos(0.6, 0.5)
    plot.addItem(note)
    plot.getAxis("bottom").setTicks(case_ticks)
    plot.setXRange(0.5, 7.5)
    plot.setYRange(0.45, 1.05)
    export(layout, "ch7_errors.png", 1800)


if __name__ == "__main__":
    sys.exit(main())
