"""Measurement protocols: the versioned TOML schema, its validation and duration estimate.

A protocol says what one session measures (``docs/protocols.md`` documents every key):
a stepped-sine sweep (thesis ch. 6.2 / design section 2), the ultrasound acquisition
settings (ch. 8), the setups (excitation point + the landmark each transducer looks at;
the operator repositions the transducers between setups) and subject metadata.

Validation refuses anything it does not understand: every problem is reported as
``KEY: rule`` (all of them, on one line), e.g. ``sweep.stop_hz: must be < prf/2 = 2500 Hz``.
Conditions that are legal but unwise (a sweep longer than a subject can keep still, 45 s in
ch. 6.2; a settle time under 50 ms) are returned as warnings instead.

Schema ``pelvislab-protocol`` version 1. Units are SI and in the key names.
"""

from __future__ import annotations

import math
import re
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import partial
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from pelvislab.drivers.acqiris import DP235_MAX_SAMPLES_PER_CHANNEL
from pelvislab.drivers.bench import SPEED_OF_SOUND_RANGE_M_S

__all__ = [
    "PROTOCOL_SCHEMA",
    "PROTOCOL_SCHEMA_VERSION",
    "MIN_DRIVE_VPP",
    "BenchLimits",
    "PlannedStep",
    "Point",
    "Protocol",
    "ProtocolError",
    "Setup",
    "Subject",
    "Sweep",
    "Ultrasound",
    "drive_profile_vpp",
    "instrument_problems",
    "load_landmarks",
    "load_protocol",
    "parse_protocol",
]

PROTOCOL_SCHEMA = "pelvislab-protocol"
PROTOCOL_SCHEMA_VERSION = 1

MAX_STILL_S = 45.0
"""Longest sweep a subject can be expected to keep perfectly still (thesis ch. 6.2), s."""
MIN_SETTLE_S = 0.05
"""Settle time between frequency steps used in ch. 6.2 (50 ms); less draws a warning."""
MIN_PERIODS_PER_RECORD = 2.0
"""A record must hold at least this many drive periods for a phasor estimate."""
MAX_STEPS = 20_000
"""Sanity bound on setups x frequencies."""
MIN_DRIVE_VPP = 0.02
"""Lowest drive level a profile or auto-ranging may use, V pk-pk: the Agilent 33220A's
minimum amplitude into an open circuit (10 mVpp into 50 ohm, 20 mVpp high-Z; data sheet,
``pelvislab.drivers.agilent33220a.AMPLITUDE_50OHM_VPP``); the bench drives high-Z."""
DRIVE_MODES = ("fixed", "auto")
MAX_POINT_DISTANCE_M = 1.0
"""A point farther than this from the model origin (between the SIAS, design 4.1) is
refused: no place on a pelvis is (the landmark catalogue's points lie within 0.16 m of it,
every coordinate within 0.15 m), so it is a unit slip, millimetres typed into
``position_m`` (a run measured 2 of 2 steps of a point 93 m away, every FRF line NaN)."""
MIN_BONE_POINT_DISTANCE_M = 0.02
"""A point on a bone nearer than this to the model origin is refused: the origin (between
the SIAS, design 4.1) lies in front of the abdomen, the nearest bone (the pubic symphysis,
appendix E) some 90 mm below it, and the catalogue's nearest landmark 115 mm away; such a
point is metres typed into ``position_mm`` (0.05 read as 0.05 mm)."""
MIDLINE_TOLERANCE_M = 0.01
"""How far (m) a point on one innominate may lie across the mid-sagittal plane (y = 0): the
bones meet at the pubic symphysis, on that plane (appendix E's symphysis springs attach at
y = 0 and +-5 mm); a right-innominate point at y > 0 is a sign slip (design 4.1: +y to the
subject's left, right-side points have y < 0)."""
SHADOW_MOVE_MM = 20.0
SHADOW_TURN_DEG = 30.0
"""A [points] entry named like a catalogue landmark farther than this from it (the
catalogue's coordinates are estimates to ~2 cm), turned more, or on another bone, draws a
warning: sessions would carry another point under the landmark's name."""
CHANNEL_KEYS = {"ch1": 1, "ch2": 2, "ch3": 3, "ch4": 4}
BONES = ("innominate_right", "innominate_left", "sacrum", "")
SUBJECT_POSITIONS = ("face-up", "face-down", "side", "specimen", "phantom", "simulated", "")
PULSE_ENERGIES = ("low", "high")


class ProtocolError(ValueError):
    """An invalid protocol; the one-line message names each offending key and the rule."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.source = source
        self.problems = list(problems)
        shown = "; ".join(problems[:6])
        more = f" (and {len(problems) - 6} more)" if len(problems) > 6 else ""
        super().__init__(f"{source}: {shown}{more}")


# --------------------------------------------------------------------------- data classes
@dataclass(frozen=True)
class Point:
    """A named measurement or excitation point: bone, position (m, model frame), direction.

    ``direction`` is a unit vector; for a measurement it points from the bone surface toward
    the transducer, for an excitation it is the direction of the applied force (design 4.1).
    """

    name: str
    bone: str
    position_m: tuple[float, float, float]
    direction: tuple[float, float, float]


@dataclass(frozen=True)
class Subject:
    """Subject metadata (pseudonymous: no names in protocol or session files)."""

    id: str = ""
    position: str = ""
    notes: str = ""
    extra: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Sweep:
    """Stepped-sine sweep: frequencies in acquisition order and the per-step timing."""

    frequencies_hz: tuple[float, ...]
    """Frequencies in acquisition order (after ``order``), Hz."""
    order: str
    drive_vpp: float
    """Shaker-drive generator amplitude, V pk-pk."""
    settle_s: float
    """Wait after each frequency change before acquiring, s (at least)."""
    settle_periods: float
    """...and at least this many drive periods."""
    periods_per_step: float | None
    """Record length in drive periods (thesis: 10); None: ``ultrasound.pulses`` per record."""
    repeats: int = 1
    """Acquisitions per frequency, one after the other (ch. 8 validation: 4-6)."""
    drive_profile: tuple[tuple[float, float], ...] = ()
    """Optional drive-level profile ((frequency_hz, vpp), ...), frequencies increasing;
    empty: ``drive_vpp`` at every step. See :func:`drive_profile_vpp`."""
    drive_mode: str = "fixed"
    """``fixed``: the planned level; ``auto``: a step whose motion exceeds
    ``max_displacement_m`` (or loses echoes) is repeated once at a lower level."""
    max_displacement_m: float | None = None
    """Auto mode: largest acceptable displacement amplitude (peak, any channel), m."""
    min_drive_vpp: float = MIN_DRIVE_VPP
    """Auto mode: the lowest level a repeat may use, V pk-pk."""

    def drive_vpp_at(self, frequency_hz: float) -> float:
        """Planned drive level at ``frequency_hz``, V pk-pk (profile, else ``drive_vpp``)."""
        if not self.drive_profile:
            return float(self.drive_vpp)
        return float(drive_profile_vpp(self.drive_profile, frequency_hz))


@dataclass(frozen=True)
class Ultrasound:
    """Pulse-echo acquisition settings. Thesis ch. 8.3 gives ``prf_hz``, ``pulses``,
    ``sample_rate_hz`` and ``samples``; the other defaults are ours (the thesis names no
    speed of sound, only "soft tissue", ch. 8.2)."""

    prf_hz: float = 5000.0
    pulses: int = 2000
    sample_rate_hz: float = 500e6
    samples: int = 500
    delay_s: float = 10e-6
    speed_of_sound_m_s: float = 1540.0
    full_scale_v: float = 1.0
    offset_v: float = 0.0
    trigger_width_s: float = 1e-6
    trigger_high_v: float = 5.0
    gain_db: float = 40.0
    pulse_energy: str = "low"
    damping_ohm: float = 50.0
    high_pass_hz: float | None = None
    low_pass_hz: float | None = None

    @property
    def record_end_s(self) -> float:
        """Time after the trigger at which one echo record ends, s."""
        return self.delay_s + self.samples / self.sample_rate_hz


@dataclass(frozen=True)
class Setup:
    """One transducer placement: the excitation point and what each channel looks at."""

    name: str
    excitation: str
    transducers: Mapping[int, str]
    """Digitizer channel (1-based) -> point name."""
    prompt: str = ""
    excitation_direction: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Unit direction of the applied force (default: into the surface, -landmark direction)."""
    gates: Mapping[int, tuple[int, int]] = field(default_factory=dict)
    """Channel -> (start, stop) samples of the record to track the bone echo in, for a rig
    whose echoes are known beforehand (a phantom, a fixed fixture); other channels (and
    these, once the operator sets or clears a gate) use the automatic gate."""


