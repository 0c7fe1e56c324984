"""``pelvislab model``: modes and FRFs of the pelvis model (thesis ch. 4-5, app. E)."""

from __future__ import annotations

import argparse

from pelvislab.app.commands._common import not_implemented


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``model modes`` and ``model frf`` to the CLI."""
    p = subparsers.add_parser("model", help="modes and FRFs of the pelvis model")
    sub = p.add_subparsers(dest="model_command", metavar="ACTION")
    sub.required = True
    m = sub.add_parser("modes", help="elastic modes of the model (default: thesis appendix E)")
    m.add_argument("--model", metavar="M.toml", help="model file; default: thesis appendix E")
    m.add_argument("--json", action="store_true", help="print JSON to stdout")
    m.set_defaults(handler=not_implemented("model modes"))
    f = sub.add_parser("frf", help="FRFs of the model at catalogue points")
    f.add_argument("--model", metavar="M.toml", help="model file; default: thesis appendix E")
    f.add_argument("--points", metavar="NAMES", help="comma-separated landmark names")
    f.add_argument("--json", action="store_true", help="print JSON to stdout")
    f.set_defaults(handler=not_implemented("model frf"))
