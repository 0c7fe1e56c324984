"""``pelvislab run`` and ``pelvislab reprocess``: headless sessions (design 4.3).

Exit codes of ``run``: 0 completed; 1 bad input (protocol, bench or session file; nothing
is written over an existing file); 3 an instrument fault (outputs off, reason recorded,
every completed step kept); 4 aborted (operator prompt refused); 5 an output could not be
confirmed off (whatever else happened: the operator must switch the amplifier off by hand);
130 interrupted (Ctrl-C, SIGTERM, SIGHUP or SIGQUIT). A one-line reason goes to stderr in
every non-zero case.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import re
import signal
import sys
import threading
import time
from typing import Any, TextIO

EXIT_FAULT = 3
EXIT_ABORTED = 4
EXIT_UNSAFE = 5
EXIT_INTERRUPTED = 130


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``run`` and ``reprocess`` to the CLI."""
    p = subparsers.add_parser(
        "run", help="run a protocol headless (simulated bench unless --bench is given)",
        description="Run a measurement protocol and write the session file step by step. "
        "Exit codes: 0 completed, 1 bad input, 3 instrument fault, 4 aborted, 5 an output "
        "could not be confirmed off (switch it off by hand), 130 interrupted.",
    )
    p.add_argument("protocol", metavar="PROTOCOL.toml", help="protocol file")
    p.add_argument("--out", required=True, metavar="S.h5", help="session file to write")
    p.add_argument("--bench", metavar="BENCH.toml", help="bench file; default: simulated bench")
    p.add_argument("--resume", action="store_true",
                   help="continue the interrupted session in --out (same protocol)")
    prompts = p.add_mutually_exclusive_group()
    prompts.add_argument("--wait-prompts", action="store_true",
                         help="wait for Enter at each operator prompt (the default on a real "
                         "bench; the simulated bench auto-continues)")
    prompts.add_argument("--auto-continue", action="store_true",
                         help="answer the operator prompts automatically also on a real bench "
                         "(only for a rig whose transducers need no repositioning)")
    p.add_argument("--subject-id", metavar="ID", help="pseudonymous subject ID for this "
                   "session (overrides the protocol's subject.id)")
    p.add_argument("--quiet", action="store_true", help="no progress output")
    p.set_defaults(handler=run_command)

    p = subparsers.add_parser(
        "reprocess", help="recompute displacement, phasors and /frf from raw echoes",
        description="Re-track the raw echoes of a session with other settings into a new file.",
    )
    p.add_argument("session", metavar="S.h5", help="recorded session file")
    p.add_argument("--out", required=True, metavar="S2.h5", help="new session file")
    p.add_argument("--estimator", help="sub-sample peak estimator (phase, parabolic, cosine, "
                   "spline)")
    p.add_argument("--max-lag-samples", type=int, help="correlation lag half-range, samples")
    p.add_argument("--min-correlation", type=float, help="echoes below this are lost")
    p.add_argument("--gate", action="append", default=[], metavar="[chN=]START:STOP",
                   help="bone echo window, samples: for every channel, or chN=START:STOP for "
                   "one (repeatable); 'auto' or chN=auto for the automatic gate. Without it, "
                   "gates set at acquisition (by the operator or the protocol) are kept")
    p.add_argument("--speed-of-sound", type=float, metavar="M_S",
                   help="speed of sound to assume instead of the recorded one, m/s")
    p.add_argument("--tracking", action="append", default=[], metavar="KEY=VALUE",
                   help="any other TrackingOptions field (repeatable)")
    p.add_argument("--progress", dest="verbose_progress", action="store_true",
                   help="print progress lines on stderr even when not a terminal")
    p.set_defaults(handler=reprocess_command)