@dataclass(frozen=True)
class PlannedStep:
    """One frequency step of the plan."""

    index: int
    """Position in the plan (0-based, setups x frequencies)."""
    setup_index: int
    setup: str
    frequency_hz: float
    n_pulses: int
    settle_s: float
    repeat: int = 0
    """0 .. sweep.repeats - 1."""
    drive_vpp: float = 0.0
    """Planned drive level of this step, V pk-pk (auto mode may lower it)."""

    @property
    def key(self) -> tuple[str, float, int]:
        """(setup name, frequency, repeat) identifies a step across resumed runs."""
        return (self.setup, round(self.frequency_hz, 9), self.repeat)


@dataclass(frozen=True)
class BenchLimits:
    """Bench limits a protocol is checked against (from the bench file when given)."""

    max_drive_vpp: float = 2.0
    n_channels: int = 2
    max_sample_rate_hz: float = 500e6
    name: str = "simulated bench"
    max_samples_per_channel: int = DP235_MAX_SAMPLES_PER_CHANNEL
    """Digitizer acquisition memory per channel (samples): one record, all segments,
    ``n_pulses x samples`` (the driver's per-segment padding is not counted); the Acqiris
    DP235's as assumed in ``pelvislab.drivers.acqiris``."""
    trigger_load_ohm: float | None = None
    """The trigger generator's declared load (ohm, inf = high-Z); None: not known."""
    max_trigger_vpp: float | None = None
    """The bench limit on the trigger generator (V pk-pk), as its driver applies it."""
    drive_limit_note: str = ""
    """Why ``max_drive_vpp`` is below the bench file's limit, when it is (appended to the
    drive messages)."""
    drive_calibration_range_hz: tuple[float, float] | None = None
    """(lowest, highest) frequency of the bench's per-frequency drive calibration (Hz);
    None: one constant N/V, valid at every frequency."""
    instruments: tuple[Any, ...] | None = None
    """The bench's instruments (``pelvislab.drivers.bench.InstrumentModel``), whose own
    checks the acquisition settings must pass (:func:`instrument_problems`); None: not known,
    not checked (:func:`parse_protocol` without ``limits`` uses the default simulated
    bench's)."""

    @classmethod
    def from_config(cls, config: Any) -> BenchLimits:
        """Limits of a :class:`pelvislab.drivers.bench.BenchConfig`: the drive limit is
        also capped at what the drive generator gives into its declared load (a bench
        limit of 50 Vpp passed the check; the 33220A gives at most 20 Vpp into high-Z:
        a first-day review, session 36)."""
        from pelvislab.drivers.agilent33220a import amplitude_limits_vpp

        max_drive = float(config.generator_limit_vpp("drive"))
        note = ""
        load = config.generator_load_ohm("drive")
        if load is not None and amplitude_limits_vpp(load)[1] < max_drive:
            max_drive = amplitude_limits_vpp(load)[1]
            into = "high-Z" if math.isinf(load) else f"{load:g} ohm"
            note = f": the 33220A gives at most {max_drive:g} Vpp into {into}"
        return cls(max_drive_vpp=max_drive, name=str(config.name), drive_limit_note=note,
                   trigger_load_ohm=config.generator_load_ohm("trigger"),
                   max_trigger_vpp=config.generator_limit_vpp("trigger"),
                   drive_calibration_range_hz=getattr(config, "drive_calibration_range_hz",
                                                      None),
                   instruments=tuple(config.instrument_models()))


@dataclass(frozen=True)
class Protocol:
    """A validated protocol."""

    name: str
    description: str
    subject: Subject
    sweep: Sweep
    ultrasound: Ultrasound
    setups: tuple[Setup, ...]
    points: Mapping[str, Point]
    """Every point a transducer looks at, resolved (catalogue or the file's ``[points]``);
    direction: bone surface -> transducer."""
    text: str
    """The TOML source (stored verbatim in the session's ``/protocol``)."""
    source: str = "<string>"
    warnings: tuple[str, ...] = ()
    excitations: Mapping[str, Point] = field(default_factory=dict)
    """Every excitation point; direction: that of the applied force (design 4.1)."""

    def n_pulses(self, frequency_hz: float) -> int:
        """Pulses (echoes) per record at ``frequency_hz``."""
        if self.sweep.periods_per_step is None:
            return int(self.ultrasound.pulses)
        return int(math.ceil(self.sweep.periods_per_step * self.ultrasound.prf_hz
                             / frequency_hz - 1e-9))

    def settle_s(self, frequency_hz: float) -> float:
        """Settle time at ``frequency_hz``: max(settle_s, settle_periods / f), s."""
        return max(self.sweep.settle_s, self.sweep.settle_periods / frequency_hz)

    def step_duration_s(self, frequency_hz: float) -> float:
        """Settle + record time of one step (no transfer/processing overhead), s."""
        return self.settle_s(frequency_hz) + self.n_pulses(frequency_hz) / self.ultrasound.prf_hz

    def sweep_duration_s(self) -> float:
        """Duration of one setup's sweep (what the subject must keep still for), s."""
        return float(sum(self.step_duration_s(f) for f in self.sweep.frequencies_hz)
                     * self.sweep.repeats)

    def estimated_duration_s(self) -> float:
        """Settle + record time of the whole protocol (operator repositioning excluded), s."""
        return self.sweep_duration_s() * len(self.setups)

    def steps(self) -> list[PlannedStep]:
        """The plan: every setup in order, each swept over ``sweep.frequencies_hz``."""
        out: list[PlannedStep] = []
        for si, setup in enumerate(self.setups):
            for f in self.sweep.frequencies_hz:
                for r in range(self.sweep.repeats):
                    out.append(PlannedStep(len(out), si, setup.name, float(f),
                                           self.n_pulses(f), self.settle_s(f), r,
                                           self.sweep.drive_vpp_at(f)))
        return out

    @property
    def channels(self) -> tuple[int, ...]:
        """Every digitizer channel any setup uses, sorted."""
        return tuple(sorted({ch for s in self.setups for ch in s.transducers}))

    def _drive_text(self) -> str:
        sw = self.sweep
        levels = [sw.drive_vpp_at(f) for f in sw.frequencies_hz]
        text = (f"{sw.drive_vpp:g} Vpp" if not sw.drive_profile else
                f"{min(levels):.3g}-{max(levels):.3g} Vpp (profile)")
        if sw.drive_mode == "auto":
            text += (f", auto-ranging to {sw.max_displacement_m * 1e6:g} um "
                     f"(floor {sw.min_drive_vpp:g} Vpp)")
        return text

    def summary(self) -> str:
        """A few lines describing the plan, for ``pelvislab protocol check``."""
        f = self.sweep.frequencies_hz
        lo, hi = min(f), max(f)
        pulses = [self.n_pulses(x) for x in f]
        lines = [
            f"protocol {self.name!r} ({self.source}), schema {PROTOCOL_SCHEMA} "
            f"v{PROTOCOL_SCHEMA_VERSION}",
            f"  sweep: {len(f)} step{'s' if len(f) != 1 else ''} {lo:g}-{hi:g} Hz "
            f"({self.sweep.order}"
            + (f", each {self.sweep.repeats} times" if self.sweep.repeats > 1 else "")
            + "), drive " + self._drive_text() + ", "
            f"{min(pulses)}-{max(pulses)} pulses per step at "
            f"{self.ultrasound.prf_hz:g} Hz PRF",
            f"  setups: {len(self.setups)} ("
            + ", ".join(f"{s.name}: {s.excitation} -> "
                        + "/".join(s.transducers[c] for c in sorted(s.transducers))
                        + "".join(f", ch{c} gate {g[0]}-{g[1]}"
                                  for c, g in sorted(s.gates.items()))
                        for s in self.setups) + ")",
            f"  estimated duration: {self.estimated_duration_s():.1f} s "
            f"({self.sweep_duration_s():.1f} s per setup sweep; settle + record time, "
            "transducer repositioning not included)",
        ]
        return "\n".join(lines)


