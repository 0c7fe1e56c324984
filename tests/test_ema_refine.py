"""The pole refinement (pole/residue fit) and residual modes of the EMA, on the pelvis model.

Appendix E with the thesis' ch. 11 layout and 1 % proportional noise (the fixture of
``test_ema_pelvis``). p-LSCF poles minimise an equation error and are biased where few lines
cover a mode; the refinement fits the FRFs themselves; the pelvis model's 303.6 Hz mode sits
just above a 5-300 Hz sweep and must be fitted as a residual mode (docs/ema.md).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from pelvislab.acquisition.frfset import Channels, FrfSet, write_frf
from pelvislab.app.cli import main
from pelvislab.model.ema import ema, pole_frequency_damping, poles_from_modal, refine_poles
from pelvislab.model.frf import frf
from pelvislab.tests.test_ema_estimator import modal_receptance
from pelvislab.tests.test_ema_pelvis import pelvis  # noqa: F401  (fixture)


def _frf(pelvis, f, n_in):  # noqa: F811
    model, outputs, inputs, *_ = pelvis
    return frf(model, f, outputs, inputs)[:, :, :n_in]


def _noisy(H0, seed):
    rng = np.random.default_rng(seed)
    return H0 * (1 + 0.01 * (rng.normal(size=H0.shape) + 1j * rng.normal(size=H0.shape))
                 / np.sqrt(2))


def _damping_errors(result, modes, inband):
    out = []
    for r in inband:
        j = int(np.argmin(np.abs(result.frequency_hz - modes.natural_frequencies_hz[r])))
        assert abs(result.frequency_hz[j] / modes.natural_frequencies_hz[r] - 1) < 0.01
        out.append(result.damping_ratio[j] / modes.damping_ratios[r] - 1)
    return np.array(out)


def test_refinement_removes_the_lscf_bias_on_a_non_uniform_grid(pelvis):  # noqa: F811
    """Non-uniform ~1 Hz grid, two inputs: p-LSCF alone overestimates the 174.9 Hz mode's
    damping by 14-17 % (measured on 3 draws); refined, the largest error of the five modes is
    below 10 % and that mode's below 2 %."""
    _, _, _, modes, _, inband = pelvis
    f = np.sort(np.random.default_rng(5).uniform(5.0, 300.0, 300))
    H = _noisy(_frf(pelvis, f, 2), 1)
    plain = _damping_errors(ema(f, H, refine=False), modes, inband)
    refined = _damping_errors(ema(f, H, refine=True), modes, inband)
    assert plain[3] > 0.10, plain  # the bias this test is about
    assert abs(refined[3]) < 0.02 and np.abs(refined).max() < 0.10, refined


def test_mode_just_above_the_band_is_fitted_as_a_residual_mode(pelvis):  # noqa: F811
    """Noise-free, 2.5 Hz grid, true poles as the start: with per-line weights the 303.6 Hz
    mode's tail biases the refined damping of the in-band modes (measured up to 7.1 %); with
    it as a residual mode at most 0.57 %. The default analysis finds that pole itself and
    does not report it as a mode."""
    _, _, _, modes, _, inband = pelvis
    f = np.arange(5.0, 300.0 + 1e-9, 2.5)
    H0 = _frf(pelvis, f, 1)
    fn, zn = modes.natural_frequencies_hz, modes.damping_ratios
    true = poles_from_modal(fn[inband], zn[inband])
    above = poles_from_modal(fn[inband[-1] + 1: inband[-1] + 2],
                             zn[inband[-1] + 1: inband[-1] + 2])
    assert 300 < fn[inband[-1] + 1] < 310
    std = 0.01 * np.abs(H0)
    _, z_without = pole_frequency_damping(refine_poles(f, H0, true, std))
    _, z_with = pole_frequency_damping(refine_poles(f, H0, np.concatenate([true, above]), std))
    assert np.abs(z_without / zn[inband] - 1).max() > 0.04  # measured 7.1 % (38.1 Hz)
    assert np.abs(z_with[: inband.size] / zn[inband] - 1).max() < 0.01  # measured 0.57 %

    result = ema(f, _noisy(H0, 3), refine=True)
    assert result.frequency_hz.size == inband.size
    f_res, _ = pole_frequency_damping(result.residual_poles)
    assert f_res.size == 1 and abs(f_res[0] / fn[inband[-1] + 1] - 1) < 0.005, f_res
    assert any("residual mode" in n for n in result.notes)
    without = ema(f, _noisy(H0, 3), residual_poles=False)
    assert without.residual_poles.size == 0


