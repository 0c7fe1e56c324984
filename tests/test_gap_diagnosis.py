"""Gap diagnosis (issue 10): effect physics, noise estimate, verdicts on small cases, JSON
contract of design 4.4, CLI. Small problems only; the full self-check is the benchmark."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pelvislab.acquisition.frfset import Channels, FrfSet, write_frf
from pelvislab.app.cli import main
from pelvislab.model.frf import frf
from pelvislab.model.gap import (
    GapOptions,
    _context,
    diagnose,
    estimate_noise,
    excess_gap,
    prepare_data,
    third_differences,
)
from pelvislab.model.gap_benchmark import BenchCase, place_correct, predicted_place
from pelvislab.model.gap_effects import EffectTerms, candidate_library, evaluate
from pelvislab.model.pelvis import PointMass, Spring, default_model

F_HZ = np.arange(5.0, 300.1, 5.0)
OUT = Channels(
    ["sacrum_x", "sias_R_x", "sias_L_y"], ["sacrum", "innominate_right", "innominate_left"],
    np.array([[-0.16, 0.0, -0.06], [0.0, -0.11, 0.0], [-0.01, 0.12, -0.01]]),
    np.array([[-1.0, 0, 0], [1, 0, 0], [0, 1, 0]]),
)
IN = Channels(["sips_R_x", "sips_L_x"], ["innominate_right", "innominate_left"],
              np.array([[-0.14, -0.045, 0.02], [-0.14, 0.045, 0.02]]),
              np.array([[1.0, 0, 0], [1, 0, 0]]))


def assert_jacobian_matches_differences(ctx, theta, terms, params=(0, 4, 15, 17)) -> None:
    """``evaluate``'s ∂H/∂log θ against central differences (step 1e-6 in log θ).

    Central, not forward: the forward difference's truncation error on a lightly damped
    mode came to 1.04e-4 of the column's largest value on one machine's BLAS (session 15),
    beyond the tolerance."""
    _H, dH = evaluate(ctx, theta, terms, jacobian=True)
    for j in params:
        step = 1e-6
        up, down = theta.copy(), theta.copy()
        up[j] *= np.exp(step)
        down[j] *= np.exp(-step)
        fd = (evaluate(ctx, up, terms)[0] - evaluate(ctx, down, terms)[0]) / (2 * step)
        assert np.max(np.abs(fd - dH[..., j])) < 1e-4 * np.max(np.abs(dH[..., j])) + 1e-30, j


def true_model():
    """Appendix E with a few parameters moved and damping far from nominal."""
    m = default_model()
    m = m.with_mass("sacrum", 0.36 * 1.15)
    m = m.replace_spring("io_R", stiffness_n_per_m=1.2e6)
    m = m.replace_spring("pubh", stiffness_n_per_m=0.8e5)
    for d in m.dashpots:
        m = m.replace_dashpot(d.name, coefficient_n_s_per_m=150.0)
    return m


def noisy(H, rng, rel=0.005):
    sigma = rel * np.max(np.abs(H), axis=0, keepdims=True) * np.ones(H.shape)
    e = sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
    return H + e, sigma


def ctx_for(model, f=F_HZ):
    data = prepare_data(f, np.ones((f.size, 3, 2), complex), np.ones((f.size, 3, 2)), OUT, IN)
    return _context(model, data)


def pick(ctx, effect, place, variant=None):
    for c in candidate_library(ctx):
        if c.effect == effect and c.place == place and (variant is None or c.variant == variant):
            return c
    raise AssertionError(f"no candidate {effect} at {place}")


# ---------------------------------------------------------------------------------------
# Effect physics against the model core's own extension methods (independent code paths)

def test_added_mass_candidate_matches_model_point_mass():
    m = default_model()
    ctx = ctx_for(m)
    cand = pick(ctx, "added_mass", "innominate_left")
    ref = m.body("innominate_left").com_m
    u = np.array([np.log(0.2), 0.01, -0.02, 0.015])
    H, _ = evaluate(ctx, ctx.base.nominal, cand.build(u, ctx))
    m2 = m.with_point_mass(PointMass("x", "innominate_left", ref + u[1:], 0.2))
    H2 = frf(m2, F_HZ, OUT, IN)
    np.testing.assert_allclose(H, H2, rtol=1e-5, atol=1e-9 * np.abs(H2).max())


def test_ligament_candidate_matches_model_spring():
    m = default_model()
    ctx = ctx_for(m)
    cand = pick(ctx, "missing_ligament", "sij_right")
    n = np.array([0.3, -0.5, 0.8])
    n /= np.linalg.norm(n)
    k = 3e5
    u = np.concatenate([np.sqrt(k / 1e5) * n, [0.01, 0.0, -0.03]])
    H, _ = evaluate(ctx, ctx.base.nominal, cand.build(u, ctx))
    p = np.array([-0.088, -0.04, 0.0]) + u[3:]
    m2 = m.with_spring(Spring("extra", "innominate_right", p - 0.01 * n, "sacrum",
                              p + 0.02 * n, k))
    H2 = frf(m2, F_HZ, OUT, IN)
    np.testing.assert_allclose(H, H2, rtol=1e-5, atol=1e-9 * np.abs(H2).max())


def test_frequency_dependent_stiffness_matches_eq_7_3():
    m = default_model()
    ctx = ctx_for(m)
    cand = pick(ctx, "frequency_dependent_stiffness", "all springs")
    H, _ = evaluate(ctx, ctx.base.nominal, cand.build(np.array([0.7]), ctx))
    H2 = frf(m.with_frequency_dependence(f_k=0.7, f_max_hz=F_HZ.max()), F_HZ, OUT, IN)
    np.testing.assert_allclose(H, H2, rtol=1e-5, atol=1e-9 * np.abs(H2).max())


@pytest.mark.parametrize("effect, u", [("frequency_dependent_stiffness", 0.7),
                                       ("hysteretic_damping", 5.0)])
def test_band_scaled_effects_are_the_same_on_a_subset_of_lines(effect, u):
    # eq. 7.2-7.3 scale with the band's omega_max; the held-out lines (every 4th) end below
    # the band's top, and evaluated with their own maximum f_k was 0.6 % larger there
    # (judge-like set 5315_026: the true f_k left a held-out gap of 1.9, all of it on the
    # line beside a mode of zeta ~0.01 %; named unexplained)
    ctx = ctx_for(true_model())
    cand = pick(ctx, effect, "all springs" if effect.startswith("freq") else "all joints")
    held = np.flatnonzero(np.arange(F_HZ.size) % 4 == 2)
    assert F_HZ[held].max() < F_HZ.max()
    sub = ctx.subset(held)
    assert sub.omega_max == ctx.omega_max
    H, _ = evaluate(ctx, ctx.base.nominal, cand.build(np.array([u]), ctx))
    H_sub, _ = evaluate(sub, ctx.base.nominal, cand.build(np.array([u]), sub))
    np.testing.assert_allclose(H_sub, H[held], rtol=1e-12, atol=0)


def test_support_bed_limit_is_a_grounding_spring():
    m = default_model()
    ctx = ctx_for(m)
    cand = pick(ctx, "support_resonance", "sacrum xyz")
    # stiff contact, negligible mass: k_eff -> k_s + i w c_s (a grounding spring-damper)
    f_s, zeta, mass = 40.0, 0.2, 1e-3
    ks = mass * (2 * np.pi * f_s) ** 2
    cs = 2 * zeta * mass * 2 * np.pi * f_s
    u = np.log([f_s, zeta, mass, 1e12])
    H, _ = evaluate(ctx, ctx.base.nominal, cand.build(u, ctx))
    m2 = m.with_grounding("sacrum", ks, coefficient_n_s_per_m=cs)
    # with a rigid contact the support mass moves with the bone point: a point mass there
    m2 = m2.with_point_mass(PointMass("bed", "sacrum", m.body("sacrum").com_m, mass))
    H2 = frf(m2, F_HZ, OUT, IN)
    assert np.max(np.abs(H - H2)) < 1e-5 * np.max(np.abs(H2))


def test_jacobian_matches_finite_differences():
    m = true_model()
    ctx = ctx_for(m)
    theta = ctx.base.nominal * np.linspace(0.8, 1.2, ctx.base.n_params)
    terms = pick(ctx, "soft_tissue", "sias_R_x").build(np.log([80.0, 0.3, 0.05]), ctx)
    assert_jacobian_matches_differences(ctx, theta, terms)


def test_terms_identity_is_the_base_model():
    m = true_model()
    ctx = ctx_for(m)
    H, _ = evaluate(ctx, ctx.base.nominal, EffectTerms())
    np.testing.assert_allclose(H, frf(m, F_HZ, OUT, IN), rtol=1e-9)


# ---------------------------------------------------------------------------------------
# Noise estimate and gap definition

def test_noise_estimate_recovers_sigma():
    rng = np.random.default_rng(3)
    f = np.arange(5.0, 300.1, 1.5)
    H = frf(true_model(), f, OUT, IN)
    Hn, sigma = noisy(H, rng, rel=0.01)
    est = estimate_noise(Hn)
    ratio = est[0] / sigma[0]
    assert np.all((ratio > 0.75) & (ratio < 1.35)), ratio


def test_third_differences_vanish_on_a_quadratic_on_any_grid():
    """Divided differences where the lines are unevenly spaced: a quadratic leaves nothing,
    and the squared coefficients sum to 20 as (1, −3, 3, −1) do on an even grid (plain Δ³
    on alternating 1/2 Hz steps leaves even a straight line in)."""
    rng = np.random.default_rng(7)
    f = np.cumsum(rng.uniform(0.25, 10.0, 40)) + 5.0
    quadratic = (3.0 - 2.0j) + (0.5 + 1.0j) * f - 0.01 * f**2
    d, c2, uneven = third_differences(quadratic, f)
    assert uneven.all()
    assert np.max(np.abs(d)) < 1e-9 * np.max(np.abs(quadratic))
    assert np.allclose(c2.sum(axis=1), 20.0)
    even = np.arange(5.0, 50.0, 1.5)
    d_even, c2_even, uneven_even = third_differences(even**3, even)
    thirds = np.round(5.0 + np.arange(60) / 3.0, 9)  # a sweep's 1e-9 Hz rounding: even
    assert not third_differences(thirds, thirds)[2].any()
    assert not uneven_even.any() and np.array_equal(d_even, np.diff(even**3, 3))
    assert np.array_equal(c2_even, np.tile([1.0, 9.0, 9.0, 1.0], (d_even.size, 1)))
    alternating = np.cumsum(np.r_[5.0, np.tile([1.0, 2.0], 20)])
    assert np.max(np.abs(np.diff(alternating, 3))) > 1.0  # what plain Δ³ leaves of f itself


def test_noise_estimate_over_each_frfs_own_lines_and_spacing():
    """With the frequencies, σ comes from each FRF's own measured lines: an FRF measured on
    every other line had no difference of neighbouring lines (5 % of its peak: ~10x the
    noise here), and on alternating 1/2 Hz steps noise ∝ |H| came out ~1.8x. An even grid
    with every line measured gives the same σ, bit for bit, with or without them."""
    rng = np.random.default_rng(5)
    even = np.arange(5.0, 300.1, 1.5)
    H = frf(true_model(), even, OUT, IN)
    Hn, sigma = noisy(H, rng, rel=0.005)
    assert np.array_equal(estimate_noise(Hn, even), estimate_noise(Hn))
    Hn[1::2] = np.nan
    on = np.isfinite(Hn)
    ratio = np.median(estimate_noise(Hn, even)[on] / sigma[on])
    assert 0.8 < ratio < 1.25, ratio
    uneven = np.cumsum(np.r_[5.0, np.tile([1.0, 2.0], 100)])
    H = frf(true_model(), uneven, OUT, IN)
    sigma = 0.01 * np.abs(H)
    e = sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
    ratio = np.median(estimate_noise(H + e, uneven) / sigma)
    assert 0.8 < ratio < 1.25, ratio


def test_noise_proportional_to_a_falling_receptance_is_followed_to_the_band_edge():
    """A free-free receptance falls as 1/f²; noise ∝ |H| on a 2.5 Hz grid then grows 16x
    in σ² per octave toward 5 Hz, and the running median, held at the first full window,
    gave σ 25-40x too small at the first line (judge-like no-effect set 1414_019:
    `unexplained`, 95 % of its residual in 5-54 Hz). Each end follows a significant trend
    of the differences now; noise of constant level keeps the window's median."""
    f = np.arange(5.0, 300.1, 2.5)
    mass_line = -1.0 / (0.5 * (2 * np.pi * f) ** 2) * (1 + 0.3j * f / 300)
    H = np.repeat(mass_line[:, None, None], 2, axis=2)
    for seed in range(6):
        rng = np.random.default_rng(seed)
        sigma = 0.01 * np.abs(H)
        e = sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
        ratio = (estimate_noise(H + e, f) / sigma)[:, 0, 0]
        assert ratio[0] > 0.15 and np.all(ratio[2:8] > 0.5), ratio[:8]  # was 0.03, 0.1-0.5
        assert 0.8 < np.median(ratio) < 1.25
        constant = 0.01 * np.abs(H).max() * np.ones(H.shape)
        e = constant / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
        ratio = (estimate_noise(H + e, f) / constant)[:, 0, 0]
        assert np.ptp(ratio) == 0.0 and 0.75 < ratio[0] < 1.3, ratio[:4]


