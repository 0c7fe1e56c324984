"""Modal analysis of the model: undamped modes, state-space complex modes, MAC, pairing.

- Undamped modes (thesis eq. 4.26-4.34): ``(−ω² M + K) z = 0``, mass-normalised real shapes,
  modal mass ``μ = zᵀ M z`` (eq. 4.33).
- Complex modes in state space (ch. 4.3, app. B): ``A y + λ B y = 0`` with
  ``A = [[K, 0], [0, −M]]``, ``B = [[C, M], [M, 0]]``, ``y = (z, λ z)``; poles
  ``λ = −σ + i ω_d``; ``ρ = zᵀ C z + 2 λ zᵀ M z`` (eq. 4.56, B-20); damping ratio
  ``ζ = σ / sqrt(ω_d² + σ²)`` (eq. 7.5, D-11); natural frequency ``sqrt(σ² + ω_d²)`` (4.48).
- Frequency-dependent matrices (eq. 7.1-7.3): per-mode fixed-point iteration of app. D.
- FRF by modal superposition (eq. 4.55 / B-21), plus the rigid-body term for a free model.
- MAC (eq. 4.49) and MAC-based mode pairing (ch. 14).

All functions are pure numerics on arrays; frequencies in Hz, poles in rad/s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg
from scipy.optimize import linear_sum_assignment

RIGID_RTOL = 1e-11
"""An undamped eigenvalue ω² below RIGID_RTOL × max ω² counts as a rigid-body mode."""


@dataclass(frozen=True, eq=False)
class UndampedModes:
    """Real modes of (M, K), ascending: rigid-body modes first.

    ``frequencies_hz`` (n,) (rigid-body modes reported as 0), ``omega2`` (n,) the raw
    eigenvalues ω² (rad²/s²), ``shapes`` (n_dof, n) mass-normalised (``Φᵀ M Φ = I``).
    """

    frequencies_hz: np.ndarray
    omega2: np.ndarray
    shapes: np.ndarray
    n_rigid_body: int

    @property
    def elastic(self) -> slice:
        """Index of the elastic modes."""
        return slice(self.n_rigid_body, None)


def undamped_modes(M: np.ndarray, K: np.ndarray, rigid_rtol: float = RIGID_RTOL) -> UndampedModes:
    """Undamped modes (eq. 4.26-4.27) by the symmetric-definite eigensolver."""
    w2, phi = scipy.linalg.eigh(K, M)
    scale = max(float(np.abs(w2).max()), np.finfo(float).tiny)
    rigid = w2 < rigid_rtol * scale
    n_rb = int(rigid.sum())
    f = np.sqrt(np.where(rigid, 0.0, np.abs(w2))) / (2 * np.pi)
    return UndampedModes(f, w2, phi, n_rb)


def modal_mass(M: np.ndarray, shapes: np.ndarray) -> np.ndarray:
    """Modal masses ``μ_j = z_jᵀ M z_j`` (eq. 4.33) of the columns of ``shapes``."""
    return np.einsum("ij,ik,kj->j", shapes, M, shapes)


@dataclass(frozen=True, eq=False)
class ComplexModes:
    """Elastic complex modes, ascending in damped frequency.

    ``poles`` (n,) λ = −σ + iω_d with ω_d > 0; ``shapes`` (n_dof, n) complex z normalised
    so that the largest-magnitude component is 1; ``rho`` (n,) = zᵀCz + 2λ zᵀMz (eq. 4.56)
    for that normalisation (residue of mode s: ``z zᵀ / ρ``); ``overdamped_poles`` real
    poles of non-oscillating elastic motion, with ``overdamped_shapes`` / ``overdamped_rho``;
    ``rigid_shapes`` (n_dof, n_rb) mass-normalised rigid-body modes (empty if grounded).
    """

    poles: np.ndarray
    shapes: np.ndarray
    rho: np.ndarray
    n_rigid_body: int
    rigid_shapes: np.ndarray
    overdamped_poles: np.ndarray
    overdamped_shapes: np.ndarray
    overdamped_rho: np.ndarray
    iterations: np.ndarray | None = None

    @property
    def damped_frequencies_hz(self) -> np.ndarray:
        """ω_d / 2π (Hz)."""
        return self.poles.imag / (2 * np.pi)

    @property
    def natural_frequencies_hz(self) -> np.ndarray:
        """|λ| / 2π = sqrt(σ² + ω_d²) / 2π (eq. 4.48)."""
        return np.abs(self.poles) / (2 * np.pi)

    @property
    def damping_ratios(self) -> np.ndarray:
        """ζ = σ / sqrt(ω_d² + σ²) (eq. 7.5, D-11)."""
        return -self.poles.real / np.abs(self.poles)


def _state_space_eig(M: np.ndarray, K: np.ndarray, C: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """All 2N eigenpairs (λ, z) of the quadratic problem (λ²M + λC + K) z = 0.

    Solved as the state-space problem of app. B in mass-normalised coordinates
    (``M = L Lᵀ``), which keeps the ~1e9 spread between K and M entries out of the
    eigensolver; ``z = L⁻ᵀ x``.
    """
    n = M.shape[0]
    # Explicit inverse of the 18x18 triangular factor: scipy's solve_triangular was measured
    # at ~20 ms per call here (threading overhead), np.linalg.inv at ~20 µs.
    Li = np.linalg.inv(np.linalg.cholesky(M))
    Kt = Li @ K @ Li.T
    Ct = Li @ C @ Li.T
    S = np.zeros((2 * n, 2 * n))
    S[:n, n:] = np.eye(n)
    S[n:, :n] = -0.5 * (Kt + Kt.T)
    S[n:, n:] = -0.5 * (Ct + Ct.T)
    lam, v = np.linalg.eig(S)
    z = Li.T @ v[:n]
    return lam, z


def _rho(M: np.ndarray, C: np.ndarray, lam: np.ndarray, z: np.ndarray) -> np.ndarray:
    return (np.einsum("ij,ik,kj->j", z, C, z) + 2 * lam * np.einsum("ij,ik,kj->j", z, M, z))


def _normalise(z: np.ndarray) -> np.ndarray:
    k = np.argmax(np.abs(z), axis=0)
    return z / z[k, np.arange(z.shape[1])]


def _split(M: np.ndarray, K: np.ndarray, C: np.ndarray, n_rb: int
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Elastic oscillating (Im λ > 0) and overdamped (real) eigenpairs, rigid ones dropped."""
    lam, z = _state_space_eig(M, K, C)
    order = np.argsort(np.abs(lam))
    keep = order[2 * n_rb:]  # a rigid-body mode is a double zero pole
    lam, z = lam[keep], z[:, keep]
    osc = lam.imag > 0
    real = lam.imag == 0
    return lam[osc], z[:, osc], lam[real], z[:, real]


