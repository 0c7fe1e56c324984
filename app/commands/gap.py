"""``pelvislab gap``: sim-to-real gap diagnosis and its withheld-effect self-check (design 4.4).

``gap diagnose`` reads the /frf set of a session or FRF-only file, runs
:func:`pelvislab.model.gap.diagnose` and writes the design 4.4 JSON, a readable report on
stdout and PNG plots next to the JSON. With ``--json -`` the JSON is all that goes to
stdout: the report goes to stderr and no plots are saved (there is no file to put them
next to).

``gap benchmark`` runs the diagnosis blind on data sets with one hidden effect each. The
data generator lives on the *test* side (``pelvislab.tests.benchmarks.bench_gap``), which
is allowed to use the simulator (``sim_instruments``): product code never imports the
simulator (design 3), and the generator shares no code with the diagnosis, so the check
stays blind. The command imports it lazily, only when asked to run the self-check.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pelvislab.app.commands._common import (
    check_new_output,
    comma_list,
    incomplete_session_warning,
    infinite_as_unmeasured,
    keep_freed_memory_for_reuse,
    print_json,
    require_response,
    write_json,
)

_JOBS_HELP = ("worker processes for the candidate fits (default 0: every core; 1: serial). "
              "The result does not depend on it")


def _check_jobs(jobs: int) -> None:
    """Refuse a negative worker count before any work starts (0 = every core)."""
    if jobs < 0:
        raise ValueError(f"--jobs must be >= 0 (0 = every core), got {jobs}")


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``gap diagnose`` and ``gap benchmark`` to the CLI."""
    p = subparsers.add_parser("gap", help="sim-to-real gap diagnosis")
    sub = p.add_subparsers(dest="gap_command", metavar="ACTION")
    sub.required = True
    d = sub.add_parser(
        "diagnose", help="where the model misses the data, and which effect",
        description="Fit the model's parameters to /frf, map where the model and the data "
        "still disagree (by band, output and bone), try each candidate unmodelled effect "
        "fitted with the parameters and judged on held-out lines, and say which one closes "
        "the gap and by how much: 'none' when updating alone explains the data to the "
        "noise, 'unexplained' when no candidate does.")
    d.add_argument("session", metavar="S.h5", help="session or FRF-only file")
    d.add_argument("--model", metavar="M.toml", help="base model; default: thesis appendix E")
    d.add_argument("--json", required=True, metavar="OUT",
                   help="write the diagnosis JSON to this file (the plots go next to it, "
                   "the report to stdout); '-': print the JSON on stdout, the report on "
                   "stderr, and save no plots")
    d.add_argument("--effects", metavar="LIST",
                   help="comma-separated candidate effects to try (default: all, and "
                        "per_dashpot_damping, an extension of parameter updating)")
    d.add_argument("--updating-range", type=float, default=None, metavar="FACTOR",
                   help="stiffness and mass are updated within the model's values x/÷ "
                        "FACTOR (default 1.6: subjects within +-30 %% of the model)")
    d.add_argument("--damping-max", type=float, default=None, metavar="FACTOR",
                   help="damping is updated up to FACTOR times the model's values "
                        "(default 3e4: appendix E's 0.8 N s/m -> 24000 N s/m)")
    d.add_argument("--no-plots", action="store_true", help="do not write PNG plots")
    d.add_argument("--progress", dest="verbose_progress", action="store_true",
                   help="print a line per stage (base fit, screen, joint fits, searches) "
                        "on stderr even when not a terminal")
    d.add_argument("--jobs", type=int, default=0, metavar="N",
                   help=_JOBS_HELP)
    d.set_defaults(handler=_diagnose)
    b = sub.add_parser(
        "benchmark", help="diagnose data sets with a withheld effect each",
        description="Generate data sets with one hidden effect each (random kind, size and "
        "place) and some with none, diagnose them without telling, and report the verdicts' "
        "confusion matrix, the place found for local effects and the shrink.")
    b.add_argument("--json", required=True, metavar="OUT", help="write the benchmark JSON here")
    b.add_argument("--cases", type=int, default=2, metavar="N",
                   help="data sets per effect kind (plus N without effect); default 2")
    b.add_argument("--seed", type=int, default=1, help="random seed of the generator")
    b.add_argument("--source", choices=("auto", "sim", "model", "chain"), default="auto",
                   help="data generator: the simulator's effect_frf ('sim'), the test-side "
                   "model generator ('model'), sim when available ('auto'), or only "
                   "sessions of the full simulated chain ('chain', --cases per kind)")
    b.add_argument("--chain-cases", type=int, default=0, metavar="N",
                   help="also N full-chain data sets per kind (simulated bench, face-up "
                   "protocol on a 5 Hz grid, ~20-30 s each); default 0")
    b.add_argument("--chain-step-hz", type=float, default=5.0, metavar="HZ",
                   help="line spacing of the full-chain sessions (default 5 Hz)")
    b.add_argument("--kinds", metavar="LIST",
                   help="comma-separated kinds to generate (default: none and every effect)")
    b.add_argument("--progress", dest="verbose_progress", action="store_true",
                   help="print one line per data set on stderr even when not a terminal")
    b.add_argument("--jobs", type=int, default=0, metavar="N",
                   help=_JOBS_HELP)
    b.set_defaults(handler=_benchmark)


