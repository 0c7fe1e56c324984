"""Local effects a base fit absorbs (issue 10): the missing-ligament line-spring geometry
behind its linearised start, the cheap Jacobian of ΔZ-only effects, noise that varies along
frequency, and a ligament and an added mass that the base fit absorbs being found at
their place."""

from __future__ import annotations

import numpy as np

from pelvislab.model.frf import frf
from pelvislab.model.gap import GapOptions, _Lines, diagnose, prepare_data
from pelvislab.model.gap_effects import (
    line_spring_basis,
    line_spring_parameters,
    line_spring_rows,
)
from pelvislab.model.pelvis import Spring, default_model
from pelvislab.tests.test_gap_diagnosis import F_HZ, IN, OUT, ctx_for, noisy, pick, true_model


def _spring_g(ctx, place, point_a, point_b, k):
    """g = √k nᵀ (G_a(p_a) − G_b(p_b)) of a spring between two points (eq. 4.12-4.13)."""
    n = (point_b - point_a) / np.linalg.norm(point_b - point_a)
    ga = ctx.base.rows([place.bone_a] * 3, np.tile(point_a, (3, 1)), np.eye(3))
    gb = (ctx.base.rows([place.bone_b] * 3, np.tile(point_b, (3, 1)), np.eye(3))
          if place.bone_b else 0.0)
    return np.sqrt(k) * (n @ (ga - gb))


def test_line_spring_basis_spans_every_line_and_parameters_round_trip():
    ctx = ctx_for(true_model())
    rng = np.random.default_rng(3)
    for place_name in ("sij_right", "pubic", "sacrum to ground"):
        cand = pick(ctx, "missing_ligament", place_name)
        place = cand.line_spring
        Q = line_spring_basis(ctx.base, place)
        assert Q.shape[0] == 6
        for _ in range(3):
            pa = place.centre_m + rng.uniform(-0.03, 0.03, 3)
            pb = pa + rng.normal(size=3) * 0.05
            g = _spring_g(ctx, place, pa, pb, 1e5)
            assert np.linalg.norm(g - Q.T @ (Q @ g)) < 1e-9 * np.linalg.norm(g)
            u, misfit = line_spring_parameters(ctx.base, place, g)
            assert misfit < 1e-6
            dK = cand.build(u, ctx).dZ[0].real
            assert np.allclose(dK, np.outer(g, g), rtol=0, atol=1e-6 * np.max(np.abs(dK)))
        # the rows are those of the relative motion at the point
        G = line_spring_rows(ctx.base, place, place.centre_m)
        assert G.shape == (3, ctx.base.n_dof)


def _diagnose_spring_to_ground(seed, bone, bone_point_m, ground_point_m, k_n_per_m):
    """Diagnosis (ligament candidates only) of a benchmark subject drawn with ``seed`` plus
    a spring from ``bone`` to ground, on every 4th line of the benchmark grid, 1 % noise
    (seed + 1)."""
    from pelvislab.tests.benchmarks import bench_gap as bg

    subject = bg.perturbed_model(np.random.default_rng(seed)).with_spring(Spring(
        "iliolumbar", bone, np.array(bone_point_m), "ground", np.array(ground_point_m),
        k_n_per_m))
    f = bg.FREQUENCY_HZ[::4]
    H, sigma = noisy(frf(subject, f, bg.OUTPUTS, bg.INPUTS), np.random.default_rng(seed + 1))
    H = np.where(bg.MEASURED[None], H, np.nan + 0j)
    sigma = np.where(bg.MEASURED[None], sigma, np.nan)
    data = prepare_data(f, H, sigma, bg.OUTPUTS, bg.INPUTS)
    return diagnose(data, default_model(), GapOptions(effects=("missing_ligament",))).report


def test_ligament_absorbed_by_the_base_fit_is_found_at_its_bone():
    """An iliolumbar-like spring to ground (3.8e5 N/m) on a subject ±30 % from appendix E:
    the base fit absorbs part of it in the left joint's springs. Started only from the
    frozen-base screen the ligament went to the sacrum (gap 1.09 -> 0.61); with the
    linearised start from the undistorted stiffness it is on the left innominate."""
    rep = _diagnose_spring_to_ground(5, "innominate_left", [-0.11878395, 0.06111192, 0.05542903],
                                     [-0.11, 0.015, 0.09], 379884.15)
    best = rep["candidates"][0]
    assert rep["verdict"] == "missing_ligament", rep["verdict_reason"]
    assert best["place"] == "innominate_left to ground"
    assert best["shrink"] > 0.5


