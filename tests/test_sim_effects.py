"""Unmodelled effects of the simulated bench: effect_frf against closed forms and limits."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pelvislab.model.frf import Points, frf
from pelvislab.model.pelvis import default_model
from pelvislab.sim_instruments.effects import (
    AddedMass,
    ExtraLigament,
    FrequencyDependentStiffness,
    HystereticDamping,
    SensorMisorientation,
    ShakerDynamics,
    SoftTissue,
    SpeedOfSoundError,
    StaticClutter,
    SubjectDrift,
    SupportResonance,
    effect_frf,
    misoriented_direction,
    split_effects,
)

MODEL = default_model()
OUT = Points(("sacrum", "innominate_right", "innominate_left"),
             [[-0.150, 0.0, -0.055], [-0.135, -0.040, 0.005], [0.0, 0.105, 0.0]],
             [[-1, 0, 0], [-1, 0, 0], [1, 0, 0]], ("sacrum_x", "SIPS_R_x", "SIAS_L_x"))
IN = Points(("innominate_right",), [[0.0, -0.105, 0.0]], [[-1, 0, 0]], ("SIAS_R_x",))
F = np.linspace(5.0, 300.0, 60)
H0 = frf(MODEL, F, OUT, IN)


def rel(a, b):
    return np.max(np.abs(a - b) / np.abs(b))


def test_no_effect_is_the_model():
    assert np.allclose(effect_frf(MODEL, None, F, OUT, IN), H0, rtol=1e-12, atol=0)
    assert np.allclose(effect_frf(MODEL, [], F, OUT, IN), H0, rtol=1e-12, atol=0)


@pytest.mark.parametrize("effect", [
    SupportResonance(), SoftTissue(), FrequencyDependentStiffness(), HystereticDamping(),
    SensorMisorientation(), AddedMass(), ExtraLigament(), ShakerDynamics(),
    SpeedOfSoundError(),
])
def test_every_effect_changes_the_frf_and_leaves_the_model_alone(effect):
    H = effect_frf(MODEL, effect, F, OUT, IN)
    assert H.shape == H0.shape and np.all(np.isfinite(H))
    assert rel(H, H0) > 0.02
    # pure: the nominal model is unchanged
    assert np.allclose(frf(MODEL, F, OUT, IN), H0, rtol=1e-12, atol=0)


def test_soft_tissue_vanishes_when_stiff_and_light():
    e = SoftTissue(stiffness_n_per_m=1e10, damping_n_s_per_m=0.0, mass_kg=1e-6)
    # a 1e-6 kg, 1e10 N/m layer: left is its compliance and mass near resonances
    assert rel(effect_frf(MODEL, e, F, OUT, IN), H0) < 1e-3


@pytest.mark.parametrize("effect", [
    SupportResonance(contact_stiffness_n_per_m=0.0),
    FrequencyDependentStiffness(f_k=0.0),
    HystereticDamping(f_c=0.0, loss_factor=0.0),
    SensorMisorientation(tilt_deg=0.0),
    AddedMass(mass_kg=0.0),
    ExtraLigament(stiffness_n_per_m=0.0),
    ShakerDynamics(amplifier_cutoff_hz=None, armature_mass_kg=0.0,
                   suspension_stiffness_n_per_m=0.0),
    SpeedOfSoundError(relative_error=0.0),
])
def test_each_effect_vanishes_at_its_neutral_setting(effect):
    assert rel(effect_frf(MODEL, effect, F, OUT, IN), H0) < 1e-6


def test_frequency_dependence_is_thesis_eq_7_1():
    H = effect_frf(MODEL, [FrequencyDependentStiffness(f_k=0.4), HystereticDamping(
        f_c=0.7, loss_factor=0.0)], F, OUT, IN)
    expected = frf(MODEL.with_frequency_dependence(f_k=0.4, f_c=0.7, f_max_hz=300.0), F, OUT, IN)
    assert rel(H, expected) < 1e-12


def test_loss_factor_is_complex_stiffness():
    from pelvislab.model.assembly import assemble
    from pelvislab.model.frf import receptance, rows_for

    s = assemble(MODEL)
    expected = receptance(s.M, s.K * (1 + 0.1j), s.C, F, rows_for(MODEL, OUT), rows_for(MODEL, IN))
    H = effect_frf(MODEL, HystereticDamping(loss_factor=0.1), F, OUT, IN)
    assert rel(H, expected) < 1e-12


def test_misorientation_projects_on_the_tilted_beam():
    e = SensorMisorientation(tilt_deg=10.0, azimuth_deg=30.0, outputs=("SIPS_R_x",))
    H = effect_frf(MODEL, e, F, OUT, IN)
    d = OUT.direction.copy()
    d[1] = misoriented_direction(d[1], 10.0, 30.0)
    expected = frf(MODEL, F, Points(OUT.bone, OUT.position_m, d, OUT.name), IN)
    assert rel(H, expected) < 1e-12
    assert np.allclose(H[:, [0, 2]], H0[:, [0, 2]], rtol=1e-12, atol=0)
    assert float(d[1] @ OUT.direction[1]) == pytest.approx(math.cos(math.radians(10.0)))
    surface = effect_frf(MODEL, SensorMisorientation(tilt_deg=10.0, mode="surface"), F, OUT, IN)
    assert np.allclose(surface, H0 / math.cos(math.radians(10.0)), rtol=1e-12, atol=0)


def test_speed_of_sound_error_scales_the_selected_outputs():
    H = effect_frf(MODEL, SpeedOfSoundError(0.05, outputs=("sacrum_x",)), F, OUT, IN)
    assert np.allclose(H[:, 0], H0[:, 0] / 1.05, rtol=1e-12, atol=0)
    assert np.allclose(H[:, 1:], H0[:, 1:], rtol=1e-12, atol=0)


def test_added_mass_equals_heavier_body_at_its_centre_of_mass():
    body = MODEL.body("sacrum")
    e = AddedMass(bone="sacrum", position_m=tuple(body.com_m), mass_kg=0.05)
    H = effect_frf(MODEL, e, F, OUT, IN)
    heavier = MODEL.replace_body("sacrum", mass_kg=body.mass_kg + 0.05)
    assert rel(H, frf(heavier, F, OUT, IN)) < 1e-9


def _point_compliance(p, bone):
    """3x3 compliance at point p, and the maps p <-> outputs / input (m/N), over F."""
    xyz = Points((bone,) * 3, [p] * 3, np.eye(3), ("x", "y", "z"))
    return frf(MODEL, F, xyz, xyz), frf(MODEL, F, OUT, xyz), frf(MODEL, F, xyz, IN)


def test_support_resonance_is_a_grounded_mass_spring_in_contact():
    e = SupportResonance(bone="innominate_right", position_m=(-0.06, -0.07, -0.03), mass_kg=2.0,
                         frequency_hz=60.0, damping_ratio=0.1, contact_stiffness_n_per_m=2e5)
    H = effect_frf(MODEL, e, F, OUT, IN)
    G_pp, G_op, G_pi = _point_compliance(e.position_m, e.bone)
    w = 2 * np.pi * F
    k_g = e.mass_kg * (2 * np.pi * e.frequency_hz) ** 2
    z_g = k_g + 1j * w * 2 * e.damping_ratio * np.sqrt(k_g * e.mass_kg) - w**2 * e.mass_kg
    k_eff = e.contact_stiffness_n_per_m * z_g / (e.contact_stiffness_n_per_m + z_g)
    expected = np.empty_like(H0)
    for j in range(F.size):
        # a grounded isotropic spring k_eff at p: Woodbury update of the receptance
        corr = np.linalg.solve(np.eye(3) + k_eff[j] * G_pp[j], k_eff[j] * G_pi[j])
        expected[j] = H0[j] - G_op[j] @ corr
    assert rel(H, expected) < 1e-6
    # the free-free pelvis is now held at one point (it can still rock about it)
    assert np.abs(H[0]).max() < 0.5 * np.abs(H0[0]).max()


def test_soft_tissue_is_a_mass_on_a_spring_damper_in_series():
    e = SoftTissue(stiffness_n_per_m=3e4, damping_n_s_per_m=15.0, mass_kg=0.04)
    H = effect_frf(MODEL, e, F, OUT, IN)
    G_pp, G_op, _ = _point_compliance(IN.position_m[0], IN.bone[0])
    w = 2 * np.pi * F
    z_s = e.stiffness_n_per_m + 1j * w * e.damping_n_s_per_m
    expected = np.empty_like(H0)
    for j in range(F.size):
        # force reaching the bone: F_b = [I - w^2 m (G_pp + I/z_s)]^-1 e F
        a = np.eye(3) - w[j] ** 2 * e.mass_kg * (G_pp[j] + np.eye(3) / z_s[j])
        f_b = np.linalg.solve(a, IN.direction[0])
        expected[j, :, 0] = G_op[j] @ f_b
    assert rel(H, expected) < 1e-6
    with pytest.raises(ValueError, match="no point named"):
        effect_frf(MODEL, SoftTissue(inputs=("nope",)), F, OUT, IN)


def test_shaker_amplifier_is_a_first_order_low_pass():
    e = ShakerDynamics(amplifier_cutoff_hz=200.0, armature_mass_kg=0.0,
                       suspension_stiffness_n_per_m=0.0)
    H = effect_frf(MODEL, e, F, OUT, IN)
    assert np.allclose(H, H0 / (1 + 1j * F / 200.0)[:, None, None], rtol=1e-12, atol=0)


def test_echo_effects_refuse_the_frf_and_split():
    with pytest.raises(TypeError, match="echo records"):
        effect_frf(MODEL, SubjectDrift(), F, OUT, IN)
    frf_list, echo_list = split_effects([AddedMass(), StaticClutter(), SpeedOfSoundError()])
    assert [type(e) for e in frf_list] == [AddedMass]
    assert [type(e) for e in echo_list] == [StaticClutter, SpeedOfSoundError]


def test_effects_are_reciprocal_where_physics_says_so():
    # structural effects keep the system symmetric: H_ab = H_ba
    pts = Points(("sacrum", "innominate_left"), [[-0.15, 0, -0.055], [0.0, 0.105, 0.0]],
                 [[-1, 0, 0], [1, 0, 0]], ("a", "b"))
    for e in (SupportResonance(), AddedMass(), ExtraLigament(), HystereticDamping(),
              FrequencyDependentStiffness()):
        H = effect_frf(MODEL, e, F, pts, pts)
        assert np.allclose(H[:, 0, 1], H[:, 1, 0], rtol=1e-9, atol=0)