def test_reported_uncertainties_match_the_scatter_over_noise_draws(pelvis):  # noqa: F811
    """2.5 Hz grid (the thesis' stepped sine), 10 draws: for every mode the rms damping and
    frequency errors are at most 2x the median reported standard uncertainty (never badly
    optimistic) and at least a quarter of it (HC3 is conservative: 231.9 Hz frequency 0.35).
    The 0.06 % and 0.02 % damped modes are not resolved on this grid (errors ~10 %), and
    their std says so. (HC1, without the leverage correction, read the 112 Hz mode's damping
    std 2.2x too small; the plain residual-variance formula 8x.)"""
    _, _, _, modes, _, inband = pelvis
    f = np.arange(5.0, 300.0 + 1e-9, 2.5)
    H0 = _frf(pelvis, f, 1)
    fn, zn = modes.natural_frequencies_hz[inband], modes.damping_ratios[inband]
    z_err, z_sd, f_err, f_sd = [], [], [], []
    for seed in range(1, 11):
        r = ema(f, _noisy(H0, seed), refine=True)
        j = [int(np.argmin(np.abs(r.frequency_hz - x))) for x in fn]
        z_err.append(r.damping_ratio[j] - zn)
        z_sd.append(r.damping_ratio_std[j])
        f_err.append(r.frequency_hz[j] - fn)
        f_sd.append(r.frequency_std_hz[j])
    z_ratio = np.sqrt(np.mean(np.square(z_err), axis=0)) / np.median(z_sd, axis=0)
    f_ratio = np.sqrt(np.mean(np.square(f_err), axis=0)) / np.median(f_sd, axis=0)
    assert np.all((z_ratio > 0.25) & (z_ratio < 2.0)), z_ratio
    assert np.all((f_ratio > 0.25) & (f_ratio < 2.0)), f_ratio
    assert np.median(z_sd, axis=0)[1] / zn[1] > 0.05  # the unresolved 38 Hz mode says so


def test_cli_reports_uncertainties_and_residual_modes(pelvis, tmp_path, capsys):  # noqa: F811
    _, outputs, inputs, *_ = pelvis
    f = np.arange(5.0, 300.0 + 1e-9, 2.5)
    H = _noisy(_frf(pelvis, f, 1), 3)
    n = outputs.position_m.shape[0]
    out_ch = Channels([f"o{k}" for k in range(n)], list(outputs.bone), outputs.position_m,
                      outputs.direction)
    in_ch = Channels(["drive"], [inputs.bone[0]], inputs.position_m[:1], inputs.direction[:1])
    write_frf(tmp_path / "s.h5", FrfSet(f, H, out_ch, in_ch))
    assert main(["ema", str(tmp_path / "s.h5"), "--refine", "--json",
                 str(tmp_path / "a.json")]) == 0
    doc = json.loads((tmp_path / "a.json").read_text())
    assert len(doc["modes"]) == 5 and "refined" in doc["method"]
    assert all(m["damping_ratio_std"] > 0 and m["frequency_std_hz"] > 0 for m in doc["modes"])
    assert len(doc["residual_modes"]) == 1
    assert 300 < doc["residual_modes"][0]["frequency_hz"] < 305
    assert "+/-" in capsys.readouterr().err
    assert main(["ema", str(tmp_path / "s.h5"), "--json", str(tmp_path / "b.json"),
                 "--plot"]) == 0
    png = tmp_path / "b_stabilisation.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["ema", str(tmp_path / "s.h5"), "--json", str(tmp_path / "c.json"),
                 "--plot"]) == 0
    # refused before the analysis: an existing plot, or a plot with the JSON on stdout
    (tmp_path / "d_stabilisation.png").write_bytes(b"keep")
    assert main(["ema", str(tmp_path / "s.h5"), "--json", str(tmp_path / "d.json"),
                 "--plot"]) == 1
    assert not (tmp_path / "d.json").exists()
    assert (tmp_path / "d_stabilisation.png").read_bytes() == b"keep"
    assert main(["ema", str(tmp_path / "s.h5"), "--json", "-", "--plot"]) == 1
    doc = json.loads((tmp_path / "b.json").read_text())
    assert all(m["damping_ratio_std"] is None for m in doc["modes"])
    assert "refined" not in doc["method"]


@pytest.mark.parametrize("refine", [False, True])
def test_refinement_only_on_request(pelvis, refine):  # noqa: F811
    _, _, _, modes, _, inband = pelvis
    f = np.arange(5.0, 300.0 + 1e-9, 2.5)
    H = _noisy(_frf(pelvis, f, 1), 3)
    result = ema(f, H, frequencies_hz=[174.9, 231.9], refine=refine)
    assert result.selection == "manual"
    assert np.all(np.isnan(result.damping_ratio_std)) == (not refine)
    assert np.all(np.isnan(ema(f, H, refine=refine).damping_ratio_std)) == (not refine)
    # off by default: a mode left out of the selection pulls the refined poles (docs/ema.md)
    assert np.all(np.isnan(ema(f, H).damping_ratio_std))


def test_an_frf_with_zero_h_std_does_not_cost_a_real_mode():
    """H_std of 0 (or NaN) for a whole FRF: LSFD leaves it out, so the significance check
    must too. It scored the misfit of that unfitted FRF, dropped the 90 Hz mode (found by
    session 32's review), and the refinement then fitted two poles to three modes."""
    rng = np.random.default_rng(2)
    f = np.arange(10.0, 110.0, 0.5)
    poles = poles_from_modal(np.array([30.0, 62.0, 90.0]), np.array([0.02, 0.01, 0.03]))
    phi, part = rng.normal(size=(3, 3)), rng.normal(size=(2, 3))
    H0 = modal_receptance(f, poles, phi, part)
    H = _noisy(H0, 1)
    std = 0.01 * np.abs(H0)
    std[:, 1, 1] = 0.0
    for refine in (False, True):
        result = ema(f, H, H_std=std, refine=refine)
        np.testing.assert_allclose(result.frequency_hz, [30.0, 62.0, 90.0], rtol=2e-3)


