"""Sensitivity-based modal updating (thesis ch. 6.1, appendix C).

Measured data: natural frequencies (Hz) and real mode shapes at the measured points and
directions (any scaling and sign). The model's undamped modes (K - w^2 M) z = 0 are paired
with the measured ones by MAC; the residual stacks relative squared-frequency errors and
unit-normalised shape differences, and is minimised by a trust-region Gauss-Newton
(``scipy.optimize.least_squares``) in log-parameters with the analytic sensitivities of
appendix C:

* eigenvalue, eq. C-4: dw_s^2/dp = z_s^T (dK - w_s^2 dM) z_s / mu_s;
* eigenvector, eq. C-7 to C-10: a particular solution through the generalised inverse of
  (K - w_s^2 M), made unique by keeping the modal mass mu_s = z_s^T M z_s constant;
* at the measured points, eq. 6.2: the observation matrix maps DOF sensitivities to
  point displacements.

Frequencies and shapes alone cannot see a common scaling of M and K (eq. 6.7-6.8 and 6.9):
the identifiability report names that combination when all masses and stiffnesses are free.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.linalg import eigh
from scipy.optimize import least_squares

from pelvislab.model.identification import (
    FitResult,
    FrfProblem,
    covariance_report,
    one_blas_thread,
)


@dataclass(frozen=True)
class ModalData:
    """Measured modes: frequency_hz (n_m,), shapes (n_points, n_m) real, any scaling."""

    frequency_hz: np.ndarray
    shapes: np.ndarray

    def __post_init__(self) -> None:
        f = np.asarray(self.frequency_hz, float).reshape(-1)
        s = np.asarray(self.shapes, float)
        if s.ndim != 2 or s.shape[1] != f.size:
            raise ValueError(f"shapes must be (n_points, {f.size}); got {s.shape}")
        object.__setattr__(self, "frequency_hz", f)
        object.__setattr__(self, "shapes", s)


def undamped_modes(M: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues w^2 (rad^2/s^2, ascending) and mass-normalised modes (z^T M z = 1)."""
    lam, Z = eigh(K, M)
    return lam, Z


def eigen_sensitivities(
    M: np.ndarray, K: np.ndarray, dM: np.ndarray, dK: np.ndarray, lam: np.ndarray,
    Z: np.ndarray, modes: Sequence[int],
) -> tuple[np.ndarray, np.ndarray]:
    """d(w_s^2)/dp (n_modes, n_p) and dz_s/dp (n_modes, n_p, n_dof) of appendix C.

    Eq. C-4 (with mu_s = 1 for mass-normalised modes) and eq. C-7/C-10 (generalised
    inverse of the singular K - w_s^2 M, plus the modal-mass constraint C-8).
    """
    n_p = dM.shape[0]
    dlam = np.empty((len(modes), n_p))
    dz = np.empty((len(modes), n_p, M.shape[0]))
    for i, s in enumerate(modes):
        z = Z[:, s]
        w2 = lam[s]
        mu = z @ M @ z
        dMz = dM @ z  # (n_p, n)
        dKz = dK @ z
        dlam[i] = (dKz @ z - w2 * (dMz @ z)) / mu  # C-4
        A_plus = np.linalg.pinv(K - w2 * M, rcond=1e-10)
        rhs = w2 * dMz + dlam[i][:, None] * (M @ z)[None, :] - dKz  # C-6 right side
        zt = rhs @ A_plus.T  # C-7, one row per parameter
        alpha = -(0.5 * (dMz @ z) + zt @ (M @ z)) / mu  # C-9
        dz[i] = zt + alpha[:, None] * z[None, :]  # C-10
    return dlam, dz


