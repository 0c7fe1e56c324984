"""Gap verdict against the measurement chain's tolerances (issue 10): a per-FRF gain within
the calibration tolerance, or a probe tilt within the mounting tolerance, is not an
unmodelled effect. Small cases only (same layout as ``test_gap_diagnosis``)."""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.app.commands.gap import format_report
from pelvislab.model.frf import frf
from pelvislab.model.gap import (
    CandidateResult,
    GapOptions,
    _context,
    _Lines,
    _predictive_chi2,
    _within_tolerance,
    calibrated_chi2,
    diagnose,
    prepare_data,
)
from pelvislab.model.pelvis import default_model
from tests.test_gap_diagnosis import F_HZ, IN, OPTS, OUT, ctx_for, noisy, pick, true_model


def test_calibrated_chi2_fits_one_gain_per_frf_within_tolerance():
    rng = np.random.default_rng(0)
    Hm = rng.normal(size=(40, 3, 2)) + 1j * rng.normal(size=(40, 3, 2))
    sigma = np.full(Hm.shape, 0.01)
    true_g = np.array([[1.003, 0.998], [1.0, 1.004], [0.99, 1.02]])
    H = Hm * true_g[None]
    held = np.zeros(Hm.shape, bool)
    held[2::4] = True
    fit = ~held
    chi2, g = calibrated_chi2(H, sigma, Hm, fit, held, 0.005)
    np.testing.assert_allclose(g, np.clip(true_g, 0.995, 1.005), atol=1e-12)
    # only the two gains beyond the tolerance leave a residual: 0.005 and 0.015 of |Hm|
    expect = np.sum(np.abs(Hm[held[:, 2, 0], 2, 0] * 0.005) ** 2 / 1e-4)
    expect += np.sum(np.abs(Hm[held[:, 2, 1], 2, 1] * 0.015) ** 2 / 1e-4)
    assert chi2 == pytest.approx(expect, rel=1e-9)
    # tolerance 0: the plain held-out chi2
    chi2_0, g0 = calibrated_chi2(H, sigma, Hm, fit, held, 0.0)
    assert np.all(g0 == 1.0)
    assert chi2_0 == pytest.approx(np.sum(np.abs(H - Hm)[held] ** 2 / 1e-4))


def _result(cand, u):
    return CandidateResult(cand, np.asarray(u, float), np.ones(1), 0.0, 0.0, 0.0, 0.0, 1)


def test_misorientation_within_mounting_or_calibration_tolerance_is_flagged():
    ctx = ctx_for(default_model())
    tilt = pick(ctx, "sensor_misorientation", "sias_R_x", "tilted axis")
    gain = pick(ctx, "sensor_misorientation", "sias_R_x", "1/cos gain")
    opt = GapOptions()
    assert "mounting" in _within_tolerance(_result(tilt, [np.tan(np.radians(0.3)), 0.0]), opt)
    assert _within_tolerance(_result(tilt, [np.tan(np.radians(8.0)), 0.0]), opt) == ""
    assert "calibration" in _within_tolerance(_result(gain, [np.log(1.004)]), opt)
    assert _within_tolerance(_result(gain, [np.log(1 / np.cos(np.radians(8.0)))]), opt) == ""
    other = pick(ctx, "frequency_dependent_stiffness", "all springs")
    assert _within_tolerance(_result(other, [0.01]), opt) == ""


def _gain_case(gain, rel):
    """True model (no effect) with one output's gain off by ``gain`` (a calibration error)."""
    rng = np.random.default_rng(3)
    H = frf(true_model(), F_HZ, OUT, IN)
    H[:, 1, :] *= gain
    Hn, sigma = noisy(H, rng, rel=rel)
    return prepare_data(F_HZ, Hn, sigma, OUT, IN)


def test_channel_gain_within_calibration_tolerance_gives_none():
    # a 0.4 % gain on sias_R_x on precise data (sigma 0.02 % of the peak, as the simulated
    # chain): below noise but significant; before the calibration null it was named
    # sensor_misorientation (a 1/cos gain of 1.004 takes the gap from 0.66 to 0.32)
    rep = diagnose(_gain_case(1.004, 2e-4), default_model(), OPTS).report
    assert rep["verdict"] == "none", rep["verdict_reason"]
    assert rep["calibration"]["gap_before"] < rep["gap_before"]
    assert rep["thresholds"]["calibration_tol"] == 0.005
    top = rep["candidates"][0]
    assert top["effect"] == "sensor_misorientation" and top["place"] == "sias_R_x"
    assert "calibration" in top["within_tolerance"]


