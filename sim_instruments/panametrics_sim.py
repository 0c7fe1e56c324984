"""A simulated serial port with a 5077PR behind it, for the product's real pulser driver.

``open_simulated_bench(pulsers="panametrics")`` (the default) opens
``pelvislab.drivers.panametrics5077.Panametrics5077PR(SimSerialPort(world, ch), ...)``: the
real driver (its declared, still UNCONFIRMED command table, acknowledgement and read-back
checks, safe state) talks to this port, which answers exactly as that table expects and
turns the settings into the world's receiver of that channel. The table is read from the
driver module, so the simulation follows it when it is corrected against the manual.

Faults: ``PulserSilent(channel)`` makes the port answer nothing (the driver raises
``InstrumentTimeoutError``); ``LostConnection("pulserN", at_call=k)`` makes writes fail from
the k-th exchange on (``OSError``, as pyserial's ``SerialException``; the driver raises
``InstrumentConnectionError``).
"""

from __future__ import annotations

from typing import Any

from pelvislab.drivers.panametrics5077 import COMMANDS, SERIAL_SETTINGS
from pelvislab.sim_instruments.echo import Receiver
from pelvislab.sim_instruments.faults import LostConnection, PulserSilent
from pelvislab.sim_instruments.world import World

__all__ = ["SimSerialPort"]

_POWER_ON = {"trigger": "INT", "mode": "PE", "gain_db": "0", "pulse_energy": "100",
             "damping_ohm": "50", "high_pass_hz": "OUT", "low_pass_hz": "FULL"}


def _token_hz(token: str) -> float | None:
    t = token.strip().upper()
    if t in ("OUT", "FULL"):
        return None
    if t.endswith("MHZ"):
        return float(t[:-3]) * 1e6
    return float(t)


class SimSerialPort:
    """pyserial-like port (write/read_until/reset_input_buffer/close) of one 5077PR."""

    def __init__(self, world: World, channel: int, identity: str | None = None) -> None:
        self.world = world
        self.channel = int(channel)
        self.identity = identity or f"PANAMETRICS 5077PR SIM CH{channel}"
        self.tokens = dict(_POWER_ON)
        self.n_exchanges = 0
        self.opened = False
        """Set by the bench once the driver has opened (identified) the instrument."""
        self._answer = b""
        self._closed = False
        self._wt = SERIAL_SETTINGS["write_termination"].encode()
        self._rt = SERIAL_SETTINGS["read_termination"].encode()
        self._ack = SERIAL_SETTINGS["ack"]
        self._by_set = {c.set_fmt.split(" ")[0]: (k, c) for k, c in COMMANDS.items()
                        if c.set_fmt}
        self._by_query = {c.query: k for k, c in COMMANDS.items() if c.query}

    # -- pyserial surface --------------------------------------------------------------------
    def reset_input_buffer(self) -> None:
        self._answer = b""

    def write(self, data: bytes) -> int:
        if self._closed:
            raise OSError("port closed")
        call = self.n_exchanges
        if self.opened:
            self.n_exchanges += 1
        fault = self.world.faults.pulser_fault(self.channel, call, opening=not self.opened)
        if isinstance(fault, LostConnection):
            raise OSError(f"simulated serial port of pulser {self.channel}: device "
                          "disconnected")
        if isinstance(fault, PulserSilent):
            self._answer = b""
            return len(data)
        text = data.decode("ascii", "replace")
        if text.endswith(self._wt.decode()):
            text = text[: -len(self._wt)]
        self._answer = self._respond(text.strip()).encode("ascii") + self._rt
        return len(data)

    def read_until(self, expected: bytes = b"\n", size: int | None = None) -> bytes:
        answer, self._answer = self._answer, b""
        return answer

    def close(self) -> None:
        self._closed = True

    # -- the instrument ------------------------------------------------------------------------
    def _respond(self, text: str) -> str:
        if text == COMMANDS["identify"].query:
            return self.identity
        if text in self._by_query:
            return self.tokens.get(self._by_query[text], "")
        head, _, arg = text.partition(" ")
        if head in self._by_set and arg:
            key, cmd = self._by_set[head]
            allowed = set(cmd.choices.values()) if cmd.choices is not None else None
            if allowed is not None and arg not in allowed:
                return "ERR"
            if allowed is None:
                try:
                    float(arg)
                except ValueError:
                    return "ERR"
            self.tokens[key] = arg
            self._update_world()
            return self._ack
        return "ERR"

    def _update_world(self) -> None:
        t = self.tokens
        live = t["trigger"] == "EXT" and t["mode"] == "PE"
        receiver: Any = None
        if live:
            receiver = Receiver(gain_db=float(t["gain_db"]),
                                pulse_voltage_v=float(t["pulse_energy"]),
                                high_pass_hz=_token_hz(t["high_pass_hz"]),
                                low_pass_hz=_token_hz(t["low_pass_hz"]),
                                snr_db=self.world.snr_db)
        with self.world._lock:
            self.world.receivers[self.channel] = receiver
