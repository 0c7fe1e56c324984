"""The sweep runner: executes a protocol on a bench and emits events (design 2 and 3).

Separation as in Bluesky: the :class:`Runner` executes the plan (setups x frequency steps)
and *emits events*; everything else listens. The CLI progress bar, the GUI and the session
writer (:class:`SessionRecorder`) are listeners, called synchronously in the runner's
thread, in subscription order. ``docs/runner.md`` lists every event type.

Control from any thread (GUI buttons, signal handlers): :meth:`Runner.pause`,
:meth:`Runner.resume`, :meth:`Runner.abort`, :meth:`Runner.confirm` (operator prompt),
:meth:`Runner.set_gate` and :meth:`Runner.live_echoes_in_pause` (re-placing a transducer).
``abort`` puts the bench in its safe state *immediately in the calling thread* (outputs
off), then the runner stops at its next check.

Safety rule: whatever ends a run (completion, abort, Ctrl-C, an exception in any instrument,
a listener or the numerics), every output goes off (``Bench.safe_state``) before the runner
returns, the reason is recorded (``RunFinished.reason``, session ``/runs``), and every step
completed so far has already been written.

Per step (design section 2): set the drive frequency -> wait to settle (max(settle_s,
settle_periods/f)) -> acquire N echoes per channel -> track displacement (ch. 8) -> phasor
at the drive frequency -> FRF line H = X / F, with F from the calibrated drive chain.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pelvislab.acquisition.frf_lines import calibrated_newton_per_volt
from pelvislab.acquisition.frfset import FrfSet
from pelvislab.acquisition.protocol import PlannedStep, Protocol, Setup
from pelvislab.acquisition.session import (
    STATUS_COMPLETE,
    ChannelData,
    SessionReader,
    SessionWriter,
    StepData,
    extend_cut_session,
    first_difference,
    frf_from_steps,
    partial_path,
    run_records,
)
from pelvislab.acquisition.tracking import gate_problem
from pelvislab.drivers.bench import SPEED_OF_SOUND_RANGE_M_S

__all__ = [
    "DRIVE_PHASE_AT_FIRST_PULSE_RAD",
    "AimedEcho",
    "AimingEchoes",
    "Event",
    "Fault",
    "LogMessage",
    "NothingToResume",
    "OperatorPrompt",
    "Paused",
    "PreparedSession",
    "Progress",
    "Quality",
    "Resumed",
    "RunFinished",
    "RunStarted",
    "Runner",
    "SessionRecorder",
    "SetupFinished",
    "SetupStarted",
    "StepFinished",
    "StepStarted",
    "drive_voltage_phasor",
    "prepare_session",
    "process_channel",
    "reprocess_session",
]

log = logging.getLogger(__name__)

DRIVE_PHASE_AT_FIRST_PULSE_RAD = -math.pi / 2
"""Phase of the drive sine at the first pulse of a record.

The trigger burst starts on the drive generator's SYNC edge, i.e. at the start of a sine
period (design section 2), so v(t) = A sin(wt) = Re(A e^{-i pi/2} e^{iwt}) from the first
pulse on (harmonic convention of design 4.1).
"""
QUALITY_MIN_CORRELATION = 0.8
QUALITY_MAX_LOST_FRACTION = 0.05
QUALITY_MIN_PERIODS = 1.0
"""Tracked echoes spanning less of the drive than this (periods) give no usable phasor."""


# --------------------------------------------------------------------------- events
@dataclass(frozen=True)
class Event:
    """Base of every runner event; ``t_s`` is seconds since the run started."""

    t_s: float


@dataclass(frozen=True)
class RunStarted(Event):
    """The run begins; ``n_done`` steps were already in the session (resume)."""

    protocol: str
    n_steps: int
    n_done: int
    estimated_s: float
    simulated: bool


@dataclass(frozen=True)
class SetupStarted(Event):
    """A setup (transducer placement) begins."""

    setup_index: int
    setup: str
    excitation: str
    transducers: Mapping[int, str]
    n_setups: int


@dataclass(frozen=True)
class OperatorPrompt(Event):
    """Reposition the transducers: the runner waits for :meth:`Runner.confirm` (or abort)
    unless it runs with ``auto_continue``. The drive is off while it waits; the trigger
    pulses only for the live echoes (:class:`AimingEchoes`)."""

    setup_index: int
    setup: str
    message: str
    auto_continue: bool


@dataclass(frozen=True)
class AimedEcho:
    """One channel's latest echo while the operator places its transducer."""

    channel: int
    landmark: str
    time_s: np.ndarray
    """(n_samples,) time of each sample after the trigger (s)."""
    volts: np.ndarray
    """(n_samples,) the last pulse's echo (V)."""
    gate: tuple[int, int] | None
    """The samples the steps will track in (None: no echo to gate on)."""
    gate_source: str
    """``operator`` (:meth:`Runner.set_gate`), ``protocol`` (the setup's ``gates``),
    ``options`` (the tracking options' gate) or ``auto`` (the strongest echo)."""
    notes: tuple[str, ...]
    """What the tracker would say about the gate (a rival echo, a clipped gate) or why no
    gate was found."""
    sample_rate_hz: float
    delay_s: float
    rival_sample: int | None = None
    """Sample of another echo within 10 dB of the gated one (automatic gate), else None."""


@dataclass(frozen=True)
class AimingEchoes(Event):
    """Live echoes while the runner waits at an operator prompt, or in a pause when asked
    (:meth:`Runner.live_echoes_in_pause`): the trigger pulses the transducers, the drive
    stays off. Lets the operator find the bone echo and set each channel's gate
    (:meth:`Runner.set_gate`) before anything is measured, or again before the next step."""

    setup_index: int
    echoes: tuple[AimedEcho, ...]


@dataclass(frozen=True)
class StepStarted(Event):
    """A frequency step begins (``index`` in the plan)."""

    step: PlannedStep
    n_done: int
    n_steps: int


@dataclass(frozen=True)
class StepFinished(Event):
    """A step was acquired and processed; ``data`` is what the session stores."""

    step: PlannedStep
    data: StepData
    duration_s: float


@dataclass(frozen=True)
class Quality(Event):
    """Signal quality of one channel of one step (echo tracking, ch. 8)."""

    step: PlannedStep
    channel: str
    ok: bool
    correlation_median: float
    lost_fraction: float
    snr_db_median: float
    message: str


@dataclass(frozen=True)
class Progress(Event):
    """Steps done of the plan, and the estimated time left."""

    n_done: int
    n_steps: int
    elapsed_s: float
    eta_s: float

    @property
    def fraction(self) -> float:
        """Done fraction 0..1."""
        return self.n_done / self.n_steps if self.n_steps else 1.0


@dataclass(frozen=True)
class Paused(Event):
    """The runner paused between steps (outputs off; the trigger pulses again only for
    live echoes, when asked: :meth:`Runner.live_echoes_in_pause`)."""

    reason: str


@dataclass(frozen=True)
class Resumed(Event):
    """The runner resumed after a pause."""


@dataclass(frozen=True)
class SetupFinished(Event):
    """Every step of a setup is done (outputs off)."""

    setup_index: int
    setup: str


@dataclass(frozen=True)
class LogMessage(Event):
    """A line for the operator and the session log."""

    level: str
    text: str


@dataclass(frozen=True)
class Fault(Event):
    """An instrument (or the session writer) failed; outputs are already off.
    ``fault_t_s``: when the runner caught the failure (before the safe state), same clock."""

    reason: str
    fault_t_s: float = float("nan")


@dataclass(frozen=True)
class RunFinished(Event):
    """The run ended: ``status`` is completed, aborted, interrupted or failed.

    ``unsafe``: what the run's last safe state could not confirm (an ``OUTP OFF`` that
    failed, a pulser that did not answer); empty when every output was confirmed off. Not
    empty means an output may still be on: the operator must switch it off by hand."""

    status: str
    reason: str
    n_done: int
    n_steps: int
    unsafe: tuple[str, ...] = ()


Listener = Callable[[Event], None]


class _Stop(Exception):
    """Raised inside the runner when an abort was requested."""


class RunInterrupted(KeyboardInterrupt):
    """Raised by :meth:`Runner.interrupt` (a signal handler) to cut a wait short.

    A subclass, not ``KeyboardInterrupt`` itself: CPython 3.11 marks the process for exit
    *by* SIGINT (exit status -2 instead of our 130) whenever an exact KeyboardInterrupt
    passes through code run by ``exec`` of a string, even if it is caught later; the handler
    can fire while a lazy import defines a dataclass (dataclasses build methods that way).
    The exact-type check there does not match a subclass; ``except KeyboardInterrupt``
    still does."""


# --------------------------------------------------------------------------- numerics glue
def drive_voltage_phasor(amplitude_vpp: float) -> complex:
    """Drive-voltage phasor (V, peak) at the first pulse of a record."""
    return 0.5 * amplitude_vpp * complex(math.cos(DRIVE_PHASE_AT_FIRST_PULSE_RAD),
                                         math.sin(DRIVE_PHASE_AT_FIRST_PULSE_RAD))


def force_phasor(frequency_hz: float, amplitude_vpp: float, newton_per_volt: complex) -> complex:
    """Force phasor (N, peak, at the first pulse) from the calibrated drive chain
    (:func:`pelvislab.acquisition.frf_lines.drive_force_phasor`)."""
    from pelvislab.acquisition.frf_lines import drive_force_phasor

    return complex(drive_force_phasor(frequency_hz, amplitude_vpp, newton_per_volt,
                                      DRIVE_PHASE_AT_FIRST_PULSE_RAD).value)