# --------------------------------------------------------------------------- console listener
class ConsoleProgress:
    """Runner listener for the terminal: a progress bar on a tty, a few lines otherwise."""

    def __init__(self, runner: Any, stream: TextIO = sys.stderr, wait_prompts: bool = False,
                 quiet: bool = False) -> None:
        self.runner = runner
        self.stream = stream
        self.tty = bool(getattr(stream, "isatty", lambda: False)())
        self.wait_prompts = wait_prompts
        self.quiet = quiet
        self._bar = False
        self._tenth = 0  # without a terminal: the last tenth of the plan reported
        self._aim_said: dict[int, Any] = {}  # channel -> the live echo's gate/notes said

    def _line(self, text: str) -> None:
        if self._bar:
            self.stream.write("\n")
            self._bar = False
        self.stream.write(text + "\n")
        self.stream.flush()

    def _answer(self) -> None:
        """Enter confirms the operator prompt; ``chN=START:STOP`` (or ``chN=auto``) sets a
        channel's gate first (:meth:`Runner.set_gate`); end of input aborts the run."""
        while True:
            answer = sys.stdin.readline()
            if self.runner.aborted:
                return
            if not answer:
                real = not getattr(getattr(self.runner, "bench", None), "simulated", True)
                self.runner.abort("operator prompt: no answer (stdin closed"
                                  + ("; a rig whose transducers need no repositioning can "
                                     "run with --auto-continue)" if real else ")"))
                return
            if not answer.strip():
                self.runner.confirm()
                return
            self._set_gate(answer.strip())

    def _set_gate(self, text: str) -> None:
        """``chN=START:STOP`` or ``chN=auto`` typed at a prompt."""
        match = re.fullmatch(r"ch([1-9][0-9]*)\s*=\s*(auto|(\d+)\s*:\s*(\d+))", text)
        if match is None:
            self._line(f"not understood: {text!r}; type chN=START:STOP (samples) or "
                       "chN=auto to set a gate, or press Enter when the transducers are "
                       "in place")
            return
        channel = int(match.group(1))
        gate = None if match.group(2) == "auto" else (int(match.group(3)), int(match.group(4)))
        try:
            self.runner.set_gate(channel, gate)
        except ValueError as exc:
            self._line(f"gate not set: {exc}")
            return
        self._line(f"ch{channel}: " + ("automatic gate" if gate is None else
                                      f"gate set to samples {gate[0]}-{gate[1]}")
                   + "; press Enter when the transducers are in place")

    LIVE_GATE_MOVE_SAMPLES = 10
    """A live echo's automatic gate is said again when an edge moved more than this: it
    jitters by 1-2 samples from echo to echo (18 lines in 4 s before: review, session 38)."""

    def _say_live_echoes(self, event: Any) -> None:
        """At a prompt: each channel's gate and the tracker's notes on it when the notes or
        the gate's source change, or an edge moves by more than LIVE_GATE_MOVE_SAMPLES.
        Under --quiet only the channels with a note."""
        for echo in event.echoes:
            if self.quiet and not echo.notes:
                continue
            said = self._aim_said.get(echo.channel)
            # the notes' figures jitter too (a rival's level, its sample): compared without
            notes = tuple(re.sub(r"\d+(\.\d+)?", "#", n) for n in echo.notes)
            if said is not None and said[1:] == (echo.gate_source, notes) and (
                    (said[0] is None) == (echo.gate is None)) and (
                    echo.gate is None or max(abs(a - b) for a, b in zip(
                        said[0], echo.gate, strict=True)) <= self.LIVE_GATE_MOVE_SAMPLES):
                continue
            self._aim_said[echo.channel] = (echo.gate, echo.gate_source, notes)
            if echo.gate is None:
                where = "no gate"
            else:
                t0, t1 = (echo.delay_s + g / echo.sample_rate_hz for g in echo.gate)
                where = (f"gate {echo.gate[0]}-{echo.gate[1]} ({echo.gate_source}; "
                         f"{t0 * 1e6:.2f}-{t1 * 1e6:.2f} us after the trigger)")
            self._line(f"live echo ch{echo.channel} -> {echo.landmark}: {where}"
                       + "".join(f"\n  note: {n}" for n in echo.notes))

    def __call__(self, event: Any) -> None:
        from pelvislab.acquisition import runner as r

        if isinstance(event, r.RunFinished):
            if self._bar:  # end the open line (bar, or an unanswered prompt) before the
                self.stream.write("\n")  # command's own last line
                self.stream.flush()
                self._bar = False
            return
        if isinstance(event, r.AimingEchoes):
            if self.wait_prompts:  # --quiet: only what needs the operator's eye (a note)
                self._say_live_echoes(event)
            return
        if isinstance(event, r.OperatorPrompt):
            self._aim_said = {}
            if self.wait_prompts:
                self._line(f"PROMPT: {event.message}")
                self.stream.write("press Enter when the transducers are in place; type "
                                  "chN=START:STOP to set a channel's gate (Ctrl-C aborts) ")
                self.stream.flush()
                self._bar = True  # a line left open: the next one starts on its own
                # read in a thread: blocked in this listener, the runner could not see an
                # abort (Ctrl-C, SIGTERM) until Enter; its own wait does (_wait_prompt)
                threading.Thread(target=self._answer, name="pelvislab-prompt",
                                 daemon=True).start()
            elif not self.quiet:
                self._line(f"prompt (auto-continue): {event.message}")
        elif self.quiet:
            return
        elif isinstance(event, r.RunStarted):
            self._line(f"run {event.protocol!r}: {event.n_steps - event.n_done} steps to go "
                       f"(~{event.estimated_s:.0f} s of bench time + processing) on the "
                       f"{'simulated' if event.simulated else 'real'} bench")
        elif isinstance(event, r.Progress) and self.tty:
            width = 30
            filled = int(round(width * event.fraction))
            self.stream.write(f"\r[{'#' * filled}{'.' * (width - filled)}] "
                              f"{event.n_done}/{event.n_steps} steps, "
                              f"{event.elapsed_s:5.1f} s, ETA {event.eta_s:5.1f} s ")
            self.stream.flush()
            self._bar = True
        elif isinstance(event, r.Progress):
            # a log file (nohup, a service) gets a line at every tenth of the plan
            tenth = int(10 * event.fraction)
            if tenth > self._tenth and event.n_done < event.n_steps:
                self._tenth = tenth
                self._line(f"progress: {event.n_done}/{event.n_steps} steps "
                           f"({100 * event.fraction:.0f} %), {event.elapsed_s:.0f} s, "
                           f"ETA {event.eta_s:.0f} s")
        elif isinstance(event, r.SetupStarted) and not self.tty:
            self._line(f"setup {event.setup_index + 1}/{event.n_setups} {event.setup!r}")
        elif isinstance(event, r.Quality) and not event.ok:
            self._line(f"quality warning: step {event.step.index} "
                       f"({event.step.frequency_hz:g} Hz) {event.channel}: {event.message}")
        elif isinstance(event, r.LogMessage) and event.level in ("WARNING", "ERROR"):
            if event.text.startswith(("run interrupted:", "run aborted:", "run failed:")):
                return  # the run's closing log line: the command's last line says it
            self._line(f"{event.level.lower()}: {event.text}")