def _setup_gates(raw: Any, channels: Mapping[int, str], ultrasound: Ultrasound | None,
                 where: str, p: _Problems) -> dict[int, tuple[int, int]]:
    """A setup's ``gates = { ch1 = [START, STOP], ... }``: sample indices of the record,
    for channels of this setup, that the default tracking can use (tracking.gate_problem)."""
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        p.add(where, "must be a table like { ch1 = [START, STOP] } (samples of the record)")
        return {}
    from pelvislab.acquisition.tracking import TrackingOptions, gate_problem

    gates: dict[int, tuple[int, int]] = {}
    for key, value in raw.items():
        ch = CHANNEL_KEYS.get(key)
        if ch is None or ch not in channels:
            p.add(f"{where}.{key}", f"not a channel of this setup (its transducers: "
                  f"{', '.join(f'ch{c}' for c in sorted(channels)) or 'none'})")
            continue
        if not (isinstance(value, list) and len(value) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) for v in value)
                and value[0] < value[1]):
            p.add(f"{where}.{key}", f"must be [START, STOP]: two whole sample numbers, "
                  f"START < STOP; got {value!r}")
            continue
        gate = (int(value[0]), int(value[1]))
        if ultrasound is not None:
            problem = gate_problem(gate, TrackingOptions().max_lag_samples,
                                   ultrasound.samples)
            if problem:
                p.add(f"{where}.{key}", problem)
                continue
        gates[ch] = gate
    return gates


# --------------------------------------------------------------------------- drive profile
def drive_profile_vpp(profile: Any, frequency_hz: Any) -> Any:
    """Drive level (V pk-pk) of a profile at ``frequency_hz`` (Hz; scalar or array).

    ``profile``: ((frequency_hz, vpp), ...) with strictly increasing frequencies. Between
    two points, log(vpp) is linear in log(frequency) (a straight line on a log-log plot,
    i.e. a power law; one point: constant); outside the profile the end level is held.
    A stepped-sine FRF is a ratio (response / force), so the level may change per step.
    """
    table = np.asarray(profile, dtype=float).reshape(-1, 2)
    if table.shape[0] == 0:
        raise ValueError("empty drive profile")
    f = np.asarray(frequency_hz, dtype=float)
    logf = np.log(np.clip(f, table[0, 0], table[-1, 0]))
    out = np.exp(np.interp(logf, np.log(table[:, 0]), np.log(table[:, 1])))
    return float(out) if out.ndim == 0 else out


# --------------------------------------------------------------------------- landmarks
def load_landmarks(path: Path | str | None = None) -> dict[str, Point]:
    """The landmark catalogue (``protocols/landmarks.toml`` unless ``path`` is given).

    Accepts ``[landmarks.NAME]`` (or top-level ``[NAME]``) tables with ``bone``,
    ``position_m`` (or ``position_mm``) and ``direction``. A missing catalogue gives an
    empty mapping: protocols may define their own ``[points]``.
    """
    if path is None:
        resource = resources.files("pelvislab.protocols") / "landmarks.toml"
        if not resource.is_file():
            return {}
        text = resource.read_text(encoding="utf-8")
        where = "landmarks.toml"
    else:
        text = Path(path).read_text(encoding="utf-8")
        where = str(path)
    data = tomllib.loads(text)
    table = data.get("landmarks", data)
    if isinstance(table, list):  # [[landmarks]] array of tables with a name key
        table = {str(t.get("name")): t for t in table if isinstance(t, Mapping)}
    problems = _Problems()
    out: dict[str, Point] = {}
    for name, entry in table.items():
        if not isinstance(entry, Mapping) or not ({"position_m", "position_mm"} & set(entry)):
            continue
        point = _point(name, entry, name, problems, strict=False)
        if point is not None:
            out[name] = point
    if problems.items:
        raise ProtocolError(where, problems.items)
    return out


# --------------------------------------------------------------------------- parsing
_TOP = {"schema", "schema_version", "name", "description", "subject", "sweep", "ultrasound",
        "setups", "points"}
_SWEEP = {"start_hz", "stop_hz", "step_hz", "frequencies_hz", "order", "drive_vpp", "settle_s",
          "repeats", "settle_periods", "periods_per_step", "drive_profile", "drive_mode",
          "max_displacement_m", "min_drive_vpp"}
_US_FLOAT = {"prf_hz", "sample_rate_hz", "delay_s", "speed_of_sound_m_s", "full_scale_v",
             "offset_v", "trigger_width_s", "trigger_high_v", "gain_db", "damping_ohm",
             "high_pass_hz", "low_pass_hz"}
_US = _US_FLOAT | {"pulses", "samples", "pulse_energy"}
_SETUP = {"name", "excitation", "excitation_direction", "transducers", "prompt", "gates"}
_SUBJECT = {"id", "position", "notes", "age_years", "mass_kg", "height_m", "sex", "side"}
_POINT = {"bone", "position_m", "position_mm", "direction", "description"}


class _Problems:
    """Collects ``key: rule`` problems."""

    def __init__(self) -> None:
        self.items: list[str] = []

    def add(self, key: str, rule: str) -> None:
        self.items.append(f"{key}: {rule}")


def _unit_of(key: str) -> str:
    # longest suffix first: speed_of_sound_m_s is in m/s, not in s
    for suffix, unit in (("_m_s", "m/s"), ("_hz", "Hz"), ("_s", "s"), ("_vpp", "V pk-pk"),
                         ("_v", "V"), ("_db", "dB"), ("_ohm", "ohm"), ("_mm", "mm"),
                         ("_m", "m"), ("_kg", "kg"), ("_years", "years")):
        if key.endswith(suffix):
            return unit
    return ""


def _number(table: Mapping[str, Any], key: str, where: str, p: _Problems,
            default: float | None = None, *, minimum: float | None = None,
            exclusive: bool = True, maximum: float | None = None) -> float | None:
    """A finite number (int or float, not bool) with optional bounds, or ``default``."""
    if key not in table:
        return default
    value = table[key]
    full = f"{where}.{key}" if where else key
    unit = _unit_of(key)
    if isinstance(value, bool) or not isinstance(value, int | float):
        hint = f" in {unit}" if unit else ""
        if isinstance(value, str):
            p.add(full, f"must be a number{hint} (the unit is in the key name), got the "
                        f"string {value!r}")
        else:
            p.add(full, f"must be a number{hint}, got {type(value).__name__} {value!r}")
        return None
    v = float(value)
    if not math.isfinite(v):
        p.add(full, f"must be finite, got {value!r}")
        return None
    if minimum is not None and (v <= minimum if exclusive else v < minimum):
        p.add(full, f"must be {'>' if exclusive else '>='} {minimum:g} {unit}".rstrip()
              + f", got {value!r}")
        return None
    if maximum is not None and v > maximum:
        p.add(full, f"must be <= {maximum:g} {unit}".rstrip() + f", got {value!r}")
        return None
    return v


def _integer(table: Mapping[str, Any], key: str, where: str, p: _Problems, default: int,
             minimum: int, maximum: int) -> int | None:
    if key not in table:
        return default
    value = table[key]
    full = f"{where}.{key}"
    if isinstance(value, bool) or not isinstance(value, int):
        p.add(full, f"must be an integer, got {type(value).__name__} {value!r}")
        return None
    if not minimum <= value <= maximum:
        p.add(full, f"must be an integer in {minimum}..{maximum}, got {value}")
        return None
    return int(value)


def _string(table: Mapping[str, Any], key: str, where: str, p: _Problems, default: str = "",
            choices: tuple[str, ...] | None = None) -> str | None:
    if key not in table:
        return default
    value = table[key]
    full = f"{where}.{key}" if where else key
    if not isinstance(value, str):
        p.add(full, f"must be a string, got {type(value).__name__} {value!r}")
        return None
    if choices is not None and value not in choices:
        p.add(full, f"must be one of {list(choices)}, got {value!r}")
        return None
    return value


