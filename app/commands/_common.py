"""Small helpers shared by the command modules."""

from __future__ import annotations

import argparse
from collections.abc import Callable

from pelvislab.app.errors import NotImplementedCommand

Handler = Callable[[argparse.Namespace], "int | None"]


def not_implemented(command: str) -> Handler:
    """A handler for a registered command whose feature is not built yet (exit code 2)."""

    def handler(args: argparse.Namespace) -> int:
        raise NotImplementedCommand(command)

    handler.not_implemented = True  # type: ignore[attr-defined]  # lets tests find stubs
    return handler