def _progress(always: bool = False) -> object:
    """A progress printer on stderr: on a terminal, or ``always`` (``--progress``)."""
    if always or sys.stderr.isatty():
        return lambda msg: print(f"  {msg}", file=sys.stderr, flush=True)
    return None


@dataclass
class GapReport:
    """One diagnosis of a file: the design 4.4 document plus what the views draw."""

    document: dict[str, Any]
    residual_map: Any  # (n_rows, n_f) array: |normalised residual| of the base fit
    row_labels: list[str]  # "output / input" of each measured pair
    frequency_hz: Any  # (n_f,) array
    diagnosis: Any  # pelvislab.model.gap.Diagnosis

    def to_json(self) -> dict[str, Any]:
        """The JSON document written by ``pelvislab gap diagnose --json``."""
        return self.document


def diagnose_file(path: str | Path, model_path: str | Path | None = None,
                  progress: Callable[[str], None] | None = None,
                  effects: tuple[str, ...] | None = None,
                  updating_range: float | None = None,
                  damping_max: float | None = None, jobs: int = 0) -> GapReport:
    """Sim-to-real gap diagnosis of the /frf of ``path`` (session or FRF-only file).

    ``updating_range`` / ``damping_max`` override :class:`GapOptions`' prior ranges of the
    parameter updating (factors on the model's values, > 1); ``jobs``: worker processes
    (0 = every core; the GUI's worker thread runs it serially, see
    :mod:`pelvislab.model.parallel`).

    The one entry point of the CLI and the GUI's replay view; the numerics are
    :func:`pelvislab.model.gap.diagnose`.
    """
    import numpy as np

    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.gap import GapOptions, diagnose, prepare_data
    from pelvislab.model.gap_effects import EFFECT_NAMES, NULL_EXTENSIONS
    from pelvislab.model.pelvis import load_model

    ranges = {k: v for k, v in (("updating_range", updating_range),
                                 ("damping_max", damping_max)) if v is not None}
    for key, value in ranges.items():
        if not (np.isfinite(value) and value > 1.0):
            raise ValueError(f"--{key.replace('_', '-')} must be a finite factor > 1, "
                             f"got {value}")
    frf = read_frf(path)
    infinite_note = infinite_as_unmeasured(frf)
    H_std, warnings = usable_std(frf)
    if infinite_note:
        warnings.insert(0, infinite_note)
    model = load_model(model_path)
    if effects is not None:
        unknown = sorted(set(effects) - set(EFFECT_NAMES) - set(NULL_EXTENSIONS))
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; known: "
                             f"{', '.join((*EFFECT_NAMES, *NULL_EXTENSIONS))}")
    data = prepare_data(frf.frequency_hz, frf.H, H_std, frf.outputs, frf.inputs)
    _check_jobs(jobs)
    result = diagnose(data, model, GapOptions(effects=effects, jobs=jobs, **ranges),
                      progress=progress)
    document = dict(result.report)
    if warnings:
        document["warnings"] = warnings
    note = left_out_note(document.get("where") or {})
    if note:
        document["notes"] = [note]
    document["source"] = {"file": str(Path(path).resolve()),
                          "model": str(model_path) if model_path else "appendix_e (default)"}
    residual = np.abs(np.asarray(result.residual_map))
    rows, labels = [], []
    for i, out in enumerate(frf.outputs.name):
        for j, inp in enumerate(frf.inputs.name):
            if np.any(data.mask[:, i, j]):
                rows.append(np.where(data.mask[:, i, j], residual[:, i, j], np.nan))
                labels.append(f"{out} / {inp}")
    residual_rows = np.array(rows) if rows else np.zeros((0, frf.frequency_hz.size))
    return GapReport(document, residual_rows, labels, np.asarray(frf.frequency_hz), result)


