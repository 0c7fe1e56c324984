"""FRF lines (acquisition/frf_lines.py): ratio, uncertainty, assembly into FrfSet, end to end."""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.acquisition.frf_lines import (
    FrfLine,
    assemble_frf,
    displacement_phasor,
    drive_force_phasor,
    frf_line,
    frf_ratio,
)
from pelvislab.acquisition.frfset import Channels
from pelvislab.acquisition.phasor import estimate_phasor, phase_difference_deg
from pelvislab.acquisition.tracking import track_echoes
from pelvislab.tests.echo_synth import synth_echoes

PRF, FS, C = 5000.0, 500e6, 1540.0


def _channels(names: list[str]) -> Channels:
    n = len(names)
    return Channels(names, ["sacrum"] * n, np.zeros((n, 3)), np.tile([1.0, 0.0, 0.0], (n, 1)))


def test_ratio_and_its_uncertainty_calibrated():
    rng = np.random.default_rng(0)
    x0, f0 = 2e-6 * np.exp(0.3j), 5.0 * np.exp(-0.2j)
    sx, sf = 5e-8, 0.1
    H0 = x0 / f0
    H, std = frf_ratio(x0, sx, f0, sf)
    assert H == pytest.approx(H0)
    draws = []
    for _ in range(4000):
        x = x0 + sx / np.sqrt(2) * complex(*rng.normal(size=2))
        f = f0 + sf / np.sqrt(2) * complex(*rng.normal(size=2))
        draws.append(x / f)
    actual = np.sqrt(np.mean(np.abs(np.array(draws) - H0) ** 2))
    assert actual / std == pytest.approx(1.0, abs=0.1)
    with pytest.raises(ValueError, match="zero"):
        frf_ratio(1.0, 0.0, 0.0, 0.0)


def test_drive_force_phasor_and_line():
    F = drive_force_phasor(80.0, 2.0, 3.0 * np.exp(0.1j), drive_phase_rad=0.5,
                           newton_per_volt_std=0.03)
    assert F.value == pytest.approx(3.0 * np.exp(0.6j))
    assert F.std == pytest.approx(0.03)
    t = np.arange(2000) / PRF
    X = estimate_phasor(np.real(1e-6 * np.exp(2j * np.pi * 80 * t)), t, 80.0)
    line = frf_line(X, F, "sias_r", "shaker", acquired_at_s=1.5)
    assert line.H == pytest.approx(1e-6 / F.value)
    assert line.H_std == pytest.approx(abs(line.H) * 0.01, rel=1e-6)
    with pytest.raises(ValueError, match="Hz"):
        frf_line(X, drive_force_phasor(81.0, 2.0, 3.0), "a", "b")


def test_assemble_into_frfset_with_gaps_and_repeats():
    outs, ins = _channels(["a", "b"]), _channels(["s"])
    lines = [
        FrfLine(80.0, "a", "s", 1 + 1j, 0.1, 0.0),
        FrfLine(80.0, "b", "s", 2 + 0j, 0.2, 0.1),
        FrfLine(82.5, "a", "s", 3 + 0j, 0.1, 0.5),
        FrfLine(82.5, "a", "s", 5 + 0j, 0.1, 0.9),  # repeat: inverse-variance mean
    ]
    frf = assemble_frf(lines, outs, ins)
    assert frf.frequency_hz.tolist() == [80.0, 82.5]
    assert frf.H[0, 0, 0] == 1 + 1j and frf.H[0, 1, 0] == 2
    assert frf.H[1, 0, 0] == pytest.approx(4.0)
    assert frf.H_std[1, 0, 0] == pytest.approx(0.1 / np.sqrt(2))
    assert np.isnan(frf.H[1, 1, 0]) and np.isnan(frf.H_std[1, 1, 0])
    assert frf.acquired_at_s.tolist() == [0.0, 0.5]
    with pytest.raises(KeyError):
        assemble_frf([FrfLine(80.0, "zz", "s", 1, 0.1)], outs, ins)


def test_end_to_end_two_channels_phase_shift():
    # Two bones moving at 200 Hz, the second lagging by 80.9 deg (table 8.1 row): echoes ->
    # tracking -> phasors -> FRF lines and their phase difference.
    rng = np.random.default_rng(3)
    f, n = 200.0, 2000
    t = np.arange(n) / PRF
    Xa, Xb = 2e-6 * np.exp(0.2j), 1.5e-6 * np.exp(1j * (0.2 - np.radians(80.9)))
    phasors = []
    for X in (Xa, Xb):
        d = np.real(X * np.exp(2j * np.pi * f * t))
        codes, off = synth_echoes(0.5e-6 - 2 * d / C, snr_db=30.0, rng=rng)
        phasors.append(displacement_phasor(track_echoes(codes, off, FS, C), PRF, f))
    pa, pb = phasors
    assert pa.method == "dft"
    # Relative to pulse 0 only adds a constant: the line is unaffected.
    assert abs(pa.value - Xa) < 4 * pa.std and abs(pb.value - Xb) < 4 * pb.std
    diff, std = phase_difference_deg(pa, pb)
    assert diff == pytest.approx(-80.9, abs=max(4 * std, 0.05))
    assert std < 0.5
    F = drive_force_phasor(f, 1.0, 4.0)
    frf = assemble_frf([frf_line(pa, F, "a", "s"), frf_line(pb, F, "b", "s")],
                       _channels(["a", "b"]), _channels(["s"]))
    assert frf.H[0, 1, 0] == pytest.approx(Xb / 2.0, abs=4 * frf.H_std[0, 1, 0])


def test_phasor_std_from_tracked_echoes_predicts_the_scatter():
    # Whole chain: echoes -> tracking -> phasor; the residual-based std of the displacement
    # phasor must predict the actual error (calibrated within a factor 1.4).
    rng = np.random.default_rng(4)
    f, n = 180.0, 500
    t = np.arange(n) / PRF
    errs, stds = [], []
    for _ in range(24):
        X = 0.5e-6 * np.exp(1j * rng.uniform(-np.pi, np.pi))
        d = np.real(X * np.exp(2j * np.pi * f * t))
        codes, off = synth_echoes(0.5e-6 - 2 * d / C, snr_db=25.0, rng=rng)
        p = displacement_phasor(track_echoes(codes, off, FS, C), PRF, f)
        errs.append(p.value - X)
        stds.append(p.std)
    ratio = np.sqrt(np.mean(np.abs(np.array(errs)) ** 2)) / np.mean(stds)
    assert 1 / 1.4 < ratio < 1.4
