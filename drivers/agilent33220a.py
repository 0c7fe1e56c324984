"""Agilent 33220A 20 MHz function/arbitrary waveform generator over VISA (SCPI).

Used twice on the bench (design section 2, thesis ch. 8): #1 the pulse-repetition trigger
of the pulser/receivers (pulse function, externally triggered burst of N pulses at the
PRF), #2 the shaker drive (continuous sine into the current-driven amplifier).

Every setting is declared in the command table below (:class:`Agilent33220A` controls).
Ranges are checked BEFORE anything is sent, with the rules that depend on the function and
on the declared output load (``OUTP:LOAD``), and the bench's drive limit (``max_vpp``) is
enforced here, not only in the GUI. After every configuration block the error queue is
read until ``+0,"No error"``; any error raises with the instrument's text and puts the
output off.

Sources of the limits (cited per entry as ``[UG]``/``[DS]``): Agilent 33220A User's Guide
(Edition 2/4, ch. 3 "Features and Functions" and ch. 4 "Remote Interface Reference") and
the 33220A data sheet ("Specifications"), as known to us; numbers marked "check" could not
be verified against a copy of the manual here.
"""

from __future__ import annotations

import logging
import math
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from pelvislab.drivers.interfaces import DriverError, InstrumentError, LimitError
from pelvislab.drivers.scpi import (
    Control,
    SCPIInstrument,
    Transport,
    VisaTransport,
    format_number,
)

__all__ = [
    "Agilent33220A",
    "ReferenceUnlockedError",
    "amplitude_limits_vpp",
    "check_amplitude_offset",
    "check_frequency",
    "check_pulse",
    "check_pulse_burst",
    "load_factor",
    "min_pulse_width_s",
]

log = logging.getLogger(__name__)

# --------------------------------------------------------------------------- the specs
SOURCE_IMPEDANCE_OHM = 50.0
"""Output impedance [DS]."""

FREQUENCY_LIMITS_HZ: dict[str, tuple[float, float]] = {
    "sine": (1e-6, 20e6),     # [DS] Sine 1 uHz to 20 MHz
    "square": (1e-6, 20e6),   # [DS] Square 1 uHz to 20 MHz
    "ramp": (1e-6, 200e3),    # [DS] Ramp/triangle 1 uHz to 200 kHz
    "pulse": (500e-6, 5e6),   # [DS] Pulse 500 uHz to 5 MHz (period 200 ns to 2000 s)
    "user": (1e-6, 6e6),      # [DS] Arbitrary 1 uHz to 6 MHz
}
"""Frequency range per function, Hz. Noise and DC have no frequency."""

AMPLITUDE_50OHM_VPP = (10e-3, 10.0)
"""Amplitude into 50 ohm: 10 mVpp to 10 Vpp [DS]; twice that into an open circuit."""
MAX_PEAK_50OHM_V = 5.0
"""|offset| + Vpp/2 <= 5 V into 50 ohm (10 V open circuit) [UG 'Output Configuration']."""
LOAD_LIMITS_OHM = (1.0, 10e3)
"""OUTP:LOAD accepts 1 ohm to 10 kohm, or INFinity [UG]."""

PULSE_PERIOD_S = (200e-9, 2000.0)
"""Pulse period [DS]."""
PULSE_EDGE_S = (5e-9, 100e-9)
"""FUNC:PULS:TRAN, both edges, 5 ns to 100 ns [UG]."""
EDGE_TO_WIDTH_MAX = 0.625
"""Edge time <= 0.625 x pulse width [UG 'Pulse Waveforms']."""
BURST_EDGE_S = 5e-9
"""Edge time of the trigger pulses of :meth:`Agilent33220A.configure_pulse_burst`, s."""
BURST_CYCLES = (1, 50_000)
"""BURS:NCYC 1 to 50 000 cycles [UG]."""
BURST_PERIOD_S = (1e-6, 500.0)
"""BURS:INT:PER 1 us to 500 s (internal trigger only) [UG]."""
PHASE_DEG = (-360.0, 360.0)
"""BURS:PHAS and PHAS, degrees [UG]."""

RESET_STATE: dict[str, Any] = {
    "function": "sine", "frequency_hz": 1e3, "amplitude_vpp": 0.1, "offset_v": 0.0,
    "period_s": 1e-3, "width_s": 100e-6, "edge_s": 5e-9, "burst": False,
}
"""Settings after ``*RST`` (factory defaults [UG 'Factory Default Settings'])."""

