"""``pelvislab ema``: experimental modal analysis from /frf (thesis ch. 10-11, 14).

Poles by p-LSCF with a stabilisation diagram, residues by LSFD (``pelvislab.model.ema``),
rigid-body content of the shapes and a per-channel rigid-motion check
(``pelvislab.model.rigid_body``); with ``--update``, MAC-based model updating on the
identified modes (thesis eq. 14.1, ``pelvislab.model.correlation_updating``). Writes a
JSON file (``-`` for stdout) and prints a one-line-per-mode summary on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from pelvislab.app.commands._common import (
    check_new_output,
    comma_list,
    incomplete_session_warning,
    infinite_as_unmeasured,
    require_response,
    write_json,
)

#: Below this significance a mode is marked weak in the summary (docs/ema.md, known limits:
#: noise poles passed the check at 1.25-1.84; real modes measured 5.5-700)
WEAK_SIGNIFICANCE = 2.0


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``ema`` to the CLI."""
    p = subparsers.add_parser(
        "ema", help="poles, damping and mode shapes from a session's FRFs",
        description="Experimental modal analysis of the /frf receptances: p-LSCF poles with a "
        "stabilisation diagram and automatic (or --frequencies) pole selection, LSFD residues "
        "with lower/upper residuals, complex shapes, complexity (MPC/MPD), rigid-body content.",
    )
    p.add_argument("session", metavar="S.h5", help="session or FRF-only file")
    p.add_argument("--band", nargs=2, type=float, metavar=("LO", "HI"), help="band in Hz")
    p.add_argument("--json", required=True, metavar="OUT", help="write the result JSON here "
                   "('-' for stdout)")
    p.add_argument("--frequencies", nargs="+", type=float, metavar="F",
                   help="manual pole selection: the stable poles nearest these frequencies (Hz)")
    p.add_argument("--max-order", type=int, metavar="N",
                   help="highest model order of the stabilisation diagram (default: automatic)")
    p.add_argument("--refine", action="store_true",
                   help="polish the poles by a bounded nonlinear pole/residue fit to the FRFs, "
                   "which removes p-LSCF's damping bias and gives the uncertainties (for noise "
                   "independent between lines and FRFs); only when every mode of the band is "
                   "selected: a mode left out pulls the refined poles")
    p.add_argument("--plot", action="store_true",
                   help="also write OUT_stabilisation.png (OUT without its suffix): the "
                   "stabilisation diagram under the summed FRF, as the GUI's Modes tab shows "
                   "it (needs --json to a file)")
    p.add_argument("--no-diagram", action="store_true",
                   help="leave the stabilisation diagram out of the JSON")
    p.add_argument("--update", metavar="NAMES",
                   help="then update these model parameters (comma-separated, e.g. "
                   "k_io,k_asa,c_sij; attachment coordinates r_<group>_<a|b>_<x|y|z>) so the "
                   "model's modes match the measured ones: MAC-based updating, thesis eq. 14.1 "
                   "(JSON key model_updating)")
    p.add_argument("--model", metavar="M.toml",
                   help="model to update (with --update); default: thesis appendix E")
    p.add_argument("--with-damping", action="store_true",
                   help="with --update: match the measured damping ratios too (only where the "
                   "grid resolves the modes' bandwidths; default: shapes and frequencies)")
    p.add_argument("--no-rigid-filter", action="store_true",
                   help="with --update: correlate the plain shapes at the channels instead of "
                   "the rigid-body filtered ones of thesis fig. 14.1 (which need a layout that "
                   "determines all six rigid motions)")
    p.set_defaults(handler=run_ema)


