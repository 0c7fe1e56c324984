"""Effects the nominal pelvis model lacks, switchable and parameterised (one dataclass each).

Two families:

- **FRF effects** change what a perfect ultrasound chain would measure: the structure
  (support/fixture resonance, soft tissue under the shaker, frequency-dependent stiffness,
  hysteretic damping, added mass, an extra ligament, shaker/amplifier dynamics) or the
  measurement geometry and scale (sensor misorientation, speed-of-sound error). They are all
  available through one pure function, :func:`effect_frf`, which the gap-diagnosis benchmark
  uses to generate withheld-effect data *independently of the diagnosis code* (this module
  imports nothing from ``pelvislab.model.gap*``).
- **Echo effects** act on the raw records only (static clutter, drift of the subject); the
  simulated bench applies them in the echo synthesis. A speed-of-sound error acts on both:
  the echoes travel at the true speed, the tracker converts with the assumed one.

Names (``kind``) follow design 4.4: ``support_resonance``, ``soft_tissue``,
``frequency_dependent_stiffness``, ``hysteretic_damping``, ``sensor_misorientation``,
``added_mass``, ``missing_ligament``; plus ``speed_of_sound_error``, ``shaker_dynamics``,
``static_clutter``, ``subject_drift``.

Conventions: design 4.1 (frame, x(t) = Re(X e^{+i omega t}), H in m/N, output direction from
the bone toward the sensor).
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

import numpy as np

from pelvislab.model.assembly import assemble
from pelvislab.model.frf import Points, PointsLike, receptance, rows_for
from pelvislab.model.pelvis import GROUND, Body, Dashpot, PelvisModel, PointMass, Spring

__all__ = [
    "ECHO_EFFECTS",
    "FRF_EFFECTS",
    "AddedMass",
    "Effect",
    "ExtraLigament",
    "FrequencyDependentStiffness",
    "HystereticDamping",
    "SensorMisorientation",
    "ShakerDynamics",
    "SoftTissue",
    "SpeedOfSoundError",
    "StaticClutter",
    "SubjectDrift",
    "SupportResonance",
    "effect_frf",
    "misoriented_direction",
    "split_effects",
]

_XYZ = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))


# --------------------------------------------------------------------------- FRF effects
@dataclass(frozen=True)
class SupportResonance:
    """The exam bed / fixture under the subject: a mass on a grounded spring, in contact
    with a bone at a point.

    A rigid support body of ``mass_kg`` sits on ground springs tuned to ``frequency_hz``
    (k = m (2 pi f)^2 per axis, viscous damping ratio ``damping_ratio``) and touches
    ``bone`` at ``position_m`` through contact springs of ``contact_stiffness_n_per_m`` per
    axis. ``position_m`` None = the bone's centre of mass.
    """

    kind = "support_resonance"
    bone: str = "sacrum"
    position_m: tuple[float, float, float] | None = None
    mass_kg: float = 2.0
    frequency_hz: float = 60.0
    damping_ratio: float = 0.1
    contact_stiffness_n_per_m: float = 2e5


@dataclass(frozen=True)
class SoftTissue:
    """Soft tissue between the shaker tip and the bone at the excitation point(s).

    The shaker pushes on a tissue mass ``mass_kg`` coupled to the bone by a spring
    ``stiffness_n_per_m`` and a dashpot ``damping_n_s_per_m`` on each axis; the force reaching
    the bone is therefore filtered (a tissue resonance near sqrt(k/m)/2 pi). ``inputs``: names
    of the affected inputs (None = all).
    """

    kind = "soft_tissue"
    stiffness_n_per_m: float = 5e4
    damping_n_s_per_m: float = 20.0
    mass_kg: float = 0.05
    inputs: tuple[str, ...] | None = None


@dataclass(frozen=True)
class FrequencyDependentStiffness:
    """Stiffness growing linearly with frequency, thesis eq. 7.1 and 7.3: K' = f_k K/(4 w_max)."""

    kind = "frequency_dependent_stiffness"
    f_k: float = 0.5
    f_max_hz: float = 300.0