def test_spring_to_ground_with_a_resonance_in_the_band_is_found_from_its_axis_starts():
    """An iliolumbar spring of 6e5 N/m from the right innominate to ground (judge-like set
    1357_009's geometry) puts a suspension resonance near 100 Hz: far beyond the linearised
    start, from which the fit stalled at the base gap (1.50 -> 1.30, `unexplained`); the
    place's own axis starts reach 0.21."""
    rep = _diagnose_spring_to_ground(11, "innominate_right", [-0.1177, -0.0550, 0.0496],
                                     [-0.1091, -0.0333, 0.0755], 5.97e5)
    best = rep["candidates"][0]
    assert rep["verdict"] == "missing_ligament", rep["verdict_reason"]
    assert best["place"] == "innominate_right to ground"
    assert best["shrink"] > 0.6


def test_dZ_only_jacobian_matches_differences_of_the_whole_model():
    """The cheap Jacobian of ΔZ-only effects (ligament, added mass, bed support) against
    forward differences of the full FRF model, base and effect parameters alike."""
    from pelvislab.model.gap import _Model, _only_dZ

    ctx = ctx_for(true_model())
    data = prepare_data(F_HZ, np.ones((F_HZ.size, 3, 2), complex), np.ones((F_HZ.size, 3, 2)),
                        OUT, IN)
    lines = _Lines.build(ctx, data, np.ones(F_HZ.size, bool))
    theta = ctx.base.nominal * np.linspace(0.8, 1.2, ctx.base.n_params)
    checked = 0
    for effect, place in (("missing_ligament", "sij_left"), ("added_mass", "sacrum"),
                          ("support_resonance", "innominate_right xyz")):
        cand = pick(ctx, effect, place)
        u = cand.starts[-1] + 0.01
        assert _only_dZ(cand.build(u, ctx))
        model = _Model(lines, cand, None, theta.size)
        x = np.concatenate([np.log(theta), u])
        J = model.jacobian(x)
        r0 = model.residual(x)
        for k in (0, 5, theta.size, x.size - 1):
            h = 1e-6 * max(1.0, abs(x[k]))
            xk = x.copy()
            xk[k] += h
            fd = (model.residual(xk) - r0) / h
            assert np.max(np.abs(J[:, k] - fd)) < 1e-3 * np.max(np.abs(fd)) + 1e-9, (effect, k)
        checked += 1
    assert checked == 3


def test_noise_estimate_follows_noise_that_varies_along_frequency():
    """σ from running third differences follows noise 20x larger at the low end (a drive
    profile) and noise proportional to |H|, where one σ per FRF is > 3x worse in mean
    |e|²/σ²; constant noise keeps one σ per FRF."""
    from pelvislab.model.gap import estimate_noise

    rng = np.random.default_rng(11)
    f = np.arange(5.0, 300.1, 1.0)
    H = frf(true_model(), f, OUT, IN)
    peak = np.max(np.abs(H), axis=0, keepdims=True)
    shapes = {"drive profile": 0.002 * peak * (1 + 19 * np.exp(-(f - 5.0) / 30.0))[:, None, None],
              "relative": 0.01 * np.abs(H)}
    for name, sigma in shapes.items():
        e = sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
        est = estimate_noise(H + e)
        z2 = np.mean(np.abs(e) ** 2 / est**2)
        one = estimate_noise(H + e, noise_form_gain=np.inf)  # one σ per FRF
        z2_one = np.mean(np.abs(e) ** 2 / one**2)
        ratio = np.median(est / sigma)
        assert 0.6 < z2 < 2.5 and 0.75 < ratio < 1.33 and z2_one > 3 * z2, (name, z2, z2_one)
    # constant noise keeps one σ per FRF
    sigma = 0.01 * peak * np.ones(H.shape)
    e = sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
    est = estimate_noise(H + e)
    assert np.all(np.ptp(est, axis=0) == 0.0)


def test_added_mass_absorbed_by_the_base_fit_is_found_on_its_bone():
    """Benchmark set seed 4242, added mass #0 (right innominate), every 3rd line: from the
    fitted base only, the mass went to the left innominate (gap 0.75 -> 0.65, verdict
    none); from the undistorted stiffness it is on the right one."""
    from pelvislab.tests.benchmarks.bench_gap import make_generator

    case = make_generator("sim", 4242)[0]("added_mass", 0)
    lines = slice(None, None, 3)
    data = prepare_data(case.frequency_hz[lines], case.H[lines],
                        None if case.H_std is None else case.H_std[lines],
                        case.outputs, case.inputs)
    rep = diagnose(data, default_model(), GapOptions(effects=("added_mass",))).report
    assert case.place == "innominate_right"
    assert rep["verdict"] == "added_mass", rep["verdict_reason"]
    assert rep["candidates"][0]["place"] == "innominate_right"