def complex_modes(M: np.ndarray, K: np.ndarray, C: np.ndarray, f_k: float = 0.0,
                  f_c: float = 0.0, f_max_hz: float = 300.0, tol: float = 1e-6,
                  max_iter: int = 100) -> ComplexModes:
    """State-space complex modes (app. B); with ``f_k``/``f_c`` ≠ 0 the app. D iteration.

    The number of rigid-body modes comes from the undamped problem; their 2 n_rb zero poles
    are the smallest in magnitude and are dropped. The rigid-body shapes are returned
    separately (mass-normalised) for the FRF's rigid-body term.
    """
    und = undamped_modes(M, K)
    n_rb = und.n_rigid_body
    rigid = und.shapes[:, :n_rb]
    lam, z, lam_r, z_r = _split(M, K, C, n_rb)
    iters = None
    if f_k != 0.0 or f_c != 0.0:
        lam, z, iters = _fixed_point(M, K, C, lam, z, n_rb, f_k, f_c, f_max_hz, tol, max_iter)
        # overdamped poles are kept from the constant-matrix solution
    order = np.argsort(lam.imag)
    lam, z = lam[order], _normalise(z[:, order])
    if iters is not None:
        iters = iters[order]
    if z_r.shape[1]:
        z_r = _normalise(z_r)
    rho_r = _rho(M, C, lam_r, z_r) if lam_r.size else np.zeros(0, complex)
    if f_k != 0.0 or f_c != 0.0:
        wmax = 2 * np.pi * f_max_hz
        w = lam.imag
        rho = np.array([
            _rho(M, C * (1 + f_c * wmax / (4 * w[s])), lam[s:s + 1], z[:, s:s + 1])[0]
            for s in range(lam.size)
        ]) if lam.size else np.zeros(0, complex)
    else:
        rho = _rho(M, C, lam, z)
    return ComplexModes(lam, z, rho, n_rb, rigid, lam_r.astype(complex), z_r.astype(complex),
                        rho_r, iters)


