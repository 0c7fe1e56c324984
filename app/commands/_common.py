"""Small helpers shared by the command modules."""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

from pelvislab.app.errors import NotImplementedCommand

Handler = Callable[[argparse.Namespace], "int | None"]


def not_implemented(command: str) -> Handler:
    """A handler for a registered command whose feature is not built yet (exit code 2)."""

    def handler(args: argparse.Namespace) -> int:
        raise NotImplementedCommand(command)

    handler.not_implemented = True  # type: ignore[attr-defined]  # lets tests find stubs
    return handler


def json_safe(value: object) -> object:
    """``value`` with NaN/inf floats (numpy included) replaced by None, so the file is
    strict JSON that every other tool can read."""
    import math

    if isinstance(value, dict):
        return {str(k): json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(v) for v in value]
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):
        return json_safe(value.tolist())  # numpy arrays and scalars
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def check_new_output(path: str | Path) -> Path:
    """Refuse, before any long work, an output that exists (results are never overwritten,
    like sessions) or whose folder does not."""
    target = Path(path)
    if target.is_dir():
        raise IsADirectoryError(f"{target} is a folder; give a file name for the output")
    if target.exists():
        raise FileExistsError(f"{target} exists; not overwriting it (choose another name)")
    if not target.parent.exists():
        raise FileNotFoundError(f"output folder {target.parent} does not exist")
    return target


def write_json(path: str | Path, document: object) -> Path:
    """Write a result document as strict JSON, atomically (a crash never leaves a
    half-written file) and only if no file of that name exists."""
    import json
    import os
    import tempfile

    target = check_new_output(path)
    text = json.dumps(json_safe(document), indent=2, allow_nan=False) + "\n"
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    try:
        with os.fdopen(fd, "w") as handle:
            handle.write(text)
        os.link(tmp, target)  # fails if the name appeared meanwhile: never overwrite
        Path(tmp).unlink()
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return target