def test_excess_gap_is_zero_at_noise_level_and_grows():
    assert excess_gap(100.0, 100) == 0.0
    assert excess_gap(90.0, 100) == 0.0
    assert excess_gap(500.0, 100) == pytest.approx(2.0)


# ---------------------------------------------------------------------------------------
# Diagnosis on small cases (restricted candidate lists keep them fast)

FAST = ("sensor_misorientation", "frequency_dependent_stiffness")
OPTS = GapOptions(effects=FAST, base_starts=1, max_nfev_joint=20, max_nfev_short=8, finish_jobs=2)


def test_no_effect_gives_verdict_none():
    rng = np.random.default_rng(11)
    Hn, sigma = noisy(frf(true_model(), F_HZ, OUT, IN), rng)
    data = prepare_data(F_HZ, Hn, sigma, OUT, IN)
    notes = []
    rep = diagnose(data, default_model(), OPTS, progress=notes.append).report
    assert rep["verdict"] == "none", rep["verdict_reason"]
    assert rep["gap_before"] < 0.5
    # progress on the long stages (CLI --progress on a terminal, the GUI's status line)
    stages = [n.split(":")[0] for n in notes]
    assert "joint fits" in stages and any(s.startswith("polish") for s in stages), notes
    assert stages.index("joint fits") < stages.index(next(s for s in stages
                                                           if s.startswith("polish")))
    assert "best" in notes[stages.index("joint fits")]


