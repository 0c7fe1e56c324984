"""Declarative SCPI command tables, transports and the error-queue discipline.

An instrument class declares its commands as :class:`Control` descriptors (in the spirit of
PyMeasure's ``Instrument.control``; written here from scratch)::

    class Gen(SCPIInstrument):
        frequency_hz = Control("FREQ?", "FREQ {}", "Output frequency, Hz.",
                               kind=float, limits=(1e-6, 20e6), spec="33220A datasheet")

``gen.frequency_hz = 1e3`` validates 1e3 against the static limits BEFORE anything is sent,
then writes ``FREQ 1000``; reading ``gen.frequency_hz`` sends ``FREQ?`` and parses the
answer. Cross-parameter rules (limits that depend on the function or the load) belong to
the instrument's high-level methods; an instrument whose settings depend on each other
(the 33220A) sets :attr:`SCPIInstrument.raw_settings` False, so that the table's settings
are made only by those methods (reading stays free). After every configuration block the
instrument's error queue is read until it reports no error; any error raises with the
instrument's own text (:meth:`SCPIInstrument.check_errors`).

Transports: :class:`VisaTransport` (pyvisa, real or pyvisa-sim) and
:class:`ScriptedTransport`, a protocol-level fake that checks the exact command strings
sent, in order, and returns scripted answers (used by the tests).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Protocol

from pelvislab.drivers.interfaces import (
    DriverError,
    InstrumentConnectionError,
    InstrumentError,
    InstrumentTimeoutError,
    LimitError,
)

__all__ = [
    "Control",
    "ScriptedTransport",
    "SCPIInstrument",
    "Transport",
    "VisaTransport",
    "format_number",
    "parse_bool",
    "parse_error",
    "parse_number",
    "send_all",
]

log = logging.getLogger(__name__)

MAX_ERROR_READS = 32
"""The 33220A error queue holds at most 20 entries; stop draining after this many reads."""

SAFE_STATE_IO_WAIT_S = 0.5
"""How long a safe state waits for another thread's exchange with the same instrument to
end (one command or query takes milliseconds) before it sends anyway: an output left on
is worse than a query of the run thread cut short."""


# --------------------------------------------------------------------------- formatting
def format_number(value: float) -> str:
    """SCPI <NRf> text for a number: up to 15 significant digits, no trailing zeros."""
    if isinstance(value, bool):
        raise TypeError("a bool is not a number here")
    if isinstance(value, int):
        return str(value)
    if not math.isfinite(value):
        raise LimitError(f"not a finite number: {value!r}")
    text = f"{value:.15G}"
    return text


def parse_number(text: str) -> float:
    """Parse an SCPI numeric answer (``+1.000000000000000E+03``, ``INF``, ``9.9E+37``)."""
    t = text.strip()
    v = float(t)
    # SCPI's 9.9E37 stands for infinity (e.g. OUTP:LOAD? with a high-Z load).
    if abs(v) >= 9.9e37:
        return math.copysign(math.inf, v)
    return v


def parse_bool(text: str) -> bool:
    """Parse an SCPI boolean answer: ``1``/``0`` (also ``ON``/``OFF``)."""
    t = text.strip().upper()
    if t in ("1", "ON", "+1"):
        return True
    if t in ("0", "OFF", "+0"):
        return False
    raise InstrumentError(f"expected a boolean answer (0/1), got {text!r}")


def parse_error(text: str) -> tuple[int, str]:
    """Parse a ``SYST:ERR?`` answer ``-222,"Data out of range"`` into (code, message)."""
    t = text.strip()
    code_text, sep, message = t.partition(",")
    try:
        code = int(float(code_text))
    except ValueError:
        raise InstrumentError(f"unexpected SYST:ERR? answer {text!r}") from None
    return code, message.strip().strip('"') if sep else ""


def _one_line(exc: BaseException) -> str:
    """The last meaningful line of an exception text (some backends embed a traceback)."""
    text = str(exc).replace("\\n", "\n").replace("\\'", "'")
    parts = [p.strip(" '\"\\") for p in text.splitlines()]
    parts = [p for p in parts if p]
    return parts[-1] if parts else type(exc).__name__


# --------------------------------------------------------------------------- transports
class Transport(Protocol):
    """What an SCPI instrument needs from its connection."""

    def write(self, command: str) -> None:
        """Send one command (termination added by the transport)."""
        ...

    def query(self, command: str) -> str:
        """Send one query and return its answer without termination."""
        ...

    def close(self) -> None:
        """Release the connection. Idempotent."""
        ...


class VisaTransport:
    """A pyvisa message-based resource; pyvisa errors become driver errors.

    ``visa_library`` is passed to :class:`pyvisa.ResourceManager` (``""``: the system VISA;
    ``"bench.yaml@sim"``: pyvisa-sim).
    """

    def __init__(self, resource_name: str, *, timeout_s: float = 5.0, visa_library: str = "",
                 read_termination: str = "\n", write_termination: str = "\n") -> None:
        import pyvisa  # lazily: importing pyvisa is not free

        self.resource_name = resource_name
        self.timeout_s = timeout_s
        self._errors = pyvisa.errors
        try:
            self._rm = pyvisa.ResourceManager(visa_library)
        except (pyvisa.errors.Error, OSError, ValueError) as exc:
            raise InstrumentConnectionError(
                f"cannot load the VISA library {visa_library or '(system default)'!r} for "
                f"{resource_name!r}: {_one_line(exc)}") from exc
        try:
            self._res = self._rm.open_resource(resource_name)
        except (pyvisa.errors.Error, OSError, ValueError) as exc:
            self._rm.close()
            raise InstrumentConnectionError(
                f"cannot open VISA resource {resource_name!r}: {_one_line(exc)}") from exc
        self._res.timeout = timeout_s * 1000.0  # pyvisa wants ms
        self._res.read_termination = read_termination
        self._res.write_termination = write_termination

    def _translate(self, exc: Exception, what: str) -> DriverError:
        from pyvisa import constants

        if isinstance(exc, self._errors.VisaIOError) and \
                exc.error_code == constants.StatusCode.error_timeout:
            return InstrumentTimeoutError(
                f"{self.resource_name}: no answer to {what!r} within {self.timeout_s:g} s "
                "(instrument off, cable unplugged, or command not understood)")
        return InstrumentConnectionError(f"{self.resource_name}: {what!r} failed: {exc}")

    def write(self, command: str) -> None:
        if self._res is None:
            raise InstrumentConnectionError(f"{self.resource_name}: connection closed")
        try:
            self._res.write(command)
        except (self._errors.Error, OSError) as exc:
            raise self._translate(exc, command) from exc

    def query(self, command: str) -> str:
        if self._res is None:
            raise InstrumentConnectionError(f"{self.resource_name}: connection closed")
        try:
            return str(self._res.query(command)).strip()
        except (self._errors.Error, OSError) as exc:
            raise self._translate(exc, command) from exc

    def clear(self) -> None:
        """VISA device clear: flushes the instrument's input and output buffers."""
        if self._res is None:
            return
        try:
            self._res.clear()
        except (self._errors.Error, OSError, NotImplementedError) as exc:
            raise self._translate(exc, "<device clear>") from exc

    def close(self) -> None:
        """Close this instrument's session only. The ResourceManager is shared by every
        resource of the same VISA library in the process (pyvisa keeps one per library), so
        closing it here would cut the other generator's session ("Invalid session handle");
        pyvisa closes it at exit."""
        res, self._res = self._res, None
        if res is not None:
            res.close()


