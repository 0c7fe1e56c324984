"""FRF synthesis at surface points and its parameter Jacobian, batched over frequency.

Harmonic convention (design 4.1): x(t) = Re(X e^{+iωt}). Receptance (thesis eq. 4.54),
extended with frequency-dependent stiffness and hysteretic damping (eq. 7.1-7.3)::

    Z(ω) = a_k(ω) K − ω² M + i a_c(ω) C,   a_k = 1 + f_k ω / (4 ω_max),  a_c = ω + f_c ω_max / 4
    H_points(ω) = O Z(ω)⁻¹ Iᵀ        (n_f, n_out, n_in), m/N

``O`` (n_out, n_dof) maps generalised coordinates to the displacement of output points along
their directions and ``I`` (n_in, n_dof) does the same for input points (a force F along the
input direction is the generalised force ``Iᵀ F``), both from rigid-body kinematics with
small rotations (eq. 4.9, 6.2). Everything is one batched ``np.linalg.solve`` over the
stacked (n_f, n_dof, n_dof) matrices: no Python loop over frequency lines.

Jacobian: ``∂H/∂p = −O Z⁻¹ (∂Z/∂p) Z⁻¹ Iᵀ = −Aᵀ (∂Z/∂p) B`` with ``A = Z⁻¹ Oᵀ`` and
``B = Z⁻¹ Iᵀ`` (Z is complex symmetric, so ``O Z⁻¹ = Aᵀ``), both from the same single solve.
Each ``∂Z/∂p`` is a short sum of rank-1 "atoms" ``w · coef_kind(ω) · v vᵀ`` (one per spring
or dashpot, six per body mass), so the Jacobian costs a few small matrix products.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from pelvislab.model.assembly import SystemMatrices, assemble, point_rows
from pelvislab.model.pelvis import PelvisModel

# Kinds of derivative atoms: how the atom's v vᵀ enters Z(ω).
KIND_K = 0  # a_k(ω) = 1 + f_k ω/(4 ω_max)
KIND_M = 1  # −ω²
KIND_C = 2  # i a_c(ω) = i (ω + f_c ω_max/4)
KIND_KPRIME = 3  # ∂Z/∂f_k per unit K: ω / (4 ω_max)
KIND_D = 4  # ∂Z/∂f_c per unit C: i ω_max / 4


class PointsLike(Protocol):
    """Anything with ``bone`` (n,), ``position_m`` (n, 3) and ``direction`` (n, 3), e.g.
    :class:`Points` or ``pelvislab.acquisition.frfset.Channels``."""

    bone: list[str] | tuple[str, ...]
    position_m: np.ndarray
    direction: np.ndarray


@dataclass(frozen=True, eq=False)
class Points:
    """Measurement or excitation points: bone names, positions (m, model frame), directions.

    Directions are normalised on construction. ``name`` is optional (for reports).
    """

    bone: tuple[str, ...]
    position_m: np.ndarray
    direction: np.ndarray
    name: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        object.__setattr__(self, "bone", tuple(str(b) for b in self.bone))
        pos = np.asarray(self.position_m, dtype=float).reshape(-1, 3)
        d = np.asarray(self.direction, dtype=float).reshape(-1, 3)
        if not (len(self.bone) == pos.shape[0] == d.shape[0]):
            raise ValueError(f"points disagree: {len(self.bone)} bones, {pos.shape[0]} "
                             f"positions, {d.shape[0]} directions")
        n = np.linalg.norm(d, axis=1)
        if np.any(n == 0):
            raise ValueError("point directions must be non-zero")
        object.__setattr__(self, "position_m", pos)
        object.__setattr__(self, "direction", d / n[:, None])
        names = tuple(str(x) for x in self.name) or tuple(f"p{i}" for i in range(len(self.bone)))
        if len(names) != len(self.bone):
            raise ValueError(f"{len(names)} names for {len(self.bone)} points")
        object.__setattr__(self, "name", names)

    def __len__(self) -> int:
        return len(self.bone)


def rows_for(model: PelvisModel, points: PointsLike) -> np.ndarray:
    """(n, n_dof) observation/forcing rows of ``points`` on ``model`` (eq. 4.9)."""
    return point_rows(model, list(points.bone), points.position_m, points.direction)


# ---------------------------------------------------------------------------------------
# Frequency factors and dynamic stiffness
# ---------------------------------------------------------------------------------------

def _omega(frequency_hz: np.ndarray) -> np.ndarray:
    f = np.asarray(frequency_hz, dtype=float).reshape(-1)
    if not np.all(np.isfinite(f)) or np.any(f < 0):
        raise ValueError("frequency_hz must be finite and >= 0")
    return 2.0 * np.pi * f


def kind_coefficients(frequency_hz: np.ndarray, f_k: float = 0.0, f_c: float = 0.0,
                      f_max_hz: float = 300.0) -> np.ndarray:
    """(n_f, 5) complex factor multiplying an atom ``v vᵀ`` of each kind in Z(ω)."""
    w = _omega(frequency_hz)
    wmax = 2.0 * np.pi * f_max_hz
    coef = np.empty((w.size, 5), dtype=complex)
    coef[:, KIND_K] = 1.0 + f_k * w / (4.0 * wmax)
    coef[:, KIND_M] = -(w**2)
    coef[:, KIND_C] = 1j * (w + f_c * wmax / 4.0)
    coef[:, KIND_KPRIME] = w / (4.0 * wmax)
    coef[:, KIND_D] = 1j * wmax / 4.0
    return coef


def dynamic_stiffness(M: np.ndarray, K: np.ndarray, C: np.ndarray, frequency_hz: np.ndarray,
                      f_k: float = 0.0, f_c: float = 0.0, f_max_hz: float = 300.0) -> np.ndarray:
    """Z(ω) stacked over frequency, (n_f, n, n) complex (eq. 4.52 and 7.1)."""
    coef = kind_coefficients(frequency_hz, f_k, f_c, f_max_hz)
    _check_static(K, frequency_hz)
    return (coef[:, KIND_K, None, None] * K + coef[:, KIND_M, None, None] * M
            + coef[:, KIND_C, None, None] * C)


def _check_static(K: np.ndarray, frequency_hz: np.ndarray) -> None:
    # At 0 Hz Z = K; LAPACK does not always flag a numerically singular K, so check it.
    if np.any(np.asarray(frequency_hz) == 0) and np.linalg.matrix_rank(K) < K.shape[0]:
        raise ValueError("dynamic stiffness is singular at 0 Hz: the model has rigid-body "
                         "modes (free-free); use frequencies > 0 or ground it")


def _solve(Z: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Batched solve of Z X = rhs for every frequency; a clear error when Z is singular."""
    try:
        return np.linalg.solve(Z, np.broadcast_to(rhs, (Z.shape[0], *rhs.shape)))
    except np.linalg.LinAlgError:
        raise ValueError(
            "dynamic stiffness is singular at some frequency (a free-free model at 0 Hz?)"
        ) from None


