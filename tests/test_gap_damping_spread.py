"""Gap diagnosis when the subject's damping coefficients are decades apart.

Issue 10's withheld sets have "damping coefficients far from" appendix E, not necessarily
alike: one joint's dashpots may be two decades from another's (design 4.5 groups), or the
three dashpots of one joint decades apart (one coefficient per dashpot). The subjects here
are those of two judge-like sets that the diagnosis got wrong (seed 1357, sets 14 and 0),
without their effects; the data come from the independent thesis model
(``tests/independent_pelvis.py``).
"""

import numpy as np

from pelvislab.model.gap import (
    GapOptions,
    _context,
    _line_spring_search,
    _Lines,
    diagnose,
    fit_base,
    prepare_data,
)
from pelvislab.model.gap_effects import candidate_library
from pelvislab.model.pelvis import default_model
from pelvislab.tests import independent_pelvis as ip
from pelvislab.tests.benchmarks.bench_gap import FREQUENCY_HZ, INPUTS, MEASURED, OUTPUTS

MASS_KG = {"innominate_right": 0.821, "innominate_left": 0.523, "sacrum": 0.404}
STIFFNESS_N_PER_M = {"io_R": 7.94e5, "asa_R": 1.170e6, "asd_R": 8.51e5, "pss_R": 1.174e6,
                     "psl_R": 1.132e6, "io_L": 1.084e6, "asa_L": 9.34e5, "asd_L": 1.014e6,
                     "pss_L": 1.031e6, "psl_L": 1.062e6, "pubh": 7.38e4, "pubs": 4.05e3}


def _frf(damping_n_s_per_m: dict[str, float], f_k: float = 0.0) -> np.ndarray:
    """Face-up layout FRFs (m/N) of the subject, with frequency-dependent stiffness
    K (1 + f_k ω / (4 ω_max)) (thesis eq. 7.1, 7.3) when ``f_k`` > 0."""
    mass_scale = {b: MASS_KG[b] / ip.MASS[b] for b in ip.BONES}
    m, c, k = ip.matrices(mass_scale, STIFFNESS_N_PER_M, damping_n_s_per_m,
                          dashpot_lever="points")
    return _layout_frf(m, c, k, f_k)


def _layout_frf(m: np.ndarray, c: np.ndarray, k: np.ndarray, f_k: float = 0.0,
                lines: slice = slice(None)) -> np.ndarray:
    """FRFs (m/N) of M, C, K (independent model's coordinates) at the benchmark layout's
    outputs and inputs on its grid's ``lines``, K scaled by (1 + f_k ω / (4 ω_max))
    (eq. 7.1, 7.3; ω_max of the whole grid)."""
    d_out = np.array([d @ ip.point_map(b, p) for b, p, d in
                      zip(OUTPUTS.bone, OUTPUTS.position_m, OUTPUTS.direction, strict=True)])
    d_in = np.array([d @ ip.point_map(b, p) for b, p, d in
                     zip(INPUTS.bone, INPUTS.position_m, INPUTS.direction, strict=True)])
    w_max = 2 * np.pi * FREQUENCY_HZ.max()
    f_hz = FREQUENCY_HZ[lines]
    H = np.empty((f_hz.size, len(d_out), len(d_in)), complex)
    for i, w in enumerate(2 * np.pi * f_hz):
        z = -w * w * m + 1j * w * c + k * (1 + f_k * w / (4 * w_max))
        H[i] = d_out @ np.linalg.solve(z, d_in.T)
    return H


def _data(H: np.ndarray, seed: int, noise_of_peak: float = 0.01, noise_of_h: float = 0.0,
          lines: slice = slice(None)):
    """``H`` (on the grid's ``lines``) with complex noise ``noise_of_peak`` of each FRF's
    peak (or ``noise_of_h`` of |H| line by line), measured pairs only."""
    rng = np.random.default_rng(seed)
    sigma = (noise_of_h * np.abs(H) if noise_of_h else
             noise_of_peak * np.max(np.abs(H), axis=0, keepdims=True) * np.ones(H.shape))
    H = H + sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
    measured = MEASURED[None] & np.ones(H.shape, bool)
    return prepare_data(FREQUENCY_HZ[lines], np.where(measured, H, np.nan + 0j),
                        np.where(measured, sigma, np.nan), OUTPUTS, INPUTS)