def mac(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Modal assurance criterion matrix (eq. 4.49) between the columns of a and b."""
    num = np.abs(a.T @ b) ** 2
    return num / np.outer(np.sum(a * a, 0), np.sum(b * b, 0))


@one_blas_thread
def identify_modal(
    problem: FrfProblem,
    data: ModalData,
    *,
    free: Sequence[str] | None = None,
    start: np.ndarray | None = None,
    frequency_weight: float = 1.0,
    shape_weight: float = 1.0,
    n_rigid: int | None = None,
    bounds_factor: float = 10.0,
    max_nfev: int = 100,
    progress: Callable[[str], None] | None = None,
) -> FitResult:
    """Gauss-Newton modal updating of the ``free`` parameters (default: the stiffnesses).

    Measured shapes live at the rows of ``problem.outputs``. Model modes below 1e-6 x the
    largest eigenvalue (rigid-body modes) are never paired. Mode pairing by maximum MAC
    is redone at every residual evaluation (modes may swap order while updating).
    """
    t0 = time.perf_counter()
    names = list(problem.names)
    if free is None:  # masses + stiffnesses together are invisible up to scale (eq. 6.7-6.9)
        free = [n for n in names if n.startswith("k_")] or list(names)
    unknown = [n for n in free if n not in names]
    if unknown:
        raise ValueError(f"unknown parameter(s) {unknown}; the model has {names}")
    idx = np.array([names.index(n) for n in free], dtype=int)
    base = np.asarray(problem.nominal if start is None else start, float).copy()
    O = np.asarray(problem.outputs, float)
    if data.shapes.shape[0] != O.shape[0]:
        raise ValueError(
            f"measured shapes have {data.shapes.shape[0]} points, model outputs {O.shape[0]}")
    n_modes = data.frequency_hz.size
    # independent equations per mode: its frequency and its shape's direction (a unit
    # vector at n outputs has n - 1 degrees of freedom)
    n_equations = n_modes * O.shape[0]
    if n_equations < len(free):
        # more unknowns than equations: the fit would return one of many solutions
        raise ValueError(
            f"{n_modes} mode(s) at {O.shape[0]} output(s) give {n_equations} independent "
            f"equations (a frequency and a unit shape per mode), fewer than the "
            f"{len(free)} parameters to update; free fewer parameters or measure more modes")
    w2_meas = (2 * np.pi * data.frequency_hz) ** 2
    phi_meas = data.shapes / np.linalg.norm(data.shapes, axis=0)
    evals = [0]

    def model(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        values = base.copy()
        values[idx] = np.exp(x)
        mats = problem.assemble(values)
        lam, Z = undamped_modes(mats.M, mats.K)
        elastic = np.flatnonzero(lam > 1e-6 * lam.max()) if n_rigid is None \
            else np.arange(n_rigid, lam.size)
        # pair each measured mode with the elastic model mode of highest MAC (frequency
        # proximity breaks ties)
        phi_model = O @ Z[:, elastic]
        m = mac(phi_model, phi_meas)
        fratio = np.abs(np.log(lam[elastic][:, None] / w2_meas[None, :]))
        score = m - 0.01 * fratio
        pairs = elastic[np.argmax(score, axis=0)]
        dlam, dz = eigen_sensitivities(mats.M, mats.K, mats.dM[idx], mats.dK[idx], lam, Z,
                                       list(pairs))
        evals[0] += 1
        r_f = frequency_weight * (lam[pairs] / w2_meas - 1.0)
        J_f = frequency_weight * dlam / w2_meas[:, None]
        r_s, J_s = [], []
        for i, s in enumerate(pairs):
            u = O @ Z[:, s]
            nu = np.linalg.norm(u)
            n_hat = u / nu
            sign = np.sign(n_hat @ phi_meas[:, i]) or 1.0
            r_s.append(shape_weight * (sign * n_hat - phi_meas[:, i]))
            du = dz[i] @ O.T  # (n_p, n_points)
            dn = (du - np.outer(du @ n_hat, n_hat)) / nu
            J_s.append(shape_weight * sign * dn.T)
        r = np.concatenate([r_f, *r_s])
        J = np.vstack([J_f, *J_s]) * values[idx][None, :]  # d/dlog p
        return r, J

    cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = {}

    def get(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = x.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = model(x)
        return cache[key]

    x0 = np.log(base[idx])
    lo, hi = x0 - np.log(bounds_factor), x0 + np.log(bounds_factor)
    sol = least_squares(lambda x: get(x)[0], x0, jac=lambda x: get(x)[1], bounds=(lo, hi),
                        method="trf", ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=max_nfev)
    r, J = get(sol.x)
    values = base.copy()
    values[idx] = np.exp(sol.x)
    std, corr, sv, weak = covariance_report(J, r, list(free), values[idx],
                                            absolute_sigma=False)
    rms = float(np.sqrt(np.mean(r**2)))
    at_bound = bool(np.any(np.isclose(sol.x, lo, atol=1e-6) | np.isclose(sol.x, hi, atol=1e-6)))
    message = str(sol.message) + ("; a parameter sits on its bound" if at_bound else "")
    if progress:
        progress(f"modal updating: rms residual {rms:.3g} after {evals[0]} evaluations")
    return FitResult(
        names=list(free), values=values[idx], std=std, correlation=corr,
        cost=0.5 * float(r @ r), converged=bool(sol.status > 0) and not at_bound,
        evaluations=evals[0], wall_time_s=time.perf_counter() - t0, residual_kind="modal",
        singular_values=sv, weak_directions=weak, message=message,
        extra={"rms_residual": rms},
    )


def modes_from_frf(
    frequency_hz: np.ndarray, H: np.ndarray, *, max_modes: int = 12, min_prominence: float = 0.1,
) -> ModalData:
    """Peak picking (ch. 4.5): peaks of the mean log|H|, shapes = the FRF column there.

    A simple single-degree-of-freedom estimator for lightly damped, well separated modes:
    the column (input) with the largest response at each peak supplies the shape. NaN
    lines are ignored; ``min_prominence`` is in natural-log units. Good enough to seed modal
    updating; the EMA module does better.
    """
    from scipy.signal import find_peaks

    Hm = np.where(np.isfinite(H), H, 0.0)
    lines = np.abs(Hm).reshape(Hm.shape[0], -1)
    lines = lines[:, np.all(lines > 0, axis=0)]
    if lines.size == 0:
        raise ValueError("no complete FRF line to pick peaks from")
    # mean log-magnitude over the lines: every FRF counts, peaks of small ones too
    total = np.mean(np.log(lines), axis=1)
    peaks, props = find_peaks(total, prominence=min_prominence)
    if peaks.size == 0:
        raise ValueError("no resonance peaks found in the FRFs")
    order = np.argsort(-props["prominences"])[:max_modes]
    peaks = np.sort(peaks[order])
    shapes = []
    for k in peaks:
        col = int(np.argmax(np.sum(np.abs(Hm[k]), axis=0)))
        h = Hm[k, :, col]
        # dominant real direction of the complex column: Im H on the peak, Re H when the
        # grid misses a lightly damped peak (the nearest mode dominates either way)
        u, _, _ = np.linalg.svd(np.stack([h.real, h.imag], axis=1), full_matrices=False)
        shapes.append(u[:, 0])
    return ModalData(np.asarray(frequency_hz, float)[peaks], np.array(shapes).T)