def process_channel(channel: ChannelData, frequency_hz: float, options: Any = None,
                    speed_of_sound_m_s: float | None = None) -> ChannelData:
    """Track ``channel``'s echoes and estimate the displacement phasor, in place.

    Uses :func:`pelvislab.acquisition.tracking.track_echoes` (ch. 8) and
    :func:`pelvislab.acquisition.phasor.estimate_phasor`, referred to the first pulse: echo
    ``k`` samples the bone at k / prf plus half the echo's round trip (s,
    :func:`~pelvislab.acquisition.frf_lines.bone_sampling_delay_s`, in
    ``quality['bone_sampling_delay_s']``). Tracking failures leave ``phasor_m`` None and say
    why in ``quality['message']``.
    """
    from pelvislab.acquisition.frf_lines import bone_sampling_delay_s
    from pelvislab.acquisition.phasor import estimate_phasor
    from pelvislab.acquisition.tracking import track_echoes

    c = float(speed_of_sound_m_s or channel.speed_of_sound_m_s)
    channel.speed_of_sound_m_s = c
    try:
        result = track_echoes(channel.codes, channel.trigger_offset_s, channel.sample_rate_hz,
                              c, volts_per_count=channel.volts_per_count, options=options)
    except Exception as exc:  # bad echoes are a quality problem, not a crash
        channel.displacement_m = None
        channel.phasor_m = None
        channel.phasor_std_m = None
        channel.quality = {"ok": False, "message": f"tracking failed: {exc}"}
        return channel
    disp = np.asarray(result.displacement_m, dtype=float)
    sampling_delay_s = bone_sampling_delay_s(channel.delay_s, result)
    time_s = np.arange(disp.size, dtype=float) / channel.prf_hz + sampling_delay_s
    lost = np.asarray(getattr(result, "lost", np.zeros(disp.size, bool)), dtype=bool)
    quality: dict[str, Any] = {"bone_sampling_delay_s": sampling_delay_s}
    corr = np.asarray(getattr(result, "correlation", np.ones(disp.size)), dtype=float)
    snr = np.asarray(getattr(result, "snr_db", np.full(disp.size, np.nan)), dtype=float)
    quality["correlation_median"] = float(np.nanmedian(corr)) if corr.size else float("nan")
    quality["correlation_min"] = float(np.nanmin(corr)) if corr.size else float("nan")
    quality["snr_db_median"] = float(np.nanmedian(snr)) if np.isfinite(snr).any() else float(
        "nan")
    quality["lost_fraction"] = float(lost.mean()) if lost.size else 0.0
    gate = getattr(result, "gate", None)
    if gate is not None:
        quality["gate_start"], quality["gate_stop"] = int(gate[0]), int(gate[1])
    hops = getattr(result, "peak_hops", None)
    if hops is not None:
        quality["peak_hops"] = int(np.count_nonzero(np.asarray(hops)))
    good = ~lost & np.isfinite(disp)
    channel.displacement_m = disp
    try:
        if good.sum() < 4:
            raise ValueError("fewer than 4 tracked echoes")
        ph = estimate_phasor(disp[good], time_s[good], frequency_hz)
        channel.phasor_m = complex(ph.value)
        channel.phasor_std_m = float(getattr(ph, "std", float("nan")))
        thd = getattr(ph, "thd", None)
        if thd is not None:
            quality["thd"] = float(thd)
    except Exception as exc:
        channel.phasor_m = None
        channel.phasor_std_m = None
        quality["message"] = f"phasor failed: {exc}"
    # the protocol asks for 2 or more periods per record; a digitizer that returned fewer
    # segments (a truncated acquisition) gave 13 mm for 1 um from 8 pulses, "ok" (tracking
    # review, session 36)
    span_periods = (float(frequency_hz * np.ptp(time_s[good])) if good.sum() >= 2 else 0.0)
    quality["periods_tracked"] = span_periods
    short = channel.phasor_m is not None and span_periods < QUALITY_MIN_PERIODS
    if short:
        recorded_periods = float(frequency_hz * np.ptp(time_s)) if time_s.size >= 2 else 0.0
        # a full record whose echoes were lost is not a truncated one (audit, session 41:
        # a nine-point step at 10 Hz, 5000 pulses, most echoes out of the window, read
        # "a truncated acquisition?")
        why = (f"{disp.size} segments recorded: a truncated acquisition?"
               if recorded_periods < QUALITY_MIN_PERIODS else
               f"the record spans {recorded_periods:.2g} periods; {int(good.sum())} of {disp.size} "
               f"echoes tracked, the rest lost")
        quality["message"] = (f"the tracked echoes span {span_periods:.2g} period(s) of the "
                              f"drive, under the {QUALITY_MIN_PERIODS:g} a phasor needs "
                              f"({why})")
    ok = (channel.phasor_m is not None and not short
          and quality["correlation_median"] >= QUALITY_MIN_CORRELATION
          and quality["lost_fraction"] <= QUALITY_MAX_LOST_FRACTION)
    quality["ok"] = bool(ok)
    quality.setdefault("message", "ok" if ok else (
        f"poor tracking: median correlation {quality['correlation_median']:.2f}, "
        f"{100 * quality['lost_fraction']:.1f}% echoes lost"))
    # The tracker says in words what went wrong or was corrected (e.g. the echo left the
    # recorded window, and what to change): that belongs in front of the operator too.
    tracker_warnings = [" ".join(str(w).split()) for w in getattr(result, "warnings", []) or []]
    if tracker_warnings:
        quality["tracking_warnings"] = "; ".join(tracker_warnings)
        if not ok:
            quality["message"] = f"{quality['message']}; {quality['tracking_warnings']}"
    channel.quality = quality
    return channel


AUTO_RANGE_MARGIN = 0.7
"""Auto drive mode aims at this fraction of ``max_displacement_m`` (motion scales with the
drive level, but the measured amplitude of a record that lost echoes is uncertain)."""
AUTO_RANGE_LOST_STEP = 0.2
"""Auto drive mode: largest level factor when echoes were lost during large motion."""
AUTO_RANGE_UNKNOWN_STEP = 0.05
"""Auto drive mode: level factor when (nearly) every echo was lost and the motion is
unknown: the echo leaves the record beyond ~100 um amplitude, 5x the usual 20 um limit, and
at a sharp resonance far more (face_up, sacrum drive point, 175 Hz: 0.1 Vpp still lost 47 %
of the echoes where 0.5 Vpp lost all)."""


def _max_lost(data: StepData) -> float:
    return max((float(c.quality.get("lost_fraction", 1.0)) for c in data.channels),
               default=0.0)


def motion_amplitude_m(phasor_m: complex | None, displacement_m: np.ndarray | None) -> float:
    """Largest displacement amplitude (m, peak) a record shows: the phasor magnitude or
    half the peak-to-peak of the tracked displacement, whichever is larger (NaN: none)."""
    amp = abs(phasor_m) if phasor_m is not None else math.nan
    if displacement_m is not None:
        d = np.asarray(displacement_m, dtype=float)
        d = d[np.isfinite(d)]
        if d.size:
            half_pp = 0.5 * float(d.max() - d.min())
            amp = half_pp if not math.isfinite(amp) else max(amp, half_pp)
    return float(amp)


def auto_range_level(phasors_m: Sequence[complex | None],
                     displacements_m: Sequence[np.ndarray | None],
                     lost_fractions: Sequence[float], level_vpp: float,
                     max_displacement_m: float,
                     min_drive_vpp: float) -> tuple[float | None, str]:
    """Lower drive level (V pk-pk) for repeating a step, or (None, "") to keep it.

    Per channel: the measured amplitude (:func:`motion_amplitude_m`, m) and the fraction of
    lost echoes. The step is repeated when an amplitude exceeds ``max_displacement_m``
    (new level = level x max / measured x :data:`AUTO_RANGE_MARGIN`: displacement is
    linear in the force), or when more than 5 % of a channel's echoes were lost while its
    motion was large (over half the limit: x :data:`AUTO_RANGE_LOST_STEP` or the ratio
    rule if smaller) or unknown (no phasor: x :data:`AUTO_RANGE_UNKNOWN_STEP`). The level
    never goes under ``min_drive_vpp`` and a step already at the floor is not repeated.
    The second string says why.
    """
    amps = [motion_amplitude_m(p, d) for p, d in zip(phasors_m, displacements_m, strict=True)]
    worst = max((a for a in amps if math.isfinite(a)), default=math.nan)
    factor = math.inf
    why = ""
    if math.isfinite(worst) and worst > max_displacement_m:
        factor = max_displacement_m / worst * AUTO_RANGE_MARGIN
        why = f"motion {worst * 1e6:.3g} um > {max_displacement_m * 1e6:.3g} um"
    for a, lost in zip(amps, lost_fractions, strict=True):
        if lost <= QUALITY_MAX_LOST_FRACTION:
            continue
        if not math.isfinite(a):
            factor = min(factor, AUTO_RANGE_UNKNOWN_STEP)
            why = why or f"{lost:.0%} echoes lost, motion unknown"
        elif a > 0.5 * max_displacement_m:
            factor = min(factor, AUTO_RANGE_LOST_STEP)
            why = why or f"{lost:.0%} echoes lost with large motion"
    if not math.isfinite(factor) or level_vpp <= min_drive_vpp * (1 + 1e-9):
        return None, ""
    return max(min_drive_vpp, level_vpp * min(factor, 0.9)), why


def better_record(first: StepData, second: StepData, max_displacement_m: float) -> StepData:
    """The better of two records of one step: fewer channels with poor quality, then fewer
    lost echoes (worst channel, to 0.1 %), then fewer channels moving more than
    ``max_displacement_m``; a tie keeps ``first`` (the higher level: better SNR)."""
    def score(d: StepData) -> tuple[int, float, int]:
        bad = sum(not bool(c.quality.get("ok")) for c in d.channels)
        over = sum(motion_amplitude_m(c.phasor_m, c.displacement_m) > max_displacement_m
                   for c in d.channels)
        return bad, round(_max_lost(d), 3), over

    return second if score(second) < score(first) else first


class NothingToResume(Exception):
    """``prepare_session(resume=True)`` on a session that already holds every step of its
    plan: nothing is opened or written."""


def check_protocol_gates(protocol: Protocol, tracking_options: Any) -> None:
    """Raise ValueError when a setup's ``gates`` (checked by the protocol with the default
    lag range) cannot be tracked with ``tracking_options`` (its lag range)."""
    lag = int(_with_gate(tracking_options, None).max_lag_samples)
    for setup in protocol.setups:
        for ch, gate in sorted(setup.gates.items()):
            problem = gate_problem(gate, lag, int(protocol.ultrasound.samples))
            if problem:
                raise ValueError(f"setups {setup.name!r}: gate {gate} for ch{ch} with these "
                                 f"tracking options: {problem}")


NO_LIVE_ECHOES = "no live echoes"
"""How the WARNING of a failed live echo begins (the GUI ends its live echoes on it)."""


