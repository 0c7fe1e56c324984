"""The gap verdict's view of a diagnosis made by hand (χ² values, no fitting), for tests
of :func:`pelvislab.model.gap._verdict_stage` and its significance tests."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from pelvislab.model import gap


def fitted_result(effect: str, place_kind: str, n_params: int, held: float, fitted: float,
                  held_n: int, *, beyond_null: float | None = None, variant: str = "",
                  place: str = "") -> SimpleNamespace:
    """A candidate's fit: held-out χ² ``held`` over ``held_n`` lines, fitted-line χ²
    ``fitted``, one place tried, no tolerance note."""
    return SimpleNamespace(
        candidate=SimpleNamespace(effect=effect, place_kind=place_kind, n_params=n_params,
                                  variant=variant, place=place),
        screened_places=1, chi2_heldout=held, chi2_fitted=fitted, chi2_calibrated=0.0,
        beyond_null=beyond_null, theta=np.ones(2), tolerance_note="",
        score=held + 2 * n_params, gap_after=gap.excess_gap(held, held_n))


def verdict_stages(ranked, base_held: float, base_fitted: float, held_n: int, fit_n: int,
                   *, refit: tuple[float, float] | None = None,
                   own_starts: tuple[float, float] | None = None) -> SimpleNamespace:
    """The diagnosis's stages as the verdict reads them: a base fit with held-out χ²
    ``base_held`` and fitted-line χ² ``base_fitted``, σ declared (H_std), and for each of
    ``ranked`` the base refitted from its parameters at ``refit`` (fitted, held-out χ²;
    default the base fit's own)."""
    fitted, held = (base_fitted, base_held) if refit is None else refit
    return SimpleNamespace(
        opt=gap.GapOptions(), data=SimpleNamespace(noise_source="H_std"),
        chi2_base=base_held, chi2_base_fitted=base_fitted, chi2_own_starts=own_starts,
        base_refits={id(r): (r, np.ones(2), fitted, held) for r in ranked},
        fit=SimpleNamespace(n=fit_n), held=SimpleNamespace(n=held_n),
        gap_before=gap.excess_gap(base_held, held_n), base_refitted_from=None, timing={})


#: the verdict's calibration null when the data show no per-FRF gains
NO_CALIBRATION = SimpleNamespace(chi2_base=1e9, evident=False, gap_before=0.0)
