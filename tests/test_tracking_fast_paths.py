"""The tracker's shortcuts give exactly what the plain numpy expressions they replace give."""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.acquisition import tracking
from pelvislab.acquisition.tracking import auto_gate
from pelvislab.tests.echo_synth import synth_echoes

FS = 500e6


@pytest.mark.parametrize("dtype", [np.int8, np.int16, np.float64])
@pytest.mark.parametrize("start", [100, 101])
@pytest.mark.parametrize("width", [296, 297])
@pytest.mark.parametrize("par", [0, 1])
def test_every_other_sample_as_float32(dtype, start, width, par):
    rng = np.random.default_rng(start + width + par)
    codes = rng.integers(-128, 128, (50, 500)).astype(dtype)  # -128 and 127 included
    W = codes[:, start: start + width]
    got = tracking._every_other_float32(W, par)
    assert got.dtype == np.float32 and got.flags.c_contiguous
    np.testing.assert_array_equal(got, W[:, par::2].astype(np.float32))


def _gate_by_fft(codes: np.ndarray, band: tuple[float, float], threshold: float = 0.1,
                 margin: int = 5) -> tuple[int, int]:
    """auto_gate's envelope as two full FFTs (the definition the DFT path must match)."""
    x = codes[:8].astype(float)
    x -= x.mean(axis=1, keepdims=True)
    m = x.shape[1]
    nfft = 2 * m
    f = np.fft.fftfreq(nfft, 1.0 / FS)
    keep = np.where((f >= band[0]) & (f <= band[1]), 2.0, 0.0)
    env = np.abs(np.fft.ifft(np.fft.fft(x, nfft, axis=1) * keep, axis=1)[:, :m]).mean(axis=0)
    k = int(np.argmax(env))
    below = env < threshold * env[k]
    left, right = np.nonzero(below[:k])[0], np.nonzero(below[k:])[0]
    start = (left[-1] + 1 if left.size else 0) - margin
    stop = (k + right[0] if right.size else m) + margin
    return max(0, int(start)), min(m, int(stop))


@pytest.mark.parametrize("band", [(2e6, 8e6), (0.5e6, 60e6)])  # 13 bins (DFT), 119 (FFT)
def test_auto_gate_envelope_matches_the_fft_definition(band):
    rng = np.random.default_rng(4)
    arrival = 0.5e-6 + rng.uniform(-2e-9, 2e-9, 16)
    codes, _ = synth_echoes(arrival, snr_db=20.0, rng=rng,
                            extra_echoes=((-0.25e-6, 0.3), (0.2e-6, 0.5)))
    assert auto_gate(codes, FS, band_hz=band) == _gate_by_fft(codes, band)
    x = codes[:8].astype(float)
    x -= x.mean(axis=1, keepdims=True)
    nfft = 2 * x.shape[1]
    bins = np.nonzero((np.fft.fftfreq(nfft, 1 / FS) >= band[0])
                      & (np.fft.fftfreq(nfft, 1 / FS) <= band[1]))[0]
    fwd, inv = tracking._band_dft(x.shape[1], nfft, tuple(bins.tolist()))
    spec = np.fft.fft(x, nfft, axis=1)
    np.testing.assert_allclose(x @ fwd, spec[:, bins], rtol=0, atol=1e-9 * np.abs(spec).max())
    only = np.zeros_like(spec)
    only[:, bins] = spec[:, bins]
    np.testing.assert_allclose((x @ fwd) @ inv, np.fft.ifft(only, axis=1)[:, : x.shape[1]],
                               rtol=0, atol=1e-9 * np.abs(x).max())


def test_int8_shortcuts_give_the_generic_results():
    # int8 codes take the int16-pair read, one product for the aligned reference and
    # np.vecdot for the window energies (sums exact in any order); int16 codes of the same
    # values take the generic path. Every output must be bit-identical.
    rng = np.random.default_rng(15)
    t = np.arange(1000) / 5000.0
    arrival = 0.5e-6 - 2 * 2e-6 * np.sin(2 * np.pi * 180 * t) / 1540.0
    codes, off = synth_echoes(arrival, snr_db=25.0, rng=rng)
    a = tracking.track_echoes(codes, off, FS, 1540.0)
    b = tracking.track_echoes(codes.astype(np.int16), off, FS, 1540.0)
    for name in ("delay_s", "correlation", "snr_db", "lost", "peak_hops"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.echo_amplitude_v == b.echo_amplitude_v
