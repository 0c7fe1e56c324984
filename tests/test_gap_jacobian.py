"""The gap diagnosis's least-squares Jacobian (issue 10): the solve shared with the
residual, ΔZ-direction columns for ΔZ-only effects and for a null extension's parameters
on any effect, and the columns of every other effect parameter from the same solve
(``effect_jacobian``), each against differences of the whole model's residual."""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.gap import _context, _Lines, _Model, prepare_data
from pelvislab.model.gap_effects import (
    ARMATURE_VARIANT,
    PER_DASHPOT_DAMPING,
    candidate_library,
    evaluate,
    model_jacobian,
    solve,
    with_extension,
)
from pelvislab.model.pelvis import default_model
from pelvislab.tests.test_gap_diagnosis import IN, OUT  # three outputs, two inputs

F_HZ = np.arange(5.0, 250.1, 7.5)


@pytest.fixture(scope="module")
def lines():
    """All lines of a small set whose 'measurement' is the nominal model x 1.1 (any
    values do: only derivatives are checked)."""
    ctx0 = _context(default_model(), prepare_data(
        F_HZ, np.ones((F_HZ.size, 3, 2), complex), np.ones((F_HZ.size, 3, 2)), OUT, IN))
    H = 1.1 * evaluate(ctx0, ctx0.base.nominal)[0]
    sigma = 0.01 * np.abs(H).max(axis=0, keepdims=True) * np.ones(H.shape)
    data = prepare_data(F_HZ, H, sigma, OUT, IN)
    return _Lines.build(_context(default_model(), data), data, np.ones(F_HZ.size, bool))


def candidate(ctx, effect, variant=None):
    for c in candidate_library(ctx):
        if c.effect == effect and (variant is None or c.variant == variant):
            return c
    raise AssertionError(f"no candidate {effect}")


def residual_differences(model, x, step=1e-4):
    """∂residual/∂x by central differences of the whole model (two solves per column;
    a step of 1e-4 keeps the rounding of the small damping columns below 1e-6)."""
    cols = []
    for k in range(x.size):
        h = step * max(1.0, abs(x[k]))
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        cols.append((model.residual(xp) - model.residual(xm)) / (2 * h))
    return np.stack(cols, axis=1)


def random_point(ctx, cand, seed):
    """Effect parameters u near the candidate's first start (inside its bounds) and the
    fit's x = (log θ near the nominal values, u)."""
    rng = np.random.default_rng(seed)
    u = np.clip(cand.starts[0] + rng.normal(0, 0.1, cand.n_params),
                cand.lower + 0.05, cand.upper - 0.05)
    x = np.concatenate([np.log(ctx.base.nominal) + rng.normal(0, 0.1, ctx.base.n_params),
                        u])
    return u, x


def assert_columns_close(J, J_fd, rtol=2e-3):
    for k in range(J.shape[1]):
        scale = np.max(np.abs(J_fd[:, k])) + 1e-300
        assert np.max(np.abs(J[:, k] - J_fd[:, k])) <= rtol * scale, k


@pytest.mark.parametrize("effect, variant", [
    ("added_mass", None),                                # ΔZ only: every column via ΔZ
    ("hysteretic_damping", "loss factor (K(1+i eta))"),  # a_k: a change of the factor
    ("soft_tissue", "tissue at output"),                 # ΔZ and an output gain
])
def test_jacobian_with_null_extension_matches_differences(lines, effect, variant):
    ctx = lines.ctx
    extension = candidate(ctx, PER_DASHPOT_DAMPING)
    cand = with_extension(candidate(ctx, effect, variant), extension)
    n1 = cand.n_params - extension.n_params
    assert cand.dZ_params[-extension.n_params:] == tuple(range(n1, cand.n_params))
    u, x = random_point(ctx, cand, seed=3)
    model = _Model(lines, cand, None, ctx.base.n_params)
    J = model.jacobian(x)
    assert J.shape == (2 * lines.n, ctx.base.n_params + cand.n_params)
    assert_columns_close(J, residual_differences(model, x))
    # with the base frozen, only the effect's columns
    fixed = _Model(lines, cand, np.exp(x[:ctx.base.n_params]), ctx.base.n_params)
    np.testing.assert_allclose(fixed.jacobian(u), J[:, ctx.base.n_params:], rtol=1e-12,
                               atol=1e-12 * np.abs(J).max())


