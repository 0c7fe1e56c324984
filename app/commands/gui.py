"""``pelvislab gui``: the operator GUI, or replay of a recorded session."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``gui`` to the CLI."""
    p = subparsers.add_parser(
        "gui", help="operator GUI; with a session file: replay it",
        description="Open the operator window, or replay a recorded session.",
    )
    p.add_argument("session", nargs="?", metavar="S.h5", help="session file to replay")
    p.add_argument("--bench", metavar="BENCH.toml", help="bench file; default: simulated bench")
    p.add_argument("--screenshot", metavar="OUT.png", help="render offscreen to a PNG and exit")
    p.add_argument("--after", type=float, default=0.0, metavar="SECONDS",
                   help="with --screenshot: wait this long before rendering")
    p.add_argument("--start", metavar="PROTOCOL.toml",
                   help="start this protocol at once (prompts auto-confirmed with --screenshot)")
    p.add_argument("--out", metavar="S.h5", help="with --start: the session file to write")
    p.add_argument("--analyse", choices=("identify", "gap", "ema"),
                   help="with a session: run the identification, the gap diagnosis or the "
                   "modal analysis at once")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    """Open the window (or render it to --screenshot)."""
    session = Path(args.session) if args.session else None
    if session is not None and not session.is_file():
        raise FileNotFoundError(f"no such session file: {session}")
    if args.analyse and session is None:
        raise ValueError("--analyse needs a session file (pelvislab gui S.h5 --analyse …)")
    if not 0 <= args.after <= 3600:  # inf or NaN would never render
        raise ValueError("--after must be within 0-3600 seconds")
    if args.after and not args.screenshot:  # else silently ignored, the window left open
        raise ValueError("--after goes with --screenshot (the wait before rendering)")
    if args.out and not args.start:
        raise ValueError("--out goes with --start (the session file the started run writes)")
    if args.bench:
        # a missing or invalid bench file is the command's error, not a cut table row with
        # Start still enabled (first-day review, session 36)
        from pelvislab.drivers.bench import BenchConfig

        BenchConfig.load(args.bench)
    start = Path(args.start) if args.start else None
    if start is not None and not start.is_file():
        raise FileNotFoundError(f"no such protocol file: {start}")
    if args.out and Path(args.out).exists():
        raise FileExistsError(f"{args.out} exists; not overwriting it")
    from pelvislab.app.gui_main import run_gui

    return run_gui(session, Path(args.screenshot) if args.screenshot else None, args.after,
                   Path(args.bench) if args.bench else None, start_protocol=start,
                   out_path=Path(args.out) if args.out else None, analyse=args.analyse)
