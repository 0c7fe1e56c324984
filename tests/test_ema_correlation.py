"""COMAC, FRAC, complexity, pairing and the eq. 14.1 cost (model/correlation.py)."""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.correlation import (
    comac,
    complexity,
    complexity_plot,
    correlate,
    correlation_shapes,
    frac,
    mac_cost,
)


def _shapes(seed: int = 0, n: int = 12, m: int = 4) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, m)) + 0.05j * rng.normal(size=(n, m))


def test_comac_is_one_for_rescaled_modes_and_finds_a_bad_channel():
    a = _shapes()
    b = a * np.exp(1j * np.array([0.3, 1.0, -2.0, 0.1])) * np.array([2.0, 0.5, 1.0, 3.0])
    np.testing.assert_allclose(comac(a, b), 1.0, atol=1e-12)
    bad = b.copy()
    bad[5] = bad[5, [1, 0, 3, 2]]  # one sensor's readings shuffled between modes
    c = comac(a, bad)
    assert int(np.argmin(c)) == 5 and c[5] < 0.9 and np.delete(c, 5).min() > 0.95


def test_frac_per_frf():
    f = np.linspace(10, 100, 200)
    s = 2j * np.pi * f
    H1 = 1 / (s**2 + 2 * 0.02 * 300 * s + 300.0**2)
    H2 = 1 / (s**2 + 2 * 0.02 * 330 * s + 330.0**2)
    Ha = np.stack([H1, H1], axis=1)[:, :, None]
    Hb = np.stack([(2 - 1j) * H1, H2], axis=1)[:, :, None]
    Hb[3, 0, 0] = np.nan
    r = frac(Ha, Hb)
    assert r.shape == (2, 1)
    assert r[0, 0] == pytest.approx(1.0) and r[1, 0] < 0.99


def test_correlate_pairs_permuted_modes():
    a = _shapes(1)
    perm = [2, 0, 3, 1]
    b = a[:, perm] * 1.7
    fa = np.array([10.0, 20.0, 30.0, 40.0])
    fb = fa[perm] * 1.01
    c = correlate(fa, a, fb, b, damping_a=np.full(4, 0.02), damping_b=np.full(4, 0.01))
    assert c.pairs == [(0, 1), (1, 3), (2, 0), (3, 2)]
    np.testing.assert_allclose(c.mac, 1.0)
    np.testing.assert_allclose(c.frequency_error, 1 / 1.01 - 1)
    np.testing.assert_allclose(c.damping_difference, 0.01)
    assert c.mac_matrix.shape == (4, 4) and len(c.as_rows()) == 4
    np.testing.assert_allclose(c.comac, 1.0)


def test_mac_cost_eq_14_1():
    a = _shapes(2)
    assert mac_cost(a, a * 3j, [(0, 0), (1, 1)]) == pytest.approx(0.0, abs=1e-12)
    cost = mac_cost(a, a[:, ::-1], [(0, 0), (1, 1), (2, 2)])
    assert 0.0 < cost <= 3.0


def test_complexity_and_plot():
    real = np.array([1.0, -2.0, 0.5]) * np.exp(0.4j)
    c = complexity(real)
    assert c["complexity"][0] == pytest.approx(0.0, abs=1e-12)
    view = complexity_plot(real)
    assert view[0] == 1 and np.allclose(view.imag, 0)
    with pytest.raises(ValueError, match="zero"):
        complexity_plot(np.array([0.0, 1.0]))


def test_correlation_shapes_remove_global_motion_and_keep_bone_motion():
    rng = np.random.default_rng(3)
    pos = rng.normal(size=(14, 3)) * 0.05
    d = rng.normal(size=(14, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    bones = ["sacrum"] * 7 + ["innominate_left"] * 7
    from pelvislab.model.rigid_body import rigid_body_matrix

    Rg = rigid_body_matrix(pos, d)
    rigid = Rg @ rng.normal(size=(6, 1))
    x = correlation_shapes(rigid, bones, pos, d)
    np.testing.assert_allclose(x, 0.0, atol=1e-12)  # pure global motion leaves nothing