# --------------------------------------------------------------------------- runner
class Runner:
    """Runs ``protocol`` on an open ``bench`` (see module docstring).

    ``skip``: step keys ``(setup, frequency, repeat)`` already in the session (resume).
    ``auto_continue``: answer operator prompts automatically (headless runs).
    """

    def __init__(self, protocol: Protocol, bench: Any, *, auto_continue: bool = True,
                 tracking_options: Any = None, skip: Iterable[tuple[Any, ...]] = (),
                 clock: Callable[[], float] = time.monotonic, aim_pulses: int = 16,
                 aim_interval_s: float = 0.3) -> None:
        self.protocol = protocol
        self.bench = bench
        self.auto_continue = auto_continue
        self.tracking_options = tracking_options
        self.aim_pulses = int(aim_pulses)
        """Pulses per live echo while the runner waits at a prompt (0: no live echoes)."""
        self.aim_interval_s = float(aim_interval_s)
        """Seconds between two live echoes at a prompt or in a pause."""
        self._gates: dict[int, tuple[int, int]] = {}
        self._protocol_gated: set[int] = set()  # channels on their protocol gate
        self._gates_lock = threading.Lock()
        self._current_setup: Setup | None = None  # the setup being placed or measured
        self._skip = {(k[0], round(float(k[1]), 9), int(k[2]) if len(k) > 2 else 0)
                      for k in skip}
        check_protocol_gates(protocol, self._tracking_options())
        self._clock = clock
        self._listeners: list[tuple[Listener, bool]] = []
        self._abort = threading.Event()
        self._abort_reason = ""
        self._abort_status = "aborted"
        self._pause = threading.Event()
        self._pause_lock = threading.Lock()
        self._resumes = 0  # resume() calls: each ends the pause under way
        self._live_in_pause = threading.Event()
        self._live_requests = 0  # "on" requests of live_echoes_in_pause so far
        self._confirm = threading.Event()
        self._wake = threading.Event()
        self._lock = threading.RLock()  # generator commands vs. abort from another thread
        self._t0 = clock()
        self.critical = False
        """True while listeners run (they write the session): signal handlers must then
        only call :meth:`abort`, not raise."""
        self.state = "idle"
        self._notes: list[tuple[str, str]] = []  # (level, text) from other threads
        self._notes_lock = threading.Lock()
        self._unsafe: list[str] = []  # failures of the last safe state that completed

    # -------------------------------------------------------------- listeners
    def subscribe(self, listener: Listener, critical: bool = False) -> None:
        """Call ``listener(event)`` for every event. An exception in a ``critical``
        listener (the session writer) is a fault that stops the run, raised once every
        other listener has had the event; in another listener it is logged and that
        listener is dropped."""
        self._listeners.append((listener, critical))

    def _emit(self, event: Event) -> None:
        # Listeners write files: a signal handler must not raise inside them (see critical).
        was = self.critical
        self.critical = True
        critical_failure: Exception | None = None
        try:
            for listener, critical in list(self._listeners):
                try:
                    listener(event)
                except Exception as exc:
                    if critical:
                        # the others still get the event: a session writer refusing every
                        # write after a failed one kept the Fault and RunFinished from the
                        # GUI, which showed "RUNNING — OUTPUTS ON" for a run ended with its
                        # outputs off (session 51)
                        critical_failure = critical_failure or exc
                        continue
                    log.error("listener %r failed on %s, dropped: %s", listener,
                              type(event).__name__, exc)
                    self._listeners.remove((listener, critical))
        finally:
            self.critical = was
        if critical_failure is not None:
            raise critical_failure

    def _t(self) -> float:
        return self._clock() - self._t0

    @property
    def started_clock_s(self) -> float:
        """The clock reading (``time.monotonic`` by default) at which the run started:
        event time ``t_s`` + this = clock time."""
        return self._t0

    def _log(self, text: str, level: str = "INFO") -> None:
        self._emit(LogMessage(self._t(), level, text))

    # -------------------------------------------------------------- control (any thread)
    def pause(self) -> None:
        """Pause before the next step (outputs go off until :meth:`resume`)."""
        self._pause.set()

    def resume(self) -> None:
        """Continue after :meth:`pause` (live echoes, if on, stop first). Every resume ends
        the pause under way, also when :meth:`pause` follows before the runner saw it: a
        new pause (``Resumed``, then ``Paused``) begins then, with the outputs still off."""
        with self._pause_lock:
            self._live_in_pause.clear()
            self._resumes += 1
            self._pause.clear()
        self._wake.set()

    def live_echoes_in_pause(self, on: bool) -> None:
        """While paused: show live echoes (``on``) or stop them. The trigger then pulses
        for each live echo (:class:`AimingEchoes`); the drive stays off. For re-placing a
        transducer that moved during the run and setting its gate again
        (:meth:`set_gate`) before the next step. Off again at :meth:`resume`; a request
        outside a pause is kept for the next pause of this run."""
        if on:
            # counted: an "on" asked again after live echoes failed retries them, even when
            # the pause loop never saw the "off" between (a GUI unchecks and the operator
            # presses again within one of its waits: the retry was lost; seen under load)
            self._live_requests += 1
            self._live_in_pause.set()
        else:
            self._live_in_pause.clear()
        self._wake.set()

    def confirm(self) -> None:
        """Answer the current operator prompt: transducers are in place, go on."""
        self._confirm.set()
        self._wake.set()

    def abort(self, reason: str = "aborted by the operator", status: str = "aborted") -> None:
        """Stop the run: every output off now (in this thread), the runner stops next."""
        self._request_abort(reason, status)
        self._safe_state()

    def _request_abort(self, reason: str, status: str) -> None:
        if not self._abort.is_set():
            self._abort_reason = reason
            self._abort_status = status
        self._abort.set()
        self._wake.set()

    def interrupt(self, reason: str = "interrupted (SIGINT)", safe_state: bool = True) -> None:
        """For a signal handler in the runner's own thread: abort (outputs off at once) and,
        unless listeners are writing, raise KeyboardInterrupt to cut a wait short.

        ``safe_state=False`` when another thread already puts the outputs off (the CLI's
        signal watcher): the handler runs between any two bytecodes of the run, also inside
        an instrument's (or the simulator's) lock, and switching outputs off from there
        deadlocked against that thread's safe state (it held a pulser's lock and waited for
        the simulator's, the handler the other way round: a Ctrl-C'd run that never ended,
        seen in 2 of 4 full test runs under load)."""
        if safe_state:
            self.abort(reason, "interrupted")
        else:
            self._request_abort(reason, "interrupted")
        if not self.critical and self.state in ("running", "waiting", "paused"):
            raise RunInterrupted(reason)

    def set_gate(self, channel: int, gate: tuple[int, int] | None) -> None:
        """Track ``channel``'s echoes in ``gate`` (start, stop: sample indices of the
        record) from the next step of the current setup on; None: the automatic gate again.

        Any thread. When a setup starts (its transducers are placed anew) the gates are
        the setup's own from the protocol (``Setup.gates``; usually none); set one at the
        prompt, where the live echoes (:class:`AimingEchoes`) show the record.
        Raises ValueError for a channel the protocol does not record, a gate that does
        not fit the record with the tracking's lag range, or a call before the run's first
        setup has started (nothing is changed then)."""
        if channel not in self.protocol.channels:
            raise ValueError(f"channel {channel} is not recorded by this protocol "
                             f"(channels {list(self.protocol.channels)})")
        setup = self._current_setup
        if setup is not None and channel not in setup.transducers:
            # accepted, it would wait unused until the setup ends (review, session 38)
            raise ValueError(f"channel {channel} is not used in setup {setup.name!r} "
                             f"(channels {sorted(setup.transducers)})")
        if gate is not None:
            gate = (int(gate[0]), int(gate[1]))
            problem = gate_problem(gate, int(self._tracking_options().max_lag_samples),
                                   int(self.protocol.ultrasound.samples))
            if problem:
                raise ValueError(f"gate {gate} for ch{channel}: {problem}")
        if setup is None:
            # accepted before, and replaced by the first setup's own gates when it started:
            # every step tracked automatically (docs audit, session 43)
            raise ValueError(f"no setup is under way to gate ch{channel} in: a gate is for "
                             "the transducers as placed; set it at a setup's prompt, or give "
                             "the setup `gates` in the protocol")
        with self._gates_lock:
            if self._current_setup is not setup:
                # the next setup started while this was checked: its transducers are placed
                # anew, so a gate seen in the last one's echoes does not apply
                raise ValueError(f"setup {setup.name!r} ended before the gate for "
                                 f"ch{channel} was set: nothing changed; set it in setup "
                                 f"{self._current_setup.name!r}'s echoes")
            self._protocol_gated.discard(channel)
            if gate is None:
                self._gates.pop(channel, None)
            else:
                self._gates[channel] = gate
        self._defer_log(f"ch{channel}: gate set by the operator to samples {gate[0]}-{gate[1]}"
                        if gate is not None else f"ch{channel}: automatic gate again")

    @property
    def gates(self) -> dict[int, tuple[int, int]]:
        """The gates of the current setup, by channel: the protocol's (``Setup.gates``)
        and those set with :meth:`set_gate`."""
        with self._gates_lock:
            return dict(self._gates)

    def _tracking_options(self, gate: tuple[int, int] | None = None) -> Any:
        """The runner's tracking options (the defaults when it has none), with ``gate``
        (an operator's gate) if given."""
        return _with_gate(self.tracking_options, gate if gate is not None
                          else getattr(self.tracking_options, "gate", None))

    def _gates_now(self) -> dict[int, tuple[tuple[int, int], str]]:
        """Channel -> (gate, ``protocol`` or ``operator``) of the current setup, at once."""
        with self._gates_lock:
            return {ch: (g, "protocol" if ch in self._protocol_gated else "operator")
                    for ch, g in self._gates.items()}

    def _gate_source(self, gate: tuple[tuple[int, int], str] | None) -> str:
        """How a channel's gate was chosen (see :attr:`AimedEcho.gate_source`), from its
        entry in :meth:`_gates_now` (None: none there)."""
        if gate is not None:
            return gate[1]
        return "options" if getattr(self.tracking_options, "gate", None) else "auto"

    @property
    def aborted(self) -> bool:
        """True once an abort was requested."""
        return self._abort.is_set()

    def _safe_state(self) -> None:
        got = self._lock.acquire(timeout=0.05)  # never wait long for the runner thread
        try:
            # what matters is whether the outputs are off now: the last call that completed
            # decides (an interrupt inside one leaves it to the next, e.g. the run's end)
            self._unsafe = list(self.bench.safe_state() or [])
        except BaseException as exc:  # Bench.safe_state raises only an interrupt, after
            log.error("safe state: %s", exc)  # every instrument; the run's end redoes it
        finally:
            if got:
                self._lock.release()

    @property
    def unsafe(self) -> tuple[str, ...]:
        """Failures of the last completed safe state (see :class:`RunFinished`)."""
        return tuple(self._unsafe)

    def _outputs_phrase(self) -> str:
        return ("OUTPUTS NOT CONFIRMED OFF (" + "; ".join(self._unsafe)
                + "): switch the shaker amplifier off by hand" if self._unsafe
                else "outputs off")

    # -------------------------------------------------------------- helpers
    def add_note(self, text: str) -> None:
        """Operator note from any thread; the runner's thread emits it as a LogMessage of
        level NOTE (so the session writer stays single-threaded) at its next check."""
        self._defer_log(text, "NOTE")

    def _defer_log(self, text: str, level: str = "INFO") -> None:
        """A log line from any thread, emitted by the runner's thread at its next check
        (listeners write the session: they run in that thread only)."""
        with self._notes_lock:
            self._notes.append((level, " ".join(str(text).split())))
        self._wake.set()

    def _flush_notes(self) -> None:
        with self._notes_lock:
            notes, self._notes = self._notes, []
        for level, note in notes:
            self._emit(LogMessage(self._t(), level, note))

    def _check(self) -> None:
        if self._notes:
            self._flush_notes()
        if self._abort.is_set():
            raise _Stop(self._abort_reason)

    def _sleep(self, seconds: float) -> None:
        """Interruptible wait (abort wakes it)."""
        deadline = self._clock() + seconds
        while True:
            self._check()
            left = deadline - self._clock()
            if left <= 0:
                return
            self._wake.wait(min(left, 0.05))
            self._wake.clear()

    def _settle(self, seconds: float) -> None:
        """Wait for the response to settle: real time, except on a fast-paced simulated
        bench, whose own clock then skips the wait (its physics sees the time pass)."""
        clock = getattr(getattr(self.bench, "world", None), "clock", None)
        if (self.bench.simulated and clock is not None
                and getattr(clock, "pacing", "") == "fast" and hasattr(clock, "wait")):
            self._check()
            clock.wait(seconds)
            return
        self._sleep(seconds)

    def _generators(self, on: bool) -> None:
        with self._lock:
            if on:
                self._check()  # never switch on after an abort
                self.bench.drive.output_on()
                # an abort that could not wait for this lock (50 ms) may have put both off
                # meanwhile: do not switch the trigger back on after it
                self._check()
                self.bench.trigger.output_on()
            else:
                try:
                    self.bench.drive.output_off()
                finally:  # the trigger off even when the drive's OFF raised
                    self.bench.trigger.output_off()

    def _wait_prompt(self, setup_index: int, setup: Setup, first: PlannedStep) -> None:
        """Prompt the operator and wait for :meth:`confirm`, showing live echoes meanwhile
        (:meth:`_aim`; they leave the trigger and the digitizer configured for themselves)."""
        transducers = ", ".join(f"ch{c} -> {p}" for c, p in sorted(setup.transducers.items()))
        message = (setup.prompt or f"Setup {setup.name!r}: excitation at {setup.excitation}; "
                   f"place the transducers: {transducers}.")
        self._confirm.clear()
        self._emit(OperatorPrompt(self._t(), setup_index, setup.name, message,
                                  self.auto_continue))
        if self.auto_continue:
            self._log(f"prompt auto-continued (headless): {message}")
            return
        self.state = "waiting"
        t_wait = self._clock()
        aiming = self.aim_pulses > 0 and self._aim_configure(setup, first)
        next_aim = self._clock()
        while not self._confirm.is_set():
            self._check()
            # a pause at the prompt holds the trigger off too
            if aiming and not self._pause.is_set() and self._clock() >= next_aim:
                aiming = self._aim(setup_index, setup, first)
                next_aim = self._clock() + self.aim_interval_s
                continue  # a confirm during the acquisition is seen at once
            self._wake.wait(0.05)
            self._wake.clear()
        self._waited_s += self._clock() - t_wait
        self.state = "running"
        self._log(f"operator confirmed setup {setup.name!r}")

    def _aim_failed(self, exc: Exception) -> bool:
        self._log(f"{NO_LIVE_ECHOES} while placing the transducers: {type(exc).__name__}: "
                  f"{' '.join(str(exc).split())} (the steps configure the bench anew)",
                  "WARNING")
        return False

    @staticmethod
    def _instrument_errors() -> type[Exception]:
        """What an instrument raises (a timeout, a SCPI error, a limit): the live echoes
        stop with a warning. Anything else (a listener writing the session) is a fault."""
        from pelvislab.drivers.interfaces import DriverError

        return DriverError

    def _aim_configure(self, setup: Setup, first: PlannedStep, drive: bool = True) -> bool:
        """Configure short trigger bursts and records for the live echoes, and (``drive``)
        the drive's sine at the first step (its SYNC may trigger the bursts) with its
        output left off. In a pause the drive keeps the sine it had."""
        us = self.protocol.ultrasound
        try:
            with self._lock:
                self._check()
                if drive:
                    self.bench.drive.configure_sine(
                        first.frequency_hz, first.drive_vpp or self.protocol.sweep.drive_vpp)
                self.bench.trigger.configure_pulse_burst(
                    us.prf_hz, self.aim_pulses, us.trigger_width_s, us.trigger_high_v)
            self.bench.digitizer.configure_sequence(
                sorted(setup.transducers), us.sample_rate_hz, us.samples, self.aim_pulses,
                us.delay_s, us.full_scale_v, us.offset_v)
        except self._instrument_errors() as exc:
            return self._aim_failed(exc)
        return True

    def _aim(self, setup_index: int, setup: Setup, first: PlannedStep,
             sync_hz: float | None = None) -> bool:
        """One live echo per channel (trigger on for ``aim_pulses`` pulses, then off; the
        drive stays off), emitted as :class:`AimingEchoes`. False after a failure (said).
        ``sync_hz``: the frequency of the sine the drive holds (default ``first``'s)."""
        from pelvislab.acquisition.tracking import gate_preview

        us = self.protocol.ultrasound
        # a burst may wait for the drive's SYNC: one period of the sine it holds (in a
        # pause the previous step's: 1 s at 1 Hz, where the next step's 40 Hz gave 0.53 s
        # and every live echo timed out; review, session 39)
        sync_wait_s = 1.0 / (sync_hz or first.frequency_hz)
        failure: Exception | None = None
        try:
            with self._lock:
                self._check()
                self.bench.trigger.output_on()
                # an abort that could not wait for this lock (50 ms) put the outputs off
                # meanwhile: stop before acquiring (the finally puts the trigger off again)
                self._check()
            records = self.bench.digitizer.acquire(
                timeout_s=self.aim_pulses / us.prf_hz + sync_wait_s + 0.5)
        except self._instrument_errors() as exc:
            failure = exc
        finally:
            # also when switching it on failed half-way; an OFF that fails leaves the
            # trigger perhaps pulsing: a fault (the run stops in the safe state), never a
            # warning at a prompt that goes on waiting
            with self._lock:
                self.bench.trigger.output_off()
        if failure is not None:
            return self._aim_failed(failure)
        self._check()
        gates = self._gates_now()
        echoes = []
        for ch in sorted(setup.transducers):
            rec = records.get(ch)
            if rec is None:
                continue
            codes = np.asarray(rec.codes)
            gate: tuple[int, int] | None = None
            notes: tuple[str, ...] = ()
            rival = None
            set_gate = gates.get(ch)
            try:
                gate, found, rival = gate_preview(
                    codes, float(rec.sample_rate_hz),
                    self._tracking_options(None if set_gate is None else set_gate[0]))
                notes = tuple(found)
            except ValueError as exc:
                notes = (str(exc),)
            samples = codes.shape[1]
            echoes.append(AimedEcho(
                channel=ch, landmark=setup.transducers[ch],
                time_s=float(rec.delay_s) + np.arange(samples) / float(rec.sample_rate_hz),
                volts=codes[-1].astype(float) * float(rec.volts_per_count)
                - float(rec.volts_offset),
                gate=gate, gate_source=self._gate_source(set_gate), notes=notes,
                sample_rate_hz=float(rec.sample_rate_hz), delay_s=float(rec.delay_s),
                rival_sample=rival))
        self._emit(AimingEchoes(self._t(), setup_index, tuple(echoes)))
        return True

    def _place(self, setup: Setup) -> None:
        """On a simulated bench, let its simulated operator move shaker and transducers
        (a bench exposing ``place`` or ``world.place``); a real operator did it already."""
        place = getattr(self.bench, "place", None) or getattr(
            getattr(self.bench, "world", None), "place", None)
        if place is None or not self.bench.simulated:
            return
        excitation = self.protocol.excitations[setup.excitation]
        place(excitation=excitation,
              channels={ch: self.protocol.points[name] for ch, name in setup.transducers.items()},
              excitation_direction=excitation.direction,
              speed_of_sound_m_s=self.protocol.ultrasound.speed_of_sound_m_s)
        self._log(f"simulated operator placed the shaker at {excitation.name} and the "
                  f"transducers for setup {setup.name!r}")

    def _maybe_pause(self, setup_index: int, setup: Setup, step: PlannedStep,
                     drive_hz: float) -> tuple[bool, bool]:
        """Honour a pause request before ``step``: (paused, reconfigured). Paused: the
        outputs were off. Live echoes while paused when asked (:meth:`live_echoes_in_pause`;
        the drive holds its sine at ``drive_hz``, whose SYNC may trigger the bursts); then
        trigger and digitizer are configured for ``step`` again before it (reconfigured)."""
        if not self._pause.is_set():
            return False, False
        with self._lock:
            self._generators(False)
        reconfigure = False
        # a resume and a pause asked again before this thread saw the resume (it was in a
        # live echo's acquisition) are two pauses, each said: the GUI ends the first's
        # live echoes at Resume and offers them again at the second's Paused (review,
        # session 39: the window showed live echoes that Resume had stopped)
        while self._pause.is_set():
            reconfigure |= self._one_pause(setup_index, setup, step, drive_hz)
        if reconfigure:  # the live echoes configured trigger and digitizer for themselves
            self._configure(step, tuple(sorted(setup.transducers)))
        return True, reconfigure

    def _one_pause(self, setup_index: int, setup: Setup, step: PlannedStep,
                   drive_hz: float) -> bool:
        """One pause, from ``Paused`` to ``Resumed`` (outputs off throughout, the live
        echoes when asked); True if live echoes configured trigger and digitizer."""
        with self._pause_lock:
            resumes = self._resumes
        self.state = "paused"
        self._emit(Paused(self._t(), "paused by the operator"))
        self._log("paused; outputs off")
        t_wait = self._clock()
        live = "off"  # "on": configured and pulsing; "failed": said, until asked again
        started_under = -1  # the "on" request the live echoes last started under
        reconfigure = False
        next_aim = self._clock()
        while self._pause.is_set() and self._resumes == resumes:
            self._check()
            wanted = self._live_in_pause.is_set() and self.aim_pulses > 0
            if live == "failed" and self._live_requests != started_under:
                live = "off"  # asked again since they failed: try anew
            if not wanted and live != "off":
                if live == "on":
                    self._log("live echoes off; outputs off")
                live = "off"
            elif wanted and live == "off":
                started_under = self._live_requests
                live = "on" if self._aim_configure(setup, step, drive=False) else "failed"
                reconfigure = True
                if live == "on":
                    self._log("live echoes in the pause: the trigger pulses, the drive "
                              "stays off")
                    next_aim = self._clock()
            if live == "on" and self._clock() >= next_aim:
                ok = self._aim(setup_index, setup, step, sync_hz=drive_hz)
                live = "on" if ok else "failed"
                next_aim = self._clock() + self.aim_interval_s
                continue  # a resume during the acquisition is seen at once
            self._wake.wait(0.05)
            self._wake.clear()
        self._waited_s += self._clock() - t_wait
        self.state = "running"
        self._emit(Resumed(self._t()))
        self._log("resumed")
        return reconfigure

    def _configure(self, step: PlannedStep, channels: tuple[int, ...]) -> None:
        us = self.protocol.ultrasound
        with self._lock:
            self._check()
            self.bench.trigger.configure_pulse_burst(us.prf_hz, step.n_pulses,
                                                     us.trigger_width_s, us.trigger_high_v)
        self.bench.digitizer.configure_sequence(
            list(channels), us.sample_rate_hz, us.samples, step.n_pulses, us.delay_s,
            us.full_scale_v, us.offset_v)

    def _silent_on_simulated_bench(self) -> list[str]:
        """Points on no bone that a transducer looks at in a setup whose excitation is on a
        bone: the simulated bench has nothing there that moves (a still echo, quality ok, an
        FRF of noise; review, session 41). Where the excitation itself is
        on no bone it drives the ch. 8.3 phantom, whose faces do echo (the validation
        protocols: this warning said their data were void while every step was ok)."""
        points = self.protocol.points
        return sorted({name for setup in self.protocol.setups
                       if points[setup.excitation].bone
                       for name in setup.transducers.values() if not points[name].bone})

    # -------------------------------------------------------------- the run
    def run(self) -> RunFinished:
        """Execute the plan; returns the final event (also emitted). Never leaves an
        output on. KeyboardInterrupt ends the run as ``interrupted`` (not re-raised)."""
        plan = self.protocol.steps()
        todo = [s for s in plan if s.key not in self._skip]
        n_total = len(plan)
        n_done = n_total - len(todo)
        self._t0 = self._clock()
        self.state = "running"
        status, reason = "completed", ""
        try:
            self._emit(RunStarted(self._t(), self.protocol.name, n_total, n_done,
                                  sum(self.protocol.step_duration_s(s.frequency_hz)
                                      for s in todo), bool(self.bench.simulated)))
            if n_done:
                self._log(f"resuming: {n_done} of {n_total} steps already in the session")
            silent = self._silent_on_simulated_bench()
            if self.bench.simulated and silent:
                self._log(f"the simulated bench models the pelvis, and a phantom only where "
                          f"the shaker drives a point on no bone: points on no bone looked "
                          f"at while the shaker is on the pelvis ({', '.join(silent)}) do "
                          f"not move there (a still echo: their FRF holds noise only)",
                          "WARNING")
            n_done = self._run_plan(todo, n_done, n_total)
        except _Stop as exc:
            status, reason = self._abort_status, str(exc) or "aborted"
        except KeyboardInterrupt:
            self.abort("interrupted (Ctrl-C / SIGINT)", "interrupted")
            status, reason = self._abort_status, self._abort_reason
        except Exception as exc:
            fault_t = self._t()
            self._safe_state()
            if self._abort.is_set():  # an abort made an instrument call fail: not a fault
                status, reason = self._abort_status, self._abort_reason
            else:
                status = "failed"
                reason = f"fault: {type(exc).__name__}: {' '.join(str(exc).split())}"
                try:
                    self._emit(Fault(self._t(), reason, fault_t))
                except Exception as listener_exc:
                    log.error("listener failed on Fault: %s", listener_exc)
        finally:
            self._safe_state()
        self.state = "finished"
        if status != "completed" or self._unsafe:
            # a fault or an output not confirmed off is an error; a STOP, a Ctrl-C or a
            # signal with the outputs off is what was asked for, said as a warning (the
            # operator's STOP read "ERROR run aborted": GUI review, session 43)
            level = "ERROR" if status == "failed" or self._unsafe else "WARNING"
            try:
                self._log(f"run {status}: {reason}; {self._outputs_phrase()}", level)
            except Exception as exc:
                log.error("listener failed on the final log line: %s", exc)
        try:
            self._flush_notes()
        except Exception as exc:
            log.error("listener failed on a note: %s", exc)
        done = n_total - len(todo) + self._n_new
        final = RunFinished(self._t(), status, reason, done, n_total, self.unsafe)
        try:
            self._emit(final)
        except Exception as exc:
            log.error("listener failed on RunFinished: %s", exc)
        return final

    _n_new = 0
    _waited_s = 0.0

    def _run_plan(self, todo: list[PlannedStep], n_done: int, n_total: int) -> int:
        proto = self.protocol
        bench = self.bench
        us = proto.ultrasound
        channels = proto.channels
        self._n_new = 0
        cfg = bench.config
        # every step's force calibration, before a prompt or an output: a runner not made
        # through parse_protocol's bench limits (its public API) failed at the first step
        # outside the table, after the operator had placed the transducers
        force_per_volt_by_hz = {
            s.frequency_hz: calibrated_newton_per_volt(
                s.frequency_hz, cfg.drive_newton_per_volt,
                getattr(cfg, "drive_calibration_frequency_hz", ()),
                getattr(cfg, "drive_calibration_newton_per_volt", ()))
            for s in todo}
        remaining_est = [proto.step_duration_s(s.frequency_hz) for s in todo]
        est_done = 0.0
        with self._lock:
            self._check()
            bench.drive.output_off()
            bench.trigger.output_off()
        for ch in channels:
            if ch - 1 < len(bench.pulsers):
                bench.pulsers[ch - 1].configure(us.gain_db, us.pulse_energy, us.damping_ohm,
                                                us.high_pass_hz, us.low_pass_hz)
        n_setups = len(proto.setups)
        configured: tuple[int, tuple[int, ...]] = (-1, ())
        t_run = self._clock()
        self._waited_s = 0.0  # at operator prompts and in pauses: not bench time
        pace_from: tuple[float, float] | None = None  # (measuring s, planned s) at step 1
        for si, setup in enumerate(proto.setups):
            steps = [s for s in todo if s.setup_index == si]
            if not steps:
                continue
            self._check()
            with self._gates_lock:  # the transducers are placed anew
                self._gates = dict(setup.gates)  # a fixed rig's, from the protocol
                self._protocol_gated = set(setup.gates)
                self._current_setup = setup
            self._emit(SetupStarted(self._t(), si, setup.name, setup.excitation,
                                    dict(setup.transducers), n_setups))
            for ch, gate in sorted(setup.gates.items()):
                self._log(f"ch{ch}: gate from the protocol, samples {gate[0]}-{gate[1]}")
            cut_said: set[tuple[Any, ...]] = set()  # gates said to cut the echo
            first = steps[0]
            aims = not self.auto_continue and self.aim_pulses > 0
            if aims:  # the simulated operator places first, so that the live echoes show it
                self._place(setup)
            self._wait_prompt(si, setup, first)
            if aims:  # the live echoes configured trigger and digitizer for themselves
                configured = (-1, ())
            else:
                self._place(setup)
            level = first.drive_vpp or proto.sweep.drive_vpp
            with self._lock:
                self._check()
                bench.drive.configure_sine(first.frequency_hz, level)
            setup_channels = tuple(sorted(setup.transducers))
            # the trigger generator configured before its output goes on: in its *RST state
            # (a 1 kHz continuous sine) it would fire the pulsers and the digitizer (helper
            # review, session 34)
            if (first.n_pulses, setup_channels) != configured:
                self._configure(first, setup_channels)
                configured = (first.n_pulses, setup_channels)
            # a pause asked at the prompt holds before the outputs go on, not after one
            # step's ON (GUI review, session 35: ON and OFF again on the subject)
            drive_hz = first.frequency_hz  # the sine the drive holds (its SYNC)
            if self._maybe_pause(si, setup, first, drive_hz)[1]:
                configured = (first.n_pulses, setup_channels)
            self._generators(True)
            for step in steps:
                self._check()
                paused, reconfigured = self._maybe_pause(si, setup, step, drive_hz)
                if reconfigured:
                    configured = (step.n_pulses, setup_channels)
                if paused:
                    self._generators(True)
                self._emit(StepStarted(self._t(), step, n_done, n_total))
                t_step = self._clock()
                started_at = self._session_time()
                planned = step.drive_vpp or proto.sweep.drive_vpp
                with self._lock:
                    self._check()
                    bench.drive.set_frequency(step.frequency_hz)
                    drive_hz = step.frequency_hz
                    if planned != level:  # drive profile: a new level for this step
                        bench.drive.set_amplitude(planned)
                        level = planned
                if (step.n_pulses, setup_channels) != configured:
                    self._configure(step, setup_channels)
                    configured = (step.n_pulses, setup_channels)
                force_per_volt = force_per_volt_by_hz[step.frequency_hz]
                data = self._acquire(step, setup, force_per_volt, started_at, level)
                if proto.sweep.drive_mode == "auto":
                    data, level = self._auto_range(step, setup, force_per_volt, data, level)
                self._emit(StepFinished(self._t(), step, data, self._clock() - t_step))
                for c in data.channels:
                    q = c.quality
                    self._emit(Quality(self._t(), step, c.name, bool(q.get("ok", False)),
                                       float(q.get("correlation_median", np.nan)),
                                       float(q.get("lost_fraction", np.nan)),
                                       float(q.get("snr_db_median", np.nan)),
                                       str(q.get("message", ""))))
                    cut = _cut_gate_note(q)
                    said = (c.name, q.get("gate_start"), q.get("gate_stop"))
                    if cut and said not in cut_said:
                        # an `ok` step's note is only stored: a gate through the echo (5x
                        # the noise) is said once per setup, channel and gate (CLI, GUI log)
                        cut_said.add(said)
                        self._log(f"{c.name} (setup {setup.name!r}, from "
                                  f"{step.frequency_hz:g} Hz): {cut}", "WARNING")
                n_done += 1
                self._n_new += 1
                est_done += remaining_est.pop(0)
                elapsed = self._clock() - t_run
                left = sum(remaining_est)
                # the pace of the bench alone: a prompt answered after 6 s made the ETA
                # jump from 15 to 32 s; the prompts still to come are not counted either.
                # Measured from the end of the first step, whose one-off start (opening the
                # bench, configuring the digitizer) read as pace gave a resumed run's first
                # ETA as 103 s for 5 s of work; until then the plan's own estimate
                measuring = max(elapsed - self._waited_s, 0.0)
                if pace_from is None:
                    pace_from = (measuring, est_done)
                    eta = left
                else:
                    spent, planned = measuring - pace_from[0], est_done - pace_from[1]
                    eta = left * (spent / planned) if planned > 0 else left
                self._emit(Progress(self._t(), n_done, n_total, elapsed, eta))
            self._generators(False)
            self._emit(SetupFinished(self._t(), si, setup.name))
        return n_done

    def _acquire(self, step: PlannedStep, setup: Setup, force_per_volt: complex,
                 started_at: float, level_vpp: float) -> StepData:
        """Settle, acquire one record at drive level ``level_vpp`` (V pk-pk), process it."""
        self._settle(step.settle_s)
        record_s = step.n_pulses / self.protocol.ultrasound.prf_hz
        records = self.bench.digitizer.acquire(timeout_s=2.0 * record_s + 5.0)
        self._check()  # an abort during the acquisition: do not keep a cut record
        return self._process(step, setup, records, force_per_volt, started_at, level_vpp)

    def _auto_range(self, step: PlannedStep, setup: Setup, force_per_volt: complex,
                    data: StepData, level_vpp: float) -> tuple[StepData, float]:
        """Auto drive mode: repeat ``step`` once at a lower level when its motion was too
        large (see :func:`auto_range_level`); returns the better record and the level now
        set on the generator."""
        sweep = self.protocol.sweep
        data.extra["drive_planned_vpp"] = float(level_vpp)
        data.extra["drive_attempts"] = 1
        lower, why = auto_range_level(
            [c.phasor_m for c in data.channels],
            [c.displacement_m for c in data.channels],
            [float(c.quality.get("lost_fraction", 1.0)) for c in data.channels],
            level_vpp, float(sweep.max_displacement_m or math.inf), sweep.min_drive_vpp)
        if lower is None:
            return data, level_vpp
        with self._lock:
            self._check()
            self.bench.drive.set_amplitude(lower)
        retry = self._acquire(step, setup, force_per_volt, self._session_time(), lower)
        keep = better_record(data, retry, float(sweep.max_displacement_m or math.inf))
        for d in (data, retry):
            d.extra["drive_planned_vpp"] = float(level_vpp)
            d.extra["drive_attempts"] = 2
        other = data if keep is retry else retry
        keep.extra["drive_rejected_vpp"] = float(other.drive_vpp)
        self._log(f"step {step.index} ({step.setup}, {step.frequency_hz:g} Hz): {why} at "
                  f"{level_vpp:.3g} Vpp; repeated at {lower:.3g} Vpp, kept the "
                  f"{keep.drive_vpp:.3g} Vpp record (lost "
                  f"{_max_lost(data):.1%} -> {_max_lost(retry):.1%})")
        return keep, lower

    def _session_time(self) -> float:
        return self.session_offset_s + self._t()

    session_offset_s = 0.0
    """Seconds between the session's creation and this run's start (set by the caller)."""

    def _process(self, step: PlannedStep, setup: Setup, records: Mapping[int, Any],
                 force_per_volt: complex, started_at: float,
                 level_vpp: float | None = None) -> StepData:
        proto = self.protocol
        us = proto.ultrasound
        cfg = self.bench.config
        gates = self._gates_now()  # one snapshot per step (the GUI may set one meanwhile)
        chans: list[ChannelData] = []
        for ch in sorted(setup.transducers):
            if ch not in records:
                raise RuntimeError(f"digitizer returned no record for channel {ch}")
            rec = records[ch]
            c = speed_of_sound_used(cfg, ch, us.speed_of_sound_m_s,
                                    test_object=not proto.points[setup.excitation].bone)
            cd = ChannelData(
                name=f"ch{ch}", codes=np.asarray(rec.codes),
                trigger_offset_s=np.asarray(rec.trigger_offset_s, dtype=float),
                sample_rate_hz=float(rec.sample_rate_hz), prf_hz=us.prf_hz,
                delay_s=float(rec.delay_s), volts_per_count=float(rec.volts_per_count),
                volts_offset=float(rec.volts_offset), speed_of_sound_m_s=c,
                output=proto.points[setup.transducers[ch]])
            gate = gates.get(ch)
            process_channel(cd, step.frequency_hz, self.tracking_options if gate is None
                            else self._tracking_options(gate[0]))
            cd.quality["gate_source"] = self._gate_source(gate)
            chans.append(cd)
        level = float(level_vpp if level_vpp is not None else
                      (step.drive_vpp or proto.sweep.drive_vpp))
        # the level actually set on the generator for this record: the FRF's denominator
        force = force_phasor(step.frequency_hz, level, force_per_volt)
        ok = all(bool(c.quality.get("ok")) for c in chans)
        return StepData(setup=setup.name, frequency_hz=step.frequency_hz,
                        input=proto.excitations[setup.excitation], started_at_s=started_at,
                        channels=chans, force_phasor_n=force, drive_vpp=level,
                        status=STATUS_COMPLETE,
                        extra={"plan_index": step.index, "setup_index": step.setup_index,
                               "repeat": step.repeat, "n_pulses": step.n_pulses,
                               "quality_ok": ok})


