"""Gap verdict against the measurement chain's tolerances (issue 10): a per-FRF gain within
the calibration tolerance, or a probe tilt within the mounting tolerance, is not an
unmodelled effect. Small cases only (same layout as ``test_gap_diagnosis``)."""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.frf import frf
from pelvislab.model.gap import (
    CandidateResult,
    GapOptions,
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
