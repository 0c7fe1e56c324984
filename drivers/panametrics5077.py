"""Panametrics (Olympus) 5077PR square-wave pulser/receiver over a serial port (pyserial).

!! The remote command set below is NOT confirmed. !!
No copy of the 5077PR remote-interface manual was available when this was written. Every
command string, answer, value list and the serial settings are kept in ONE declared table
(:data:`COMMANDS`, :data:`SERIAL_SETTINGS`) marked "to be checked against the instrument
manual"; the value lists follow the 5077PR front-panel settings as we know them. The
driver is strict so that a wrong table shows up at once, not as bad data: every command
must be acknowledged exactly as the table says, every setting is read back and compared,
and anything else raises an error that says the table may be wrong.

Role on the bench (design section 2, thesis ch. 8): one 5077PR per transducer, fired by the
external trigger (generator #1's pulse burst), its RF output into one digitizer channel.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Protocol

from pelvislab.drivers.interfaces import (
    DriverError,
    InstrumentConnectionError,
    InstrumentError,
    InstrumentTimeoutError,
    LimitError,
)

__all__ = [
    "COMMANDS",
    "SERIAL_SETTINGS",
    "Panametrics5077PR",
    "SerialCommand",
    "UnexpectedAnswerError",
]

log = logging.getLogger(__name__)

UNCONFIRMED = "to be checked against the instrument manual"


@dataclass(frozen=True)
class SerialCommand:
    """One declared remote command of the pulser/receiver.

    ``set_fmt`` formats the token of a value (``"GAIN {}"``); ``query`` reads it back;
    ``choices`` maps Python values to the instrument's tokens (None = any number within
    ``limits`` in steps of ``step``).
    """

    name: str
    set_fmt: str | None
    query: str | None
    unit: str = ""
    choices: Mapping[Any, str] | None = None
    limits: tuple[float, float] | None = None
    step: float | None = None
    status: str = UNCONFIRMED

    def allowed(self) -> str:
        """What the table accepts, in words: ``-20..59 dB in 1 dB steps``, ``one of: 50,
        100, 200, 500 ohm`` (None shown as ``none``: filter out / full band)."""
        unit = f" {self.unit}" if self.unit else ""
        if self.choices is not None:
            return "one of: " + ", ".join(_shown(k) for k in self.choices) + unit
        if self.limits is None:
            return "any number"
        text = f"{self.limits[0]:g}..{self.limits[1]:g}{unit}"
        return text + (f" in {self.step:g}{unit} steps" if self.step is not None else "")

    def token(self, value: Any) -> str:
        """The instrument token for ``value`` (LimitError, ``setting`` = the command's
        name, if the table does not allow it)."""
        unit = f" {self.unit}" if self.unit else ""
        if self.choices is not None:
            key = value.strip().lower() if isinstance(value, str) else value
            if key in self.choices:
                return self.choices[key]
            shown = _shown(value) + (unit if isinstance(value, int | float) else "")
            raise LimitError(f"{self.name} = {shown} is not {self.allowed()}", self.name)
        if isinstance(value, bool) or not isinstance(value, int | float) or \
                not math.isfinite(value):
            raise LimitError(f"{self.name}: expected a number, got {value!r}", self.name)
        if self.limits is not None and not self.limits[0] <= value <= self.limits[1]:
            raise LimitError(f"{self.name} = {value:g}{unit} outside {self.allowed()}",
                             self.name)
        if self.step is not None:
            n = round(value / self.step)
            if abs(n * self.step - value) > 1e-9 * max(1.0, abs(value)):
                raise LimitError(f"{self.name} = {value:g}{unit} is not a multiple of "
                                 f"{self.step:g}{unit} ({self.allowed()})", self.name)
            value = n * self.step
        return f"{value:g}"


def _shown(value: Any) -> str:
    if value is None:
        return "none"
    if isinstance(value, int | float) and not isinstance(value, bool):
        return f"{value:g}"
    return str(value)


# ---------------------------------------------------------------- THE declared table
SERIAL_SETTINGS: dict[str, Any] = {
    "baudrate": 9600, "bytesize": 8, "parity": "N", "stopbits": 1,
    "write_termination": "\r", "read_termination": "\r",
    "ack": "OK",
    "status": UNCONFIRMED,
}
"""Serial framing and the acknowledgement every setting command must answer."""

COMMANDS: dict[str, SerialCommand] = {
    "identify": SerialCommand("identify", None, "ID?"),
    "trigger": SerialCommand("trigger", "TRIG {}", "TRIG?",
                             choices={"external": "EXT", "internal": "INT"}),
    "mode": SerialCommand("mode", "MODE {}", "MODE?",
                          choices={"pulse-echo": "PE", "through": "TT"}),
    "gain_db": SerialCommand("gain_db", "GAIN {}", "GAIN?", unit="dB",
                             limits=(-20.0, 59.0), step=1.0),
    # pulse energy = square-wave pulse voltage, 100 V to 400 V in 50 V steps (front panel)
    "pulse_energy": SerialCommand(
        "pulse_energy", "VOLT {}", "VOLT?", unit="V",
        choices={**{f"{v}v": str(v) for v in range(100, 401, 50)},
                 **{str(v): str(v) for v in range(100, 401, 50)},
                 "low": "100", "high": "400"}),
    "damping_ohm": SerialCommand("damping_ohm", "DAMP {}", "DAMP?", unit="ohm",
                                 choices={50: "50", 100: "100", 200: "200", 500: "500"}),
    "high_pass_hz": SerialCommand("high_pass_hz", "HPF {}", "HPF?", unit="Hz",
                                  choices={None: "OUT", 1e6: "1MHZ"}),
    "low_pass_hz": SerialCommand("low_pass_hz", "LPF {}", "LPF?", unit="Hz",
                                 choices={None: "FULL", 10e6: "10MHZ", 20e6: "20MHZ"}),
}
"""Every remote command the driver uses — ALL to be checked against the 5077PR manual."""

IDENTITY_MUST_CONTAIN = "5077"
SAFE_PULSE_ENERGY = "low"


class UnexpectedAnswerError(InstrumentError):
    """The instrument answered, but not as the (unconfirmed) command table expects."""


class SerialPort(Protocol):
    """The part of pyserial's ``Serial`` the driver uses."""

    def write(self, data: bytes) -> int | None:
        ...

    def read_until(self, expected: bytes = b"\n", size: int | None = None) -> bytes:
        ...

    def reset_input_buffer(self) -> None:
        ...

    def close(self) -> None:
        ...