# --------------------------------------------------------------------------- recorder
def command_logs(bench: Any, copy: bool = True) -> dict[str, Sequence[tuple[float, str]]]:
    """Every instrument's command log (``command_log`` attribute), by role; with
    ``copy=False`` the instruments' own growing lists (the session writer appends only
    their new tail with each step: copying every log at every step grew with the square
    of the run's length)."""
    roles = [("trigger", bench.trigger), ("drive", bench.drive), ("digitizer", bench.digitizer)]
    roles += [(f"pulser{i + 1}", p) for i, p in enumerate(bench.pulsers)]
    out: dict[str, Sequence[tuple[float, str]]] = {}
    for role, inst in roles:
        entries = getattr(inst, "command_log", None)
        if entries is not None:
            out[role] = ([(float(t), str(s)) for t, s in list(entries)] if copy
                         else entries)
    return out


@dataclass
class SessionRecorder:
    """The session writer as a listener: steps, log lines and the run's end go to the file.

    Subscribe it as *critical* (a failure to write is a fault that stops the run).
    """

    writer: SessionWriter
    bench: Any = None
    steps_written: int = 0
    statuses: list[str] = field(default_factory=list)
    samples: int = 500  # samples per echo (the protocol's), for the space check
    channels: tuple[int, ...] = ()

    def __call__(self, event: Event) -> None:
        if isinstance(event, StepStarted):
            # before the step is acquired (the drive may already be on for the setup; a
            # fault here switches it off): raw echoes (1 byte per sample per channel) and
            # the per-pulse arrays (trigger offsets, displacement), uncompressed
            channels = len(self.channels) or 2
            self.writer.check_space(event.step.n_pulses * channels * (self.samples + 16))
        elif isinstance(event, StepFinished):
            ok = all(bool(c.quality.get("ok", False)) for c in event.data.channels)
            self.writer.log(f"step {event.step.index} setup {event.step.setup!r} "
                            f"{event.step.frequency_hz:g} Hz: "
                            f"{'ok' if ok else 'quality warning'} "
                            f"({event.duration_s:.3f} s)", "DEBUG")
            if self.bench is not None:  # the audit trail so far, flushed with the step
                self.writer.append_command_logs(command_logs(self.bench, copy=False))
            self.writer.append_step(event.data)  # flushes
            self.steps_written += 1
        elif isinstance(event, LogMessage):
            self.writer.log(event.text, event.level, flush=event.level in ("WARNING", "ERROR"))
        elif isinstance(event, Quality) and not event.ok:
            self.writer.log(f"quality: step {event.step.index} {event.channel}: "
                            f"{event.message}", "WARNING")
        elif isinstance(event, OperatorPrompt):
            self.writer.log(f"prompt: {event.message}")
        elif isinstance(event, Fault):
            self.writer.log(event.reason, "ERROR", flush=True)
        elif isinstance(event, RunFinished):
            logs = command_logs(self.bench) if self.bench is not None else {}
            self.writer.finish_run(event.status, event.reason, logs, unsafe=event.unsafe)