def test_surface_misorientation_beyond_calibration_tolerance_is_named():
    # 1/cos 14 deg = a 3 % gain on sias_R_x: far beyond calibration, still found
    rep = diagnose(_gain_case(1 / np.cos(np.radians(14.0)), 2e-3), default_model(),
                   OPTS).report
    assert rep["verdict"] == "sensor_misorientation", rep["verdict_reason"]
    assert rep["candidates"][0]["place"] == "sias_R_x"
    assert rep["candidates"][0]["within_tolerance"] is None


def test_gain_beyond_tolerance_by_less_than_its_uncertainty_gives_none():
    # a 0.55 % gain on sias_R_x on precise data: fitted with the base as a 1/cos gain of
    # 1.0054; capped at 1.005 the chi2 of fitted and held-out lines rises by ~5 (< 10.8 at
    # p 0.001), so the data do not show it beyond the tolerance. Before, it was named
    # sensor_misorientation, as make demo's session was (the simulated chain's speckle
    # gain at sacrum_x, fitted 1.0057: capped, the chi2 rose by 0.3)
    rep = diagnose(_gain_case(1.0055, 2e-4), default_model(), OPTS).report
    assert rep["verdict"] == "none", rep["verdict_reason"]
    top = rep["candidates"][0]
    assert top["effect"] == "sensor_misorientation" and top["variant"] == "1/cos gain"
    assert top["params"]["gain"] > 1.005
    assert "not significantly beyond" in top["within_tolerance"]


# The null fitted as a whole before a verdict "unexplained" (plain face_up session: per-output
# tracking gains and a held-out line beside appendix E's 10.38 Hz mode carried its gap)

F_FINE_HZ = np.arange(5.0, 150.1, 2.5)  # the held-out lines (every 4th, offset 2) include 10 Hz


def _precise(model, gains, seed=0):
    """Receptances of ``model`` with one real gain per output and noise 0.03 % of |H| per
    line (the simulated chain's phasor scatter below 50 Hz)."""
    rng = np.random.default_rng(seed)
    H = frf(model, F_FINE_HZ, OUT, IN) * np.asarray(gains)[None, :, None]
    sigma = 3e-4 * np.abs(H)
    e = sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
    return prepare_data(F_FINE_HZ, H + e, sigma, OUT, IN)


def test_output_gains_within_tolerance_fitted_with_the_base_give_none():
    # gains 0.9965 / 1.003 / 1 on precise data: the base gap is 7.3 and no candidate
    # explains it (before: "unexplained", f_k best at 7.13); the base refitted with the
    # gains leaves the noise (they lie within +-0.5 % of a common scale)
    rep = diagnose(_precise(default_model(), [0.9965, 1.003, 1.0]), default_model(),
                   OPTS).report
    assert rep["gap_before"] > 5.0
    assert rep["verdict"] == "none", rep["verdict_reason"]
    assert "null hypothesis fitted as a whole" in rep["verdict_reason"]
    joint = rep["calibration"]["joint_null"]
    assert joint["gap_predictive"] <= 0.5
    g = joint["gains"]
    assert g["gain_sacrum_x"] / g["gain_sias_R_x"] == pytest.approx(0.9965 / 1.003, abs=5e-4)
    assert "output gains of the null fitted with the base parameters: sacrum_x" in (
        format_report(rep))


def test_output_gains_beyond_tolerance_stay_unexplained():
    # 2 % apart: more than the tolerance allows, so the null does not explain them
    rep = diagnose(_precise(default_model(), [0.99, 1.01, 1.0]), default_model(),
                   OPTS).report
    assert rep["verdict"] == "unexplained", rep["verdict_reason"]
    assert rep["calibration"]["joint_null"]["gap_predictive"] > 0.5


def test_prediction_variance_is_largest_on_the_line_beside_a_lightly_damped_mode():
    # (the plain face_up session, 7 outputs x 3 inputs, 450 held-out lines: 764 there)
    model = default_model()
    data = _precise(model, [1.0, 1.0, 1.0])
    ctx = _context(model, data)
    held_lines = np.arange(F_FINE_HZ.size) % 4 == 2
    fit = _Lines.build(ctx, data, ~held_lines)
    held = _Lines.build(ctx, data, held_lines)
    x = np.log(ctx.base.nominal)
    lo, hi = x - 1.0, x + 1.0
    chi2_plain, chi2_pred, v = _predictive_chi2(None, fit, held, x, lo, hi)
    line = np.argwhere(held.mask)[np.argmax(v) % held.n][0]
    # appendix E's first mode: 10.38 Hz, zeta 0.43 % (half-power band 0.09 Hz)
    assert held.ctx.frequency_hz[line] == 10.0
    assert v.max() > 1.0 and v.max() > 30 * np.median(v)
    assert 0.0 <= v.min() and chi2_pred < chi2_plain
    # at the truth the plain held-out chi2 is noise: ~ n lines
    assert abs(chi2_plain - held.n) < 5 * np.sqrt(held.n)
