"""Property test of the EMA (p-LSCF, significance, residual modes, with and without the pole
refinement) on random modal systems and grids: it never crashes, reports finite
uncertainties for refined modes, and finds well-resolved, well-separated modes where they
are."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pelvislab.model.ema import ema, poles_from_modal
from pelvislab.tests.test_ema_estimator import modal_receptance


@st.composite
def modal_sets(draw):
    n_modes = draw(st.integers(1, 3))
    # well separated (>= 25 %) so that each is its own mode on any grid below
    f0 = draw(st.floats(30.0, 60.0))
    ratios = draw(st.lists(st.floats(1.25, 1.6), min_size=n_modes - 1, max_size=n_modes - 1))
    fn = f0 * np.cumprod([1.0, *ratios])
    zeta = np.array(draw(st.lists(st.floats(0.005, 0.05), min_size=n_modes,
                                  max_size=n_modes)))
    n_out, n_in = draw(st.integers(1, 4)), draw(st.integers(1, 2))
    seed = draw(st.integers(0, 10_000))
    grid = draw(st.sampled_from(["uniform", "random", "gappy"]))
    return fn, zeta, n_out, n_in, seed, grid


def _frf(fn, zeta, n_out, n_in, seed, grid):
    rng = np.random.default_rng(seed)
    lo, hi = 10.0, 1.25 * fn[-1]
    # a line spacing that resolves the lightest mode (half-power bandwidth / 2), and at least
    # 60 lines, as a stepped-sine sweep has (with 15 lines the diagram has 5 orders, too
    # few for the selection rule's 4 fully stable ones: docs/ema.md)
    step = min(float(min(2 * zeta * fn)) / 2, (hi - lo) / 60)
    f = np.arange(lo, hi, step)
    if grid == "random":
        f = np.sort(rng.uniform(lo, hi, f.size))
    elif grid == "gappy":
        f = f[rng.uniform(size=f.size) > 0.2]
    poles = poles_from_modal(fn, zeta)
    phi = rng.normal(size=(n_out, fn.size)) + 0.2
    part = rng.normal(size=(n_in, fn.size)) + 0.2
    H = modal_receptance(f, poles, phi, part)
    noise = (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape)) / np.sqrt(2)
    # each mode's largest modal constant over the channels, relative to the largest of all
    visible = np.abs(phi[:, None, :] * part[None, :, :]).max(axis=(0, 1))
    return f, H * (1 + 0.005 * noise), visible / visible.max()


@settings(max_examples=25)
@given(modal_sets(), st.booleans())
def test_analysis_finds_resolved_modes_and_reports_their_uncertainty(case, refine):
    fn, zeta, n_out, n_in, seed, grid = case
    f, H, visible = _frf(fn, zeta, n_out, n_in, seed, grid)
    result = ema(f, H, refine=refine)
    assert np.all(np.isfinite(result.frequency_hz)) and np.all(result.damping_ratio > 0)
    for k in range(fn.size):
        if visible[k] < 0.1:  # a mode whose modal constant is tiny at every channel may
            continue          # go unseen (1 % of the other one's: below the noise)
        j = int(np.argmin(np.abs(result.frequency_hz - fn[k]))) if result.frequency_hz.size \
            else -1
        assert j >= 0 and abs(result.frequency_hz[j] / fn[k] - 1) < 0.01, \
            (fn, result.frequency_hz, result.notes)
        assert abs(result.damping_ratio[j] / zeta[k] - 1) < 0.3, (zeta, result.damping_ratio)
    refined = np.isfinite(result.damping_ratio_std)
    assert refine or not refined.any()
    assert np.all(result.damping_ratio_std[refined] > 0)
    assert np.all(np.isfinite(result.frequency_std_hz[refined]))
    assert np.isfinite(result.fit_error())
