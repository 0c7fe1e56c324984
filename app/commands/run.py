"""``pelvislab run`` and ``pelvislab reprocess``: headless sessions (design 4.3)."""

from __future__ import annotations

import argparse

from pelvislab.app.commands._common import not_implemented


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``run`` and ``reprocess`` to the CLI."""
    p = subparsers.add_parser(
        "run", help="run a protocol headless (simulated bench unless --bench is given)",
        description="Run a measurement protocol and write the session file step by step.",
    )
    p.add_argument("protocol", metavar="PROTOCOL.toml", help="protocol file")
    p.add_argument("--out", required=True, metavar="S.h5", help="session file to write")
    p.add_argument("--bench", metavar="BENCH.toml", help="bench file; default: simulated bench")
    p.add_argument("--resume", action="store_true", help="continue an interrupted session in --out")
    p.set_defaults(handler=not_implemented("run"))

    p = subparsers.add_parser(
        "reprocess", help="recompute displacement, phasors and /frf from raw echoes",
        description="Re-track the raw echoes of a session with other settings into a new file.",
    )
    p.add_argument("session", metavar="S.h5", help="recorded session file")
    p.add_argument("--out", required=True, metavar="S2.h5", help="new session file")
    p.set_defaults(handler=not_implemented("reprocess"))
