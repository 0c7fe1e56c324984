"""Gap diagnosis (issue 10): candidate forms added after the blind judge-like check
(``tests/judge_like_generator.py``), each against the model core's own extension methods
(extra bodies on springs and dashpots: an independent code path).

* support (bed) contact at a measured point of a bone, not only at its centre of mass,
  and its refined form with the contact damped (fitted from the contact's fit);
* the shaker's moving mass on its suspension between the coil force and the bone, in the
  driven input's column only (support_resonance), and the same lump without suspension
  (soft tissue under the shaker, along its axis);
* one damping coefficient per dashpot (a null extension: verdict ``none``);
* a tissue fitted rigid in the band is a mass, not a tissue.
"""

from __future__ import annotations

import numpy as np

from pelvislab.model.frf import Points, frf
from pelvislab.model.gap import (
    CandidateResult,
    GapOptions,
    _within_tolerance,
    diagnose,
    prepare_data,
)
from pelvislab.model.gap_effects import (
    DAMPED_BED_VARIANT,
    NULL_EXTENSIONS,
    evaluate,
    support_on_line,
)
from pelvislab.model.pelvis import GROUND, Body, Dashpot, Spring
from pelvislab.tests.test_gap_diagnosis import (
    F_HZ,
    IN,
    OUT,
    ctx_for,
    noisy,
    pick,
    true_model,
)


def _on_axis_body(model, name, mass_kg, point_m, axis, links):
    """``model`` with a small body ``name`` at ``point_m`` joined along ``axis`` by
    ``links``: [(other body, k, c)] (other body may be ground)."""
    m = model.with_body(Body(name, mass_kg, point_m, 1e-6 * np.eye(3)))
    for n, (other, k, c) in enumerate(links):
        m = m.with_spring(Spring(f"{name}_k{n}", name, point_m, other, point_m, k, axis=axis))
        if c > 0:
            m = m.with_dashpot(Dashpot(f"{name}_c{n}", name, point_m, other, point_m, c,
                                       axis=axis))
    return m


def test_bed_contact_at_a_measured_point_is_a_support_body_there():
    m = true_model()
    ctx = ctx_for(m)
    cand = pick(ctx, "support_resonance", "innominate_right at sias_R_x x")
    f_s, zeta, mass, kc = 60.0, 0.2, 1.5, 4e5
    ws = 2 * np.pi * f_s
    H, _ = evaluate(ctx, ctx.base.nominal, cand.build(np.log([f_s, zeta, mass, kc]), ctx))
    point = OUT.position_m[1]
    m2 = _on_axis_body(m, "bed", mass, point, np.eye(3)[0],
                       [("innominate_right", kc, 0.0), (GROUND, mass * ws**2,
                                                         2 * zeta * mass * ws)])
    # the bed body's lateral and rotational DOFs carry only their own mass: give them a
    # stiff grounding so that they stay out of the way (they are not coupled anyway)
    for j, axis in enumerate(np.eye(3)[1:]):
        m2 = m2.with_spring(Spring(f"bed_lat{j}", "bed", point, GROUND, point, 1e3,
                                   axis=axis))
    H2 = frf(m2, F_HZ, OUT, IN)
    np.testing.assert_allclose(H, H2, rtol=1e-6, atol=1e-9 * np.abs(H2).max())


def test_a_bed_contacts_refined_form_damps_its_contact():
    """The refined form of a bed contact (fitted from the contact's fit): the same bed
    body touching the bone through a spring and a dashpot, c_c = 2 ζ_c √(k_c m)."""
    m = true_model()
    ctx = ctx_for(m)
    bed = pick(ctx, "support_resonance", "innominate_right at sias_R_x x")
    damped, extra = bed.refined
    assert damped.variant == DAMPED_BED_VARIANT and damped.place == bed.place
    assert damped.labels[:4] == bed.labels and extra.shape == (1,)
    f_s, zeta, mass, kc, zeta_c = 60.0, 0.2, 1.5, 4e5, 0.07
    ws = 2 * np.pi * f_s
    H, _ = evaluate(ctx, ctx.base.nominal,
                    damped.build(np.log([f_s, zeta, mass, kc, zeta_c]), ctx))
    point = OUT.position_m[1]
    m2 = _on_axis_body(m, "bed", mass, point, np.eye(3)[0],
                       [("innominate_right", kc, 2 * zeta_c * np.sqrt(kc * mass)),
                        (GROUND, mass * ws**2, 2 * zeta * mass * ws)])
    for j, axis in enumerate(np.eye(3)[1:]):
        m2 = m2.with_spring(Spring(f"bed_lat{j}", "bed", point, GROUND, point, 1e3,
                                   axis=axis))
    H2 = frf(m2, F_HZ, OUT, IN)
    np.testing.assert_allclose(H, H2, rtol=1e-6, atol=1e-9 * np.abs(H2).max())