@dataclass
class ScriptedTransport:
    """Protocol-level fake: expects exactly ``script``'s commands, in order.

    ``script`` is a list of ``(command, answer)``; ``answer`` None means a write (no
    answer expected), a string means a query with that answer, and an exception instance
    is raised when that command arrives (to simulate timeouts and lost connections).
    Anything unexpected raises AssertionError naming what was sent and what was expected.
    """

    script: list[tuple[str, str | BaseException | None]]
    sent: list[str] = field(default_factory=list)
    closed: bool = False

    def _next(self, command: str, is_query: bool) -> str | None:
        self.sent.append(command)
        if not self.script:
            raise AssertionError(f"unexpected extra command {command!r} (script exhausted)")
        expected, answer = self.script.pop(0)
        if command != expected:
            raise AssertionError(f"sent {command!r}, script expected {expected!r}")
        if isinstance(answer, BaseException):
            raise answer
        if is_query and answer is None:
            raise AssertionError(f"{command!r} sent as a query, script says it is a write")
        if not is_query and answer is not None:
            raise AssertionError(f"{command!r} sent as a write, script expects a query")
        return answer

    def write(self, command: str) -> None:
        self._next(command, False)

    def query(self, command: str) -> str:
        answer = self._next(command, True)
        assert answer is not None
        return answer

    def clear(self) -> None:
        """Device clear: recorded as ``"<clear>"`` in ``sent`` (not part of the script)."""
        self.sent.append("<clear>")

    def close(self) -> None:
        self.closed = True

    def assert_done(self) -> None:
        """Fail when scripted commands were never sent."""
        if self.script:
            raise AssertionError(f"commands never sent: {[c for c, _ in self.script]}")