# --------------------------------------------------------------------------- wiring
@dataclass
class PreparedSession:
    """A runner wired to an open bench and session writer (CLI ``run`` and the GUI).

    Subscribe your own listeners to ``runner``, then call :meth:`run` (any thread) and
    finally :meth:`close` (idempotent: safe state, close the file, release the bench).
    """

    runner: Runner
    writer: SessionWriter
    bench: Any
    protocol: Protocol
    path: Path
    resumed: bool = False
    problems: list[str] = field(default_factory=list)
    """Damaged or incomplete step groups found when resuming (kept; measured again)."""
    previous_run: tuple[str, str] | None = None
    """When resuming: how the session's last run ended (status, reason); ``running``
    means its process died without closing (killed, crashed, power lost)."""
    final: RunFinished | None = None
    _closed: bool = False
    _unsafe_at_close: list[str] | None = None

    @property
    def unsafe(self) -> tuple[str, ...]:
        """What the last completed safe state could not confirm off: :meth:`close`'s, or
        the run's (empty: every output confirmed off)."""
        if self._unsafe_at_close is not None:
            return tuple(self._unsafe_at_close)
        return self.runner.unsafe
    _running: threading.Event = field(default_factory=threading.Event)
    _done: threading.Event = field(default_factory=threading.Event)

    def run(self) -> RunFinished:
        """Execute the plan (see :meth:`Runner.run`); call it once, from any one thread."""
        self._running.set()
        try:
            self.final = self.runner.run()
        finally:
            self._done.set()
        return self.final

    def close(self, timeout_s: float = 30.0) -> None:
        """Outputs off, session flushed and closed, instruments released. Safe twice.

        Called while :meth:`run` is still going in another thread, it aborts the run and
        waits (up to ``timeout_s``) for it to end before closing the file.
        """
        if self._closed:
            return
        if self._running.is_set() and not self._done.is_set():
            self.runner.abort("session closed while running")
            self._done.wait(timeout_s)
        self._closed = True
        try:
            self._unsafe_at_close = list(self.bench.safe_state() or [])
        finally:
            try:
                if self.final is None and self.writer.run_group is not None:
                    # run() never ran or died without an end event: record that honestly
                    self.writer.finish_run("aborted", "session closed before the run ended",
                                           command_logs(self.bench),
                                           unsafe=self._unsafe_at_close or ())
                elif self._unsafe_at_close is not None and self.writer.run_group is not None:
                    # the close's safe state is the last one: the file says what it found
                    # (as the exit code does), not what the run's end found before it
                    attrs = self.writer.run_group.attrs
                    attrs["outputs_confirmed_off"] = not self._unsafe_at_close
                    if self._unsafe_at_close:
                        attrs["safe_state_errors"] = "\n".join(self._unsafe_at_close)
            except Exception as exc:
                log.error("recording the end of the run: %s", exc)
            finally:
                try:
                    self.writer.close()
                finally:
                    self.bench.close()

    def __enter__(self) -> PreparedSession:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def prepare_session(protocol_path: Path | str, out_path: Path | str,
                    bench_path: Path | str | None = None, resume: bool = False,
                    auto_continue: bool = True, tracking_options: Any = None,
                    software_version: str = "", bench: Any = None,
                    subject_id: str | None = None) -> PreparedSession:
    """Validate the protocol against the bench, open the bench and the session file.

    Checks everything that can be checked before touching an instrument or a file: the
    bench file, the protocol (against the bench limits), and that ``out_path`` does not
    exist (new session) or is a readable session of the same protocol (``resume``).
    Nothing is ever written over an existing file. ``bench``: an already open bench to use
    instead of opening ``bench_path`` (its config then supplies the limits); it is closed
    with the session. ``subject_id`` overrides the protocol's ``subject.id`` in the session's
    root attribute ``subject_id`` (the /protocol text stays as the file was).
    """
    from pelvislab.acquisition.protocol import (
        BenchLimits,
        ProtocolError,
        instrument_problems,
        load_protocol,
    )
    from pelvislab.acquisition.session import bench_description, check_subject_id
    from pelvislab.drivers.bench import BenchConfig, open_bench

    out = Path(out_path)
    if subject_id is not None:
        check_subject_id(subject_id)
    bench_file = Path(bench_path) if bench_path is not None else None
    if bench is not None:
        config = bench.config
    elif bench_file is not None:
        config = BenchConfig.load(bench_file)
    else:
        config = BenchConfig.default()
    protocol = load_protocol(protocol_path, BenchLimits.from_config(config))
    # before any file or instrument is opened (it left a new session file behind: review)
    check_protocol_gates(protocol, tracking_options)
    skip: list[tuple[str, float, int]] = []
    every: list[StepData] = []
    problems: list[str] = []
    previous_run: tuple[str, str] | None = None
    if not str(out_path).strip():  # Path("") is ".", which read ". is a folder" (review)
        raise ValueError("the session file's name is empty: give one, e.g. session.h5")
    if out.is_dir():  # "exists; use --resume" sent the user the wrong way (review, session 39)
        raise IsADirectoryError(f"{out} is a folder: give the session file's name, e.g. "
                                f"{out / 'session.h5'}")
    cut_note = ""
    if resume:
        if not out.is_file():
            raise FileNotFoundError(f"--resume: no session file {out} to continue")
        size_found = out.stat().st_size
        cut_note = extend_cut_session(out)
        try:
            reader = SessionReader(out)
        except Exception:
            if cut_note:  # it does not open even so: leave it as it was found
                os.truncate(out, size_found)
            raise
        with reader:
            if cut_note and reader.protocol_text != protocol.text:
                os.truncate(out, size_found)  # another session, or another protocol
            if reader.protocol_text != protocol.text:
                where = first_difference(reader.protocol_text, protocol.text)
                raise ValueError(f"{out}: its /protocol differs from {protocol_path} "
                                 f"({where}); resume with the protocol the session started "
                                 "with (the text itself: a comment counts)")
            every = list(reader.steps(include_incomplete=True, with_echoes=False))
            skip = [s.key for s in every if s.status == STATUS_COMPLETE]
            done = {(k[0], round(float(k[1]), 9), int(k[2])) for k in skip}
            # a group cut short whose step was measured again since is history, not a step
            # to measure: no "measured again" for it (helper review, session 39)
            problems = reader.damaged + [
                f"{s.index:06d}: status {s.status!r}" for s in every
                if s.status != STATUS_COMPLETE
                and (s.key[0], round(float(s.key[1]), 9), int(s.key[2])) not in done]
            previous_run = reader.status
            source = reader.attrs.get("reprocessed_from")
            if source is not None:
                # its steps were re-tracked with other options: new steps tracked as
                # recorded would mix the two in one FRF (replay review, session 36)
                source = source.decode() if isinstance(source, bytes) else str(source)
                raise ValueError(f"--resume: {out} was reprocessed from {source}; resume "
                                 "that session and reprocess it again")
            recorded = reader.attrs.get("subject_id", "")
            recorded = recorded.decode() if isinstance(recorded, bytes) else str(recorded)
        # one subject per file: continuing it with another ID would mix two subjects'
        # steps in one FRF (found while adding the GUI's resume, session 35)
        if subject_id is not None and subject_id != recorded:
            raise ValueError(f"--resume: {out} is the session of subject {recorded!r}, not "
                             f"{subject_id!r}; resume without --subject-id, or start a new "
                             "session for that subject")
        planned = {(s.setup, round(float(s.frequency_hz), 9), int(s.repeat))
                   for s in protocol.steps()}
        kept = {(k[0], round(float(k[1]), 9), int(k[2])) for k in skip}
        if planned <= kept:
            # it opened the bench and wrote a run record into a finished file (first-day
            # review, session 39); a cut step measured again since (an incomplete group
            # left in the file) does not change that. Only /frf lines lost to a kill after
            # the last step's flush are written (repair_frf), nothing else
            repaired = _repair_frf_only(out, protocol.text, cut_note)
            last = previous_run[0] if previous_run else "?"
            raise NothingToResume(
                f"{out} already holds every step of {protocol.name!r} (last run {last}): "
                "nothing to measure; " + "; ".join(filter(None, (
                    cut_note, f"/frf was rebuilt from its steps ({repaired})"
                    if repaired else ""))) + ("" if cut_note or repaired else
                                              "the file is left as it is"))
    elif out.exists():
        raise FileExistsError(f"{out} exists; not overwriting it (use --resume to continue "
                              "that session, or choose another --out)")
    if bench is None:
        bench = open_bench(bench_file)
    try:
        # the open instruments' own checks of every configuration the run will make,
        # before the session file exists: a setting they refuse is bad input (exit 1,
        # nothing written), not a fault of a run that left a 0-step file blocking the
        # name (audit). The protocol check did the same with the bench file's classes;
        # this asks the instruments actually open (an instrument may know more)
        models = getattr(bench, "instrument_models", None)
        refused = instrument_problems(protocol, models(), str(bench.config.name)) \
            if models is not None else []
        if refused:
            raise ProtocolError(protocol.source, refused)
        description = bench_description(bench)
        if resume:
            with SessionReader(out) as reader:
                recorded = reader.bench()
            differences = bench_differences(recorded, description)
            differences += speed_of_sound_differences(every, bench.config, protocol)
            if differences:
                raise ValueError(
                    f"--resume: {out} was measured on another bench ({'; '.join(differences)}"
                    "): its steps and the new ones would not be comparable; resume with the "
                    "session's bench (--bench), or start a new session")
            writer = SessionWriter.resume(out, protocol.text)
        else:
            writer = SessionWriter.create(out, protocol, description, software_version,
                                          subject_id)
        try:
            runner = Runner(protocol, bench, auto_continue=auto_continue,
                            tracking_options=tracking_options, skip=skip)
            runner.session_offset_s = writer.elapsed_s()
            runner.subscribe(SessionRecorder(writer, bench,
                                             samples=protocol.ultrasound.samples,
                                             channels=tuple(protocol.channels)),
                             critical=True)
            writer.start_run(description, software_version)
            writer.log(f"run started: protocol {protocol.name!r} ({protocol.source}), "
                       f"{'resumed, ' + str(len(skip)) + ' steps kept' if resume else 'new'}"
                       f" session, bench {description['name']!r}", flush=True)
            if cut_note:
                writer.log(f"resume: {cut_note}", "WARNING")
            for problem in problems:
                writer.log(f"resume: step {problem}; measured again", "WARNING")
            replaced = speed_of_sound_note(bench.config, protocol)
            if replaced:
                writer.log(replaced)
            if resume:
                writer.repair_frf()
            if subject_id is not None:
                writer.log(f"subject id set to {subject_id!r} (protocol says "
                           f"{protocol.subject.id!r})")
                assert writer.run_group is not None
                writer.run_group.attrs["subject_id"] = subject_id
        except BaseException as exc:
            if writer.run_group is not None:
                # the run's record says how it ended; left "running", every failed resume
                # added a run that "may have left an output on" (review, session 50)
                try:
                    # the outputs as the safe state finds them now (the bench is closed
                    # next), not assumed off (review, session 50)
                    unsafe = list(bench.safe_state() or [])
                    writer.finish_run("interrupted" if isinstance(exc, KeyboardInterrupt)
                                      else "failed",
                                      f"before the first step: {exc}" if str(exc) else
                                      "before the first step", unsafe=unsafe)
                except Exception as record_exc:  # the file may be what failed
                    log.error("could not record the run's end in %s: %s", out, record_exc)
            writer.close()
            raise
    except BaseException:
        bench.close()
        raise
    return PreparedSession(runner, writer, bench, protocol, out, resume, problems,
                           previous_run=previous_run)