REFERENCE_UNLOCKED_CODE = 580
"""Error 'Reference phase-locked loop is unlocked' (option 001) [UG error list] — check."""
EXTERNAL_REFERENCE_HZ = 10e6
"""The external timebase (option 001) input's frequency: the shared 10 MHz reference of
design section 2 [DS]."""
EXTERNAL_REFERENCE_LOCK_RANGE_HZ = 500.0
"""Option 001 locks to ``EXTERNAL_REFERENCE_HZ`` plus or minus this: 10 MHz +- 500 Hz
(50 ppm) [DS "External Reference Input", lock range] — check."""


class ReferenceUnlockedError(InstrumentError):
    """The generator lost lock on the external 10 MHz reference (option 001)."""


def load_factor(load_ohm: float) -> float:
    """Displayed-amplitude factor for a declared load, relative to 50 ohm.

    The 33220A shows the voltage across the declared load of its 50-ohm source:
    ``2 R / (R + 50)``: 1 at 50 ohm, 2 for a high-Z (infinite) load.
    """
    if math.isinf(load_ohm):
        return 2.0
    return 2.0 * load_ohm / (load_ohm + SOURCE_IMPEDANCE_OHM)


def amplitude_limits_vpp(load_ohm: float) -> tuple[float, float]:
    """(min, max) amplitude in Vpp for a declared load [DS]."""
    k = load_factor(load_ohm)
    return AMPLITUDE_50OHM_VPP[0] * k, AMPLITUDE_50OHM_VPP[1] * k


def check_frequency(function: str, frequency_hz: float) -> None:
    """LimitError unless ``frequency_hz`` is within the function's range."""
    if function not in FREQUENCY_LIMITS_HZ:
        raise LimitError(f"function {function!r} has no frequency setting", "function")
    lo, hi = FREQUENCY_LIMITS_HZ[function]
    if not (math.isfinite(frequency_hz) and lo <= frequency_hz <= hi):
        raise LimitError(
            f"frequency {frequency_hz!r} Hz outside the 33220A {function} range "
            f"[{lo:g}, {hi:g}] Hz", "frequency_hz")


def check_amplitude_offset(amplitude_vpp: float, offset_v: float, load_ohm: float,
                           max_vpp: float | None = None) -> None:
    """LimitError unless amplitude (Vpp) and offset (V) fit the load and the bench limit.

    Instrument rules [DS/UG]: amplitude within :func:`amplitude_limits_vpp`;
    ``|offset| + amplitude/2 <= 5 V x load_factor``. Bench rule: ``amplitude <= max_vpp``
    and ``|offset| + amplitude/2 <= max_vpp/2`` (the peak never exceeds what the limit
    allows for a symmetric signal).
    """
    for name, v, setting in (("amplitude", amplitude_vpp, "amplitude_vpp"),
                             ("offset", offset_v, "offset_v")):
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise LimitError(f"{name} must be a finite number, got {v!r}", setting)
    lo, hi = amplitude_limits_vpp(load_ohm)
    load = "high-Z" if math.isinf(load_ohm) else f"{load_ohm:g} ohm"
    if not lo <= amplitude_vpp <= hi:
        raise LimitError(f"amplitude {amplitude_vpp:g} Vpp outside [{lo:g}, {hi:g}] Vpp "
                         f"for a {load} load (33220A)", "amplitude_vpp")
    peak = abs(offset_v) + amplitude_vpp / 2.0
    vmax = MAX_PEAK_50OHM_V * load_factor(load_ohm)
    if peak > vmax * (1 + 1e-12):
        raise LimitError(f"|offset| + amplitude/2 = {peak:g} V exceeds {vmax:g} V for a "
                         f"{load} load (33220A)", "offset_v")
    if max_vpp is not None:
        if amplitude_vpp > max_vpp * (1 + 1e-12):
            raise LimitError(f"amplitude {amplitude_vpp:g} Vpp exceeds the bench limit "
                             f"{max_vpp:g} Vpp (bench file [limits])", "amplitude_vpp")
        if peak > max_vpp / 2.0 * (1 + 1e-12):
            raise LimitError(f"peak |offset| + amplitude/2 = {peak:g} V exceeds the bench "
                             f"limit {max_vpp / 2:g} V (max {max_vpp:g} Vpp)", "offset_v")


def min_pulse_width_s(period_s: float) -> float:
    """Minimum pulse width for a pulse period [UG 'Pulse Waveforms']:
    20 ns up to 10 s, 200 ns up to 100 s, 2 us up to 1000 s, 20 us above."""
    if period_s <= 10.0:
        return 20e-9
    if period_s <= 100.0:
        return 200e-9
    if period_s <= 1000.0:
        return 2e-6
    return 20e-6