def test_support_on_a_fitted_line_is_a_damped_contact_to_a_bed_body():
    # a bed body (mass on its suspension) touching the right innominate at a point no
    # probe measures, through a damped contact, along the line of a spring to ground
    m = true_model()
    ctx = ctx_for(m)
    spring = pick(ctx, "missing_ligament", "innominate_right to ground")
    point = np.array([-0.055, -0.125, 0.005])
    n = np.array([0.2, -0.95, 0.1])
    n /= np.linalg.norm(n)
    f_s, zeta_s, mass, kc, zeta_c = 32.0, 0.03, 2.2, 1.1e6, 0.1
    u_line = np.concatenate([np.sqrt(kc / spring.line_spring.k0_n_per_m) * n,
                             point - spring.line_spring.centre_m])
    cand = support_on_line(spring, u_line, F_HZ)
    assert cand.effect == "support_resonance" and cand.bone == "innominate_right"
    assert cand.n_params == 10 and len(cand.starts) == 36
    u = np.concatenate([u_line, np.log([f_s, zeta_s, mass, zeta_c])])
    H, _ = evaluate(ctx, ctx.base.nominal, cand.build(u, ctx))
    ws = 2 * np.pi * f_s
    m2 = _on_axis_body(m, "bed", mass, point, n,
                       [("innominate_right", kc, 2 * zeta_c * np.sqrt(kc * mass)),
                        (GROUND, mass * ws**2, 2 * zeta_s * mass * ws)])
    for j, axis in enumerate(np.linalg.svd(n[None])[2][1:]):  # the two axes across n
        m2 = m2.with_spring(Spring(f"bed_lat{j}", "bed", point, GROUND, point, 1e3,
                                   axis=axis))
    H2 = frf(m2, F_HZ, OUT, IN)
    np.testing.assert_allclose(H, H2, rtol=1e-6, atol=1e-9 * np.abs(H2).max())
    # its limit without contact damping on a rigid suspension is the spring itself
    u_stiff = np.concatenate([u_line, np.log([3000.0, 0.005, 50.0, 1e-9])])
    H3, _ = evaluate(ctx, ctx.base.nominal, cand.build(u_stiff, ctx))
    H4, _ = evaluate(ctx, ctx.base.nominal, spring.build(u_line, ctx))
    np.testing.assert_allclose(H3, H4, rtol=1e-3, atol=1e-6 * np.abs(H4).max())


def _driven_through(model, j, mass, kt, ct, ks, cs):
    """Setup-wise FRF: column j driven through a mass on (kt, ct) to the bone and (ks, cs)
    to ground along the drive axis; the other columns are the bare model."""
    H = frf(model, F_HZ, OUT, IN)
    point, axis = IN.position_m[j], IN.direction[j] / np.linalg.norm(IN.direction[j])
    links = [(IN.bone[j], kt, ct)] + ([(GROUND, ks, cs)] if ks > 0 else [])
    m2 = _on_axis_body(model, "armature", mass, point, axis, links)
    bones = list(IN.bone)
    bones[j] = "armature"
    H[:, :, j] = frf(m2, F_HZ, OUT, Points(tuple(bones), IN.position_m, IN.direction))[:, :, j]
    return H


