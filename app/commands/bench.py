"""``pelvislab bench check``: contact every instrument of a bench file, drive nothing.

A lab's first contact with its instruments (a first-day review, session 36: the only
hardware test had been a run, which drives the shaker). Opening is the same as a run's
(``drivers.bench.open_bench``): the generators are identified before anything else is sent
and their outputs switched off; then each identity, resource and reference lock is printed
and the bench is made safe and closed.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

EXIT_FAULT = 3
EXIT_UNSAFE = 5


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``bench`` to the CLI."""
    p = subparsers.add_parser("bench", help="bench file tools")
    sub = p.add_subparsers(dest="bench_command", metavar="ACTION")
    sub.required = True
    c = sub.add_parser(
        "check", help="contact every instrument of a bench file; outputs stay off",
        description="Open each instrument of the bench file in a run's order (trigger, "
        "drive, digitizer, pulsers), print its identity, resource and 10 MHz reference "
        "lock, then switch every output off and close. Nothing is driven. Exit 1 for a "
        "bad bench file, 3 naming the instrument that did not answer as expected, 5 when an "
        "output could not be confirmed off.")
    c.add_argument("file", metavar="BENCH.toml", help="bench file (docs/bench-file.md)")
    c.set_defaults(handler=check_command)


def _lock_text(instrument: object) -> str:
    ask = getattr(instrument, "reference_locked", None)
    if ask is None:
        return ""
    locked = ask()
    return {True: "reference locked", False: "REFERENCE NOT LOCKED",
            None: "reference lock not reported"}[locked]


def drive_calibration_text(config: Any) -> str:
    """The bench's drive chain calibration in a few words: the constant, or the table's
    rows, range and file."""
    span = config.drive_calibration_range_hz
    u_rel = tuple(getattr(config, "drive_calibration_u_rel", ()))
    if not u_rel:  # (a simulated chain is exact)
        stated = "" if getattr(config, "simulated", False) else "; its uncertainty not stated"
    elif len(u_rel) == 1:
        stated = f", u = {100 * u_rel[0]:.3g} % (k = 1)"
    else:
        stated = f", u = {100 * min(u_rel):.3g}-{100 * max(u_rel):.3g} % (k = 1)"
    if span is None:
        return f"{complex(config.drive_newton_per_volt):g} N/V at every frequency{stated}"
    rows = len(config.drive_calibration_frequency_hz)
    return (f"{rows} rows, {span[0]:g}-{span[1]:g} Hz (not extrapolated){stated}, from "
            f"{config.drive_calibration_source}")


def speed_of_sound_text(config: Any) -> str:
    """The bench file's speed of sound in a few words: what every channel and which
    channels get, over the protocol's ``ultrasound.speed_of_sound_m_s``."""
    every = config.speed_of_sound_m_s
    text = (f"{every:g} m/s on every channel (over the protocol's)" if every is not None
            else "the protocol's")
    own = dict(config.channel_speed_of_sound_m_s)
    if own:
        text += "; " + ", ".join(f"ch{ch} {c:g} m/s" for ch, c in sorted(own.items()))
    if every is not None or own:
        text += "; on tissue: a test object (excitation on no bone) keeps the protocol's"
    return text


def _instrument_line(role: str, instrument: Any, lock: str) -> str:
    return (f"  {role:10s} {getattr(instrument, 'identity', '?')}  "
            f"[{getattr(instrument, 'resource', '')}]" + (f"  {lock}" if lock else ""))


def _report_unsafe(unsafe: list[str]) -> None:
    for message in unsafe:
        print(f"pelvislab bench check: {message}", file=sys.stderr)
    print("pelvislab bench check: OUTPUTS NOT CONFIRMED OFF: switch the shaker amplifier "
          "off by hand", file=sys.stderr)


def check_command(args: argparse.Namespace) -> int:
    """Open, list, make safe, close; the exit code says what failed: 5 an output not
    confirmed off, 3 an instrument fault, 141 stdout's reader gone (``| head``), else 0."""
    import os

    from pelvislab.app.cli import EXIT_BROKEN_PIPE
    from pelvislab.drivers.bench import BenchConfig, open_bench
    from pelvislab.drivers.interfaces import DriverError

    path = Path(args.file)
    if not path.is_file():
        raise FileNotFoundError(f"bench file not found: {path}")
    config = BenchConfig.load(path)
    piped_away = False

    def say(text: str) -> None:
        # stdout's reader may go away (`| head -1`): the check goes on to its safe state
        # and its report on stderr (a BrokenPipeError skipped them: helper review)
        nonlocal piped_away
        if piped_away:
            return
        try:
            print(text, flush=True)
        except BrokenPipeError:
            piped_away = True
            try:
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            except (OSError, ValueError, AttributeError):
                pass

    say(f"{config.name}{' (SIMULATED)' if config.simulated else ''}")
    say(f"  drive calibration: {drive_calibration_text(config)}")
    say(f"  speed of sound: {speed_of_sound_text(config)}")
    sections = config.simulated_sections_note()
    if sections:
        say(f"  note: {sections}")
    listed: set[str] = set()

    def answered(role: str, instrument: Any) -> None:
        # each instrument as it opens: when a later one does not, those that answered
        # are listed (only the failure was printed: first-day review, session 39)
        say(_instrument_line(role, instrument, _lock_text(instrument)))
        listed.add(role)

    try:
        bench = open_bench(path, on_open=answered)
    except DriverError as exc:
        print(f"pelvislab bench check: instrument fault: {' '.join(str(exc).split())}",
              file=sys.stderr)
        unsafe = list(getattr(exc, "unsafe", []) or [])
        if unsafe:  # the instruments opened before it could not all be made safe
            _report_unsafe(unsafe)
            return EXIT_UNSAFE
        return EXIT_FAULT
    fault = None
    try:
        roles = [("trigger", bench.trigger), ("drive", bench.drive),
                 ("digitizer", bench.digitizer)]
        roles += [(f"pulsers[{i}]", p) for i, p in enumerate(bench.pulsers)]
        for role, instrument in roles:
            if role in listed:
                continue
            try:
                lock = _lock_text(instrument)
            except DriverError as exc:  # answered at open, not now: a fault, named
                fault = f"{path}: [{role}] {getattr(instrument, 'resource', '')}: {exc}"
                break
            say(_instrument_line(role, instrument, lock))
    finally:
        # the safe state's and the close's failures, whatever happened above
        seen = len(bench.safe_state_errors)
        bench.close()
        unsafe = bench.safe_state_errors[seen:]
    if fault is not None:
        print(f"pelvislab bench check: instrument fault: {' '.join(fault.split())}",
              file=sys.stderr)
    if unsafe:
        _report_unsafe(unsafe)
        return EXIT_UNSAFE
    if fault is not None:
        return EXIT_FAULT
    say("ok: every instrument answered; outputs off")
    return EXIT_BROKEN_PIPE if piped_away else 0