def check_pulse(period_s: float, width_s: float, edge_s: float) -> None:
    """LimitError unless period, width and edge time (s) satisfy the 33220A pulse rules:
    period in [200 ns, 2000 s]; Wmin <= width <= period - Wmin; edge in [5, 100] ns and
    edge <= 0.625 x width [UG/DS]."""
    for name, v, setting in (("period", period_s, "period_s"), ("width", width_s, "width_s"),
                             ("edge time", edge_s, "edge_s")):
        if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
            raise LimitError(f"pulse {name} must be a finite positive number, got {v!r}",
                             setting)
    lo, hi = PULSE_PERIOD_S
    if not lo <= period_s <= hi:
        raise LimitError(f"pulse period {period_s:g} s outside [{lo:g}, {hi:g}] s "
                         f"(PRF {1 / period_s:g} Hz)", "period_s")
    wmin = min_pulse_width_s(period_s)
    if width_s < wmin * (1 - 1e-9):
        raise LimitError(f"pulse width {width_s:g} s below the minimum {wmin:g} s",
                         "width_s")
    if width_s > (period_s - wmin) * (1 + 1e-12):
        raise LimitError(f"pulse width {width_s:g} s must be <= period - {wmin:g} s = "
                         f"{period_s - wmin:g} s", "width_s")
    elo, ehi = PULSE_EDGE_S
    if not elo * (1 - 1e-9) <= edge_s <= ehi * (1 + 1e-9):
        raise LimitError(f"edge time {edge_s:g} s outside [{elo:g}, {ehi:g}] s", "edge_s")
    if edge_s > EDGE_TO_WIDTH_MAX * width_s * (1 + 1e-9):
        raise LimitError(f"edge time {edge_s:g} s must be <= 0.625 x width "
                         f"= {EDGE_TO_WIDTH_MAX * width_s:g} s", "edge_s")


def check_pulse_burst(prf_hz: float, n_pulses: int, width_s: float, high_v: float,
                      low_v: float = 0.0, *, edge_s: float = BURST_EDGE_S,
                      load_ohm: float = math.inf, max_vpp: float | None = None) -> None:
    """LimitError (``setting`` naming the argument) unless
    :meth:`Agilent33220A.configure_pulse_burst` with these arguments is within the 33220A's
    rules for the declared ``load_ohm`` and the bench limit ``max_vpp``; nothing is sent.
    What that method checks first (a plan can be checked before any instrument is open)."""
    if not (isinstance(prf_hz, int | float) and math.isfinite(prf_hz) and prf_hz > 0):
        raise LimitError(f"prf_hz must be a positive number, got {prf_hz!r}", "prf_hz")
    check_frequency("pulse", prf_hz)
    check_pulse(1.0 / prf_hz, width_s, edge_s)
    if isinstance(n_pulses, bool) or int(n_pulses) != n_pulses or \
            not BURST_CYCLES[0] <= n_pulses <= BURST_CYCLES[1]:
        raise LimitError(f"n_pulses must be an integer in {list(BURST_CYCLES)} (burst "
                         f"cycles), got {n_pulses!r}", "n_pulses")
    if not high_v > low_v:
        raise LimitError(f"high_v ({high_v!r} V) must be above low_v ({low_v!r} V)",
                         "high_v")
    check_amplitude_offset(high_v - low_v, (high_v + low_v) / 2.0, load_ohm, max_vpp)


# --------------------------------------------------------------------------- the driver
_FUNCTIONS = {"sine": "SIN", "square": "SQU", "ramp": "RAMP", "pulse": "PULS",
              "noise": "NOIS", "dc": "DC", "user": "USER"}