def test_misoriented_sensor_is_found_with_its_place_and_shrink():
    rng = np.random.default_rng(5)
    d = OUT.direction.copy()
    t = np.radians(20.0)
    d[1] = np.array([np.cos(t), 0.0, np.sin(t)])  # sias_R_x tilted 20 deg toward +z
    tilted = Channels(OUT.name, OUT.bone, OUT.position_m, d)
    Hn, sigma = noisy(frf(true_model(), F_HZ, tilted, IN), rng)
    data = prepare_data(F_HZ, Hn, sigma, OUT, IN)
    rep = diagnose(data, default_model(), OPTS).report
    assert rep["verdict"] == "sensor_misorientation", rep["verdict_reason"]
    best = rep["candidates"][0]
    assert best["effect"] == "sensor_misorientation" and best["place"] == "sias_R_x"
    assert best["shrink"] > 0.7
    assert rep["gap_before"] > 1.0
    # design 4.4 contract: shares sum to 1, largest first
    for key in ("bands", "outputs", "bones"):
        shares = [x["share"] for x in rep["where"][key]]
        assert sum(shares) == pytest.approx(1.0, abs=1e-9)
        assert shares == sorted(shares, reverse=True)
    assert rep["where"]["outputs"][0]["name"] == "sias_R_x"
    for c in rep["candidates"]:
        assert set(c) >= {"effect", "gap_after", "shrink", "params", "evidence"}
        assert c["shrink"] == pytest.approx(1 - c["gap_after"] / rep["gap_before"], abs=1e-4)