def _drive_profile(sw: Mapping[str, Any], limits: BenchLimits,
                   p: _Problems) -> tuple[tuple[float, float], ...] | None:
    """``sweep.drive_profile``: [[frequency_hz, vpp], ...], frequencies increasing."""
    if "drive_profile" not in sw:
        return None
    key = "sweep.drive_profile"
    raw = sw["drive_profile"]
    if (not isinstance(raw, list) or not raw
            or any(not isinstance(row, list) or len(row) != 2
                   or any(isinstance(v, bool) or not isinstance(v, int | float) for v in row)
                   for row in raw)):
        p.add(key, "must be a non-empty list of [frequency_hz, vpp] pairs of numbers, e.g. "
                   f"[[5.0, 0.02], [40.0, 0.5]], got {raw!r}")
        return None
    rows = tuple((float(f), float(v)) for f, v in raw)
    n_before = len(p.items)
    for i, (f, v) in enumerate(rows):
        where = f"{key}[{i}]"
        if not (math.isfinite(f) and f > 0):
            p.add(where, f"frequency must be finite and > 0 Hz, got {f!r}")
        if not math.isfinite(v) or v < MIN_DRIVE_VPP:
            p.add(where, f"level {v!r} V pk-pk is below the generator minimum "
                         f"{MIN_DRIVE_VPP:g} V pk-pk (33220A, high-Z load)")
        elif v > limits.max_drive_vpp:
            p.add(where, f"level {v:g} V pk-pk is above the bench limit "
                         f"{limits.max_drive_vpp:g} V pk-pk ({limits.name}"
                         f"{limits.drive_limit_note})")
        if i and not f > rows[i - 1][0]:
            p.add(where, f"frequencies must increase strictly ({f:g} Hz after "
                         f"{rows[i - 1][0]:g} Hz)")
    return rows if len(p.items) == n_before else None


def _unknown(table: Mapping[str, Any], known: set[str], where: str, p: _Problems) -> None:
    for key in table:
        if key not in known:
            full = f"{where}.{key}" if where else str(key)
            stem = str(key).split("_")[0]
            twins = sorted(k for k in known if k.split("_")[0] == stem and "_" in k)
            if twins and "_" in str(key):
                p.add(full, f"unknown key; did you mean {' or '.join(twins)}? (SI units, "
                            "named in the key)")
            else:
                p.add(full, f"unknown key (known: {', '.join(sorted(known))})")


def _table(data: Mapping[str, Any], key: str, p: _Problems,
           required: bool = False) -> Mapping[str, Any]:
    if key not in data:
        if required:
            p.add(key, "missing table")
        return {}
    value = data[key]
    if not isinstance(value, Mapping):
        p.add(key, f"must be a table ([{key}]), got {type(value).__name__}")
        return {}
    return value


def _vector(value: Any, key: str, p: _Problems) -> tuple[float, float, float] | None:
    if (not isinstance(value, list) or len(value) != 3
            or any(isinstance(v, bool) or not isinstance(v, int | float) for v in value)):
        p.add(key, f"must be a list of 3 numbers, got {value!r}")
        return None
    vec = tuple(float(v) for v in value)
    if not all(math.isfinite(v) for v in vec):
        p.add(key, f"must be finite, got {value!r}")
        return None
    return vec  # type: ignore[return-value]


def _point(name: str, entry: Mapping[str, Any], where: str, p: _Problems,
           strict: bool = True) -> Point | None:
    if strict:
        _unknown(entry, _POINT, where, p)
    n_before = len(p.items)
    bone = _string(entry, "bone", where, p, default="", choices=BONES)
    if "position_m" in entry and "position_mm" in entry:
        p.add(where, "give position_m or position_mm, not both")
    if "position_mm" in entry:
        pos = _vector(entry["position_mm"], f"{where}.position_mm", p)
        pos = None if pos is None else tuple(v / 1000.0 for v in pos)
    elif "position_m" in entry:
        pos = _vector(entry["position_m"], f"{where}.position_m", p)
    else:
        p.add(f"{where}.position_m", "missing")
        pos = None
    if pos is not None:
        distance = math.sqrt(sum(v * v for v in pos))
        key = "position_mm" if "position_mm" in entry else "position_m"

        def listed(factor: float = 1.0) -> str:
            return "[" + ", ".join(f"{v * factor:g}" for v in entry[key]) + "]"

        rule = ""
        if distance > MAX_POINT_DISTANCE_M:
            rule = (f"{listed()} is {distance:.3g} m from the model origin (between the "
                    f"SIAS), where no pelvis is (at most {MAX_POINT_DISTANCE_M:g} m)")
            if key == "position_m":
                rule += (f": position_m is in metres, so if these are millimetres write "
                         f"position_m = {listed(1e-3)} or position_mm = {listed()}")
        elif bone and distance < MIN_BONE_POINT_DISTANCE_M:
            rule = (f"{listed()} is {distance * 1e3:.3g} mm from the model origin (between "
                    f"the SIAS, in front of the abdomen), where no bone is (a point on "
                    f"{bone} lies at least {MIN_BONE_POINT_DISTANCE_M * 1e3:g} mm from it)")
            if key == "position_mm":
                rule += (f": position_mm is in millimetres, so if these are metres write "
                         f"position_mm = {listed(1e3)} or position_m = {listed()}")
        if rule:
            p.add(f"{where}.{key}", rule)
            pos = None
    if pos is not None and bone in ("innominate_right", "innominate_left"):
        # a right-side point typed with y > 0 passed and its FRFs were the right bone's
        # motion at a place on the left (review, session 42)
        right = bone == "innominate_right"
        y = pos[1]
        if (y > MIDLINE_TOLERANCE_M) if right else (y < -MIDLINE_TOLERANCE_M):
            key = "position_mm" if "position_mm" in entry else "position_m"
            side, other = ("right", "left") if right else ("left", "right")
            given = entry[key][1]
            p.add(f"{where}.{key}",
                  f"y = {given:g} {'mm' if key == 'position_mm' else 'm'} is on the subject's "
                  f"{other} (+y to the left, design 4.1), but bone = {bone!r} is the {side} "
                  f"one: {side}-side points have y {'<' if right else '>'} 0 (the "
                  f"innominates meet at y = 0 +- {MIDLINE_TOLERANCE_M * 1e3:g} mm); flip the "
                  "sign of y, or name the other bone")
            pos = None
    if "direction" not in entry:
        p.add(f"{where}.direction", "missing (unit vector bone -> transducer)")
        direction = None
    else:
        direction = _vector(entry["direction"], f"{where}.direction", p)
        if direction is not None:
            norm = math.sqrt(sum(v * v for v in direction))
            if not 0.98 < norm < 1.02:
                p.add(f"{where}.direction", f"must be a unit vector, norm is {norm:.3g}")
                direction = None
            else:
                direction = tuple(v / norm for v in direction)
    if len(p.items) > n_before or pos is None or direction is None or bone is None:
        return None
    return Point(name, bone, pos, direction)  # type: ignore[arg-type]


