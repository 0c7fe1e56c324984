"""``pelvislab export-uff`` / ``import-uff``: FRF interchange via UFF 58 (+ geometry, modes)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pelvislab.app.commands._common import (
    check_new_output,
    incomplete_session_warning,
    infinite_as_unmeasured,
)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``export-uff`` and ``import-uff`` to the CLI."""
    e = subparsers.add_parser(
        "export-uff", help="write a session's FRFs as UFF 58 with geometry",
        description="Write /frf as UFF: 164 (SI units), geometry (2411 or 15), one binary "
        "dataset 58 per measured FRF (receptance: H round-trips exactly; UFF 58 has no place "
        "for H_std or acquisition times, which are not written), modes as 55 when given.",
    )
    e.add_argument("session", metavar="S.h5", help="session or FRF-only file")
    e.add_argument("out", metavar="OUT.uff", help="UFF file to write (must not exist)")
    modes = e.add_mutually_exclusive_group()
    modes.add_argument("--modes", metavar="EMA.json",
                       help="add the modes of a `pelvislab ema --json` result as dataset 55")
    modes.add_argument("--ema", action="store_true",
                       help="run the automatic modal analysis now and add its modes")
    e.add_argument("--ascii", action="store_true",
                   help="ASCII dataset 58 (values with 12 significant digits, frequencies "
                   "with 6: not an exact round trip; refused where two lines would become "
                   "one)")
    e.add_argument("--geometry", type=int, choices=(2411, 15), default=2411,
                   help="geometry dataset (default 2411, double precision)")
    e.set_defaults(handler=run_export)
    i = subparsers.add_parser(
        "import-uff", help="read UFF 58 FRFs into an FRF-only session file",
        description="Read every FRF dataset 58 (receptance, mobility or accelerance; the latter "
        "two converted to receptance) with node geometry into an FRF-only file.",
    )
    i.add_argument("uff", metavar="IN.uff", help="UFF file to read")
    i.add_argument("--out", required=True, metavar="S.h5", help="FRF-only file to write")
    i.add_argument("--points", metavar="POINTS.toml", help="map UFF nodes to landmarks and bones")
    i.set_defaults(handler=run_import)


def _modes_from_json(path: Path, frf: object) -> object:
    import numpy as np

    from pelvislab.acquisition.uff import UffModes

    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"no such file: {path}") from None
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path} is not JSON ({exc})") from None
    try:
        names = [o["name"] for o in doc["outputs"]]
        modes = doc["modes"]
        def part(values: list) -> np.ndarray:
            # `ema` writes null for an entry not measured around the mode (strict JSON)
            return np.array([np.nan if v is None else v for v in values], dtype=float)

        shapes = np.array([part(m["shape"]["re"]) + 1j * part(m["shape"]["im"])
                           for m in modes]).T.reshape(len(names), len(modes))
        freq = np.array([m["frequency_hz"] for m in modes], dtype=float)
        zeta = np.array([m["damping_ratio"] for m in modes], dtype=float)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{path} is not a `pelvislab ema` result with shapes ({exc})") from None
    missing = [n for n in frf.outputs.name if n not in names]
    if missing:
        raise ValueError(f"{path} has no shape entries for output(s) {missing}")
    order = [names.index(n) for n in frf.outputs.name]
    return UffModes(freq, zeta, shapes[order])


def run_export(args: argparse.Namespace) -> int:
    """Handler of ``pelvislab export-uff``."""
    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.acquisition.uff import UffModes, write_uff

    out = check_new_output(args.out)  # before the work: a missing or read-only folder too
    warning = incomplete_session_warning(args.session)
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    frf = read_frf(Path(args.session))
    import numpy as np

    if not np.isfinite(frf.H).any():  # a file of geometry only, which import-uff refuses
        raise ValueError(f"{args.session} holds no measured FRF line yet: nothing to export")
    infinite = infinite_as_unmeasured(frf)
    if infinite:  # dataset 58 holds the measured lines only
        print(f"warning: {infinite}", file=sys.stderr)
    ascii_note = None
    if args.ascii:  # refused before the modal analysis, noted after the file is written
        from pelvislab.acquisition.uff import ascii_frequency_note

        ascii_note = ascii_frequency_note(frf.frequency_hz)
    modes = None
    if args.modes:
        modes = _modes_from_json(Path(args.modes), frf)
    elif args.ema:
        from pelvislab.app.commands.ema import ema_file

        _, result = ema_file(Path(args.session))  # as `pelvislab ema` does it
        modes = UffModes(result.frequency_hz, result.damping_ratio, result.shapes)
        for note in result.notes:  # what `pelvislab ema` would say (modes left out, ...)
            print(f"note (ema): {note}", file=sys.stderr)
    n = write_uff(out, frf, modes, binary=not args.ascii, geometry=args.geometry)
    if ascii_note:
        print(f"note: {ascii_note}", file=sys.stderr)
    if frf.H_std is not None:
        # what each analysis of the imported file does without it (`identify` and `gap
        # diagnose` estimate the noise from the data; `ema` does not: docs/ema.md)
        print("note: H_std is not in the UFF file (dataset 58 has no place for it): on the "
              "imported file `identify` (by default) and `gap diagnose` estimate the noise from "
              "the data, and `ema` weights each FRF by 1/RMS of its values, with no per-line "
              "weights and no note of a missing mode (which needs H_std)", file=sys.stderr)
    n_modes = 0
    if modes is not None:
        # a mode without any shape entry (no FRF measured around it) gets no dataset 55
        written = np.isfinite(np.asarray(modes.shapes)).any(axis=0)
        n_modes = int(written.sum())
        for f_hz, ok in zip(modes.frequency_hz, written, strict=True):
            if not ok:
                print(f"note: the mode at {f_hz:.6g} Hz is not in the file: no output has a "
                      "shape entry for it (no FRF measured around it)", file=sys.stderr)
    print(f"wrote {out}: {n} datasets ({n_modes} modes)", file=sys.stderr)
    return 0


def run_import(args: argparse.Namespace) -> int:
    """Handler of ``pelvislab import-uff``."""
    from pelvislab.acquisition.frfset import write_frf
    from pelvislab.acquisition.uff import read_points_file, read_uff

    out = check_new_output(args.out)
    points = read_points_file(Path(args.points)) if args.points else None
    frf, notes = read_uff(Path(args.uff), points)
    write_frf(out, frf)
    for note in notes:
        print(f"note: {note}", file=sys.stderr)
    print(f"wrote {out}: {frf.H.shape[0]} lines, {len(frf.outputs)} outputs, "
          f"{len(frf.inputs)} inputs", file=sys.stderr)
    return 0