def test_residual_solve_is_reused_by_the_jacobian(lines):
    ctx = lines.ctx
    model = _Model(lines, None, None, ctx.base.n_params)
    x = np.log(ctx.base.nominal)
    r = model.residual(x)
    n_solves = model.nfev
    J = model.jacobian(x.copy())
    assert model.nfev == n_solves  # the same point: no second solve
    np.testing.assert_array_equal(r, model.residual(x))
    x2 = x.copy()
    x2[0] += 1e-3
    model.residual(x2)
    assert model.nfev == n_solves + 1
    # the reused solve gives the Jacobian of a fresh evaluation
    s = solve(ctx, np.exp(x))
    np.testing.assert_array_equal(J, lines.jac(model_jacobian(ctx, s)))


@pytest.mark.parametrize("effect, variant", [
    ("frequency_dependent_stiffness", "eq7.3"),                       # a_k
    ("hysteretic_damping", "eq7.2 (D = f_c C w_max/4)"),              # a_c
    ("hysteretic_damping", "loss factor (K(1+i eta))"),               # complex a_k
    ("support_resonance", "excitation fixture"),                      # input gain
    ("support_resonance", "shaker armature on its suspension"),       # ΔZ per input + gain
    ("soft_tissue", "tissue at output"),                              # ΔZ + output gain
    ("soft_tissue", "tissue at input"),                               # ΔZ + input gain
    ("soft_tissue", "tissue under the shaker, every input"),          # ΔZ per input, shared
    ("sensor_misorientation", "tilted axis"),                         # output rows
    ("sensor_misorientation", "1/cos gain"),                          # output gain
])
def test_effect_columns_need_no_solve_and_match_differences(lines, effect, variant):
    """Effects that change more than the common ΔZ get their columns from the residual's
    solve too (``effect_jacobian``: forward differences of the terms carried through it),
    not from a solve per parameter; base and effect columns against central differences
    of the whole model."""
    ctx = lines.ctx
    cand = candidate(ctx, effect, variant)
    _u, x = random_point(ctx, cand, seed=7)
    model = _Model(lines, cand, None, ctx.base.n_params)
    model.residual(x)
    solves = model.nfev
    J = model.jacobian(x)
    assert model.nfev == solves  # no solve beyond the residual's
    # a step of 1e-5: with 1e-4 the reference itself missed k_io_R's column by 0.36 %
    # on the f_k draw (a sharp resonance), against 4e-5 with 1e-5
    assert_columns_close(J, residual_differences(model, x, step=1e-5))


@pytest.mark.parametrize("effect, variant", [
    ("added_mass", None),                          # ΔZ only: ΔZ-direction columns
    ("support_resonance", ARMATURE_VARIANT),       # a ΔZ per input (two solve groups), gain
])
def test_measured_rows_and_frozen_base_columns_are_the_full_jacobians_bits(lines, effect,
                                                                          variant):
    """model_jacobian(rows=...) forms only the measured FRFs' rows, and without the base's
    columns for a fit with the base frozen: the same values, bit for bit, as the rows and
    columns of the full array (the fits' results must not depend on it)."""
    ctx = lines.ctx
    cand = candidate(ctx, effect, variant)
    u, x = random_point(ctx, cand, seed=3)
    s = solve(ctx, np.exp(x[:ctx.base.n_params]), cand.build(u, ctx))
    dirs = None
    if effect == "added_mass":
        dirs = _Model(lines, cand, None, ctx.base.n_params)._dZ_directions(
            s, u, range(u.size))
    full = model_jacobian(ctx, s, dirs)
    full = full.reshape(-1, full.shape[-1])
    # every other measured value: rows of both inputs, not in one block
    rows = np.flatnonzero(lines.mask)[::2]
    got = model_jacobian(ctx, s, dirs, rows=rows)
    assert got.tobytes() == full[rows].tobytes()
    if dirs is not None:
        frozen = model_jacobian(ctx, s, dirs, rows=rows, base_columns=False)
        assert frozen.tobytes() == full[rows, ctx.base.n_params:].tobytes()


def test_a_kept_base_solve_is_the_fresh_solves_bits(lines):
    """solve keeps the base Z(θ) and its solve per context: a second call with the same θ
    (an effect that changes only a gain, or a ΔZ) gives what a fresh context gives."""
    ctx = lines.ctx
    theta = ctx.base.nominal * 1.05
    for cand in (candidate(ctx, "support_resonance", ARMATURE_VARIANT),
                 candidate(ctx, "added_mass")):
        u = cand.starts[0]
        first, again = (solve(ctx, theta, cand.build(u, ctx)) for _ in range(2))
        fresh_ctx = ctx.subset(np.arange(ctx.frequency_hz.size))
        fresh = solve(fresh_ctx, theta, cand.build(u, fresh_ctx))
        for s in (first, again):
            assert s.H.tobytes() == fresh.H.tobytes()
            for (cols, X), (cols_f, X_f) in zip(s.groups, fresh.groups, strict=True):
                assert cols == cols_f and X.tobytes() == X_f.tobytes()
