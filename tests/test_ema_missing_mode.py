"""The EMA notes where its modes leave the data beyond the noise, away from every mode found
(issue 9's module; session 32's review: a heavily damped mode was missed silently), and,
with the automatic selection, fits a heavily damped mode there when the data show one
(fit_missing_pole).

Synthetic FRFs by modal superposition with H_std written, as design 4.2 defines it.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.ema import ema, fit_missing_pole, misfit_beyond_noise, poles_from_modal
from pelvislab.tests.test_ema_estimator import (
    add_noise,
    analytic_system,
    modal_receptance,
    receptance,
)

F_HZ = np.arange(5.0, 300.01, 1.0)


def _modal_frf(frequency_hz, damping_ratio, shapes):
    """Receptance (n_f, n_out, 1) of modes with the given shapes, driven at output 0."""
    poles = poles_from_modal(np.asarray(frequency_hz), np.asarray(damping_ratio))
    return modal_receptance(F_HZ, poles, shapes, shapes[:1])


def _noisy(H0, rng):
    std = 0.01 * np.abs(H0).max(axis=0, keepdims=True) * np.ones(H0.shape)
    e = (rng.normal(size=H0.shape) + 1j * rng.normal(size=H0.shape)) / np.sqrt(2)
    return H0 + std * e, std


def _heavily_damped_middle_mode(trial):
    """Draw ``trial``: a 25 % damped mode at 150 Hz between two 1 % modes (60, 240 Hz), as
    strong as they (its shape x5), with 1 % noise; returns (H, H_std)."""
    rng = np.random.default_rng([33, trial])
    shapes = rng.normal(size=(5, 3))
    shapes[:, 1] *= 5.0
    return _noisy(_modal_frf([60, 150, 240], [0.01, 0.25, 0.01], shapes), rng)


def _note_hz(notes):
    """The frequency of the missing-mode note, or None when there is none."""
    found = [n for n in notes if "away from every mode found" in n]
    if not found:
        return None
    (note,) = found
    return float(note.split("the data near ")[1].split(" Hz")[0])


def test_a_heavily_damped_mode_the_selection_leaves_out_is_fitted():
    """A 25 % damped mode at 150 Hz between two 1 % modes, as strong as they (shape x5):
    its p-LSCF poles do not stabilise over orders, and the selection left it out in 6 of
    these 8 draws (1, 2, 3, 5, 16, 17), with a note pointing within 20 Hz of it; in 3 (2,
    3, 17) its misfit also made the 240 Hz mode fail the significance check. Now a pole is
    fitted where the misfit is (fit_missing_pole) and the check is run again with it:
    the mode in every draw (within 2.5 %, the weak ones: the refinement's std of these is
    0.5-1.9 Hz), the 240 Hz mode back where the data show it (not in draw 2, whose 240 Hz
    mode is weak at the driving point: dropped before too), no other mode, no
    missing-mode note."""
    added = 0
    for trial in (0, 1, 2, 3, 4, 5, 16, 17):
        H, std = _heavily_damped_middle_mode(trial)
        result = ema(F_HZ, H, H_std=std)
        fn, zeta = result.frequency_hz, result.damping_ratio
        j = int(np.argmin(np.abs(fn - 150)))
        assert abs(fn[j] / 150 - 1) < 0.025 and abs(zeta[j] / 0.25 - 1) < 0.05, (trial, fn, zeta)
        if trial in (3, 17):  # strong here (refined std 0.07 Hz): fitted again once the
            # 240 Hz mode is back (0.6-0.9 % off when fitted without it)
            assert abs(fn[j] / 150 - 1) < 1e-3, (trial, fn)
        assert np.all(np.min(np.abs(fn[:, None] - [60, 150, 240]), axis=1) < 3), (trial, fn)
        assert (fn.size == 3) == (trial != 2), (trial, fn)
        assert _note_hz(result.notes) is None, (trial, result.notes)
        added += any("heavily damped mode(s) fitted" in n and f"{fn[j]:.4g} Hz" in n
                     for n in result.notes)
    assert added == 6  # the draws the selection left it out in


def test_the_note_points_at_a_heavily_damped_mode_left_out():
    """Where the mode is left out, the note points within 20 Hz of it: by a manual pick
    of the other two (which adds no mode: --frequencies is the user's choice), and by the
    automatic analysis where the data barely show it (draw 19: local mean 4.8 at 138 Hz;
    a pole fitted there has significance 1.0-1.2 and is not kept)."""
    for trial in (0, 1, 2, 3):
        H, std = _heavily_damped_middle_mode(trial)
        result = ema(F_HZ, H, H_std=std, frequencies_hz=[60, 240])
        assert result.frequency_hz.size == 2
        assert abs(_note_hz(result.notes) - 150) <= 20, result.notes
    H, std = _heavily_damped_middle_mode(19)
    result = ema(F_HZ, H, H_std=std)
    assert not np.any(np.abs(result.frequency_hz - 150) < 10), result.frequency_hz
    assert abs(_note_hz(result.notes) - 150) <= 20, result.notes


@pytest.mark.parametrize("trial", [5, 8])
def test_a_light_mode_is_not_fitted_at_the_damping_floor(trial):
    """A weak 3 % damped mode at 150 Hz that the poles given leave out: the fit of a pole
    there runs into the lightest damping allowed (0.05) and, so bounded, brought the
    misfit there under the threshold in these draws; a damping at its bound is no
    estimate (67 % off here), so no pole is returned."""
    rng = np.random.default_rng([5, trial])
    shapes = rng.normal(size=(3, 2))
    shapes[:, 1] *= 0.2
    H0 = _modal_frf([60, 150], [0.01, 0.03], shapes)
    std = 0.01 * np.abs(H0).max(axis=0, keepdims=True) * np.ones(H0.shape)
    H = H0 + std * (rng.normal(size=H0.shape) + 1j * rng.normal(size=H0.shape)) / np.sqrt(2)
    assert fit_missing_pole(F_HZ, H, poles_from_modal(np.array([60.0]), np.array([0.01])),
                            std).size == 0


@pytest.mark.parametrize("seed", [0, 2, 4])
@pytest.mark.parametrize("step_hz, level", [(2.5, 0.003), (0.5, 0.01)])
def test_no_note_when_every_mode_is_found(seed, step_hz, level):
    """The analytic chains with every mode found: p-LSCF's pole bias leaves misfit at the
    modes (local mean up to 14 on these systems), not away from them."""
    M, K, C = analytic_system(seed=seed)
    f = np.arange(5.0, 300.01, step_hz)
    H0 = receptance(M, K, C, f, list(range(6)), [0, 3])
    result = ema(f, add_noise(H0, level, seed + 10), H_std=level * np.abs(H0))
    assert result.frequency_hz.size == 6
    assert not any("beyond their noise" in n for n in result.notes), result.notes


def test_misfit_beyond_noise_measures_in_noise_units():
    rng = np.random.default_rng(5)
    H_true = rng.normal(size=(40, 2, 1)) + 1j * rng.normal(size=(40, 2, 1))
    std = np.full(H_true.shape, 0.1)
    H_model = H_true.copy()
    H_model[20] += 0.5  # 5 sigma on one line, both FRFs
    chi2, f_worst, local = misfit_beyond_noise(np.arange(40.0), H_true, H_model, std)
    assert chi2 == pytest.approx(25 / 40)
    assert f_worst == 20.0
    assert local == pytest.approx(25 / 7)
    # values without a positive H_std do not count
    std[:, 1] = 0.0
    assert misfit_beyond_noise(np.arange(40.0), H_true, H_model, std)[0] == pytest.approx(
        25 / 40)


def test_the_note_warns_that_refined_poles_assumed_every_mode_selected():
    """With ``refine`` the same note says the refined poles are suspect (docs/ema.md: a
    mode left out pulls them); without it, it does not."""
    H, std = _heavily_damped_middle_mode(1)
    plain = ema(F_HZ, H, H_std=std, frequencies_hz=[60, 240])
    assert _note_hz(plain.notes) is not None
    assert not any("--refine" in n for n in plain.notes)
    refined = ema(F_HZ, H, H_std=std, frequencies_hz=[60, 240], refine=True)
    notes = [n for n in refined.notes if "away from every mode found" in n]
    assert notes and "compare without --refine" in notes[0], refined.notes


def test_misfit_beyond_noise_on_fewer_lines_than_its_window():
    # validation_phase.toml measures 5 lines: the 7-line window made an IndexError
    # (`pelvislab ema` on its sessions failed; review, session 36)
    H_true = np.ones((5, 1, 1), complex)
    H_model = H_true.copy()
    H_model[3] += 0.3
    chi2, f_worst, local = misfit_beyond_noise(np.arange(5.0), H_true, H_model,
                                               np.full(H_true.shape, 0.1))
    assert chi2 == pytest.approx(9 / 5)
    # every line's neighbourhood holds line 3; those at the edges average fewer lines
    assert f_worst in (0.0, 4.0)
    assert local == pytest.approx(9 / 4)


def test_an_added_pole_whose_band_holds_no_line_away_from_the_others_explains_nothing():
    """_region_explained passed vacuously when no line of the new pole's band lay away from
    the earlier poles (review): it explained nothing it was added for."""
    from pelvislab.model.ema import _region_explained

    H, std = _heavily_damped_middle_mode(0)
    wide = poles_from_modal(np.array([150.0]), np.array([0.3]))  # reaches every line
    new = complex(poles_from_modal(np.array([150.0]), np.array([0.25]))[0])
    assert not _region_explained(F_HZ, H, H, std, wide, new)  # a perfect fit, nowhere
    light = poles_from_modal(np.array([60.0, 240.0]), np.array([0.01, 0.01]))
    assert _region_explained(F_HZ, H, H, std, light, new)