def test_unmodellable_effect_is_unexplained():
    # a pure time delay on every FRF is none of the candidate effects
    rng = np.random.default_rng(8)
    H = frf(true_model(), F_HZ, OUT, IN) * np.exp(-2j * np.pi * F_HZ * 1.5e-3)[:, None, None]
    Hn, sigma = noisy(H, rng)
    data = prepare_data(F_HZ, Hn, sigma, OUT, IN)
    rep = diagnose(data, default_model(), OPTS).report
    assert rep["verdict"] == "unexplained", rep["verdict_reason"]
    assert rep["gap_before"] > 1.0


# ---------------------------------------------------------------------------------------
# Benchmark scoring and CLI

def _case(kind, place, place_kind, bone=""):
    return BenchCase(F_HZ, np.zeros((1, 1, 1)), None, OUT, IN, kind, place, place_kind, bone)


def test_place_scoring_uses_verdict_candidate_then_where():
    rep = {"verdict": "added_mass",
           "candidates": [{"effect": "added_mass", "place": "sacrum", "place_kind": "bone",
                           "bone": "sacrum"}],
           "where": {"bones": [{"bone": "innominate_left", "share": 0.6}],
                     "outputs": [{"name": "sias_L_y", "share": 0.6}], "inputs": []}}
    assert place_correct(rep, _case("added_mass", "sacrum", "bone", "sacrum"))
    assert not place_correct(rep, _case("added_mass", "innominate_left", "bone"))
    rep["verdict"] = "unexplained"
    assert predicted_place(rep, _case("soft_tissue", "sias_L_y", "output")) == "sias_L_y"
    assert predicted_place(rep, _case("added_mass", "x", "bone")) == "innominate_left"


