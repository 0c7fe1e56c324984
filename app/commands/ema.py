"""``pelvislab ema``: experimental modal analysis from /frf (thesis ch. 10-11, 14).

Poles by p-LSCF with a stabilisation diagram, residues by LSFD (``pelvislab.model.ema``),
rigid-body content of the shapes and a per-channel rigid-motion check
(``pelvislab.model.rigid_body``). Writes a JSON file
(``-`` for stdout) and prints a one-line-per-mode summary on stderr.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path


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
                   help="polish the selected poles by a bounded nonlinear pole/residue fit")
    p.add_argument("--no-diagram", action="store_true",
                   help="leave the stabilisation diagram out of the JSON")
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


def result_to_json(frf: object, result: object, diagram: bool = True) -> dict:
    """The JSON document of an :class:`~pelvislab.model.ema.EmaResult` on an FRF set."""
    import numpy as np

    from pelvislab.model.rigid_body import filter_bones, filter_global

    outputs = frf.outputs
    shapes = result.shapes
    rigid: list[dict | None] = [None] * result.frequency_hz.size
    if shapes.size:
        g = filter_global(shapes, outputs.position_m, outputs.direction)
        if g.rank == 6:
            b = filter_bones(g.x_el, outputs.bone, outputs.position_m, outputs.direction)
            rigid = [{"global_content": float(g.rigid_content[r]),
                      "bone_rigidity": {bone: float(b.rigidity[bone][r]) for bone in b.bones
                                        if b.rank[bone] == 6}}
                     for r in range(shapes.shape[1])]
    checks = _channel_check(frf, result)
    modes = []
    for r in range(result.frequency_hz.size):
        modes.append({
            "frequency_hz": float(result.frequency_hz[r]),
            "damping_ratio": float(result.damping_ratio[r]),
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
        "method": "p-LSCF (z-domain) poles, LSFD residues with lower/upper residuals",
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


def run_ema(args: argparse.Namespace) -> int:
    """Handler of ``pelvislab ema``."""
    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.ema import ema

    out = None if args.json == "-" else Path(args.json)
    if out is not None:  # before the fit: a finished result is never written over, nor lost
        if out.exists():
            raise FileExistsError(f"{out} exists; not overwriting it")
        if not out.parent.is_dir():
            raise FileNotFoundError(f"output folder {out.parent} does not exist")
    frf = read_frf(Path(args.session))
    if args.max_order is not None and args.max_order < 1:
        raise ValueError(f"--max-order must be >= 1, got {args.max_order}")
    result = ema(frf.frequency_hz, frf.H, band_hz=tuple(args.band) if args.band else None,
                 H_std=frf.H_std, max_order=args.max_order, frequencies_hz=args.frequencies,
                 refine=args.refine)
    doc = result_to_json(frf, result, diagram=not args.no_diagram)
    text = json.dumps(doc, indent=1)
    if out is None:
        print(text)
    else:
        with out.open("x", encoding="utf-8") as fh:  # "x": still never overwrite
            fh.write(text + "\n")
    for m in doc["modes"]:
        print(f"{m['frequency_hz']:10.3f} Hz  zeta {m['damping_ratio']:.4f}  "
              f"complexity {m['complexity']:.3f}", file=sys.stderr)
    for note in doc["notes"]:
        print(f"note: {note}", file=sys.stderr)
    for c in doc.get("channel_check") or []:
        if c["flagged"]:
            print(f"channel {c['name']} is inconsistent with rigid motion of {c['bone']} "
                  f"(residual {c['relative_residual']:.2f}; best direction "
                  f"{c['direction_error_deg']:.0f} deg off)", file=sys.stderr)
    if not doc["modes"]:
        print("no mode found in the band", file=sys.stderr)
    return 0