def _fixed_point(M: np.ndarray, K: np.ndarray, C: np.ndarray, lam0: np.ndarray,
                 z0: np.ndarray, n_rb: int, f_k: float, f_c: float, f_max_hz: float,
                 tol: float, max_iter: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """App. D: for each mode, solve with K(ω_i) = K + ω_i K', C(ω_i) = C + D/ω_i and update
    ω_i = |Im λ| until the relative change of ω and σ is below ``tol`` (eq. D-5 to D-10).
    The mode is followed from step to step by the pole nearest to the previous one."""
    wmax = 2 * np.pi * f_max_hz
    lam_out = lam0.copy()
    z_out = z0.copy()
    iters = np.zeros(lam0.size, dtype=int)
    for s in range(lam0.size):
        lam_s = lam0[s]
        for it in range(1, max_iter + 1):  # noqa: B007 - it is reported below
            w = abs(lam_s.imag)
            Ki = K * (1 + f_k * w / (4 * wmax))
            Ci = C * (1 + f_c * wmax / (4 * w))
            lam, z, _, _ = _split(M, Ki, Ci, n_rb)
            # Follow the mode by its shape (MAC with the previous step), not by the nearest
            # pole: K' ∝ K moves every pole, so neighbours can swap order.
            j = int(np.argmax(mac(z_out[:, s], z)[0]))
            new = lam[j]
            dw = abs(abs(new.imag) - w) / abs(new.imag)
            sig_new, sig_old = -new.real, -lam_s.real
            ds = abs(sig_new - sig_old) / max(abs(sig_new), 1e-300)
            lam_s = new
            z_out[:, s] = z[:, j]
            if dw < tol and (ds < tol or abs(sig_new - sig_old) < 1e-12 * abs(new)):
                break
        else:
            raise RuntimeError(f"app. D iteration did not converge for mode {s + 1} "
                               f"in {max_iter} steps")
        lam_out[s] = lam_s
        iters[s] = it
    return lam_out, z_out, iters


def modal_receptance(modes: ComplexModes, frequency_hz: np.ndarray, out_rows: np.ndarray,
                     in_rows: np.ndarray) -> np.ndarray:
    """FRF at points by modal superposition (eq. 4.55 / B-21), (n_f, n_out, n_in), m/N.

    ``H = Σ_s [O z_s z_sᵀ Iᵀ / (ρ_s (iω − λ_s)) + conj. mode] + overdamped terms
    − O Φ_r Φ_rᵀ Iᵀ / ω²`` (rigid-body term of a free model whose dashpots do not act on
    rigid motion, as for every model built from springs and dashpots between bodies).
    Exact for constant matrices; with eq. 7.1 frequency dependence it is the modal
    approximation only.
    """
    w = 2 * np.pi * np.asarray(frequency_hz, dtype=float).reshape(-1)
    iw = 1j * w[:, None]
    oz = out_rows @ modes.shapes  # (n_out, n)
    iz = in_rows @ modes.shapes  # (n_in, n)
    g = 1.0 / (modes.rho * (iw - modes.poles))  # (n_f, n)
    gc = 1.0 / (np.conj(modes.rho) * (iw - np.conj(modes.poles)))
    H = np.einsum("fs,os,is->foi", g, oz, iz) + np.einsum("fs,os,is->foi", gc, np.conj(oz),
                                                          np.conj(iz))
    if modes.overdamped_poles.size:
        ozr = out_rows @ modes.overdamped_shapes
        izr = in_rows @ modes.overdamped_shapes
        gr = 1.0 / (modes.overdamped_rho * (iw - modes.overdamped_poles))
        H += np.einsum("fs,os,is->foi", gr, ozr, izr)
    if modes.n_rigid_body:
        orr = out_rows @ modes.rigid_shapes
        irr = in_rows @ modes.rigid_shapes
        H += -(orr @ irr.T)[None] / (w[:, None, None] ** 2)
    return H


def mac(shapes_a: np.ndarray, shapes_b: np.ndarray) -> np.ndarray:
    """Modal Assurance Criterion (eq. 4.49) between the columns of two shape sets.

    ``MAC_rs = |z̄_rᵀ z_s|² / ((z̄_rᵀ z_r)(z̄_sᵀ z_s))``; (n_a, n_b), values in [0, 1].
    Vectors are columns (n_points, n_modes); 1-D inputs are single modes.
    """
    a = np.asarray(shapes_a)
    b = np.asarray(shapes_b)
    a = a[:, None] if a.ndim == 1 else a
    b = b[:, None] if b.ndim == 1 else b
    if a.shape[0] != b.shape[0]:
        raise ValueError(f"shapes have {a.shape[0]} and {b.shape[0]} components")
    cross = np.abs(np.conj(a).T @ b) ** 2
    na = np.sum(np.abs(a) ** 2, axis=0)
    nb = np.sum(np.abs(b) ** 2, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = cross / np.outer(na, nb)
    return np.nan_to_num(out, nan=0.0)


@dataclass(frozen=True)
class ModePair:
    """Mode ``a`` of the first set paired with mode ``b`` of the second, with their MAC."""

    a: int
    b: int
    mac: float


def pair_modes(shapes_a: np.ndarray, shapes_b: np.ndarray, min_mac: float = 0.0
               ) -> list[ModePair]:
    """One-to-one pairing maximising the total MAC (Hungarian assignment, ch. 14).

    Pairs with MAC below ``min_mac`` are dropped; sorted by the index in set ``a``.
    """
    m = mac(shapes_a, shapes_b)
    rows, cols = linear_sum_assignment(-m)
    pairs = [ModePair(int(r), int(c), float(m[r, c])) for r, c in zip(rows, cols, strict=True)
             if m[r, c] >= min_mac]
    return sorted(pairs, key=lambda p: p.a)


def mode_shapes_at_points(shapes: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Modal displacements at points along their directions: ``rows @ shapes`` (eq. 4.9)."""
    return rows @ shapes


def model_modes(model: object) -> ComplexModes:
    """Complex modes of a :class:`~pelvislab.model.pelvis.PelvisModel` (with its eq. 7.1
    factors, app. D iteration when they are non-zero)."""
    from pelvislab.model.assembly import assemble

    s = assemble(model)  # type: ignore[arg-type]
    return complex_modes(s.M, s.K, s.C, s.f_k, s.f_c, s.f_max_hz)
