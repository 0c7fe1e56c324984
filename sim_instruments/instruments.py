"""The virtual instruments: what the runner talks to on the simulated bench.

- Generators: the REAL 33220A driver (``pelvislab.drivers.agilent33220a.Agilent33220A``)
  over a :class:`SimTransport`. The transport passes every SCPI command on to pyvisa-sim
  (the drivers' YAML ``sim_instruments/agilent_33220a.yaml``) or, with
  ``generators="python"``, to a small built-in responder, and updates the world's view of
  the generator from the same commands (as the instrument itself would). Faults are
  injected at this level, so the driver's own error handling is what gets exercised.
- Digitizer and pulser/receivers: Python classes implementing the Protocols of
  ``pelvislab.drivers.interfaces``, with a command log of the calls the real drivers
  would make. (The bench can also run the product's Acqiris and 5077PR drivers over a
  simulated library / serial port: ``acqiris_sim.py``, ``panametrics_sim.py``; the 5077PR
  driver is the default pulser.)
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from typing import Any

from pelvislab.drivers.acqiris import DP235_CHANNELS, DP235_MAX_SAMPLES_PER_CHANNEL
from pelvislab.drivers.interfaces import (
    DriverError,
    InstrumentConnectionError,
    InstrumentTimeoutError,
    LimitError,
    SegmentedRecord,
)
from pelvislab.sim_instruments.echo import Receiver
from pelvislab.sim_instruments.faults import (
    FaultBook,
    InstrumentTimeout,
    LostConnection,
    PulserSilent,
    ScpiError,
)
from pelvislab.sim_instruments.world import GeneratorState, SimClock, World

__all__ = [
    "MAX_SAMPLES_PER_CHANNEL",
    "PULSE_ENERGY_V",
    "ScpiResponder",
    "SimDigitizer",
    "SimPulserReceiver",
    "SimTransport",
]

MAX_SAMPLES_PER_CHANNEL = DP235_MAX_SAMPLES_PER_CHANNEL
"""Acquisition memory per channel of the simulated DP235 (samples): the real one's."""
PULSE_ENERGY_V = {"low": 100.0, "medium": 200.0, "high": 400.0}
"""Pulser voltage of the named energy settings (5077PR: 100-400 V)."""
DIGITIZER_CHANNELS = DP235_CHANNELS


# --------------------------------------------------------------------------- generators
class ScpiResponder:
    """A minimal 33220A answering queries from the world's :class:`GeneratorState`
    (``generators="python"``: no pyvisa-sim)."""

    def __init__(self, state: GeneratorState, serial: str) -> None:
        self.state = state
        self.serial = serial

    def write(self, command: str) -> None:  # the state is updated by the transport
        return None

    def query(self, command: str) -> str:
        s = self.state
        q = command.strip().upper()
        answers = {
            "*IDN?": f"Agilent Technologies,33220A,{self.serial},2.02-2.02-22-2",
            "*OPC?": "1",
            "SYST:ERR?": '+0,"No error"',
            "OUTP?": "1" if s.output else "0",
            "OUTP:SYNC?": "1" if s.sync else "0",
            "FUNC?": s.function,
            "FREQ?": f"{s.frequency_hz:+.15E}",
            "VOLT?": f"{s.amplitude_vpp:+.15E}",
            "VOLT:OFFS?": f"{s.offset_v:+.15E}",
            "BURS:STAT?": "1" if s.burst else "0",
            "BURS:NCYC?": f"{s.burst_cycles:+.15E}",
            "PULS:PER?": f"{s.pulse_period_s:+.15E}",
            "PHAS:UNL:ERR:STAT?": "1",
            "VOLT:UNIT?": "VPP",
        }
        if q not in answers:
            raise InstrumentTimeoutError(f"simulated 33220A {self.serial}: no answer to "
                                         f"{command!r}")
        return answers[q]

    def close(self) -> None:
        return None