def left_out_note(where: dict[str, Any]) -> str | None:
    """A note naming the outputs and inputs ``where`` leaves out of its shares (a point on
    no modelled bone, design 4.1, or a channel with no usable line), or ``None``."""
    items = where.get("left_out") or []
    if not items:
        return None
    reasons: dict[str, list[str]] = {}
    for item in items:
        reasons.setdefault(str(item["reason"]), []).append(f"{item['side']} {item['name']}")
    why = {"on no modelled bone": "on no modelled bone: the model predicts nothing there"}
    return "left out of the diagnosis and of the where shares: " + "; ".join(
        f"{', '.join(names)} ({why.get(reason, reason)})" for reason, names in reasons.items())


MIN_FREQUENCY_LINES = 12
"""Fewest measured frequency lines ``gap diagnose`` accepts: every 4th line is held out,
so 12 leave 9 to fit and 3 to judge the fit on."""


def usable_std(frf: Any) -> tuple[Any, list[str]]:
    """``frf.H_std`` if it can weight the fit, else ``None`` (noise then estimated from the
    data) with the reason; refuses a set with no measured line or fewer than
    :data:`MIN_FREQUENCY_LINES` frequency lines.

    A writer may store ``H_std`` as zeros (noise-free synthetic data) or NaN everywhere
    (no uncertainty known): design 4.2 makes ``H_std`` optional, so such a file is read as
    one without it rather than refused.
    """
    import numpy as np

    require_response(frf.H)
    measured = np.isfinite(frf.H)
    n_lines = int(np.any(measured, axis=(1, 2)).sum())
    if n_lines < MIN_FREQUENCY_LINES:
        raise ValueError(f"/frf has {n_lines} measured frequency lines; the diagnosis needs "
                         f">= {MIN_FREQUENCY_LINES} (every 4th is held out)")
    if frf.H_std is None:
        return None, []
    good = np.isfinite(frf.H_std) & (frf.H_std > 0)
    if good[measured].any():
        return frf.H_std, []
    return None, ["H_std holds no positive finite value on the measured lines; "
                  "the noise is estimated from the data instead"]


def plot_paths(out: Path) -> list[Path]:
    """The PNGs ``gap diagnose --json OUT`` writes next to its JSON (OUT without suffix)."""
    stem = out.with_suffix("")
    return [Path(f"{stem}_residual_map.png"), Path(f"{stem}_worst_frf.png")]


