"""FRF updating (thesis ch. 6.2, 7): Jacobians, recovery, uncertainty, on a small chain model.

The chain is a test fixture (a few masses and springs), not a pelvis model: it keeps these
tests fast. The pelvis-model cases live in test_identification_pelvis.py and the benchmark.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.identification import (
    FrfProblem,
    ResidualSpec,
    Strategy,
    SystemMatrices,
    _Target,
    covariance_report,
    frf_with_jacobian,
    identify_frf,
)


def chain_problem(n: int = 3, seed: int = 0, damping: float = 2.0) -> FrfProblem:
    """n masses in a grounded chain; parameters m_i, k_i and one dashpot factor c."""
    rng = np.random.default_rng(seed)
    names = [f"m{i}" for i in range(n)] + [f"k{i}" for i in range(n)] + ["c"]
    nominal = np.concatenate([rng.uniform(0.5, 1.5, n), rng.uniform(1e4, 3e4, n), [damping]])
    z = np.zeros((n, n))
    dMs = [np.diag(np.eye(n)[i]) for i in range(n)]
    dKs = []
    for i in range(n):
        g = np.zeros(n)
        g[i] = 1
        if i > 0:
            g[i - 1] = -1
        dKs.append(np.outer(g, g))
    c_shape = sum(dKs)

    def assemble(p: np.ndarray) -> SystemMatrices:
        M = sum(mi * d for mi, d in zip(p[:n], dMs, strict=True))
        K = sum(ki * d for ki, d in zip(p[n:2 * n], dKs, strict=True))
        return SystemMatrices(
            M, p[-1] * c_shape, K,
            np.array(dMs + [z] * (n + 1)), np.array([z] * (2 * n) + [c_shape]),
            np.array([z] * n + dKs + [z]),
        )

    return FrfProblem(tuple(names), nominal, assemble, np.eye(n)[[0, n - 1]],
                      np.eye(n)[:, [n - 1]], 2 * np.pi * 80)


def synth(problem: FrfProblem, values: np.ndarray, f: np.ndarray, f_k: float = 0.0,
          f_c: float = 0.0) -> np.ndarray:
    H, _ = frf_with_jacobian(problem.assemble(values), problem.outputs, problem.inputs, f,
                             f_k=f_k, f_c=f_c, omega_max_rad_s=problem.omega_max_rad_s,
                             jacobian=False)
    return H


def test_frf_jacobian_matches_finite_differences() -> None:
    p = chain_problem(4)
    f = np.linspace(1.0, 60.0, 25)
    x = p.nominal
    _, dH = frf_with_jacobian(p.assemble(x), p.outputs, p.inputs, f, f_k=0.3, f_c=0.2,
                              omega_max_rad_s=p.omega_max_rad_s, freq_dep_jacobian=True)
    for j in range(p.n_params):
        h = x[j] * 1e-6
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        fd = (synth(p, xp, f, 0.3, 0.2) - synth(p, xm, f, 0.3, 0.2)) / (2 * h)
        assert np.max(np.abs(fd - dH[:, j])) < 1e-5 * np.max(np.abs(dH[:, j]))
    for col, (fk, fc) in ((p.n_params, (0.3 + 1e-6, 0.2)), (p.n_params + 1, (0.3, 0.2 + 1e-6))):
        fk_m, fc_m = 0.6 - fk, 0.4 - fc
        fd = (synth(p, x, f, fk, fc) - synth(p, x, f, fk_m, fc_m)) / 2e-6
        assert np.max(np.abs(fd - dH[:, col])) < 1e-5 * np.max(np.abs(dH[:, col]))


@pytest.mark.parametrize("kind", ["eq610", "std", "log"])
def test_residual_jacobian_matches_finite_differences(kind: str) -> None:
    p = chain_problem(3)
    f = np.linspace(2.0, 50.0, 20)
    rng = np.random.default_rng(1)
    H_meas = synth(p, p.nominal * 1.1, f)
    H_std = 0.01 * np.abs(H_meas) + 1e-9
    target = _Target.build(f, H_meas, H_std, ResidualSpec(kind, a=0.3, b=1.0))
    x = p.nominal * (1 + 0.05 * rng.uniform(-1, 1, p.n_params))
    H, dH = frf_with_jacobian(p.assemble(x), p.outputs, p.inputs, f)
    J = target.jacobian(H, dH)
    r0 = target.residual(H)
    assert r0.shape == (2 * H_meas.size,) == (J.shape[0],)
    for j in range(p.n_params):
        h = x[j] * 1e-7
        xp = x.copy()
        xp[j] += h
        fd = (target.residual(synth(p, xp, f)) - r0) / h
        assert np.allclose(fd, J[:, j], rtol=1e-4, atol=1e-5 * np.max(np.abs(J[:, j])))


@pytest.mark.parametrize("kind", ["log", "eq610"])
def test_recovers_parameters_from_perturbed_start(kind: str) -> None:
    p = chain_problem(4, seed=2)
    f = np.arange(2.0, 80.0, 1.0)
    rng = np.random.default_rng(5)
    true = p.nominal * (1 + 0.3 * rng.uniform(-1, 1, p.n_params))
    res = identify_frf(p, f, synth(p, true, f), residual=ResidualSpec(kind),
                       strategy=Strategy(max_starts=10, stop_rms=1e-7))
    assert res.converged, res.message
    np.testing.assert_allclose(res.values, true, rtol=1e-6)
    assert res.evaluations > 0 and res.wall_time_s > 0
    d = res.as_dict()
    assert set(d["parameters"]) == set(p.names)
    assert d["parameters"]["k0"]["value"] == pytest.approx(true[4], rel=1e-6)
    low, high = d["parameters"]["k0"]["interval_95"]
    assert low < d["parameters"]["k0"]["value"] < high


def test_wrong_start_is_reported_not_hidden() -> None:
    """A single start far away with a tight noise target must say it did not converge."""
    p = chain_problem(4, seed=2)
    f = np.arange(2.0, 80.0, 1.0)
    true = p.nominal.copy()
    start = p.nominal * np.array([3, 0.3, 3, 0.3, 3, 0.3, 3, 0.3, 1])
    res = identify_frf(p, f, synth(p, true, f), start=start, residual=ResidualSpec("eq610"),
                       strategy=Strategy(max_starts=1, stop_rms=1e-9, max_nfev=5))
    assert not res.converged
    assert "above the target" in res.message


def test_version_b_recovers_frequency_dependence() -> None:
    p = chain_problem(3, seed=4)
    f = np.arange(2.0, 80.0, 1.0)
    true = p.nominal * 1.15
    H = synth(p, true, f, f_k=0.7, f_c=0.4)
    res = identify_frf(p, f, H, version_b=True, start_freq_dep=(0.0, 0.0),
                       strategy=Strategy(max_starts=6, stop_rms=1e-7))
    assert res.converged, res.message
    assert res.names[-2:] == ["f_k", "f_c"]
    np.testing.assert_allclose(res.values[:-2], true, rtol=1e-6)
    np.testing.assert_allclose(res.values[-2:], [0.7, 0.4], atol=1e-6)


def test_standard_errors_match_the_scatter_of_noisy_fits() -> None:
    """With H_std-weighted residuals the reported std must describe the actual error."""
    p = chain_problem(3, seed=6, damping=20.0)
    f = np.arange(2.0, 60.0, 1.0)
    H0 = synth(p, p.nominal, f)
    sigma = 0.02 * np.abs(H0)
    rng = np.random.default_rng(0)
    z = []
    for _ in range(12):
        noise = sigma / np.sqrt(2) * (rng.standard_normal(H0.shape)
                                      + 1j * rng.standard_normal(H0.shape))
        res = identify_frf(p, f, H0 + noise, sigma, residual=ResidualSpec("std"),
                           strategy=Strategy(max_starts=1))
        z.append((res.values - p.nominal) / res.std)
    z = np.array(z)
    # normalised errors should be ~N(0, 1): their rms within a generous band
    assert 0.5 < np.sqrt(np.mean(z**2)) < 1.6


def test_identifiability_flags_invisible_combination() -> None:
    # Two identical columns: the sum is seen, the difference is not.
    J = np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 1.0], [0.5, 0.5, 3.0], [1.0, 1.0, 1.0]])
    std, corr, s, weak = covariance_report(J, np.zeros(4), ["a", "b", "c"],
                                           np.ones(3), absolute_sigma=True)
    assert s[-1] < 1e-10 * s[0]
    assert not weak[0]["resolved"]
    assert set(weak[0]["combination"]) == {"a", "b"}
    assert np.isnan(std[0]) and np.isnan(std[1]) and np.isfinite(std[2])


def test_bad_inputs_raise_clear_errors() -> None:
    p = chain_problem(3)
    f = np.arange(2.0, 10.0)
    H = synth(p, p.nominal, f)
    with pytest.raises(ValueError, match="unknown parameter"):
        identify_frf(p, f, H, free=["nope"])
    with pytest.raises(ValueError, match="H_std"):
        identify_frf(p, f, H, residual=ResidualSpec("std"))
    with pytest.raises(ValueError, match="no measured"):
        identify_frf(p, f, np.full_like(H, np.nan))