def test_cli_diagnose_writes_json_and_report(tmp_path, capsys):
    rng = np.random.default_rng(2)
    Hn, sigma = noisy(frf(true_model(), F_HZ, OUT, IN), rng)
    path = tmp_path / "s.h5"
    write_frf(path, FrfSet(F_HZ, Hn, OUT, IN, H_std=sigma))
    out = tmp_path / "gap.json"
    code = main(["gap", "diagnose", str(path), "--json", str(out), "--effects", "added_mass",
                 "--progress"])
    assert code == 0
    rep = json.loads(out.read_text())
    assert set(rep) >= {"gap_before", "where", "candidates", "verdict"}
    assert rep["verdict"] in ("none", "added_mass", "unexplained")
    printed = capsys.readouterr()
    assert "verdict" in printed.out
    # --progress: the stages on stderr although it is not a terminal here
    assert "  joint fits: " in printed.err and "  screened " in printed.err
    assert len(rep["plots"]) == 2
    for p in rep["plots"]:
        assert open(p, "rb").read(8) == b"\x89PNG\r\n\x1a\n"


def test_unmeasured_lines_and_estimated_noise():
    # drive-point layout: some output/input pairs never measured (NaN), no H_std in the file
    rng = np.random.default_rng(4)
    f = np.arange(5.0, 300.1, 2.5)
    Hn, _ = noisy(frf(true_model(), f, OUT, IN), rng)
    Hn[:, 0, 1] = np.nan
    data = prepare_data(f, Hn, None, OUT, IN)
    assert data.noise_source.startswith("estimated")
    with np.errstate(all="raise"):
        rep = diagnose(data, default_model(), OPTS).report
    assert rep["verdict"] == "none", rep["verdict_reason"]
    assert all(x["output"] != "sacrum_x" or x["input"] != "sips_L_x"
               for x in rep["where"]["frac"])