# --------------------------------------------------------------------------- controls
@dataclass(frozen=True)
class Control:
    """One declared SCPI setting: how to get it, how to set it, what is valid.

    ``values`` maps Python values to SCPI tokens (e.g. ``{"sine": "SIN"}``) for discrete
    settings; ``kind`` (float, int, bool) parses answers and checks types; ``limits``
    (lo, hi) are the instrument's static limits (inclusive), checked before sending;
    ``spec`` says where the limits come from.
    """

    get_cmd: str | None
    set_cmd: str | None
    doc: str
    kind: type = float
    values: Mapping[Any, str] | None = None
    limits: tuple[float, float] | None = None
    spec: str = ""
    name: str = field(default="", compare=False)

    def __set_name__(self, owner: type, name: str) -> None:
        object.__setattr__(self, "name", name)

    def __get__(self, instrument: Any, owner: type | None = None) -> Any:
        if instrument is None:
            return self
        if self.get_cmd is None:
            raise AttributeError(f"{self.name} cannot be read")
        return self.parse(instrument.ask(self.get_cmd))

    def __set__(self, instrument: Any, value: Any) -> None:
        command = self.command_for(value)
        check = getattr(instrument, "check_raw_setting", None)
        if check is not None:
            check(self)
        instrument.write(command)

    # pure helpers, usable without an instrument -------------------------------------
    def validate(self, value: Any) -> str:
        """Check ``value`` and return the SCPI token for it (LimitError if invalid)."""
        if self.values is not None:
            key = value.lower() if isinstance(value, str) else value
            if key in self.values:
                return self.values[key]
            known = sorted(map(str, self.values))
            raise LimitError(f"{self.name}: {value!r} is not one of {known}")
        if self.kind is bool:
            if not isinstance(value, bool):
                raise LimitError(f"{self.name}: expected True/False, got {value!r}")
            return "ON" if value else "OFF"
        if self.kind is int:
            if isinstance(value, bool) or not float(value).is_integer():
                raise LimitError(f"{self.name}: expected an integer, got {value!r}")
            value = int(value)
        elif self.kind is float:
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise LimitError(f"{self.name}: expected a number, got {value!r}")
            value = float(value)
            if math.isinf(value) and self.values is None:
                raise LimitError(f"{self.name}: infinite value")
            if math.isnan(value):
                raise LimitError(f"{self.name}: NaN")
        if self.limits is not None:
            lo, hi = self.limits
            if not lo <= value <= hi:
                where = f" ({self.spec})" if self.spec else ""
                raise LimitError(f"{self.name} = {value!r} outside [{lo:g}, {hi:g}]{where}")
        return format_number(value) if self.kind in (int, float) else str(value)

    def command_for(self, value: Any) -> str:
        """The exact command that sets ``value`` (after validation)."""
        if self.set_cmd is None:
            raise AttributeError(f"{self.name} cannot be set")
        return self.set_cmd.format(self.validate(value))

    def parse(self, answer: str) -> Any:
        """Python value of the instrument's answer to ``get_cmd``."""
        if self.values is not None:
            token = answer.strip().strip('"').upper()
            for key, tok in self.values.items():
                if tok.upper() == token:
                    return key
            raise InstrumentError(f"{self.get_cmd} answered {answer!r}, not one of "
                                  f"{list(self.values.values())}")
        if self.kind is bool:
            return parse_bool(answer)
        try:
            number = parse_number(answer)
        except ValueError:
            raise InstrumentError(f"{self.get_cmd} answered {answer!r}, not a number") from None
        return int(round(number)) if self.kind is int else number