def test_a_mode_in_a_gap_of_a_random_grid_is_kept_and_a_pulled_pole_is_flagged():
    """A random grid left no line within the significance window (1.5 Hz) of a clear
    37.5 Hz mode: the check saw no line, scored 1 and dropped the mode; the refinement then
    pushed the other pole to its bounds (29.40 Hz, damping doubled). Now the 2 nearest lines
    on each side count. A pole that a left-out mode pulls to the bounds is named in the
    notes and gets no std (found by the property test, tests/test_ema_properties.py)."""
    from pelvislab.tests.test_ema_properties import _frf

    f, H, _ = _frf(np.array([30.0, 37.5]), np.array([0.03125, 0.03125]), 1, 1, 588, "random")
    result = ema(f, H, refine=True)
    np.testing.assert_allclose(result.frequency_hz, [30.0, 37.5], rtol=2e-3)
    pulled = ema(f, H, frequencies_hz=[30.0], refine=True)  # the 37.5 Hz mode left out
    assert any("to their bounds" in n for n in pulled.notes), pulled.notes
    assert np.all(np.isnan(pulled.damping_ratio_std))


def test_cli_ignores_an_all_zero_h_std_and_says_why_few_lines_find_no_mode(tmp_path, capsys):
    """H_std written as zeros (another tool): weighed as absent with a note, not a hard
    error. A diagram too short to show a mode: the note names its order limit and
    --max-order, not the grid's resolution (both found by session 32's user review)."""
    from pelvislab.tests.test_ema_properties import _frf

    f, H, _ = _frf(np.array([40.0]), np.array([0.05]), 2, 1, 3, "uniform")
    out_ch = Channels(["a", "b"], ["", ""], np.zeros((2, 3)), np.tile([0.0, 0.0, 1.0], (2, 1)))
    in_ch = Channels(["drive"], [""], np.zeros((1, 3)), [[0.0, 0.0, 1.0]])
    write_frf(tmp_path / "z.h5", FrfSet(f, H, out_ch, in_ch, H_std=np.zeros(H.shape)))
    assert main(["ema", str(tmp_path / "z.h5"), "--json", str(tmp_path / "z.json")]) == 0
    doc = json.loads((tmp_path / "z.json").read_text())
    assert any("H_std holds no positive" in n for n in doc["notes"])
    assert len(doc["modes"]) == 1 and abs(doc["modes"][0]["frequency_hz"] / 40.0 - 1) < 0.01
    few = np.linspace(30.0, 50.0, 9)
    write_frf(tmp_path / "few.h5", FrfSet(few, np.interp(few, f, H[:, 0, 0].real)[:, None, None]
                                           + 1j * np.interp(few, f, H[:, 0, 0].imag)[:, None,
                                                                                     None],
                                           Channels(["a"], [""], np.zeros((1, 3)),
                                                    [[0.0, 0.0, 1.0]]), in_ch))
    # nine lines reach order 12 since the default's floor (review of the EMA path), which
    # finds the mode; a diagram cut at order 5 says why it finds none
    assert main(["ema", str(tmp_path / "few.h5"), "--json", str(tmp_path / "few.json")]) == 0
    modes = json.loads((tmp_path / "few.json").read_text())["modes"]
    assert len(modes) == 1 and abs(modes[0]["frequency_hz"] / 40.0 - 1) < 0.01
    assert main(["ema", str(tmp_path / "few.h5"), "--max-order", "5",
                 "--json", str(tmp_path / "few5.json")]) == 0
    notes = json.loads((tmp_path / "few5.json").read_text())["notes"]
    assert any("up to order 5 only" in n and "try --max-order 12" in n for n in notes), notes


def test_every_automatically_selected_mode_passes_the_significance_check():
    """Dropping a pole changes its neighbours' significance: the check (and that of the edge
    poles) is repeated until every kept pole passes. With one round, a random search of the
    property test's systems kept a spurious 72.5 Hz mode at 1.23 and a 10.8 Hz one at 1.2
    beside two true modes."""
    from pelvislab.tests.test_ema_properties import _frf

    cases = [((56.53195813, 74.14081529), (0.03522043, 0.0064447), 2, 1, 8665, "uniform"),
             ((52.95968612, 58.2433223), (0.00364949, 0.04985804), 2, 1, 3129, "random")]
    for fn, zeta, n_out, n_in, seed, grid in cases:
        f, H, _ = _frf(np.array(fn), np.array(zeta), n_out, n_in, seed, grid)
        result = ema(f, H)
        np.testing.assert_allclose(result.frequency_hz, fn, rtol=2e-3)
        assert np.all(result.significance >= 1.25), result.significance
