"""EMA on FRFs measured over part of the band (a run stopped, a setup measured another band):
a mode's shape has no entry from an FRF without lines around it (replay review, session 36:
the demo stopped at 173.75 Hz made an output the 231.9 Hz mode's reference, 1.0 where the
complete session gives 0.69, with the other entries near 0)."""

from __future__ import annotations

import numpy as np

from pelvislab.model.ema import ema, frfs_around_modes, poles_from_modal
from pelvislab.tests.test_ema_estimator import (
    add_noise,
    analytic_system,
    receptance,
    reference_modes,
)


def test_an_frf_stopped_before_a_mode_gives_it_no_shape_entry():
    M, K, C = analytic_system(6, seed=1)
    lam, V = reference_modes(M, K, C)
    f = np.arange(5.0, 300.01, 1.0)
    H = add_noise(receptance(M, K, C, f, list(range(6)), [0]), 0.002, seed=4)
    full = ema(f, H)
    fn = full.frequency_hz
    assert fn.size >= 3
    stop_hz = 0.5 * (fn[-2] + fn[-1])  # output 5 stops between the last two modes
    cut = H.copy()
    cut[f > stop_hz, 5, 0] = np.nan
    part = ema(f, cut)
    np.testing.assert_allclose(part.frequency_hz, fn, rtol=1e-3)
    last = part.shapes[:, -1]
    assert np.isnan(last[5]) and np.all(np.isfinite(last[:5]))
    # the other entries as the complete data give them (same normalisation: largest 1)
    ref = full.shapes[:5, -1] / full.shapes[np.nanargmax(np.abs(full.shapes[:5, -1])), -1]
    np.testing.assert_allclose(np.abs(last[:5]), np.abs(ref), atol=0.02)
    assert np.all(np.isfinite(part.shapes[:, 0]))  # modes below the stop keep output 5
    assert any("shape entries left out" in n and "1 FRF(s)" in n for n in part.notes)
    assert not any("shape entries left out" in n for n in full.notes)


def test_lines_on_both_sides_and_one_near_the_mode():
    f = np.arange(100.0, 200.01, 2.0)
    measured = np.ones((f.size, 3, 1), dtype=bool)
    measured[f > 149.0, 1, 0] = False  # stops just below the mode at 150 Hz
    measured[(f > 120) & (f < 180), 2, 0] = False  # a gap around it
    around = frfs_around_modes(f, measured, poles_from_modal(np.array([150.0]),
                                                             np.array([0.01])))
    assert around[0, :, 0].tolist() == [True, False, False]


def test_the_reach_follows_the_lines_around_the_mode_not_the_whole_grid():
    # review of session 36's diff: the demo's grid (10 Hz lines, 0.5 Hz zoom windows) has
    # a 0.5 Hz median spacing, and a complete session's 105 Hz mode got no FRF at all
    f = np.unique(np.concatenate([np.arange(30.0, 301.0, 10.0), np.arange(172.0, 178.01, 0.25),
                                  np.arange(226.0, 238.01, 0.5)]))  # protocols/demo.toml
    assert np.median(np.diff(f)) == 0.5
    measured = np.ones((f.size, 4, 2), dtype=bool)
    poles = poles_from_modal(np.array([105.0, 174.9]), np.array([0.008, 0.002]))
    assert frfs_around_modes(f, measured, poles).all()


def test_an_input_without_frfs_around_a_mode_has_no_participation():
    from pelvislab.model.ema import shapes_from_residues

    residues = np.ones((1, 3, 2), dtype=complex)
    measured = np.ones((1, 3, 2), dtype=bool)
    measured[0, :, 1] = False  # input 1 measured nowhere around this mode
    shapes, part = shapes_from_residues(residues, measured)
    assert np.isfinite(shapes[:, 0]).all()
    assert np.isfinite(part[0, 0]) and np.isnan(part[0, 1])  # was 0: "does not excite it"