def speed_of_sound_used(config: Any, channel: int, protocol_m_s: float,
                        test_object: bool = False) -> float:
    """The speed of sound (m/s) tracking assumes on digitizer ``channel``: the bench
    file's per-channel value, else its ``[calibration] speed_of_sound_m_s``, else the
    protocol's ``ultrasound.speed_of_sound_m_s`` (``protocol_m_s``); on a ``test_object``
    (a setup whose excitation is on no bone, the validation protocols' phantoms in water)
    the protocol's. The bench file describes the setup measured that day (before, its
    global value was recorded in ``/bench`` and given to the simulated echoes but not used
    here: an audit); its values are the tissue's (``BenchConfig.speed_of_sound_for``)."""
    if hasattr(config, "speed_of_sound_for"):
        return float(config.speed_of_sound_for(channel, protocol_m_s, test_object))
    return float(protocol_m_s)


def _source(config: Any, channel: int, test_object: bool) -> str:
    source = getattr(config, "speed_of_sound_source", None)
    return source(channel, test_object) if source is not None else ""


def speed_of_sound_differences(steps: Any, config: Any, protocol: Any) -> list[str]:
    """Channels whose complete ``steps`` (of a session being resumed) were tracked with
    another speed of sound than the one the bench ``config`` and ``protocol`` give now for
    the same setup: the new steps would not be comparable with them in one FRF. Compared on
    the steps' echoes datasets (what was used), not on ``/bench``: a session written before
    the bench file's ``[calibration] speed_of_sound_m_s`` was applied recorded it there
    without using it."""
    us = protocol.ultrasound.speed_of_sound_m_s
    found: dict[int, tuple[set[float], float, str]] = {}
    on_test_object: set[int] = set()
    for step in steps:
        if step.status != STATUS_COMPLETE:
            continue
        excitation = getattr(step, "input", None)
        test_object = excitation is not None and not excitation.bone
        for channel in step.channels:
            name = str(channel.name)
            if not (name.startswith("ch") and name[2:].isdigit()):
                continue
            ch = int(name[2:])
            then = float(channel.speed_of_sound_m_s)
            now = speed_of_sound_used(config, ch, us, test_object)
            if not math.isclose(then, now, rel_tol=1e-9):
                seen = found.setdefault(ch, (set(), now, _source(config, ch, test_object)))
                seen[0].add(then)
                if test_object:
                    on_test_object.add(ch)
    out = []
    for ch in sorted(found):
        then, now, source = found[ch]
        why = f"the bench file's {source}" if source else "the protocol's"
        text = (f"speed of sound on ch{ch}: {', '.join(f'{c:g}' for c in sorted(then))} "
                f"m/s in the session's steps, {now:g} m/s now ({why})")
        if len(then) == 1 and ch not in on_test_object:
            # the bench file may be the session's own: sessions recorded before session 41
            # were tracked without its [calibration] speed_of_sound_m_s (review)
            text += (f"; to track the new steps as these, give the bench file "
                     f"[calibration.channel_speed_of_sound_m_s] {ch} = {min(then):g}")
        out.append(text)
    return out