def parse_protocol(text: str, source: str = "<string>", limits: BenchLimits | None = None,
                   landmarks: Mapping[str, Point] | None = None) -> Protocol:
    """Parse and validate protocol TOML ``text``; raise :class:`ProtocolError` if invalid.

    ``limits``: the bench's limits (default: the simulated bench). ``landmarks``: the point
    catalogue (default: the shipped ``protocols/landmarks.toml``).
    """
    if limits is None:
        from pelvislab.drivers.bench import BenchConfig

        limits = BenchLimits(instruments=BenchConfig.default().instrument_models())
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ProtocolError(source, [f"not valid TOML: {exc}"]) from None
    p = _Problems()
    notes: list[str] = []  # warnings found while reading (returned after the others' checks)
    _unknown(data, _TOP, "", p)

    schema = data.get("schema")
    if schema != PROTOCOL_SCHEMA:
        p.add("schema", f"must be {PROTOCOL_SCHEMA!r}, got {schema!r}")
    version = data.get("schema_version")
    if isinstance(version, bool) or version != PROTOCOL_SCHEMA_VERSION:
        p.add("schema_version",
              f"this pelvislab reads version {PROTOCOL_SCHEMA_VERSION}, got {version!r}")
        raise ProtocolError(source, p.items)  # other versions: nothing else is meaningful
    name = _string(data, "name", "", p)
    if name == "" and "name" not in data:
        p.add("name", "missing (a short protocol name)")
    elif isinstance(name, str) and not name.strip():
        # required, so not blank either: sessions and the GUI name the protocol by it
        p.add("name", "is blank; give a short protocol name")
    description = _string(data, "description", "", p) or ""

    # subject ---------------------------------------------------------------------
    sub = _table(data, "subject", p)
    _unknown(sub, _SUBJECT, "subject", p)
    extra: dict[str, Any] = {}
    for key, most, slip, factor in (("age_years", 130.0, "months", 1 / 12),
                                    ("mass_kg", 400.0, "grams", 1e-3),
                                    ("height_m", 2.8, "centimetres", 1e-2)):
        v = _number(sub, key, "subject", p, minimum=0.0)
        if v is not None and v > most:
            # 72000 (g), 178 (cm) passed into every session's metadata (review, session 42)
            unit = _unit_of(key)
            p.add(f"subject.{key}", f"{v:g} {unit} is more than any subject ({most:g} "
                                    f"{unit} at most); if these are {slip}, write "
                                    f"{key} = {v * factor:.3g}")
        elif v is not None:
            extra[key] = v
    for key in ("sex", "side"):
        v = _string(sub, key, "subject", p)
        if v:
            extra[key] = v
    sid = _string(sub, "id", "subject", p) or ""
    if not re.fullmatch(r"[A-Za-z0-9._-]{0,32}", sid):
        p.add("subject.id", "letters, digits, '-', '_', '.' only, at most 32 characters "
                            "(a pseudonymous ID, never a name)")
    subject = Subject(
        id=sid,
        position=_string(sub, "position", "subject", p, choices=SUBJECT_POSITIONS) or "",
        notes=_string(sub, "notes", "subject", p) or "",
        extra=extra,
    )

    # ultrasound -----------------------------------------------------------------
    us = _table(data, "ultrasound", p)
    _unknown(us, _US, "ultrasound", p)
    d = Ultrasound()
    prf = _number(us, "prf_hz", "ultrasound", p, d.prf_hz, minimum=0.0, maximum=100e3)
    pulses = _integer(us, "pulses", "ultrasound", p, d.pulses, 2, 1_000_000)
    fs = _number(us, "sample_rate_hz", "ultrasound", p, d.sample_rate_hz, minimum=0.0,
                 maximum=limits.max_sample_rate_hz)
    samples = _integer(us, "samples", "ultrasound", p, d.samples, 8, 1_000_000)
    delay = _number(us, "delay_s", "ultrasound", p, d.delay_s, minimum=0.0, exclusive=False)
    c = _number(us, "speed_of_sound_m_s", "ultrasound", p, d.speed_of_sound_m_s,
                minimum=SPEED_OF_SOUND_RANGE_M_S[0], maximum=SPEED_OF_SOUND_RANGE_M_S[1])
    fsv = _number(us, "full_scale_v", "ultrasound", p, d.full_scale_v, minimum=0.0)
    offset = _number(us, "offset_v", "ultrasound", p, d.offset_v)
    tw = _number(us, "trigger_width_s", "ultrasound", p, d.trigger_width_s, minimum=0.0)
    th = _number(us, "trigger_high_v", "ultrasound", p, d.trigger_high_v, minimum=0.0,
                 maximum=10.0)
    gain = _number(us, "gain_db", "ultrasound", p, d.gain_db, minimum=-60.0, maximum=80.0)
    energy = _string(us, "pulse_energy", "ultrasound", p, d.pulse_energy, PULSE_ENERGIES)
    damping = _number(us, "damping_ohm", "ultrasound", p, d.damping_ohm, minimum=0.0)
    hp = _number(us, "high_pass_hz", "ultrasound", p, None, minimum=0.0)
    lp = _number(us, "low_pass_hz", "ultrasound", p, None, minimum=0.0)
    ultrasound = None
    if None not in (prf, pulses, fs, samples, delay, c, fsv, offset, tw, th, gain, energy,
                    damping):
        ultrasound = Ultrasound(prf, pulses, fs, samples, delay, c, fsv, offset, tw, th, gain,
                                energy, damping, hp, lp)  # type: ignore[arg-type]
        if ultrasound.record_end_s >= 1.0 / ultrasound.prf_hz:
            p.add("ultrasound.samples",
                  f"record (delay_s + samples/sample_rate_hz = "
                  f"{ultrasound.record_end_s * 1e6:.4g} us) must end before the next pulse "
                  f"(1/prf_hz = {1e6 / ultrasound.prf_hz:.4g} us)")
        from pelvislab.acquisition.tracking import MIN_GATE_SAMPLES, TrackingOptions

        lag = TrackingOptions().max_lag_samples
        if samples < MIN_GATE_SAMPLES + 2 * lag:  # type: ignore[operator]
            # 16 samples passed the check and the run then tracked nothing, every FRF line
            # NaN (review, session 42): no gate fits such a record
            p.add("ultrasound.samples",
                  f"a record of {samples} samples cannot be tracked: the tracking needs a "
                  f"gate of {MIN_GATE_SAMPLES} samples or more with its lag range "
                  f"({lag} samples) on both sides, {MIN_GATE_SAMPLES + 2 * lag} samples at "
                  "least (thesis ch. 8.3 records 500)")
        if tw is not None and tw >= 1.0 / prf:  # type: ignore[operator]
            p.add("ultrasound.trigger_width_s", "must be shorter than the pulse period 1/prf_hz")
        if limits.trigger_load_ohm is not None or limits.max_trigger_vpp is not None:
            # the trigger generator's own rules and the bench limit, as its driver applies
            # them: the run failed on them after the bench had opened, when `protocol
            # check` had said ok (a first-day review, session 36)
            from pelvislab.drivers.agilent33220a import check_amplitude_offset
            from pelvislab.drivers.interfaces import LimitError

            load = (limits.trigger_load_ohm if limits.trigger_load_ohm is not None
                    else math.inf)
            try:
                check_amplitude_offset(th, th / 2.0, load, limits.max_trigger_vpp)
            except LimitError as exc:
                p.add("ultrasound.trigger_high_v",
                      f"the trigger pulse 0-{th:g} V on {limits.name}: {exc}")
        if hp is not None and lp is not None and hp >= lp:
            p.add("ultrasound.high_pass_hz", "must be below ultrasound.low_pass_hz")
        if hp is not None and hp >= fs / 2:  # type: ignore[operator]
            p.add("ultrasound.high_pass_hz", "must be below sample_rate_hz/2")

    # sweep ---------------------------------------------------------------------
    sw = _table(data, "sweep", p, required=True)
    _unknown(sw, _SWEEP, "sweep", p)
    freqs: list[float] | None = None
    has_range = any(k in sw for k in ("start_hz", "stop_hz", "step_hz"))
    if "frequencies_hz" in sw and has_range:
        p.add("sweep.frequencies_hz", "give either frequencies_hz or start_hz/stop_hz/step_hz")
    elif "frequencies_hz" in sw:
        raw = sw["frequencies_hz"]
        if (not isinstance(raw, list) or not raw
                or any(isinstance(v, bool) or not isinstance(v, int | float) for v in raw)):
            p.add("sweep.frequencies_hz", f"must be a non-empty list of numbers (Hz), got {raw!r}")
        elif not all(math.isfinite(v) and round(v, 9) > 0 for v in raw):
            p.add("sweep.frequencies_hz", "every frequency must be finite and > 0 Hz")
        else:
            # on the 1 nHz grid of start/stop/step and of a step's key (PlannedStep.key):
            # 80.0 and 80.0000000001 passed as two lines, ran as one key, and the session
            # then said "2 acquired of 3 planned" of a completed run (review, session 42)
            grid = [round(float(v), 9) for v in raw]
            repeated = sorted({f for f in grid if grid.count(f) > 1})
            if repeated:
                p.add("sweep.frequencies_hz", "frequencies must not repeat (to 1 nHz): "
                      + "; ".join(f"{f:.10g} Hz is given as "
                                  + ", ".join(f"frequencies_hz[{i}] = {raw[i]!r}"
                                              for i, g in enumerate(grid) if g == f)
                                  for f in repeated))
            else:
                freqs = sorted(grid)
    elif sw:
        missing = [k for k in ("start_hz", "stop_hz", "step_hz") if k not in sw]
        if missing:
            for k in missing:
                p.add(f"sweep.{k}", "missing (or give sweep.frequencies_hz)")
        else:
            start = _number(sw, "start_hz", "sweep", p, minimum=0.0)
            stop = _number(sw, "stop_hz", "sweep", p, minimum=0.0)
            step = _number(sw, "step_hz", "sweep", p, minimum=0.0)
            if None not in (start, stop, step):
                if stop < start:  # type: ignore[operator]
                    p.add("sweep.stop_hz", f"must be >= start_hz ({start:g} Hz)")
                else:
                    n = int(math.floor((stop - start) / step + 1e-9)) + 1  # type: ignore[operator]
                    if n > MAX_STEPS:
                        p.add("sweep.step_hz", f"gives {n} steps, more than {MAX_STEPS}")
                    else:
                        freqs = [round(start + i * step, 9) for i in range(n)]  # type: ignore
                        if freqs[0] <= 0.0:  # a stepped sine needs a frequency (1 nHz grid)
                            p.add("sweep.start_hz", f"must be > 0 Hz, got {start!r}")
                            freqs = None
                        elif stop - freqs[-1] > 1e-6:  # type: ignore[operator]
                            # 40-120 Hz in 30 Hz steps ended at 100 Hz, and 500 Hz steps
                            # measured 40 Hz alone, unsaid (review, session 42)
                            notes.append(
                                f"sweep.stop_hz: {stop:g} Hz is not on the grid of start_hz "
                                f"{start:g} Hz + k x step_hz {step:g} Hz: the sweep ends at "
                                f"{freqs[-1]:g} Hz ({n} line{'s' if n > 1 else ''}); "
                                "make stop_hz - start_hz a multiple of step_hz")
    order = _string(sw, "order", "sweep", p, "up", ("up", "down"))
    drive = _number(sw, "drive_vpp", "sweep", p, minimum=0.0)
    profile = _drive_profile(sw, limits, p)
    if "drive_vpp" in sw and "drive_profile" in sw:
        p.add("sweep.drive_profile", "give either sweep.drive_vpp or sweep.drive_profile, "
                                     "not both")
    elif "drive_vpp" not in sw and "drive_profile" not in sw and sw:
        p.add("sweep.drive_vpp", "missing (shaker-drive amplitude, V pk-pk; or give "
                                 "sweep.drive_profile)")
    elif drive is not None and drive > limits.max_drive_vpp:
        p.add("sweep.drive_vpp", f"{drive:g} V pk-pk is above the bench limit "
                                 f"{limits.max_drive_vpp:g} V pk-pk ({limits.name}"
                                 f"{limits.drive_limit_note})")
    elif drive is not None and drive < MIN_DRIVE_VPP:
        p.add("sweep.drive_vpp", f"{drive:g} V pk-pk is below the generator minimum "
                                 f"{MIN_DRIVE_VPP:g} V pk-pk (33220A, high-Z load)")
    if profile:
        drive = max(v for _, v in profile)  # the highest level: what the limit applies to
    drive_mode = _string(sw, "drive_mode", "sweep", p, "fixed", DRIVE_MODES)
    max_disp = _number(sw, "max_displacement_m", "sweep", p, None, minimum=0.0,
                       maximum=1e-3)
    min_drive = _number(sw, "min_drive_vpp", "sweep", p, MIN_DRIVE_VPP, minimum=MIN_DRIVE_VPP,
                        exclusive=False, maximum=limits.max_drive_vpp)
    if drive_mode == "auto" and "max_displacement_m" not in sw:
        p.add("sweep.max_displacement_m", "missing: drive_mode = \"auto\" needs the largest "
                                          "acceptable displacement amplitude (m, peak)")
    if drive_mode == "fixed":
        for key in ("max_displacement_m", "min_drive_vpp"):
            if key in sw:
                p.add(f"sweep.{key}", "only used with drive_mode = \"auto\"")
    settle = _number(sw, "settle_s", "sweep", p, MIN_SETTLE_S, minimum=0.0, exclusive=False,
                     maximum=60.0)
    settle_periods = _number(sw, "settle_periods", "sweep", p, 0.0, minimum=0.0,
                             exclusive=False, maximum=1000.0)
    periods = _number(sw, "periods_per_step", "sweep", p, None, minimum=0.0, maximum=10_000.0)
    if periods is not None and "pulses" in us:
        p.add("sweep.periods_per_step", "give either sweep.periods_per_step or "
                                        "ultrasound.pulses, not both")

    repeats = _integer(sw, "repeats", "sweep", p, 1, 1, 100)
    sweep = None
    if freqs is not None and None not in (order, drive, settle, settle_periods, repeats,
                                          drive_mode):
        ordered = tuple(freqs if order == "up" else reversed(freqs))
        sweep = Sweep(ordered, order, drive, settle, settle_periods, periods,  # type: ignore
                      repeats, profile or (), drive_mode or "fixed", max_disp,
                      min_drive if min_drive is not None else MIN_DRIVE_VPP)
        calibrated = limits.drive_calibration_range_hz
        if calibrated is not None:
            lo, hi = calibrated
            tol = 1e-9 * hi  # as the interpolation's own edge (frf_lines)
            below = [f for f in freqs if f < lo - tol]
            above = [f for f in freqs if f > hi + tol]
            for side, key, where in ((below, "start_hz", f"below {lo:g} Hz"),
                                     (above, "stop_hz", f"above {hi:g} Hz")):
                if side:
                    span = (f"{side[0]:g} Hz" if len(side) == 1
                            else f"{min(side):g}-{max(side):g} Hz")
                    # a table written in kHz (0.005-0.3 for 5-300 Hz; 0.001-20 overlaps
                    # the sweep's start: review) covers the sweep x 1000
                    hint = ("; its rows x 1000 would cover the sweep: kHz in its "
                            "frequency_hz column?" if lo * 1e3 <= min(freqs) + tol
                            and max(freqs) <= hi * 1e3 + tol else "")
                    p.add(f"sweep.{key}" if key in sw else "sweep.frequencies_hz",
                          f"{len(side)} of {len(freqs)} frequencies ({span}) {where}, "
                          f"outside the drive calibration of {limits.name} "
                          f"({lo:g}-{hi:g} Hz), which is not extrapolated: calibrate the "
                          f"drive chain over the sweep, or narrow the sweep{hint}")
        if ultrasound is not None:
            nyquist = ultrasound.prf_hz / 2
            if max(freqs) >= nyquist:
                p.add("sweep.stop_hz" if "stop_hz" in sw else "sweep.frequencies_hz",
                      f"highest frequency {max(freqs):g} Hz must be below prf_hz/2 = "
                      f"{nyquist:g} Hz (displacement is sampled once per pulse)")
            if periods is None:
                worst = min(freqs) * ultrasound.pulses / ultrasound.prf_hz
                if worst < MIN_PERIODS_PER_RECORD:
                    p.add("ultrasound.pulses",
                          f"a record of {ultrasound.pulses} pulses at {ultrasound.prf_hz:g} Hz "
                          f"holds only {worst:.3g} periods of {min(freqs):g} Hz; at least "
                          f"{MIN_PERIODS_PER_RECORD:g} are needed (or use "
                          "sweep.periods_per_step)")
            elif periods < MIN_PERIODS_PER_RECORD:
                p.add("sweep.periods_per_step",
                      f"must be >= {MIN_PERIODS_PER_RECORD:g} periods per record")
            if periods is None:
                most = ultrasound.pulses
            else:
                most = int(math.ceil(periods * ultrasound.prf_hz / min(freqs) - 1e-9))
            if most * ultrasound.samples > limits.max_samples_per_channel:
                p.add("sweep.periods_per_step" if periods is not None else "ultrasound.pulses",
                      f"the longest record ({most} pulses x {ultrasound.samples} samples = "
                      f"{most * ultrasound.samples} samples, at {min(freqs):g} Hz) exceeds "
                      f"the digitizer memory of {limits.max_samples_per_channel} samples per "
                      "channel (DP235 as assumed: 8 Mi points)")

    # points and setups ----------------------------------------------------------
    own: dict[str, Point] = {}
    refused_points: set[str] = set()  # [points] entries refused above: said once, there
    pts = _table(data, "points", p)
    for pname, entry in pts.items():
        if not isinstance(entry, Mapping):
            p.add(f"points.{pname}", "must be a table")
            refused_points.add(pname)
            continue
        point = _point(pname, entry, f"points.{pname}", p)
        if point is not None:
            own[pname] = point
            if "bone" not in entry:
                # a researcher's point on the sacrum without `bone` was silently on no bone:
                # the model-based analyses left it out unsaid (review, session 42)
                notes.append(
                    f"points.{pname}.bone: not given, so the point is on no modelled bone "
                    "(\"\"): identify and the gap diagnosis leave it out; write bone = "
                    "\"sacrum\", \"innominate_right\" or \"innominate_left\", or bone = \"\" "
                    "for a point on no bone")
        else:
            refused_points.add(pname)
    catalogue = dict(load_landmarks() if landmarks is None else landmarks)
    for pname, point in own.items():
        landmark = catalogue.get(pname)
        if landmark is None:
            continue
        # a point named like a landmark replaces it (documented), but one elsewhere was
        # unsaid: sessions then carry another place under the landmark's name, which a
        # reader takes for the catalogue's (review, session 42)
        moved_mm = 1e3 * math.dist(point.position_m, landmark.position_m)
        turned = math.degrees(math.acos(max(-1.0, min(1.0, sum(
            a * b for a, b in zip(point.direction, landmark.direction, strict=True))))))
        changes = []
        if point.bone != landmark.bone:
            changes.append(f"bone {landmark.bone!r} -> {point.bone!r}")
        # a subject's own coordinates may correct the catalogue's estimates ("a few mm to
        # ~2 cm", its header) and its direction somewhat: beyond that it is another point
        if moved_mm > SHADOW_MOVE_MM:
            changes.append(f"position {moved_mm:.0f} mm away")
        if turned > SHADOW_TURN_DEG:
            changes.append(f"direction turned {turned:.0f} deg")
        if changes:
            notes.append(
                f"points.{pname}: replaces the catalogue landmark of that name ("
                + ", ".join(changes) + "); sessions record this point under the landmark's "
                "name: give it a name of its own (a landmark corrected for a subject stays "
                f"within {SHADOW_MOVE_MM:g} mm and {SHADOW_TURN_DEG:g} deg, on its bone)")
    known_points = {**catalogue, **own}

    setups: list[Setup] = []
    raw_setups = data.get("setups")
    if raw_setups is None:
        p.add("setups", "missing: at least one [[setups]] table")
        raw_setups = []
    elif not isinstance(raw_setups, list) or not raw_setups:
        p.add("setups", "must be a non-empty array of tables ([[setups]])")
        raw_setups = []
    used: dict[str, Point] = {}
    excitations: dict[str, Point] = {}

    def resolve(pname: Any, key: str) -> str | None:
        if not isinstance(pname, str) or not pname:
            p.add(key, f"must be a point name (string), got {pname!r}")
            return None
        if pname in refused_points:
            # its [points] entry is named with the reason; "unknown point" here too was a
            # knock-on of it (audit), and the catalogue's point of that name is not meant
            return None
        if pname not in known_points:
            close = sorted(k for k in known_points if k[:3].lower() == pname[:3].lower())[:5]
            hint = f"; similar: {close}" if close else ""
            p.add(key, f"unknown point {pname!r}: not in the landmark catalogue nor in "
                       f"[points]{hint}")
            return None
        used[pname] = known_points[pname]
        return pname

    for i, raw in enumerate(raw_setups):
        where = f"setups[{i}]"
        if not isinstance(raw, Mapping):
            p.add(where, "must be a table")
            continue
        _unknown(raw, _SETUP, where, p)
        sname = _string(raw, "name", where, p, default=f"setup{i + 1}")
        if isinstance(sname, str) and not sname.strip():
            # a step's setup is its name: a blank one reads as none in the session
            p.add(f"{where}.name", f"is blank; give the setup a name or leave the key out "
                                   f"(then setup{i + 1})")
        excitation = resolve(raw.get("excitation"), f"{where}.excitation")
        prompt = _string(raw, "prompt", where, p) or ""
        tr = raw.get("transducers")
        channels: dict[int, str] = {}
        if not isinstance(tr, Mapping) or not tr:
            p.add(f"{where}.transducers", "must be a table like { ch1 = \"POINT\", ch2 = ... }")
        else:
            for key, value in tr.items():
                if key not in CHANNEL_KEYS or CHANNEL_KEYS[key] > limits.n_channels:
                    allowed = [k for k, v in CHANNEL_KEYS.items() if v <= limits.n_channels]
                    p.add(f"{where}.transducers.{key}",
                          f"unknown channel (this bench has {allowed})")
                    continue
                pname = resolve(value, f"{where}.transducers.{key}")
                if pname is not None:
                    channels[CHANNEL_KEYS[key]] = pname
            if len(set(channels.values())) != len(channels):
                p.add(f"{where}.transducers", "two channels look at the same point")
        gates = _setup_gates(raw.get("gates"), channels, ultrasound, f"{where}.gates", p)
        force_dir = None
        if excitation is not None:
            force_dir = tuple(-v for v in known_points[excitation].direction)
        if "excitation_direction" in raw:
            force_dir = _vector(raw["excitation_direction"], f"{where}.excitation_direction", p)
            if force_dir is not None:
                norm = math.sqrt(sum(v * v for v in force_dir))
                if not 0.98 < norm < 1.02:
                    p.add(f"{where}.excitation_direction",
                          f"must be a unit vector, norm is {norm:.3g}")
                    force_dir = None
                else:
                    force_dir = tuple(v / norm for v in force_dir)
        if excitation is not None and force_dir is not None:
            earlier = excitations.get(excitation)
            if earlier is not None and not np.allclose(earlier.direction, force_dir):
                p.add(f"{where}.excitation_direction",
                      f"{excitation!r} is excited along {list(earlier.direction)} in an "
                      "earlier setup; one point, one force direction")
            pt = known_points[excitation]
            excitations[excitation] = Point(pt.name, pt.bone, pt.position_m,
                                            force_dir)  # type: ignore[arg-type]
        if sname is not None and excitation is not None and channels and force_dir:
            setups.append(Setup(sname, excitation, channels, prompt,
                                force_dir, gates))  # type: ignore[arg-type]
    names = [s.name for s in setups]
    for dup in sorted({n for n in names if names.count(n) > 1}):
        p.add("setups", f"setup name {dup!r} is used twice")
    if sweep is not None and len(setups) * len(sweep.frequencies_hz) > MAX_STEPS:
        p.add("setups", f"setups x frequencies exceeds {MAX_STEPS} steps")

    if ultrasound is not None and limits.instruments is not None:
        # what the bench's own instruments accept (a 70 dB gain passed the check and the run
        # then failed on it as an instrument fault, leaving a 0-step file: audit); after
        # the file's own rules, which keep a key they already refused
        taken = {item.split(": ", 1)[0] for item in p.items}
        used_channels = {ch for s in setups for ch in s.transducers}
        for problem in _instrument_problems(ultrasound, freqs, periods, used_channels,
                                            limits.instruments, limits.name):
            if problem.split(": ", 1)[0] not in taken:
                p.items.append(problem)

    if p.items or sweep is None or ultrasound is None or name is None:
        if not p.items:
            p.add("sweep", "incomplete")
        raise ProtocolError(source, p.items)

    protocol = Protocol(name, description, subject, sweep, ultrasound, tuple(setups), used,
                        text, source, (), excitations)
    warnings: list[str] = list(notes)
    if sweep.settle_s < MIN_SETTLE_S:
        warnings.append(f"sweep.settle_s: {sweep.settle_s:g} s is under the "
                        f"{MIN_SETTLE_S * 1e3:g} ms of ch. 6.2; responses may not have settled")
    still = protocol.sweep_duration_s()
    if still > MAX_STILL_S:
        settling = sum(protocol.settle_s(f) for f in sweep.frequencies_hz) * sweep.repeats
        if settling > still / 2 and sweep.settle_s >= 1.0:
            # settle_s = 50 (ms meant) drew "consider a coarser step_hz" (review, session 42)
            hint = (f"{settling:.1f} s of it settling: settle_s = {sweep.settle_s:g} s per step "
                    f"(in seconds: {sweep.settle_s:g} ms is {sweep.settle_s / 1e3:g})")
        elif settling > still / 2:
            hint = f"{settling:.1f} s of it settling (settle_s, settle_periods)"
        else:
            hint = "consider a coarser step_hz"
        warnings.append(
            f"sweep: each setup's sweep takes {still:.1f} s, longer than a subject can keep "
            f"still ({MAX_STILL_S:g} s, thesis ch. 6.2); {hint}")
    if sweep.drive_mode == "auto":
        levels = [sweep.drive_vpp_at(f) for f in sweep.frequencies_hz]
        floored = [v for v in levels if v < sweep.min_drive_vpp * (1 - 1e-9)]
        if floored:
            # min_drive_vpp = 1 with drive_vpp = 0.5 passed; auto-ranging then never acted,
            # unsaid (a step at or under the floor is not repeated; one planned at the floor,
            # the generator minimum in the shipped profiles, is meant so; review, session 42)
            warnings.append(
                f"sweep.min_drive_vpp: {sweep.min_drive_vpp:g} Vpp is above the planned "
                f"level of {len(floored)} of {len(levels)} lines (lowest {min(levels):.3g} "
                "Vpp): auto-ranging never lowers those")
    lowest = min(sweep.frequencies_hz)
    if sweep.periods_per_step is not None and sweep.periods_per_step < 10:
        warnings.append(f"sweep.periods_per_step: {sweep.periods_per_step:g} is below the "
                        "10 periods per step of ch. 6.2")
    elif sweep.periods_per_step is None and lowest * ultrasound.pulses / ultrasound.prf_hz < 10:
        warnings.append(f"ultrasound.pulses: the {lowest:g} Hz record holds "
                        f"{lowest * ultrasound.pulses / ultrasound.prf_hz:.3g} periods "
                        "(ch. 6.2 uses 10)")
    aliased = harmonic_aliases(protocol)
    if aliased:
        warnings.append(
            "sweep: at " + ", ".join(f"{f:g} Hz (harmonic {h})" for f, h in aliased[:5])
            + (f" and {len(aliased) - 5} more" if len(aliased) > 5 else "")
            + f" a harmonic of the motion, sampled once per pulse ({ultrasound.prf_hz:g} Hz), "
            "aliases onto the drive frequency and biases its phasor (f = prf/3, prf/4): "
            "move those lines")
    return Protocol(name, description, subject, sweep, ultrasound, tuple(setups), used, text,
                    source, tuple(warnings), excitations)


