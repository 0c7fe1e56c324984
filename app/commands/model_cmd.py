"""``pelvislab model``: modes and FRFs of the pelvis model (thesis ch. 4-5, 7, app. B, D, E)."""

from __future__ import annotations

import argparse
import json
import sys

from pelvislab.app.commands._common import check_new_output, comma_list


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``model modes`` and ``model frf`` to the CLI."""
    p = subparsers.add_parser("model", help="modes and FRFs of the pelvis model")
    sub = p.add_subparsers(dest="model_command", metavar="ACTION")
    sub.required = True
    m = sub.add_parser("modes", help="elastic modes of the model (default: thesis appendix E)",
                       description="Damped and natural frequencies (Hz), damping ratios and mode "
                       "shapes of the pelvis model's elastic modes (state-space eigenproblem, "
                       "thesis ch. 4.3, eq. 4.39-4.48 and app. B; app. D with f_k, f_c).")
    m.add_argument("--model", metavar="M.toml", help="model file; default: thesis appendix E")
    m.add_argument("--json", action="store_true", help="print JSON to stdout")
    m.add_argument("--f-k", type=float, default=None, metavar="F",
                   help="eq. 7.3 stiffness slope factor (overrides the model file)")
    m.add_argument("--f-c", type=float, default=None, metavar="F",
                   help="eq. 7.2 hysteretic damping factor (overrides the model file)")
    m.add_argument("--points", metavar="NAMES",
                   help="also give the complex mode shapes at these landmarks (JSON 'shapes')")
    m.add_argument("--landmarks", metavar="L.toml",
                   help="landmark catalogue; default: protocols/landmarks.toml")
    m.set_defaults(handler=_modes)
    f = sub.add_parser("frf", help="FRFs of the model at catalogue points",
                       description="Receptance FRFs (m/N) of the pelvis model between landmarks "
                       "of protocols/landmarks.toml, printed or written as an FRF-only file. "
                       "Outputs: displacement along the landmark direction (bone toward sensor); "
                       "inputs: force into the surface (minus the landmark direction), the "
                       "convention of a session's /frf, so both agree in sign.")
    f.add_argument("--model", metavar="M.toml", help="model file; default: thesis appendix E")
    f.add_argument("--points", metavar="NAMES",
                   help="comma-separated landmark names (outputs; also inputs unless --inputs), "
                   "e.g. sacrum_x,SIAS_R_x,SIAS_L_x (see protocols/landmarks.toml)")
    f.add_argument("--inputs", metavar="NAMES", help="comma-separated landmark names of the "
                   "excitation points (unit force into the surface, along minus the landmark "
                   "direction, as a protocol's default excitation); default: --points")
    f.add_argument("--landmarks", metavar="L.toml",
                   help="landmark catalogue; default: protocols/landmarks.toml")
    f.add_argument("--start-hz", type=float, default=5.0, help="first line, Hz (default 5)")
    f.add_argument("--stop-hz", type=float, default=300.0, help="last line, Hz (default 300)")
    f.add_argument("--step-hz", type=float, default=2.5, help="line spacing, Hz (default 2.5)")
    f.add_argument("--json", action="store_true", help="print JSON to stdout")
    f.add_argument("--out", metavar="F.h5", help="also write an FRF-only HDF5 file (/frf)")
    f.set_defaults(handler=_frf)


def _load(path: str | None):  # noqa: ANN202 - returns PelvisModel (import kept lazy)
    from pelvislab.model.pelvis import load_model

    return load_model(path)


def _modes(args: argparse.Namespace) -> int:
    import numpy as np

    from pelvislab.model.modal import model_modes

    # eq. 7.1-7.3: K (1 + f_k w / (4 w_max)) stays positive up to w_max for f_k > -4; the
    # hysteretic term f_c C w_max / 4 is a damping only for f_c >= 0
    for name, value, low in (("--f-k", args.f_k, -4.0), ("--f-c", args.f_c, 0.0)):
        if value is not None and not (np.isfinite(value) and low <= value <= 100.0
                                      and value != -4.0):
            raise ValueError(f"{name} {value}: must be between {low:g} and 100 (eq. 7.1-7.3)")
    model = _load(args.model)
    if args.f_k is not None or args.f_c is not None:
        fd = model.frequency_dependence
        model = model.with_frequency_dependence(
            fd.f_k if args.f_k is None else args.f_k, fd.f_c if args.f_c is None else args.f_c)
    modes = model_modes(model)
    result = {
        "frequencies_hz": [float(x) for x in modes.damped_frequencies_hz],
        "damping_ratios": [float(x) for x in modes.damping_ratios],
        "n_rigid_body": int(modes.n_rigid_body),
        "natural_frequencies_hz": [float(x) for x in modes.natural_frequencies_hz],
        "overdamped_poles_rad_s": [float(x.real) for x in modes.overdamped_poles],
        "model": model.name,
    }
    if args.points:
        from pelvislab.model.frf import rows_for
        from pelvislab.model.landmarks import landmark_points, load_landmarks

        names = _names(args.points)
        pts = landmark_points(names, load_landmarks(args.landmarks))
        shapes = rows_for(model, pts) @ modes.shapes  # (n_points, n_modes), eq. 4.9
        result["shapes"] = {"points": names, "real": shapes.real.tolist(),
                            "imag": shapes.imag.tolist()}
    if args.json:
        json.dump(result, sys.stdout, indent=2)
        sys.stdout.write("\n")
    else:
        print(f"model {model.name!r}: {modes.n_rigid_body} rigid-body modes, "
              f"{len(modes.poles)} elastic modes")
        print("  mode  damped f (Hz)  damping ratio")
        for i, (fr, z) in enumerate(zip(result["frequencies_hz"], result["damping_ratios"],
                                        strict=True)):
            print(f"  {i + 1:4d}  {fr:13.3f}  {z:13.5f}")
    return 0


def _names(text: str) -> list[str]:
    names = comma_list(text)
    if not names:
        raise ValueError("no landmark names given")
    return names


def _frf(args: argparse.Namespace) -> int:
    import numpy as np

    from pelvislab.model.frf import frf
    from pelvislab.model.landmarks import excitation_points, landmark_points, load_landmarks

    if not args.points:
        raise ValueError("give --points NAMES (comma-separated landmark names from "
                         "protocols/landmarks.toml, e.g. sacrum_x,SIAS_R_x,SIAS_L_x)")
    values = (args.start_hz, args.stop_hz, args.step_hz)
    if not (all(np.isfinite(values)) and 0 < args.start_hz <= args.stop_hz
            and args.step_hz > 0):
        raise ValueError("need finite 0 < --start-hz <= --stop-hz and --step-hz > 0")
    if (args.stop_hz - args.start_hz) / args.step_hz > 1_000_000:
        raise ValueError("more than a million frequency lines: choose a larger --step-hz")
    if args.out:
        check_new_output(args.out)  # a missing or read-only folder said plainly, up front
    model = _load(args.model)
    catalogue = load_landmarks(args.landmarks)
    out_names = _names(args.points)
    in_names = _names(args.inputs) if args.inputs else out_names
    outputs = landmark_points(out_names, catalogue)
    # force into the surface, as a protocol's default excitation_direction: the same sign
    # as a session's /frf for the same (output, input) names
    inputs = excitation_points(in_names, catalogue)
    n = int(np.floor((args.stop_hz - args.start_hz) / args.step_hz + 1e-9)) + 1
    f = args.start_hz + args.step_hz * np.arange(n)
    H = frf(model, f, outputs, inputs)
    if args.out:
        from pelvislab.acquisition.frfset import Channels, FrfSet, write_frf

        def channels(points) -> Channels:  # noqa: ANN001
            return Channels(list(points.name), list(points.bone), points.position_m,
                            points.direction)

        write_frf(args.out, FrfSet(f, H, channels(outputs), channels(inputs)))
        print(f"wrote {H.shape[1]} x {H.shape[2]} FRFs, {f.size} lines to {args.out}",
              file=sys.stderr)
    if args.json:
        json.dump({
            "model": model.name,
            "units": "m/N",
            "frequency_hz": f.tolist(),
            "outputs": out_names,
            "inputs": in_names,
            "input_directions": inputs.direction.tolist(),
            "H_real": H.real.tolist(),
            "H_imag": H.imag.tolist(),
        }, sys.stdout)
        sys.stdout.write("\n")
    elif not args.out:
        print("inputs: unit force into the surface (minus the landmark direction), "
              "as in a session's /frf")
        for i, o in enumerate(out_names):
            for j, e in enumerate(in_names):
                k = int(np.argmax(np.abs(H[:, i, j])))
                print(f"{o} <- {e}: max |H| = {abs(H[k, i, j]):.3e} m/N at {f[k]:g} Hz")
    return 0
