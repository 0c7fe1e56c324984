"""``pelvislab identify``: parameter identification from /frf (thesis ch. 6-7, design 4.5)."""

from __future__ import annotations

import argparse

from pelvislab.app.commands._common import not_implemented


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``identify`` to the CLI."""
    p = subparsers.add_parser(
        "identify", help="identify stiffness, damping and mass from a session's FRFs",
    )
    p.add_argument("session", metavar="S.h5", help="session or FRF-only file")
    p.add_argument("--method", choices=("frf", "modal"), default="frf", help="updating method")
    p.add_argument("--params", metavar="NAMES", help="comma-separated parameters to identify")
    p.add_argument("--model", metavar="M.toml", help="starting model; default: thesis appendix E")
    p.add_argument("--json", required=True, metavar="OUT", help="write the result JSON here")
    p.set_defaults(handler=not_implemented("identify"))
