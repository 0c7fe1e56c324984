"""Gap diagnosis (issue 10): the soft-tissue candidates against the model core's own
extension methods (a tissue body on springs and dashpots: an independent code path), and
a small diagnosis of tissue under the shaker.

In a session the FRF is measured setup by setup with the shaker at one input each (thesis
table 6.3): tissue between the shaker and the bone filters only that input's column and
loads the bone only while the shaker pushes there. The full simulated chain produces
exactly that (docs/gap-diagnosis.md, full-chain soft-tissue sets); a candidate that keeps
the tissue attached in every column left most of that gap (31 -> 21 sigma)."""

from __future__ import annotations

import numpy as np

from pelvislab.model.frf import Points, frf
from pelvislab.model.gap import GapOptions, _context, diagnose, prepare_data
from pelvislab.model.gap_effects import candidate_library, evaluate
from pelvislab.model.pelvis import Body, Dashpot, Spring, default_model
from pelvislab.tests.test_gap_diagnosis import (
    F_HZ,
    IN,
    OUT,
    assert_jacobian_matches_differences,
)

# tissue: k, c, m -> f_t = sqrt(k/m)/2 pi ~ 159 Hz, zeta = c / (2 sqrt(k m)) = 0.075
K_T, C_T, M_T = 1.0e5, 15.0, 0.1
U_T = np.log([np.sqrt(K_T / M_T) / (2 * np.pi), C_T / (2 * np.sqrt(K_T * M_T)), M_T])


def true_model():
    """Appendix E with a few parameters moved and damping far from nominal."""
    m = default_model()
    m = m.with_mass("sacrum", 0.36 * 1.15)
    m = m.replace_spring("io_R", stiffness_n_per_m=1.2e6)
    for d in m.dashpots:
        m = m.replace_dashpot(d.name, coefficient_n_s_per_m=150.0)
    return m


def with_tissue(model, bone, point_m):
    """``model`` with a tissue body at ``point_m`` on ``bone`` (spring + dashpot per axis)."""
    m = model.with_body(Body("tissue", M_T, point_m, 0.4 * M_T * 0.01**2 * np.eye(3)))
    for j, axis in enumerate(np.eye(3)):
        m = m.with_spring(Spring(f"tissue_k{j}", bone, point_m, "tissue", point_m, K_T,
                                 axis=axis))
        m = m.with_dashpot(Dashpot(f"tissue_c{j}", bone, point_m, "tissue", point_m, C_T,
                                   axis=axis))
    return m


def driven_through_tissue(model, j, f=F_HZ):
    """Setup-wise FRF: column j (or every column for ``j=None``) driven through tissue
    under the shaker, the other columns measured in setups without it (the bare bone)."""
    H = frf(model, f, OUT, IN)
    for jj in range(len(IN.name)) if j is None else (j,):
        bones = list(IN.bone)
        bones[jj] = "tissue"
        H_j = frf(with_tissue(model, IN.bone[jj], IN.position_m[jj]), f, OUT,
                  Points(tuple(bones), IN.position_m, IN.direction))
        H[:, :, jj] = H_j[:, :, jj]
    return H


def ctx_for(model):
    data = prepare_data(F_HZ, np.ones((F_HZ.size, 3, 2), complex), np.ones((F_HZ.size, 3, 2)),
                        OUT, IN)
    return _context(model, data)


def pick(ctx, variant, place):
    for c in candidate_library(ctx, ("soft_tissue",)):
        if c.variant == variant and c.place == place:
            return c
    raise AssertionError(f"no soft_tissue candidate {variant!r} at {place}")


def test_tissue_at_input_is_a_tissue_body_attached_in_every_column():
    m = true_model()
    ctx = ctx_for(m)
    H, _ = evaluate(ctx, ctx.base.nominal, pick(ctx, "tissue at input", "sips_L_x")
                    .build(U_T, ctx))
    bones = list(IN.bone)
    bones[1] = "tissue"
    H2 = frf(with_tissue(m, IN.bone[1], IN.position_m[1]), F_HZ, OUT,
             Points(tuple(bones), IN.position_m, IN.direction))
    np.testing.assert_allclose(H, H2, rtol=1e-6, atol=1e-9 * np.abs(H2).max())


def test_tissue_under_the_shaker_acts_only_in_its_inputs_setups():
    m = true_model()
    ctx = ctx_for(m)
    cand = pick(ctx, "tissue under the shaker", "sips_L_x")
    assert cand.n_params == 3 and cand.place_kind == "input"
    H, _ = evaluate(ctx, ctx.base.nominal, cand.build(U_T, ctx))
    H2 = driven_through_tissue(m, 1)
    np.testing.assert_allclose(H, H2, rtol=1e-6, atol=1e-9 * np.abs(H2).max())
    # the other input's column is the bare bone, unlike the attached-tissue variant
    np.testing.assert_allclose(H[:, :, 0], frf(m, F_HZ, OUT, IN)[:, :, 0], rtol=1e-9)
    # "all inputs": one shared tissue under the shaker at every driven input
    both = pick(ctx, "tissue under the shaker, every input", "all inputs")
    assert both.place_kind == "global" and both.n_params == 3
    Hb, _ = evaluate(ctx, ctx.base.nominal, both.build(U_T, ctx))
    H3 = driven_through_tissue(m, 0)
    np.testing.assert_allclose(Hb[:, :, 0], H3[:, :, 0], rtol=1e-6,
                               atol=1e-9 * np.abs(H3).max())
    np.testing.assert_allclose(Hb[:, :, 1], H2[:, :, 1], rtol=1e-6,
                               atol=1e-9 * np.abs(H2).max())