def test_spring_between_bones_screened_behind_another_joint_is_found():
    """Benchmark set seed 31337, ligament #1 (1.34e5 N/m across the left sacroiliac joint,
    all 197 lines): no local start reached it (best 1.14 after a base gap of 2.27,
    verdict unexplained); the global line search of the springs between bones, run only
    before that verdict, found it at its joint near the noise. Since a026161 the screened
    start at sij_left (not the best-screened joint) reaches it first and the search does
    not run (no end-to-end case of it is left)."""
    from pelvislab.tests.benchmarks.bench_gap import make_generator

    case = make_generator("sim", 31337)[0]("missing_ligament", 1)
    data = prepare_data(case.frequency_hz, case.H, case.H_std, case.outputs, case.inputs)
    rep = diagnose(data, default_model(), GapOptions(effects=("missing_ligament",))).report
    assert case.place == "sij_left"
    assert rep["verdict"] == "missing_ligament", rep["verdict_reason"]
    assert rep["candidates"][0]["place"] == "sij_left"
    assert rep["candidates"][0]["gap_after"] < 0.5


def test_global_search_finds_a_spring_between_bones_that_the_joint_fits_missed(monkeypatch):
    """The search of the springs between bones along their lines, run when no candidate
    has come near the noise (``_line_search_stage(between_bones=True)``), on every other
    line of the set above (99 lines: 49 -> 28 s of CPU) with the joint fits' springs
    between bones taken away (as they were before a026161: no local start reached the
    spring). The springs to ground and their search stay; the pair search must find the
    spring at its joint (gap 0.34; with the pair search returning nothing the verdict is
    ``unexplained``, a spring to ground leading at 1.76)."""
    from pelvislab.model import gap
    from pelvislab.tests.benchmarks.bench_gap import make_generator

    case = make_generator("sim", 31337)[0]("missing_ligament", 1)
    lines = slice(None, None, 2)
    data = prepare_data(case.frequency_hz[lines], case.H[lines], case.H_std[lines],
                        case.outputs, case.inputs)
    joint_fit_stage, searches = gap._joint_fit_stage, []

    def without_springs_between_bones(*args, **kwargs):
        return [res for res in joint_fit_stage(*args, **kwargs)
                if not (res.candidate.line_spring and res.candidate.line_spring.bone_b)]

    def recorded(search):
        def run(*args, between_bones=False, **kwargs):
            new = search(*args, between_bones=between_bones, **kwargs)
            searches.append((between_bones, len(new)))
            return new
        return run

    monkeypatch.setattr(gap, "_joint_fit_stage", without_springs_between_bones)
    monkeypatch.setattr(gap, "_line_search_stage", recorded(gap._line_search_stage))
    rep = diagnose(data, default_model(), GapOptions(effects=("missing_ligament",))).report
    assert searches[-1][0] and searches[-1][1] > 0  # the pair search ran and fitted
    assert "pair_search_s" in rep["timing_s"]
    assert rep["verdict"] == "missing_ligament", rep["verdict_reason"]
    best = rep["candidates"][0]
    assert best["place"] == "sij_left" and best["variant"] == "extra spring"
    assert best["gap_after"] < 0.5


def test_noise_estimate_is_not_switched_by_one_outlier_nor_by_unmeasured_lines():
    """One line 50σ off, a block of unmeasured lines or an all-zero FRF must not turn
    constant noise into a varying σ (found in review: before the cap, one spike switched
    every FRF and σ ranged 0.01-61x the truth)."""
    from pelvislab.model.gap import estimate_noise

    rng = np.random.default_rng(4)
    f = np.arange(5.0, 300.1, 1.0)
    H = frf(true_model(), f, OUT, IN)
    sigma = 0.01 * np.max(np.abs(H), axis=0, keepdims=True) * np.ones(H.shape)
    Hn = H + sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
    Hn[140] += 50 * sigma[140]
    Hn[60:100, 0, 0] = np.nan
    Hn[:, 2, 1] = 0.0
    est = estimate_noise(Hn)
    measured = np.isfinite(Hn)
    for o in range(3):
        for i in range(2):
            if o == 2 and i == 1:
                assert np.all(est[:, o, i] == 0.0)
                continue
            e = est[measured[:, o, i], o, i]
            assert np.ptp(e) == 0.0, (o, i)  # one σ kept
            assert 0.85 < e[0] / sigma[0, o, i] < 1.2, (o, i)