def test_base_fit_finds_damping_groups_two_decades_apart():
    # c_sij_R 672, c_sij_L 2756, c_pub 20 N s/m with f_k = 0.55 and noise 1.45 % of |H|
    # (the base fit cannot reach the noise, ~1.4 is its floor): the common damping decade
    # of the grid and restarts of x/÷e left c_pub at ~180x and a fitted-line gap of 53
    # before the per-group scan (seeds 14-16)
    groups = {"R": 672.0, "L": 2756.0, "P": 20.0}
    damping = {d: groups[d[0]] if d.startswith("P") else groups[d[-1]]
               for d in ip.default_damping()}
    data = _data(_frf(damping, f_k=0.55), seed=14, noise_of_h=0.0145)
    ctx = _context(default_model().with_dashpot_lever("points"), data)
    fit = _Lines.build(ctx, data, np.arange(data.frequency_hz.size) % 4 != 2)
    base = fit_base(fit, ctx.base.nominal.copy(), ctx.base.names, GapOptions())
    assert base.gap_fit <= 3.0
    fitted = dict(zip(ctx.base.names, base.values, strict=True))
    assert abs(np.log(fitted["c_pub"] / 20.0)) < np.log(2.0)


def test_dashpots_of_one_joint_decades_apart_are_parameter_updating():
    # one coefficient per dashpot, 23-1652 N s/m within a joint, no effect: parameter
    # updating with the per-dashpot extension explains it (verdict none, extension at the
    # noise); a per-dashpot scan start was tried against equal starts on 15 judge-like
    # per-dashpot sets and changed nothing but one ligament set, so there is none
    damping = {"S1_R": 23.0, "S2_R": 1652.0, "S3_R": 720.0, "S1_L": 116.0, "S2_L": 528.0,
               "S3_L": 1287.0, "P1": 23.0, "P2": 392.0}
    data = _data(_frf(damping), seed=0)
    report = diagnose(data, default_model(), GapOptions(
        effects=("per_dashpot_damping", "frequency_dependent_stiffness"))).report
    assert report["verdict"] == "none", report["verdict_reason"]
    per_dashpot = [c for c in report["candidates"] if c["effect"] == "per_dashpot_damping"]
    assert per_dashpot and per_dashpot[0]["gap_after"] <= GapOptions().near_noise_gap


def test_strong_spring_on_a_per_dashpot_subject_is_refitted_with_the_extension():
    # judge-like set 6174_029's subject (dashpots 69-2508 N s/m, one per dashpot) with a
    # 1.9e5 N/m iliolumbar spring from the right ilium to a fixed L5. The extension alone
    # explains nothing of the spring's misfit, so it looked insignificant and no effect
    # was refitted with it: the spring stopped at gap ~11 and a support on its line was
    # named. Every effect is now refitted with the extension when no candidate comes near
    # the noise. The library here leaves the support out (with it: 76 s against 46 s on
    # one core, the same spring at the same gap): what the test needs is the spring's own
    # refit, and without it the spring stops at gap 13.8 and the last assertion fails
    # (checked by disabling the stage's "no candidate near the noise" branch). On every
    # other line of the grid (99 lines; 42 -> 25 s on one core, the same verdict and place:
    # gap 0.48, 0.52 on all 197 lines) that check still fails: the spring stops at 13.6
    mass = {"innominate_right": 0.479, "innominate_left": 0.659, "sacrum": 0.255}
    stiffness = {"io_R": 1.034e6, "asa_R": 7.16e5, "asd_R": 1.251e6, "pss_R": 7.98e5,
                 "psl_R": 9.25e5, "io_L": 1.221e6, "asa_L": 7.10e5, "asd_L": 1.214e6,
                 "pss_L": 9.49e5, "psl_L": 7.60e5, "pubh": 8.1e4, "pubs": 5.0e3}
    damping = {"S1_R": 514.0, "S2_R": 365.0, "S3_R": 2508.0, "S1_L": 1393.0, "S2_L": 68.7,
               "S3_L": 738.0, "P1": 160.0, "P2": 262.0}
    m, c, k = ip.matrices({b: mass[b] / ip.MASS[b] for b in ip.BONES}, stiffness, damping,
                          dashpot_lever="points")
    crest_m = np.array([-0.1140, -0.0552, 0.0477])
    l5_m = np.array([-0.1068, -0.0388, 0.0813])
    axis = (l5_m - crest_m) / np.linalg.norm(l5_m - crest_m)
    row = axis @ ip.point_map("innominate_right", crest_m)
    k = k + 1.9e5 * np.outer(row, row)
    every_other = slice(None, None, 2)
    data = _data(_layout_frf(m, c, k, lines=every_other), seed=29, noise_of_h=0.0106,
                 lines=every_other)
    report = diagnose(data, default_model(), GapOptions(
        effects=("per_dashpot_damping", "missing_ligament"))).report
    assert report["verdict"] == "missing_ligament", report["verdict_reason"]
    best = report["candidates"][0]
    assert best["place"] == "innominate_right to ground"
    assert best["gap_after"] <= GapOptions().near_noise_gap