def _diagnose(args: argparse.Namespace) -> int:
    # '-': the JSON alone on stdout (design 4.3, as identify and ema print it); the report
    # then goes to stderr, and the plots, which are saved next to a JSON file, are skipped
    # with a note rather than refused: they are a default, not something asked for
    out = None if args.json == "-" else check_new_output(args.json)
    plotting = not args.no_plots and out is not None
    if plotting:
        for path in plot_paths(out):  # results are never overwritten, plots neither
            check_new_output(path)
    if out is None and not args.no_plots:
        print("pelvislab gap diagnose: note: no plots with --json - (they are saved next "
              "to a JSON file): give --json FILE for them, or add --no-plots to drop this "
              "note", file=sys.stderr)
    keep_freed_memory_for_reuse()
    effects = None
    if args.effects:
        effects = tuple(comma_list(args.effects))
    warning = incomplete_session_warning(args.session)
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    report = diagnose_file(args.session, args.model, _progress(args.verbose_progress), effects,
                           args.updating_range, args.damping_max, args.jobs)
    plots: list[str] = []
    if plotting:
        try:
            plots = _plots(report.diagnosis, out)
        except Exception as exc:  # plots are a convenience; the JSON is the result
            print(f"pelvislab gap diagnose: warning: no plots ({exc})", file=sys.stderr)
    document = report.to_json()
    document["plots"] = plots
    for w in document.get("warnings", []):
        print(f"pelvislab gap diagnose: warning: {w}", file=sys.stderr)
    for n in document.get("notes", []):
        print(f"pelvislab gap diagnose: note: {n}", file=sys.stderr)
    if out is None:
        print_json(document)
    else:
        write_json(out, document)
    text = sys.stdout if out is not None else sys.stderr  # stdout holds the JSON alone
    print(format_report(document), file=text)
    print(f"\nJSON: {out if out is not None else 'standard output'}", file=text)
    for p in plots:
        print(f"plot: {p}", file=text)
    return 0


def format_report(report: dict) -> str:
    """A readable text version of the design 4.4 report."""
    lines = [f"sim-to-real gap diagnosis: verdict = {report['verdict']}",
             f"  {report.get('verdict_reason', '')}",
             f"  gap before (held-out model error beyond noise, in sigma; 0 = noise level): "
             f"{report['gap_before']:.3g}"
             f"   noise: {report.get('noise', {}).get('source', '?')}"]
    noise_note = (report.get("noise") or {}).get("note")
    if noise_note:
        lines.append(f"  noise: {noise_note}")
    joint = (report.get("calibration") or {}).get("joint_null") or {}
    if joint.get("gains"):
        lines.append("  output gains of the null fitted with the base parameters: " + ", ".join(
            f"{n.removeprefix('gain_')} {g:.4f}" for n, g in joint["gains"].items()))
    base_fit = report.get("base_fit", {})
    refitted_from, own = base_fit.get("refitted_from"), base_fit.get("own_starts")
    if refitted_from and own:
        lines.append(f"  base parameters refitted from {refitted_from['effect']}'s "
                     f"({refitted_from['variant']} @ {refitted_from['place']}): fitted-line "
                     f"chi2 {base_fit['chi2_fitted_lines']:.4g}, from the model's own starts "
                     f"{own['chi2_fitted_lines']:.4g} (held-out gap {own['gap_held_out']:.3g})")
    at_bound = base_fit.get("at_bound", {})
    if at_bound:
        lines.append("  updating ended at the bounds of its range (x model value): " + ", ".join(
            f"{n} {v:.3g}" for n, v in at_bound.items()))
    where = report["where"]
    lines.append("where:")
    lines.append("  bands:   " + ", ".join(
        f"{b['lo_hz']:.0f}-{b['hi_hz']:.0f} Hz {b['share']:.0%}" for b in where["bands"][:4]))
    lines.append("  outputs: " + ", ".join(
        f"{o['name']} {o['share']:.0%}" for o in where["outputs"][:4]))
    lines.append("  bones:   " + ", ".join(
        f"{b['bone'] or '(no bone)'} {b['share']:.0%}" for b in where["bones"]))
    left_out = where.get("left_out") or []
    if left_out:
        lines.append("  left out (no share): " + ", ".join(
            f"{x['side']} {x['name']} ({x['reason']})" for x in left_out))
    worst = sorted(where.get("frac", []), key=lambda x: x["frac"])[:3]
    if worst:
        lines.append("  lowest FRAC: " + ", ".join(
            f"{w['output']}/{w['input']} {w['frac']:.3f}" for w in worst))
    lines.append("which (held-out gap after adding the effect):")
    # 1 - gap_after/gap_before is undefined where gap_before is 0 (the JSON holds 0.0)
    undefined = not report["gap_before"] > 0
    for c in report["candidates"]:
        shrink = "n/a" if undefined or c["shrink"] is None else f"{c['shrink']:.0%}"
        lines.append(f"  {c['effect']:<30} gap {c['gap_after']:<8.3g} shrink "
                     f"{shrink:>6}  [{c.get('variant', '')} @ {c.get('place', '')}]")
    if undefined and report["candidates"]:
        lines.append("  (shrink n/a: the base model's gap is 0, at the noise level, so no "
                     "shrink can be measured; the chi2 test decides)")
    ranges = report.get("not_excluded") or []
    if ranges:
        lines.append("not excluded by the data (global effects; chi2 of all lines within the "
                     "test's critical value of its best, base refitted):")
        for r in ranges:
            lines.append(f"  {r['effect']:<30} {r['parameter']} {r['low']:.3g} .. {r['high']:.3g}"
                         f" (fitted {r['fitted']:.3g}"
                         + ("; 0 inside: updating may absorb it" if r["null_inside"] else "")
                         + ")")
    return "\n".join(lines)


