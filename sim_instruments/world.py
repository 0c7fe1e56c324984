"""The simulated world behind the virtual instruments: one subject, one shaker, two probes.

The instruments only change the world's state (generator settings from the SCPI commands
they receive, pulser/receiver settings); the digitizer asks the world for records. A record
is synthesised from the state at that moment:

    drive volts (generator #2: frequency, amplitude, output on/off)
      -> force   F = N/V calibration x V           (+ optional shaker dynamics effect)
      -> bone    U = H(f) F at each transducer's landmark, along its axis
                   (pelvislab.model receptance through sim_instruments.effects.effect_frf)
      -> motion  u(t_k) = Re(U e^{i w t_k}) at each pulse time, + subject drift
      -> echoes  sim_instruments.echo.synthesize_channel (8-bit records)

Timing (design 2): generator #2's SYNC output (rising edge at the positive zero crossing of
its sine, i.e. sine phase 0) triggers generator #1's burst of N pulses at the PRF; each pulse
fires both pulsers and triggers the digitizer. So the first pulse of every record sits at
drive phase 0: the drive voltage is v(t) = (Vpp/2) sin(w t), whose phasor at the first pulse
is V = -i Vpp/2 (x(t) = Re(X e^{+iwt}), design 4.1), and the force phasor is
``drive_newton_per_volt * V`` (or its per-frequency table's value). With
``trigger_source="internal"`` the bursts start at a random drive phase (a bench without the
SYNC link).

Clock: ``fast`` pacing never sleeps: the world's time is virtual, advanced by every
acquisition's duration and by the runner's settle waits (``world.clock.wait``), so runs are
reproducible to the bit; ``realtime`` follows the wall clock and sleeps through
acquisitions, so the simulated bench runs at the real one's pace.
"""

from __future__ import annotations

import math
import threading
import time
import zlib
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from pelvislab.drivers.interfaces import (
    InstrumentConnectionError,
    InstrumentTimeoutError,
    SegmentedRecord,
)
from pelvislab.model.frf import Points
from pelvislab.model.pelvis import PelvisModel
from pelvislab.sim_instruments.echo import (
    Acoustics,
    Receiver,
    bone_amplitude_v,
    synthesize_channel,
)
from pelvislab.sim_instruments.effects import (
    SpeedOfSoundError,
    StaticClutter,
    SubjectDrift,
    effect_frf,
    split_effects,
)
from pelvislab.sim_instruments.faults import FaultBook
from pelvislab.sim_instruments.layout import Landmark, resolve

__all__ = [
    "AcquisitionTruth",
    "Phantom",
    "GeneratorState",
    "SimClock",
    "World",
]


# --------------------------------------------------------------------------- clock
class SimClock:
    """Seconds since the bench opened, as the simulated world sees them.

    ``fast``: purely virtual, advanced only by :meth:`wait` (acquisitions, the runner's
    settle waits), so a run is reproducible to the bit whatever the machine's speed.
    ``realtime``: the wall clock; :meth:`wait` sleeps.
    """

    def __init__(self, pacing: str = "fast") -> None:
        if pacing not in ("fast", "realtime"):
            raise ValueError(f"pacing must be 'fast' or 'realtime', got {pacing!r}")
        self.pacing = pacing
        self._t0 = time.monotonic()
        self._virtual = 0.0
        self._lock = threading.Lock()

    def now(self) -> float:
        """Simulated time, s."""
        if self.pacing == "realtime":
            return time.monotonic() - self._t0
        with self._lock:
            return self._virtual

    def wait(self, seconds: float) -> None:
        """Let ``seconds`` of bench time pass (sleep in realtime, skip in fast pacing)."""
        if seconds <= 0:
            return
        if self.pacing == "realtime":
            time.sleep(seconds)
        else:
            with self._lock:
                self._virtual += seconds


