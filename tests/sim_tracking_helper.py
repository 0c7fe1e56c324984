"""A small, independent echo tracker for the simulated-bench tests (not the product's).

Phase-slope delay of every echo against the mean echo over the pulse band, the per-segment
trigger offset applied (SegmentedRecord convention), d = c * dt / 2 positive toward the
transducer, and a least-squares sine fit at the drive frequency.
"""

from __future__ import annotations

import numpy as np


def track(record, speed_of_sound_m_s: float, band_hz=(3e6, 7e6)) -> np.ndarray:
    """Displacement (m) of every echo relative to echo 0, positive toward the transducer."""
    x = record.volts()
    x = x - x.mean(axis=1, keepdims=True)
    n = 2048
    X = np.fft.rfft(x, n, axis=1)
    f = np.fft.rfftfreq(n, 1.0 / record.sample_rate_hz)
    band = (f >= band_hz[0]) & (f <= band_hz[1])
    ref = X[0]
    cross = X[:, band] * np.conj(ref[band])[None, :]
    phase = np.unwrap(np.angle(cross), axis=1)
    w = np.abs(ref[band]) ** 2
    fb = f[band]
    slope = (phase * (w * fb)[None, :]).sum(axis=1) / np.sum(w * fb**2)
    shift_s = -slope / (2 * np.pi)  # delay of echo k in the record relative to echo 0
    tof_change_s = shift_s + record.trigger_offset_s - record.trigger_offset_s[0]
    return -speed_of_sound_m_s * tof_change_s / 2.0


def phasor(displacement_m: np.ndarray, prf_hz: float, frequency_hz: float) -> complex:
    """Least-squares phasor U (peak, m) of u(t) = Re(U e^{i w t}) + a + b t, t_0 = 0."""
    t = np.arange(displacement_m.size) / prf_hz
    w = 2 * np.pi * frequency_hz
    A = np.column_stack([np.cos(w * t), -np.sin(w * t), np.ones_like(t), t])
    coef, *_ = np.linalg.lstsq(A, displacement_m, rcond=None)
    return complex(coef[0], coef[1])
