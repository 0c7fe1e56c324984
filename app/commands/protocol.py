"""``pelvislab protocol check``: validate a protocol file and estimate its duration."""

from __future__ import annotations

import argparse

from pelvislab.app.commands._common import not_implemented


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``protocol`` to the CLI."""
    p = subparsers.add_parser("protocol", help="protocol file tools")
    sub = p.add_subparsers(dest="protocol_command", metavar="ACTION")
    sub.required = True
    c = sub.add_parser("check", help="validate a protocol file and print its estimated duration")
    c.add_argument("file", metavar="FILE", help="protocol file (TOML)")
    c.add_argument("--bench", metavar="BENCH.toml", help="bench file whose limits apply")
    c.set_defaults(handler=not_implemented("protocol check"))
