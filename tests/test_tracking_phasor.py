"""Phasor estimation at the drive frequency (acquisition/phasor.py)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pelvislab.acquisition.phasor import estimate_phasor, phase_difference_deg

PRF = 5000.0
T = np.arange(2000) / PRF  # 0.4 s: 2.5 Hz grid frequencies hold whole periods


def _sine(X: complex, f: float, t: np.ndarray = T) -> np.ndarray:
    return np.real(X * np.exp(2j * np.pi * f * t))


@pytest.mark.parametrize("f_hz, method", [(80.0, "dft"), (180.0, "dft"), (81.3, "lsq"),
                                          (279.77, "lsq")])
def test_known_sine_exact_without_noise(f_hz, method):
    X = 1.5e-6 * np.exp(-1j * 2.1)
    p = estimate_phasor(_sine(X, f_hz) + 4e-7, T, f_hz)
    assert p.method == method
    assert abs(p.value - X) < 1e-9 * abs(X)
    assert p.offset == pytest.approx(4e-7, rel=1e-6)
    assert p.std < 1e-12 and p.thd < 1e-6


def test_convention_cosine_phase_and_time_origin():
    # x(t) = A cos(w t + phi)  <=>  X = A e^{i phi}, with t = 0 at the first sample.
    p = estimate_phasor(2.0 * np.cos(2 * np.pi * 100 * T + 0.3), T, 100.0)
    assert p.amplitude == pytest.approx(2.0) and p.phase_rad == pytest.approx(0.3)
    p_sin = estimate_phasor(np.sin(2 * np.pi * 100 * T), T, 100.0)
    assert p_sin.phase_rad == pytest.approx(-np.pi / 2)


def test_harmonic_distortion_measured():
    f = 120.0
    x = _sine(1.0, f) + _sine(0.05j, 2 * f) + _sine(0.02, 3 * f)
    for t, xx in ((T, x), (T[:-37], x[:-37])):  # coherent and non-coherent records
        p = estimate_phasor(xx, t, f)
        assert p.distortion == pytest.approx([0.05, 0.02], abs=1e-9)
        assert p.harmonics[0] == pytest.approx(0.05j, abs=1e-9)
        assert p.thd == pytest.approx(np.hypot(0.05, 0.02), rel=1e-9)


def test_third_harmonic_above_nyquist_is_nan():
    p = estimate_phasor(_sine(1.0, 1000.0), T, 1000.0)
    assert np.isfinite(p.harmonics[0]) and np.isnan(p.harmonics[1])
    assert np.isfinite(p.thd)  # from the 2nd harmonic alone


def test_thd_is_nan_when_no_harmonic_can_be_estimated():
    # tracking review, session 36: 0.0 ("no distortion") above prf/4, whatever the motion
    p = estimate_phasor(_sine(1.0, 1400.0) + _sine(0.3, 2800.0), T, 1400.0)
    assert np.isnan(p.harmonics).all() and np.isnan(p.thd)


@pytest.mark.parametrize("f_hz", [80.0, 81.3])
def test_uncertainty_predicts_scatter(f_hz):
    rng = np.random.default_rng(int(f_hz * 10))
    X = 1e-6 * np.exp(0.4j)
    vals, stds, amp_s, ph_s = [], [], [], []
    for _ in range(200):
        p = estimate_phasor(_sine(X, f_hz) + rng.normal(0, 2e-7, T.size), T, f_hz)
        vals.append(p.value)
        stds.append(p.std)
        amp_s.append(p.amplitude_std)
        ph_s.append(p.phase_std_rad)
    vals = np.array(vals)
    assert np.sqrt(np.mean(np.abs(vals - X) ** 2)) / np.mean(stds) == pytest.approx(1, abs=0.2)
    assert np.std(np.abs(vals)) / np.mean(amp_s) == pytest.approx(1, abs=0.25)
    assert np.std(np.angle(vals)) / np.mean(ph_s) == pytest.approx(1, abs=0.25)


def test_gaps_and_trend():
    f = 80.0
    x = _sine(1e-6, f) + 2e-6 * T  # slow drift
    x[[5, 600, 1999]] = np.nan
    p = estimate_phasor(x, T, f, detrend=True)
    assert p.method == "lsq" and p.n_used == 1997
    assert abs(p.value - 1e-6) < 1e-12
    leaky = estimate_phasor(_sine(1e-6, f) + 2e-6 * T, T, f)  # drift leaks without detrend
    assert abs(leaky.value - 1e-6) > 1e-9


def test_phase_difference_as_table_8_1():
    a = estimate_phasor(_sine(1e-6, 250.0), T, 250.0)
    b = estimate_phasor(_sine(0.8e-6 * np.exp(-1j * np.radians(156.05)), 250.0), T, 250.0)
    diff, std = phase_difference_deg(a, b)
    assert diff == pytest.approx(-156.05, abs=1e-6)  # b lags a
    assert std < 1e-6
    with pytest.raises(ValueError, match="different frequencies"):
        phase_difference_deg(a, estimate_phasor(_sine(1.0, 80.0), T, 80.0))


def test_bad_input():
    with pytest.raises(ValueError, match="samples"):
        estimate_phasor(np.zeros(10), np.arange(11.0), 1.0)
    with pytest.raises(ValueError, match="Nyquist"):
        estimate_phasor(np.zeros(100), np.arange(100) / 100.0, 60.0)
    with pytest.raises(ValueError, match="lsq"):
        estimate_phasor(_sine(1.0, 81.3), T, 81.3, method="dft")


@settings(max_examples=10, deadline=None)
@given(f=st.floats(5.0, 300.0), amp=st.floats(1e-7, 1e-5), phase=st.floats(-3.1, 3.1),
       n=st.integers(200, 2000))
def test_random_sines_recovered(f, amp, phase, n):
    X = amp * np.exp(1j * phase)
    t = T[:n]
    if f * n / PRF < 1.0:  # less than one period: not a phasor problem
        return
    p = estimate_phasor(_sine(X, f, t), t, f)
    assert abs(p.value - X) < 1e-7 * amp