# --------------------------------------------------------------------------- generator state
@dataclass
class GeneratorState:
    """A 33220A as the world sees it, kept up to date from the SCPI commands it receives
    (factory defaults after ``*RST``)."""

    function: str = "SIN"
    frequency_hz: float = 1e3
    amplitude_vpp: float = 0.1
    offset_v: float = 0.0
    output: bool = False
    sync: bool = True
    load: str = "50"
    pulse_period_s: float = 1e-3
    pulse_width_s: float = 100e-6
    burst: bool = False
    burst_cycles: int = 1
    burst_mode: str = "TRIG"
    trigger_source: str = "IMM"
    phase_deg: float = 0.0
    changed_at_s: float = 0.0

    _BOOL = {"ON": True, "1": True, "OFF": False, "0": False}

    def apply(self, command: str, now_s: float) -> None:
        """Update the state from one SCPI command (queries and unknown commands ignored)."""
        text = command.strip()
        if not text or text.endswith("?"):
            return
        head, _, arg = text.partition(" ")
        head = head.upper()
        arg = arg.strip()
        if head == "*RST":
            fresh = GeneratorState()
            for name in self.__dataclass_fields__:
                setattr(self, name, getattr(fresh, name))
            self.changed_at_s = now_s
            return
        setters = {
            "FUNC": ("function", str.upper),
            "FREQ": ("frequency_hz", float),
            "VOLT": ("amplitude_vpp", float),
            "VOLT:OFFS": ("offset_v", float),
            "OUTP": ("output", self._bool),
            "OUTP:SYNC": ("sync", self._bool),
            "OUTP:LOAD": ("load", str.upper),
            "PULS:PER": ("pulse_period_s", float),
            "FUNC:PULS:WIDT": ("pulse_width_s", float),
            "BURS:STAT": ("burst", self._bool),
            "BURS:NCYC": ("burst_cycles", lambda s: int(float(s))),
            "BURS:MODE": ("burst_mode", str.upper),
            "TRIG:SOUR": ("trigger_source", str.upper),
            "PHAS": ("phase_deg", float),
        }
        if head in setters and arg:
            name, parse = setters[head]
            try:
                setattr(self, name, parse(arg))
            except (ValueError, KeyError):
                return  # the instrument would queue an error; the state does not change
            if head == "PULS:PER":
                self.frequency_hz = 1.0 / self.pulse_period_s
            elif head == "FREQ" and self.function.startswith("PULS"):
                self.pulse_period_s = 1.0 / self.frequency_hz
            self.changed_at_s = now_s

    def _bool(self, text: str) -> bool:
        return self._BOOL[text.upper()]

    @property
    def is_sine(self) -> bool:
        """True when the output is a continuous sine."""
        return self.function.startswith("SIN") and not self.burst

    @property
    def prf_hz(self) -> float:
        """Pulse repetition frequency of the pulse function, Hz."""
        return 1.0 / self.pulse_period_s


# --------------------------------------------------------------------------- phantoms
@dataclass(frozen=True)
class Phantom:
    """The bench-top test objects of thesis ch. 8.3, used when the excitation point is on no
    modelled bone (``bone = ""``, the validation protocols).

    The driven face (a point at the excitation's position) is a calibrated piezoshaker:
    displacement ``piezo_m_per_v`` per drive volt, flat in frequency (Vlaanderen et al.
    2005: 0.25-3 um). Any other ``bone = ""`` point is a second body on a viscoelastic layer
    on the first (Conza et al. 2006): base-excited mass-spring-damper,
    T = (k + i w c) / (k - w^2 m + i w c) with natural frequency ``layer_frequency_hz`` and
    damping ratio ``layer_damping_ratio`` (fitted to table 8.1: within 5 deg at 80, 200 and
    250 Hz; 4-11 deg less lag at 125-156 Hz). The medium is a water/gel stand-off at
    ``speed_of_sound_m_s`` (assumed known: the validation protocols state it), ``depth_m``
    deep (echo 10.67 us after the pulse, inside a record starting at 10 us), without
    speckle and with negligible attenuation.
    """

    piezo_m_per_v: float = 1e-5
    layer_frequency_hz: float = 200.0
    layer_damping_ratio: float = 0.074
    speed_of_sound_m_s: float = 1480.0
    depth_m: float = 7.9e-3
    reflection: float = 0.4
    """Echo of the test object's face (keeps the default echo at ~60 % of the 8-bit range
    without the tissue's attenuation)."""

    def transmissibility(self, frequency_hz: float) -> complex:
        """Layer transmissibility T(f) = x_B / x_A."""
        w = 2 * math.pi * frequency_hz
        wn = 2 * math.pi * self.layer_frequency_hz
        c = 2j * self.layer_damping_ratio * wn * w
        return complex((wn**2 + c) / (wn**2 - w**2 + c))