@dataclass(frozen=True)
class HystereticDamping:
    """Frequency-independent (hysteretic) damping.

    ``f_c``: thesis eq. 7.1-7.2, D = f_c C w_max / 4 (proportional to the dashpots);
    ``loss_factor``: structural damping eta K of every spring (the classical hysteretic
    model, useful when the dashpots are weak, as in appendix E).
    """

    kind = "hysteretic_damping"
    f_c: float = 0.0
    loss_factor: float = 0.05
    f_max_hz: float = 300.0


@dataclass(frozen=True)
class SensorMisorientation:
    """A transducer tilted by ``tilt_deg`` from its nominal axis.

    ``mode="projection"``: the echo tracks the bone motion along the tilted beam axis (the
    nominal axis rotated by ``tilt_deg`` toward the azimuth ``azimuth_deg``, measured in the
    plane perpendicular to the nominal axis from the projection of +z, or +x when the axis is
    vertical). ``mode="surface"``: thesis fig. 6.9, a flat reflector moving along its normal
    d reads d / cos(tilt). ``outputs``: names of the affected outputs (None = all).
    """

    kind = "sensor_misorientation"
    tilt_deg: float = 8.0
    azimuth_deg: float = 0.0
    mode: Literal["projection", "surface"] = "projection"
    outputs: tuple[str, ...] | None = None


@dataclass(frozen=True)
class AddedMass:
    """A lumped mass rigidly attached to ``bone`` at ``position_m`` (e.g. a fixture, a sensor)."""

    kind = "added_mass"
    bone: str = "innominate_left"
    position_m: tuple[float, float, float] = (-0.06, 0.09, -0.03)
    mass_kg: float = 0.1


@dataclass(frozen=True)
class ExtraLigament:
    """A spring the nominal model does not have (design 4.4 name ``missing_ligament``).

    The default is an estimate of the right sacrotuberous ligament (sacrum near S4-S5 to the
    ischial tuberosity; thesis ch. 5.3 and 11 explain why the model omits it), with the
    stiffness of table 7.1 (k_st = 8e4 N/m). ``body_b = "ground"`` grounds it (e.g. an
    iliolumbar ligament to an immobile L5).
    """

    kind = "missing_ligament"
    name: str = "sacrotuberous_R"
    body_a: str = "sacrum"
    point_a_m: tuple[float, float, float] = (-0.150, -0.015, -0.060)
    body_b: str = "innominate_right"
    point_b_m: tuple[float, float, float] = (-0.110, -0.055, -0.150)
    stiffness_n_per_m: float = 8e4


@dataclass(frozen=True)
class ShakerDynamics:
    """The drive chain between generator volts and force on the structure.

    First-order amplifier roll-off at ``amplifier_cutoff_hz`` (None = flat), and the
    shaker's moving armature (``armature_mass_kg``) on its suspension
    (``suspension_stiffness_n_per_m``) attached at the excitation point along the drive
    direction: both load the structure there. The bench calibration only knows the
    nominal N/V constant.
    """

    kind = "shaker_dynamics"
    amplifier_cutoff_hz: float | None = 1000.0
    armature_mass_kg: float = 0.02
    suspension_stiffness_n_per_m: float = 2e3


@dataclass(frozen=True)
class SpeedOfSoundError:
    """The true speed of sound differs from the one the tracker assumes.

    ``relative_error`` = c_true / c_assumed - 1. Echo delays follow c_true, the tracker
    converts with c_assumed, so every displacement (and FRF) of the affected ``outputs``
    (names, or digitizer channel numbers as strings "1", "2"; None = all) reads
    1 / (1 + relative_error) times the truth.
    """

    kind = "speed_of_sound_error"
    relative_error: float = 0.03
    outputs: tuple[str, ...] | None = None


# --------------------------------------------------------------------------- echo effects
@dataclass(frozen=True)
class StaticClutter:
    """Echoes that do not move with the bone (reverberation in a stand-off, a fixed reflector).

    ``depth_m``: apparent depth of each clutter echo (round trip at the true speed of sound);
    ``level_db``: its peak relative to the bone echo; ``channels``: digitizer channels (None =
    all).
    """

    kind = "static_clutter"
    depth_m: tuple[float, ...] = (14.9e-3,)
    level_db: tuple[float, ...] = (-12.0,)
    channels: tuple[int, ...] | None = None