_TRIGGER_KEYS = {"prf_hz": "ultrasound.prf_hz", "frequency_hz": "ultrasound.prf_hz",
                 "period_s": "ultrasound.prf_hz", "width_s": "ultrasound.trigger_width_s",
                 "edge_s": "ultrasound.trigger_width_s", "high_v": "ultrasound.trigger_high_v",
                 "amplitude_vpp": "ultrasound.trigger_high_v",
                 "offset_v": "ultrasound.trigger_high_v"}
"""The trigger generator's ``check_pulse_burst`` arguments -> the protocol's keys
(``n_pulses``: the record length's key)."""
_DIGITIZER_KEYS = {"channels": "setups", "sample_rate_hz": "ultrasound.sample_rate_hz",
                   "n_samples": "ultrasound.samples", "delay_s": "ultrasound.delay_s",
                   "full_scale_v": "ultrasound.full_scale_v",
                   "offset_v": "ultrasound.offset_v"}
"""The digitizer's ``check_sequence`` arguments -> the protocol's keys (``n_segments``:
the record length's key)."""


def instrument_problems(protocol: Protocol, instruments: Any, bench_name: str) -> list[str]:
    """``KEY: rule`` for every setting of ``protocol`` that one of ``instruments`` (the
    ``InstrumentModel`` of an open bench, :meth:`pelvislab.drivers.bench.Bench.
    instrument_models`, or of a bench file) refuses by its own checks, the ones its
    configuring methods run before sending anything. Empty: every configuration the run
    makes (pulsers; the trigger burst and the digitizer record of every step) passes them."""
    return _instrument_problems(protocol.ultrasound, list(protocol.sweep.frequencies_hz),
                                protocol.sweep.periods_per_step, set(protocol.channels),
                                instruments, bench_name)