def test_cli_errors_are_one_line(tmp_path, capsys):
    code = main(["gap", "diagnose", str(tmp_path / "missing.h5"), "--json",
                 str(tmp_path / "o.json")])
    assert code == 1
    err = capsys.readouterr().err.strip()
    assert "missing.h5" in err and "\n" not in err
    rng = np.random.default_rng(2)
    Hn, sigma = noisy(frf(true_model(), F_HZ, OUT, IN), rng)
    path = tmp_path / "s.h5"
    write_frf(path, FrfSet(F_HZ, Hn, OUT, IN, H_std=sigma))
    code = main(["gap", "diagnose", str(path), "--json", str(tmp_path / "o.json"),
                 "--effects", "telepathy"])
    assert code == 1
    assert "telepathy" in capsys.readouterr().err


def test_false_none_counts_absorbed_sets_apart_but_keeps_them():
    from pelvislab.model.gap_benchmark import _score

    def entry(kind, verdict, gap):
        return {"kind": kind, "verdict": verdict, "correct": kind == verdict,
                "place_correct": None, "shrink": None, "gap_before": gap, "none_gap": 0.5,
                "wall_time_s": 1.0, "cpu_time_s": 1.0}

    cases = [entry("added_mass", "none", 0.04), entry("added_mass", "none", 0.9),
             entry("none", "none", 0.0), entry("added_mass", "added_mass", 2.0)]
    res = _score(cases, ["none", "added_mass"], ["none", "added_mass", "unexplained"])
    assert res["false_none"] == 2
    assert res["false_none_absorbed_by_updating"] == 1
    assert res["verdict_accuracy"] == 0.5


def test_shrink_distribution_leaves_out_sets_named_at_base_gap_0():
    from pelvislab.model.gap_benchmark import _score, format_summary

    def entry(gap, shrink):
        return {"kind": "added_mass", "verdict": "added_mass", "correct": True,
                "place_correct": None, "shrink": shrink, "gap_before": gap, "none_gap": 0.5,
                "wall_time_s": 1.0, "cpu_time_s": 1.0}

    # the report's shrink at gap_before 0 is null (undefined); 0.0 in entries of older runs
    cases = [entry(2.0, 0.9), entry(0.0, None), entry(1.0, 0.8), entry(0.0, 0.0)]
    res = _score(cases, ["added_mass"], ["none", "added_mass", "unexplained"])
    assert res["shrink_correct"]["values"] == [0.9, 0.8]
    assert res["shrink_correct"]["min"] == 0.8
    assert res["shrink_correct"]["undefined_gap_before_0"] == 2
    res.update(wall_time_s={"median": 1, "max": 1}, cpu_time_s={"median": 1, "max": 1})
    assert "2 more named at base gap 0" in format_summary(res)


def test_benchmark_takes_a_null_shrink_of_a_set_named_at_base_gap_0(monkeypatch):
    """At gap_before 0 the shrink is undefined (the report's 0.0): the case holds null, so
    the benchmark counts such sets apart; it read float(shrink) of a null once."""
    from types import SimpleNamespace

    from pelvislab.model import gap_benchmark

    report = {"verdict": "added_mass", "gap_before": 0.0, "thresholds": {"none_gap": 0.5},
              "where": {}, "candidates": [{"effect": "added_mass", "gap_after": 0.0,
                                           "shrink": 0.0}],
              "verdict_reason": "added_mass lowers the held-out chi2 by 40 (> 18)",
              "significance": {"candidate": "added_mass", "significant": True,
                               "by": "held-out lines", "held_out_chi2_drop": 40.0,
                               "held_out_critical": 18.0, "pooled_chi2_drop": 90.0,
                               "pooled_critical": 20.9, "pooled_gap_before": None,
                               "pooled_gap_after": None, "shrink_judged": None,
                               "beyond_null_failed": None, "null": "the base fit",
                               "note": "likelihood-ratio test ..."}}
    monkeypatch.setattr(gap_benchmark, "diagnose",
                        lambda data, model, options: SimpleNamespace(report=report))
    H = np.ones((F_HZ.size, 3, 2), complex)

    def generator(kind, index):
        return BenchCase(F_HZ, H, np.ones(H.shape), OUT, IN, kind)

    res = gap_benchmark.run_benchmark(generator, kinds=["added_mass"], cases_per_kind=1)
    assert res["cases"][0]["shrink"] is None
    # each case says why: the verdict's reason and the test behind it
    assert res["cases"][0]["verdict_reason"] == report["verdict_reason"]
    assert res["cases"][0]["significance"] == {
        k: v for k, v in report["significance"].items() if k not in ("null", "note")}
    assert res["shrink_correct"]["undefined_gap_before_0"] == 1
    assert res["shrink_correct"]["values"] == []


