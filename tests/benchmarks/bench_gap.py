"""Gap diagnosis: withheld-effect self-check (verdict/place accuracy, shrink, time per set).

This module is also the *data generator* of ``pelvislab gap benchmark``: it lives on the
test side because it drives the simulator's independent effect generator
(``pelvislab.sim_instruments.effects.effect_frf``), which product code must not import
(design 3), and because it must share no code with the diagnosis (``pelvislab.model.gap*``)
for the check to be blind. When the simulator's effect module is not available, a
model-based generator built here from ``pelvislab.model.pelvis`` (``with_point_mass``,
``with_spring``, ...) and ``pelvislab.model.frf`` is used instead.

Data sets: the thesis face-up scenario (table 6.3 / protocols/face_up.toml, landmark
catalogue geometry: 3 excitation points x 5 pick-ups = 15 FRFs), 5-300 Hz in 1.5 Hz
steps (197 lines); every mass and spring drawn within +-30 % of appendix E (left and
right independently), every dashpot group log-uniform in [10, 3000] N s/m (far from
appendix E's 0.8); complex Gaussian noise of 0.3-2 % of each FRF's peak, ``H_std`` given
in two of three sets (else the diagnosis estimates the noise). One hidden effect per set,
random kind, size and place; an effect too small to be seen (rms change < 3 sigma on the
measured lines) is redrawn.
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np

from pelvislab.acquisition.frfset import Channels
from pelvislab.model.frf import frf
from pelvislab.model.gap_benchmark import BenchCase
from pelvislab.model.landmarks import load_landmarks
from pelvislab.model.pelvis import GROUND, PelvisModel, PointMass, Spring, default_model
from pelvislab.tests.benchmarks.harness import Result

FREQUENCY_HZ = np.arange(5.0, 300.01, 1.5)

# Face-up scenario of thesis table 6.3 as in protocols/face_up.toml: excitation at S4 and
# both SIPS (x, force into the bone), pick-ups at the drive point and the four SIAS points;
# geometry from the shipped landmark catalogue. 7 outputs x 3 inputs, 15 measured FRFs, the
# other drive-point combinations are NaN (not measured), as in a real session's /frf.
_CAT = load_landmarks()
_OUT_NAMES = ["sacrum_x", "SIPS_R_x", "SIPS_L_x", "SIAS_R_x", "SIAS_L_x", "SIAS_R_y", "SIAS_L_y"]
_IN_NAMES = ["sacrum_x", "SIPS_R_x", "SIPS_L_x"]
OUTPUTS = Channels(_OUT_NAMES, [_CAT[n].bone for n in _OUT_NAMES],
                   np.array([_CAT[n].position_m for n in _OUT_NAMES]),
                   np.array([_CAT[n].direction for n in _OUT_NAMES]))
INPUTS = Channels(_IN_NAMES, [_CAT[n].bone for n in _IN_NAMES],
                  np.array([_CAT[n].position_m for n in _IN_NAMES]),
                  -np.array([_CAT[n].direction for n in _IN_NAMES]))
MEASURED = np.ones((len(_OUT_NAMES), len(_IN_NAMES)), bool)
for _j, _name in enumerate(_IN_NAMES):  # a drive point is picked up only for its own input
    for _o, _oname in enumerate(_OUT_NAMES[:3]):
        MEASURED[_o, _j] = _oname == _name
BONES = ("innominate_right", "innominate_left", "sacrum")
PAIR_JOINT = {frozenset({"innominate_right", "sacrum"}): "sij_right",
              frozenset({"innominate_left", "sacrum"}): "sij_left",
              frozenset({"innominate_right", "innominate_left"}): "pubic"}


def perturbed_model(rng: np.random.Generator) -> PelvisModel:
    """Appendix E with masses and springs within +-30 % and damping far from nominal."""
    m = default_model()
    for b in m.bodies:
        m = m.with_mass(b.name, b.mass_kg * (1 + rng.uniform(-0.3, 0.3)))
    for s in m.springs:
        m = m.replace_spring(s.name,
                             stiffness_n_per_m=s.stiffness_n_per_m * (1 + rng.uniform(-0.3, 0.3)))
    groups = sorted({(d.group, d.side) for d in m.dashpots})
    values = {g: 10 ** rng.uniform(1.0, 3.5) for g in groups}
    for d in m.dashpots:
        m = m.replace_dashpot(d.name, coefficient_n_s_per_m=values[(d.group, d.side)])
    return m


def _random_effect(kind: str, rng: np.random.Generator, model: PelvisModel
                   ) -> tuple[object, str, str, str, dict[str, float]]:
    """A random simulator effect: (effect, place, place_kind, bone, params)."""
    from pelvislab.sim_instruments import effects as fx

    if kind == "support_resonance":
        bone = str(rng.choice(BONES))
        e = fx.SupportResonance(bone=bone, mass_kg=float(rng.uniform(0.5, 4.0)),
                                frequency_hz=float(rng.uniform(15, 150)),
                                damping_ratio=float(rng.uniform(0.05, 0.3)),
                                contact_stiffness_n_per_m=float(10 ** rng.uniform(4.5, 6.0)))
        return e, bone, "bone", bone, {"f_hz": e.frequency_hz, "m_kg": e.mass_kg}
    if kind == "soft_tissue":
        j = int(rng.integers(len(INPUTS)))
        e = fx.SoftTissue(stiffness_n_per_m=float(10 ** rng.uniform(4.3, 5.3)),
                          damping_n_s_per_m=float(rng.uniform(5, 40)),
                          mass_kg=float(rng.uniform(0.02, 0.1)), inputs=(INPUTS.name[j],))
        return e, INPUTS.name[j], "input", INPUTS.bone[j], {"k": e.stiffness_n_per_m}
    if kind == "frequency_dependent_stiffness":
        e = fx.FrequencyDependentStiffness(f_k=float(rng.uniform(2.5, 5.0)),
                                           f_max_hz=float(FREQUENCY_HZ.max()))
        return e, "", "global", "", {"f_k": e.f_k}
    if kind == "hysteretic_damping":
        if rng.uniform() < 0.5:
            e = fx.HystereticDamping(f_c=float(rng.uniform(0.5, 1.0)), loss_factor=0.0,
                                     f_max_hz=float(FREQUENCY_HZ.max()))
        else:
            e = fx.HystereticDamping(f_c=0.0, loss_factor=float(rng.uniform(0.03, 0.15)),
                                     f_max_hz=float(FREQUENCY_HZ.max()))
        return e, "", "global", "", {"f_c": e.f_c, "loss_factor": e.loss_factor}
    if kind == "sensor_misorientation":
        o = int(rng.integers(len(OUTPUTS)))
        e = fx.SensorMisorientation(tilt_deg=float(rng.uniform(8, 30)),
                                    azimuth_deg=float(rng.uniform(0, 360)),
                                    mode=str(rng.choice(["projection", "surface"])),
                                    outputs=(OUTPUTS.name[o],))
        return e, OUTPUTS.name[o], "output", OUTPUTS.bone[o], {"tilt_deg": e.tilt_deg}
    if kind == "added_mass":
        bone = str(rng.choice(BONES))
        p = model.body(bone).com_m + rng.uniform(-0.03, 0.03, 3)
        e = fx.AddedMass(bone=bone, position_m=tuple(float(x) for x in p),
                         mass_kg=float(rng.uniform(0.08, 0.3)))
        return e, bone, "bone", bone, {"m_kg": e.mass_kg}
    if kind == "missing_ligament":
        a, b = _ligament_ends(rng, model)
        e = fx.ExtraLigament(name="extra", body_a=a[0], point_a_m=tuple(a[1]), body_b=b[0],
                             point_b_m=tuple(b[1]),
                             stiffness_n_per_m=float(10 ** rng.uniform(4.7, 5.7)))
        return e, *_ligament_place(a[0], b[0]), {"k": e.stiffness_n_per_m}
    raise ValueError(f"unknown effect kind {kind!r}")


def _ligament_ends(rng: np.random.Generator, model: PelvisModel
                   ) -> tuple[tuple[str, np.ndarray], tuple[str, np.ndarray]]:
    side = rng.choice([-1.0, 1.0])
    inn = "innominate_right" if side < 0 else "innominate_left"
    choice = rng.integers(3)
    if choice == 0:  # sacrotuberous/sacrospinous-like: sacrum low to the ischium
        pa = np.array([-0.150, 0.015 * side, -0.060]) + rng.uniform(-0.01, 0.01, 3)
        pb = np.array([-0.110, 0.055 * side, -0.150]) + rng.uniform(-0.02, 0.02, 3)
        return ("sacrum", pa), (inn, pb)
    if choice == 1:  # an extra sacroiliac band
        pa = np.array([-0.095, 0.030 * side, 0.010]) + rng.uniform(-0.015, 0.015, 3)
        pb = pa + rng.normal(size=3) * 0.02 * np.array([1, 1, 1])
        return (inn, pb), ("sacrum", pa)
    # iliolumbar-like: innominate crest to an immobile L5 (ground)
    pa = np.array([-0.110, 0.060 * side, 0.060]) + rng.uniform(-0.01, 0.01, 3)
    pb = np.array([-0.110, 0.015 * side, 0.090])
    return (inn, pa), (GROUND, pb)


def _ligament_place(a: str, b: str) -> tuple[str, str, str]:
    if b == GROUND:
        return a, "bone", a
    joint = PAIR_JOINT[frozenset({a, b})]
    inn = a if a.startswith("innominate") else b
    return joint, "joint", inn


def _model_effect_frf(kind: str, rng: np.random.Generator, model: PelvisModel
                      ) -> tuple[np.ndarray, str, str, str, dict[str, float]]:
    """Fallback generator without the simulator: structural effects through the model's
    own extension methods, chain effects applied to the FRF."""
    f = FREQUENCY_HZ
    if kind == "support_resonance":
        bone = str(rng.choice(BONES))
        fs = rng.uniform(15, 100)
        mt = sum(b.mass_kg for b in model.bodies)
        k = mt * (2 * np.pi * fs) ** 2
        m2 = model.with_grounding(bone, k, coefficient_n_s_per_m=2 * 0.15 * mt * 2 * np.pi * fs)
        return frf(m2, f, OUTPUTS, INPUTS), bone, "bone", bone, {"f_hz": fs}
    if kind == "added_mass":
        bone = str(rng.choice(BONES))
        p = model.body(bone).com_m + rng.uniform(-0.03, 0.03, 3)
        m2 = model.with_point_mass(PointMass("extra", bone, p, rng.uniform(0.08, 0.3)))
        return frf(m2, f, OUTPUTS, INPUTS), bone, "bone", bone, {}
    if kind == "missing_ligament":
        a, b = _ligament_ends(rng, model)
        m2 = model.with_spring(Spring("extra", a[0], a[1], b[0], b[1],
                                      10 ** rng.uniform(4.7, 5.7)))
        return frf(m2, f, OUTPUTS, INPUTS), *_ligament_place(a[0], b[0]), {}
    if kind == "frequency_dependent_stiffness":
        m2 = model.with_frequency_dependence(f_k=rng.uniform(2.5, 5.0), f_max_hz=f.max())
        return frf(m2, f, OUTPUTS, INPUTS), "", "global", "", {}
    if kind == "hysteretic_damping":
        m2 = model.with_frequency_dependence(f_c=rng.uniform(0.5, 1.0), f_max_hz=f.max())
        return frf(m2, f, OUTPUTS, INPUTS), "", "global", "", {}
    if kind == "sensor_misorientation":
        o = int(rng.integers(len(OUTPUTS)))
        d = OUTPUTS.direction.copy()
        ax = rng.normal(size=3)
        ax -= (ax @ d[o]) * d[o]
        ax /= np.linalg.norm(ax)
        t = np.radians(rng.uniform(8, 30))
        d[o] = np.cos(t) * d[o] + np.sin(t) * ax
        outs = Channels(OUTPUTS.name, OUTPUTS.bone, OUTPUTS.position_m, d)
        return frf(model, f, outs, INPUTS), OUTPUTS.name[o], "output", OUTPUTS.bone[o], {}
    if kind == "soft_tissue":
        j = int(rng.integers(len(INPUTS)))
        ft, z = rng.uniform(60, 250), rng.uniform(0.1, 0.4)
        wn, w = 2 * np.pi * ft, 2 * np.pi * f
        T = (wn**2 + 2j * z * wn * w) / (wn**2 + 2j * z * wn * w - w**2)
        H = frf(model, f, OUTPUTS, INPUTS)
        H[:, :, j] *= T[:, None]
        return H, INPUTS.name[j], "input", INPUTS.bone[j], {}
    raise ValueError(f"unknown effect kind {kind!r}")


def sim_available() -> bool:
    """Whether the simulator's independent effect generator can be imported."""
    try:
        from pelvislab.sim_instruments.effects import effect_frf  # noqa: F401
    except ImportError:
        return False
    return True