def _instrument_problems(us: Ultrasound, frequencies: list[float] | None,
                         periods: float | None, channels: set[int], instruments: Any,
                         bench_name: str) -> list[str]:
    from pelvislab.drivers.interfaces import LimitError

    pulses_key = "sweep.periods_per_step" if periods is not None else "ultrasound.pulses"
    # the record lengths of the plan (largest first), as Protocol.n_pulses counts them
    records: dict[int, float] = {}
    if periods is None:
        records[int(us.pulses)] = math.nan  # every record: no frequency to name
    elif frequencies:
        for f in sorted(frequencies, reverse=True):
            records[int(math.ceil(periods * us.prf_hz / f - 1e-9))] = f
    lengths = sorted(records, reverse=True)
    found: dict[tuple[str, str, str], list[str]] = {}

    def refused(model: Any, keys: Mapping[str, str], call: partial[Any],
                n_pulses: int | None = None) -> bool:
        """Run one check (``call()``); note what it refuses under the protocol's key."""
        try:
            call()
        except LimitError as exc:
            setting = getattr(exc, "setting", None)
            record = setting in ("n_pulses", "n_segments")
            key = pulses_key if record else keys.get(str(setting), "ultrasound")
            text = str(exc)
            if record and n_pulses is not None and math.isfinite(records[n_pulses]):
                text += f" (the record at {records[n_pulses]:g} Hz)"
            found.setdefault((key, model.model, text), []).append(model.role)
            return True
        return False

    for model in instruments:
        role = str(model.role)
        checks = model.checks
        if role.startswith("pulsers"):
            check = getattr(checks, "check_configuration", None)
            if check is not None and (not channels or model.channel in channels):
                refused(model, {k: f"ultrasound.{k}" for k in _US},
                        partial(check, us.gain_db, us.pulse_energy, us.damping_ohm,
                                us.high_pass_hz, us.low_pass_hz))
        elif role == "trigger" and hasattr(checks, "check_pulse_burst"):
            load = model.load_ohm if model.load_ohm is not None else math.inf
            for n in lengths:  # one message per instrument: the longest record first
                if refused(model, _TRIGGER_KEYS,
                           partial(checks.check_pulse_burst, us.prf_hz, n, us.trigger_width_s,
                                   us.trigger_high_v, load_ohm=load, max_vpp=model.max_vpp),
                           n):
                    break
        elif role == "digitizer" and hasattr(checks, "check_sequence"):
            for n in lengths:
                if refused(model, _DIGITIZER_KEYS,
                           partial(checks.check_sequence, sorted(channels) or [1],
                                   us.sample_rate_hz, us.samples, n, us.delay_s,
                                   us.full_scale_v, us.offset_v), n):
                    break
    out = []
    for (key, model_name, text), roles in found.items():
        out.append(f"{key}: the {model_name} ({', '.join(roles)} of {bench_name}) refuses "
                   f"it: {text}")
    return out