# --------------------------------------------------------------------------- run
def run_command(args: argparse.Namespace) -> int:
    """``pelvislab run``."""
    from pelvislab.acquisition.runner import NothingToResume, prepare_session
    from pelvislab.app.cli import package_version
    from pelvislab.drivers.interfaces import DriverError

    args.wait_prompts = wait_for_operator(args)
    try:
        prepared = prepare_session(args.protocol, args.out, args.bench, resume=args.resume,
                                   auto_continue=not args.wait_prompts,
                                   software_version=package_version(),
                                   subject_id=args.subject_id)
    except NothingToResume as exc:
        # on stderr with every other last line of run (stdout held it alone; review)
        print(f"pelvislab run: {exc}", file=sys.stderr)
        return 0
    except DriverError as exc:
        # an instrument that does not open is an instrument fault (exit 3), not bad input
        # (a missing VISA backend exited 1: a first-day review, session 36); the bench
        # was made safe and closed, no session file was written
        print(f"pelvislab run: instrument fault: {' '.join(str(exc).split())}; nothing "
              f"written to {args.out}", file=sys.stderr)
        unsafe = list(getattr(exc, "unsafe", []) or [])
        if unsafe:  # an instrument opened before it could not be made safe
            for message in unsafe:
                print(f"pelvislab run: {message}", file=sys.stderr)
            print("pelvislab run: OUTPUTS NOT CONFIRMED OFF: switch the shaker amplifier off "
                  "by hand", file=sys.stderr)
            return EXIT_UNSAFE
        return EXIT_FAULT
    restore: dict[int, Any] = {}  # signal handlers to put back once the summary is out
    try:
        return _run_and_report(args, prepared, restore)
    finally:  # also when closing the session raised
        for sig, handler in restore.items():
            signal.signal(sig, handler)


