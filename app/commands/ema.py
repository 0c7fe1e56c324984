"""``pelvislab ema``: experimental modal analysis from /frf (thesis ch. 10-11, 14)."""

from __future__ import annotations

import argparse

from pelvislab.app.commands._common import not_implemented


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``ema`` to the CLI."""
    p = subparsers.add_parser("ema", help="poles, damping and mode shapes from a session's FRFs")
    p.add_argument("session", metavar="S.h5", help="session or FRF-only file")
    p.add_argument("--band", nargs=2, type=float, metavar=("LO", "HI"), help="band in Hz")
    p.add_argument("--json", required=True, metavar="OUT", help="write the result JSON here")
    p.set_defaults(handler=not_implemented("ema"))