def uniform_columns(frequency_hz: Any, max_columns: int = 4000) -> tuple[Any, float, float]:
    """Image columns for a frequency grid: ``(line index per column, first column's
    frequency, column width)``. A uniform grid maps one line per column; a non-uniform one
    (log-spaced, gaps) is resampled at its smallest spacing (at most ``max_columns``), each
    column showing the nearest line, so features sit at their true frequency."""
    import numpy as np

    f = np.asarray(frequency_hz, float)
    if f.size < 2:
        return np.zeros(f.size, int), float(f[0]) if f.size else 0.0, 1.0
    steps = np.diff(f)
    if np.allclose(steps, steps.mean(), rtol=1e-3):
        return np.arange(f.size), float(f[0]), float(steps.mean())
    df = max(float(steps.min()), float(f[-1] - f[0]) / (max_columns - 1))
    grid = f[0] + df * np.arange(int(np.floor((f[-1] - f[0]) / df)) + 1)
    right = np.clip(np.searchsorted(f, grid), 1, f.size - 1)
    nearest = np.where(grid - f[right - 1] <= f[right] - grid, right - 1, right)
    return nearest, float(f[0]), df


def _plots(result: object, out: Path) -> list[str]:
    """Residual map and measured/base/best FRF of the worst FRF as PNG (pyqtgraph)."""
    import numpy as np

    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    import pyqtgraph as pg

    pg.mkQApp()
    data = result.data  # type: ignore[attr-defined]
    rmap = np.abs(result.residual_map)  # type: ignore[attr-defined]
    n_f, n_out, n_in = rmap.shape
    f = np.asarray(data.frequency_hz, float)
    columns, f0, df = uniform_columns(f)  # a non-uniform grid drawn at its true frequencies
    img = np.nan_to_num(rmap.reshape(n_f, n_out * n_in))[columns]
    paths = []
    residual_path, worst_path = plot_paths(out)
    # 1. residual map: frequency x (output, input), |r| in noise units, log colour
    widget = pg.PlotWidget()
    widget.resize(1000, 500)
    plot = widget.getPlotItem()
    plot.setTitle("normalised residual |H - H_base| / sigma (log10)")
    image = pg.ImageItem(np.log10(np.maximum(img, 1e-2)))
    image.setColorMap(pg.colormap.get("viridis"))
    image.setRect(pg.QtCore.QRectF(f0 - df / 2, 0, df * columns.size, n_out * n_in))
    plot.addItem(image)
    plot.setLabel("bottom", "frequency", units="Hz")
    plot.setLabel("left", "FRF index (output-major)")
    _export(plot, residual_path, paths)
    # 2. the FRF with the largest residual: measured, base model, best candidate
    energy = np.nansum(rmap**2, axis=0)
    o, i = np.unravel_index(int(np.argmax(energy)), energy.shape)
    widget2 = pg.PlotWidget()
    widget2.resize(1000, 500)
    plot = widget2.getPlotItem()
    plot.setTitle(f"|H| {data.out_names[o]} / {data.in_names[i]}: measured (white), "
                  "base (red), best candidate (green)")
    plot.setLogMode(y=True)
    plot.plot(f, np.abs(data.H[:, o, i]), pen=None, symbol="o", symbolSize=3)
    plot.plot(f, np.abs(result.H_base[:, o, i]), pen=pg.mkPen("r", width=2))  # type: ignore
    if result.H_best is not None:  # type: ignore[attr-defined]
        plot.plot(f, np.abs(result.H_best[:, o, i]), pen=pg.mkPen("g", width=2))  # type: ignore
    plot.setLabel("bottom", "frequency", units="Hz")
    plot.setLabel("left", "receptance", units="m/N")
    _export(plot, worst_path, paths)
    return paths