class Agilent33220A(SCPIInstrument):
    """One Agilent 33220A. Implements :class:`pelvislab.drivers.interfaces.Generator`.

    Open it with :meth:`open` (VISA) or pass any :class:`~pelvislab.drivers.scpi.Transport`.
    Use it as a context manager: the output goes off on exit, on error and on
    KeyboardInterrupt.
    """

    model = "Agilent 33220A"
    # ``gen.amplitude = 15`` would pass the static limits only, not the load's, the offset's
    # or the bench's max_vpp, and leave the tracked state wrong (safety review, session 34)
    raw_settings = False
    setting_methods = {
        "function": "configure_sine() or configure_pulse_burst()",
        "frequency_hz": "set_frequency()",
        "amplitude": "set_amplitude() or configure_sine()",
        "offset_v": "configure_sine()",
        "output": "output_on()/output_off()",
        "output_load": "the load_ohm given at open",
        "sync_output": "set_sync_output()",
        "phase_deg": "set_phase()",
    }

    # ---- the declared command table -------------------------------------------------
    function = Control("FUNC?", "FUNC {}", "Output function.", kind=str, values=_FUNCTIONS,
                       spec="[UG] FUNCtion {SIN|SQU|RAMP|PULS|NOIS|DC|USER}")
    frequency_hz = Control("FREQ?", "FREQ {}", "Output frequency, Hz (limits per function "
                           "in FREQUENCY_LIMITS_HZ, checked by the methods).",
                           limits=(1e-6, 20e6), spec="[DS] 1 uHz to 20 MHz (sine)")
    amplitude = Control("VOLT?", "VOLT {}", "Amplitude in VOLT:UNIT (the driver uses VPP) "
                        "across the declared load.", limits=(10e-3, 20.0),
                        spec="[DS] 10 mVpp-10 Vpp into 50 ohm, x2 open circuit")
    offset_v = Control("VOLT:OFFS?", "VOLT:OFFS {}", "DC offset, V.", limits=(-10.0, 10.0),
                       spec="[DS] +-5 V into 50 ohm, x2 open circuit; |off|+Vpp/2 rule")
    voltage_unit = Control("VOLT:UNIT?", "VOLT:UNIT {}", "Amplitude unit.", kind=str,
                           values={"vpp": "VPP", "vrms": "VRMS", "dbm": "DBM"},
                           spec="[UG] VOLTage:UNIT {VPP|VRMS|DBM}")
    output = Control("OUTP?", "OUTP {}", "Main output on/off.", kind=bool,
                     spec="[UG] OUTPut {OFF|ON}")
    output_load = Control("OUTP:LOAD?", "OUTP:LOAD {}", "Declared load, ohm (use "
                          "set_load for INF).", limits=LOAD_LIMITS_OHM,
                          spec="[UG] 1 ohm to 10 kohm or INFinity; 9.9E+37 means INF")
    sync_output = Control("OUTP:SYNC?", "OUTP:SYNC {}", "Front-panel Sync output.",
                          kind=bool, spec="[UG] OUTPut:SYNC {OFF|ON}")
    pulse_period_s = Control("PULS:PER?", "PULS:PER {}", "Pulse period, s.",
                             limits=PULSE_PERIOD_S, spec="[DS] 200 ns to 2000 s")
    pulse_width_s = Control("FUNC:PULS:WIDT?", "FUNC:PULS:WIDT {}", "Pulse width, s.",
                            limits=(20e-9, 2000.0),
                            spec="[UG] >= Wmin(period), <= period - Wmin")
    pulse_edge_s = Control("FUNC:PULS:TRAN?", "FUNC:PULS:TRAN {}", "Pulse edge time, s.",
                           limits=PULSE_EDGE_S, spec="[UG] 5-100 ns, <= 0.625 x width")
    burst_enabled = Control("BURS:STAT?", "BURS:STAT {}", "Burst mode on/off.", kind=bool,
                            spec="[UG] BURSt:STATe {OFF|ON}")
    burst_mode = Control("BURS:MODE?", "BURS:MODE {}", "Burst mode.", kind=str,
                         values={"triggered": "TRIG", "gated": "GAT"},
                         spec="[UG] BURSt:MODE {TRIGgered|GATed}")
    burst_cycles = Control("BURS:NCYC?", "BURS:NCYC {}", "Cycles (pulses) per burst.",
                           kind=int, limits=BURST_CYCLES, spec="[UG] 1 to 50 000")
    burst_period_s = Control("BURS:INT:PER?", "BURS:INT:PER {}", "Burst period with the "
                             "internal trigger, s.", limits=BURST_PERIOD_S,
                             spec="[UG] 1 us to 500 s; > cycles/frequency + 200 ns")
    burst_phase_deg = Control("BURS:PHAS?", "BURS:PHAS {}", "Burst start phase, degrees.",
                              limits=PHASE_DEG, spec="[UG] -360 to +360 degrees")
    trigger_source = Control("TRIG:SOUR?", "TRIG:SOUR {}", "Trigger source.", kind=str,
                             values={"immediate": "IMM", "external": "EXT", "bus": "BUS"},
                             spec="[UG] TRIGger:SOURce {IMM|EXT|BUS}")
    trigger_slope = Control("TRIG:SLOP?", "TRIG:SLOP {}", "External trigger edge.", kind=str,
                            values={"positive": "POS", "negative": "NEG"},
                            spec="[UG] TRIGger:SLOPe {POSitive|NEGative}")
    phase_deg = Control("PHAS?", "PHAS {}", "Output phase offset, degrees.",
                        limits=PHASE_DEG, spec="[UG] -360 to +360 degrees")
    unlock_error_enabled = Control(
        "PHAS:UNL:ERR:STAT?", "PHAS:UNL:ERR:STAT {}",
        "Generate an error when the external-reference phase lock is lost (option 001).",
        kind=bool, spec="[UG] PHASe:UNLock:ERRor:STATe {OFF|ON}, option 001 only")

    # Commands without a value, and the common ones (also part of the table):
    IDN = "*IDN?"
    RESET = "*RST"
    CLEAR = "*CLS"
    OPC = "*OPC?"
    PHASE_REFERENCE = "PHAS:REF"

    def __init__(self, transport: Transport, resource: str = "", *,
                 load_ohm: float = 50.0, max_vpp: float | None = None,
                 external_reference: bool = True, reset: bool = True) -> None:
        super().__init__(transport, resource)
        try:
            self.load_ohm = _parse_load(load_ohm)
            if max_vpp is not None and not (math.isfinite(max_vpp) and max_vpp > 0):
                raise LimitError(f"max_vpp must be a positive number, got {max_vpp!r}")
        except BaseException:
            transport.close()  # nothing was sent; the connection is not left open
            raise
        self.max_vpp = max_vpp
        self.identity = ""
        self.has_option_001: bool | None = None
        self.safe_state_errors: list[str] = []
        self._state: dict[str, Any] = dict(RESET_STATE)
        self._closed = False
        self._identified = False  # never send OUTP OFF to something that is not a 33220A
        try:
            self._initialise(reset, external_reference)
        except BaseException:
            self.close()
            raise

    @classmethod
    def open(cls, resource: str, *, load_ohm: float | str = 50.0, max_vpp: float | None = None,
             timeout_s: float = 5.0, external_reference: bool = True,
             visa_library: str = "") -> Agilent33220A:
        """Open a 33220A by VISA resource name (``visa_library="x.yaml@sim"`` for
        pyvisa-sim), reset it, set VPP units and the declared load."""
        load = _parse_load(load_ohm)  # refused before a connection is opened
        transport = VisaTransport(resource, timeout_s=timeout_s, visa_library=visa_library)
        return cls(transport, resource, load_ohm=load, max_vpp=max_vpp,
                   external_reference=external_reference)

    def _initialise(self, reset: bool, external_reference: bool) -> None:
        with warnings.catch_warnings():
            # an instrument that answers nothing or junk is said below in one line; pyvisa's
            # own warning about the missing terminator only added a confusing second one
            warnings.filterwarnings("ignore", message="read string doesn't end with")
            self.identity = self.ask(self.IDN)
        fields = [f.strip() for f in self.identity.split(",")]
        if len(fields) < 2 or "33220A" not in fields[1].upper():
            raise DriverError(f"{self.resource!r} answers *IDN? with {self.identity!r}: "
                              "not an Agilent 33220A")
        self._identified = True
        if reset:
            self.write(self.RESET)
            self._state = dict(RESET_STATE)
        self.write(self.CLEAR)
        # *CLS empties the queue on the instrument; read it anyway so that a stale error
        # (from whoever used the instrument before) cannot be blamed on our first block.
        stale = self.read_errors()
        if stale:
            log.warning("%s: stale errors discarded at open: %s", self.resource, stale)
        if reset:
            answer = self.ask(self.OPC)
            if answer.strip() not in ("1", "+1"):
                raise InstrumentError(f"*OPC? answered {answer!r}, expected 1")
        with self.configuration("initialisation"):
            self.write("OUTP OFF")
            self.voltage_unit = "vpp"
            self.write(f"OUTP:LOAD {_load_token(self.load_ohm)}")
        if not reset or self.load_ohm != 50.0:
            # the levels are *RST's only after a reset into *RST's 50 ohm load: the
            # instrument rescales the displayed amplitude to another one (0.1 Vpp reads
            # 0.2 Vpp at high Z), and without a reset they are whatever was left
            self._forget_levels()
        if external_reference:
            # Option 001 (external timebase) is the only way to know about the lock; a
            # 33220A without it refuses the command (an error, not a silence).
            with self.driver_settings():
                self.unlock_error_enabled = True
            errors = self.read_errors()
            unlocked = [e for e in errors
                        if e[0] == REFERENCE_UNLOCKED_CODE or "unlock" in e[1].lower()]
            # only a refused command means no option 001; error 580 means the option is
            # there and the 10 MHz reference is not locked (cable out), which was taken
            # for "no option" and never reported (helper review, session 34)
            self.has_option_001 = len(unlocked) == len(errors)
            if not self.has_option_001:
                log.info("%s: no option 001 (%s): reference lock cannot be reported",
                         self.resource, errors)
            elif unlocked:
                raise ReferenceUnlockedError(
                    f"{self.model} {self.resource}: not locked to the external 10 MHz "
                    f"reference at open ({unlocked}): check the reference cable, or declare "
                    "external_reference = false for this generator")

    # ---- helpers -----------------------------------------------------------------------
    def _check_open(self) -> None:
        if self._closed:
            raise DriverError(f"{self.model} {self.resource}: already closed")

    @contextmanager
    def _operation(self, context: str) -> Iterator[None]:
        """A configuration block; any failure inside (instrument error, lost connection,
        timeout, KeyboardInterrupt) puts the output off before propagating."""
        self._check_open()
        try:
            with self.configuration(context):
                yield
        except BaseException:
            # what the instrument holds is unknown now (a VOLT may have been executed
            # before the error, e.g. a timeout on SYST:ERR?): the next block sends the
            # levels again instead of skipping them as unchanged (helper review, session 34:
            # 4 Vpp stayed set after a failed block, and a retry at 1 Vpp sent no VOLT)
            self._forget_levels()
            self.safe_state()
            raise

    def _forget_levels(self) -> None:
        """Mark amplitude and offset unknown: the next configuration sends both."""
        self._state["amplitude_vpp"] = None
        self._state["offset_v"] = None

    def _error_for(self, errors: list[tuple[int, str]], context: str) -> InstrumentError:
        base = super()._error_for(errors, context)
        if any(code == REFERENCE_UNLOCKED_CODE or "unlock" in msg.lower()
               for code, msg in errors):
            return ReferenceUnlockedError(str(base))
        return base

    def _amp_offset_commands(self, amplitude_vpp: float, offset_v: float) -> list[str]:
        """VOLT/VOLT:OFFS in an order whose intermediate state is always valid."""
        old_amp, old_off = self._state["amplitude_vpp"], self._state["offset_v"]
        vmax = MAX_PEAK_50OHM_V * load_factor(self.load_ohm)
        amp_cmd = f"VOLT {format_number(amplitude_vpp)}"
        off_cmd = f"VOLT:OFFS {format_number(offset_v)}"
        cmds: list[str] = []
        if old_amp is None or old_off is None:
            # levels unknown: offset 0 is valid with any amplitude the instrument holds,
            # then the amplitude, then the offset (each state valid)
            cmds = ["VOLT:OFFS 0", amp_cmd] + ([off_cmd] if offset_v != 0 else [])
        elif amplitude_vpp != old_amp and offset_v != old_off:
            if abs(old_off) + amplitude_vpp / 2 <= vmax:
                cmds = [amp_cmd, off_cmd]
            elif abs(offset_v) + old_amp / 2 <= vmax:
                cmds = [off_cmd, amp_cmd]
            else:
                cmds = ["VOLT:OFFS 0", amp_cmd, off_cmd]
        elif amplitude_vpp != old_amp:
            cmds = [amp_cmd]
        elif offset_v != old_off:
            cmds = [off_cmd]
        return cmds

    # ---- Generator interface ----------------------------------------------------------
    def configure_sine(self, frequency_hz: float, amplitude_vpp: float,
                       offset_v: float = 0.0) -> None:
        """Continuous sine (burst off); output state unchanged. Validated first."""
        check_frequency("sine", frequency_hz)
        check_amplitude_offset(amplitude_vpp, offset_v, self.load_ohm, self.max_vpp)
        with self._operation("configure_sine"):
            self.function = "sine"
            self.burst_enabled = False
            self.frequency_hz = frequency_hz
            for c in self._amp_offset_commands(amplitude_vpp, offset_v):
                self.write(c)
        self._state.update(function="sine", burst=False, frequency_hz=frequency_hz,
                           amplitude_vpp=amplitude_vpp, offset_v=offset_v)

    def set_frequency(self, frequency_hz: float) -> None:
        """New frequency (Hz) for the present function."""
        fn = self._state["function"]
        check_frequency(fn, frequency_hz)
        if fn == "pulse":  # the pulse width and edges must still fit the new period
            check_pulse(1.0 / frequency_hz, self._state["width_s"], self._state["edge_s"])
        with self._operation("set_frequency"):
            self.frequency_hz = frequency_hz
        self._state["frequency_hz"] = frequency_hz
        if fn == "pulse":
            self._state["period_s"] = 1.0 / frequency_hz

    def set_amplitude(self, amplitude_vpp: float) -> None:
        """New amplitude (Vpp) with the present offset."""
        if self._state["offset_v"] is None:
            raise DriverError(f"{self.model} {self.resource}: the offset is unknown after a "
                              "failed configuration; configure the waveform again first")
        check_amplitude_offset(amplitude_vpp, self._state["offset_v"], self.load_ohm,
                               self.max_vpp)
        with self._operation("set_amplitude"):
            self.amplitude = amplitude_vpp
        self._state["amplitude_vpp"] = amplitude_vpp

    check_pulse_burst = staticmethod(check_pulse_burst)
    """LimitError unless :meth:`configure_pulse_burst` would accept these arguments (give
    the generator's ``load_ohm`` and ``max_vpp``); see the module function."""

    def configure_pulse_burst(self, prf_hz: float, n_pulses: int, width_s: float,
                              high_v: float, low_v: float = 0.0, *,
                              edge_s: float = BURST_EDGE_S,
                              slope: str = "positive") -> None:
        """Externally triggered burst of ``n_pulses`` pulses at ``prf_hz`` (Hz), ``width_s``
        (s) wide, from ``low_v`` to ``high_v`` (V), edges ``edge_s`` (s); output unchanged.

        Sent as amplitude ``high_v - low_v`` (Vpp) and offset ``(high_v + low_v)/2``.
        """
        check_pulse_burst(prf_hz, n_pulses, width_s, high_v, low_v, edge_s=edge_s,
                          load_ohm=self.load_ohm, max_vpp=self.max_vpp)
        period_s = 1.0 / prf_hz
        amplitude_vpp = high_v - low_v
        offset_v = (high_v + low_v) / 2.0
        Agilent33220A.trigger_slope.validate(slope)
        with self._operation("configure_pulse_burst"):
            self.function = "pulse"
            # Order width/period/edge so that no intermediate state breaks a pulse rule: a
            # shorter edge first (a narrower width may need it: edge <= 0.625 x width), a
            # longer one last (helper review, session 34: always last gave -221 when the
            # old edge did not fit the new width)
            old_w, old_e = self._state["width_s"], self._state["edge_s"]
            if edge_s < old_e:
                self.pulse_edge_s = edge_s
            if width_s < old_w:
                self.pulse_width_s = width_s
            self.pulse_period_s = period_s
            if width_s >= old_w:
                self.pulse_width_s = width_s
            if edge_s >= old_e:
                self.pulse_edge_s = edge_s
            for c in self._amp_offset_commands(amplitude_vpp, offset_v):
                self.write(c)
            self.trigger_source = "external"
            self.trigger_slope = slope
            self.burst_mode = "triggered"
            self.burst_cycles = int(n_pulses)
            self.burst_enabled = True
        self._state.update(function="pulse", period_s=period_s, frequency_hz=prf_hz,
                           width_s=width_s, edge_s=edge_s, amplitude_vpp=amplitude_vpp,
                           offset_v=offset_v, burst=True)

    def output_on(self) -> None:
        """Main output on (after the error check of the previous configuration)."""
        with self._operation("output_on"):
            self.output = True

    def output_off(self) -> None:
        """Main output off."""
        with self._operation("output_off"):
            self.output = False

    @property
    def output_enabled(self) -> bool:
        """Asks the instrument (``OUTP?``)."""
        self._check_open()
        return bool(self.output)

    def set_sync_output(self, enabled: bool) -> None:
        """Front-panel Sync on/off (generator #2's Sync triggers generator #1's burst)."""
        with self._operation("set_sync_output"):
            self.sync_output = enabled

    def set_phase(self, phase_deg: float) -> None:
        """Output phase offset, degrees (``PHAS``)."""
        with self._operation("set_phase"):
            self.phase_deg = phase_deg

    def set_phase_reference(self) -> None:
        """Make the present phase the zero-phase reference (``PHAS:REF``)."""
        with self._operation("set_phase_reference"):
            self.write(self.PHASE_REFERENCE)

    def reference_locked(self) -> bool | None:
        """Lock on the external 10 MHz reference (option 001), via PHAS:UNL:ERR:STAT.

        None: no option 001 (or not checked at open). False: the instrument reported
        'Reference phase-locked loop is unlocked' (error 580, check). True: option 001
        present and no unlock error reported. The 33220A has no ROSC query; this is as
        much as it tells.
        """
        self._check_open()
        if not self.has_option_001:
            return None
        if not self.unlock_error_enabled:
            with self.driver_settings():
                self.unlock_error_enabled = True
        errors = self.read_errors()
        unlocked = [e for e in errors
                    if e[0] == REFERENCE_UNLOCKED_CODE or "unlock" in e[1].lower()]
        others = [e for e in errors if e not in unlocked]
        if others:
            raise self._error_for(others, "reference_locked")
        return not unlocked

    def safe_state(self) -> list[str]:
        """Output off. Never raises an Exception; returns this call's failures, also kept
        in ``safe_state_errors`` (a list another thread's safe state may append to
        meanwhile) and logged.

        From any thread: it waits for another thread's exchange under way (at most
        ``SAFE_STATE_IO_WAIT_S``), else sends ``OUTP OFF`` anyway after a device clear;
        the read-back ``OUTP?`` is then asked only once that exchange has ended, since
        its pending read would take the answer (review of session 35's diff)."""
        if self._closed or not self._identified:
            return []
        with self.safe_state_io() as free:  # never between another query and its answer
            self.clear_if_interrupted()  # so that a late answer cannot be mistaken later
            try:
                self.write("OUTP OFF")
            except BaseException as exc:  # the caller is already handling a failure
                failures = [self._not_confirmed(exc)]
                if not isinstance(exc, Exception):
                    raise
                return failures
            if free:
                return self._confirm_output_off()
        with self.safe_state_io(force=False) as free:
            if free:
                return self._confirm_output_off()
            return [self._not_confirmed("sent while another thread's exchange hung; not "
                                        "asked back (its pending read would take the "
                                        "answer)")]

    def _not_confirmed(self, reason: object) -> str:
        msg = f"{self.model} {self.resource}: OUTP OFF not confirmed: {reason}"
        self.safe_state_errors.append(msg)
        log.error(msg)
        return msg

    def _confirm_output_off(self) -> list[str]:
        """Ask ``OUTP?`` after ``OUTP OFF`` (a write that went out is not an executed
        command: "outputs off" is said only when the instrument says so; helper review,
        session 34), then empty the error queue. Returns the failure, if any."""
        try:
            answer = self.ask("OUTP?").strip()
            if answer not in ("0", "+0", "OFF"):
                raise InstrumentError(f"OUTP? answered {answer!r} after OUTP OFF")
        except BaseException as exc:
            failure = self._not_confirmed(exc)
            if not isinstance(exc, Exception):
                raise
            return [failure]
        self._drain_errors_after_safe_state()
        return []

    def _drain_errors_after_safe_state(self) -> None:
        """Empty the error queue once the output is confirmed off: errors left by the block
        that failed (a timeout before its SYST:ERR?) are logged here instead of being
        blamed on the next configuration block. Not a safe-state failure if it fails, nor
        if Ctrl-C cuts it (the output is off; whoever stops the run has the abort)."""
        try:
            stale = self.read_errors()
        except (Exception, KeyboardInterrupt) as exc:
            log.warning("%s %s: error queue not read after the safe state: %r", self.model,
                        self.resource, exc)
            return
        if stale:
            log.warning("%s %s: errors left in the queue at the safe state: %s", self.model,
                        self.resource, stale)

    def close(self) -> None:
        """Output off, then release the connection. Idempotent."""
        if self._closed:
            return
        try:
            self.safe_state()
        finally:
            self._closed = True
            try:
                self.transport.close()
            except Exception as exc:
                log.error("%s %s: close failed: %s", self.model, self.resource, exc)

    def __enter__(self) -> Agilent33220A:
        return self

    def __exit__(self, exc_type: object, exc: object, tb: object) -> None:
        self.close()


def _parse_load(load: float | str) -> float:
    if isinstance(load, str):
        if load.strip().lower() in ("inf", "infinity", "high-z", "highz", "hiz"):
            return math.inf
        raise LimitError(f"load must be ohms or 'inf', got {load!r}")
    v = float(load)
    if math.isinf(v):
        return v
    lo, hi = LOAD_LIMITS_OHM
    if not lo <= v <= hi:
        raise LimitError(f"load {v:g} ohm outside [{lo:g}, {hi:g}] ohm (or 'inf')")
    return v


def _load_token(load_ohm: float) -> str:
    return "INF" if math.isinf(load_ohm) else format_number(load_ohm)