def harmonic_aliases(protocol: Protocol, harmonics: tuple[int, ...] = (2, 3)
                     ) -> list[tuple[float, int]]:
    """(frequency Hz, harmonic) of the sweep's lines where a harmonic of the motion at or
    above the pulse rate's Nyquist frequency (``prf_hz / 2``; below it the phasor fits it)
    aliases to within one record bin (1 / record duration) of the line itself, where no fit
    can tell it from the fundamental: f near prf/3 (2nd) or prf/4 (3rd). Measured by a
    review (session 36): at prf/3 a 10 % 2nd harmonic moved the tracked amplitude 9.5 %
    (21 of its std), with nothing flagged."""
    prf = protocol.ultrasound.prf_hz
    out = []
    for f in protocol.sweep.frequencies_hz:
        resolution_hz = prf / protocol.n_pulses(f)
        for h in harmonics:
            if h * f < prf / 2:
                continue
            alias = abs(h * f - round(h * f / prf) * prf)
            if abs(alias - f) < resolution_hz:
                out.append((float(f), h))
    return out


def load_protocol(path: Path | str, limits: BenchLimits | None = None,
                  landmarks: Mapping[str, Point] | None = None) -> Protocol:
    """Read and validate the protocol file ``path`` (see :func:`parse_protocol`)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"protocol file not found: {path}")
    try:
        # "utf-8-sig": an editor's "UTF-8 with BOM" (Windows Notepad) was refused as
        # "not valid TOML: Invalid statement (at line 1, column 1)" (review, session 42)
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ProtocolError(str(path), [f"not a UTF-8 text file (byte {exc.start}): save it "
                                        "as UTF-8"]) from None
    return parse_protocol(text, str(path), limits, landmarks)


def points_array(points: list[Point]) -> tuple[np.ndarray, np.ndarray]:
    """(position_m (n, 3), direction (n, 3)) arrays of ``points``."""
    pos = np.array([pt.position_m for pt in points], dtype=float).reshape(-1, 3)
    dirs = np.array([pt.direction for pt in points], dtype=float).reshape(-1, 3)
    return pos, dirs