def _clean(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    bad = ~np.all(np.isfinite(rows), axis=1)
    return np.where(bad[:, None], 0.0, rows), bad


MODAL_MIN_LINES = 48
"""``method="auto"`` uses the spectral path from this many frequency lines on."""


@dataclass(frozen=True, eq=False)
class Spectral:
    """Exact spectral form of Z(ω)⁻¹ for Z = (K + iD) + ω (K' + iC) − ω² M (eq. 7.1).

    ``Z(ω)⁻¹ = −R Rᵀ / ω² + Σ_k ψ_k ψ_kᵀ / (β_k (ω + s_k))`` with ``R`` (n, n_rb) the
    mass-normalised rigid-body modes (common null space of K and C) and ``ψ`` (n, 2m),
    ``s``, ``β`` from the symmetric linearisation of the quadratic matrix polynomial on the
    M-orthogonal complement of R (the same construction as app. B, with ω as the variable,
    so that the eq. 7.1 terms linear in ω are exact too).
    """

    rigid: np.ndarray
    psi: np.ndarray
    s: np.ndarray
    beta: np.ndarray

    def weights(self, frequency_hz: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(n_f, 2m) modal weights 1/(β(ω+s)) and (n_f,) rigid weight −1/ω²."""
        w = _omega(frequency_hz)
        with np.errstate(divide="ignore"):
            rig = -1.0 / w**2
        return 1.0 / (self.beta * (w[:, None] + self.s)), rig


def spectral(M: np.ndarray, K: np.ndarray, C: np.ndarray, f_k: float = 0.0, f_c: float = 0.0,
             f_max_hz: float = 300.0) -> Spectral | None:
    """The :class:`Spectral` form, or None when it does not apply (C acts on a null vector
    of K, i.e. a mechanism or a damped rigid-body motion, which makes the pencil defective)."""
    import scipy.linalg

    wmax = 2.0 * np.pi * f_max_hz
    Li = np.linalg.inv(np.linalg.cholesky(M))
    Kt = Li @ K @ Li.T
    Kt = 0.5 * (Kt + Kt.T)
    lam, U = np.linalg.eigh(Kt)
    scale = max(float(np.abs(lam).max()), np.finfo(float).tiny)
    null = lam < 1e-11 * scale
    Ct = Li @ C @ Li.T
    Ct = 0.5 * (Ct + Ct.T)
    Ur, Ue = U[:, null], U[:, ~null]
    if Ur.shape[1] and np.abs(Ct @ Ur).max() > 1e-9 * max(np.abs(Ct).max(initial=0), 1e-300):
        return None
    Ke, Ce = Ue.T @ Kt @ Ue, Ue.T @ Ct @ Ue
    m = Ke.shape[0]
    if m == 0:  # no elastic coordinates: only the rigid-body term
        return Spectral(Li.T @ Ur, np.zeros((M.shape[0], 0), complex), np.zeros(0, complex),
                        np.zeros(0, complex))
    # Scale ω by the largest elastic frequency so that the pencil's entries are O(1)
    # (unscaled, K ~ 1e7 against I ~ 1 cost ~3 digits in the eigenvectors).
    wr = float(np.sqrt(max(np.abs(np.diag(Ke)).max(), np.finfo(float).tiny)))
    A0 = (Ke + 1j * (f_c * wmax / 4.0) * Ce) / wr**2
    A1 = ((f_k / (4.0 * wmax)) * Ke + 1j * Ce) / wr
    eye = np.eye(m)
    A = np.block([[A0, np.zeros((m, m))], [np.zeros((m, m)), eye]])
    B = np.block([[A1, -eye], [-eye, np.zeros((m, m))]])
    s, Y = scipy.linalg.eig(A, B)
    if not np.all(np.isfinite(s)):
        return None
    beta = np.einsum("ik,ij,jk->k", Y, B, Y)
    if np.any(np.abs(beta) < 1e-12 * np.abs(Y).max() ** 2 * max(np.abs(B).max(), 1.0)):
        return None
    E = Li.T @ Ue
    return Spectral(Li.T @ Ur, E @ Y[:m], wr * s, wr * beta)


def _receptance_spectral(sp: Spectral, frequency_hz: np.ndarray, o: np.ndarray,
                         i: np.ndarray) -> np.ndarray:
    g, rig = sp.weights(frequency_hz)
    op, ip = o @ sp.psi, i @ sp.psi
    pair = (op[:, None, :] * ip[None, :, :]).reshape(o.shape[0] * i.shape[0], sp.s.size)
    # einsum's own C loop, not BLAS: a threaded zgemm of this size was measured 20x slower
    # on a loaded 2-core machine (OpenBLAS thread contention).
    H = np.einsum("fk,pk->fp", g, pair).reshape(-1, o.shape[0], i.shape[0])
    if sp.rigid.shape[1]:
        H += rig[:, None, None] * ((o @ sp.rigid) @ (i @ sp.rigid).T)
    return H


def receptance(M: np.ndarray, K: np.ndarray, C: np.ndarray, frequency_hz: np.ndarray,
               out_rows: np.ndarray, in_rows: np.ndarray, f_k: float = 0.0, f_c: float = 0.0,
               f_max_hz: float = 300.0, method: str = "auto") -> np.ndarray:
    """Receptance at points, H (n_f, n_out, n_in) complex, m/N (eq. 4.54 with 7.1).

    ``out_rows`` (n_out, n) and ``in_rows`` (n_in, n) come from :func:`rows_for`; a NaN row
    (point on no modelled bone) gives NaN FRFs. ``method``: ``"solve"`` (one batched solve
    of the stacked Z(ω)), ``"spectral"`` (exact spectral form, :func:`spectral`; one small
    eigenproblem then a sum per line) or ``"auto"`` (spectral from ``MODAL_MIN_LINES``
    lines on, checked against the direct solve at three lines, solve otherwise).
    """
    o, bad_o = _clean(np.asarray(out_rows, dtype=float))
    i, bad_i = _clean(np.asarray(in_rows, dtype=float))
    f = np.asarray(frequency_hz, dtype=float).reshape(-1)
    if method not in ("auto", "solve", "spectral"):
        raise ValueError(f"method must be 'auto', 'solve' or 'spectral', not {method!r}")
    H = None
    if method == "spectral" or (method == "auto" and f.size >= MODAL_MIN_LINES):
        _check_static(K, f)
        sp = spectral(M, K, C, f_k, f_c, f_max_hz)
        if sp is None and method == "spectral":
            raise ValueError("spectral form not applicable (damped mechanism); use 'solve'")
        if sp is not None:
            H = _receptance_spectral(sp, f, o, i)
            if method == "auto":
                # guard against a nearly defective pencil: compare with the direct solve
                probe = np.unique(np.array([0, f.size // 2, f.size - 1]))
                Zp = dynamic_stiffness(M, K, C, f[probe], f_k, f_c, f_max_hz)
                ref = o @ _solve(Zp, i.T.astype(complex))
                tol = 1e-8 * max(np.abs(ref).max(), np.finfo(float).tiny)
                if not np.abs(H[probe] - ref).max() <= tol:
                    H = None
    if H is None:
        Z = dynamic_stiffness(M, K, C, f, f_k, f_c, f_max_hz)
        H = o @ _solve(Z, i.T.astype(complex))
    if bad_o.any() or bad_i.any():
        H[:, bad_o, :] = np.nan
        H[:, :, bad_i] = np.nan
    return H


@dataclass(frozen=True, eq=False)
class DerivativeAtoms:
    """∂Z/∂p_j = Σ_{a: params[a]=j} weights[a] · coef_{kinds[a]}(ω) · v_a v_aᵀ.

    ``vectors`` (n_a, n_dof), ``weights`` (n_a,), ``kinds`` (n_a,) int (KIND_*),
    ``params`` (n_a,) int in [0, n_params).
    """

    vectors: np.ndarray
    weights: np.ndarray
    kinds: np.ndarray
    params: np.ndarray
    n_params: int


def atoms_from_matrices(dM: np.ndarray, dK: np.ndarray, dC: np.ndarray,
                        rtol: float = 1e-12) -> DerivativeAtoms:
    """Rank-1 atoms from dense symmetric derivative matrices (n_p, n, n) each, by
    eigendecomposition; for derivatives not built by :mod:`pelvislab.model.parameters`."""
    vecs, weights, kinds, params = [], [], [], []
    n_p = dM.shape[0]
    for kind, mats in ((KIND_M, dM), (KIND_K, dK), (KIND_C, dC)):
        for p in range(n_p):
            mat = 0.5 * (mats[p] + mats[p].T)
            scale = np.abs(mat).max()
            if scale == 0:
                continue
            lam, v = np.linalg.eigh(mat)
            keep = np.abs(lam) > rtol * scale * mat.shape[0]
            for lk, vk in zip(lam[keep], v[:, keep].T, strict=True):
                vecs.append(vk)
                weights.append(lk)
                kinds.append(kind)
                params.append(p)
    n = dM.shape[-1]
    return DerivativeAtoms(np.array(vecs).reshape(-1, n), np.array(weights, dtype=float),
                           np.array(kinds, dtype=int), np.array(params, dtype=int), n_p)


def receptance_and_jacobian(M: np.ndarray, K: np.ndarray, C: np.ndarray,
                            frequency_hz: np.ndarray, out_rows: np.ndarray,
                            in_rows: np.ndarray, atoms: DerivativeAtoms, f_k: float = 0.0,
                            f_c: float = 0.0, f_max_hz: float = 300.0
                            ) -> tuple[np.ndarray, np.ndarray]:
    """H (n_f, n_out, n_in) and ∂H/∂p (n_f, n_out, n_in, n_p), from one batched solve.

    ``dH[..., j] = −Aᵀ (∂Z/∂p_j) B`` with ``A = Z⁻¹ Oᵀ`` and ``B = Z⁻¹ Iᵀ``.
    """
    o, bad_o = _clean(np.asarray(out_rows, dtype=float))
    i, bad_i = _clean(np.asarray(in_rows, dtype=float))
    n_out, n_in = o.shape[0], i.shape[0]
    coef = kind_coefficients(frequency_hz, f_k, f_c, f_max_hz)
    _check_static(K, frequency_hz)
    Z = (coef[:, KIND_K, None, None] * K + coef[:, KIND_M, None, None] * M
         + coef[:, KIND_C, None, None] * C)
    X = _solve(Z, np.concatenate([o, i]).T.astype(complex))  # (n_f, n, n_out + n_in)
    A, B = X[..., :n_out], X[..., n_out:]
    H = o @ B
    # Atoms sorted by parameter, so that one reduceat sums each parameter's atoms.
    order = np.argsort(atoms.params, kind="stable")
    V = atoms.vectors[order]
    # atom projections a = V A (n_f, n_a, n_out), b = V B (n_f, n_a, n_in): stacked small
    # matmuls (fast); one big 2-D gemm here was measured 20x slower under thread contention
    a = V @ A
    b = V @ B
    c = atoms.weights[order] * coef[:, atoms.kinds[order]]  # (n_f, n_a)
    outer = (a * c[:, :, None])[:, :, :, None] * b[:, :, None, :]  # (n_f, n_a, n_out, n_in)
    n_f = Z.shape[0]
    params = atoms.params[order]
    dH = np.zeros((n_f, atoms.n_params, n_out, n_in), dtype=complex)
    if params.size:
        present, starts = np.unique(params, return_index=True)
        dH[:, present] = -np.add.reduceat(outer, starts, axis=1)
    dH = np.ascontiguousarray(dH.transpose(0, 2, 3, 1))
    if bad_o.any() or bad_i.any():
        H[:, bad_o, :] = np.nan
        H[:, :, bad_i] = np.nan
        dH[:, bad_o] = np.nan
        dH[:, :, bad_i] = np.nan
    return H, dH


# ---------------------------------------------------------------------------------------
# Model-level convenience
# ---------------------------------------------------------------------------------------

def frf(model: PelvisModel, frequency_hz: np.ndarray, outputs: PointsLike,
        inputs: PointsLike, matrices: SystemMatrices | None = None) -> np.ndarray:
    """Receptance of ``model`` between input and output points, (n_f, n_out, n_in), m/N.

    Uses the model's eq. 7.1-7.3 factors. ``matrices`` may pass a pre-assembled
    :class:`SystemMatrices` to skip assembly.
    """
    s = assemble(model) if matrices is None else matrices
    return receptance(s.M, s.K, s.C, frequency_hz, rows_for(model, outputs),
                      rows_for(model, inputs), s.f_k, s.f_c, s.f_max_hz)