def test_shaker_armature_is_a_mass_between_the_coil_force_and_the_bone():
    m = true_model()
    ctx = ctx_for(m)
    mass, f_t, z_t, f_s = 0.12, 140.0, 0.04, 12.0
    wt, ws = 2 * np.pi * f_t, 2 * np.pi * f_s
    cand = pick(ctx, "support_resonance", "sips_L_x", "shaker armature on its suspension")
    assert cand.n_params == 4 and cand.place_kind == "input"
    terms = cand.build(np.log([f_t, z_t, mass, f_s]), ctx)
    H, _ = evaluate(ctx, ctx.base.nominal, terms)
    H2 = _driven_through(m, 1, mass, mass * wt**2, 2 * z_t * mass * wt, mass * ws**2,
                         2 * 0.05 * mass * ws)
    np.testing.assert_allclose(H, H2, rtol=1e-6, atol=1e-9 * np.abs(H2).max())
    # ∂H/∂log θ against central differences (step 1e-4: the sharp armature resonance
    # makes forward differences of 1e-6 round-off limited at ~1e-4)
    theta = ctx.base.nominal * np.linspace(0.8, 1.2, ctx.base.n_params)
    _, dH = evaluate(ctx, theta, terms, jacobian=True)
    for p in (0, 4, 15, 17):
        up, down = theta.copy(), theta.copy()
        up[p] *= np.exp(1e-4)
        down[p] *= np.exp(-1e-4)
        fd = (evaluate(ctx, up, terms)[0] - evaluate(ctx, down, terms)[0]) / 2e-4
        assert np.abs(fd - dH[..., p]).max() < 1e-5 * np.abs(dH[..., p]).max(), p
    # without suspension: tissue under the shaker along its axis
    tissue = pick(ctx, "soft_tissue", "sips_L_x", "tissue under the shaker, along its axis")
    assert tissue.n_params == 3
    Ht, _ = evaluate(ctx, ctx.base.nominal, tissue.build(np.log([f_t, 0.3, mass]), ctx))
    Ht2 = _driven_through(m, 1, mass, mass * wt**2, 2 * 0.3 * mass * wt, 0.0, 0.0)
    np.testing.assert_allclose(Ht, Ht2, rtol=1e-6, atol=1e-9 * np.abs(Ht2).max())


def _per_dashpot(model, values):
    for d in model.dashpots:
        model = model.replace_dashpot(d.name, coefficient_n_s_per_m=values[d.name])
    return model


VALUES = {"S1_R": 400.0, "S2_R": 150.0, "S3_R": 60.0, "S1_L": 900.0, "S2_L": 120.0,
          "S3_L": 40.0, "P1": 20.0, "P2": 1500.0}


def test_per_dashpot_damping_is_the_model_with_each_dashpots_own_coefficient():
    m = true_model()  # every dashpot at 150 N s/m
    ctx = ctx_for(m)
    cand = pick(ctx, "per_dashpot_damping", "all dashpots")
    assert cand.effect in NULL_EXTENSIONS and cand.n_params == 8
    # group coefficients at the smallest of their dashpots, the rest as extras
    theta = ctx.base.nominal.copy()
    names = list(ctx.base.names)
    low = {"c_sij_R": 60.0, "c_sij_L": 40.0, "c_pub": 20.0}
    for n, v in low.items():
        theta[names.index(n)] = v
    order = [d.name for d in m.dashpots]
    group = {d.name: f"c_{d.group}_{d.side}" if d.side else f"c_{d.group}" for d in m.dashpots}
    extra = np.array([max(VALUES[d] - low[group[d]], 1e-3) for d in order])
    H, _ = evaluate(ctx, theta, cand.build(np.log(extra), ctx))
    H2 = frf(_per_dashpot(m, VALUES), F_HZ, OUT, IN)
    # (the extras' lower bound 1e-3 N s/m stands for 0 on the three smallest dashpots)
    assert np.abs(H - H2).max() < 1e-6 * np.abs(H2).max()


def test_per_dashpot_damping_data_are_none():
    # no effect, every dashpot its own coefficient (outside design 4.5's groups): the
    # grouped base leaves a gap, the per-dashpot extension explains it -> none
    rng = np.random.default_rng(4)
    f = np.arange(5.0, 300.1, 2.5)
    H = frf(_per_dashpot(true_model(), VALUES), f, OUT, IN)
    Hn, sigma = noisy(H, rng, rel=0.002)
    opts = GapOptions(effects=("per_dashpot_damping", "hysteretic_damping"), base_starts=2)
    rep = diagnose(prepare_data(f, Hn, sigma, OUT, IN), true_model(), opts).report
    assert rep["gap_before"] > 1.0, rep["gap_before"]
    assert rep["candidates"][0]["effect"] == "per_dashpot_damping"
    assert rep["verdict"] == "none", rep["verdict_reason"]
    assert "each dashpot has its own coefficient" in rep["verdict_reason"]


