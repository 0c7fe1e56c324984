"""Small synthetic pulse-echo records for the tracking unit tests and benchmark.

Not the physical simulator (that is ``sim_instruments``): one Gaussian-modulated pulse per
segment at a known arrival time, optional weaker echoes (skin/fat interfaces), white Gaussian
noise at a set SNR, and 8-bit quantisation.

Timing convention (the one ``pelvislab.acquisition.tracking`` expects, docs/tracking.md):
sample ``n`` of segment ``k`` holds the signal at time ``delay_s + trigger_offset_s[k] + n /
sample_rate_hz`` after that segment's trigger (= the instant the pulser fires).

SNR convention: ``snr_db = 20 log10(peak envelope amplitude / noise standard deviation)``,
both in counts before quantisation.
"""

from __future__ import annotations

import numpy as np


def pulse_sigma_s(center_frequency_hz: float, fractional_bandwidth: float) -> float:
    """Envelope standard deviation (s) of a Gaussian pulse with the given -6 dB bandwidth."""
    sigma_f = fractional_bandwidth * center_frequency_hz / (2.0 * np.sqrt(2.0 * np.log(2.0)))
    return 1.0 / (2.0 * np.pi * sigma_f)


def gaussian_pulse(t_s: np.ndarray, center_frequency_hz: float = 5e6,
                   fractional_bandwidth: float = 0.6) -> np.ndarray:
    """Unit-peak Gaussian-modulated cosine centred on t = 0."""
    sig = pulse_sigma_s(center_frequency_hz, fractional_bandwidth)
    return np.exp(-0.5 * (t_s / sig) ** 2) * np.cos(2.0 * np.pi * center_frequency_hz * t_s)


def gaussian_pulse_derivative(t_s: np.ndarray, center_frequency_hz: float = 5e6,
                              fractional_bandwidth: float = 0.6) -> np.ndarray:
    """d/dt of :func:`gaussian_pulse` (1/s)."""
    sig = pulse_sigma_s(center_frequency_hz, fractional_bandwidth)
    w = 2.0 * np.pi * center_frequency_hz
    env = np.exp(-0.5 * (t_s / sig) ** 2)
    return env * (-(t_s / sig**2) * np.cos(w * t_s) - w * np.sin(w * t_s))


def synth_echoes(arrival_s: np.ndarray, *, n_samples: int = 500, sample_rate_hz: float = 500e6,
                 delay_s: float = 0.0, trigger_offset_s: np.ndarray | None = None,
                 amplitude_counts: float = 100.0, snr_db: float | None = 30.0,
                 center_frequency_hz: float = 5e6, fractional_bandwidth: float = 0.6,
                 extra_echoes: tuple[tuple[float, float], ...] = (),
                 rng: np.random.Generator | None = None,
                 quantise: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """Synthetic segmented record: ``(codes, trigger_offset_s)``.

    arrival_s: (n_pulses,) arrival time of the echo centre after each trigger (s).
    trigger_offset_s: (n_pulses,) horPos per segment; default uniform in [-1/fs, 0).
    extra_echoes: (time shift s relative to the main echo, relative amplitude) pairs that move
    with the main echo (they model shallower, weaker interfaces).
    Returns int8 codes (or float64 when ``quantise`` is False) and the trigger offsets used.
    """
    rng = np.random.default_rng() if rng is None else rng
    arrival_s = np.asarray(arrival_s, dtype=float).reshape(-1)
    n = arrival_s.size
    if trigger_offset_s is None:
        trigger_offset_s = -rng.uniform(0.0, 1.0, n) / sample_rate_hz
    trigger_offset_s = np.asarray(trigger_offset_s, dtype=float).reshape(n)
    t = delay_s + trigger_offset_s[:, None] + np.arange(n_samples)[None, :] / sample_rate_hz
    x = amplitude_counts * gaussian_pulse(t - arrival_s[:, None], center_frequency_hz,
                                          fractional_bandwidth)
    for shift_s, rel in extra_echoes:
        x += rel * amplitude_counts * gaussian_pulse(
            t - arrival_s[:, None] - shift_s, center_frequency_hz, fractional_bandwidth)
    if snr_db is not None:
        x += rng.normal(0.0, noise_sd_counts(amplitude_counts, snr_db), x.shape)
    if not quantise:
        return x, trigger_offset_s
    return np.clip(np.rint(x), -128, 127).astype(np.int8), trigger_offset_s


def noise_sd_counts(amplitude_counts: float, snr_db: float) -> float:
    """Noise standard deviation (counts) giving ``snr_db`` for a pulse of that peak amplitude."""
    return amplitude_counts / 10.0 ** (snr_db / 20.0)


def delay_crb_s(*, amplitude_counts: float, noise_sd_counts: float,
                sample_rate_hz: float = 500e6, center_frequency_hz: float = 5e6,
                fractional_bandwidth: float = 0.6) -> float:
    """Cramér–Rao bound (standard deviation, s) for the delay of one echo of known shape.

    Deterministic (specular) matched-filter bound, the fully correlated limit of Walker &
    Trahey (1995): ``var(tau) >= sigma_n^2 / sum_n s'(t_n)^2`` for white Gaussian noise of
    variance ``sigma_n^2`` per sample and an echo ``s`` sampled at ``t_n``.
    """
    t = np.arange(-4096, 4097) / sample_rate_hz
    ds = amplitude_counts * gaussian_pulse_derivative(t, center_frequency_hz,
                                                      fractional_bandwidth)
    return float(noise_sd_counts / np.sqrt(np.sum(ds**2)))