@dataclass(frozen=True)
class SubjectDrift:
    """Slow motion of the subject along each beam during the sweep (breathing excluded).

    Depth change (positive = away from the transducer) = ``rate_m_per_s`` * t plus a random
    walk of ``random_walk_m_per_sqrt_s`` (per sqrt second) plus an optional breathing-like
    sinusoid (``breathing_amplitude_m`` at ``breathing_hz``). ``channels``: None = all.
    """

    kind = "subject_drift"
    rate_m_per_s: float = 20e-6
    random_walk_m_per_sqrt_s: float = 5e-6
    breathing_amplitude_m: float = 0.0
    breathing_hz: float = 0.25
    channels: tuple[int, ...] | None = None
    seed: int = 0


FRF_EFFECTS = (SupportResonance, SoftTissue, FrequencyDependentStiffness, HystereticDamping,
               SensorMisorientation, AddedMass, ExtraLigament, ShakerDynamics, SpeedOfSoundError)
ECHO_EFFECTS = (StaticClutter, SubjectDrift, SpeedOfSoundError)
Effect = (SupportResonance | SoftTissue | FrequencyDependentStiffness | HystereticDamping
          | SensorMisorientation | AddedMass | ExtraLigament | ShakerDynamics
          | SpeedOfSoundError | StaticClutter | SubjectDrift)


def split_effects(effects: Iterable[Any]) -> tuple[list[Any], list[Any]]:
    """(FRF effects, echo effects) of a list; a speed-of-sound error goes to the echo list
    (the bench realises it through the echo delays, not through the FRF)."""
    frf_list: list[Any] = []
    echo_list: list[Any] = []
    for e in effects:
        if isinstance(e, ECHO_EFFECTS):
            echo_list.append(e)
        elif isinstance(e, FRF_EFFECTS):
            frf_list.append(e)
        else:
            raise TypeError(f"not a simulated-bench effect: {e!r}")
    return frf_list, echo_list


# --------------------------------------------------------------------------- the FRF
@dataclass(frozen=True)
class _Chain:
    """What an FRF effect may change: the model, the points, per-point gains, eta."""

    model: PelvisModel
    outputs: Points
    inputs: Points
    out_names: tuple[str, ...]
    in_names: tuple[str, ...]
    out_gain: tuple[Any, ...]  # callables f_hz -> complex array, one per effect
    in_gain: tuple[Any, ...]
    loss_factor: float = 0.0


def _points(p: PointsLike) -> tuple[Points, tuple[str, ...]]:
    names = tuple(getattr(p, "name", ()) or ())
    pts = Points(tuple(p.bone), np.asarray(p.position_m), np.asarray(p.direction),
                 names if names else ())
    return pts, pts.name


def _select(names: tuple[str, ...], wanted: tuple[str, ...] | None, what: str) -> np.ndarray:
    if wanted is None:
        return np.ones(len(names), dtype=bool)
    unknown = sorted(set(wanted) - set(names))
    if unknown:
        raise ValueError(f"{what}: no point named {unknown} (have {list(names)})")
    return np.array([n in wanted for n in names])


def _small_body(name: str, mass_kg: float, position_m: np.ndarray, radius_m: float) -> Body:
    inertia = 0.4 * mass_kg * radius_m**2 * np.eye(3)  # a small solid sphere
    return Body(name, mass_kg, position_m, inertia)


def _unique(model: PelvisModel, stem: str) -> str:
    names = set(model.body_names) | {s.name for s in model.springs}
    k = 0
    while f"{stem}_{k}" in names:
        k += 1
    return f"{stem}_{k}"


