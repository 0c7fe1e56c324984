"""Echo physics of the simulated bench (sim_instruments/echo.py): timing, levels, statistics."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import scipy.fft
from scipy import signal

from pelvislab.sim_instruments.echo import (
    Acoustics,
    Receiver,
    attenuation_gain,
    bone_echo_peak_v,
    pulse_sigma_s,
    pulse_spectrum,
    quantize,
    synthesize_channel,
)

FS = 500e6
DELAY = 10.0e-6
QUIET = Acoustics(speckle_level_db=-300.0)  # bone echo only
CLEAN = Receiver(snr_db=math.inf)


def _records(u, offsets=None, acoustics=QUIET, receiver=CLEAN, seed=0, full_scale_v=1.0,
             n_samples=500, delay_s=DELAY, **kw):
    u = np.asarray(u, dtype=float)
    offsets = np.zeros(u.size) if offsets is None else np.asarray(offsets, dtype=float)
    codes, vpc = synthesize_channel(
        acoustics, receiver, u, offsets, sample_rate_hz=FS, n_samples=n_samples,
        delay_s=delay_s, full_scale_v=full_scale_v, rng=np.random.default_rng(seed), **kw)
    return codes, vpc


def _delay_between(a: np.ndarray, b: np.ndarray) -> float:
    """Delay (s) of b relative to a from the cross-spectrum phase slope over the pulse band."""
    n = 4096
    A = scipy.fft.rfft(a, n)
    B = scipy.fft.rfft(b, n)
    f = scipy.fft.rfftfreq(n, 1 / FS)
    band = (f > 3e6) & (f < 7e6)
    phase = np.unwrap(np.angle(B[band] * np.conj(A[band])))
    w = np.abs(A[band]) ** 2
    slope = np.sum(w * f[band] * phase) / np.sum(w * f[band] ** 2)
    return -slope / (2 * np.pi)


def test_pulse_has_half_amplitude_at_band_edges():
    f0, fb = 5e6, 0.5
    peak = pulse_spectrum(np.array([f0]), f0, fb)[0]
    edges = pulse_spectrum(np.array([f0 * (1 - fb / 2), f0 * (1 + fb / 2)]), f0, fb)
    assert edges / peak == pytest.approx([0.5, 0.5], rel=1e-4)
    # sigma of the envelope: 0.150 us for 5 MHz, 50 %
    assert pulse_sigma_s(f0, fb) == pytest.approx(math.sqrt(2 * math.log(2)) / (math.pi * 2.5e6))


def test_bone_echo_arrives_at_round_trip_time():
    # a 2 us record with the echo in the middle, so the envelope has no edge effects
    codes, vpc = _records(np.zeros(1), n_samples=1000, delay_s=9.65e-6)
    env = np.abs(signal.hilbert(codes[0].astype(float)))
    expected = (2 * QUIET.bone_depth_m / QUIET.speed_of_sound_m_s - 9.65e-6) * FS
    # the envelope is 175 samples wide (FWHM) and quantised: its centroid within 1 sample
    top = env > 0.5 * env.max()
    centroid = np.sum(np.arange(1000)[top] * env[top]) / np.sum(env[top])
    assert abs(centroid - expected) <= 1.0


def test_layers_are_exact_fractional_delays():
    import scipy.fft as sfft

    from pelvislab.sim_instruments.echo import layer_spectrum, synthesize_layers

    n_fft = 1125
    f = sfft.rfftfreq(n_fft, 1 / FS)[:40]
    shape = pulse_spectrum(f, 5e6, 0.5)
    t0 = 305.2 / FS
    shifts = np.array([[0.0, 0.37 / FS, -12.5 / FS]])
    y = synthesize_layers(layer_spectrum(f, [t0], [1.0], shape)[None, :], shifts, f, n_fft,
                          600, FS)
    t = np.arange(600) / FS
    sigma = pulse_sigma_s(5e6, 0.5)
    for row, shift in zip(y, shifts[0], strict=True):
        tau = t - t0 - shift
        ref = np.exp(-(tau**2) / (2 * sigma**2)) * np.cos(2 * np.pi * 5e6 * tau)
        assert np.abs(row - ref).max() < 1e-12


def test_displacement_toward_transducer_makes_echo_earlier_by_2u_over_c():
    u = np.array([0.0, 2e-6, -3e-6])
    codes, _ = _records(u, n_samples=1000, delay_s=9.65e-6)
    x = codes.astype(float)
    for k in (1, 2):
        measured = _delay_between(x[0], x[k])
        # 8-bit quantisation of a noiseless echo leaves a few hundredths of a sample
        assert measured == pytest.approx(-2 * u[k] / QUIET.speed_of_sound_m_s, abs=0.05 / FS)


def test_trigger_offset_convention_matches_segmented_record():
    # sample n is at delay + n/fs + offset: a negative offset samples earlier times, so
    # the echo appears later in the record, by -offset.
    offsets = np.array([0.0, -1.0e-9])
    codes, _ = _records(np.zeros(2), offsets=offsets, n_samples=1000, delay_s=9.65e-6)
    measured = _delay_between(codes[0].astype(float), codes[1].astype(float))
    assert measured == pytest.approx(1.0e-9, abs=0.05 / FS)


def test_snr_is_peak_envelope_over_noise_rms():
    receiver = Receiver(gain_db=40.0, snr_db=30.0)
    peak_v = bone_echo_peak_v(QUIET, receiver, FS)
    silent = replace(receiver, enabled=False)  # noise only
    codes, vpc = _records(np.zeros(400), receiver=silent, full_scale_v=1.0)
    noise_rms_v = codes.astype(float).std() * vpc
    # quantisation adds vpc^2/12 of variance
    expected = peak_v / 10 ** (30 / 20)
    assert math.sqrt(noise_rms_v**2 - vpc**2 / 12) == pytest.approx(expected, rel=0.03)


def test_default_echo_fills_half_of_the_quantiser_range_without_clipping():
    codes, vpc = _records(np.zeros(50), acoustics=Acoustics(), receiver=Receiver())
    peak_codes = np.abs(codes.astype(float)).max(axis=1)
    assert 0.4 * 128 < np.median(peak_codes) < 0.75 * 128
    assert np.all(codes > -128) and np.all(codes < 127)


def test_high_gain_clips_at_the_code_limits():
    codes, _ = _records(np.zeros(5), receiver=replace(CLEAN, gain_db=60.0))
    assert codes.max() == 127 and codes.min() == -128
    assert codes.dtype == np.int8


def test_quantize_convention():
    codes, vpc = quantize(np.array([0.0, 0.1, -0.6, 0.6]), full_scale_v=1.0, offset_v=0.0)
    assert vpc == 1.0 / 256
    assert codes.tolist() == [0, round(0.1 * 256), -128, 127]
    codes, vpc = quantize(np.array([0.2]), full_scale_v=1.0, offset_v=0.1)
    assert codes[0] * vpc - 0.1 == pytest.approx(0.2, abs=vpc)


def test_seeded_and_reproducible():
    kw = dict(acoustics=Acoustics(), receiver=Receiver())
    u = 1e-6 * np.sin(np.arange(300) * 0.1)
    a, _ = _records(u, seed=3, **kw)
    b, _ = _records(u, seed=3, **kw)
    c, _ = _records(u, seed=4, **kw)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)


def test_speckle_pattern_is_fixed_by_its_seed_and_lies_above_the_bone():
    acoustics = Acoustics(speckle_level_db=-20.0)
    kw = dict(n_samples=1000, delay_s=9.65e-6)
    a, _ = _records(np.zeros(1), acoustics=acoustics, speckle_seed=1, **kw)
    b, _ = _records(np.zeros(1), acoustics=acoustics, speckle_seed=1, **kw)
    c, _ = _records(np.zeros(1), acoustics=acoustics, speckle_seed=2, **kw)
    bone_only, _ = _records(np.zeros(1), **kw)
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    bone = int(round((2 * acoustics.bone_depth_m / acoustics.speed_of_sound_m_s - 9.65e-6) * FS))
    speckle = a[0].astype(int) - bone_only[0]
    assert np.all(speckle[bone + 300:] == 0)  # 4 sigma after the bone echo: bone shadow
    assert np.abs(speckle[: bone - 150]).max() >= 3


def test_attenuation_lowers_and_downshifts_deeper_echoes():
    f = np.array([3e6, 5e6, 7e6])
    g = attenuation_gain(f, 0.03)
    assert g[1] == pytest.approx(10 ** (-50 * 5 * 0.03 / 20))
    assert g[0] > g[1] > g[2]
    shallow = bone_echo_peak_v(Acoustics(bone_depth_m=10e-3), Receiver(), FS)
    deep = bone_echo_peak_v(Acoustics(bone_depth_m=30e-3), Receiver(), FS)
    assert deep < shallow


def test_successive_echoes_correlate_as_snr_predicts():
    """Correlation of two echoes of a still bone: rho = E / (E + N sigma^2) per record."""
    receiver = Receiver(snr_db=20.0)
    codes, _ = _records(np.zeros(200), acoustics=Acoustics(), receiver=receiver)
    x = codes.astype(float)
    x -= x.mean(axis=1, keepdims=True)
    rho = np.mean(np.sum(x[1:] * x[:-1], axis=1)
                  / np.sqrt(np.sum(x[1:] ** 2, axis=1) * np.sum(x[:-1] ** 2, axis=1)))
    clean, _ = _records(np.zeros(1), acoustics=Acoustics(), receiver=replace(receiver,
                                                                                snr_db=math.inf))
    energy = np.sum(clean.astype(float) ** 2)
    peak = np.abs(signal.hilbert(clean[0].astype(float))).max()
    noise_var = (peak / 10) ** 2 + 1 / 12
    predicted = energy / (energy + 500 * noise_var)
    assert rho == pytest.approx(predicted, abs=0.01)
    assert 0.8 < rho < 0.99