def wait_for_operator(args: argparse.Namespace) -> bool:
    """Whether the run waits for Enter at each operator prompt: on a real bench unless
    ``--auto-continue``, on the simulated bench only with ``--wait-prompts``. A real bench
    auto-continued: the shaker drove on at once after the instruments opened, and every
    setup's data went under landmarks nobody had placed a transducer on (a first-day
    review, session 36)."""
    from pelvislab.drivers.bench import BenchConfig

    if args.wait_prompts:
        return True
    simulated = args.bench is None or BenchConfig.load(args.bench).simulated
    return not simulated and not args.auto_continue


def _run_and_report(args: argparse.Namespace, prepared: Any, restore: dict[int, Any]) -> int:
    """Run ``prepared`` under the signal handlers, close it, print the summary; returns the
    exit code. ``restore`` receives the handlers that ``run_command`` puts back."""
    from pelvislab.acquisition.runner import speed_of_sound_note

    with prepared:
        for warning in prepared.protocol.warnings:
            print(f"warning: {warning}", file=sys.stderr)
        replaced = speed_of_sound_note(prepared.bench.config, prepared.protocol)
        if replaced:
            print(f"note: {replaced}", file=sys.stderr)
        if prepared.previous_run is not None:
            status, reason = prepared.previous_run
            print(f"resuming {args.out}: its last run ended {status}"
                  + (f" ({reason})" if reason else ""), file=sys.stderr)
            if status == "running":
                # the process died without closing: nothing confirmed its outputs off
                print("warning: that run did not end normally (killed, crashed or power "
                      "lost): its outputs were never confirmed off; opening the bench for "
                      "this run switched the generators' outputs off", file=sys.stderr)
        for problem in prepared.problems:
            print(f"warning: {args.out}: step {problem} (kept; measured again)",
                  file=sys.stderr)
        prepared.runner.subscribe(ConsoleProgress(prepared.runner, sys.stderr,
                                                  args.wait_prompts, args.quiet))
        started = time.perf_counter()
        # closed (outputs off, file closed) while the handlers still turn signals into an
        # abort: repeated Ctrl-C during the close raised KeyboardInterrupt in it; then the
        # signals are ignored until the summary is out (the run has ended, outputs off)
        final = _run_with_signals(prepared, close=True, then_ignore=restore)
        elapsed = time.perf_counter() - started
    return _report(args, prepared, final, elapsed)


def _report(args: argparse.Namespace, prepared: Any, final: Any, elapsed: float) -> int:
    """The run's last line on stderr and its exit code (the code says how the run ended,
    even when nobody reads stderr any more: ``pelvislab run ... 2>&1 | head -1``)."""

    def say(text: str) -> None:
        try:
            sys.stderr.write(text + "\n")
            sys.stderr.flush()
        except (OSError, ValueError):  # a closed pipe (EPIPE), a hung-up terminal (EIO) or
            pass  # a closed stream: the exit code still tells

    where = f"{final.n_done} of {final.n_steps} steps in {args.out}"
    unsafe = prepared.unsafe
    if unsafe:
        # the one thing the operator must act on: an output the bench could not switch off
        say(f"pelvislab run: {final.status}: {final.reason or 'done'}; OUTPUTS NOT "
            f"CONFIRMED OFF ({'; '.join(unsafe)}): switch the shaker amplifier off by "
            f"hand; {where}")
        return EXIT_UNSAFE
    if final.status == "completed":
        say(f"session complete: {where} ({elapsed:.1f} s)"
            + _missing_frf_values(args.out, prepared.protocol))
        return 0
    say(f"pelvislab run: {final.status}: {final.reason}; outputs off; {where}")
    return {"failed": EXIT_FAULT, "aborted": EXIT_ABORTED}.get(final.status, EXIT_INTERRUPTED)