# --------------------------------------------------------------------------- truth
@dataclass(frozen=True)
class AcquisitionTruth:
    """What really happened during one acquisition (for tests and benchmarks)."""

    index: int
    start_s: float
    """Time of the first pulse on the world's clock, s."""
    frequency_hz: float
    drive_vpp: float
    drive_on: bool
    voltage_phasor_v: complex
    """Drive-voltage phasor at the first pulse (amplitude, V)."""
    force_phasor_n: complex
    """Force phasor on the structure at the first pulse (N), as the bench calibration says
    (the true force also carries any shaker_dynamics effect; H_true includes it)."""
    displacement_phasor_m: dict[int, complex]
    """Per channel, bone displacement phasor along the beam (m, peak), relative to the
    first pulse: what a perfect tracker would measure with the true speed of sound."""
    measured_phasor_m: dict[int, complex]
    """Per channel, what a perfect tracker using the bench's (assumed) speed of sound
    reads: displacement_phasor_m * c_assumed / c_true."""
    drift_m: dict[int, np.ndarray] = field(repr=False, default_factory=dict)
    """Per channel, depth change by drift at each pulse (m, + = away from the transducer)."""
    trigger_phase_rad: float = 0.0
    """Drive sine phase at the first pulse (0 with the SYNC trigger)."""


# --------------------------------------------------------------------------- the world
@dataclass
class ChannelSetup:
    """One transducer: the landmark it looks at and its acoustic path."""

    landmark: Landmark
    acoustics: Acoustics