def speed_of_sound_note(config: Any, protocol: Any) -> str:
    """One line naming the channels on which the bench file's speed of sound replaces a
    different one in ``protocol`` (``""`` when none does; setups on a test object keep the
    protocol's, :func:`speed_of_sound_used`)."""
    us = float(protocol.ultrasound.speed_of_sound_m_s)
    parts: dict[int, str] = {}
    for setup in protocol.setups:
        test_object = not protocol.points[setup.excitation].bone
        for ch in sorted(setup.transducers):
            c = speed_of_sound_used(config, ch, us, test_object)
            if ch not in parts and not math.isclose(c, us, rel_tol=1e-9):
                parts[ch] = f"ch{ch} {c:g} m/s ({_source(config, ch, test_object)})"
    if not parts:
        return ""
    return (f"speed of sound from the bench file: {', '.join(parts[c] for c in sorted(parts))}"
            f"; the protocol's {us:g} m/s is not used there")


BENCH_KEYS_THAT_SHAPE_THE_DATA = ("simulated", "drive_newton_per_volt",
                                  "drive_calibration_frequency_hz",
                                  "drive_calibration_newton_per_volt")
"""The speed of sound shapes the data too: :func:`speed_of_sound_differences` compares it
on the session's steps."""


def bench_differences(recorded: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """What differs between a session's ``/bench`` and the bench now open, among what
    shapes the measured FRF: simulated or real and the drive chain's force calibration
    (N/V, one constant, NaN for a per-frequency table, or the table). Instrument
    identities may change (a repaired instrument) without changing the data. The speed of
    sound is compared on the steps themselves (:func:`speed_of_sound_differences`)."""
    def norm(value: Any) -> Any:
        if isinstance(value, np.generic):
            value = value.item()
        return complex(value) if isinstance(value, complex) else value

    def value(bench: dict[str, Any], key: str) -> Any:
        return norm(bench.get(key))

    def differs(key: str) -> bool:
        a, b = value(recorded, key), value(current, key)
        if a is None:  # not recorded (an older file): nothing to compare with
            return False
        if b is None:
            return True
        if isinstance(a, (float, complex, np.ndarray)):
            a_arr, b_arr = np.atleast_1d(a), np.atleast_1d(np.asarray(b))
            return not (a_arr.shape == b_arr.shape and bool(np.all(np.isclose(
                a_arr, b_arr, rtol=1e-9, atol=0.0, equal_nan=True))))
        return a != b

    # the drive calibration in words, one line (its keys' raw values read "(8+0j) in the
    # session, (nan+nanj) now", or printed two whole tables)
    out = []
    calibration = [k for k in _DRIVE_CALIBRATION_KEYS if differs(k)]
    if calibration:
        then, now = _drive_calibration_words(recorded), _drive_calibration_words(current)
        if then.startswith("a per-frequency") and now.startswith("a per-frequency"):
            now = f"another table ({_first_table_difference(recorded, current)})"
        out.append(f"drive calibration ({', '.join(calibration)}): {then} in the session, "
                   f"{now} now")
    keys = [k for k in BENCH_KEYS_THAT_SHAPE_THE_DATA if k not in _DRIVE_CALIBRATION_KEYS]
    out += [f"{key}: {value(recorded, key)!r} in the session, {value(current, key)!r} now"
            for key in keys if differs(key)]
    return out


_DRIVE_CALIBRATION_KEYS = ("drive_newton_per_volt", "drive_calibration_frequency_hz",
                           "drive_calibration_newton_per_volt")
"""The ``/bench`` keys of the drive calibration (compared as one, said in words)."""


def _drive_calibration_words(bench: dict[str, Any]) -> str:
    """A ``/bench`` description's drive calibration in a few words."""
    table = np.atleast_1d(np.asarray(bench.get("drive_calibration_frequency_hz", []),
                                     dtype=float))
    if table.size:
        return f"a per-frequency table ({table.size} rows, {table[0]:g}-{table[-1]:g} Hz)"
    constant = bench.get("drive_newton_per_volt")
    if constant is None:
        return "none recorded"
    # digits enough to show a difference the comparison (rtol 1e-9) sees
    return f"one constant {complex(constant):.10g} N/V"


def _first_table_difference(a: dict[str, Any], b: dict[str, Any]) -> str:
    """Where two per-frequency drive calibrations first differ, in words."""
    fa = np.atleast_1d(np.asarray(a["drive_calibration_frequency_hz"], dtype=float))
    fb = np.atleast_1d(np.asarray(b["drive_calibration_frequency_hz"], dtype=float))
    ga = np.atleast_1d(np.asarray(a.get("drive_calibration_newton_per_volt", []), complex))
    gb = np.atleast_1d(np.asarray(b.get("drive_calibration_newton_per_volt", []), complex))
    if fa.shape != fb.shape:
        return f"{fb.size} rows, {fb[0]:g}-{fb[-1]:g} Hz"
    moved = ~np.isclose(fa, fb, rtol=1e-9, atol=0.0)
    if moved.any():
        row = int(np.argmax(moved))
        return f"row {row + 1} at {fb[row]:.10g} Hz, was {fa[row]:.10g} Hz"
    if ga.shape != gb.shape:
        return f"{gb.size} values for {fb.size} rows"
    changed = ~np.isclose(ga, gb, rtol=1e-9, atol=0.0, equal_nan=True)
    if not changed.any():
        return "the same rows"
    row = int(np.argmax(changed))
    return f"first different at {fa[row]:g} Hz: {ga[row]:.10g} -> {gb[row]:.10g} N/V"


# --------------------------------------------------------------------------- reprocessing
def _repair_frf_only(path: Path, protocol_text: str, cut_note: str = "") -> str:
    """Rebuild ``path``'s /frf from its complete steps when it differs from them (a kill
    between a step's flush and its /frf lines); what differed if it did ("" otherwise).
    Nothing else is written but one log line. Values missing from /frf are a kill's mark;
    values that differ may be one too (a repeated step's line, combined with the earlier
    one) or a damaged step or /frf, so the count of each is said (a corrupted phasor's
    step rewrote a correct line as "lines lost to a kill"; review, session 50)."""
    with SessionReader(path) as reader:
        layout = reader.frf_layout()
        if layout is None:
            return ""
        stored = reader.frf()
        rebuilt = frf_from_steps(list(reader.steps(with_echoes=False)), *layout)
    both = np.isfinite(stored.H) & np.isfinite(rebuilt.H)
    missing = int(np.sum(~np.isfinite(stored.H) & np.isfinite(rebuilt.H)))
    extra = int(np.sum(np.isfinite(stored.H) & ~np.isfinite(rebuilt.H)))
    changed = int(np.sum(~np.isclose(stored.H[both], rebuilt.H[both], rtol=1e-9, atol=0.0)))
    if not (missing or extra or changed):
        if cut_note:  # the extension is in the file's own log too
            with SessionWriter.resume(path, protocol_text) as writer:
                writer.log(f"resume: every step already measured; {cut_note}", "WARNING")
        return ""
    parts = ([f"{missing} value(s) missing: lost to a kill after a step's flush"]
             if missing else [])
    if changed or extra:
        parts.append(f"{changed + extra} value(s) that differed from the steps: a repeated "
                     "step's line lost to a kill, or a damaged step or /frf (check the log "
                     "and `session info`)")
    what = "; ".join(parts)
    with SessionWriter.resume(path, protocol_text) as writer:
        lines = writer.repair_frf()
        writer.log(f"resume: every step already measured; /frf rebuilt from the steps "
                   f"({lines} lines; {what})", "WARNING")
        if cut_note:
            writer.log(f"resume: {cut_note}", "WARNING")
    return what


def _with_gate(options: Any, gate: tuple[int, int] | None) -> Any:
    """``options`` (the defaults when None) with ``gate`` (None: automatic)."""
    from dataclasses import replace

    from pelvislab.acquisition.tracking import TrackingOptions

    return replace(options or TrackingOptions(), gate=gate)


def _recorded_gate(channel: ChannelData) -> tuple[tuple[int, int], str] | None:
    """The gate set for this channel record at acquisition, if any, with who set it:
    ``operator`` (at a prompt) or ``protocol`` (the setup's ``gates``)."""
    q = channel.quality or {}
    source = q.get("gate_source")
    if source not in ("operator", "protocol") or "gate_start" not in q or "gate_stop" not in q:
        return None
    return (int(q["gate_start"]), int(q["gate_stop"])), str(source)


def _cut_gate_note(quality: Mapping[str, Any]) -> str:
    """The tracker's note on a gate that cuts the echo, from a channel's quality, else ""."""
    from pelvislab.acquisition.tracking import GATE_CUT_NOTE

    found = GATE_CUT_NOTE.search(str(quality.get("tracking_warnings", "")))
    return found.group(0) if found else ""


def bone_unstated_points(frf: FrfSet, unstated: set[tuple[str, str]]
                         ) -> list[tuple[str, str]]:
    """The ``("output" | "input", name)`` points of ``frf`` written on no modelled bone only
    because nothing gave their bone (``unstated``: ``SessionReader.bone_unstated``, points
    some step left without a bone; ``frf`` takes each point from its steps, so a point
    another step gives a bone is not among them)."""
    return [(prefix, name)
            for prefix, channels in (("output", frf.outputs), ("input", frf.inputs))
            for name, bone in zip(channels.name, channels.bone, strict=True)
            if bone == "" and (prefix, name) in unstated]


def _bone_unstated_notes(frf: FrfSet, unstated: set[tuple[str, str]]) -> list[str]:
    """A note per point of ``frf`` written on no modelled bone only because nothing gave
    its bone (a session written from design 4.2 alone names its points only, and the
    landmark catalogue does not know this name): identify and gap diagnose then leave it
    out as deliberately off-bone, so the user hears that it was unknown instead."""
    return [f"{prefix} point {name!r} is not in the landmark catalogue "
            f"(protocols/landmarks.toml) and its steps give no {prefix}_bone: written "
            f"as on no modelled bone (''), so identify and gap diagnose leave it out. "
            f"If it is on a bone, add {prefix}_bone (innominate_right, "
            f"innominate_left or sacrum) to the steps or use the catalogue's name "
            f"for the point; {prefix}_bone = '' says it is off-bone on purpose"
            for prefix, name in bone_unstated_points(frf, unstated)]


def _stored_bytes(group: Any) -> int:
    """Bytes the datasets under the HDF5 ``group`` take in their file (0 for None): what a
    copy of them needs, without the free space or a hole the file may hold."""
    import h5py

    if group is None:
        return 0
    total = [0]

    def add(_name: str, item: Any) -> None:
        if isinstance(item, h5py.Dataset):
            total[0] += item.id.get_storage_size()

    group.visititems(add)
    return total[0]


def reprocess_session(source: Path | str, target: Path | str, tracking_options: Any = None,
                      speed_of_sound_m_s: float | None = None,
                      progress: Callable[[int, int], None] | None = None,
                      software_version: str = "",
                      channel_gates: Mapping[str, tuple[int, int] | None] | None = None,
                      keep_operator_gates: bool = True,
                      notes: list[str] | None = None) -> tuple[int, list[str]]:
    """Recompute displacement, phasors and /frf of ``source`` from its raw echoes alone.

    Writes a new session ``target`` (never over an existing file) with the same /protocol,
    /bench and raw echoes, and a log line naming the source and the options. The file is
    built under a temporary name and given ``target``'s name only when complete (a killed
    reprocessing leaves nothing at ``target``). Refuses a speed of sound outside
    100-10000 m/s (the protocol's range), and options with which no FRF line survives
    (every echo lost). Returns (steps reprocessed, problems met: damaged or incomplete
    groups skipped).

    Gates, per channel record: ``channel_gates[name]`` (``"ch1"``: a (start, stop) gate for
    that channel in every step, or None for the automatic gate) first, then the gate of
    ``tracking_options`` (every channel), then the gate set at acquisition by the operator
    or the protocol (recorded as ``gate_source = "operator"`` or ``"protocol"``: kept
    unless ``keep_operator_gates`` is False, so that re-tracking with another estimator
    does not silently drop it), else the automatic gate. A gate for a channel no step has
    is refused (nothing written).

    ``notes`` (when given) receives, per channel, the tracker's note on a gate set by hand
    that cuts the echo (:data:`pelvislab.acquisition.tracking.GATE_CUT_LEVEL`) with the
    number of steps it was made on; the file's log gets the same lines.
    """

    import h5py

    from pelvislab.acquisition.frfset import write_frf
    from pelvislab.acquisition.session import (
        SESSION_SCHEMA,
        SESSION_SCHEMA_VERSION,
        _is_write_failure,
        create_log,
        log_entry,
        new_hdf5_file,
        publish_new_file,
        remove_stale_partials,
    )

    source, target = Path(source), Path(target)
    if target.exists():
        raise FileExistsError(f"{target} exists; not overwriting it")
    if target.resolve() == source.resolve():
        raise ValueError("--out must differ from the session being reprocessed")
    low, high = SPEED_OF_SOUND_RANGE_M_S
    if speed_of_sound_m_s is not None and not (
            math.isfinite(speed_of_sound_m_s) and low < speed_of_sound_m_s <= high):
        raise ValueError(f"speed of sound {speed_of_sound_m_s} m/s: must be within "
                         f"{low:g}-{high:g} m/s")
    if not target.parent.is_dir():
        raise FileNotFoundError(f"output folder {target.parent} does not exist")
    remove_stale_partials(target)
    partial = partial_path(target)
    reader = SessionReader(source)
    try:
        names = reader.step_names()
        with new_hdf5_file(partial, target, _stored_bytes(reader.handle.get("steps"))) as out:
            for k in reader.handle.attrs:
                out.attrs[k] = reader.handle.attrs[k]
            out.attrs["schema"] = SESSION_SCHEMA
            out.attrs["schema_version"] = SESSION_SCHEMA_VERSION
            out.attrs["reprocessed_from"] = str(source)
            out.attrs["software_version"] = software_version
            for group in ("protocol", "bench"):
                if group in reader.handle:
                    reader.handle.copy(reader.handle[group], out, name=group)
            damaged_runs = []
            if isinstance(reader.handle.get("runs"), h5py.Group):
                runs_out = out.create_group("runs")
                for name, attrs, problem in run_records(reader.handle):
                    try:
                        if attrs is None:
                            raise OSError(problem)
                        reader.handle.copy(reader.handle["runs"][name], runs_out, name=name)
                    except Exception as exc:  # a record damaged by a kill: say so, go on
                        if _is_write_failure(exc):  # the new file refused it: not the record
                            raise
                        damaged_runs.append(f"run {name} not copied: "
                                            f"{' '.join(str(exc).split())[:200]}")
            create_log(out, reader.log_lines() + damaged_runs + [
                f"reprocessed from {source} with tracking options {tracking_options!r}"
                + (f", speed of sound {speed_of_sound_m_s} m/s" if speed_of_sound_m_s else "")
                + (f", gates {dict(channel_gates)!r}" if channel_gates else "")])
            steps_out = out.create_group("steps")
            done: list[StepData] = []
            chosen = dict(channel_gates or {})
            options_gate = getattr(tracking_options, "gate", None)
            kept: dict[str, int] = {}  # recorded gates kept, by who set them
            cut_gates: dict[str, tuple[int, str]] = {}  # steps, first note, per channel
            records: dict[str, int] = {}  # steps, per channel
            for n, step in enumerate(reader.steps()):
                for c in step.channels:
                    if c.name in chosen:  # given for this channel: it decides
                        gate = chosen[c.name]
                        options = _with_gate(tracking_options, gate)
                        gate_source = "auto" if gate is None else "options"
                    elif options_gate is not None:  # given for every channel
                        options, gate_source = tracking_options, "options"
                    else:
                        recorded = _recorded_gate(c) if keep_operator_gates else None
                        gate, gate_source = recorded or (None, "auto")
                        options = (tracking_options if gate is None
                                   else _with_gate(tracking_options, gate))
                        kept[gate_source] = kept.get(gate_source, 0) + 1
                    if gate_source != "auto" and options is not None and options.gate:
                        # a channel's gate that cannot be tracked lost that channel in
                        # every step, and the command said nothing (review, session 38)
                        problem = gate_problem(options.gate, int(options.max_lag_samples),
                                               int(np.shape(c.codes)[1]))
                        if problem:
                            recorded_by = gate_source in ("operator", "protocol")
                            raise ValueError(
                                f"gate {options.gate} for {c.name} (step {step.index}"
                                + (f", set by the {gate_source} at acquisition"
                                   if recorded_by else "") + f"): {problem}"
                                + (f"; --gate {c.name}=auto tracks the automatic gate"
                                   if recorded_by else "") + "; nothing written")
                    process_channel(c, step.frequency_hz, options, speed_of_sound_m_s)
                    c.quality["gate_source"] = gate_source
                    records[c.name] = records.get(c.name, 0) + 1
                    cut = _cut_gate_note(c.quality)
                    if cut:
                        count, first = cut_gates.get(c.name, (0, cut))
                        cut_gates[c.name] = (count + 1, first)
                failed = [str(c.quality.get("message", "")) for c in step.channels
                          if str(c.quality.get("message", "")).startswith("tracking failed")]
                if not done and step.channels and len(failed) == len(step.channels):
                    raise ValueError(f"with tracking options {tracking_options!r}: "
                                     f"{failed[0]} (first step)")
                src = reader.handle["steps"][f"{step.index:06d}"]
                g = steps_out.create_group(src.name.split("/")[-1])
                for k in src.attrs:
                    g.attrs[k] = src.attrs[k]
                g.create_group("echoes")
                for k in src["echoes"]:
                    src.copy(src["echoes"][k], g["echoes"], name=k)
                    if not k.endswith("_trigger_offset_s") and speed_of_sound_m_s:
                        g["echoes"][k].attrs["speed_of_sound_m_s"] = float(speed_of_sound_m_s)
                disp = g.create_group("displacement")
                ph = g.create_group("phasor")
                for c in step.channels:
                    # as SessionWriter: the quality with the displacement, else on the
                    # echoes (whose copy may carry the source's: replaced)
                    quality_attrs = g["echoes"][c.name].attrs
                    for qk in [k for k in quality_attrs if k.startswith("quality_")]:
                        del quality_attrs[qk]
                    if c.displacement_m is not None:
                        d = disp.create_dataset(c.name, data=c.displacement_m)
                        quality_attrs = d.attrs
                    for qk, qv in c.quality.items():
                        quality_attrs[f"quality_{qk}"] = qv
                    if c.phasor_m is not None:
                        p = ph.create_dataset(c.name, data=np.complex128(c.phasor_m))
                        p.attrs["std_m"] = float(np.nan if c.phasor_std_m is None
                                                 else c.phasor_std_m)
                g.create_dataset("force_phasor_n", data=np.complex128(step.force_phasor_n))
                # judged again with these options (it kept the recording's verdict)
                g.attrs["quality_ok"] = all(bool(c.quality.get("ok")) for c in step.channels)
                done.append(step)
                if progress is not None:
                    progress(n + 1, len(names))
            unknown = sorted(set(chosen) - {c.name for s in done for c in s.channels})
            if unknown:
                raise ValueError(f"gate for {', '.join(unknown)}: no such channel in "
                                 f"{source}'s steps; nothing written")
            for name, (count, note) in sorted(cut_gates.items()):
                # the gate is the caller's: said once, not in every step's quality only
                line = f"{name}, {count} of its {records[name]} steps: {note}"
                if notes is not None:
                    notes.append(line)
                out["log"].resize((out["log"].shape[0] + 1,))
                out["log"][-1] = log_entry(line)
            for who in ("operator", "protocol"):
                if kept.get(who):
                    out["log"].resize((out["log"].shape[0] + 1,))
                    out["log"][-1] = log_entry(f"kept the gate the {who} set at acquisition "
                                               f"on {kept[who]} channel record(s)")
            if not done:  # an empty copy is no reprocessing (it exited 0: review, session 36)
                statuses: dict[str, int] = {}
                for problem in reader.incomplete:
                    status = problem.split(": status ", 1)[-1]
                    statuses[status] = statuses.get(status, 0) + 1
                # 'incomplete' is the reader's word for a step without the attribute
                said = ", ".join(
                    (f"{n} without a status attribute (cut short)" if status == "'incomplete'"
                     else f"{n} with status {status}")
                    for status, n in sorted(statuses.items(), key=lambda item: -item[1])[:3])
                if reader.damaged:
                    said = ", ".join(filter(None, (said, f"{len(reader.damaged)} damaged "
                                                         f"({reader.damaged[0]})")))
                raise ValueError(
                    f"{source} holds no complete step to reprocess"
                    + (f" ({said}; a complete step has status 'complete', or completed, "
                       "done, ok, finished: docs/session-format.md)" if said else "")
                    + "; nothing written")
            layout = reader.frf_layout()
            if layout is not None:  # the stored /frf's bones, "" included, are the file's word
                frf = frf_from_steps(done, *layout)
            else:
                frf = frf_from_steps(done)
                for line in _bone_unstated_notes(frf, reader.bone_unstated):
                    if notes is not None:
                        notes.append(line)
                    out["log"].resize((out["log"].shape[0] + 1,))
                    out["log"][-1] = log_entry(line)
            if done and not np.isfinite(frf.H).any():
                raise ValueError(
                    f"with tracking options {tracking_options!r}"
                    + (f" and {speed_of_sound_m_s} m/s" if speed_of_sound_m_s else "")
                    + ": no step kept an FRF line (every channel's tracking failed or was "
                    "judged bad); nothing written")
            write_frf(out, frf)
        publish_new_file(partial, target)
        problems = reader.damaged + reader.incomplete
    finally:
        partial.unlink(missing_ok=True)
        reader.close()
    return len(done), problems