def _missing_frf_values(path: str, protocol: Any) -> str:
    """``"; K of N FRF values missing ..."`` for a completed session whose /frf lacks
    values the ``protocol`` plans (each setup's (looked-at point, excitation) pair at every
    line; steps whose channels failed quality), else "". A run that lost a line in every
    setup ended "session complete" with nothing but the quality warnings scrolled past to
    say so (audit, session 41); a pair that lost every line counts too (review)."""
    import numpy as np

    from pelvislab.acquisition.frfset import read_frf

    try:
        frf = read_frf(path)
        planned = {(point, setup.excitation) for setup in protocol.setups
                   for point in setup.transducers.values()}
    except Exception:  # the summary is a convenience; the file's state is what it is
        return ""
    outputs, inputs = list(frf.outputs.name), list(frf.inputs.name)
    lost = np.zeros(frf.H.shape[0], bool)
    missing = 0
    for output, excitation in planned:
        held = (np.isfinite(frf.H[:, outputs.index(output), inputs.index(excitation)])
                if output in outputs and excitation in inputs
                else np.zeros(frf.H.shape[0], bool))
        missing += int((~held).sum())
        lost |= ~held
    if not missing:
        return ""
    frequencies = frf.frequency_hz[lost]
    shown = ", ".join(f"{f:g}" for f in frequencies[:6]) + (" ..." if lost.sum() > 6 else "")
    return (f"; {missing} of {len(planned) * frf.H.shape[0]} FRF values missing (steps "
            f"whose channels failed quality: see the warnings above), at {shown} Hz")


def _run_with_signals(prepared: Any, close: bool = False,
                      then_ignore: dict[int, Any] | None = None) -> Any:
    """Run with SIGINT/SIGTERM/SIGHUP/SIGQUIT turned into an immediate abort (outputs off
    at once).

    The run (simulation, tracking, HDF5 writes) is in the main thread, where CPython runs a
    signal handler only between bytecodes: a long C call (an HDF5 flush, an FFT; 50-230 ms
    measured under load) delays it. So a watcher thread, woken by the signal's wake-up byte
    (written at once by CPython's C-level handler), aborts right away; the handler in the
    main thread then still raises to cut a wait short. ``close``: also close ``prepared``
    (safe state, file, instruments) before the handlers are put back. ``then_ignore``: leave
    the signals ignored instead and put the handlers to restore in this dict.
    """
    runner = prepared.runner
    names = {signal.SIGINT: "Ctrl-C (SIGINT)", signal.SIGTERM: "SIGTERM"}
    # a closed terminal or dropped ssh session (SIGHUP) and Ctrl-\ (SIGQUIT) would otherwise
    # end the process with the shaker still driving (POSIX only)
    for name, label in (("SIGHUP", "SIGHUP (terminal closed)"), ("SIGQUIT", "SIGQUIT")):
        if hasattr(signal, name):
            names[getattr(signal, name)] = label

    def reason(signum: int) -> str:
        return f"interrupted by {names.get(signum, f'signal {signum}')}"

    def on_signal(signum: int, frame: object) -> None:
        # the watcher thread (below) puts the outputs off; from here, between two bytecodes
        # of whatever the run was doing (inside an instrument's lock), it could deadlock
        runner.interrupt(reason(signum), safe_state=watcher is None)

    # The handler's RunInterrupted only cuts a wait short (the abort is done before it is
    # raised). Landing where no exception can propagate (a weakref callback of the import
    # machinery, a __del__), CPython prints it as "Exception ignored ... Traceback" on
    # stderr: seen once in a clean-clone run of the suite (session 35). Nothing was lost
    # there, so it is not printed.
    from pelvislab.acquisition.runner import RunInterrupted

    previous_unraisable = sys.unraisablehook

    def unraisable(args: Any) -> None:
        if isinstance(args.exc_value, RunInterrupted):
            logging.getLogger(__name__).debug(
                "an interrupt landed where it could not propagate: %r", args.object)
            return
        previous_unraisable(args)

    sys.unraisablehook = unraisable
    previous = {}
    watcher: _SignalWatcher | None = None  # until it runs, the handler makes safe itself
    for sig in names:
        try:
            if sig == getattr(signal, "SIGHUP", None) and \
                    signal.getsignal(sig) is signal.SIG_IGN:
                continue  # nohup ignores SIGHUP so that the run outlives the terminal
            # (SIGINT is ignored in background jobs of a non-interactive shell and in
            # pytest-xdist workers: an explicit kill -INT still aborts, as it always did)
            previous[sig] = signal.signal(sig, on_signal)
        except ValueError:  # not the main thread: leave signals alone
            pass
    watcher = _SignalWatcher(runner, set(previous), reason) if previous else None
    try:
        return prepared.run()
    finally:
        try:
            if close:
                prepared.close()
        finally:
            sys.unraisablehook = previous_unraisable
            if watcher is not None:
                watcher.close()
            for sig, handler in previous.items():
                if then_ignore is not None:
                    then_ignore[sig] = handler
                    signal.signal(sig, signal.SIG_IGN)
                else:
                    signal.signal(sig, handler)