def test_an_effect_on_per_dashpot_damping_is_named_with_the_extension():
    # hysteretic damping (eq. 7.2, f_c = 1) on a subject whose dashpots differ within a
    # joint: neither the effect nor the extension alone reaches the noise; together they
    # do, and the effect is significant beyond the extension
    rng = np.random.default_rng(5)
    f = np.arange(5.0, 300.1, 2.5)
    model = _per_dashpot(true_model(), VALUES).with_frequency_dependence(f_c=1.0,
                                                                         f_max_hz=f.max())
    H = frf(model, f, OUT, IN)
    Hn, sigma = noisy(H, rng, rel=0.002)
    opts = GapOptions(effects=("per_dashpot_damping", "hysteretic_damping"), base_starts=2)
    rep = diagnose(prepare_data(f, Hn, sigma, OUT, IN), true_model(), opts).report
    assert rep["verdict"] == "hysteretic_damping", rep["verdict_reason"]
    best = rep["candidates"][0]
    assert best["variant"].endswith("+ one coefficient per dashpot")
    assert best["gap_after"] <= 1.0


def test_tissue_rigid_in_the_band_is_a_mass_not_a_tissue():
    # a 130 g mass at a measured point was fitted as "tissue at output" at 5000 Hz (its
    # bound) and beat the point-mass candidate by AIC: rigid in the band, not a tissue
    ctx = ctx_for(true_model())
    tissue = pick(ctx, "soft_tissue", "sias_R_x", "tissue at output")
    opt = GapOptions()

    def note(f_hz):
        res = CandidateResult(tissue, np.log([f_hz, 0.3, 0.13]), np.ones(1), 0, 0, 0, 0, 1)
        return _within_tolerance(res, opt, float(F_HZ.max()))

    assert "added_mass" in note(5000.0)
    assert note(250.0) == ""


def _bed_on_benchmark_layout(point: np.ndarray, axis_index: int, zeta_c: float) -> dict:
    """Diagnosis report (support and ligament candidates only) of a 2.2 kg bed body on a
    32 Hz suspension (ζ 0.03) touching the right innominate at ``point`` along the axis
    ``axis_index`` through 1.1e6 N/m with contact damping ``zeta_c``; a perturbed subject
    (seed 21) on the benchmark layout, every 4th line, 1 % noise."""
    from pelvislab.model.pelvis import default_model
    from pelvislab.tests.benchmarks import bench_gap as bg

    seed = 21
    kc, mass, f_s, zeta_s = 1.1e6, 2.2, 32.0, 0.03
    ws = 2 * np.pi * f_s
    axes = np.eye(3)
    subject = _on_axis_body(bg.perturbed_model(np.random.default_rng(seed)), "bed", mass,
                            point, axes[axis_index],
                            [("innominate_right", kc, 2 * zeta_c * np.sqrt(kc * mass)),
                             (GROUND, mass * ws**2, 2 * zeta_s * mass * ws)])
    for j, across in enumerate(np.delete(axes, axis_index, axis=0)):
        subject = subject.with_spring(Spring(f"bed_lat{j}", "bed", point, GROUND, point, 1e3,
                                             axis=across))
    f = bg.FREQUENCY_HZ[::4]
    H, sigma = noisy(frf(subject, f, bg.OUTPUTS, bg.INPUTS), np.random.default_rng(seed + 1))
    data = prepare_data(f, H, sigma, bg.OUTPUTS, bg.INPUTS)
    return diagnose(data, default_model(),
                    GapOptions(effects=("support_resonance", "missing_ligament"))).report


def test_bed_under_an_unmeasured_point_is_found_on_the_line_of_a_spring_to_ground():
    """Judge-like set 4242_026's support: a bed body of 2.2 kg on a 32 Hz suspension under
    the right iliac fossa (no probe there), in contact through 1.1e6 N/m with ζ 0.1. Before,
    a spring from the sacrum to ground was named (13.1 -> 3.8; the bed contacts at the
    measured points 5.3); refitted along each grounded spring's line as a damped contact,
    the support on the right innominate reaches 0.22 (session 14's machine) or 2.19
    (session 15's, same code: the fit's local minimum depends on the BLAS kernels)."""

    rep = _bed_on_benchmark_layout(np.array([-0.055, -0.125, 0.005]), 1, zeta_c=0.1)
    best = rep["candidates"][0]
    assert rep["verdict"] == "support_resonance", rep["verdict_reason"]
    assert best["variant"] == "bed contact on a fitted line"
    assert best["place"] == "innominate_right to ground"
    assert best["gap_after"] < 3.0, best["gap_after"]
    assert 1.5 < best["params"]["mass_kg"] < 3.0, best["params"]