def make_generator(source: str = "auto", seed: int = 1
                   ) -> tuple[Callable[[str, int], BenchCase], str]:
    """The benchmark's data generator ``(kind, index) -> BenchCase`` and its description."""
    use_sim = sim_available() if source == "auto" else source == "sim"
    if use_sim and not sim_available():
        raise ValueError("the simulator's effect generator (sim_instruments.effects) is not "
                         "available; use --source model")

    def generate(kind: str, index: int) -> BenchCase:
        code = sum(ord(c) for c in kind) * 1000 + index
        rng = np.random.default_rng([seed, code])
        model = perturbed_model(rng)
        H0 = frf(model, FREQUENCY_HZ, OUTPUTS, INPUTS)
        rel = 10 ** rng.uniform(np.log10(0.003), np.log10(0.02))
        sigma = rel * np.max(np.abs(H0), axis=0, keepdims=True) * np.ones(H0.shape)
        place, place_kind, bone, params = "", "global", "", {}
        H = H0
        if kind != "none":
            for _ in range(20):
                if use_sim:
                    from pelvislab.sim_instruments.effects import effect_frf

                    eff, place, place_kind, bone, params = _random_effect(kind, rng, model)
                    H = effect_frf(model, eff, FREQUENCY_HZ, OUTPUTS, INPUTS)
                else:
                    H, place, place_kind, bone, params = _model_effect_frf(kind, rng, model)
                change = (np.abs(H - H0) ** 2 / sigma**2)[:, MEASURED]
                if np.sqrt(np.mean(change)) >= 3.0:
                    break
        noise = sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
        with_std = index % 3 != 2
        Hm = np.where(MEASURED[None], H + noise, np.nan + 0j)
        sm = np.where(MEASURED[None], sigma, np.nan)
        return BenchCase(FREQUENCY_HZ.copy(), Hm, sm if with_std else None,
                         OUTPUTS, INPUTS, kind, place, place_kind, bone,
                         {k: float(v) for k, v in params.items()})

    name = ("sim_instruments.effects.effect_frf" if use_sim
            else "test-side model generator (pelvis.with_*, model.frf)")
    return generate, name


