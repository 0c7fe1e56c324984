"""Instrument interfaces shared by the real drivers and the simulated bench.

The sweep runner talks only to these typing Protocols, so it never knows whether the
instruments are hardware (``pelvislab.drivers.*``) or the virtual bench
(``pelvislab.sim_instruments``). Bench of design section 2 / thesis ch. 8:

- two Agilent 33220A function generators: #1 the pulse-repetition trigger (a triggered
  burst of N pulses at the PRF), #2 the shaker drive (sine);
- an Acqiris DP235 digitizer (2 channels, 500 MS/s, 8 bit) in sequence (segmented) mode;
- two Panametrics 5077PR pulser/receivers.

Units are SI and in the names: ``frequency_hz``, ``amplitude_vpp`` (volts peak-to-peak, as
the generator displays it for its declared output load), ``offset_v``, ``width_s``.

Every instrument, real or simulated, should also keep a command log (see
:class:`CommandLogged`) so tests can check which commands went out and when, in particular
that outputs were switched off.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = [
    "CommandLogged",
    "Digitizer",
    "DriverError",
    "Generator",
    "InstrumentConnectionError",
    "InstrumentError",
    "InstrumentTimeoutError",
    "LimitError",
    "PulserReceiver",
    "SegmentedRecord",
]


# --------------------------------------------------------------------------- exceptions
class DriverError(RuntimeError):
    """Base class of every error raised by an instrument driver."""


class InstrumentError(DriverError):
    """The instrument reported an error (its own text is in the message)."""


class InstrumentConnectionError(DriverError):
    """The instrument cannot be reached, or the connection was lost."""


class InstrumentTimeoutError(InstrumentConnectionError):
    """The instrument did not answer (or did not finish) within the timeout."""


class LimitError(DriverError, ValueError):
    """A requested setting is outside the instrument's range or the bench's safety limit.

    Raised BEFORE anything is sent to the instrument. ``setting``: the name of the refused
    argument of the configuring call (``gain_db``, ``width_s``, ``full_scale_v``, ...) when
    the check says it, so that a caller checking a plan (``protocol check``) can name its own
    key for it; None otherwise.
    """

    def __init__(self, message: str, setting: str | None = None) -> None:
        super().__init__(message)
        self.setting = setting


# --------------------------------------------------------------------------- protocols
@runtime_checkable
class CommandLogged(Protocol):
    """An instrument that records every command it sends.

    ``command_log`` is a list of ``(time_s, text)`` with ``time_s`` from
    :func:`time.monotonic` and ``text`` the command (SCPI string, library call, serial
    line) as sent.
    """

    command_log: list[tuple[float, str]]


@runtime_checkable
class Generator(Protocol):
    """A function generator (Agilent 33220A): PRF trigger (#1) or shaker drive (#2).

    Amplitudes are volts peak-to-peak as the generator means them for its declared output
    load (``OUTP:LOAD``): into 50 ohm, or the open-circuit voltage for a high-Z load.
    Implementations validate ranges (and the bench's drive limit) before sending.
    """

    identity: str
    """``*IDN?`` answer (or a simulated equivalent)."""
    resource: str
    """Resource name the instrument was opened with (VISA string, ``SIM::...``)."""

    def configure_sine(self, frequency_hz: float, amplitude_vpp: float,
                       offset_v: float = 0.0) -> None:
        """Continuous sine of ``frequency_hz`` (Hz), ``amplitude_vpp`` (V pk-pk),
        ``offset_v`` (V). The output state is not changed."""
        ...

    def set_frequency(self, frequency_hz: float) -> None:
        """Change the frequency (Hz) of the current waveform, phase-continuous."""
        ...

    def set_amplitude(self, amplitude_vpp: float) -> None:
        """Change the amplitude (V pk-pk) of the current waveform."""
        ...

    def configure_pulse_burst(self, prf_hz: float, n_pulses: int, width_s: float,
                              high_v: float, low_v: float = 0.0) -> None:
        """Externally triggered burst of ``n_pulses`` pulses at ``prf_hz`` (Hz), each
        ``width_s`` (s) wide, from ``low_v`` to ``high_v`` (V). Output state unchanged."""
        ...

    def output_on(self) -> None:
        """Switch the main output on."""
        ...

    def output_off(self) -> None:
        """Switch the main output off."""
        ...

    @property
    def output_enabled(self) -> bool:
        """True when the main output is on."""
        ...

    def reference_locked(self) -> bool | None:
        """True/False: locked/unlocked to the external 10 MHz reference; None when the
        instrument cannot tell (e.g. 33220A without option 001)."""
        ...

    def safe_state(self) -> list[str] | None:
        """Outputs off. Never raises (failures are logged); may return this call's
        failures (the 33220A does), which ``Bench`` then reports instead of reading them
        off ``safe_state_errors``."""
        ...

    def close(self) -> None:
        """``safe_state()`` then release the connection. Idempotent."""
        ...


@dataclass
class SegmentedRecord:
    """One channel of one sequence (segmented) acquisition.

    Voltage of sample ``k`` of segment ``s``:
    ``codes[s, k] * volts_per_count - volts_offset`` (Acqiris convention: the vertical
    offset is subtracted). Time of sample ``k`` of segment ``s`` relative to that
    segment's trigger: ``delay_s + k / sample_rate_hz + trigger_offset_s[s]``
    (thesis ch. 8: each segment's sub-sample trigger position must be applied).
    """

    codes: np.ndarray
    """int8, shape (n_segments, n_samples): raw ADC codes."""
    trigger_offset_s: np.ndarray
    """float64, shape (n_segments,): sub-sample trigger offset (Acqiris ``horPos``), s."""
    sample_rate_hz: float
    """Sampling rate, Hz."""
    delay_s: float
    """Trigger delay of the first sample (horizontal delay), s."""
    volts_per_count: float
    """Vertical gain, V per code."""
    volts_offset: float
    """Vertical offset, V (subtracted, see class docstring)."""

    def __post_init__(self) -> None:
        self.codes = np.asarray(self.codes)
        self.trigger_offset_s = np.asarray(self.trigger_offset_s, dtype=np.float64)
        if self.codes.ndim != 2:
            raise ValueError(f"codes must be 2-D (n_segments, n_samples), got {self.codes.shape}")
        if self.trigger_offset_s.shape != (self.codes.shape[0],):
            raise ValueError(
                f"trigger_offset_s has shape {self.trigger_offset_s.shape}, "
                f"expected ({self.codes.shape[0]},)"
            )
        if not self.sample_rate_hz > 0:
            raise ValueError(f"sample_rate_hz must be > 0, got {self.sample_rate_hz}")

    @property
    def n_segments(self) -> int:
        """Number of segments (echoes)."""
        return int(self.codes.shape[0])

    @property
    def n_samples(self) -> int:
        """Samples per segment."""
        return int(self.codes.shape[1])

    def volts(self) -> np.ndarray:
        """Codes converted to volts, float64 (n_segments, n_samples)."""
        return self.codes.astype(np.float64) * self.volts_per_count - self.volts_offset

    def time_s(self) -> np.ndarray:
        """Sample times relative to each segment's trigger, s, (n_segments, n_samples)."""
        k = np.arange(self.n_samples, dtype=np.float64) / self.sample_rate_hz
        return self.delay_s + k[None, :] + self.trigger_offset_s[:, None]


@runtime_checkable
class Digitizer(Protocol):
    """A segmented-memory digitizer (Acqiris DP235) triggered externally."""

    identity: str
    resource: str

    def configure_sequence(self, channels: Sequence[int], sample_rate_hz: float,
                           n_samples: int, n_segments: int, delay_s: float,
                           full_scale_v: float, offset_v: float = 0.0) -> None:
        """Sequence mode on ``channels`` (1-based): ``n_segments`` records of ``n_samples``
        at ``sample_rate_hz`` (Hz), first sample ``delay_s`` (s) after the external
        trigger, vertical full scale ``full_scale_v`` (V) and offset ``offset_v`` (V)."""
        ...

    def acquire(self, timeout_s: float) -> dict[int, SegmentedRecord]:
        """Arm, wait for the end of acquisition (at most ``timeout_s`` s, else
        :class:`InstrumentTimeoutError`) and read every configured channel."""
        ...

    def abort(self) -> None:
        """Stop a running acquisition. Never raises."""
        ...

    def close(self) -> None:
        """Abort and release the instrument. Idempotent."""
        ...


@runtime_checkable
class PulserReceiver(Protocol):
    """An ultrasound pulser/receiver (Panametrics 5077PR), externally triggered."""

    identity: str
    resource: str

    def configure(self, gain_db: float, pulse_energy: str, damping_ohm: float,
                  high_pass_hz: float | None, low_pass_hz: float | None) -> None:
        """Receiver gain (dB), pulse energy (instrument's names, e.g. ``"low"``/``"high"``
        or a voltage setting), damping (ohm), filters (Hz; None = out/full band); the
        pulser fires on the external trigger input."""
        ...

    def safe_state(self) -> list[str] | None:
        """Pulser quiet (lowest energy / internal trigger off). Never raises; may return
        this call's failures (the 5077PR does), as :meth:`Generator.safe_state`."""
        ...

    def close(self) -> None:
        """``safe_state()`` then release the port. Idempotent."""
        ...