def test_support_on_a_line_is_not_tried_when_a_support_already_beats_the_spring():
    """A bed body under SIPS_R (a measured point), in contact along x: the bed contact
    there leads (gap 0.17) and a spring to ground is second (15): the stage that refits
    springs to ground as supports on their lines (4-10 s) cannot change that verdict and is
    skipped (judge-like support sets 4242_011/023 and the own generator's support sets
    paid 7-10 s for it)."""

    rep = _bed_on_benchmark_layout(np.array([-0.135, -0.035, -0.005]), 0, zeta_c=0.0)
    best, second = rep["candidates"][:2]
    assert rep["verdict"] == "support_resonance", rep["verdict_reason"]
    assert best["place"] == "innominate_right at SIPS_R_x x" and best["gap_after"] < 1.0
    assert second["effect"] == "missing_ligament" and second["place"].endswith("to ground")
    assert rep["timing_s"]["support_on_line_s"] < 0.01  # the stage did not run


def judge_like_data(seed: int, index: int, tmp_path):
    """Set ``index`` of the judge-like generator's seed ``seed``, written to a file and read
    back as ``gap diagnose`` reads it."""
    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.app.commands.gap import usable_std
    from pelvislab.tests import judge_like_generator as g

    g.write_set(g.make_set(np.random.default_rng([seed, index])), tmp_path / "set.h5")
    frf_set = read_frf(tmp_path / "set.h5")
    H_std, _ = usable_std(frf_set)
    return prepare_data(frf_set.frequency_hz, frf_set.H, H_std, frf_set.outputs,
                        frf_set.inputs)


def test_a_stalled_spring_to_ground_is_refitted_on_the_line_of_its_support(tmp_path):
    """Judge-like set 2468_032: an iliolumbar spring of 9.9e5 N/m from the left innominate
    to ground. The spring's own fit stalled at 4.5e5 N/m (gap 8.8 -> 1.16) and the support
    on its line, a 1.0e6 N/m spring in effect (resonance ~680 Hz, above the band), won at
    0.37; refitted on the support's line with its static stiffness, the spring reaches the
    same gap with 4 parameters fewer and keeps the verdict."""
    from pelvislab.model.pelvis import default_model

    # the spring and the support that won on its line (the whole library gives the same
    # verdict and gap: 34 s against 23 s)
    rep = diagnose(judge_like_data(2468, 32, tmp_path), default_model(),
                   GapOptions(effects=("missing_ligament", "support_resonance"))).report
    best = rep["candidates"][0]
    assert rep["verdict"] == "missing_ligament", rep["verdict_reason"]
    assert best["place"] == "innominate_left to ground"
    assert best["gap_after"] < 0.6, best["gap_after"]
    assert 7e5 < best["params"]["stiffness_n_per_m"] < 1.3e6, best["params"]


def test_a_bed_damped_in_its_contact_is_fitted_to_the_noise(tmp_path):
    """Judge-like set 2121_008: a 1.43 kg bed body under SIAS_R (104 Hz, ζ 0.094 in its
    contact and in its suspension, 2617σ). The undamped bed contact at SIAS_R_x was
    fitted only with one damping per dashpot added, and not to the noise (held-out gap
    1198 -> 63.7); its refined form, the contact damped and fitted from the undamped
    fit, reaches the noise at the truth's mass and contact damping."""
    from pelvislab.model.pelvis import default_model

    rep = diagnose(judge_like_data(2121, 8, tmp_path), default_model(),
                   GapOptions(effects=("support_resonance",))).report
    best = rep["candidates"][0]
    assert rep["verdict"] == "support_resonance", rep["verdict_reason"]
    assert best["place"] == "innominate_right at SIAS_R_x x"
    assert best["variant"].startswith(DAMPED_BED_VARIANT), best["variant"]
    assert best["gap_after"] < 0.5, best["gap_after"]
    assert 1.3 < best["params"]["mass_kg"] < 1.6, best["params"]
    assert 0.08 < best["params"]["contact_damping_ratio"] < 0.11, best["params"]