class _SignalWatcher:
    """Aborts ``runner`` from its own thread as soon as one of ``signals`` arrives
    (``signal.set_wakeup_fd``), whatever the main thread is doing. Main thread only."""

    def __init__(self, runner: Any, signals: set[int], reason: Any) -> None:
        self._read, self._write = os.pipe()
        os.set_blocking(self._write, False)
        self._previous_fd = signal.set_wakeup_fd(self._write, warn_on_full_buffer=False)
        self._thread = threading.Thread(target=self._watch, args=(runner, signals, reason),
                                        name="pelvislab-signals", daemon=True)
        self._thread.start()

    def _watch(self, runner: Any, signals: set[int], reason: Any) -> None:
        while True:
            data = os.read(self._read, 64)
            if not data:  # write end closed: the run is over
                return
            for signum in data:
                if signum in signals:
                    try:
                        runner.abort(reason(signum), "interrupted")
                    except Exception as exc:  # abort should not raise; keep watching
                        logging.getLogger(__name__).error("abort on signal: %s", exc)

    def close(self) -> None:
        signal.set_wakeup_fd(self._previous_fd)
        os.close(self._write)
        self._thread.join(5)
        os.close(self._read)


# --------------------------------------------------------------------------- reprocess
def _tracking_options(args: argparse.Namespace) -> Any:
    from pelvislab.acquisition.tracking import TrackingOptions

    fields = {f.name: f for f in dataclasses.fields(TrackingOptions)}
    values: dict[str, Any] = {}
    if args.estimator is not None:
        from pelvislab.acquisition.tracking import ESTIMATORS

        if args.estimator not in ESTIMATORS:
            raise ValueError(f"--estimator {args.estimator!r}: one of {list(ESTIMATORS)}")
        values["estimator"] = args.estimator
    if args.max_lag_samples is not None:
        values["max_lag_samples"] = args.max_lag_samples
    if args.min_correlation is not None:
        values["min_correlation"] = args.min_correlation
    every = [g for g in args.gate if "=" not in g]
    if len(every) > 1:
        raise ValueError(f"--gate for every channel given {len(every)} times: {every}")
    if every and every[0].strip().lower() != "auto":
        values["gate"] = _gate_value(every[0], "--gate")
    defaults = TrackingOptions()
    for item in args.tracking:
        key, sep, raw = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in fields:
            raise ValueError(f"--tracking {item!r}: expected KEY=VALUE with KEY one of "
                             f"{sorted(fields)}")
        current = getattr(defaults, key)
        values[key] = _convert(raw.strip(), current, key)
    try:
        return TrackingOptions(**values)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"tracking options: {exc}") from None