# --------------------------------------------------------------------------- full chain
CHAIN_STEP_HZ = 5.0
"""Line spacing of the full-chain cases: face_up on a 5 Hz grid (60 lines, 5-300 Hz)."""
CHAIN_PERIODS = 5
"""Drive periods per step in the full-chain cases (face_up uses 10)."""


def chain_protocol_text(step_hz: float = CHAIN_STEP_HZ, periods: int = CHAIN_PERIODS,
                        stop_hz: float | None = None) -> str:
    """protocols/face_up.toml (thesis table 6.3, 9 setups, 15 FRFs) on a coarser grid."""
    import re
    from importlib import resources

    text = (resources.files("pelvislab.protocols") / "face_up.toml").read_text()
    text, n1 = re.subn(r"(?m)^step_hz = .*$", f"step_hz = {step_hz!r}", text)
    text, n2 = re.subn(r"(?m)^periods_per_step = .*$", f"periods_per_step = {int(periods)}",
                       text)
    n3 = 1
    if stop_hz is not None:
        text, n3 = re.subn(r"(?m)^stop_hz = .*$", f"stop_hz = {float(stop_hz)!r}", text)
    if (n1, n2, n3) != (1, 1, 1):
        raise ValueError("protocols/face_up.toml changed: cannot set the chain grid")
    return text


