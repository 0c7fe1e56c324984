"""Fault injection for the simulated bench (reliability tests of the runner and the GUI).

One dataclass per fault; pass a list as ``open_simulated_bench(faults=[...])``. Instruments
are named by role: ``"drive"``, ``"trigger"`` (the two 33220A), ``"digitizer"``,
``"pulser1"``, ``"pulser2"`` (pulser/receiver of digitizer channel 1, 2).

Counting: generator faults count the SCPI commands the driver sends through its transport
(writes and queries, from 0 when the driver starts talking); digitizer faults count
acquisitions (0 = the first); pulser faults count exchanges after the bench opened (serial
lines with the real driver, ``configure``/``safe_state`` calls with the Python pulser).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

__all__ = [
    "DigitizerTimeout",
    "Fault",
    "FaultBook",
    "InstrumentTimeout",
    "LostConnection",
    "PulserSilent",
    "ScpiError",
]

_ROLES = ("drive", "trigger", "digitizer", "pulser1", "pulser2")


@dataclass(frozen=True)
class InstrumentTimeout:
    """A generator stops answering at its ``at_command``-th command: that command (and, with
    ``persistent``, every later one) raises ``InstrumentTimeoutError``."""

    instrument: str = "drive"
    at_command: int = 0
    persistent: bool = False


@dataclass(frozen=True)
class ScpiError:
    """A generator queues an error at its ``at_command``-th command; the driver finds it in
    ``SYST:ERR?`` at the end of that configuration block and raises ``InstrumentError``.
    The 33220A's own texts, e.g. ``-222, "Data out of range"`` or ``580, "Reference
    phase-locked loop is unlocked"``."""

    instrument: str = "drive"
    at_command: int = 0
    code: int = -222
    message: str = "Data out of range"


@dataclass(frozen=True)
class DigitizerTimeout:
    """The ``at_acquisition``-th acquisition never ends: ``acquire`` waits its timeout
    (virtually, in fast pacing) and raises ``InstrumentTimeoutError``; later ones work
    unless ``persistent``."""

    at_acquisition: int = 0
    persistent: bool = False


@dataclass(frozen=True)
class LostConnection:
    """The connection to ``instrument`` is lost: from its ``at_command``-th command
    (generators), ``at_acquisition``-th acquisition (digitizer) or ``at_call``-th
    configure (pulsers) on, every call raises ``InstrumentConnectionError`` (``safe_state``
    cannot switch anything off either; it records the failure and does not raise)."""

    instrument: str = "digitizer"
    at_command: int = 0
    at_acquisition: int = 0
    at_call: int = 0


@dataclass(frozen=True)
class PulserSilent:
    """A pulser/receiver that does not answer: from its ``at_call``-th exchange after the
    bench opened, every exchange times out (``configure`` raises
    ``InstrumentTimeoutError``) and the transducer stays as it was (quiet if never
    configured: noise-only records). ``during_open``: silent from the start, so opening the
    bench fails (the driver identifies the instrument when it opens it)."""

    channel: int = 1
    at_call: int = 0
    during_open: bool = False


Fault = InstrumentTimeout | ScpiError | DigitizerTimeout | LostConnection | PulserSilent


@dataclass
class FaultBook:
    """The faults of one bench and the counters that trigger them."""

    faults: list[Any] = field(default_factory=list)
    fired: list[tuple[str, str]] = field(default_factory=list)
    """(instrument, description) of every fault that fired, in order."""

    def __post_init__(self) -> None:
        self.faults = list(self.faults)
        for f in self.faults:
            role = getattr(f, "instrument", None)
            if role is not None and role not in _ROLES:
                raise ValueError(f"{type(f).__name__}.instrument: unknown {role!r} "
                                 f"(one of {list(_ROLES)})")
            if not isinstance(f, InstrumentTimeout | ScpiError | DigitizerTimeout
                              | LostConnection | PulserSilent):
                raise TypeError(f"not a simulated-bench fault: {f!r}")

    @classmethod
    def of(cls, faults: Iterable[Any] | None) -> FaultBook:
        """A book from a list (None: no faults)."""
        return cls(list(faults or ()))

    def _fire(self, instrument: str, what: str) -> None:
        self.fired.append((instrument, what))

    # -- generators: called for every SCPI command, with the 0-based command index --------
    def generator_fault(self, instrument: str, index: int) -> Any | None:
        """The fault (if any) that hits generator ``instrument``'s ``index``-th command."""
        for f in self.faults:
            if isinstance(f, LostConnection) and f.instrument == instrument \
                    and index >= f.at_command:
                self._fire(instrument, "lost connection")
                return f
            if isinstance(f, InstrumentTimeout) and f.instrument == instrument and (
                    index == f.at_command or (f.persistent and index > f.at_command)):
                self._fire(instrument, "timeout")
                return f
        for f in self.faults:
            if isinstance(f, ScpiError) and f.instrument == instrument and index == f.at_command:
                self._fire(instrument, f"SYST:ERR {f.code}")
                return f
        return None

    # -- digitizer: called for every acquisition, 0-based ----------------------------------
    def digitizer_fault(self, index: int) -> Any | None:
        """The fault (if any) that hits the ``index``-th acquisition."""
        for f in self.faults:
            if isinstance(f, LostConnection) and f.instrument == "digitizer" \
                    and index >= f.at_acquisition:
                self._fire("digitizer", "lost connection")
                return f
            if isinstance(f, DigitizerTimeout) and (
                    index == f.at_acquisition or (f.persistent and index > f.at_acquisition)):
                self._fire("digitizer", "timeout")
                return f
        return None

    def digitizer_lost(self, index: int) -> bool:
        """True when the digitizer's connection is lost at acquisition ``index``."""
        return any(isinstance(f, LostConnection) and f.instrument == "digitizer"
                   and index >= f.at_acquisition for f in self.faults)

    # -- pulsers ---------------------------------------------------------------------------
    def pulser_fault(self, channel: int, call: int, opening: bool = False) -> Any | None:
        """The fault (if any) that hits pulser ``channel``'s ``call``-th exchange after the
        bench opened (``opening``: an exchange while the bench opens)."""
        role = f"pulser{channel}"
        for f in self.faults:
            if isinstance(f, PulserSilent) and f.channel == channel and (
                    f.during_open if opening else call >= f.at_call):
                self._fire(role, "no answer")
                return f
            if opening:
                continue
            if isinstance(f, LostConnection) and f.instrument == role and call >= f.at_call:
                self._fire(role, "lost connection")
                return f
        return None

    def pulser_silent(self, channel: int) -> bool:
        """True when pulser ``channel`` never answers."""
        return any(isinstance(f, PulserSilent) and f.channel == channel for f in self.faults)