def _gate_value(text: str, what: str) -> tuple[int, int] | None:
    """``START:STOP`` sample indices, or ``auto`` (None)."""
    if text.strip().lower() == "auto":
        return None
    try:
        start, stop = (int(v) for v in text.split(":"))
    except ValueError:
        raise ValueError(f"{what}: expected START:STOP sample indices or 'auto', got "
                         f"{text!r}") from None
    if not 0 <= start < stop:
        raise ValueError(f"{what}: expected 0 <= START < STOP, got {text!r}")
    return start, stop


def _channel_gates(args: argparse.Namespace) -> dict[str, tuple[int, int] | None]:
    """``--gate chN=START:STOP`` / ``chN=auto`` items, by channel name."""
    gates: dict[str, tuple[int, int] | None] = {}
    for item in args.gate:
        if "=" not in item:
            continue
        name, _, value = (part.strip() for part in item.partition("="))
        if not re.fullmatch(r"ch[1-9][0-9]*", name):
            raise ValueError(f"--gate {item!r}: expected chN=START:STOP (e.g. ch1=300:420)")
        if name in gates:
            raise ValueError(f"--gate for {name} given twice")
        gates[name] = _gate_value(value, f"--gate {name}")
    return gates


def _convert(raw: str, like: Any, key: str) -> Any:
    try:
        if isinstance(like, bool):
            if raw.lower() not in ("true", "false", "1", "0", "yes", "no"):
                raise ValueError(raw)
            return raw.lower() in ("true", "1", "yes")
        if isinstance(like, int):
            return int(raw)
        if isinstance(like, float):
            return float(raw)
        if isinstance(like, tuple) or (like is None and ":" in raw):
            return tuple(float(v) if "." in v or "e" in v else int(v) for v in raw.split(":"))
        if like is None and raw.lower() == "none":
            return None
    except ValueError:
        raise ValueError(f"--tracking {key}={raw!r}: not a valid value") from None
    return raw


def reprocess_command(args: argparse.Namespace) -> int:
    """``pelvislab reprocess``."""
    from pelvislab.acquisition.runner import reprocess_session
    from pelvislab.app.cli import package_version

    options = _tracking_options(args)
    gates = _channel_gates(args)
    # 'auto' for every channel: the gates the operator set at acquisition too
    keep_operator = not any(g.strip().lower() == "auto" for g in args.gate if "=" not in g)
    tty = sys.stderr.isatty()
    # without a terminal (a log file, a batch job) a line every ~10 % on request: 35 s of
    # silence on a face_up session (first-day review, session 39)
    said = [-1]

    def progress(done: int, total: int) -> None:
        if tty:
            sys.stderr.write(f"\rreprocessing step {done}/{total} ")
            sys.stderr.flush()
        elif args.verbose_progress:
            tenth = 10 * done // max(total, 1)
            if tenth != said[0] or done == total:
                said[0] = tenth
                print(f"reprocessing step {done}/{total}", file=sys.stderr, flush=True)

    notes: list[str] = []
    n, problems = reprocess_session(args.session, args.out, options, args.speed_of_sound,
                                    progress, package_version(), channel_gates=gates,
                                    keep_operator_gates=keep_operator, notes=notes)
    if tty:
        sys.stderr.write("\n")
    for problem in problems:
        print(f"warning: skipped step {problem}", file=sys.stderr)
    for note in notes:  # a gate through the echo: noisier FRFs, each step still `ok`
        print(f"note: {note}", file=sys.stderr)
    print(f"reprocessed {n} steps -> {args.out}", file=sys.stderr)
    return 0