class SimTransport:
    """Transport of a simulated 33220A: faults, then the instrument, then the world.

    Implements ``pelvislab.drivers.scpi.Transport`` (write/query/close).
    """

    def __init__(self, role: str, inner: Any, state: GeneratorState, clock: SimClock,
                 faults: FaultBook, lock: threading.RLock | None = None) -> None:
        self.role = role
        self.inner = inner
        self.state = state
        self.clock = clock
        self.faults = faults
        self.n_commands = 0
        self._pending_errors: list[str] = []
        self._lost = False
        self._lock = lock or threading.RLock()

    def _gate(self, command: str) -> None:
        index = self.n_commands
        self.n_commands += 1
        if self._lost:
            raise InstrumentConnectionError(f"simulated 33220A ({self.role}): connection lost; "
                                            f"{command!r} not sent")
        fault = self.faults.generator_fault(self.role, index)
        if isinstance(fault, LostConnection):
            self._lost = True
            raise InstrumentConnectionError(f"simulated 33220A ({self.role}): connection lost "
                                            f"(USB cable pulled) at {command!r}")
        if isinstance(fault, InstrumentTimeout):
            raise InstrumentTimeoutError(f"simulated 33220A ({self.role}): no answer to "
                                         f"{command!r} (injected timeout)")
        if isinstance(fault, ScpiError):
            self._pending_errors.append(f'{fault.code:+d},"{fault.message}"')

    def write(self, command: str) -> None:
        with self._lock:
            self._gate(command)
            self.inner.write(command)
            self.state.apply(command, self.clock.now())

    def query(self, command: str) -> str:
        with self._lock:
            self._gate(command)
            if command.strip().upper() == "SYST:ERR?" and self._pending_errors:
                self.inner.query(command)  # keep the instrument's own queue in step
                return self._pending_errors.pop(0)
            return self.inner.query(command)

    def close(self) -> None:
        # pyvisa shares one ResourceManager per VISA library, so VisaTransport.close()
        # (which also closes the manager) would close the OTHER generator's session too.
        # Close only this resource; the manager lives as long as the process.
        res = getattr(self.inner, "_res", None)
        if res is not None:
            self.inner._res = None
            res.close()
        else:
            self.inner.close()