def test_strong_ligament_on_the_full_chain_is_found_at_its_joint():
    """A full-chain session (seed 1, sacrotuberous-like 1.36e5 N/m, sacrum to left
    innominate; /frf stored in tests/data): the base fit drives c_sij_L to x8500 and three
    left springs to x26-34. From the fitted damping the ligament stayed at the pubic joint
    (36.6 -> 35.3); the second undistorted start (damping refitted at nominal stiffness)
    finds it at the left sacroiliac joint."""
    from pathlib import Path

    from pelvislab.acquisition.frfset import read_frf

    s = read_frf(Path(__file__).parent / "data" / "chain_ligament_sij_left.h5")
    data = prepare_data(s.frequency_hz, s.H, s.H_std, s.outputs, s.inputs)
    rep = diagnose(data, default_model(), GapOptions(effects=("missing_ligament",))).report
    best = rep["candidates"][0]
    assert best["place"] == "sij_left"
    assert best["shrink"] > 0.6


def test_frequency_dependent_stiffness_on_the_full_chain_is_found():
    """Full-chain seed 3, f_k = 4.36 (eq. 7.3; /frf in tests/data): from the fitted base
    (springs stiffened to absorb it) f_k fitted 2.17, gap 31.9 -> 18.1 (unexplained); from
    the undistorted stiffness with refitted damping 4.27, -> 7.7."""
    from pathlib import Path

    from pelvislab.acquisition.frfset import read_frf

    s = read_frf(Path(__file__).parent / "data" / "chain_fk_seed3.h5")
    data = prepare_data(s.frequency_hz, s.H, s.H_std, s.outputs, s.inputs)
    rep = diagnose(data, default_model(),
                   GapOptions(effects=("frequency_dependent_stiffness",))).report
    best = rep["candidates"][0]
    assert best["shrink"] > 0.6
    assert 3.5 < best["params"]["f_k"] < 5.0


def test_dense_grid_ranks_starts_on_every_other_line_with_the_same_result():
    """Above ``dense_lines`` fitted lines (100 here, to keep the test short; 300 by
    default) the short fits that rank the starts use every other fitted line: same
    verdict, place and gap as with all lines."""
    from pelvislab.model.pelvis import PointMass

    f = np.arange(5.0, 300.1, 1.5)
    subject = true_model().with_point_mass(
        PointMass("extra", "innominate_left", np.array([-0.05, 0.09, 0.02]), 0.25))
    H, sigma = noisy(frf(subject, f, OUT, IN), np.random.default_rng(8))
    data = prepare_data(f, H, sigma, OUT, IN)
    reps = [diagnose(data, default_model(), GapOptions(effects=("added_mass",),
                                                       dense_lines=n)).report
            for n in (100, 10**9)]
    for rep in reps:
        assert rep["verdict"] == "added_mass", rep["verdict_reason"]
        assert rep["candidates"][0]["place"] == "innominate_left"
    assert abs(reps[0]["candidates"][0]["gap_after"] - reps[1]["candidates"][0]["gap_after"]) < 0.2


def test_ligament_at_a_joint_screened_behind_another_gets_the_base_fit_start():
    """Full-chain seed 3, ligament #0 (8.2e4 N/m, sacrum to left innominate; /frf in
    tests/data): the base fit ends with five springs at the updating bounds and the pubic
    joint screens ahead of sij_left. With only its linearised starts the sij_left spring's
    short fit ended at robust cost 5.5e4 and its finish at held-out chi2 2.4e6 (the base
    has 2.2e5); the full diagnosis named a support under the sacrum (gap 31 -> 7.6), this
    one (ligaments and supports only) failed too. Started also from the screened spring
    with the base fit, it ends at chi2 246 (gap -> 0.3)."""
    from pathlib import Path

    from pelvislab.acquisition.frfset import read_frf

    s = read_frf(Path(__file__).parent / "data" / "chain_ligament_seed3.h5")
    data = prepare_data(s.frequency_hz, s.H, s.H_std, s.outputs, s.inputs)
    rep = diagnose(data, default_model(),
                   GapOptions(effects=("missing_ligament", "support_resonance"))).report
    assert rep["verdict"] == "missing_ligament", rep["verdict_reason"]
    best = rep["candidates"][0]
    assert best["place"] == "sij_left"
    assert best["gap_after"] < 1.0
