"""The ``pelvislab`` command line (design notes, section 4.3).

Each command family lives in its own module under :mod:`pelvislab.app.commands` and
registers its subparsers here. Every command exits 0 on success; bad input gives a
non-zero exit code and a one-line reason on stderr, never a traceback (``-v`` adds it).
"""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
from collections.abc import Sequence
from importlib import metadata
from typing import Any, NoReturn

from pelvislab.app.commands import COMMAND_MODULES
from pelvislab.app.errors import NotImplementedCommand

log = logging.getLogger("pelvislab")

EXIT_OK = 0
EXIT_FAILURE = 1
EXIT_USAGE = 2
EXIT_INTERRUPTED = 130
EXIT_BROKEN_PIPE = 141
"""The reader of stdout went away (``| head``): 128 + SIGPIPE, as a shell tool ends then."""


def package_version() -> str:
    """Installed version of the ``pelvislab`` distribution."""
    try:
        return metadata.version("pelvislab")
    except metadata.PackageNotFoundError:  # running from an uninstalled tree
        return "0+unknown"


def configure_logging(verbosity: int) -> None:
    """The one logging configuration of the application: stderr, level by ``-v`` count."""
    level = logging.WARNING if verbosity <= 0 else logging.INFO if verbosity == 1 else logging.DEBUG
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)