# --------------------------------------------------------------------------- digitizer
class SimDigitizer:
    """A simulated Acqiris DP235 (2 channels, <= 500 MS/s, 8 bit, sequence mode).

    Implements ``pelvislab.drivers.interfaces.Digitizer``; ``command_log`` holds the
    AcqrsD1 calls the real driver would make.
    """

    model = "simulated Acqiris DP235"

    def __init__(self, world: World, resource: str = "SIM::DP235::INSTR") -> None:
        self.world = world
        self.resource = resource
        self.identity = "Acqiris DP235 (simulated), 2 ch, 500 MS/s, 8 bit"
        self.command_log: list[tuple[float, str]] = []
        self._config: dict[str, Any] | None = None
        self._closed = False
        self._log("AcqrsD1_InitWithOptions")

    def _log(self, text: str) -> None:
        self.command_log.append((time.monotonic(), text))

    @staticmethod
    def check_sequence(channels: Sequence[int], sample_rate_hz: float, n_samples: int,
                       n_segments: int, delay_s: float, full_scale_v: float,
                       offset_v: float = 0.0) -> None:
        """LimitError (``setting``: the argument's name) unless :meth:`configure_sequence`
        would accept these arguments; nothing else happens (a plan checked before the
        bench is open: ``protocol check``, ``run``)."""
        chans = [int(c) for c in channels]
        if not chans or len(set(chans)) != len(chans) or \
                any(c not in DIGITIZER_CHANNELS for c in chans):
            raise LimitError(f"channels must be distinct values of {DIGITIZER_CHANNELS}, "
                             f"got {list(channels)}", "channels")
        if not (math.isfinite(sample_rate_hz) and 0 < sample_rate_hz <= 500e6):
            raise LimitError(f"sample_rate_hz must be in (0, 500e6], got {sample_rate_hz!r}",
                             "sample_rate_hz")
        if int(n_samples) != n_samples or not 16 <= n_samples <= 65536:
            raise LimitError(f"n_samples must be an integer in [16, 65536], got {n_samples!r}",
                             "n_samples")
        if int(n_segments) != n_segments or n_segments < 1:
            raise LimitError(f"n_segments must be a positive integer, got {n_segments!r}",
                             "n_segments")
        if n_samples * n_segments > MAX_SAMPLES_PER_CHANNEL:
            raise LimitError(f"{n_segments} x {n_samples} samples exceed the "
                             f"{MAX_SAMPLES_PER_CHANNEL} samples of memory per channel",
                             "n_segments")
        if not (math.isfinite(delay_s) and 0 <= delay_s <= 1e-3):
            raise LimitError(f"delay_s must be in [0, 1 ms], got {delay_s!r}", "delay_s")
        if not (math.isfinite(full_scale_v) and 0.05 <= full_scale_v <= 5.0):
            raise LimitError(f"full_scale_v must be in [0.05, 5] V, got {full_scale_v!r}",
                             "full_scale_v")
        if not (math.isfinite(offset_v) and abs(offset_v) <= 2.0 * full_scale_v):
            raise LimitError(f"offset_v must be within +-2 full scales, got {offset_v!r}",
                             "offset_v")

    def configure_sequence(self, channels: Sequence[int], sample_rate_hz: float,
                           n_samples: int, n_segments: int, delay_s: float,
                           full_scale_v: float, offset_v: float = 0.0) -> None:
        """Sequence mode; validated like the DP235 (see :class:`Digitizer`)."""
        self._check_open()
        self.check_sequence(channels, sample_rate_hz, n_samples, n_segments, delay_s,
                            full_scale_v, offset_v)
        chans = [int(c) for c in channels]
        self._lost_check()
        self._log(f"AcqrsD1_configHorizontal(sampInterval={1.0 / sample_rate_hz:.6g}, "
                  f"delayTime={delay_s:.6g})")
        for c in chans:
            self._log(f"AcqrsD1_configVertical(channel={c}, fullScale={full_scale_v:g}, "
                      f"offset={offset_v:g})")
        self._log(f"AcqrsD1_configMemory(nbrSamples={int(n_samples)}, "
                  f"nbrSegments={int(n_segments)})")
        self._log("AcqrsD1_configTrigSource(External1, rising)")
        self._config = dict(channels=chans, sample_rate_hz=float(sample_rate_hz),
                            n_samples=int(n_samples), n_segments=int(n_segments),
                            delay_s=float(delay_s), full_scale_v=float(full_scale_v),
                            offset_v=float(offset_v))

    def _lost_check(self) -> None:
        if self.world.faults.digitizer_lost(self.world.acquisitions):
            raise InstrumentConnectionError("simulated digitizer: connection lost")

    def acquire(self, timeout_s: float) -> dict[int, SegmentedRecord]:
        """Arm, wait for the end of the sequence (<= ``timeout_s``), read every channel."""
        self._check_open()
        if self._config is None:
            raise DriverError("simulated digitizer: acquire() before configure_sequence()")
        self._log("AcqrsD1_acquire")
        self._log(f"AcqrsD1_waitForEndOfAcquisition(timeout_ms={timeout_s * 1e3:.0f})")
        cfg = self._config
        records = self.world.acquire(cfg["channels"], cfg["sample_rate_hz"], cfg["n_samples"],
                                     cfg["n_segments"], cfg["delay_s"], cfg["full_scale_v"],
                                     cfg["offset_v"], timeout_s)
        for c in cfg["channels"]:
            self._log(f"AcqrsD1_readData(channel={c}, ReadInt8, sequence)")
        return records

    def abort(self) -> None:
        """Stop an acquisition. Never raises."""
        if not self._closed:
            self._log("AcqrsD1_stopAcquisition")

    def close(self) -> None:
        """Abort and release. Idempotent."""
        if self._closed:
            return
        self.abort()
        self._log("AcqrsD1_close")
        self._closed = True

    def _check_open(self) -> None:
        if self._closed:
            raise DriverError("simulated digitizer: already closed")

    def __enter__(self) -> SimDigitizer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# --------------------------------------------------------------------------- pulsers