def misoriented_direction(nominal: np.ndarray, tilt_deg: float, azimuth_deg: float) -> np.ndarray:
    """The unit beam axis after tilting ``nominal`` by ``tilt_deg`` toward ``azimuth_deg``.

    Azimuth 0 is the projection of +z on the plane normal to ``nominal`` (+x when nominal is
    vertical); positive azimuth turns about ``nominal`` (right hand).
    """
    n = np.asarray(nominal, dtype=float)
    n = n / np.linalg.norm(n)
    ref = np.array([0.0, 0.0, 1.0]) if abs(n[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    e1 = ref - (ref @ n) * n
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    az = math.radians(azimuth_deg)
    perp = math.cos(az) * e1 + math.sin(az) * e2
    t = math.radians(tilt_deg)
    return math.cos(t) * n + math.sin(t) * perp


def _apply(chain: _Chain, effect: Any) -> _Chain:
    model = chain.model
    if isinstance(effect, SupportResonance):
        body = model.body(effect.bone)
        p = body.com_m if effect.position_m is None else np.asarray(effect.position_m, float)
        name = _unique(model, "support")
        model = model.with_body(_small_body(name, effect.mass_kg, p, 0.05))
        k_g = effect.mass_kg * (2 * math.pi * effect.frequency_hz) ** 2
        c_g = 2 * effect.damping_ratio * math.sqrt(k_g * effect.mass_kg)
        for j, ax in enumerate(_XYZ):
            axis = np.asarray(ax)
            model = model.with_spring(Spring(f"{name}_ground_{j}", name, p, GROUND, p, k_g,
                                             axis=axis))
            if c_g > 0:
                model = model.with_dashpot(Dashpot(f"{name}_ground_{j}", name, p, GROUND, p,
                                                   c_g, axis=axis))
            model = model.with_spring(Spring(f"{name}_contact_{j}", effect.bone, p, name, p,
                                             effect.contact_stiffness_n_per_m, axis=axis))
        return replace(chain, model=model)
    if isinstance(effect, SoftTissue):
        sel = _select(chain.in_names, effect.inputs, "soft_tissue.inputs")
        bones = list(chain.inputs.bone)
        for i in np.nonzero(sel)[0]:
            bone = bones[i]
            if bone in ("", GROUND):
                continue
            p = chain.inputs.position_m[i]
            name = _unique(model, "soft_tissue")
            model = model.with_body(_small_body(name, effect.mass_kg, p, 0.01))
            for j, ax in enumerate(_XYZ):
                axis = np.asarray(ax)
                model = model.with_spring(Spring(f"{name}_k{j}", bone, p, name, p,
                                                 effect.stiffness_n_per_m, axis=axis))
                if effect.damping_n_s_per_m > 0:
                    model = model.with_dashpot(Dashpot(f"{name}_c{j}", bone, p, name, p,
                                                       effect.damping_n_s_per_m, axis=axis))
            bones[i] = name
        inputs = Points(tuple(bones), chain.inputs.position_m, chain.inputs.direction,
                        chain.in_names)
        return replace(chain, model=model, inputs=inputs)
    if isinstance(effect, FrequencyDependentStiffness):
        fd = model.frequency_dependence
        return replace(chain, model=model.with_frequency_dependence(
            f_k=fd.f_k + effect.f_k, f_c=fd.f_c, f_max_hz=effect.f_max_hz))
    if isinstance(effect, HystereticDamping):
        fd = model.frequency_dependence
        if effect.f_c:
            model = model.with_frequency_dependence(f_k=fd.f_k, f_c=fd.f_c + effect.f_c,
                                                    f_max_hz=effect.f_max_hz)
        return replace(chain, model=model, loss_factor=chain.loss_factor + effect.loss_factor)
    if isinstance(effect, SensorMisorientation):
        sel = _select(chain.out_names, effect.outputs, "sensor_misorientation.outputs")
        direction = chain.outputs.direction.copy()
        gains = np.ones(len(chain.out_names))
        for i in np.nonzero(sel)[0]:
            if effect.mode == "projection":
                direction[i] = misoriented_direction(direction[i], effect.tilt_deg,
                                                     effect.azimuth_deg)
            elif effect.mode == "surface":
                gains[i] = 1.0 / math.cos(math.radians(effect.tilt_deg))
            else:
                raise ValueError(f"sensor_misorientation.mode: unknown {effect.mode!r}")
        outputs = Points(chain.outputs.bone, chain.outputs.position_m, direction,
                         chain.out_names)
        gain = _constant(gains)
        return replace(chain, outputs=outputs, out_gain=(*chain.out_gain, gain))
    if isinstance(effect, AddedMass):
        name = _unique(model, "added_mass")
        return replace(chain, model=model.with_point_mass(
            PointMass(name, effect.bone, np.asarray(effect.position_m, float), effect.mass_kg)))
    if isinstance(effect, ExtraLigament):
        spring = Spring(effect.name, effect.body_a, np.asarray(effect.point_a_m, float),
                        effect.body_b, np.asarray(effect.point_b_m, float),
                        effect.stiffness_n_per_m)
        return replace(chain, model=model.with_spring(spring))
    if isinstance(effect, ShakerDynamics):
        for i, bone in enumerate(chain.inputs.bone):
            if bone in ("", GROUND):
                continue
            p = chain.inputs.position_m[i]
            d = chain.inputs.direction[i]
            if effect.armature_mass_kg > 0:
                model = model.with_point_mass(PointMass(_unique(model, "armature"), bone, p,
                                                        effect.armature_mass_kg))
            if effect.suspension_stiffness_n_per_m > 0:
                model = model.with_spring(Spring(_unique(model, "suspension"), bone, p, GROUND,
                                                 p, effect.suspension_stiffness_n_per_m,
                                                 axis=d))
        cutoff = effect.amplifier_cutoff_hz

        def amplifier(f: np.ndarray, n: int = len(chain.in_names)) -> np.ndarray:
            g = np.ones(f.shape, complex) if cutoff is None else 1.0 / (1.0 + 1j * f / cutoff)
            return np.repeat(g[:, None], n, axis=1)

        return replace(chain, model=model, in_gain=(*chain.in_gain, amplifier))
    if isinstance(effect, SpeedOfSoundError):
        sel = _select(chain.out_names, effect.outputs, "speed_of_sound_error.outputs")
        gains = np.where(sel, 1.0 / (1.0 + effect.relative_error), 1.0)
        return replace(chain, out_gain=(*chain.out_gain, _constant(gains)))
    if isinstance(effect, StaticClutter | SubjectDrift):
        raise TypeError(f"{effect.kind} acts on the echo records, not on the FRF: simulate "
                        "it on the bench (open_simulated_bench(effects=[...]))")
    raise TypeError(f"not a simulated-bench effect: {effect!r}")


def _constant(gains: np.ndarray) -> Any:
    def gain(f: np.ndarray) -> np.ndarray:
        return np.broadcast_to(gains.astype(complex), (f.size, gains.size))

    return gain


def effect_frf(model: PelvisModel, effect: Any | Sequence[Any] | None,
               frequency_hz: np.ndarray, outputs: PointsLike, inputs: PointsLike) -> np.ndarray:
    """Receptance (m/N, (n_f, n_out, n_in) complex) the bench would measure with ``effect``.

    ``effect``: None (the nominal model), one FRF effect, or a sequence applied in order.
    ``outputs`` / ``inputs``: points with ``bone``, ``position_m``, ``direction`` and,
    for effects that select points by name, ``name`` (``Channels`` or
    ``pelvislab.model.frf.Points``). Pure: ``model`` is not modified.
    The structural part uses ``pelvislab.model`` (assembly and eq. 4.54 / 7.1 receptance);
    measurement-chain gains multiply the result per output and per input.
    """
    f = np.asarray(frequency_hz, dtype=float).reshape(-1)
    out_pts, out_names = _points(outputs)
    in_pts, in_names = _points(inputs)
    chain = _Chain(model, out_pts, in_pts, out_names, in_names, (), ())
    if effect is None:
        effects: Sequence[Any] = ()
    elif isinstance(effect, Sequence) and not isinstance(effect, str):
        effects = effect
    else:
        effects = (effect,)
    for e in effects:
        chain = _apply(chain, e)
    s = assemble(chain.model)
    K = s.K * (1.0 + 1j * chain.loss_factor) if chain.loss_factor else s.K
    H = receptance(s.M, K, s.C, f, rows_for(chain.model, chain.outputs),
                   rows_for(chain.model, chain.inputs), s.f_k, s.f_c, s.f_max_hz)
    for g in chain.out_gain:
        H = H * g(f)[:, :, None]
    for g in chain.in_gain:
        H = H * g(f)[:, None, :]
    return H