class Panametrics5077PR:
    """One 5077PR. Implements :class:`pelvislab.drivers.interfaces.PulserReceiver`.

    ``port`` is an open pyserial port (or a fake with ``write``/``read_until``/
    ``reset_input_buffer``/``close``). Use :meth:`open` with a port name (``COM3``,
    ``/dev/ttyUSB0``) or any pyserial URL. Context manager: quiet on exit.
    """

    model = "Panametrics 5077PR"

    def __init__(self, port: SerialPort, resource: str = "", *, channel: int | None = None,
                 verify: bool = True) -> None:
        self.port = port
        self.resource = resource
        self.channel = channel
        self.verify = verify
        self.command_log: list[tuple[float, str]] = []
        self.safe_state_errors: list[str] = []
        self.settings: dict[str, str] = {}
        self._closed = False
        # one exchange at a time: a safe state from another thread (an abort) must not
        # flush the run thread's answer (reset_input_buffer) or take it. It waits for the
        # exchange under way, at most the port's timeout: unlike the generators' OUTP OFF,
        # nothing is urgent here, the pulser fires only on the trigger, off by then.
        self._io_lock = threading.RLock()
        self.identity = ""
        try:
            self.identity = self._query(COMMANDS["identify"].query or "")
            if IDENTITY_MUST_CONTAIN not in self.identity:
                raise UnexpectedAnswerError(
                    f"{resource}: identification answered {self.identity!r}, expected text "
                    f"containing {IDENTITY_MUST_CONTAIN!r} (wrong port/baud rate, or the "
                    f"command table is wrong: {UNCONFIRMED})")
        except BaseException:
            self._close_port()
            raise

    @classmethod
    def open(cls, resource: str, *, baudrate: int | None = None, timeout_s: float = 1.0,
             channel: int | None = None) -> Panametrics5077PR:
        """Open the serial port ``resource`` (pyserial URL or device) with the table's
        framing and identify the instrument."""
        import serial  # pyserial, imported only when a real port is opened

        try:
            port = serial.serial_for_url(
                resource, baudrate=baudrate or SERIAL_SETTINGS["baudrate"],
                bytesize=SERIAL_SETTINGS["bytesize"], parity=SERIAL_SETTINGS["parity"],
                stopbits=SERIAL_SETTINGS["stopbits"], timeout=timeout_s,
                write_timeout=timeout_s)
        except (serial.SerialException, ValueError, OSError) as exc:
            raise InstrumentConnectionError(f"cannot open serial port {resource!r}: {exc}"
                                            ) from exc
        return cls(port, resource, channel=channel)

    # ---- I/O ----------------------------------------------------------------------------
    def _exchange(self, text: str) -> str:
        with self._io_lock:
            return self._exchange_locked(text)

    def _exchange_locked(self, text: str) -> str:
        if self._closed:
            raise DriverError(f"{self.model} {self.resource}: closed")
        self.command_log.append((time.monotonic(), text))
        wt = SERIAL_SETTINGS["write_termination"].encode()
        rt = SERIAL_SETTINGS["read_termination"].encode()
        try:
            self.port.reset_input_buffer()
            self.port.write(text.encode("ascii") + wt)
            raw = self.port.read_until(rt)
        except OSError as exc:  # pyserial's SerialException is an OSError
            raise InstrumentConnectionError(
                f"{self.model} {self.resource}: {text!r} failed: {exc}") from exc
        if not raw.endswith(rt):
            what = f"a partial answer {raw!r}" if raw else "no answer"
            raise InstrumentTimeoutError(
                f"{self.model} {self.resource}: {what} to {text!r} (instrument off, wrong "
                f"port/baud rate, or the command table is wrong: {UNCONFIRMED})")
        return raw[: -len(rt)].decode("ascii", "replace").strip()

    def _query(self, text: str) -> str:
        return self._exchange(text)

    def _set(self, key: str, value: Any) -> None:
        with self._io_lock:  # the setting and its read-back together
            self._set_locked(key, value)

    def _set_locked(self, key: str, value: Any) -> None:
        cmd = COMMANDS[key]
        assert cmd.set_fmt is not None
        token = cmd.token(value)
        line = cmd.set_fmt.format(token)
        answer = self._exchange(line)
        if answer != SERIAL_SETTINGS["ack"]:
            raise UnexpectedAnswerError(
                f"{self.model} {self.resource}: {line!r} answered {answer!r}, the table "
                f"expects {SERIAL_SETTINGS['ack']!r} ({UNCONFIRMED})")
        if self.verify and cmd.query:
            back = self._exchange(cmd.query)
            if back.strip().upper() != token.upper():
                raise UnexpectedAnswerError(
                    f"{self.model} {self.resource}: after {line!r}, {cmd.query!r} answered "
                    f"{back!r}, expected {token!r} ({UNCONFIRMED})")
        self.settings[key] = token

    # ---- PulserReceiver interface ------------------------------------------------------
    @staticmethod
    def _configuration(gain_db: float, pulse_energy: str, damping_ohm: float,
                       high_pass_hz: float | None, low_pass_hz: float | None
                       ) -> dict[str, Any]:
        return {"trigger": "external", "mode": "pulse-echo", "gain_db": gain_db,
                "pulse_energy": pulse_energy, "damping_ohm": damping_ohm,
                "high_pass_hz": high_pass_hz, "low_pass_hz": low_pass_hz}

    @staticmethod
    def check_configuration(gain_db: float, pulse_energy: str, damping_ohm: float,
                            high_pass_hz: float | None, low_pass_hz: float | None) -> None:
        """LimitError (``setting``: the argument's name) unless :meth:`configure` would
        accept these values: every one against the declared table (:data:`COMMANDS`);
        nothing is sent. What ``configure`` checks first, so that a plan can be checked
        before the instrument is open (``protocol check``, ``run``)."""
        values = Panametrics5077PR._configuration(gain_db, pulse_energy, damping_ohm,
                                                  high_pass_hz, low_pass_hz)
        for key, v in values.items():
            COMMANDS[key].token(v)

    def configure(self, gain_db: float, pulse_energy: str, damping_ohm: float,
                  high_pass_hz: float | None, low_pass_hz: float | None) -> None:
        """External trigger, pulse-echo, gain (dB), pulse energy (``"100V"``..``"400V"``,
        ``"low"``/``"high"``), damping (ohm), filters (Hz, None = out/full band).
        All values are checked against the table before anything is sent."""
        values = self._configuration(gain_db, pulse_energy, damping_ohm, high_pass_hz,
                                     low_pass_hz)
        self.check_configuration(gain_db, pulse_energy, damping_ohm, high_pass_hz,
                                 low_pass_hz)  # all first, before anything is sent
        try:
            for key, v in values.items():
                self._set(key, v)
        except BaseException:
            self.safe_state()
            raise

    def safe_state(self) -> list[str]:
        """Lowest pulse energy on external trigger (fires only when the, by then stopped,
        trigger generator fires). Never raises an Exception; returns this call's failures
        (also logged and kept in ``safe_state_errors``, which another thread's safe state
        may append to meanwhile)."""
        if self._closed:
            return []
        failed: list[str] = []
        for key, v in (("pulse_energy", SAFE_PULSE_ENERGY), ("trigger", "external")):
            try:
                self._set(key, v)
            except Exception as exc:
                msg = f"{self.model} {self.resource}: safe state {key} failed: {exc}"
                failed.append(msg)
                self.safe_state_errors.append(msg)
                log.error(msg)
        return failed

    def _close_port(self) -> None:
        self._closed = True
        try:
            self.port.close()
        except Exception as exc:
            log.error("%s %s: closing the port failed: %s", self.model, self.resource, exc)

    def close(self) -> None:
        """Safe state, then release the port. Idempotent."""
        if self._closed:
            return
        self.safe_state()
        self._close_port()

    def __enter__(self) -> Panametrics5077PR:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close()