class SimPulserReceiver:
    """A simulated Panametrics 5077PR feeding digitizer channel ``channel``.

    Implements ``pelvislab.drivers.interfaces.PulserReceiver``. Pulse energy: ``"low"``
    (100 V), ``"medium"`` (200 V), ``"high"`` (400 V) or a voltage (``"300"``, ``"300V"``).
    """

    model = "simulated Panametrics 5077PR"
    GAIN_DB = (-20.0, 59.0)

    def __init__(self, world: World, channel: int, resource: str = "") -> None:
        self.world = world
        self.channel = int(channel)
        self.resource = resource or f"SIM::5077PR::{channel}"
        self.identity = f"Panametrics 5077PR (simulated), channel {channel}"
        self.command_log: list[tuple[float, str]] = []
        self.safe_state_errors: list[str] = []
        self.n_calls = 0
        self._closed = False

    def _log(self, text: str) -> None:
        self.command_log.append((time.monotonic(), text))

    def _gate(self, what: str) -> None:
        call = self.n_calls
        self.n_calls += 1
        fault = self.world.faults.pulser_fault(self.channel, call)
        if isinstance(fault, PulserSilent):
            raise InstrumentTimeoutError(f"simulated 5077PR ch{self.channel} "
                                         f"({self.resource}): no answer to {what}")
        if isinstance(fault, LostConnection):
            raise InstrumentConnectionError(f"simulated 5077PR ch{self.channel}: serial "
                                            "connection lost")

    @staticmethod
    def pulse_voltage(pulse_energy: str) -> float:
        """Pulser voltage (V) of an energy setting; LimitError when unknown."""
        text = str(pulse_energy).strip().lower()
        if text in PULSE_ENERGY_V:
            return PULSE_ENERGY_V[text]
        try:
            volts = float(text.removesuffix("v").strip())
        except ValueError:
            raise LimitError(f"pulse_energy {pulse_energy!r}: use low, medium, high or a "
                             "voltage 100-400") from None
        if not 100.0 <= volts <= 400.0:
            raise LimitError(f"pulse_energy {pulse_energy!r}: voltage must be 100-400 V")
        return volts

    @classmethod
    def check_configuration(cls, gain_db: float, pulse_energy: str, damping_ohm: float,
                            high_pass_hz: float | None, low_pass_hz: float | None) -> None:
        """LimitError (``setting``: the argument's name) unless :meth:`configure` would
        accept these values; nothing else happens."""
        if not (math.isfinite(gain_db) and cls.GAIN_DB[0] <= gain_db <= cls.GAIN_DB[1]):
            raise LimitError(f"gain_db must be in {list(cls.GAIN_DB)}, got {gain_db!r}",
                             "gain_db")
        try:
            cls.pulse_voltage(pulse_energy)
        except LimitError as exc:
            raise LimitError(str(exc), "pulse_energy") from None
        if not (math.isfinite(damping_ohm) and damping_ohm > 0):
            raise LimitError(f"damping_ohm must be > 0, got {damping_ohm!r}", "damping_ohm")
        for name, v in (("high_pass_hz", high_pass_hz), ("low_pass_hz", low_pass_hz)):
            if v is not None and not (math.isfinite(v) and v > 0):
                raise LimitError(f"{name} must be > 0 or None, got {v!r}", name)

    def configure(self, gain_db: float, pulse_energy: str, damping_ohm: float,
                  high_pass_hz: float | None, low_pass_hz: float | None) -> None:
        """Gain, energy, damping and filters; fires on the external trigger from now on."""
        if self._closed:
            raise DriverError(f"simulated 5077PR ch{self.channel}: already closed")
        self.check_configuration(gain_db, pulse_energy, damping_ohm, high_pass_hz,
                                 low_pass_hz)
        volts = self.pulse_voltage(pulse_energy)
        self._gate("configure")
        self._log(f"GAIN {gain_db:g}")
        self._log(f"ENERGY {volts:g}V")
        self._log(f"DAMPING {damping_ohm:g}")
        self._log(f"HPF {'OUT' if high_pass_hz is None else f'{high_pass_hz:g}'}")
        self._log(f"LPF {'OUT' if low_pass_hz is None else f'{low_pass_hz:g}'}")
        self._log("TRIGGER EXT")
        with self.world._lock:
            self.world.receivers[self.channel] = Receiver(
                gain_db=float(gain_db), pulse_voltage_v=volts, high_pass_hz=high_pass_hz,
                low_pass_hz=low_pass_hz, snr_db=self.world.snr_db)

    def safe_state(self) -> None:
        """Pulser quiet. Never raises."""
        if self._closed:
            return
        try:
            self._gate("safe_state")
            self._log("TRIGGER OFF")
            with self.world._lock:
                self.world.receivers[self.channel] = None
        except Exception as exc:
            self.safe_state_errors.append(str(exc))

    def close(self) -> None:
        """Safe state then release. Idempotent."""
        if self._closed:
            return
        self.safe_state()
        self._log("close")
        self._closed = True

    def __enter__(self) -> SimPulserReceiver:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