def test_jacobian_with_per_input_stiffness_matches_finite_differences():
    m = true_model()
    ctx = ctx_for(m)
    theta = ctx.base.nominal * np.linspace(0.8, 1.2, ctx.base.n_params)
    terms = pick(ctx, "tissue under the shaker", "sips_R_x").build(U_T, ctx)
    H, _ = evaluate(ctx, theta, terms, jacobian=True)
    H0, _ = evaluate(ctx, theta, terms)
    np.testing.assert_allclose(H, H0, rtol=1e-12)
    assert_jacobian_matches_differences(ctx, theta, terms)


def _diagnose_tissue(j):
    rng = np.random.default_rng(12)
    H = driven_through_tissue(true_model(), j)
    sigma = 0.001 * np.max(np.abs(H), axis=0, keepdims=True) * np.ones(H.shape)
    Hn = H + sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
    data = prepare_data(F_HZ, Hn, sigma, OUT, IN)
    opts = GapOptions(effects=("soft_tissue", "added_mass"), base_starts=1, max_nfev_joint=40,
                      max_nfev_short=8, finish_jobs=2)
    rep = diagnose(data, default_model(), opts).report
    print(rep["gap_before"], [(c["variant"], c["place"], c["gap_after"])
                              for c in rep["candidates"]])
    assert rep["gap_before"] > 3.0
    assert rep["verdict"] == "soft_tissue", rep["verdict_reason"]
    best = rep["candidates"][0]
    assert best["shrink"] > 0.9
    assert abs(best["params"]["frequency_hz"] / np.exp(U_T[0]) - 1) < 0.05
    return best


def test_tissue_under_the_shaker_is_diagnosed_with_its_place_and_shrink():
    best = _diagnose_tissue(1)
    assert best["variant"] == "tissue under the shaker" and best["place"] == "sips_L_x"


def test_tissue_under_the_shaker_at_every_input_is_diagnosed():
    best = _diagnose_tissue(None)
    assert best["variant"] == "tissue under the shaker, every input"


def test_every_tissue_variant_gets_a_joint_fit():
    """Seed-4242 soft-tissue set #2 of the benchmark (simulator's tissue at input sacrum_x,
    attached in every column): the base fit absorbs the tissue's mass, the screen costs of
    the tissue variants differ by < 0.4 % and the exact variant ranked third. When only the
    two best-screened variants were fitted, an added mass won (tissue under the shaker
    left 0.098)."""
    from pelvislab.tests.benchmarks.bench_gap import make_generator

    gen, _ = make_generator("auto", 4242)
    case = gen("soft_tissue", 2)
    data = prepare_data(case.frequency_hz, case.H, case.H_std, case.outputs, case.inputs)
    rep = diagnose(data, default_model(),
                   GapOptions(effects=("soft_tissue", "added_mass"))).report
    assert rep["verdict"] == "soft_tissue", rep["verdict_reason"]
    tissue = next(c for c in rep["candidates"] if c["effect"] == "soft_tissue")
    assert (tissue["variant"], tissue["place"]) == ("tissue at input", case.place)
    assert tissue["gap_after"] < 0.05


def test_tissue_above_the_band_that_a_rigid_mass_matches_is_the_mass(tmp_path):
    """Judge-like set 1357_7 (blind generator): 339 g rigidly at SIPS_L_x, nine-point
    layout to 300 Hz. A tissue of 0.34 kg resonating at 321 Hz (zeta 0.02) and the point
    mass at the true point fit the held-out lines alike (chi2 310.5 / 310.4); AIC named the
    tissue. Above the band a tissue shows no compliance, so the mass is named."""
    from pelvislab.app.commands.gap import diagnose_file
    from pelvislab.tests import judge_like_generator as jl

    path = tmp_path / "set_1357_007.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([1357, 7])), path)
    assert truth["effect"] == "added_mass"
    # the two effects that tied (the whole library gives the same: 23 s against 8 s)
    report = diagnose_file(path, effects=("soft_tissue", "added_mass")).to_json()
    assert report["verdict"] == "added_mass", report["verdict_reason"]
    tissue = next(c for c in report["candidates"] if c["effect"] == "soft_tissue")
    assert tissue["within_tolerance"] and "no compliance shown" in tissue["within_tolerance"]
    mass = next(c for c in report["candidates"] if c["effect"] == "added_mass")
    assert mass["place"] == "innominate_left"


def test_tissue_is_compared_with_a_mass_fitted_the_same_way():
    """The tissue-above-the-band rule compares a tissue with the added mass fitted the
    same way: with one damping per dashpot both or neither (that extension alone lowers
    the held-out chi2, so a mixed pair compares unlike models)."""
    from pelvislab.model.gap import CandidateResult, _best_like

    lib = {c.effect: c for c in candidate_library(ctx_for(default_model()))}
    tissue_c, mass_c = lib["soft_tissue"], lib["added_mass"]

    def res(cand, score, beyond_null=None):
        return CandidateResult(cand, np.zeros(cand.n_params), np.ones(3), 100.0, 0.5, score,
                               score, 1, beyond_null=beyond_null)

    mass_plain, mass_ext = res(mass_c, 120.0), res(mass_c, 90.0, beyond_null=5.0)
    tissue_plain, tissue_ext = res(tissue_c, 110.0), res(tissue_c, 95.0, beyond_null=3.0)
    results = [mass_plain, mass_ext, tissue_plain, tissue_ext]
    assert _best_like(results, "added_mass", tissue_plain) is mass_plain
    assert _best_like(results, "added_mass", tissue_ext) is mass_ext
    assert _best_like([mass_ext], "added_mass", tissue_plain) is None