# judge-like set 2468_012's subject: joints damped 14-24 N s/m, pubis 285, one damping
# per joint, with its 8.1e4 N/m iliolumbar spring from the left ilium to a fixed L5
LIGHT_MASS_KG = {"innominate_right": 0.508, "innominate_left": 0.570, "sacrum": 0.326}
LIGHT_STIFFNESS_N_PER_M = {
    "io_R": 1.152e6, "asa_R": 9.26e5, "asd_R": 1.010e6, "pss_R": 8.13e5, "psl_R": 1.075e6,
    "io_L": 9.51e5, "asa_L": 1.155e6, "asd_L": 1.245e6, "pss_L": 1.000e6, "psl_L": 1.058e6,
    "pubh": 1.266e5, "pubs": 5.85e3}
LIGHT_DAMPING_N_S_PER_M = {"R": 24.1, "L": 14.3, "P": 285.0}
L5_M = np.array([-0.1016, 0.0407, 0.0849])
CREST_L_M = np.array([-0.1143, 0.0616, 0.0456])
SPRING_N_PER_M = 8.07e4


def _light_subject_with_spring(seed: int):
    """Data (0.82 % of |H| noise) of the lightly damped subject with its spring."""
    damping = {d: LIGHT_DAMPING_N_S_PER_M[d[0] if d.startswith("P") else d[-1]]
               for d in ip.default_damping()}
    m, c, k = ip.matrices({b: LIGHT_MASS_KG[b] / ip.MASS[b] for b in ip.BONES},
                          LIGHT_STIFFNESS_N_PER_M, damping, dashpot_lever="points")
    axis = (CREST_L_M - L5_M) / np.linalg.norm(CREST_L_M - L5_M)
    row = axis @ ip.point_map("innominate_left", CREST_L_M)
    k = k + SPRING_N_PER_M * np.outer(row, row)
    return _data(_layout_frf(m, c, k), seed=seed, noise_of_h=0.0082), axis


def test_line_search_lands_near_a_strong_spring_to_ground():
    # the base frozen at the subject's own values: the global search alone must land near
    # the spring's line and stiffness (its basin is narrow: the suspension resonance is
    # sharp with joints damped ~20 N s/m); the joint fits take it from there. A random
    # line is within 15 deg of the true one with probability 1.7 %.
    data, axis = _light_subject_with_spring(seed=3)
    ctx = _context(default_model().with_dashpot_lever("points"), data)
    theta = np.array([
        LIGHT_MASS_KG[n[2:]] if n.startswith("m_") else
        LIGHT_STIFFNESS_N_PER_M[n[2:]] if n.startswith("k_") else
        LIGHT_DAMPING_N_S_PER_M["P" if n == "c_pub" else n[-1]] for n in ctx.base.names])
    cand = next(c for c in candidate_library(ctx, ("missing_ligament",))
                if c.place == "innominate_left to ground")
    fit = _Lines.build(ctx, data, np.arange(data.frequency_hz.size) % 2 == 0)
    found = cand.describe(_line_spring_search(cand, fit, theta, GapOptions())[0])
    assert abs(np.log(found["stiffness_n_per_m"] / SPRING_N_PER_M)) < np.log(1.4)
    n = np.array([found["axis_x"], found["axis_y"], found["axis_z"]])
    assert abs(n @ axis) > np.cos(np.radians(15))
    p = np.array([found["x_m"], found["y_m"], found["z_m"]])
    assert np.linalg.norm(np.cross(p - CREST_L_M, axis)) < 0.025  # m from the true line


def test_strong_spring_to_ground_with_light_joint_damping_is_named_at_its_bone():
    # from the axis starts and the linearised start the spring stalled at gap 57 (at the
    # sacrum) after a base gap of 132: unexplained. The global line search (run when no
    # candidate comes near the noise) finds it.
    data, _axis = _light_subject_with_spring(seed=12)
    report = diagnose(data, default_model(), GapOptions(effects=("missing_ligament",))).report
    assert report["verdict"] == "missing_ligament", report["verdict_reason"]
    best = report["candidates"][0]
    assert best["place"] == "innominate_left to ground"
    assert best["gap_after"] <= GapOptions().near_noise_gap