def _apply_named_effects_where_placed(bench: object, effects: list[object]) -> None:
    """Work around the simulator raising when an effect names a point that the current
    setup does not use (``SoftTissue(inputs=...)`` with the shaker elsewhere,
    ``SensorMisorientation(outputs=...)`` with that transducer unplaced): the runner's
    simulated operator calls ``bench.place`` when the bench has one, so this bench gets a
    ``place`` that moves the world and then keeps only the effects whose named points are
    placed (the tilted transducer or the tissue under the shaker go with their point)."""
    world = bench.world  # type: ignore[attr-defined]

    def active() -> list[object]:
        outputs = {c.landmark.name for c in world.channels.values()}
        inputs = {world.excitation.name}
        keep = []
        for e in effects:
            named_out = getattr(e, "outputs", None)
            named_in = getattr(e, "inputs", None)
            if named_out is not None and not set(named_out) <= outputs:
                continue
            if named_in is not None and not set(named_in) <= inputs:
                continue
            keep.append(e)
        return keep

    def place(**kwargs: object) -> None:
        with world._lock:  # the FRF cache is per layout: swap the effects with the layout
            world.place(**kwargs)
            world.frf_effects = active()

    with world._lock:
        world.frf_effects = active()
    bench.place = place  # type: ignore[attr-defined]


