"""``pelvislab gui``: the operator GUI, or replay of a recorded session."""

from __future__ import annotations

import argparse

from pelvislab.app.commands._common import not_implemented


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``gui`` to the CLI."""
    p = subparsers.add_parser(
        "gui", help="operator GUI; with a session file: replay it",
        description="Open the operator window, or replay a recorded session.",
    )
    p.add_argument("session", nargs="?", metavar="S.h5", help="session file to replay")
    p.add_argument("--screenshot", metavar="OUT.png", help="render offscreen to a PNG and exit")
    p.add_argument("--after", type=float, default=0.0, metavar="SECONDS",
                   help="with --screenshot: wait this long before rendering")
    p.set_defaults(handler=not_implemented("gui"))