def _clean(value: object) -> object:
    """JSON-safe copy: NaN/inf -> None, numpy scalars -> Python."""
    if isinstance(value, dict):
        return {str(k): _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if hasattr(value, "item") and not isinstance(value, (str, bytes)):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def _finite_or_none(values: object, index: int) -> float | None:
    """``values[index]`` as a float, or None when absent or not finite (JSON has no NaN)."""
    if index >= len(values):
        return None
    v = float(values[index])
    return v if math.isfinite(v) else None


def result_to_json(frf: object, result: object, diagram: bool = True) -> dict:
    """The JSON document of an :class:`~pelvislab.model.ema.EmaResult` on an FRF set."""
    import numpy as np

    from pelvislab.model.ema import pole_frequency_damping
    from pelvislab.model.rigid_body import filter_bones, filter_global

    outputs = frf.outputs
    shapes = result.shapes
    rigid: list[dict | None] = [None] * result.frequency_hz.size
    for r in range(shapes.shape[1]):
        # on the channels whose entry is known: an entry left out (null, no FRF measured
        # around the mode) made every number of the mode null (review of the EMA path)
        known = np.flatnonzero(np.isfinite(shapes[:, r]))
        pos, dirs = outputs.position_m[known], outputs.direction[known]
        g = filter_global(shapes[known, r], pos, dirs)
        if g.rank == 6:
            b = filter_bones(g.x_el, [outputs.bone[k] for k in known], pos, dirs)
            rigid[r] = {"global_content": float(g.rigid_content[0]),
                        "bone_rigidity": {bone: float(b.rigidity[bone][0]) for bone in b.bones
                                          if b.rank[bone] == 6}}
    checks = _channel_check(frf, result)
    modes = []
    for r in range(result.frequency_hz.size):
        modes.append({
            "frequency_hz": float(result.frequency_hz[r]),
            "damping_ratio": float(result.damping_ratio[r]),
            "frequency_std_hz": _finite_or_none(result.frequency_std_hz, r),
            "damping_ratio_std": _finite_or_none(result.damping_ratio_std, r),
            "complexity": float(result.complexity[r]),
            "mpc": float(result.mpc[r]),
            "mpd_deg": float(result.mpd_deg[r]),
            "significance": float(result.significance[r]) if result.significance.size else None,
            "pole_rad_s": [float(result.poles[r].real), float(result.poles[r].imag)],
            "shape": {"re": np.real(shapes[:, r]).tolist(), "im": np.imag(shapes[:, r]).tolist()},
            "participation": {"re": np.real(result.participation[r]).tolist(),
                              "im": np.imag(result.participation[r]).tolist()},
            "rigid_body": rigid[r],
        })
    doc = {
        "modes": modes,
        "outputs": [{"name": n, "bone": b} for n, b in zip(outputs.name, outputs.bone,
                                                            strict=True)],
        "inputs": [{"name": n, "bone": b} for n, b in zip(frf.inputs.name, frf.inputs.bone,
                                                           strict=True)],
        "band_hz": [float(result.fit_frequency_hz.min()), float(result.fit_frequency_hz.max())],
        "n_lines": int(result.fit_frequency_hz.size),
        "selection": result.selection,
        "fit_error": result.fit_error(),
        "notes": list(result.notes),
        "residual_modes": [{"frequency_hz": float(fr), "damping_ratio": float(zr)}
                           for fr, zr in zip(*pole_frequency_damping(result.residual_poles),
                                             strict=True)],
        "method": "p-LSCF (z-domain) poles, LSFD residues with lower/upper residuals"
                  + (", poles refined by a pole/residue fit"
                     if np.any(np.isfinite(result.damping_ratio_std)) else ""),
    }
    if checks is not None:
        doc["channel_check"] = checks
    if diagram and result.diagram is not None:
        doc["stabilisation"] = result.diagram.as_rows()
    return _clean(doc)


def _channel_check(frf: object, result: object) -> list[dict] | None:
    """Rigid-motion check of every output channel (``rigid_body.check_channels``).

    Shapes: the measured FRF lines of the band (operating deflection shapes, one per line and
    input, where every output was measured); if fewer than 6, the identified mode shapes.
    None when no output lies on a bone.
    """
    import numpy as np

    from pelvislab.model.rigid_body import check_channels

    outputs = frf.outputs
    if not any(outputs.bone):
        return None
    H = result.H_measured  # (n_f, n_out, n_in) in the band
    cols = [H[k, :, i] for k in range(H.shape[0]) for i in range(H.shape[2])
            if np.all(np.isfinite(H[k, :, i]))]
    shapes = np.array(cols).T if len(cols) >= 6 else result.shapes
    if shapes.size == 0 or not np.all(np.isfinite(shapes)):
        return None
    check = check_channels(shapes, outputs.bone, outputs.position_m, outputs.direction)
    return [{"name": outputs.name[c], "bone": outputs.bone[c],
             "relative_residual": float(check.relative_residual[c]),
             "flagged": bool(check.flagged[c]),
             "direction_error_deg": float(check.direction_error_deg[c]),
             "best_direction": check.best_direction[c].tolist(),
             "position_shift_m": check.position_shift_m[c].tolist()}
            for c in range(len(outputs))]


def mac_updating(frf: object, result: object, model: object, names: list[str],
                 filter_rigid: bool = True, with_damping: bool = False) -> dict:
    """``model``'s parameters ``names`` updated on the EMA's modes (thesis eq. 14.1,
    :func:`~pelvislab.model.correlation_updating.update_by_mac`), as a JSON-ready dict. A
    layout or mode set the updating refuses gives ``{"error": reason, ...}`` instead, so
    that the EMA result is still written. Shapes (MAC) and natural frequencies are matched;
    the measured damping ratios only ``with_damping``: the EMA's damping is not reliable
    for modes narrower than the line spacing (docs/ema.md), and its relative errors would
    outweigh the frequencies'."""
    from pelvislab.model.correlation_updating import MeasuredModes, update_by_mac

    head = {"method": "MAC-based model updating (thesis eq. 14.1, fig. 14.1 correlation)",
            "parameters_requested": names, "filter_rigid": filter_rigid,
            "damping_ratios_fitted": with_damping}
    if result.frequency_hz.size == 0:
        return {**head, "error": "no measured mode to update the model on"}
    o = frf.outputs
    measured = MeasuredModes(result.frequency_hz, result.shapes, tuple(o.bone), o.position_m,
                             o.direction, damping_ratio=result.damping_ratio)
    try:
        updated = update_by_mac(model, measured, names, filter_rigid=filter_rigid,
                                damping_weight=1.0 if with_damping else 0.0)
    except ValueError as exc:
        return {**head, "error": str(exc).replace("filter_rigid=False",
                                                  "--no-rigid-filter (filter_rigid=False)")}
    return {**head, **updated.as_dict()}


def stability_plot_path(out: Path) -> Path:
    """The PNG ``ema --json OUT --plot`` writes next to its JSON."""
    return Path(f"{Path(out).with_suffix('')}_stabilisation.png")


def _plot(result: Any, path: Path) -> None:
    """The summed FRF over the stabilisation diagram as a PNG (pyqtgraph, offscreen)."""
    import os

    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    import pyqtgraph as pg
    from pyqtgraph.exporters import ImageExporter

    from pelvislab.app.gui_plots import draw_ema

    pg.mkQApp()
    layout = pg.GraphicsLayoutWidget()
    layout.resize(1000, 700)
    top = layout.addPlot(row=0, col=0, title="Sum of |H| over the FRFs (dB re 1 m/N)")
    bottom = layout.addPlot(row=1, col=0, title="Stabilisation diagram (grey new, blue "
                            "stable frequency, green + damping, red all); dashed: modes")
    bottom.setXLink(top)
    bottom.setLabel("bottom", "frequency", units="Hz")
    bottom.setLabel("left", "model order")
    draw_ema(top, bottom, result)
    layout.ci.setGeometry(0, 0, 1000, 700)  # the widget is never shown: size its layout
    exporter = ImageExporter(layout.ci)
    exporter.parameters()["width"] = 1000
    exporter.export(str(path))
    if not path.is_file():  # the exporter does not say when it could not write
        raise OSError(f"{path} could not be written")


def ema_file(path: Path, band_hz: tuple[float, float] | None = None,
             frequencies_hz: list[float] | None = None, max_order: int | None = None,
             refine: bool = False) -> tuple[Any, Any]:
    """Read ``/frf`` of a session or FRF-only file and run the EMA on it (with its
    ``H_std``): the step shared by ``pelvislab ema`` and the GUI's replay view.
    Returns ``(FrfSet, EmaResult)``."""
    import numpy as np

    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.ema import ema

    frf = read_frf(Path(path))
    infinite_note = infinite_as_unmeasured(frf)
    require_response(frf.H)
    H_std, note = frf.H_std, None
    if H_std is not None:
        measured = np.isfinite(frf.H)
        if not np.any(measured & np.isfinite(H_std) & (H_std > 0)):
            # written as zeros or NaN (another tool): weigh as without H_std, and say so
            H_std, note = None, ("H_std holds no positive finite value on the measured "
                                 "lines: ignored (each FRF weighted by its RMS)")
    result = ema(frf.frequency_hz, frf.H, band_hz=band_hz, H_std=H_std,
                 max_order=max_order, frequencies_hz=frequencies_hz, refine=refine)
    result.notes[:0] = [n for n in (infinite_note, note) if n]
    return frf, result


def run_ema(args: argparse.Namespace) -> int:
    """Handler of ``pelvislab ema``."""
    out = None if args.json == "-" else Path(args.json)
    if out is not None:  # before the fit: a finished result is never written over, nor lost
        out = check_new_output(out)  # (a folder it cannot write in, too)
    plot_path = None
    if args.plot:
        if out is None:
            raise ValueError("--plot needs --json to a file (the PNG goes next to it)")
        plot_path = check_new_output(stability_plot_path(out))
    if (args.model or args.no_rigid_filter or args.with_damping) and args.update is None:
        raise ValueError("--model, --no-rigid-filter and --with-damping go with --update")
    model, names = None, []
    if args.update is not None:  # the model and the names checked before any fit
        # ("" too: it was a silent no-op, exit 0, where "," is an error: review 67)
        from pelvislab.model.correlation_updating import updating_space
        from pelvislab.model.pelvis import load_model

        names = comma_list(args.update)
        if not names:
            raise ValueError("--update needs at least one parameter name")
        model = load_model(args.model)
        try:
            updating_space(model, names)
        except KeyError as exc:
            raise ValueError(f"--update: {exc.args[0]}") from None
    if args.frequencies is not None and not all(
            math.isfinite(f) and f > 0 for f in args.frequencies):
        raise ValueError(f"--frequencies {args.frequencies}: must be positive frequencies, Hz")
    warning = incomplete_session_warning(args.session)
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    if args.max_order is not None and args.max_order < 1:
        raise ValueError(f"--max-order must be >= 1, got {args.max_order}")
    frf, result = ema_file(Path(args.session), tuple(args.band) if args.band else None,
                           args.frequencies, args.max_order, args.refine)
    doc = result_to_json(frf, result, diagram=not args.no_diagram)
    if args.update:
        doc["model_updating"] = _clean(mac_updating(
            frf, result, model, names, filter_rigid=not args.no_rigid_filter,
            with_damping=args.with_damping))
    if out is None:
        print(json.dumps(doc, indent=1))
    else:
        write_json(out, doc)  # atomic, and still never over an existing file
    if plot_path is not None:
        _plot(result, plot_path)
        print(f"plot: {plot_path}", file=sys.stderr)
    for m in doc["modes"]:
        zeta_sd = m["damping_ratio_std"]
        zeta = (f"zeta {m['damping_ratio']:.4g}" if zeta_sd is None
                else f"zeta {m['damping_ratio']:.4g} +/- {zeta_sd:.2g}")
        sig = m.get("significance")
        # docs/ema.md: judge a mode below ~2 on the stabilisation diagram; the summary did
        # not show it (a noise pole at 55.4 Hz, 1.35, read like the beam's modes: review 67)
        weak = ("" if sig is None else f"  significance {sig:.3g}"
                + ("  (weak: check it on the stabilisation diagram)"
                   if sig < WEAK_SIGNIFICANCE else ""))
        print(f"{m['frequency_hz']:10.3f} Hz  {zeta}  complexity {m['complexity']:.3f}{weak}",
              file=sys.stderr)
    for note in doc["notes"]:
        print(f"note: {note}", file=sys.stderr)
    for c in doc.get("channel_check") or []:
        if c["flagged"]:
            print(f"channel {c['name']} is inconsistent with rigid motion of {c['bone']} "
                  f"(residual {c['relative_residual']:.2f}; best direction "
                  f"{c['direction_error_deg']:.0f} deg off)", file=sys.stderr)
    if not doc["modes"]:
        print("no mode found in the band", file=sys.stderr)
    upd = doc.get("model_updating")
    if upd is not None:
        if "error" in upd:
            print(f"model updating: not done: {upd['error']}", file=sys.stderr)
            return 1
        print(f"model updating (eq. 14.1): {upd['message']}", file=sys.stderr)
        for name, p in upd["parameters"].items():
            print(f"  {name:14s} {p['value']:.5g} +- {p['std']:.2g}", file=sys.stderr)
        for pair in upd["pairs"]:
            print(f"  measured mode {pair['measured']} <-> model mode {pair['model']}: MAC "
                  f"{pair['mac']:.4f}, frequency error {100 * pair['frequency_error']:+.2f} %",
                  file=sys.stderr)
    return 0