def make_chain_generator(seed: int = 1, step_hz: float = CHAIN_STEP_HZ,
                         periods: int = CHAIN_PERIODS, stop_hz: float | None = None,
                         workdir: str | None = None) -> Callable[[str, int], BenchCase]:
    """Full-chain data sets ``(kind, index) -> BenchCase`` (``source="chain"``).

    Each case opens the simulated bench (``open_simulated_bench``) on a random subject
    (:func:`perturbed_model`: +-30 % masses/springs, damping far from appendix E) with one
    hidden effect from :func:`_random_effect` (none for ``"none"``), runs the face-up
    protocol on a coarse grid (:func:`chain_protocol_text`) through the product's
    ``prepare_session`` into a temporary session file: drive, ultrasound echoes, tracking,
    phasors, auto-ranging and /frf as in a real session. The case carries that file's /frf
    (``read_frf``, as ``diagnose_file`` reads it) and its path is not kept. The effect size
    is redrawn (up to 20 times) until the effect changes the model FRF by >= 3 sigma rms on
    the protocol's lines with sigma = 1 % of each FRF's peak (the chain's noise is not
    known before the run).
    """
    import tempfile
    from pathlib import Path

    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.acquisition.runner import prepare_session
    from pelvislab.sim_instruments.bench import open_simulated_bench
    from pelvislab.sim_instruments.effects import effect_frf

    text = chain_protocol_text(step_hz, periods, stop_hz)

    def generate(kind: str, index: int) -> BenchCase:
        code = sum(ord(c) for c in kind) * 1000 + index
        rng = np.random.default_rng([seed, 7919, code])
        model = perturbed_model(rng)
        place, place_kind, bone, params = "", "global", "", {}
        effects: list[object] = []
        if kind != "none":
            f = np.arange(5.0, (stop_hz or 300.0) + 1e-9, step_hz)
            H0 = frf(model, f, OUTPUTS, INPUTS)
            sigma = 0.01 * np.max(np.abs(H0), axis=0, keepdims=True)
            for _ in range(20):
                eff, place, place_kind, bone, params = _random_effect(kind, rng, model)
                H = effect_frf(model, eff, f, OUTPUTS, INPUTS)
                if np.sqrt(np.mean((np.abs(H - H0) ** 2 / sigma**2)[:, MEASURED])) >= 3.0:
                    break
            effects = [eff]
        sim_seed = int(rng.integers(2**31))
        with tempfile.TemporaryDirectory(dir=workdir) as tmp:
            proto = Path(tmp) / "face_up_chain.toml"
            proto.write_text(text)
            out = Path(tmp) / "session.h5"
            t0 = time.perf_counter()
            bench = open_simulated_bench(model=model, effects=effects, seed=sim_seed,
                                         generators="python")
            _apply_named_effects_where_placed(bench, effects)
            with prepare_session(proto, out, bench=bench) as prepared:
                final = prepared.run()
            if final.status != "completed":
                raise RuntimeError(f"chain case {kind} #{index}: run {final.status}: "
                                   f"{final.reason}")
            run_s = time.perf_counter() - t0
            measured = read_frf(out)
        params = {k: float(v) for k, v in params.items()}
        params["chain_run_s"] = round(run_s, 2)
        return BenchCase(measured.frequency_hz, measured.H, measured.H_std, measured.outputs,
                         measured.inputs, kind, place, place_kind, bone, params,
                         source="chain", truth_model=model)

    return generate


def run() -> list[Result]:
    """A small benchmark (1 set per kind + 1 without effect) through the CLI in a
    subprocess (one BLAS thread, as the command sets it): accuracy and time per set."""
    import json
    import os
    import subprocess
    import sys
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "gap-bench.json")
        env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "pelvislab.app", "gap", "benchmark", "--json",
                        out, "--cases", "1", "--seed", "7"], check=True, env=env)
        wall = time.perf_counter() - t0
        with open(out) as fh:
            res = json.load(fh)
    return [
        Result("gap: verdict accuracy (8 sets)", res["verdict_accuracy"], "frac",
               target=">= 0.9"),
        Result("gap: place accuracy, local effects", res["place_accuracy_local"] or 0.0, "frac",
               target=">= 0.8"),
        Result("gap: median shrink, correct verdicts", res["shrink_correct"]["median"] or 0.0,
               "frac", target=">= 0.7"),
        Result("gap: false none", res["false_none"], "sets", target="0"),
        Result("gap: median wall time per set (15 FRF x 197 lines)",
               res["wall_time_s"]["median"], "s", target="<= 60"),
        Result("gap: median CPU time per set", res["cpu_time_s"]["median"], "s"),
        Result("gap: total benchmark wall time", wall, "s"),
    ]
