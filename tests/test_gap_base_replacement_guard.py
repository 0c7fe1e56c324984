"""A base refit that replaced the base fit never makes a candidate's pass easier (issue 10).

The base refitted from a leading candidate's θ replaces the base fit when it fits the
*fitted* lines better (``model.gap._adopt_better_base``). It can then fit the held-out
lines worse than the base fit from the model's own starts, which would enlarge every
candidate's held-out χ² drop. A candidate must then also pass against the own-starts
base fit. The verdict's test (``_Significance``) is exercised here on stand-in χ² values
(exact noise, one extra parameter, one place tried: critical drop 10.83 at p = 1e-3).
"""

from types import SimpleNamespace

import numpy as np
import pytest
from scipy.stats import chi2 as chi2_dist

from pelvislab.model.gap import GapOptions, _Calibration, _Significance

CRIT = float(chi2_dist.isf(1e-3, 1))


def _stages(chi2_held: float, chi2_fitted: float, own: tuple[float, float] | None,
            candidate: SimpleNamespace, refit: tuple[float, float]) -> SimpleNamespace:
    """Stand-in for ``_Stages``: the base (replaced when ``own`` is given) and the cached
    refit of the base from ``candidate``'s θ (fitted, held-out χ²)."""
    return SimpleNamespace(
        opt=GapOptions(), data=SimpleNamespace(noise_source="H_std"),
        chi2_base=chi2_held, chi2_base_fitted=chi2_fitted, chi2_own_starts=own,
        base_refitted_from=None if own is None else candidate,
        base_refits={id(candidate): (candidate, np.ones(1), *refit)})


def _candidate(chi2_held: float, chi2_fitted: float) -> SimpleNamespace:
    return SimpleNamespace(
        candidate=SimpleNamespace(n_params=1, effect="added_mass", place_kind="bone"),
        screened_places=1,
        chi2_heldout=chi2_held, chi2_fitted=chi2_fitted, chi2_calibrated=chi2_held,
        beyond_null=None)


def _test(chi2_held_cand: float, own: tuple[float, float] | None,
          base_held: float = 330.0):
    cand = _candidate(chi2_held_cand, 868.0)
    # the candidate's own base refit fits worse than the replacing one: not the null
    s = _stages(base_held, 870.0, own, cand, refit=(900.0, 300.0))
    cal = _Calibration(base_held, np.ones(3), 0.0, CRIT, evident=False)
    return _Significance(s, cal, {})(cand)


def test_pass_only_against_a_replacing_refit_that_fits_held_out_lines_worse_fails():
    # replacing refit: fitted 870 < 980, but held out 330 > 310 (own starts)
    test = _test(315.0, own=(980.0, 310.0))
    assert test.drop == pytest.approx(-5.0)  # against the own-starts base fit
    assert not test.significant
    assert test.null_kind == "own_starts"
    assert test.null_chi2_fitted == pytest.approx(980.0)


def test_pass_against_both_bases_stands():
    test = _test(290.0, own=(980.0, 310.0))
    assert test.significant
    assert test.drop == pytest.approx(40.0)  # reported against the replacing refit
    assert test.null_kind == "base"


def test_replacing_refit_that_fits_held_out_lines_better_is_the_only_null():
    # own starts fit the held-out lines worse (340 > 330): nothing more to pass
    test = _test(315.0, own=(980.0, 340.0))
    assert test.significant
    assert test.drop == pytest.approx(15.0)
    assert test.null_kind == "base"


def test_without_a_replacement_the_base_fit_is_the_null():
    assert _test(315.0, own=None).significant
    assert not _test(322.0, own=None).significant  # drop 8 < 10.83