def _export(plot: object, path: Path, paths: list[str]) -> None:
    """Export ``plot`` as a 1000-pixel-wide PNG at ``path``; listed only if it was written
    (the exporter does not say when it could not write)."""
    from pyqtgraph.exporters import ImageExporter

    exporter = ImageExporter(plot)
    exporter.parameters()["width"] = 1000
    exporter.export(str(path))
    if not path.is_file():
        raise OSError(f"{path} could not be written")
    paths.append(str(path))


def _benchmark(args: argparse.Namespace) -> int:
    from pelvislab.model.gap import GapOptions
    from pelvislab.model.gap_benchmark import format_summary, run_benchmark

    # every option checked before anything is made or run (the benchmark takes minutes)
    if args.cases < 1:
        raise ValueError("--cases must be >= 1")
    _check_jobs(args.jobs)
    if args.chain_cases < 0:
        raise ValueError("--chain-cases must be >= 0")
    if not 0.5 <= args.chain_step_hz <= 50:
        raise ValueError("--chain-step-hz must be within 0.5-50 Hz")
    kinds = None
    if args.kinds:
        from pelvislab.model.gap_effects import EFFECT_NAMES

        kinds = comma_list(args.kinds)
        unknown = sorted(set(kinds) - {"none", *EFFECT_NAMES})
        if unknown:
            raise ValueError(f"--kinds: unknown {', '.join(unknown)}; choose from none, "
                             f"{', '.join(EFFECT_NAMES)}")
    out = check_new_output(args.json)  # a missing folder refused, as by every command
    keep_freed_memory_for_reuse()
    # test-side generators (may use the simulator); see the module docstring for why
    from pelvislab.tests.benchmarks.bench_gap import make_chain_generator, make_generator

    generator, chain = None, None
    chain_cases, names = args.chain_cases, []
    if args.source == "chain":
        chain_cases = args.cases
    else:
        generator, name = make_generator(args.source, seed=args.seed)
        names.append(name)
    if chain_cases:
        chain = make_chain_generator(seed=args.seed, step_hz=args.chain_step_hz)
        names.append(f"full simulated chain (open_simulated_bench + prepare_session, face_up "
                     f"on a {args.chain_step_hz:g} Hz grid)")
    result = run_benchmark(generator, kinds=kinds, cases_per_kind=args.cases,
                           progress=_progress(args.verbose_progress),
                           chain_generator=chain, chain_cases_per_kind=chain_cases,
                           options=GapOptions(jobs=args.jobs))
    result["generator"] = " + ".join(names)
    result["command"] = "pelvislab gap benchmark " + " ".join(sys.argv[3:]) \
        if sys.argv[1:3] == ["gap", "benchmark"] else None
    write_json(out, result)
    print(format_summary(result))
    print(f"\nJSON: {out}")
    return 0
