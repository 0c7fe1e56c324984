"""``pelvislab export-uff`` / ``import-uff``: FRF interchange via UFF 58 (+ geometry)."""

from __future__ import annotations

import argparse

from pelvislab.app.commands._common import not_implemented


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``export-uff`` and ``import-uff`` to the CLI."""
    e = subparsers.add_parser("export-uff", help="write a session's FRFs as UFF 58 with geometry")
    e.add_argument("session", metavar="S.h5", help="session or FRF-only file")
    e.add_argument("out", metavar="OUT.uff", help="UFF file to write")
    e.set_defaults(handler=not_implemented("export-uff"))
    i = subparsers.add_parser("import-uff", help="read UFF 58 FRFs into an FRF-only session file")
    i.add_argument("uff", metavar="IN.uff", help="UFF file to read")
    i.add_argument("--out", required=True, metavar="S.h5", help="FRF-only file to write")
    i.add_argument("--points", metavar="POINTS.toml", help="map UFF nodes to landmarks and bones")
    i.set_defaults(handler=not_implemented("import-uff"))