class OneLineErrorParser(argparse.ArgumentParser):
    """An argument parser whose usage errors are one line on stderr (design 4.3: "a one-line
    reason on stderr for bad input"); argparse's own printed the whole usage block first,
    five lines for ``gap diagnose``. Subcommand parsers inherit the class."""

    def error(self, message: str) -> NoReturn:
        reason = " ".join(message.split())
        self.exit(EXIT_USAGE, f"{self.prog}: error: {reason} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser with every subcommand of design 4.3 registered."""
    parser = OneLineErrorParser(
        prog="pelvislab",
        description="Vibration-based diagnosis of the sacroiliac joints: instrument control, "
        "session files, identification and sim-to-real gap diagnosis.",
    )
    parser.add_argument("--version", action="version", version=f"pelvislab {package_version()}")
    parser.add_argument(
        "-v", "--verbose", action="count", default=0,
        help="log to stderr (-v info, -vv debug); show tracebacks on errors",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    for module in COMMAND_MODULES:
        module.register(subparsers)
    _verbose_anywhere(parser)
    return parser


def _verbose_anywhere(parser: argparse.ArgumentParser) -> None:
    """Accept ``-v`` after the (sub)command too (``pelvislab identify S.h5 --json o -v``,
    as docs/identification.md writes it): every subcommand parser gets the option (its
    default left unset, so that one given only before the command stays; given on both
    sides, argparse keeps the count after the command)."""
    for action in parser._actions:  # argparse keeps subparsers only there
        if isinstance(action, argparse._SubParsersAction):
            for sub in set(action.choices.values()):
                if not any("-v" in a.option_strings for a in sub._actions):
                    sub.add_argument("-v", "--verbose", action="count",
                                     default=argparse.SUPPRESS,
                                     help="as pelvislab -v (may also come here)")
                _verbose_anywhere(sub)


def _command_parser(parser: argparse.ArgumentParser,
                    args: argparse.Namespace) -> argparse.ArgumentParser:
    """The (sub)command parser that ``args`` went through (``gap diagnose``'s for a
    ``gap diagnose`` command line), for its one-line usage errors."""
    for key in ("command", *sorted(k for k in vars(args) if k.endswith("_command"))):
        name = getattr(args, key, None)
        choices = next((a.choices for a in parser._actions  # argparse keeps them only there
                        if isinstance(a, argparse._SubParsersAction)), None)
        if not isinstance(name, str) or not choices or name not in choices:
            break
        parser = choices[name]
    return parser


class Terminated(KeyboardInterrupt):
    """SIGTERM or SIGHUP asked the command to stop: handled as Ctrl-C is (files cleaned up,
    worker processes terminated, exit 130). A subclass of KeyboardInterrupt so that no
    ``except Exception`` on the way swallows it."""


def _stop_on_termination_signals() -> dict[int, object]:
    """Turn SIGTERM and SIGHUP into :class:`Terminated` in the main thread (their default
    action ended the process at once: a partial file left behind, forked workers of the gap
    fits orphaned). A SIGHUP already ignored (nohup) stays ignored. A SIGINT inherited as
    ignored (a background job of a non-interactive shell) is handled too: ``run`` handles
    it once the run starts, but a ``kill -INT`` while it opened the bench and the file was
    ignored and the whole protocol then ran (review, session 50). ``run`` and ``gui`` put
    their own handlers over these while they run. Returns the handlers to put back."""
    previous: dict[int, object] = {}
    for name in ("SIGTERM", "SIGHUP", "SIGINT"):
        sig = getattr(signal, name, None)
        if sig is None or (name == "SIGHUP" and signal.getsignal(sig) is signal.SIG_IGN):
            continue
        if name == "SIGINT" and signal.getsignal(sig) is not signal.SIG_IGN:
            continue  # Python's own handler: KeyboardInterrupt

        def stop(signum: int, frame: object, name: str = name) -> None:
            raise Terminated(f"interrupted by {name}")

        try:
            previous[sig] = signal.signal(sig, stop)
        except ValueError:  # not the main thread (a library caller): leave them alone
            pass
    return previous


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``pelvislab`` console script; returns the process exit code."""
    parser = build_parser()
    args, unknown = parser.parse_known_args(argv)
    if unknown:  # argparse names only the top-level parser for these: name the command
        words = list(sys.argv[1:] if argv is None else argv)
        before_command = (args.command in words and unknown[0] in words
                          and words.index(unknown[0]) < words.index(args.command))
        sub = parser if before_command else _command_parser(parser, args)
        sub.error(f"unrecognized arguments: {' '.join(unknown)}")
    configure_logging(args.verbose)
    previous = _stop_on_termination_signals()
    previous_unraisable, previous_excepthook = sys.unraisablehook, sys.excepthook
    sys.unraisablehook = _quiet_after_a_failed_session_write(previous_unraisable)
    # h5py's object clean-up (Cython) prints the traceback through sys.excepthook first
    sys.excepthook = _quiet_excepthook(previous_excepthook)
    try:
        code = _run_handler(args)
    finally:
        sys.unraisablehook, sys.excepthook = previous_unraisable, previous_excepthook
        for sig, handler in previous.items():
            signal.signal(sig, handler)  # type: ignore[arg-type]
    if argv is None and _session_write_failures():
        # the process, not a caller of main(): HDF5's clean-up at exit would try the
        # failed file again and crash (segmentation fault, exit 139); every complete step
        # is on disk and the command has said what happened (session.WRITE_FAILURES)
        import atexit

        try:  # Python's exit handlers still run: the bench's last safe state, pools
            atexit._run_exitfuncs()
        except Exception as exc:
            log.error("exit handlers: %s", exc)
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    return code


def _session_write_failures() -> list[str]:
    """The session files this process failed to write (none when no session was opened)."""
    session = sys.modules.get("pelvislab.acquisition.session")
    return list(getattr(session, "WRITE_FAILURES", []) or [])


def _a_failed_write(exc: BaseException | None) -> bool:
    """Whether ``exc`` is HDF5 failing a write (or an error after a session file could not
    be written): what the command reports once in its own line."""
    if not isinstance(exc, (OSError, RuntimeError)):
        return False
    if _session_write_failures():
        return True
    # the first ones come while the failed write unwinds, before it is recorded
    session = sys.modules.get("pelvislab.acquisition.session")
    return session is not None and session._is_write_failure(exc)


def _quiet_after_a_failed_session_write(previous: Any) -> Any:
    """An unraisable-exception hook that drops h5py's object clean-up errors of a session
    file that could not be written (each dropped object printed a traceback of the same
    write failure: 14-67 lines; review, session 50)."""
    def hook(unraisable: Any) -> None:
        if _a_failed_write(unraisable.exc_value) and "h5py" in repr(unraisable.object):
            log.debug("after a failed session write: %s", unraisable.exc_value)
            return
        previous(unraisable)
    return hook


def _quiet_excepthook(previous: Any) -> Any:
    """The same for the traceback h5py's clean-up prints through ``sys.excepthook`` before
    it reports the error as unraisable (only for tracebacks inside h5py's object code)."""
    def hook(kind: Any, value: Any, tb: Any) -> None:
        frames, walk = [], tb
        while walk is not None:
            frames.append(walk.tb_frame.f_code.co_filename)
            walk = walk.tb_next
        if frames and all("h5py" in f for f in frames) and _a_failed_write(value):
            log.debug("after a failed session write: %s", value)
            return
        previous(kind, value, tb)
    return hook


def _run_handler(args: argparse.Namespace) -> int:
    try:
        code = args.handler(args)
    except NotImplementedCommand as exc:
        print(f"pelvislab {exc}", file=sys.stderr)
        return EXIT_USAGE
    except Terminated as exc:
        print(f"pelvislab: {exc}", file=sys.stderr)
        return EXIT_INTERRUPTED
    except KeyboardInterrupt:
        print("pelvislab: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:
        # `pelvislab model modes --json | head -1` said "error: [Errno 32] Broken pipe":
        # the reader had all it wanted. Quiet, and stdout pointed at nothing so that the
        # interpreter's final flush does not fail again (review, session 39)
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError, AttributeError):
            pass
        return EXIT_BROKEN_PIPE
    except Exception as exc:  # the one place that turns any failure into one line
        if args.verbose:
            log.exception("command failed")
        reason = str(exc) or exc.__class__.__name__
        reason = " ".join(reason.split())  # one line, whatever the exception carried
        # the full command ("gap diagnose", "protocol check"), as the docs show it
        action = next((getattr(args, k) for k in vars(args)
                       if k.endswith("_command") and isinstance(getattr(args, k), str)), None)
        command = f"{args.command} {action}" if action else args.command
        try:
            print(f"pelvislab {command}: error: {reason}", file=sys.stderr)
        except (OSError, ValueError):  # stderr gone (terminal closed): the code still tells
            pass
        return EXIT_FAILURE
    return EXIT_OK if code is None else int(code)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
