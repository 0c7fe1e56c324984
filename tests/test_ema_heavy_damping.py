"""A heavily damped mode and the automatic selection (review of the EMA path, follow-up).

A single mode, two outputs, 1 Hz grid 5-300 Hz, 1 % proportional noise with H_std. Before:
the 35 %-damped mode's p-LSCF poles scatter by 2-3 % between orders, so the 1 % stability
rule often missed it (14 of 60 draws), and where it was found its pole was 1.5-3 % low;
the misfit left (chi^2 per value ~6) was taken up by light noise poles that passed the
significance check at 1.26-1.73 (37 extra modes in 60 draws). Now such poles are judged
with a tolerance of 5 % of their half-power bandwidth and fitted on the FRFs before the
check (`polish_wide_poles`): the mode in every draw, no extra mode (docs/ema.md).
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.ema import (
    StabilityCriteria,
    ema,
    poles_from_modal,
    select_poles,
    stabilisation_diagram,
)
from pelvislab.tests.test_ema_estimator import modal_receptance
from pelvislab.tests.test_ema_missing_mode import _modal_frf

F_HZ = np.arange(5.0, 300.01, 1.0)


def _one_mode(frequency_hz, damping_ratio, trial):
    rng = np.random.default_rng([7, trial])
    shapes = rng.normal(size=(2, 1))
    H0 = _modal_frf([frequency_hz], [damping_ratio], shapes)
    e = (rng.normal(size=H0.shape) + 1j * rng.normal(size=H0.shape)) / np.sqrt(2)
    return H0 * (1 + 0.01 * e), 0.01 * np.abs(H0)


@pytest.mark.parametrize("trial", [0, 2, 5, 7])
def test_a_heavily_damped_mode_is_found_alone_and_where_it_is(trial):
    # these draws gave, before: no mode at 150 Hz and two or three light ones elsewhere
    # (0, 7), or the mode 3 % low with a light one beside it at significance 1.4-1.6 (2, 5)
    H, std = _one_mode(150.0, 0.35, trial)
    result = ema(F_HZ, H, H_std=std)
    assert result.frequency_hz.size == 1, (result.frequency_hz, result.significance)
    assert result.frequency_hz[0] == pytest.approx(150.0, rel=0.005)
    assert result.damping_ratio[0] == pytest.approx(0.35, rel=0.02)
    chi2 = np.mean(np.abs(result.H_fit - H) ** 2 / std**2)
    assert chi2 < 1.3  # the fit explains the data to the noise


def test_bandwidth_tolerance_leaves_light_poles_alone():
    crit = StabilityCriteria()
    assert crit.frequency_tolerance(0.005) == crit.frequency_tol
    assert crit.frequency_tolerance(0.35) == pytest.approx(0.035)
    # light poles 0.9 % apart may be one mode; a light and a heavy one 0.5 % apart may not
    assert crit.same_pole(100.0, 0.01, 100.9, 0.02)
    assert not crit.same_pole(100.0, 0.02, 100.5, 0.35)
    assert crit.same_pole(100.0, 0.30, 103.0, 0.35)


def test_two_light_close_modes_are_still_told_apart():
    # the bandwidth tolerance is frequency_tol below zeta 0.1: two modes 1.5 % apart
    rng = np.random.default_rng(3)
    fr, zr = np.array([100.0, 101.5]), np.array([0.003, 0.004])
    f = np.arange(80.0, 120.0, 0.05)
    H0 = modal_receptance(f, poles_from_modal(fr, zr), rng.normal(size=(3, 2)),
                          rng.normal(size=(1, 2)))
    H = H0 * (1 + 0.01 * (rng.normal(size=H0.shape) + 1j * rng.normal(size=H0.shape))
              / np.sqrt(2))
    poles = select_poles(stabilisation_diagram(f, H, H_std=0.01 * np.abs(H0)), (80, 120))
    np.testing.assert_allclose(np.abs(poles) / (2 * np.pi), fr, rtol=3e-3)