class World:
    """Subject, shaker and probes; the physics of every simulated acquisition."""

    def __init__(self, *, model: PelvisModel, config: Any, clock: SimClock,
                 excitation: Landmark, excitation_direction: tuple[float, float, float] | None,
                 channels: dict[int, Landmark], acoustics: dict[int, Acoustics],
                 effects: list[Any], faults: FaultBook, seed: int, snr_db: float,
                 trigger_source: str = "drive_sync", trigger_latency_s: float = 0.0,
                 trigger_jitter_s: float = 0.0, readout_s_per_sample: float = 1e-8,
                 phantom: Phantom | None = None) -> None:
        self.model = model
        self.config = config
        self.clock = clock
        self.faults = faults
        self.seed = int(seed)
        self.snr_db = float(snr_db)
        if trigger_source not in ("drive_sync", "internal"):
            raise ValueError("trigger_source must be 'drive_sync' or 'internal'")
        self.trigger_source = trigger_source
        self.trigger_latency_s = float(trigger_latency_s)
        self.trigger_jitter_s = float(trigger_jitter_s)
        self.readout_s_per_sample = float(readout_s_per_sample)
        self.phantom = phantom or Phantom()
        self.frf_effects, self.echo_effects = split_effects(effects)
        self.drive = GeneratorState()
        self.trigger = GeneratorState()
        self.receivers: dict[int, Receiver | None] = {}
        self.acquisitions = 0
        self.truth: list[AcquisitionTruth] = []
        self._rng = np.random.default_rng(self.seed)
        self._lock = threading.RLock()
        self._frf_cache: dict[tuple[float, int], np.ndarray] = {}
        self._layout_version = 0
        self._acoustics_default = dict(acoustics)
        self.excitation = excitation
        self.excitation_direction = excitation_direction
        self.channels: dict[int, ChannelSetup] = {}
        self._drift_state: dict[int, tuple[float, float]] = {}
        self.protocol_speed_of_sound_m_s: float | None = None
        self.place(excitation=excitation, channels=channels,
                   excitation_direction=excitation_direction)

    # ------------------------------------------------------------------ the operator
    def place(self, excitation: str | Landmark | Any | None = None,
              channels: dict[int, str | Landmark | Any] | None = None,
              excitation_direction: tuple[float, float, float] | None = None,
              speed_of_sound_m_s: float | None = None) -> None:
        """The (simulated) operator moves the shaker and/or the transducers.

        ``excitation``: landmark name or point; ``excitation_direction``: force direction
        (default: into the bone, minus the landmark's outward direction). ``channels``:
        digitizer channel -> landmark (its direction: bone -> transducer).
        ``speed_of_sound_m_s``: the protocol's (``ultrasound.speed_of_sound_m_s``, m/s),
        which the tracker assumes where the bench file states none; the simulated tissue
        then has it (times any ``speed_of_sound_error``), as it has the bench file's value
        where that states one. None keeps the last one given (at first the bench's
        default, 1540 m/s).
        Call it where the runner prompts the operator to reposition the transducers.
        """
        with self._lock:
            if speed_of_sound_m_s is not None:
                self.protocol_speed_of_sound_m_s = float(speed_of_sound_m_s)
            if excitation is not None:
                self.excitation = resolve(excitation)
                self.excitation_direction = excitation_direction
            elif excitation_direction is not None:
                self.excitation_direction = excitation_direction
            if channels is not None:
                new: dict[int, ChannelSetup] = {}
                for ch, point in channels.items():
                    acoustics = self._acoustics_default.get(int(ch), Acoustics())
                    new[int(ch)] = ChannelSetup(resolve(point), acoustics)
                self.channels = new
            self._layout_version += 1
            self._frf_cache.clear()

    # ------------------------------------------------------------------ physics
    def _points(self) -> tuple[list[int], Points, Points]:
        chans = sorted(self.channels)
        lms = [self.channels[c].landmark for c in chans]
        outputs = Points(tuple(lm.bone for lm in lms), [lm.position_m for lm in lms],
                         [lm.direction for lm in lms], tuple(lm.name for lm in lms))
        ex = self.excitation
        # catalogue directions point out of the bone (toward a sensor); a shaker pushing
        # on that surface applies its force inward, along -direction (landmarks.toml)
        direction = self.excitation_direction or tuple(-x for x in ex.direction)
        inputs = Points((ex.bone,), [ex.position_m], [direction], (ex.name,))
        return chans, outputs, inputs

    def newton_per_volt(self, frequency_hz: float) -> complex:
        """The simulated drive chain's true N/V at ``frequency_hz``: the bench's constant,
        or its per-frequency table (held at the end values outside it: the simulated
        chain exists at every frequency; the runner refuses to extrapolate)."""
        from pelvislab.acquisition.frf_lines import calibrated_newton_per_volt

        cfg = self.config
        table = tuple(getattr(cfg, "drive_calibration_frequency_hz", ()))
        f = float(frequency_hz)
        if table:
            f = min(max(f, table[0]), table[-1])
        return calibrated_newton_per_volt(f, cfg.drive_newton_per_volt, table,
                                          getattr(cfg, "drive_calibration_newton_per_volt", ()))

    def frf(self, frequency_hz: float) -> dict[int, complex]:
        """True receptance (m/N) from the excitation to each channel's landmark along its
        beam, with every FRF effect (cached per frequency and layout)."""
        with self._lock:
            key = (round(float(frequency_hz), 12), self._layout_version)
            if key not in self._frf_cache:
                chans, outputs, inputs = self._points()
                if not chans:
                    self._frf_cache[key] = np.zeros(0, complex)
                elif self.on_phantom:
                    self._frf_cache[key] = self._phantom_frf(float(frequency_hz), outputs,
                                                             inputs)
                else:
                    H = effect_frf(self.model, self.frf_effects, np.array([frequency_hz]),
                                   outputs, inputs)[0, :, 0]
                    # a transducer on no modelled bone sees nothing move
                    self._frf_cache[key] = np.where(np.isfinite(H), H, 0.0)
                if len(self._frf_cache) > 4096:
                    self._frf_cache.clear()
            values = self._frf_cache[key]
            return {c: complex(v) for c, v in zip(sorted(self.channels), values, strict=True)}

    @property
    def on_phantom(self) -> bool:
        """True when the shaker drives a test object (excitation on no modelled bone)."""
        return self.excitation.bone == ""

    def _phantom_frf(self, frequency_hz: float, outputs: Points, inputs: Points) -> np.ndarray:
        """'Receptance' of the phantom: displacement per newton of the bench's drive chain
        (so that displacement per drive volt is the piezo's calibration)."""
        ph = self.phantom
        # the piezo moves in phase with the drive voltage: s V = (s / cal) (cal V)
        per_newton = ph.piezo_m_per_v / self.newton_per_volt(frequency_hz)
        drive_dir = inputs.direction[0]
        out = np.zeros(len(outputs.bone), complex)
        for i, bone in enumerate(outputs.bone):
            if bone != "":
                continue
            gain = float(outputs.direction[i] @ drive_dir) * per_newton
            if np.allclose(outputs.position_m[i], inputs.position_m[0]):
                out[i] = gain
            else:
                out[i] = gain * ph.transmissibility(frequency_hz)
        return out

    def speed_ratio(self, channel: int) -> float:
        """c_true / c_assumed for ``channel`` (speed-of-sound error effects)."""
        ratio = 1.0
        for e in self.echo_effects:
            if isinstance(e, SpeedOfSoundError):
                landmark = self.channels[channel].landmark.name if channel in self.channels \
                    else ""
                if e.outputs is None or landmark in e.outputs or str(channel) in e.outputs:
                    ratio *= 1.0 + e.relative_error
        return ratio

    def _drift(self, channel: int, t_s: np.ndarray) -> np.ndarray:
        """Depth change (m, + away) of ``channel`` at world times ``t_s`` (increasing)."""
        total = np.zeros_like(t_s)
        for k, e in enumerate(self.echo_effects):
            if not isinstance(e, SubjectDrift):
                continue
            if e.channels is not None and channel not in e.channels:
                continue
            total += e.rate_m_per_s * t_s
            if e.breathing_amplitude_m:
                total += e.breathing_amplitude_m * np.sin(2 * math.pi * e.breathing_hz * t_s)
            if e.random_walk_m_per_sqrt_s > 0:
                # a Wiener process continued from the last acquisition's end
                key = k * 16 + channel
                t_last, w_last = self._drift_state.get(key, (0.0, 0.0))
                rng = np.random.default_rng([e.seed, channel, self.acquisitions])
                dt = np.diff(np.concatenate(([t_last], t_s)))
                steps = rng.standard_normal(t_s.size) * np.sqrt(np.maximum(dt, 0.0))
                w = w_last + np.cumsum(steps) * e.random_walk_m_per_sqrt_s
                self._drift_state[key] = (float(t_s[-1]), float(w[-1]))
                total += w
        return total

    def _clutter(self, channel: int, acoustics: Acoustics,
                 receiver: Receiver) -> tuple[np.ndarray, np.ndarray] | None:
        times: list[float] = []
        levels: list[float] = []
        amp = bone_amplitude_v(acoustics, receiver)
        for e in self.echo_effects:
            if isinstance(e, StaticClutter) and (e.channels is None or channel in e.channels):
                if len(e.depth_m) != len(e.level_db):
                    raise ValueError("static_clutter: depth_m and level_db differ in length")
                for d, db in zip(e.depth_m, e.level_db, strict=True):
                    times.append(2.0 * d / acoustics.speed_of_sound_m_s)
                    levels.append(amp * 10.0 ** (db / 20.0))
        if not times:
            return None
        return np.array(times), np.array(levels)

    # ------------------------------------------------------------------ acquisition
    def acquire(self, channels: list[int], sample_rate_hz: float, n_samples: int,
                n_segments: int, delay_s: float, full_scale_v: float, offset_v: float,
                timeout_s: float) -> dict[int, SegmentedRecord]:
        """One sequence acquisition on ``channels``; raises like the real digitizer."""
        # waits happen outside the lock: in realtime pacing a timeout must not block the
        # other instruments (a pulser's safe state during an abort)
        failure: Exception | None = None
        wait_failure = True
        with self._lock:
            index = self.acquisitions
            self.acquisitions += 1
            fault = self.faults.digitizer_fault(index)
            trig = self.trigger
            prf = trig.prf_hz
            drive = self.drive
            wait_s = 0.0
            duration = math.inf
            if fault is not None:
                if self.faults.digitizer_lost(index):
                    wait_failure = False
                    failure = InstrumentConnectionError(
                        f"simulated digitizer: connection lost (acquisition {index})")
                else:
                    failure = InstrumentTimeoutError(
                        f"simulated digitizer: acquisition {index} did not end within "
                        f"{timeout_s:g} s (injected fault)")
            else:
                why = self._no_trigger_reason(n_segments)
                if why is None and self._synced():
                    wait_s = 1.0 / drive.frequency_hz  # at most one period to the next edge
                if why is None:
                    duration = n_segments / prf
                    if wait_s + duration > timeout_s:
                        why = (f"{n_segments} pulses at {prf:g} Hz take {duration:g} s, "
                               f"longer than the timeout {timeout_s:g} s")
                if why is not None:
                    failure = InstrumentTimeoutError(
                        f"simulated digitizer: no end of acquisition within {timeout_s:g} s: "
                        f"{why}")
        if failure is not None:
            if wait_failure:
                self.clock.wait(timeout_s)
            raise failure
        with self._lock:
            start = self.clock.now()
            if self._synced():
                # the burst starts on the next SYNC edge (sine phase 0) plus the latency
                period = 1.0 / drive.frequency_hz
                start += (drive.changed_at_s - start) % period + self.trigger_latency_s
                phase0 = 2 * math.pi * drive.frequency_hz * self.trigger_latency_s
            else:
                phase0 = float(self._rng.uniform(0, 2 * math.pi))
            records, truth = self._synthesize(index, channels, sample_rate_hz, n_samples,
                                              n_segments, delay_s, full_scale_v, offset_v,
                                              start, phase0, prf)
            self.truth.append(truth)
        readout = self.readout_s_per_sample * n_samples * n_segments * len(channels)
        self.clock.wait(wait_s + duration + readout)
        return records

    def _synced(self) -> bool:
        """True when the bursts are triggered by the drive generator's SYNC output."""
        return self.trigger_source == "drive_sync" and self.trigger.trigger_source.startswith(
            "EXT")

    def _no_trigger_reason(self, n_segments: int) -> str | None:
        trig = self.trigger
        if not trig.output:
            return "the trigger generator's output is off (no pulses)"
        if not (trig.function.startswith("PULS") and trig.burst):
            return "the trigger generator is not in pulse-burst mode"
        if trig.burst_cycles < n_segments:
            return (f"the trigger burst has {trig.burst_cycles} pulses, the digitizer waits "
                    f"for {n_segments}")
        if self._synced() and not (self.drive.sync and self.drive.function.startswith("SIN")):
            return "no SYNC pulses from the drive generator (sync off or not a sine)"
        return None

    def _synthesize(self, index: int, channels: list[int], fs: float, n_samples: int,
                    n_segments: int, delay_s: float, full_scale_v: float, offset_v: float,
                    start: float, phase0: float, prf: float
                    ) -> tuple[dict[int, SegmentedRecord], AcquisitionTruth]:
        drive = self.drive
        f = drive.frequency_hz
        on = drive.output and drive.is_sine
        amplitude = drive.amplitude_vpp / 2.0 if on else 0.0
        # sine phase phase0 at the first pulse: v = A sin(w t + phase0) = Re(A e^{i(phase0-pi/2)})
        volts = amplitude * complex(math.cos(phase0 - math.pi / 2), math.sin(phase0 - math.pi / 2))
        force = self.newton_per_volt(f) * volts
        H = self.frf(f) if on else {}
        t_pulse = np.arange(n_segments) / prf
        w = 2 * math.pi * f
        carrier = np.exp(1j * w * t_pulse)
        records: dict[int, SegmentedRecord] = {}
        disp: dict[int, complex] = {}
        meas: dict[int, complex] = {}
        drifts: dict[int, np.ndarray] = {}
        rng = np.random.default_rng([self.seed, index])
        for ch in channels:
            setup = self.channels.get(ch)
            U = complex(H.get(ch, 0.0)) * force
            disp[ch] = U
            receiver = self.receivers.get(ch)
            if self.on_phantom:
                c_assumed = self.phantom.speed_of_sound_m_s
            elif self.protocol_speed_of_sound_m_s is None:
                c_assumed = float(self.config.speed_of_sound_for(ch))
            else:  # the tracker's value: the bench file's, else the protocol's (session 42)
                c_assumed = float(self.config.speed_of_sound_for(
                    ch, self.protocol_speed_of_sound_m_s))
            ratio = self.speed_ratio(ch)
            meas[ch] = U / ratio
            drift = self._drift(ch, start + t_pulse)
            drifts[ch] = drift
            mean_drift = float(drift.mean()) if drift.size else 0.0
            if setup is None:
                acoustics = Acoustics(speed_of_sound_m_s=c_assumed * ratio)
                live = None
            else:
                acoustics = replace(setup.acoustics, speed_of_sound_m_s=c_assumed * ratio)
                live = receiver
            if self.on_phantom:  # water/gel stand-off over the test object
                acoustics = replace(acoustics, bone_depth_m=self.phantom.depth_m,
                                    attenuation_db_per_m_mhz=0.0, speckle_level_db=-300.0,
                                    bone_reflection=self.phantom.reflection)
            # each pulse meets the bone one way (depth / c) after it leaves: the echo
            # reports the motion then, not at the pulse (26 us under 40 mm of tissue)
            one_way_s = (acoustics.bone_depth_m + mean_drift) / acoustics.speed_of_sound_m_s
            u = (U * carrier * np.exp(1j * w * one_way_s)).real
            u_eff = u - (drift - mean_drift)
            offsets = -rng.uniform(0.0, 1.0 / fs, n_segments)
            rx = live if live is not None else Receiver(enabled=False)
            rx = replace(rx, snr_db=self.snr_db)
            codes, vpc = synthesize_channel(
                acoustics, rx, u_eff, offsets, sample_rate_hz=fs, n_samples=n_samples,
                delay_s=delay_s, full_scale_v=full_scale_v, offset_v=offset_v, rng=rng,
                depth_offset_m=mean_drift,
                speckle_seed=zlib.crc32(f"{self.seed}:{ch}:{setup.landmark.name if setup else ''}"
                                        .encode()),
                clutter=self._clutter(ch, acoustics, rx), jitter_s=self.trigger_jitter_s)
            records[ch] = SegmentedRecord(codes=codes, trigger_offset_s=offsets,
                                          sample_rate_hz=fs, delay_s=delay_s,
                                          volts_per_count=vpc, volts_offset=offset_v)
        truth = AcquisitionTruth(index=index, start_s=start, frequency_hz=f,
                                 drive_vpp=drive.amplitude_vpp, drive_on=on,
                                 voltage_phasor_v=volts, force_phasor_n=force,
                                 displacement_phasor_m=disp, measured_phasor_m=meas,
                                 drift_m=drifts, trigger_phase_rad=phase0)
        return records, truth
