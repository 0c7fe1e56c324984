"""Evidence on the pelvis model (appendix E): synthetic FRFs with 1 % noise, 5-300 Hz.

Outputs: the thesis' ch. 11 layout (13 landmarks, triaxial, 39 channels); inputs: the ch. 7
drive on the left iliac fossa and the sacrum. Reference: the model's state-space modes.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.assembly import point_rows
from pelvislab.model.ema import ema
from pelvislab.model.frf import Points, frf
from pelvislab.model.landmarks import load_landmarks
from pelvislab.model.modal import mac, model_modes
from pelvislab.model.pelvis import load_model
from pelvislab.tests.test_ema_rigid_body import triaxial_geometry


@pytest.fixture(scope="module")
def pelvis():
    model = load_model()
    modes = model_modes(model)
    bones, pos, dirs = triaxial_geometry()
    cat = load_landmarks()
    drive = cat["iliac_fossa_drive_L"]
    inputs = Points((drive.bone, "sacrum"), [drive.position_m, cat["sacrum_x"].position_m],
                    [-drive.direction, [1.0, 0.0, 0.0]])
    outputs = Points(tuple(bones), pos, dirs)
    shapes = point_rows(model, bones, pos, dirs) @ modes.shapes
    inband = (modes.natural_frequencies_hz >= 5) & (modes.natural_frequencies_hz <= 300)
    assert inband.sum() == 5  # appendix E: 10.4, 38.1, 112.0, 174.9, 231.9 Hz
    return model, outputs, inputs, modes, shapes, np.flatnonzero(inband)


def _noisy(model, outputs, inputs, step_hz, seed):
    f = np.arange(5.0, 300.0 + 1e-9, step_hz)
    H = frf(model, f, outputs, inputs)
    rng = np.random.default_rng(seed)
    noise = (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape)) / np.sqrt(2)
    return f, H * (1 + 0.01 * noise)


def _errors(result, modes, shapes, inband):
    fe, ze, macs = [], [], []
    for r in inband:
        j = int(np.argmin(np.abs(result.frequency_hz - modes.natural_frequencies_hz[r])))
        fe.append(result.frequency_hz[j] / modes.natural_frequencies_hz[r] - 1)
        ze.append(result.damping_ratio[j] / modes.damping_ratios[r] - 1)
        macs.append(mac(shapes[:, r], result.shapes[:, j])[0, 0])
    return np.abs(fe), np.abs(ze), np.array(macs)


def test_pelvis_quarter_hertz_grid_meets_the_targets(pelvis):
    """Every mode in band, frequency <= 0.3 %, damping <= 10 %, MAC >= 0.98. The 0.25 Hz grid
    is what the 0.06 % damped 38 Hz mode needs (measured, 3 seeds: damping errors <= 6.3 % at
    0.25 Hz, <= 13.7 % at 0.5 Hz, <= 1.1 % at 0.1 Hz; see docs/ema.md)."""
    model, outputs, inputs, modes, shapes, inband = pelvis
    f, H = _noisy(model, outputs, inputs, 0.25, 2)
    result = ema(f, H)
    assert result.frequency_hz.size == inband.size, result.frequency_hz
    fe, ze, macs = _errors(result, modes, shapes, inband)
    assert fe.max() <= 0.003, fe
    assert ze.max() <= 0.10, ze
    assert macs.min() >= 0.98, macs


def test_pelvis_stepped_sine_grid(pelvis):
    """Thesis stepped sine (2.5 Hz). Appendix E damping is tiny (0.02-0.5 %): half-power
    bandwidths of 0.05-2 Hz, below the line spacing. Frequencies and shapes still meet the
    targets; damping meets 10 % for the modes with zeta >= 0.2 % only (the 0.06 % and
    0.02 % modes are not resolved: errors of 10-130 % measured)."""
    model, outputs, inputs, modes, shapes, inband = pelvis
    f, H = _noisy(model, outputs, inputs, 2.5, 3)
    result = ema(f, H)
    assert result.frequency_hz.size == inband.size, result.frequency_hz
    fe, ze, macs = _errors(result, modes, shapes, inband)
    assert fe.max() <= 0.003 and macs.min() >= 0.98, (fe, macs)
    resolved = modes.damping_ratios[inband] >= 0.002
    assert ze[resolved].max() <= 0.10, ze


def test_demo_protocol_grid_resolves_its_two_zoomed_modes():
    """`make demo`'s protocol: a 10 Hz grid with zoom windows across the 174.9 Hz (zeta
    0.23 %) and 231.9 Hz (zeta 0.52 %) modes. On model FRFs at its drive and pick-up points
    with 3 % noise the EMA must find both, frequency <= 0.05 %, damping <= 15 %; the 10 Hz
    grid alone finds none (docs/ema.md)."""
    from importlib import resources

    from pelvislab.acquisition.protocol import load_protocol

    protocol = load_protocol(str(resources.files("pelvislab.protocols") / "demo.toml"))
    f = np.asarray(protocol.sweep.frequencies_hz, dtype=float)
    cat = load_landmarks()
    names_in = sorted({s.excitation for s in protocol.setups})
    names_out = sorted({p for s in protocol.setups for p in s.transducers.values()})
    inputs = Points(tuple(cat[n].bone for n in names_in), [cat[n].position_m for n in names_in],
                    [-cat[n].direction for n in names_in])
    outputs = Points(tuple(cat[n].bone for n in names_out),
                     [cat[n].position_m for n in names_out],
                     [cat[n].direction for n in names_out])
    model = load_model()
    modes = model_modes(model)
    H = frf(model, f, outputs, inputs)
    rng = np.random.default_rng(30)
    H = H * (1 + 0.03 * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape)) / np.sqrt(2))
    result = ema(f, H)
    assert result.frequency_hz.size >= 2, result.notes
    for r in np.flatnonzero((modes.natural_frequencies_hz > 170)
                            & (modes.natural_frequencies_hz < 240)):
        j = int(np.argmin(np.abs(result.frequency_hz - modes.natural_frequencies_hz[r])))
        assert abs(result.frequency_hz[j] / modes.natural_frequencies_hz[r] - 1) <= 5e-4
        assert abs(result.damping_ratio[j] / modes.damping_ratios[r] - 1) <= 0.15
    coarse = np.isclose(f % 10.0, 0.0)
    assert ema(f[coarse], H[coarse]).frequency_hz.size == 0
    # with H_std the 112 Hz mode between the 10 Hz lines leaves misfit beyond the noise
    # near 90-110 Hz: a pole fitted there runs into the lightest damping allowed and is
    # not kept as a heavily damped mode (fit_missing_pole)
    with_std = ema(f, H, H_std=0.03 * np.abs(H))
    np.testing.assert_allclose(with_std.frequency_hz, result.frequency_hz, rtol=1e-3)


@pytest.mark.parametrize("seed", [7, 10, 21, 30])
def test_a_zoom_window_alone_finds_its_mode(seed):
    """A 25-line zoom window (0.25 Hz) across the 174.9 Hz mode, analysed alone (`--band
    172 178` on `make demo`'s session): the default diagram stopped at order n/3 = 8, where
    the mode was fully stable at 3 orders of the 4 the selection needs, and gave "no stable
    pole" with a hint that lighter modes fall between the lines (this one spans 3 lines);
    on these model FRFs in 4 of 40 draws (these seeds). Pelvis zoom windows of 13-31 lines,
    1 % noise: 43 of 60 found their mode before the floor of 12 orders, 60 of 60 after
    (review of the EMA path)."""
    cat = load_landmarks()
    names = ["sacrum_x", "SIAS_R_x", "SIAS_L_x", "SIPS_R_x", "SIPS_L_x"]
    outputs = Points(tuple(cat[n].bone for n in names), [cat[n].position_m for n in names],
                     [cat[n].direction for n in names])
    inputs = Points((cat["SIAS_R_x"].bone,), [cat["SIAS_R_x"].position_m],
                    [-cat["SIAS_R_x"].direction])
    model = load_model()
    modes = model_modes(model)
    r = int(np.argmin(np.abs(modes.natural_frequencies_hz - 174.9)))
    f = np.arange(172.0, 178.01, 0.25)
    H = frf(model, f, outputs, inputs)
    rng = np.random.default_rng(seed)
    H = H * (1 + 0.01 * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape)) / np.sqrt(2))
    result = ema(f, H, H_std=0.01 * np.abs(H))
    assert result.frequency_hz.size == 1, result.notes
    assert result.frequency_hz[0] == pytest.approx(modes.natural_frequencies_hz[r], rel=5e-4)
    assert result.damping_ratio[0] == pytest.approx(modes.damping_ratios[r], rel=0.1)
