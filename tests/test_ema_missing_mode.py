"""The EMA notes where its modes leave the data beyond the noise, away from every mode found
(issue 9's module; session 32's review: a heavily damped mode was missed silently).

Synthetic FRFs by modal superposition with H_std written, as design 4.2 defines it.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.ema import ema, misfit_beyond_noise, poles_from_modal
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


def test_a_heavily_damped_mode_left_out_is_noted_where_it_is():
    """A 25 % damped mode at 150 Hz between two 1 % modes, as strong as they (shape x5):
    over 8 noise and shape draws the selection leaves it out in most (it does not
    stabilise over orders), and each time the note points within 20 Hz of it; when it is
    found there is no such note."""
    missed = 0
    for trial in range(8):
        H, std = _heavily_damped_middle_mode(trial)
        result = ema(F_HZ, H, H_std=std)
        notes = [n for n in result.notes if "away from every mode found" in n]
        if np.any(np.abs(result.frequency_hz - 150) < 10):
            assert not notes, notes
            continue
        missed += 1
        (note,) = notes
        f_note = float(note.split("the data near ")[1].split(" Hz")[0])
        assert abs(f_note - 150) <= 20, note
    assert missed >= 4  # the case the note is for did occur


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
    for trial in range(8):
        H, std = _heavily_damped_middle_mode(trial)
        plain = ema(F_HZ, H, H_std=std)
        if np.any(np.abs(plain.frequency_hz - 150) < 10):
            continue  # found: no note to check
        assert not any("--refine" in n for n in plain.notes)
        refined = ema(F_HZ, H, H_std=std, refine=True)
        notes = [n for n in refined.notes if "away from every mode found" in n]
        assert notes and "compare without --refine" in notes[0], refined.notes
        return
    pytest.fail("no draw left the 150 Hz mode out")


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