# --------------------------------------------------------------------------- instrument
class SCPIInstrument:
    """Base of SCPI drivers: command log, error-queue check, declared command table."""

    #: query that pops one entry off the error queue
    error_query = "SYST:ERR?"
    #: instrument's name used in messages
    model = "SCPI instrument"
    #: False: the table's settings are made only by the driver's own methods (inside a
    #: :meth:`configuration` block), which check the limits that depend on other settings
    #: (load, offset, bench limits) and keep the state they rely on; reading stays free
    raw_settings = True

    def __init__(self, transport: Transport, resource: str = "") -> None:
        self.transport = transport
        self.resource = resource
        self.command_log: list[tuple[float, str]] = []
        self.query_interrupted = False
        # One exchange at a time: an abort from another thread (GUI, session close) must
        # not send between the run thread's query and its answer, nor take that answer.
        # Re-entrant: a signal handler in the thread that is mid-exchange goes through.
        self._io_lock = threading.RLock()
        self._io_forced_by: int | None = None
        self._blocks = threading.local()  # configuration blocks open in each thread

    # raw I/O ---------------------------------------------------------------------------
    @contextmanager
    def _exchange(self) -> Iterator[None]:
        if self._io_forced_by == threading.get_ident():  # a safe state that could not wait
            yield
            return
        with self._io_lock:
            yield

    def write(self, command: str) -> None:
        """Send ``command`` (logged with its time)."""
        with self._exchange():
            self.command_log.append((time.monotonic(), command))
            self.transport.write(command)

    def ask(self, command: str) -> str:
        """Send a query (logged) and return its answer."""
        with self._exchange():
            self.command_log.append((time.monotonic(), command))
            # If this query is interrupted (timeout, KeyboardInterrupt), its answer may
            # still arrive later and be read as the answer to the next query: remember it.
            self.query_interrupted = True
            answer = self.transport.query(command)
            self.query_interrupted = False
            return answer

    @contextmanager
    def safe_state_io(self, wait_s: float | None = None, force: bool = True
                      ) -> Iterator[bool]:
        """The I/O for a safe state, from any thread: waits up to ``wait_s`` (default
        :data:`SAFE_STATE_IO_WAIT_S`) for another thread's exchange to end. Yields whether
        the instrument was free. When it was not and ``force``, this thread goes ahead
        without it (logged), because the output must go off: the other exchange counts as
        interrupted (its answer may arrive late), so :meth:`clear_if_interrupted` flushes
        it. Forced, send only commands that have no answer: the other exchange's pending
        read would take it."""
        if wait_s is None:
            wait_s = SAFE_STATE_IO_WAIT_S
        got = self._io_lock.acquire(timeout=wait_s)
        previous = self._io_forced_by
        if not got and force:
            log.warning("%s %s: another thread's exchange did not end within %g s; the "
                        "safe state goes ahead", self.model, self.resource, wait_s)
            self.query_interrupted = True
            self._io_forced_by = threading.get_ident()
        try:
            yield got
        finally:
            if got:
                self._io_lock.release()
            elif force:
                self._io_forced_by = previous  # a nested forced safe state keeps the outer

    def clear_if_interrupted(self) -> None:
        """Device clear (flush both I/O buffers) after an interrupted query. Never raises."""
        if not getattr(self, "query_interrupted", False):
            return
        self.query_interrupted = False
        clear = getattr(self.transport, "clear", None)
        if clear is None:
            return
        self.command_log.append((time.monotonic(), "<device clear>"))
        try:
            clear()
        except Exception as exc:
            log.error("%s %s: device clear failed: %s", self.model, self.resource, exc)

    # error queue -----------------------------------------------------------------------
    def read_errors(self) -> list[tuple[int, str]]:
        """Read the error queue until it says no error; return the errors found."""
        errors: list[tuple[int, str]] = []
        for _ in range(MAX_ERROR_READS):
            code, message = parse_error(self.ask(self.error_query))
            if code == 0:
                return errors
            errors.append((code, message))
        raise InstrumentError(
            f"{self.model} {self.resource}: error queue not empty after {MAX_ERROR_READS} "
            f"reads; last errors: {errors[-3:]}")

    def check_errors(self, context: str = "") -> None:
        """Raise :class:`InstrumentError` with the instrument's text if it reported errors."""
        errors = self.read_errors()
        if errors:
            raise self._error_for(errors, context)

    def _error_for(self, errors: list[tuple[int, str]], context: str) -> InstrumentError:
        text = "; ".join(f'{code:+d},"{msg}"' for code, msg in errors)
        during = f" during {context}" if context else ""
        return InstrumentError(f"{self.model} {self.resource} reported{during}: {text}")

    @contextmanager
    def configuration(self, context: str) -> Iterator[None]:
        """A configuration block: the error queue is read (and raised) at its end."""
        with self.driver_settings():
            yield
        self.check_errors(context)

    @contextmanager
    def driver_settings(self) -> Iterator[None]:
        """Settings of the table made by the driver itself (see :attr:`raw_settings`)."""
        self._blocks.depth = getattr(self._blocks, "depth", 0) + 1
        try:
            yield
        finally:
            self._blocks.depth -= 1

    def check_raw_setting(self, control: Control) -> None:
        """Refuse a setting of the table from outside the driver's methods when the
        instrument says so (:attr:`raw_settings` False); called before anything is sent."""
        if self.raw_settings or getattr(self._blocks, "depth", 0) > 0:
            return
        methods = getattr(self, "setting_methods", {}).get(control.name)
        use = f"use {methods}, which check" if methods else "the driver's methods check"
        raise LimitError(
            f"{self.model}: {control.name} is not set directly; {use} the limits that "
            "depend on other settings (load, offset, bench limits) and keep the driver's "
            "state (reading it is fine)")

    # table -----------------------------------------------------------------------------
    @classmethod
    def command_table(cls) -> list[Control]:
        """Every declared :class:`Control` of the class, in declaration order."""
        seen: dict[str, Control] = {}
        for klass in reversed(cls.__mro__):
            for name, attr in vars(klass).items():
                if isinstance(attr, Control):
                    seen[name] = attr
        return list(seen.values())


def send_all(instrument: SCPIInstrument, commands: Iterable[str]) -> None:
    """Write each command in order."""
    for c in commands:
        instrument.write(c)