def test_gap_commands_keep_freed_memory_on_glibc():
    """The allocator setting of the gap commands takes effect where glibc is the C
    library and is a no-op elsewhere (see ``keep_freed_memory_for_reuse``)."""
    import platform

    from pelvislab.app.commands._common import keep_freed_memory_for_reuse

    assert keep_freed_memory_for_reuse() is (platform.libc_ver()[0] == "glibc")


def test_where_leaves_a_channel_on_no_bone_out_of_the_shares_and_lists_it():
    """Design 4.1 spells "on no modelled bone" as an empty string. The model predicts
    nothing there, so such a channel has no share: it was listed with share 0.0 (and bone
    "" with 0.0), which reads "fits perfectly"; it is listed apart in where.left_out, as
    is a channel on a bone with no usable line."""
    from pelvislab.model.gap import where_analysis

    outs = Channels(OUT.name + ["table_z", "sacrum_z"], OUT.bone + ["", "sacrum"],
                    np.vstack([OUT.position_m, [0.0, 0.0, -0.2], [-0.1, 0.0, 0.0]]),
                    np.vstack([OUT.direction, [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]))
    ins = Channels(IN.name + ["frame_x"], IN.bone + [""],
                   np.vstack([IN.position_m, [0.0, 0.0, -0.3]]),
                   np.vstack([IN.direction, [1.0, 0.0, 0.0]]))
    H = np.ones((F_HZ.size, 5, 3), complex)
    H[:, 4, :] = np.nan  # sacrum_z: never measured
    data = prepare_data(F_HZ, H, np.ones(H.shape), outs, ins)
    H_model = H.copy()
    H_model[:, 0, :] += 3.0
    H_model[:, 3, :] += 3.0
    where = where_analysis(data, H_model)
    assert where["bones"][0] == {"bone": "sacrum", "share": 1.0}
    assert {b["bone"] for b in where["bones"]} == {"sacrum", "innominate_right",
                                                   "innominate_left"}
    assert [o["name"] for o in where["outputs"]] == [OUT.name[0], OUT.name[1], OUT.name[2]]
    assert [i["name"] for i in where["inputs"]] == IN.name
    assert where["left_out"] == [
        {"side": "output", "name": "table_z", "bone": "", "reason": "on no modelled bone"},
        {"side": "output", "name": "sacrum_z", "bone": "sacrum", "reason": "no usable line"},
        {"side": "input", "name": "frame_x", "bone": "", "reason": "on no modelled bone"}]


def test_a_file_on_no_modelled_bone_is_refused_with_that_reason():
    # a beam's FRFs gave "only 0 usable FRF lines" for 1000 lines (review, session 39)
    out = Channels(["n1", "n2"], ["", ""], np.zeros((2, 3)), np.array([[1.0, 0, 0]] * 2))
    inp = Channels(["n1"], [""], np.zeros((1, 3)), np.array([[1.0, 0, 0]]))
    H = np.ones((F_HZ.size, 2, 1), complex) * (1 + 1j)
    with pytest.raises(ValueError, match=r"3 of its 3 points are on no modelled bone: "
                                         r"output n1, output n2, input n1"):
        prepare_data(F_HZ, H, None, out, inp)


def test_a_reported_comparison_prints_two_different_numbers():
    from pelvislab.model.gap import _less_than

    assert _less_than(2287.6, 2288.1) == "2287.6 < 2288.1"  # was "2288 < 2288"
    assert _less_than(391.5, 1009.0) == "391.5 < 1009"
    assert _less_than(1.0, 1.0 + 1e-12) == "1 < 1"  # equal to 10 digits: said as they are
