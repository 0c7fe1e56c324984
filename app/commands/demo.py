"""``pelvislab demo``: the whole simulated chain end to end (``make demo``).

Runs, in order, the model, a demo protocol on the simulated bench, identification, EMA and
the gap diagnosis, writing every result into one folder and printing where each is. A stage
whose command is not built yet is reported as such and skipped; it is never faked.
"""

from __future__ import annotations

import argparse
import sys
import time
from importlib import resources
from pathlib import Path

from pelvislab.app.errors import NotImplementedCommand

DEMO_PROTOCOL = "demo.toml"


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``demo`` to the CLI."""
    p = subparsers.add_parser(
        "demo", help="run the complete simulated session end to end",
        description="Simulated bench -> session file -> identification -> EMA -> gap diagnosis.",
    )
    p.add_argument("--out", default="demo-output", metavar="DIR", help="folder for all results")
    p.set_defaults(handler=run_demo)


def _stages(out: Path, protocol: Path) -> list[tuple[str, list[str], Path | None, bool]]:
    """(title, argv, result path, needs the session) for each stage of the demo."""
    session = out / "session.h5"
    return [
        ("model modes (thesis appendix E)", ["model", "modes", "--json"], None, False),
        ("protocol check", ["protocol", "check", str(protocol)], None, False),
        ("simulated session", ["run", str(protocol), "--out", str(session)], session, False),
        ("identification", ["identify", str(session), "--json", str(out / "identify.json")],
         out / "identify.json", True),
        ("experimental modal analysis", ["ema", str(session), "--json", str(out / "ema.json")],
         out / "ema.json", True),
        ("gap diagnosis", ["gap", "diagnose", str(session), "--json", str(out / "gap.json")],
         out / "gap.json", True),
    ]


def run_demo(args: argparse.Namespace) -> int:
    """Run every built stage; exit non-zero only when a built stage fails (1) or is
    interrupted (130, and the later stages are not run)."""
    from pelvislab.app.cli import EXIT_INTERRUPTED, build_parser

    out = _fresh_folder(Path(args.out))
    out.mkdir(parents=True, exist_ok=True)
    print(f"demo results go to {out}", flush=True)
    demo_started = time.perf_counter()
    protocol_resource = resources.files("pelvislab.protocols") / DEMO_PROTOCOL
    protocol = Path(str(protocol_resource))
    parser = build_parser()
    failed = False
    have_session = False
    for title, argv, result, needs_session in _stages(out, protocol):
        print(f"== {title}: pelvislab {' '.join(argv)}", flush=True)
        if needs_session and not have_session:
            print("   skipped: no session file (the run stage did not produce one)")
            continue
        if argv[0] in ("protocol", "run") and not protocol.is_file():
            print(f"   skipped: demo protocol {DEMO_PROTOCOL} is not shipped yet")
            continue
        started = time.perf_counter()
        stage_args = parser.parse_args(argv)
        try:
            code = stage_args.handler(stage_args) or 0
        except NotImplementedCommand:
            print("   skipped: not implemented yet")
            continue
        except Exception as exc:  # report and go on with the stages that do not need it
            print(f"   FAILED: {' '.join(str(exc).split())}", file=sys.stderr)
            failed = True
            continue
        elapsed = time.perf_counter() - started
        if code == EXIT_INTERRUPTED:
            # the operator stopped it (the run stage catches Ctrl-C/SIGTERM itself and says
            # so): stop here rather than report a failure and skip the rest as missing
            session = out / "session.h5"
            kept = (f"; the session so far is kept in {session} (pelvislab run {protocol} "
                    f"--out {session} --resume continues it)" if session.exists() else "")
            print(f"   interrupted: the demo stops here{kept}", file=sys.stderr)
            return EXIT_INTERRUPTED
        if code != 0:
            print(f"   FAILED with exit code {code}", file=sys.stderr)
            failed = True
            continue
        if result is not None and result.exists():
            print(f"   done in {elapsed:.1f} s -> {result}")
            if result.suffix == ".h5":
                have_session = True
        else:
            print(f"   done in {elapsed:.1f} s")
    print(f"demo finished in {time.perf_counter() - demo_started:.1f} s; results in {out}")
    return 1 if failed else 0


def _fresh_folder(out: Path) -> Path:
    """``out``, or ``out/run-N`` when ``out`` already holds a demo session: sessions are
    never overwritten, so a second ``make demo`` writes next to the first."""
    if out.exists() and not out.is_dir():
        raise NotADirectoryError(f"{out} exists and is not a folder: --out names the folder "
                                 "for the demo's results")
    if not (out / "session.h5").exists():
        return out
    n = 2
    while (out / f"run-{n}").exists():
        n += 1
    return out / f"run-{n}"
