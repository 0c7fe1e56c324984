"""``pelvislab gap``: sim-to-real gap diagnosis and its withheld-effect self-check (design 4.4)."""

from __future__ import annotations

import argparse

from pelvislab.app.commands._common import not_implemented


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``gap diagnose`` and ``gap benchmark`` to the CLI."""
    p = subparsers.add_parser("gap", help="sim-to-real gap diagnosis")
    sub = p.add_subparsers(dest="gap_command", metavar="ACTION")
    sub.required = True
    d = sub.add_parser("diagnose", help="where the model misses the data, and which effect")
    d.add_argument("session", metavar="S.h5", help="session or FRF-only file")
    d.add_argument("--model", metavar="M.toml", help="base model; default: thesis appendix E")
    d.add_argument("--json", required=True, metavar="OUT", help="write the diagnosis JSON here")
    d.set_defaults(handler=not_implemented("gap diagnose"))
    b = sub.add_parser("benchmark", help="diagnose data sets with a withheld effect each")
    b.add_argument("--json", required=True, metavar="OUT", help="write the benchmark JSON here")
    b.set_defaults(handler=not_implemented("gap benchmark"))
