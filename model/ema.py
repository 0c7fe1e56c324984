"""Experimental modal analysis: poles, damping, complex shapes and residues from measured FRFs.

What the thesis did with commercial tools (ch. 10: STAR System, table 10.1; ch. 11: ME'scope,
then SDT, table 11.1), done here with two standard frequency-domain steps:

1. **Poles**: poly-reference least-squares complex frequency (p-LSCF, "PolyMAX"; Guillaume et
   al., IMAC XXI 2003; Peeters et al., Shock Vib. 11, 2004). A right matrix-fraction model
   ``H(z) = B(z) A(z)^-1`` with real matrix coefficients in the z-domain basis
   ``z_k = exp(i omega_k dt)``, ``dt = 1 / (2 f_nyq)``. The normal equations are built line by
   line, so the basis needs neither a uniform nor a fine grid (stepped sine: coarse,
   non-uniform, missing lines); ``z`` stays on the unit circle, which keeps the Vandermonde
   columns well conditioned where an s-domain monomial basis is not. The coefficients of
   every order ``1..max_order`` come from one set of reduced normal matrices (their leading
   blocks), giving the stabilisation diagram (frequency / damping / participation-vector
   stability between consecutive orders).
2. **Residues**: least-squares frequency-domain (LSFD) fit of complex residues with the poles
   fixed, plus a lower residual (``-LR / omega^2``, modes below the band) and an upper residual
   (constant ``UR``, modes above the band) per FRF, as ME'scope does (thesis ch. 11.3).

Automatic pole selection uses a fixed, documented clustering rule on the fully stable poles
(:func:`select_poles`), completed, with ``H_std``, by a heavily damped mode fitted where the
modes found leave the data beyond their noise (:func:`fit_missing_pole`); a list of
frequencies overrides it (:func:`pick_poles`).

Conventions (design 4.1): receptance in m/N, ``x(t) = Re(X e^{+i omega t})``; a pole is
``lambda = -zeta omega_n + i omega_n sqrt(1 - zeta^2)`` in rad/s, reported as the undamped
natural frequency ``|lambda| / 2 pi`` (Hz) and damping ratio ``-Re(lambda) / |lambda|``;
``H(omega) = sum_r R_r / (i omega - lambda_r) + conj(R_r) / (i omega - conj(lambda_r))``.
Pure numerics on arrays: no I/O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

# Status codes of a pole in the stabilisation diagram (relative to the previous order).
NEW = 0  # no matching pole at the previous order
STABLE_FREQUENCY = 1  # frequency within tolerance
STABLE_DAMPING = 2  # frequency and damping within tolerance
STABLE_ALL = 3  # frequency, damping and participation vector within tolerance


@dataclass(frozen=True)
class StabilityCriteria:
    """Tolerances between consecutive orders and the automatic selection rule.

    ``frequency_tol`` and ``damping_tol`` are relative changes; ``vector_mac`` the minimum MAC
    of participation vectors (only meaningful with more than one input). The selection rule
    that uses them is documented in :func:`select_poles`; ``min_significance`` and
    ``significance_window`` the check after the residue fit (:func:`mode_significance`);
    ``bandwidth_tol`` widens the selection's frequency tolerance for heavily damped poles to
    that fraction of their relative half-power bandwidth ``2 zeta`` (:meth:`frequency_tolerance`).
    """

    frequency_tol: float = 0.01
    damping_tol: float = 0.05
    vector_mac: float = 0.98
    max_damping_ratio: float = 0.5
    min_count: int = 4
    min_fraction: float = 0.2
    edge_lines: int = 2
    min_significance: float = 1.25
    significance_window: float = 0.02
    bandwidth_tol: float = 0.05

    def frequency_tolerance(self, damping_ratio: float | np.ndarray) -> float | np.ndarray:
        """Relative frequency tolerance for a pole of this damping ratio: ``frequency_tol``,
        or ``bandwidth_tol`` of its relative half-power bandwidth ``2 zeta`` when wider."""
        z = np.clip(np.asarray(damping_ratio, dtype=float), 0.0, self.max_damping_ratio)
        tol = np.maximum(self.frequency_tol, 2.0 * self.bandwidth_tol * z)
        return float(tol) if tol.ndim == 0 else tol

    def same_pole(self, frequency_a_hz: float | np.ndarray, damping_a: float | np.ndarray,
                  frequency_b_hz: float | np.ndarray, damping_b: float | np.ndarray
                  ) -> bool | np.ndarray:
        """Whether two poles may be the same mode: tolerances (:meth:`frequency_tolerance`)
        within a factor 2 of each other, and frequencies within the smaller one. Poles with
        ``zeta <= frequency_tol / (2 bandwidth_tol)`` (0.1) all share ``frequency_tol``."""
        ta = self.frequency_tolerance(damping_a)
        tb = self.frequency_tolerance(damping_b)
        fa = np.asarray(frequency_a_hz, dtype=float)
        fb = np.asarray(frequency_b_hz, dtype=float)
        out = ((np.maximum(ta, tb) <= 2.0 * np.minimum(ta, tb))
               & (np.abs(fa - fb) <= np.minimum(ta, tb) * fb))
        return bool(out) if np.ndim(out) == 0 else out


MISSING_MODE_LOCAL_CHI2 = 3.0
"""Local mean ``|H_fit - H|² / H_std²`` (7 lines) above which :func:`ema` notes a possibly
missing mode, when the place lies away from every mode found (:func:`_missing_mode_note`)."""


@dataclass
class StabilisationDiagram:
    """Poles of every model order (positive-frequency, stable poles only), with their status."""

    orders: np.ndarray  # (n_orders,) model orders (matrix-polynomial degree)
    poles: list[np.ndarray]  # per order: complex poles, rad/s
    participation: list[np.ndarray]  # per order: (n_poles, n_in) unit participation vectors
    status: list[np.ndarray]  # per order: int status codes (NEW .. STABLE_ALL)
    line_frequency_hz: np.ndarray = field(default_factory=lambda: np.zeros(0))  # lines fitted

    def frequency_hz(self, index: int) -> np.ndarray:
        """Undamped natural frequencies (Hz) of the poles at order ``orders[index]``."""
        return np.abs(self.poles[index]) / (2 * np.pi)

    def damping_ratio(self, index: int) -> np.ndarray:
        """Damping ratios of the poles at order ``orders[index]``."""
        return -self.poles[index].real / np.abs(self.poles[index])

    def as_rows(self) -> list[dict[str, float | int]]:
        """Flat list ``{order, frequency_hz, damping_ratio, status}`` for plots and JSON."""
        rows: list[dict[str, float | int]] = []
        for k, order in enumerate(self.orders):
            for f, z, s in zip(self.frequency_hz(k), self.damping_ratio(k), self.status[k],
                               strict=True):
                rows.append({"order": int(order), "frequency_hz": float(f),
                             "damping_ratio": float(z), "status": int(s)})
        return rows


@dataclass
class EmaResult:
    """Modal parameters identified from an FRF set; arrays are ordered by frequency."""

    frequency_hz: np.ndarray  # (n_modes,) undamped natural frequency |lambda| / 2 pi
    damping_ratio: np.ndarray  # (n_modes,)
    poles: np.ndarray  # (n_modes,) complex, rad/s
    shapes: np.ndarray  # (n_out, n_modes) complex, unit largest entry (real, positive)
    participation: np.ndarray  # (n_modes, n_in) complex
    residues: np.ndarray  # (n_modes, n_out, n_in) complex, m/N * rad/s
    mpc: np.ndarray  # (n_modes,) modal phase collinearity, 1 = normal (real) mode
    mpd_deg: np.ndarray  # (n_modes,) mean phase deviation, degrees
    lower_residual: np.ndarray  # (n_out, n_in) real, N/m... coefficient of -1/omega^2 (m/N*s^-2)
    upper_residual: np.ndarray  # (n_out, n_in) real, m/N
    fit_frequency_hz: np.ndarray  # (n_f,) lines used for the fit
    H_fit: np.ndarray  # (n_f, n_out, n_in) reconstructed receptance
    H_measured: np.ndarray  # (n_f, n_out, n_in) the fitted data (NaN where not measured)
    diagram: StabilisationDiagram | None = None
    selection: str = "auto"
    notes: list[str] = field(default_factory=list)
    significance: np.ndarray = field(default_factory=lambda: np.zeros(0))  # see mode_significance
    # poles at the edges of the lines, fitted with the modes but not reported as modes
    # (edge_poles)
    residual_poles: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=complex))
    # standard uncertainties from the pole refinement (refine_poles); NaN where not refined
    frequency_std_hz: np.ndarray = field(default_factory=lambda: np.zeros(0))
    damping_ratio_std: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def complexity(self) -> np.ndarray:
        """Modal complexity ``1 - MPC`` in [0, 1]: 0 for a normal mode (thesis ch. 14.2)."""
        return 1.0 - self.mpc

    def fit_error(self) -> float:
        """Relative RMS misfit ``||H_fit - H|| / ||H||`` over the measured lines."""
        ok = np.isfinite(self.H_measured)
        num = np.linalg.norm((self.H_fit - self.H_measured)[ok])
        den = np.linalg.norm(self.H_measured[ok])
        return float(num / den) if den > 0 else float("nan")



def _frf_arrays(frequency_hz: np.ndarray, H: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(f (n_f,), H (n_f, n_out, n_in) complex) from a 1-, 2- or 3-D FRF array."""
    f = np.asarray(frequency_hz, dtype=float).reshape(-1)
    H = np.asarray(H, dtype=complex)
    if H.ndim == 1:
        H = H[:, None, None]
    elif H.ndim == 2:
        H = H[:, :, None]
    if H.ndim != 3 or H.shape[0] != f.size:
        raise ValueError(f"H must be (n_f, n_out, n_in) with n_f = {f.size}; got {H.shape}")
    return f, H

def pole_frequency_damping(poles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Undamped natural frequency (Hz) and damping ratio of complex poles (rad/s)."""
    poles = np.asarray(poles, dtype=complex)
    wn = np.abs(poles)
    return wn / (2 * np.pi), -poles.real / np.where(wn > 0, wn, 1.0)


def poles_from_modal(frequency_hz: np.ndarray, damping_ratio: np.ndarray) -> np.ndarray:
    """Poles (rad/s, positive imaginary part) from natural frequency (Hz) and damping ratio."""
    wn = 2 * np.pi * np.asarray(frequency_hz, dtype=float)
    z = np.asarray(damping_ratio, dtype=float)
    return -z * wn + 1j * wn * np.sqrt(np.clip(1 - z**2, 0.0, None))


def _prepare(
    frequency_hz: np.ndarray, H: np.ndarray, H_std: np.ndarray | None, per_line: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated arrays: frequencies (n_f,), H (n_f, n_out, n_in), weights (n_f, n_out, n_in).

    Unmeasured lines (NaN) get weight 0. Without ``H_std`` each FRF is weighted by the inverse
    of its RMS so that every FRF counts, whatever its amplitude. With ``H_std``:
    ``per_line=True`` gives ``1 / H_std`` per line (maximum likelihood for the LSFD and the
    pole refinement, which are fits of the FRF itself); ``per_line=False`` gives each FRF the
    inverse of its RMS ``H_std`` (for p-LSCF: its equation error ``B - H A`` is not the FRF
    error, and a line-by-line ``1/H_std`` weight biases the poles badly; measured on the
    pelvis model with proportional noise: lost modes).
    """
    f, H = _frf_arrays(frequency_hz, H)
    ok = np.isfinite(H) & (f[:, None, None] > 0)
    if not ok.any():
        raise ValueError("no measured FRF line (all NaN or at 0 Hz)")
    if H_std is not None:
        std = np.asarray(H_std, dtype=float)
        if std.shape != H.shape:
            raise ValueError(f"H_std has shape {std.shape}, expected {H.shape}")
        ok &= np.isfinite(std) & (std > 0)
        if not ok.any():
            raise ValueError("no line with a finite positive H_std")
        std = np.where(ok, std, np.nan)
        floor = np.nanmedian(std) * 1e-3
        if per_line:
            weights = np.where(ok, 1.0 / np.maximum(np.nan_to_num(std, nan=1.0), floor), 0.0)
        else:
            count = ok.sum(axis=0)
            rms = np.sqrt(np.where(ok, std**2, 0.0).sum(axis=0) / np.maximum(count, 1))
            rms = np.where(count > 0, rms, np.nan)
            scale = 1.0 / np.maximum(np.nan_to_num(rms, nan=np.inf), floor)
            weights = np.where(ok, scale[None, :, :], 0.0)
    else:
        power = np.where(ok, np.abs(np.nan_to_num(H)) ** 2, 0.0).sum(axis=0)
        count = ok.sum(axis=0)
        rms = np.sqrt(power / np.maximum(count, 1))
        scale = np.where(rms > 0, 1.0 / np.where(rms > 0, rms, 1.0), 0.0)
        weights = np.where(ok, scale[None, :, :], 0.0)
    return f, np.where(ok, H, 0.0), weights


def _reduced_blocks(
    omega: np.ndarray, H: np.ndarray, weights: np.ndarray, max_order: int, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per-output blocks G_o, T_o from which the reduced p-LSCF normal matrix of any order follows.

    The unknowns are the numerator row ``beta_o`` ((p+1) x n_in) of each output and the shared
    denominator ``alpha`` ((p+1) n_in x n_in); equation of line k, output o:
    ``sum_j Omega_j(k) (beta_oj - H_o(k) alpha_j) = 0``, weighted by ``w_o(k)``. Stacking real
    and imaginary parts imposes real coefficients (conjugate pole pairs). Eliminating
    ``beta_o`` leaves ``M = sum_o Y_o^T (I - P_Xo) Y_o``; with the thin QR ``X_o = Q_o R_o``
    (nested: the first p+1 columns of Q_o span the order-p basis) this is
    ``T_o - G_o^T G_o`` restricted to the leading block, ``G_o = Q_o^T Y_o``. The QR avoids
    inverting ``X^T X``, which is ill-conditioned on the short arc of a narrow band.
    """
    n_f, n_out, n_in = H.shape
    P = max_order + 1
    basis = np.exp(1j * np.outer(omega, dt * np.arange(P)))  # (n_f, P)
    G = np.zeros((n_out, P, P * n_in))
    T = np.zeros((n_out, P * n_in, P * n_in))
    q_cache: dict[bytes, np.ndarray] = {}
    for o in range(n_out):
        # one weight per line keeps the row structure (a line missing any input is dropped
        # for this output)
        w = weights[:, o, :]
        w_line = np.where((w > 0).all(axis=1), np.sqrt(np.mean(w**2, axis=1)), 0.0)
        rows = w_line > 0
        if not rows.any():
            continue
        X = w_line[rows, None] * basis[rows]
        Y = -(X[:, :, None] * H[rows, o, None, :]).reshape(-1, P * n_in)
        Xr = np.concatenate([X.real, X.imag])
        Yr = np.concatenate([Y.real, Y.imag])
        # outputs whose line weights differ only by a factor share Q (the common case)
        key = (w_line / w_line.max()).tobytes()
        if key not in q_cache:
            q_cache[key] = np.linalg.qr(Xr, mode="reduced")[0]
        Q = q_cache[key]
        k = Q.shape[1]
        G[o, :k] = Q.T @ Yr
        T[o] = Yr.T @ Yr
    return G, T


def _denominator(G: np.ndarray, T: np.ndarray, order: int, n_in: int) -> np.ndarray | None:
    """Denominator coefficients alpha_0..alpha_{p-1} (each n_in x n_in), alpha_p = I."""
    p1 = order + 1
    m = p1 * n_in
    M = np.zeros((m, m))
    for o in range(G.shape[0]):
        Go = G[o, :p1, :m]
        M += T[o, :m, :m] - Go.T @ Go
    a = m - n_in
    try:
        alpha = -np.linalg.solve(M[:a, :a], M[:a, a:])
    except np.linalg.LinAlgError:
        alpha = -np.linalg.lstsq(M[:a, :a], M[:a, a:], rcond=None)[0]
    if not np.all(np.isfinite(alpha)):
        return None
    return alpha.reshape(order, n_in, n_in)


def _companion_poles(alpha: np.ndarray, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Poles (rad/s) and participation vectors from the matrix polynomial sum_j alpha_j z^j.

    Right fraction H = B A^-1: at a pole, ``l^T A(z) = 0`` (l: participation factor), i.e.
    ``sum_j alpha_j^T z^j l = 0``; solved through the block companion matrix.
    """
    order, n_in, _ = alpha.shape
    n = order * n_in
    C = np.zeros((n, n))
    if order > 1:
        C[: n - n_in, n_in:] = np.eye(n - n_in)
    C[n - n_in:, :] = -np.concatenate([alpha[j].T for j in range(order)], axis=1)
    z, vectors = np.linalg.eig(C)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.log(z.astype(complex)) / dt
    participation = vectors[:n_in, :].T
    norms = np.linalg.norm(participation, axis=1, keepdims=True)
    participation = participation / np.where(norms > 0, norms, 1.0)
    return s, participation


def _mac_vectors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """MAC between rows of a (n, k) and rows of b (m, k) -> (n, m); thesis eq. (4.49)."""
    num = np.abs(a.conj() @ b.T) ** 2
    den = np.outer(np.sum(np.abs(a) ** 2, axis=1), np.sum(np.abs(b) ** 2, axis=1))
    return num / np.where(den > 0, den, 1.0)


def _pole_status(poles: np.ndarray, participation: np.ndarray, previous: np.ndarray,
                 previous_participation: np.ndarray, crit: StabilityCriteria,
                 bandwidth: bool) -> np.ndarray:
    """Status (NEW .. STABLE_ALL) of one order's poles against the previous order's.

    Each pole is compared with the nearest pole of the previous order: frequency within
    ``frequency_tol``, damping within ``damping_tol``, participation MAC above
    ``vector_mac`` (more than one input). With ``bandwidth`` the frequency tolerance is that
    of :meth:`StabilityCriteria.frequency_tolerance` and only poles that
    :meth:`StabilityCriteria.same_pole` allows are compared (the selection's view of heavily
    damped modes; the diagram's statuses use ``frequency_tol``).
    """
    st = np.full(poles.size, NEW, dtype=int)
    if not (poles.size and previous.size):
        return st
    fn, zn = pole_frequency_damping(poles)
    fp, zp = pole_frequency_damping(previous)
    df = np.abs(fn[:, None] - fp[None, :]) / fn[:, None]
    if bandwidth:
        # the nearest pole of the previous order that may be the same mode: a heavily damped
        # mode's poles scatter by more than frequency_tol between orders, among light noise
        # poles
        tn = np.asarray(crit.frequency_tolerance(zn))[:, None]
        tp = np.asarray(crit.frequency_tolerance(zp))[None, :]
        df = np.where(np.maximum(tn, tp) <= 2.0 * np.minimum(tn, tp), df, np.inf)
        j = np.argmin(df, axis=1)
        close_f = df[np.arange(poles.size), j] < np.minimum(tn[:, 0], tp[0, j])
    else:
        j = np.argmin(df, axis=1)
        close_f = df[np.arange(poles.size), j] < crit.frequency_tol
    close_z = np.abs(zn - zp[j]) / np.maximum(zn, 1e-12) < crit.damping_tol
    mac = _mac_vectors(participation, previous_participation[j])[np.arange(poles.size),
                                                                 np.arange(poles.size)]
    n_in = participation.shape[1] if participation.ndim == 2 else 1
    close_v = mac > crit.vector_mac if n_in > 1 else np.ones(poles.size, dtype=bool)
    st = np.where(close_f, STABLE_FREQUENCY, NEW)
    st = np.where(close_f & close_z, STABLE_DAMPING, st)
    return np.where(close_f & close_z & close_v, STABLE_ALL, st)


def stabilisation_diagram(
    frequency_hz: np.ndarray,
    H: np.ndarray,
    max_order: int | None = None,
    H_std: np.ndarray | None = None,
    nyquist_hz: float | None = None,
    criteria: StabilityCriteria | None = None,
) -> StabilisationDiagram:
    """p-LSCF poles for model orders 1..max_order and their stability (see module docstring).

    ``frequency_hz`` (n_f,) may be non-uniform; ``H`` (n_f, n_out, n_in) receptance (NaN where
    not measured). ``nyquist_hz`` sets the z-domain sampling ``dt = 1 / (2 nyquist_hz)``;
    default 1.1 x the highest line, so poles at the band edge do not alias. Only stable poles
    with positive frequency are kept. When some output was never measured for some input
    (transducers moved between setups), the poly-reference rows are incomplete; the diagram
    then uses the common-denominator LSCF with every measured FRF as its own row (single
    reference), and the participation vectors are trivial.
    """
    crit = criteria or StabilityCriteria()
    f, Hc, w = _prepare(frequency_hz, H, H_std)
    n_f, n_out, n_in = Hc.shape
    used = (w > 0).any(axis=(1, 2))
    f, Hc, w = f[used], Hc[used], w[used]
    have = (w > 0).any(axis=0)
    if n_in > 1 and not have.all():
        Hc = Hc[:, have][:, :, None]
        w = w[:, have][:, :, None]
        n_in = 1
    if max_order is None:
        # n/3 keeps short records from over-fitting their noise, but at least 12 orders
        # (what the lines allow): a 25-line zoom window over the 174.9 Hz mode stopped at
        # order 8, where the mode was fully stable at 3 orders of the 4 the selection
        # needs ("no stable pole"; 43 of 60 pelvis zoom windows of 13-31 lines found their
        # mode, 60 of 60 with the floor, no spurious mode either way)
        max_order = max(min(12, 2 * f.size - 2), min(int(math.ceil(64 / n_in)), f.size // 3))
        max_order = max(max_order, 1)
    if not 1 <= max_order < 2 * f.size - 1:
        raise ValueError(
            f"max_order must be between 1 and {2 * f.size - 2} for {f.size} lines, got {max_order}"
        )
    f_nyq = nyquist_hz if nyquist_hz is not None else 1.1 * float(f.max())
    dt = 1.0 / (2.0 * f_nyq)
    G, T = _reduced_blocks(2 * np.pi * f, Hc, w, max_order, dt)
    orders = np.arange(1, max_order + 1)
    poles: list[np.ndarray] = []
    parts: list[np.ndarray] = []
    status: list[np.ndarray] = []
    for order in orders:
        alpha = _denominator(G, T, int(order), n_in)
        if alpha is None:
            s = np.zeros(0, dtype=complex)
            l = np.zeros((0, n_in), dtype=complex)
        else:
            s, l = _companion_poles(alpha, dt)
            keep = np.isfinite(s) & (s.imag > 0) & (s.real < 0)
            s, l = s[keep], l[keep]
            idx = np.argsort(s.imag)
            s, l = s[idx], l[idx]
        if poles:
            st = _pole_status(s, l, poles[-1], parts[-1], crit, bandwidth=False)
        else:
            st = np.full(s.size, NEW, dtype=int)
        poles.append(s)
        parts.append(l)
        status.append(st)
    return StabilisationDiagram(orders=orders, poles=poles, participation=parts, status=status,
                                line_frequency_hz=f)


def select_poles(
    diagram: StabilisationDiagram,
    band_hz: tuple[float, float] | None = None,
    criteria: StabilityCriteria | None = None,
) -> np.ndarray:
    """Automatic, reproducible pole choice from a stabilisation diagram.

    Rule (all tolerances from ``criteria``):

    0. Stability is judged as in the diagram, but with the frequency tolerance of
       :meth:`StabilityCriteria.frequency_tolerance` (``frequency_tol``, or 5 % of the
       pole's relative half-power bandwidth ``2 zeta`` when wider: zeta > 0.1), between poles
       that :meth:`StabilityCriteria.same_pole` allows. A heavily damped mode's p-LSCF poles
       scatter by 2-3 % between orders (zeta 0.35: missed in 14 of 60 draws with 1 %); for
       poles with zeta <= 0.1 nothing changes. "Within tolerance" below means ``same_pole``.
    1. Candidates: poles with damping ratio in ``(0, max_damping_ratio)``, frequency in
       ``band_hz``, and at least ``edge_lines`` measured lines on each side (a pole at the
       very edge of the data is not resolved by it, e.g. the 1 Hz artefact of accelerance
       divided by omega^2).
    2. Seeds: the fully stable candidates (frequency, damping, vector), sorted by frequency;
       each joins the nearest group whose median (frequency and damping) is within
       tolerance, else starts one (no chaining: slowly drifting noise poles do not string
       together; a light noise pole does not join or split a heavily damped mode's group).
    3. A group is a mode when it has fully stable poles at ``min_count`` or more orders and
       poles stable at least in frequency within tolerance of its median at
       ``max(min_count, ceil(min_fraction * n_orders))`` or more orders. (Damping estimates of
       lightly damped modes on a coarse grid converge slowly with the order, so full
       stability is required of a few orders only.)
    4. The mode's pole is the group's fully stable pole of highest order (nearest the median
       if that order holds several). Modes within tolerance of each other are merged (the
       one seen at more orders wins).

    Returns poles (rad/s) sorted by frequency.
    """
    crit = criteria or StabilityCriteria()
    lines = diagram.line_frequency_hz
    cands = []  # (frequency_hz, order, pole, fully_stable, damping_ratio)
    for k, order in enumerate(diagram.orders):
        fk, zk = pole_frequency_damping(diagram.poles[k])
        # statuses with the bandwidth tolerance (heavily damped poles); the diagram's own
        # use frequency_tol, and are the same for poles with zeta <= 0.1
        status = (_pole_status(diagram.poles[k], diagram.participation[k], diagram.poles[k - 1],
                               diagram.participation[k - 1], crit, bandwidth=True)
                  if k else diagram.status[k])
        for i in np.flatnonzero(status >= STABLE_FREQUENCY):
            if not 0 < zk[i] < crit.max_damping_ratio:
                continue
            if band_hz is not None and not band_hz[0] <= fk[i] <= band_hz[1]:
                continue
            if lines.size and min(np.sum(lines < fk[i]), np.sum(lines > fk[i])) < crit.edge_lines:
                continue
            cands.append((float(fk[i]), int(order), diagram.poles[k][i],
                          bool(status[i] == STABLE_ALL), float(zk[i])))
    seeds = sorted((c for c in cands if c[3]), key=lambda c: c[0])
    if not seeds:
        return np.zeros(0, dtype=complex)

    def tolerance(z: float) -> float:
        return max(crit.frequency_tol, 2.0 * crit.bandwidth_tol * min(max(z, 0.0),
                                                                    crit.max_damping_ratio))

    def same(fa: float, za: float, fb: float, zb: float) -> bool:  # crit.same_pole, scalar
        ta, tb = tolerance(za), tolerance(zb)
        return max(ta, tb) <= 2.0 * min(ta, tb) and abs(fa - fb) <= min(ta, tb) * fb

    # each group: [members, centre frequency, centre damping] (medians of its members)
    groups: list[list] = []
    reach = 2.0 * crit.bandwidth_tol * crit.max_damping_ratio + crit.frequency_tol
    for seed in seeds:
        # the nearest group that takes it (light seeds among a heavily damped mode's
        # scattered poles must not split its group)
        best = None
        for g in reversed(groups):
            if g[1] < seed[0] * (1 - 2 * reach):
                break  # groups are created in order of frequency
            if same(seed[0], seed[4], g[1], g[2]) and (
                    best is None or abs(seed[0] - g[1]) < abs(seed[0] - best[1])):
                best = g
        if best is None:
            groups.append([[seed], seed[0], seed[4]])
        else:
            best[0].append(seed)
            best[1] = float(np.median([x[0] for x in best[0]]))
            best[2] = float(np.median([x[4] for x in best[0]]))
    need = max(crit.min_count, int(math.ceil(crit.min_fraction * len(diagram.orders))))
    cf = np.array([c[0] for c in cands])
    cz = np.array([c[4] for c in cands])
    corder = np.array([c[1] for c in cands])
    chosen: list[tuple[int, complex]] = []
    for group, centre, z_centre in sorted(groups, key=lambda g: g[1]):
        if len({g[1] for g in group}) < crit.min_count:
            continue
        n_orders = np.unique(corder[crit.same_pole(cf, cz, centre, z_centre)]).size
        if n_orders < need:
            continue
        top = max(g[1] for g in group)
        rep = min((g for g in group if g[1] == top), key=lambda g: abs(g[0] - centre))[2]
        if chosen:
            f_last, z_last = pole_frequency_damping(np.array([chosen[-1][1]]))
            f_rep, z_rep = pole_frequency_damping(np.array([rep]))
            if same(f_rep[0], z_rep[0], f_last[0], z_last[0]):
                if n_orders > chosen[-1][0]:
                    chosen[-1] = (n_orders, rep)
                continue
        chosen.append((n_orders, rep))
    return np.array([c[1] for c in chosen], dtype=complex)


def edge_poles(
    diagram: StabilisationDiagram,
    criteria: StabilityCriteria | None = None,
) -> np.ndarray:
    """Poles at the edges of the measured lines, to be fitted as residual modes (rad/s).

    A mode a little above (or below) the band, like the pelvis model's 303.6 Hz mode under a
    5-300 Hz sweep, is not resolved by the data, but its tail near the band edge is far from
    the constant (or ``-1/omega^2``) residual term that LSFD gives it; the misfit then biases
    the residues and, in the refinement, the damping of the in-band modes (noise-free pelvis
    model with the true poles: 174.9 Hz damping +2.0 % with per-line weights, -0.8 % with
    per-FRF weights; 0.0 % with the 303.6 Hz pole added). Candidates are the frequency-stable
    poles with ``0 < zeta < max_damping_ratio`` that the selection rule leaves out because
    fewer than ``edge_lines`` lines lie on one side of them. They are grouped by frequency as
    in :func:`select_poles`; per side of the band, the group seen at the most orders (at least
    ``max(min_count, ceil(min_fraction * n_orders))``) gives its highest-order pole. At most
    one pole per side. The caller keeps a pole only when it explains the lines near it
    (:func:`mode_significance`). Returns up to two poles sorted by frequency.
    """
    crit = criteria or StabilityCriteria()
    lines = diagram.line_frequency_hz
    if lines.size < 2 * crit.edge_lines + 1:
        return np.zeros(0, dtype=complex)
    cands = {"low": [], "high": []}  # side -> [(frequency_hz, order, pole)]
    for k, order in enumerate(diagram.orders):
        fk, zk = pole_frequency_damping(diagram.poles[k])
        for i in np.flatnonzero(diagram.status[k] >= STABLE_FREQUENCY):
            if not 0 < zk[i] < crit.max_damping_ratio:
                continue
            below, above = np.sum(lines < fk[i]), np.sum(lines > fk[i])
            if min(below, above) >= crit.edge_lines:
                continue
            side = "low" if below < above else "high"
            cands[side].append((float(fk[i]), int(order), diagram.poles[k][i]))
    need = max(crit.min_count, int(math.ceil(crit.min_fraction * len(diagram.orders))))
    out = []
    for side in ("low", "high"):
        found = sorted(cands[side], key=lambda c: c[0])
        groups: list[list[tuple[float, int, complex]]] = []
        for cand in found:
            if groups:
                centre = float(np.median([g[0] for g in groups[-1]]))
                if abs(cand[0] - centre) / centre <= crit.frequency_tol:
                    groups[-1].append(cand)
                    continue
            groups.append([cand])
        best = None
        for group in groups:
            n_orders = len({g[1] for g in group})
            if n_orders >= need and (best is None or n_orders > best[0]):
                top = max(g[1] for g in group)
                centre = float(np.median([g[0] for g in group]))
                rep = min((g for g in group if g[1] == top), key=lambda g: abs(g[0] - centre))
                best = (n_orders, rep[2])
        if best is not None:
            out.append(best[1])
    poles = np.array(out, dtype=complex)
    return poles[np.argsort(np.abs(poles))]


def pick_poles(
    diagram: StabilisationDiagram, frequencies_hz: list[float] | np.ndarray,
    tolerance: float = 0.05, near: float = 0.01,
) -> np.ndarray:
    """Manual override: for each requested frequency, the diagram's pole nearest to it.

    Candidates are the poles stable at least in frequency (status >= ``STABLE_FREQUENCY``)
    within ``tolerance`` (relative) of the requested frequency and nearer to it than to any
    other requested frequency (on a log scale), so that two requests get two different
    poles: closely spaced modes, whose manual pick docs/ema.md recommends, otherwise both
    took the pole of the one seen fully stable at the higher order (two modes 0.7-1.7 %
    apart picked at their true frequencies: the same pole twice in 3 of 12 draws, the other
    mode lost). Among them, those within ``near`` (relative) of the requested frequency
    come first (a weak mode's column, fully stable at order 54, lost to a noise pole 4 %
    away fully stable at order 57), then fully stable poles, then the highest order, then
    the nearest. A frequency with no candidate raises ``ValueError`` naming it, and so does
    a frequency given twice.
    """
    targets = np.asarray(frequencies_hz, dtype=float).reshape(-1)
    if not np.all(np.isfinite(targets) & (targets > 0)):
        raise ValueError(f"frequencies must be positive (Hz), got {targets.tolist()}")
    if np.unique(targets).size < targets.size:
        raise ValueError(f"a frequency is given twice in {[float(t) for t in targets]}: "
                         "give one frequency per mode")
    out = []
    for n, target in enumerate(targets):
        others = np.delete(targets, n)
        best: tuple[float, ...] | None = None
        pole = 0j
        for k, order in enumerate(diagram.orders):
            fk, _ = pole_frequency_damping(diagram.poles[k])
            for i in range(fk.size):
                rel = abs(fk[i] - target) / target
                if rel > tolerance or diagram.status[k][i] < STABLE_FREQUENCY:
                    continue
                if others.size and np.min(np.abs(np.log(fk[i] / others))) < \
                        abs(math.log(fk[i] / target)):
                    continue  # nearer another requested frequency: that one's pole
                key = (int(rel > near), -int(diagram.status[k][i] == STABLE_ALL),
                       -int(order), rel)
                if best is None or key < best:
                    best, pole = key, diagram.poles[k][i]
        if best is None:
            raise ValueError(
                f"no pole stable in frequency within {tolerance:.0%} of {target:g} Hz"
                + (" nearer to it than to the other frequencies given" if others.size else "")
            )
        out.append(pole)
    poles = np.array(out, dtype=complex)
    return poles[np.argsort(np.abs(poles))]


def _lsfd_basis(omega: np.ndarray, poles: np.ndarray, lower: bool, upper: bool) -> np.ndarray:
    """Complex basis (n_f, 2 n_modes [+1] [+1]) whose real coefficients give the FRF."""
    s = 1j * omega[:, None]
    a = 1.0 / (s - poles[None, :])
    b = 1.0 / (s - poles.conj()[None, :])
    cols = [a + b, 1j * (a - b)]
    if lower:
        cols.append((-1.0 / omega**2)[:, None])
    if upper:
        cols.append(np.ones((omega.size, 1)))
    return np.concatenate(cols, axis=1)


def lsfd(
    frequency_hz: np.ndarray,
    H: np.ndarray,
    poles: np.ndarray,
    H_std: np.ndarray | None = None,
    lower_residual: bool = True,
    upper_residual: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares frequency-domain residues with fixed poles.

    Model per FRF (o, i): ``sum_r R_r/(i w - l_r) + conj(R_r)/(i w - conj l_r) - LR/w^2 + UR``
    with complex ``R_r`` and real ``LR``, ``UR``. Lines that are NaN are skipped; with
    ``H_std`` each line is weighted by ``1 / H_std``.
    Returns residues (n_modes, n_out, n_in), LR (n_out, n_in), UR (n_out, n_in) and the
    reconstructed H (n_f, n_out, n_in) on ``frequency_hz``.
    """
    f = np.asarray(frequency_hz, dtype=float).reshape(-1)
    H = np.asarray(H, dtype=complex)
    poles = np.asarray(poles, dtype=complex).reshape(-1)
    n_f, n_out, n_in = H.shape
    n_m = poles.size
    omega = 2 * np.pi * f
    positive = omega > 0
    basis = np.zeros((n_f, 2 * n_m + int(lower_residual) + int(upper_residual)), dtype=complex)
    basis[positive] = _lsfd_basis(omega[positive], poles, lower_residual, upper_residual)
    ok = np.isfinite(H) & positive[:, None, None]
    if H_std is not None:
        std = np.asarray(H_std, dtype=float)
        ok &= np.isfinite(std) & (std > 0)
    coef = np.zeros((basis.shape[1], n_out, n_in))
    columns = [(o, i) for o in range(n_out) for i in range(n_in)]
    # FRFs sharing the same measured lines (and no per-line weights) share one factorisation
    groups: dict[bytes, list[tuple[int, int]]] = {}
    for o, i in columns:
        key = ok[:, o, i].tobytes() if H_std is None else bytes(f"{o},{i}", "ascii")
        groups.setdefault(key, []).append((o, i))
    for members in groups.values():
        mask = ok[:, members[0][0], members[0][1]]
        if mask.sum() * 2 < basis.shape[1]:
            continue  # too few lines: leave this FRF unfitted (zeros)
        A = basis[mask]
        rhs = np.stack([H[mask, o, i] for o, i in members], axis=1)
        if H_std is not None:
            wline = 1.0 / np.asarray(H_std, dtype=float)[mask, members[0][0], members[0][1]]
            A = A * wline[:, None]
            rhs = rhs * wline[:, None]
        Ar = np.concatenate([A.real, A.imag])
        br = np.concatenate([rhs.real, rhs.imag])
        scale = np.linalg.norm(Ar, axis=0)
        scale = np.where(scale > 0, scale, 1.0)
        sol = np.linalg.lstsq(Ar / scale, br, rcond=None)[0] / scale[:, None]
        for c, (o, i) in enumerate(members):
            coef[:, o, i] = sol[:, c]
    residues = coef[:n_m] + 1j * coef[n_m: 2 * n_m]
    k = 2 * n_m
    LR = coef[k] if lower_residual else np.zeros((n_out, n_in))
    k += int(lower_residual)
    UR = coef[k] if upper_residual else np.zeros((n_out, n_in))
    H_fit = np.einsum("fc,coi->foi", basis, coef.astype(complex))
    H_fit[~positive] = np.nan
    return residues, LR, UR, H_fit


def _lsfd_leverage(
    frequency_hz: np.ndarray,
    ok: np.ndarray,
    weights: np.ndarray,
    poles: np.ndarray,
    H_std: np.ndarray | None,
    lower_residual: bool,
    upper_residual: bool,
) -> np.ndarray:
    """Leverage of each weighted residual entry in the LSFD fit (diagonal of the hat matrix).

    Laid out as :func:`refine_poles`' residual vector (real parts, then imaginary parts, of
    the (n_f, n_out, n_in) lines); 0 where a line is not used.
    """
    omega = 2 * np.pi * np.asarray(frequency_hz, dtype=float)
    used = ok.any(axis=(1, 2))  # ok is False at 0 Hz (and the basis undefined there)
    basis = np.zeros((omega.size, 2 * poles.size + int(lower_residual) + int(upper_residual)),
                     dtype=complex)
    basis[used] = _lsfd_basis(omega[used], poles, lower_residual, upper_residual)
    lev = np.zeros(ok.shape + (2,))
    for o in range(ok.shape[1]):
        for i in range(ok.shape[2]):
            mask = ok[:, o, i]
            if mask.sum() * 2 < basis.shape[1]:
                continue
            A = basis[mask]
            if H_std is not None:  # per-line weights change the fit; a constant one does not
                A = A * weights[mask, o, i][:, None]
            Q, _ = np.linalg.qr(np.concatenate([A.real, A.imag]))
            h = np.sum(Q**2, axis=1)
            n = int(mask.sum())
            lev[mask, o, i, 0] = h[:n]
            lev[mask, o, i, 1] = h[n:]
    return np.concatenate([lev[..., 0].ravel(), lev[..., 1].ravel()])


def refine_poles(
    frequency_hz: np.ndarray,
    H: np.ndarray,
    poles: np.ndarray,
    H_std: np.ndarray | None = None,
    lower_residual: bool = True,
    upper_residual: bool = True,
    return_std: bool = False,
    max_damping_ratio: float = 0.99,
) -> np.ndarray | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Poles refined by nonlinear least squares on the FRFs themselves (pole/residue fit).

    The residues and residual terms are linear given the poles, so they are eliminated by
    solving the LSFD problem inside the cost (variable projection; Golub & Pereyra, SIAM J.
    Numer. Anal. 10, 1973); only the poles are iterated (``scipy.optimize.least_squares``,
    trust region). This is the pole/residue optimisation of SDT (Balmes, IMAC XIV 1996) that
    the thesis used after ME'scope (ch. 11.3), and the last step of PolyMAX Plus / MLMM
    (El-kafafy et al., MSSP 2013): the p-LSCF poles minimise an equation error, not the FRF
    error, and are biased where few lines cover a mode (pelvis model, 1 % noise, 12 draws:
    mean damping error of the 38.1 Hz mode +22 % on a 2.5 Hz grid and +13 % on a 0.5 Hz grid,
    of the 174.9 Hz mode +15 % on a non-uniform ~1 Hz grid; after this fit -1 %, 0 %, 0 %).
    The LSCF poles are the start and the refinement is bounded around them; the start is kept
    when the refinement does not lower the cost. ``max_damping_ratio`` caps the damping (the
    selection rule's limit, so that a refined pole still passes it).

    With ``return_std`` also returns the standard uncertainties of the undamped frequencies
    (Hz) and damping ratios, from the reduced problem's Jacobian ``J`` and residuals ``r`` at
    the optimum: ``(J^T J)^-1 J^T diag(r_i^2 / (1 - h_i)^2) J (J^T J)^-1`` (HC3, ``h_i`` the
    leverage of residues and poles, ``1 - h_i`` floored at 0.05); NaN for a pole at a bound
    of the refinement or when the start was kept. The formula takes the noise of different
    lines and FRFs as independent: noise shared by the FRFs of one line (a force-channel
    error common to every output) is not in it, and the std then reads too small.
    """
    from pelvislab.model.identification import single_blas_thread

    # ~80 small least-squares solves per evaluation: a multi-threaded OpenBLAS on a loaded
    # 2-core machine made the refinement 50-100x slower (measured by session 32's review)
    with single_blas_thread():
        refined, f_std, z_std, _ = _refine_poles(frequency_hz, H, poles, H_std,
                                                 lower_residual, upper_residual,
                                                 max_damping_ratio)
    return (refined, f_std, z_std) if return_std else refined


def _refine_poles(
    frequency_hz: np.ndarray,
    H: np.ndarray,
    poles: np.ndarray,
    H_std: np.ndarray | None,
    lower_residual: bool,
    upper_residual: bool,
    max_damping_ratio: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`refine_poles` without the BLAS thread control: poles, their frequency and
    damping std, and which ended at a bound of the refinement."""
    import scipy.optimize

    poles = np.asarray(poles, dtype=complex).reshape(-1)
    nan = np.full(poles.size, np.nan)
    if poles.size == 0:
        return poles, nan, nan, np.zeros(poles.size, dtype=bool)
    f = np.asarray(frequency_hz, dtype=float).reshape(-1)
    Hc = np.asarray(H, dtype=complex)
    _, _, w = _prepare(f, Hc, H_std, per_line=True)
    ok = w > 0
    f0, z0 = pole_frequency_damping(poles)

    def residual(x: np.ndarray) -> np.ndarray:
        trial = poles_from_modal(f0 * np.exp(x[: poles.size]), x[poles.size:])
        _, _, _, H_fit = lsfd(f, Hc, trial, H_std, lower_residual, upper_residual)
        e = np.where(ok, (H_fit - np.nan_to_num(Hc)) * w, 0.0)
        return np.concatenate([e.real.ravel(), e.imag.ravel()])

    # a local polish, not a new search: each pole stays within +/-2 % in frequency and a
    # factor 2 in damping of its LSCF start (keeps a weak pole from drifting onto another)
    x0 = np.concatenate([np.zeros(poles.size), z0])
    lo = np.concatenate([np.full(poles.size, -0.02), z0 / 2])
    hi = np.concatenate([np.full(poles.size, 0.02),
                         np.maximum(np.minimum(2 * z0, max_damping_ratio), z0)])
    x0 = np.clip(x0, lo, hi)
    sol = scipy.optimize.least_squares(residual, x0, bounds=(lo, hi), x_scale="jac",
                                       method="trf", max_nfev=30)
    if not np.all(np.isfinite(sol.x)) or sol.cost > 0.5 * np.sum(residual(x0) ** 2):
        return poles, nan, nan, np.zeros(poles.size, dtype=bool)
    refined = poles_from_modal(f0 * np.exp(sol.x[: poles.size]), sol.x[poles.size:])
    at_bound = (sol.active_mask[: poles.size] != 0) | (sol.active_mask[poles.size:] != 0)
    f_std, z_std = nan.copy(), nan.copy()
    n_frf = int(ok.any(axis=0).sum())
    linear = n_frf * (2 * poles.size + int(lower_residual) + int(upper_residual))
    dof = 2 * int(ok.sum()) - linear - 2 * poles.size
    J = np.asarray(sol.jac)
    if dof > 0 and np.all(np.isfinite(J)):
        # sandwich (heteroscedasticity-consistent; White, Econometrica 48, 1980): the
        # weights are 1/H_std only when it is given, and noise proportional to |H| makes the
        # residual variance differ by orders of magnitude between a peak and the rest
        bread = np.linalg.pinv(J.T @ J)
        # HC3 (MacKinnon & White, J. Econometrics 29, 1985): each residual is inflated by its
        # leverage, that of the residues fitted to it (a peak's few lines hold most of it)
        # plus that of the poles; plain HC0/HC1 read 1.5-2x too small on the pelvis model
        lever = _lsfd_leverage(f, ok, w, refined, H_std, lower_residual, upper_residual)
        lever = lever + np.einsum("ij,jk,ik->i", J, bread, J)
        # (a leverage near 1 would inflate one residual without bound: capped at 20x)
        r = np.asarray(sol.fun) / np.maximum(1.0 - lever, 0.05)
        meat = (J * (r**2)[:, None]).T @ J
        cov = bread @ meat @ bread
        sd = np.sqrt(np.clip(np.diag(cov), 0.0, None))
        inside = (sol.active_mask == 0)
        free = inside[: poles.size] & inside[poles.size:]
        f_ref, _ = pole_frequency_damping(refined)
        f_std = np.where(free, f_ref * sd[: poles.size], np.nan)
        z_std = np.where(free, sd[poles.size:], np.nan)
    return refined, f_std, z_std, at_bound


def polish_wide_poles(
    frequency_hz: np.ndarray,
    H: np.ndarray,
    poles: np.ndarray,
    H_std: np.ndarray | None = None,
    fixed: np.ndarray | None = None,
    criteria: StabilityCriteria | None = None,
    lower_residual: bool = True,
    upper_residual: bool = True,
) -> np.ndarray:
    """Poles (rad/s) whose p-LSCF estimate is loose, fitted on the FRFs; the others unchanged.

    A pole is loose when the selection took it on its bandwidth tolerance
    (:meth:`StabilityCriteria.frequency_tolerance` wider than ``frequency_tol``: zeta > 0.1
    by default): a heavily damped mode's p-LSCF poles scatter between orders and are biased
    (p-LSCF minimises an equation error, not the FRF error; Peeters et al., Shock Vib. 11,
    2004). Left so, the misfit it leaves is taken up by noise poles that then pass the
    significance check (:func:`mode_significance`): a 35 %-damped mode at 150 Hz on a 1 Hz
    grid with 1 % noise came out at 144-148 Hz (chi^2 per value ~4 with ``H_std``), and
    light noise poles were kept beside it (4 in 20 draws with the bandwidth tolerance of
    the selection alone); with its pole fitted here, 150.0 Hz, chi^2 ~1 and every such
    pole's significance 1.0-1.2 (docs/ema.md). The fit is that of
    :func:`refine_poles` (variable projection, residues and residuals by LSFD, weights
    1/RMS per FRF or 1/``H_std`` per line) for the loose poles alone, every other pole of
    ``poles`` and ``fixed`` held, each loose pole within a quarter of its half-power
    bandwidth (``zeta / 2``, relative) in frequency and a factor 2 in damping (capped at
    ``max_damping_ratio``); the start is kept when the fit does not lower the cost.
    """
    import scipy.optimize

    crit = criteria or StabilityCriteria()
    poles = np.asarray(poles, dtype=complex).reshape(-1).copy()
    fixed = np.zeros(0, dtype=complex) if fixed is None else np.asarray(fixed, complex).ravel()
    f0, z0 = pole_frequency_damping(poles)
    loose = np.flatnonzero(np.asarray(crit.frequency_tolerance(z0)) > crit.frequency_tol)
    if loose.size == 0:
        return poles
    f = np.asarray(frequency_hz, dtype=float).reshape(-1)
    Hc = np.asarray(H, dtype=complex)
    _, _, w = _prepare(f, Hc, H_std, per_line=True)
    ok = w > 0

    def trial(x: np.ndarray) -> np.ndarray:
        out = poles.copy()
        out[loose] = poles_from_modal(f0[loose] * np.exp(x[: loose.size]), x[loose.size:])
        return out

    def residual(x: np.ndarray) -> np.ndarray:
        both = np.concatenate([trial(x), fixed])
        H_fit = lsfd(f, Hc, both, H_std, lower_residual, upper_residual)[3]
        e = np.where(ok, (H_fit - np.nan_to_num(Hc)) * w, 0.0)
        return np.concatenate([e.real.ravel(), e.imag.ravel()])

    z_l = z0[loose]
    x0 = np.concatenate([np.zeros(loose.size), z_l])
    lo = np.concatenate([-z_l / 2, z_l / 2])
    hi = np.concatenate([z_l / 2, np.maximum(np.minimum(2 * z_l, crit.max_damping_ratio), z_l)])
    sol = scipy.optimize.least_squares(residual, x0, bounds=(lo, hi), x_scale="jac",
                                       method="trf", max_nfev=30)
    if not np.all(np.isfinite(sol.x)) or sol.cost >= 0.5 * np.sum(residual(x0) ** 2):
        return poles
    return trial(sol.x)


MISSING_POLE_DAMPING = (0.05, 0.1, 0.2, 0.35)
"""Damping ratios from which :func:`fit_missing_pole` starts at the place of the misfit; its
lightest allowed damping is the first."""


def fit_missing_pole(
    frequency_hz: np.ndarray,
    H: np.ndarray,
    poles: np.ndarray,
    H_std: np.ndarray,
    diagram: StabilisationDiagram | None = None,
    criteria: StabilityCriteria | None = None,
    lower_residual: bool = True,
    upper_residual: bool = True,
) -> np.ndarray:
    """A heavily damped pole (rad/s) where the modal model of ``poles`` leaves the data
    beyond their noise away from every pole; an empty array when there is no such place or
    no pole there passes the checks below.

    A mode of zeta 0.2-0.35 has p-LSCF poles that scatter by 2-3 % between orders
    (docs/ema.md), so the selection may leave it out although the data show it: a 25 %
    damped mode at 150 Hz between two 1 % modes, as strong as they, 1 Hz grid and 1 %
    noise, was missed in 9 of 20 draws, and the misfit it left reached a local mean
    ``|H_fit - H|² / H_std²`` of 4.6-3900 at 131-148 Hz. The place: the line where that
    mean over 7 lines (:func:`misfit_beyond_noise`) is largest among the lines away from
    every pole (as the missing-mode note judges it: more than 5 ζf, 3 line spacings and
    2 % from each) and not within 4 lines of the band's ends (a mode outside the lines),
    when it exceeds ``MISSING_MODE_LOCAL_CHI2``. The fit: the pole alone, the others
    held, by variable projection as in :func:`refine_poles` (residues and residual terms by
    LSFD inside the cost; weights 1/``H_std`` per line; Golub & Pereyra, SIAM J. Numer.
    Anal. 10, 1973), within the lines (``edge_lines`` of them on each side) and zeta in
    ``[MISSING_POLE_DAMPING[0], max_damping_ratio]``, from that place at the damping
    ratios of ``MISSING_POLE_DAMPING`` and from every pole of ``diagram`` (any order, zeta
    in those bounds) whose half-power band ``f (1 +/- zeta)`` holds the place: the two
    starts of lowest cost are fitted. The pole is kept only when

    - it ends inside its bounds (a pole pushed to the lightest damping is a lighter mode,
      whose damping the bound misstates: a weak 3 % mode on a 1 Hz grid came out at 0.05
      and brought the misfit under the threshold in 2 of 10 draws; ``make demo``'s 112 Hz
      mode between its 10 Hz lines also ends there);
    - it lies away from every pole of ``poles`` as above (it duplicates no mode found);
    - the local mean at the place falls to ``MISSING_MODE_LOCAL_CHI2`` or below (:func:`ema`
      then runs the significance check again with it, where a 1 % mode that the missing
      one's misfit had made fail it comes back, fits it again with the modes kept, and
      checks the region, :func:`_region_explained`);
    - it passes the significance check of every mode (:func:`mode_significance`,
      ``min_significance``).

    ``frequency_hz`` (n_f,) Hz, sorted; ``H``, ``H_std`` (n_f, n_out, n_in) m/N;
    ``poles`` rad/s (modes and residual modes).
    """
    import scipy.optimize

    crit = criteria or StabilityCriteria()
    none = np.zeros(0, dtype=complex)
    poles = np.asarray(poles, dtype=complex).reshape(-1)
    f = np.asarray(frequency_hz, dtype=float).reshape(-1)
    Hc = np.asarray(H, dtype=complex)
    std = np.asarray(H_std, dtype=float)
    if f.size < 2 * (crit.edge_lines + 4) + 1:
        return none
    H_fit = lsfd(f, Hc, poles, std, lower_residual, upper_residual)[3]
    sums = _local_misfit(Hc, H_fit, std)
    if sums is None:
        return none
    local = sums[2]
    away, _ = _away_from_poles(f, f, poles)
    inner = np.zeros(f.size, dtype=bool)
    inner[4:-4] = True  # at the ends the missing-mode note speaks of a mode outside the lines
    place = away & inner & (local > MISSING_MODE_LOCAL_CHI2)
    if not place.any():
        return none
    at = int(np.flatnonzero(place)[np.argmax(local[place])])
    f_at = float(f[at])
    _, _, w = _prepare(f, Hc, std, per_line=True)
    ok = w > 0

    def pole(x: np.ndarray) -> np.ndarray:
        return poles_from_modal(np.array([f_at * np.exp(x[0])]), np.array([x[1]]))

    def residual(x: np.ndarray) -> np.ndarray:
        fit = lsfd(f, Hc, np.concatenate([poles, pole(x)]), std, lower_residual,
                   upper_residual)[3]
        e = np.where(ok, (fit - np.nan_to_num(Hc)) * w, 0.0)
        return np.concatenate([e.real.ravel(), e.imag.ravel()])

    z_lo, z_hi = MISSING_POLE_DAMPING[0], crit.max_damping_ratio
    lines = np.sort(f)
    lo = np.array([math.log(lines[crit.edge_lines] / f_at), z_lo])
    hi = np.array([math.log(lines[-1 - crit.edge_lines] / f_at), z_hi])
    starts = [np.array([0.0, z]) for z in MISSING_POLE_DAMPING]
    if diagram is not None:
        for k in range(len(diagram.orders)):
            fk, zk = diagram.frequency_hz(k), diagram.damping_ratio(k)
            near = (zk > z_lo) & (zk < z_hi) & (np.abs(fk - f_at) <= zk * fk)
            starts += [np.array([math.log(a / f_at), b]) for a, b in zip(fk[near], zk[near],
                                                                          strict=True)]
    inside = [x for x in starts if np.all(x > lo) and np.all(x < hi)]
    if not inside:
        return none
    costs = [float(np.sum(residual(x) ** 2)) for x in inside]
    best = None
    for i in np.argsort(costs)[:2]:
        sol = scipy.optimize.least_squares(residual, inside[i], bounds=(lo, hi),
                                           x_scale="jac", method="trf", max_nfev=30)
        if np.all(np.isfinite(sol.x)) and (best is None or sol.cost < best.cost):
            best = sol
    if best is None or np.any(best.active_mask != 0):
        return none
    new = pole(best.x)
    fn, zeta = pole_frequency_damping(new)
    if not _away_from_poles(f, fn, poles)[0][0]:
        return none
    both = np.concatenate([poles, new])
    fit = lsfd(f, Hc, both, std, lower_residual, upper_residual)[3]
    if _local_misfit(Hc, fit, std)[2][at] > MISSING_MODE_LOCAL_CHI2:
        return none
    significance = mode_significance(f, Hc, both, fit, crit.significance_window, std,
                                     lower_residual, upper_residual)[-1]
    if significance < crit.min_significance:
        return none
    return new


def _region_explained(frequency_hz: np.ndarray, H: np.ndarray, H_fit: np.ndarray,
                      H_std: np.ndarray, before: np.ndarray, pole: complex) -> bool:
    """Whether the fit ``H_fit`` with an added ``pole`` leaves the local mean
    ``|H_fit - H|² / H_std²`` (7 lines) at ``MISSING_MODE_LOCAL_CHI2`` or below over the
    lines of the pole's half-power band ``f (1 +/- zeta)`` that lay away from every pole
    of ``before`` (:func:`fit_missing_pole`: the added mode explains the region it was
    added for to near the noise)."""
    f = np.asarray(frequency_hz, dtype=float)
    fn, zeta = pole_frequency_damping(np.array([pole]))
    region = (_away_from_poles(f, f, before)[0]
              & (np.abs(f - fn[0]) <= zeta[0] * fn[0]))
    sums = _local_misfit(H, H_fit, H_std)
    # a band holding no such line explains nothing it was added for (it passed vacuously:
    # review)
    return (sums is not None and bool(region.any())
            and not np.any(sums[2][region] > MISSING_MODE_LOCAL_CHI2))


def modal_phase_collinearity(shapes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MPC (0..1, 1 = real mode) and mean phase deviation (deg) of complex shapes (n_dof, n).

    MPC: squared normalised eigenvalue spread of the covariance of real and imaginary parts
    (Pappa et al., J. Guid. Control Dyn. 16, 1993); MPD: magnitude-weighted mean angle between
    each entry and the best-fit straight line through the origin in the complex plane (the
    thesis' complexity plots, fig. 14.2).
    """
    shapes = np.asarray(shapes, dtype=complex)
    if shapes.ndim == 1:
        shapes = shapes[:, None]
    mpc = np.ones(shapes.shape[1])
    mpd = np.zeros(shapes.shape[1])
    for r in range(shapes.shape[1]):
        v = shapes[:, r]
        v = v[np.isfinite(v)]
        xy = np.stack([v.real, v.imag], axis=1)
        cov = xy.T @ xy
        ev = np.linalg.eigvalsh(cov)
        total = ev.sum()
        if total <= 0:
            continue
        mpc[r] = ((ev[1] - ev[0]) / total) ** 2
        direction = np.linalg.eigh(cov)[1][:, 1]
        mag = np.abs(v)
        proj = np.abs(xy @ direction)
        ang = np.arccos(np.clip(proj / np.where(mag > 0, mag, 1.0), 0.0, 1.0))
        mpd[r] = np.degrees(np.sum(mag * ang) / np.sum(mag))
    return mpc, mpd


def shapes_from_residues(residues: np.ndarray, measured: np.ndarray | None = None
                         ) -> tuple[np.ndarray, np.ndarray]:
    """Mode shapes (n_out, n_modes) and participation (n_modes, n_in) from residue matrices.

    Each residue matrix is rank one in theory (``R_r = psi_r l_r^T``); its dominant singular
    pair gives both. When some FRFs were not measured (``measured`` (n_out, n_in), or per
    mode (n_modes, n_out, n_in), False: transducers moved between setups, a run stopped
    before the mode), the rank-one factors are fitted to the measured entries only
    (alternating least squares from the SVD of the zero-filled matrix); an output with no
    measured FRF gets NaN. Shapes are normalised so their largest entry is 1.
    """
    n_m, n_out, n_in = residues.shape
    masks = np.ones((n_m, n_out, n_in), dtype=bool) if measured is None else \
        np.broadcast_to(np.asarray(measured, dtype=bool), (n_m, n_out, n_in))
    shapes = np.zeros((n_out, n_m), dtype=complex)
    part = np.zeros((n_m, n_in), dtype=complex)
    for r in range(n_m):
        mask = masks[r]
        R = np.where(mask, residues[r], 0.0)
        u, sv, vh = np.linalg.svd(R, full_matrices=False)
        psi = u[:, 0] * sv[0]
        l = vh[0].copy()
        if not mask.all():
            for _ in range(50):  # rank-one fit to the measured entries only
                den = (mask * np.abs(l[None, :]) ** 2).sum(axis=1)
                psi = np.where(den > 0, (R * l[None, :].conj()).sum(axis=1)
                               / np.where(den > 0, den, 1.0), np.nan)
                p0 = np.nan_to_num(psi)
                den = (mask * np.abs(p0[:, None]) ** 2).sum(axis=0)
                l = np.where(den > 0, (R * p0[:, None].conj()).sum(axis=0)
                             / np.where(den > 0, den, 1.0), 0.0)
            # an input with no measured FRF for this mode: unknown, not "does not excite it"
            l = np.where(mask.any(axis=0), l, np.nan)
        big = psi[np.nanargmax(np.abs(psi))] if np.any(np.isfinite(psi)) else 0
        if big != 0:
            psi, l = psi / big, l * big
        shapes[:, r] = psi
        part[r] = l
    return shapes, part


def frfs_around_modes(frequency_hz: np.ndarray, measured: np.ndarray, poles: np.ndarray
                      ) -> np.ndarray:
    """(n_modes, n_out, n_in) True where an FRF has measured lines on both sides of a
    mode's frequency (Hz), the nearest within max(5 half-power bandwidths ζf, 3 line
    spacings, 2 % of f). ``measured`` (n_f, n_out, n_in) bool on ``frequency_hz``.

    Elsewhere the FRF's residue for that mode is an extrapolation: a run stopped at
    173.75 Hz made an output the 231.9 Hz mode's reference (1.0 where the complete session
    gives 0.69) with the other entries near 0 (a helper's replay review, session 36)."""
    f = np.asarray(frequency_hz, dtype=float)
    fn, zeta = pole_frequency_damping(np.asarray(poles, dtype=complex).reshape(-1))
    n_out, n_in = measured.shape[1:]
    out = np.zeros((fn.size, n_out, n_in), dtype=bool)
    grid = np.sort(f[measured.any(axis=(1, 2))])
    for r, (fr, z) in enumerate(zip(fn, zeta, strict=True)):
        # the spacing of the lines around the mode: a stepped sine zooms in on peaks, and
        # the whole grid's median (0.5 Hz on the demo's) left a mode between its 10 Hz
        # lines no FRF (review of session 36's diff)
        at = int(np.searchsorted(grid, fr))
        spacing = _line_spacing_hz(grid[max(at - 3, 0):at + 3])
        reach = max(5 * z * fr, 3 * spacing, 0.02 * fr)
        below = measured & (f <= fr)[:, None, None]
        above = measured & (f >= fr)[:, None, None]
        near = measured & (np.abs(f - fr) <= reach)[:, None, None]
        out[r] = below.any(axis=0) & above.any(axis=0) & near.any(axis=0)
    return out


def _line_spacing_hz(frequency_hz: np.ndarray) -> float:
    """Typical line spacing (Hz): the median difference of consecutive lines (0 for one)."""
    f = np.asarray(frequency_hz, dtype=float)
    return float(np.median(np.diff(f))) if f.size > 1 else 0.0


def low_lines_dominate(frequency_hz: np.ndarray, H: np.ndarray, share: float = 0.95,
                       lowest: float = 0.01) -> str:
    """A note when the lowest lines of the band hold most of an FRF's power ("" otherwise).

    Without ``H_std`` each line of an FRF weighs alike in the residue fit and in the
    significance check, so lines whose values dwarf the rest decide both. That is what a
    receptance converted from accelerance (÷ω²) or mobility (÷ω) gives at its lowest lines,
    where the conversion multiplies the noise: the real beam (docs/ema.md) holds 99.8-99.9 %
    of each FRF's |H|² at 1 Hz, and its three strongest modes (460, 687 and 959 Hz) were
    dropped as not significant (first-day review, session 39). Judged per FRF: its largest
    value is at the band's first line, and the lowest ``lowest`` of the lines (at least one)
    hold ``share`` or more of its |H|² (a resonance near the band's start does not: the
    pelvis model's FRFs on a 2.5 Hz grid from 5 Hz hold at most 89.5 % in 5-7.5 Hz, and
    EMA finds its modes there). The note names the lowest band start at which no FRF is
    so dominated any more, if one within the lowest tenth of the lines is."""
    f = np.asarray(frequency_hz, dtype=float)
    if f.size < 2:
        return ""
    order = np.argsort(f)
    f = f[order]
    power = np.nan_to_num(np.abs(np.asarray(H)[order]) ** 2).reshape(f.size, -1)

    def dominated(start: int) -> tuple[bool, float]:
        rest = power[start:]
        n = max(1, int(np.ceil(lowest * rest.shape[0])))
        totals = rest.sum(axis=0)
        shares = np.where(totals > 0, rest[:n].sum(axis=0) / np.where(totals > 0, totals, 1),
                          0.0)
        hit = (np.argmax(rest, axis=0) == 0) & (shares >= share)
        return bool(hit.any()), float(shares[hit].max()) if hit.any() else 0.0

    hit, top = dominated(0)
    if not hit:
        return ""
    n_low = max(1, int(np.ceil(lowest * f.size)))
    # the first start that is not so dominated, among the lowest tenth of the lines (a
    # bounded search: each step reads every line), leaving the 4 lines ema needs
    last = min(f.size - 3, max(10, f.size // 10))
    start = next((k for k in range(1, last) if not dominated(k)[0]), None)
    advice = ("give H_std, or measure more lines above them" if start is None
              else f"start the band at {f[start]:.4g} Hz or above (--band), or give H_std")
    return (f"without H_std every line of an FRF weighs alike, and the lowest {n_low} "
            f"line(s) ({f[0]:.4g}-{f[n_low - 1]:.4g} Hz) hold {top:.1%} of an FRF's |H|^2: "
            "they decide the fit, and modes above may be dropped or poorly fitted (a "
            "receptance converted from accelerance or mobility multiplies the noise of its "
            f"lowest lines); {advice}")


def mode_significance(
    frequency_hz: np.ndarray,
    H: np.ndarray,
    poles: np.ndarray,
    H_fit: np.ndarray,
    window: float = 0.02,
    H_std: np.ndarray | None = None,
    lower_residual: bool = True,
    upper_residual: bool = True,
) -> np.ndarray:
    """Local significance of each mode: misfit without it over misfit with it, near it.

    For mode r, the LSFD fit is redone without its pole and the misfit is compared with the
    full fit's on the lines within ``window`` (relative) of its frequency (at least the 2
    nearest lines on each side). A physical mode explains its neighbourhood (ratio >> 1:
    measured 15-700 on the analytic, pelvis and beam data); a pole that only fits noise or an
    out-of-band tail does not (ratio ~ 1).
    """
    f = np.asarray(frequency_hz, dtype=float)
    ok = np.isfinite(H)
    if H_std is not None:  # lines lsfd leaves out (H_std zero or NaN) are not fitted: skip
        std = np.asarray(H_std, dtype=float)
        ok &= np.isfinite(std) & (std > 0)
    out = np.ones(poles.size)
    step = _line_spacing_hz(f)
    for r in range(poles.size):
        fr = abs(poles[r]) / (2 * np.pi)
        # a pole outside the lines (edge_poles) is judged on the lines at the nearest edge
        centre = min(max(fr, float(f.min())), float(f.max()))
        near = np.abs(f - centre) <= max(window * fr, 2.5 * step)
        # and the 2 nearest lines on each side, whatever the window holds (a random grid
        # left no line within 1.5 Hz of a clear 37.5 Hz mode, which was then dropped)
        below, above = np.flatnonzero(f < centre), np.flatnonzero(f >= centre)
        near[below[np.argsort(f[below])[-2:]]] = True
        near[above[np.argsort(f[above])[:2]]] = True
        mask = ok & near[:, None, None]
        if not mask.any():
            continue
        *_, without = lsfd(f, H, np.delete(poles, r), H_std, lower_residual, upper_residual)
        e_with = np.linalg.norm((H_fit - H)[mask])
        e_without = np.linalg.norm((without - H)[mask])
        out[r] = e_without / e_with if e_with > 0 else np.inf
    return out


def _local_misfit(H: np.ndarray, H_fit: np.ndarray, H_std: np.ndarray, half_window: int = 3
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Per line: the sum of ``|H_fit - H|² / H_std²`` over the FRFs, the number of values
    summed, and the mean over ``half_window`` lines on each side (arrays (n_f,)); None when
    no value has a finite fit and a positive ``H_std``. Lines in array order."""
    std = np.asarray(H_std, dtype=float)
    ok = np.isfinite(H) & np.isfinite(H_fit) & np.isfinite(std) & (std > 0)
    if not ok.any():
        return None
    r2 = np.where(ok, np.abs(np.where(ok, H_fit - H, 0)) ** 2 / np.where(ok, std, 1.0) ** 2,
                  0.0)
    kernel = np.ones(2 * half_window + 1)
    line_sum, line_n = r2.sum(axis=(1, 2)), ok.sum(axis=(1, 2))
    # "full" cut to the lines: "same" returns the kernel's length when there are fewer
    # lines than it (5 lines of validation_phase.toml: an IndexError; review, session 36)
    centred = slice(half_window, half_window + line_sum.size)
    local = (np.convolve(line_sum, kernel, "full")[centred]
             / np.maximum(np.convolve(line_n, kernel, "full")[centred], 1))
    return line_sum, line_n, local


def misfit_beyond_noise(frequency_hz: np.ndarray, H: np.ndarray, H_fit: np.ndarray,
                        H_std: np.ndarray, half_window: int = 3
                        ) -> tuple[float, float, float]:
    """How far the modal model leaves the data beyond the noise, and where most.

    Returns ``(chi2_per_value, frequency_hz, local_chi2)``: the mean of
    ``|H_fit - H|² / H_std²`` over the measured values with a positive ``H_std`` (about 1
    when the model explains the data to the noise; ``H_std`` as design 4.2 defines it,
    ``sqrt(E|H_measured - H|²)``), the line where that mean over the FRFs, averaged over
    ``half_window`` lines on each side, is largest, and that local mean (NaNs when no
    value qualifies). Arrays (n_f, n_out, n_in)."""
    sums = _local_misfit(H, H_fit, H_std, half_window)
    if sums is None:
        return float("nan"), float("nan"), float("nan")
    line_sum, line_n, local = sums
    # of the lines whose neighbourhood is worst, the worst line itself
    ties = np.flatnonzero(local >= local.max() * (1 - 1e-12))
    worst = int(ties[np.argmax(line_sum[ties] / np.maximum(line_n[ties], 1))])
    return (float(line_sum.sum() / line_n.sum()), float(np.asarray(frequency_hz, float)[worst]),
            float(local[worst]))


def _away_from_poles(frequency_hz: np.ndarray, at_hz: np.ndarray, poles: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Whether each frequency ``at_hz`` lies away from every pole: more than 5 half-power
    bandwidths ζf, 3 local line spacings (of the 7 lines of ``frequency_hz`` around it)
    and 2 % of f from each pole's frequency; and that line spacing (Hz), both (n_at,)."""
    f = np.sort(np.asarray(frequency_hz, dtype=float))
    at_hz = np.atleast_1d(np.asarray(at_hz, dtype=float))
    # the spacing of the lines there (a stepped sine zooms in on peaks: make demo's grid
    # is 0.5 Hz at the median, 10 Hz away from its two zoom windows)
    idx = np.searchsorted(f, at_hz)
    spacing_hz = np.array([_line_spacing_hz(f[max(i - 3, 0):i + 4]) for i in idx])
    fn, zeta = pole_frequency_damping(np.asarray(poles, dtype=complex).reshape(-1))
    reach = np.maximum(np.maximum(5 * zeta * fn, 0.02 * fn)[None, :],
                       3 * spacing_hz[:, None])
    away = np.all(np.abs(at_hz[:, None] - fn[None, :]) > reach, axis=1)
    return away, spacing_hz


def _missing_mode_note(frequency_hz: np.ndarray, H: np.ndarray, H_fit: np.ndarray,
                       H_std: np.ndarray, poles: np.ndarray) -> str:
    """A note when the data's largest misfit beyond the noise lies away from every pole
    fitted: a mode the selection left out ("" otherwise). Away: more than 5 half-power
    bandwidths ζf, 3 local line spacings and 2 % from each pole's frequency (misfit *at* a
    mode is p-LSCF's pole bias, which ``--refine`` removes: on the analytic test systems
    with every mode found the largest local mean, 1.3-14, lay at a mode in 19 of 20 fits,
    and none of 48 such fits gets the note)."""
    _chi2, f_worst, local = misfit_beyond_noise(frequency_hz, H, H_fit, H_std)
    if not local > MISSING_MODE_LOCAL_CHI2:
        return ""
    f = np.sort(np.asarray(frequency_hz, dtype=float))
    away, spacing = _away_from_poles(f, np.array([f_worst]), poles)
    spacing_hz = float(spacing[0])
    if not away[0]:
        return ""
    if f_worst <= f[min(3, f.size - 1)] or f_worst >= f[max(f.size - 4, 0)]:
        # the residual terms stand for the modes outside the lines; one near the edge
        # bends it more than they follow (make demo's session with 112 Hz picked: its
        # first line, 30 Hz, with the model's 10.4 Hz mode below the band)
        return (f"the data at the edge of the lines, near {f_worst:.4g} Hz, are left beyond "
                f"their noise (mean |H_fit - H|^2 / H_std^2 = {local:.3g} over 7 lines; 1 at "
                "the noise): a mode outside the lines bends them more than the residual terms "
                "follow; a wider band, where measured, would fit it")
    return (f"the data near {f_worst:.4g} Hz are left beyond their noise (mean "
            f"|H_fit - H|^2 / H_std^2 = {local:.3g} over 7 lines; 1 at the noise), away from "
            "every mode found: a mode may be missing there (too heavily damped to stabilise "
            f"over orders, or too lightly damped for lines {spacing_hz:.3g} Hz apart there); "
            "see the stabilisation diagram, or pick a pole there by hand "
            "(--frequencies, or the GUI's Modes tab)")


def _misfit_concentration_note(frequency_hz: np.ndarray, H: np.ndarray, H_fit: np.ndarray,
                               min_fit_error: float = 0.1, max_share_of_lines: float = 0.02,
                               nested: bool = True) -> str:
    """A note when, without ``H_std``, the modal fit leaves a relative misfit of at least
    ``min_fit_error`` (:meth:`EmaResult.fit_error`) and half of that misfit (in |H_fit-H|²)
    sits on at most ``max_share_of_lines`` of the lines (at least 2): "" otherwise.

    Without ``H_std`` every line of an FRF weighs alike, so a few lines the modes cannot
    follow decide the figure, and pull the residues. On the real beam (docs/ema.md) with
    ``--band 3 1000`` the fit error is 0.75, 65 % of the misfit at 3 Hz (the lowest line
    of a receptance converted from accelerance, noise ÷ω²), below the 95 % share that
    :func:`low_lines_dominate` notes; from 20 Hz it is 0.038 (measured, session 50).
    Lines at the band's start get a band start from which the lines, as fitted, would not
    get the note (``nested``: whether to look for one)."""
    f = np.asarray(frequency_hz, dtype=float)
    ok = np.isfinite(H) & np.isfinite(H_fit)
    err = np.where(ok, np.abs(H_fit - H), 0.0) ** 2
    total_err = float(err.sum())
    total = float((np.where(ok, np.abs(H), 0.0) ** 2).sum())
    if not (total > 0 and total_err > 0) or np.sqrt(total_err / total) < min_fit_error:
        return ""
    per_line = err.reshape(f.size, -1).sum(axis=1)
    order = np.argsort(per_line)[::-1]
    n = int(np.searchsorted(np.cumsum(per_line[order]), 0.5 * total_err) + 1)
    if n > max(2, int(max_share_of_lines * f.size)):
        return ""
    lines = np.sort(f[order[:n]])
    share = float(per_line[order[:n]].sum() / total_err)
    where = ", ".join(f"{x:.4g}" for x in lines)
    order_f = np.argsort(f)
    at_start = lines[-1] <= f[order_f][min(n + 2, f.size - 1)]
    start = None
    if at_start and nested:
        # the first band start whose lines, as fitted now, no longer get this note: one
        # line past the noisy ones was not enough (noise ÷ω² dominates each next lowest
        # line: the beam's advice walked 3, 4, 5 Hz...); from 19 Hz the beam fits to 0.039
        fs, Hs, Fs = f[order_f], H[order_f], H_fit[order_f]
        start = next((fs[k] for k in range(1, min(f.size - 3, max(10, f.size // 10)))
                      if not _misfit_concentration_note(fs[k:], Hs[k:], Fs[k:],
                                                        min_fit_error, max_share_of_lines,
                                                        nested=False)), None)
    advice = ("a mode may be missing or poorly fitted there: see the stabilisation diagram, "
              "or give H_std" if not at_start else
              "if they are noise (the lowest lines of a receptance converted from "
              "accelerance or mobility), "
              + (f"start the band at {start:.4g} Hz or above (--band), " if start is not None
                 else "start the band above them (--band), ")
              + "or give H_std")
    return (f"the modal fit leaves {np.sqrt(total_err / total):.0%} of the FRFs' norm "
            f"unexplained (fit_error), {share:.0%} of that misfit at {n} line(s) ({where} "
            "Hz): without H_std every line weighs alike, so those lines decide the fit; "
            + advice)


def _spacing_hint(frequency_hz: np.ndarray) -> str:
    """Why lightly damped modes may go unseen on this grid (text for the notes).

    A mode shows in stepped-sine lines only when its half-power bandwidth 2ζf_n spans
    about one line spacing Δf or more, i.e. ζ ≳ Δf / (2 f_n); the appendix E model's
    damping ratios are 0.009-0.52 % (0.018-0.52 % up to 303.6 Hz; computed from the model,
    not a thesis figure), so a 10 Hz grid resolves none of them."""
    f = np.sort(np.asarray(frequency_hz, float))
    df = _line_spacing_hz(f)
    if not df > 0:
        return ""
    lo, hi = float(f[0]), float(f[-1])
    return (f"; lines are {df:.3g} Hz apart: a mode is resolved when its half-power "
            f"bandwidth 2 zeta f spans about one spacing (zeta >= {df / (2 * hi):.2%} at "
            f"{hi:.4g} Hz, {df / (2 * lo):.2%} at {lo:.4g} Hz); lighter modes fall between "
            "the lines: measure on a finer grid around the peaks")


def _frequency_stable_hint(diagram: StabilisationDiagram, band_hz: tuple[float, float],
                           crit: StabilityCriteria) -> str:
    """The poles stable in frequency at as many orders as a mode needs but fully stable
    (frequency, damping, vector) at fewer than ``min_count``, as text for the no-mode note
    ("" when none). Such a pole's damping wanders from order to order, as that of a mode
    narrower than the line spacing does; the real beam's 51.5 Hz mode (zeta 0.05 % on a
    1 Hz grid) with ``--band 40 60``: stable in frequency at orders 3-12, fully at 3, and the
    note said only "measure on a finer grid" (review 67). Frequencies are grouped within
    ``frequency_tol`` of the first member."""
    need = max(crit.min_count, int(math.ceil(crit.min_fraction * len(diagram.orders))))
    rows = []  # (frequency_hz, order, fully stable)
    for k, order in enumerate(diagram.orders):
        fk, zk = diagram.frequency_hz(k), diagram.damping_ratio(k)
        for i in np.flatnonzero(diagram.status[k] >= STABLE_FREQUENCY):
            if 0 < zk[i] < crit.max_damping_ratio and band_hz[0] <= fk[i] <= band_hz[1]:
                rows.append((float(fk[i]), int(order), bool(diagram.status[k][i] == STABLE_ALL)))
    rows.sort()
    said = []
    start = 0
    while start < len(rows):
        end = start
        while end + 1 < len(rows) and rows[end + 1][0] <= rows[start][0] * (1 + crit.frequency_tol):
            end += 1
        group = rows[start:end + 1]
        orders = {r[1] for r in group}
        full = {r[1] for r in group if r[2]}
        if len(orders) >= need and len(full) < crit.min_count:
            f_mid = float(np.median([r[0] for r in group]))
            said.append(f"{f_mid:.5g} Hz (stable in frequency at {len(orders)} orders, in "
                        f"damping too at {len(full)})")
        start = end + 1
    if not said:
        return ""
    picks = " ".join(s.split(" Hz")[0] for s in said)
    return (f"; a mode needs {crit.min_count} orders stable in damping too, and pole(s) at "
            f"{'; '.join(said)} fall short: a damping narrower than the lines resolve "
            f"wanders with the order. Pick them by hand (--frequencies {picks}) or raise "
            "--max-order")


def ema(
    frequency_hz: np.ndarray,
    H: np.ndarray,
    band_hz: tuple[float, float] | None = None,
    H_std: np.ndarray | None = None,
    max_order: int | None = None,
    frequencies_hz: list[float] | np.ndarray | None = None,
    criteria: StabilityCriteria | None = None,
    lower_residual: bool = True,
    upper_residual: bool = True,
    refine: bool = False,
    residual_poles: bool = True,
) -> EmaResult:
    """Experimental modal analysis of receptance FRFs (p-LSCF poles, then LSFD residues).

    ``frequency_hz`` (n_f,) Hz, any spacing; ``H`` (n_f, n_out, n_in) m/N, NaN where not
    measured; ``band_hz`` restricts the analysis (default: all lines above 0 Hz);
    ``frequencies_hz`` replaces the automatic selection by the poles nearest those frequencies;
    ``refine`` polishes the selected poles by a nonlinear pole/residue fit (:func:`refine_poles`)
    and gives their uncertainties. Off by default: it removes p-LSCF's damping bias when the
    selection holds every mode of the band, but a mode left out (two close modes merged, a
    heavily damped one missed, a partial manual pick) pulls the refined poles (measured in
    docs/ema.md);
    ``residual_poles`` fits a stable pole at the edge of the lines (fewer than ``edge_lines``
    lines on one side), when one explains the lines near it, together with the modes
    (:func:`edge_poles`; ``EmaResult.residual_poles``). With ``H_std`` and the automatic
    selection, up to two heavily damped modes that do not stabilise over orders are fitted
    where the modes found leave the data beyond their noise (:func:`fit_missing_pole`; the
    notes name them).
    Returns an :class:`EmaResult` (modes sorted by frequency, shapes, complexity, fit).
    """
    from pelvislab.model.identification import single_blas_thread

    # thousands of small BLAS/LAPACK calls: a multi-threaded OpenBLAS on a loaded 2-core
    # machine made the whole analysis 5-100x slower (measured in session 32)
    with single_blas_thread():
        return _ema(frequency_hz, H, band_hz, H_std, max_order, frequencies_hz, criteria,
                    lower_residual, upper_residual, refine, residual_poles)


def _ema(
    frequency_hz: np.ndarray,
    H: np.ndarray,
    band_hz: tuple[float, float] | None,
    H_std: np.ndarray | None,
    max_order: int | None,
    frequencies_hz: list[float] | np.ndarray | None,
    criteria: StabilityCriteria | None,
    lower_residual: bool,
    upper_residual: bool,
    refine: bool,
    residual_poles: bool,
) -> EmaResult:
    """:func:`ema` without the BLAS thread control."""
    f, Hc = _frf_arrays(frequency_hz, H)
    std = None if H_std is None else np.asarray(H_std, dtype=float).reshape(Hc.shape)
    sel = f > 0
    if band_hz is not None:
        lo, hi = float(band_hz[0]), float(band_hz[1])
        if not 0 <= lo < hi:
            raise ValueError(f"band must satisfy 0 <= LO < HI, got {lo:g} {hi:g}")
        sel &= (f >= lo) & (f <= hi)
    sel &= np.isfinite(Hc).any(axis=(1, 2))
    if sel.sum() < 4:
        raise ValueError(f"only {int(sel.sum())} measured lines in the band; need at least 4")
    f, Hc = f[sel], Hc[sel]
    std = None if std is None else std[sel]
    crit = criteria or StabilityCriteria()
    diagram = stabilisation_diagram(f, Hc, max_order=max_order, H_std=std, criteria=crit)
    band = (float(f.min()), float(f.max()))
    notes: list[str] = []
    no_pole = ""
    if frequencies_hz is not None and len(frequencies_hz) > 0:
        outside = [float(x) for x in np.reshape(frequencies_hz, -1)
                   if np.isfinite(x) and not band[0] <= x <= band[1]]
        if outside:  # "no pole stable near 112 Hz" with the band at 150-250 Hz (review 67)
            raise ValueError(f"frequencies {outside} Hz lie outside the band's lines "
                             f"({band[0]:.6g}-{band[1]:.6g} Hz): widen --band or pick "
                             "within it")
        poles = pick_poles(diagram, frequencies_hz)
        selection = "manual"
    else:
        poles = select_poles(diagram, band, crit)
        selection = "auto"
        if poles.size == 0:
            top_order = int(diagram.orders[-1]) if len(diagram.orders) else 0
            if top_order < 2 * crit.min_count:
                # the selection needs min_count fully stable orders: a diagram this short
                # (a small --max-order, or so few lines that 2n - 2 is the highest order
                # they allow) cannot show them, whatever the grid resolves
                allowed = 2 * f.size - 2
                advice = (f"try --max-order {min(12, allowed)}, or measure more lines"
                          if allowed > top_order else
                          f"{f.size} lines allow no higher order: measure more lines")
                no_pole = (f"no stable pole found in the band: the stabilisation diagram "
                           f"goes up to order {top_order} only; a mode needs "
                           f"{crit.min_count} stable orders ({advice})")
            else:
                no_pole = ("no stable pole found in the band" + _spacing_hint(f)
                           + _frequency_stable_hint(diagram, band, crit))
    edges = edge_poles(diagram, crit) if residual_poles else np.zeros(0, dtype=complex)
    if edges.size and poles.size:  # a manual pick may name a pole at the edge itself
        fe, _ = pole_frequency_damping(edges)
        fm, _ = pole_frequency_damping(poles)
        apart = np.min(np.abs(fe[:, None] / fm[None, :] - 1), axis=1) > crit.frequency_tol
        edges = edges[apart]

    def fit(modes: np.ndarray, extra: np.ndarray) -> tuple[np.ndarray, ...]:
        both = np.concatenate([modes, extra])
        res, lr, ur, h = lsfd(f, Hc, both, std, lower_residual, upper_residual)
        sig = mode_significance(f, Hc, both, h, crit.significance_window, std,
                                lower_residual, upper_residual)
        return res[: modes.size], lr, ur, h, sig[: modes.size], sig[modes.size:]

    if selection == "auto" and poles.size:
        # heavily damped modes' p-LSCF poles are loose: fit them before the significance
        # check, whose verdict on their neighbours depends on them (polish_wide_poles)
        poles = polish_wide_poles(f, Hc, poles, std, edges, crit, lower_residual,
                                  upper_residual)
        poles = poles[np.argsort(np.abs(poles))]

    def check(modes: np.ndarray, extra: np.ndarray) -> tuple:
        """The modes and edge poles that pass the significance check, and their fit."""
        residues, LR, UR, H_fit, significance, edge_significance = fit(modes, extra)
        # a dropped pole changes its neighbours' significance (it may have stood in for
        # part of a mode, or for an edge pole's tail): refit and check again until every
        # mode and edge pole kept passes, a few rounds at most (a mode kept at
        # significance 1.1-1.23 after one round was found by session 32's review and
        # property search)
        for _ in range(4):
            weak = (significance < crit.min_significance if selection == "auto"
                    else np.zeros(modes.size, dtype=bool))
            weak_edges = edge_significance < crit.min_significance
            if not weak.any() and not weak_edges.any():
                break
            modes, extra = modes[~weak], extra[~weak_edges]
            residues, LR, UR, H_fit, significance, edge_significance = fit(modes, extra)
        return modes, extra, residues, LR, UR, H_fit, significance

    selected, selected_edges = poles, edges
    poles, edges, residues, LR, UR, H_fit, significance = check(poles, edges)
    added = np.zeros(0, dtype=complex)
    # a heavily damped mode does not stabilise over orders and may be left out although
    # the data show it (fit_missing_pole); one added changes what the others must explain
    # (its misfit had made a 1 % mode 90 Hz away fail the significance check), so the check
    # runs again with the selected poles it dropped, but those within the added pole's
    # half-power band: they stood in for it, and dropped together with it (all weak poles
    # go at once) they took it along (1 of 20 draws); at most two such poles
    while selection == "auto" and std is not None and added.size < 2:
        new = fit_missing_pole(f, Hc, np.concatenate([poles, edges]), std, diagram, crit,
                               lower_residual, upper_residual)
        if not new.size:
            break
        fa, za = pole_frequency_damping(np.concatenate([added, new]))
        fs, _ = pole_frequency_damping(selected)
        inside = np.any(np.abs(fs[:, None] - fa[None, :]) <= (za * fa)[None, :], axis=1)
        restored = selected[~np.isin(selected, poles) & ~inside]
        modes = np.concatenate([poles, restored, new])
        modes = modes[np.argsort(np.abs(modes))]
        state = check(modes, selected_edges)
        if np.any(state[0] == new[0]):
            # fitted again with the modes now kept (a 1 % mode restored, noise poles
            # dropped), as the selection's heavily damped poles are (zeta > 0.1; lighter
            # ones are left as fitted): 0.4-0.9 % off in frequency when fitted without the
            # restored mode, <= 0.07 % with it
            others = np.concatenate([state[0][state[0] != new[0]], state[1]])
            polished = polish_wide_poles(f, Hc, new, std, others, crit, lower_residual,
                                         upper_residual)
            if polished[0] != new[0]:
                modes[modes == new[0]] = polished[0]
                new = polished
                state = check(modes, selected_edges)
        if not np.any(state[0] == new[0]) or not _region_explained(
                f, Hc, state[5], std, np.concatenate([poles, edges]), new[0]):
            break  # not significant, or not explaining its region, with the rest refitted
        added = np.concatenate([added, new])
        poles, edges, residues, LR, UR, H_fit, significance = state
    if no_pole and not added.size:
        notes.append(no_pole)
    if added.size:
        fa, za = pole_frequency_damping(added)
        notes.append("heavily damped mode(s) fitted where the selected modes left the data "
                     "beyond their noise (their poles do not stabilise "
                     "over orders; fitted on the FRFs with the other poles held, kept as they "
                     "explain their region to the noise and pass the significance check): "
                     + ", ".join(f"{x:.4g} Hz (zeta {z:.2%})" for x, z in zip(fa, za,
                                                                             strict=True))
                     + "; judge them with the stabilisation diagram (their frequency is "
                     "known to a few % only: --refine gives its std)")
    refit = False
    dropped, _ = pole_frequency_damping(selected[~np.isin(selected, poles)])
    if dropped.size:
        notes.append("dropped pole(s) that do not explain their neighbourhood (significance "
                     f"< {crit.min_significance:g}): "
                     + ", ".join(f"{x:.4g} Hz" for x in sorted(dropped)))
    dominant = low_lines_dominate(f, Hc) if std is None else ""
    if dominant:
        notes.append(dominant)
    # the refinement comes after the significance test: polished noise poles would pass it,
    # and every extra pole costs the nonlinear fit two parameters
    f_std = np.full(poles.size, np.nan)
    z_std = np.full(poles.size, np.nan)
    if refine and poles.size:
        both, f_sd, z_sd, at_bound = _refine_poles(
            f, Hc, np.concatenate([poles, edges]), std, lower_residual, upper_residual,
            crit.max_damping_ratio)
        if np.any(at_bound[: poles.size]):
            fb, _ = pole_frequency_damping(both[: poles.size][at_bound[: poles.size]])
            notes.append("the refinement pushed the pole(s) at " + ", ".join(
                f"{x:.4g} Hz" for x in fb) + " to their bounds (+/-2 % in frequency, a factor 2 "
                "in damping): something the modal model leaves out pulls them (a mode not "
                "selected nearby?); their frequency and damping are not reliable and have "
                "no std")
        order = np.argsort(np.abs(both[: poles.size]))
        poles, edges = both[: poles.size][order], both[poles.size:]
        f_std, z_std = f_sd[: order.size][order], z_sd[: order.size][order]
        refit = True
    if refit:
        residues, LR, UR, H_fit, significance, _ = fit(poles, edges)
    if edges.size:
        fe, ze = pole_frequency_damping(edges)
        notes.append("residual mode(s) at the edge of the lines (fewer than "
                     f"{crit.edge_lines} lines on one side), fitted with the modes but not "
                     "reported as modes: " + ", ".join(
                         f"{x:.4g} Hz (zeta {z:.2%})" for x, z in zip(fe, ze, strict=True)))
    if selection == "manual" and np.any(significance < crit.min_significance):
        # kept because picked, where the automatic selection drops them: a pick of the
        # real beam's 55.4 Hz noise pole (significance 1.06) read like a mode (review 67)
        fw, _ = pole_frequency_damping(poles[significance < crit.min_significance])
        notes.append("picked pole(s) that do not pass the significance check (< "
                     f"{crit.min_significance:g}; kept because picked): " + ", ".join(
                         f"{x:.4g} Hz ({s_:.3g})" for x, s_ in zip(
                             fw, significance[significance < crit.min_significance],
                             strict=True))
                     + ": the data near them are explained about as well without them; "
                     "check them on the stabilisation diagram")
    if std is None and not dominant:
        concentrated = _misfit_concentration_note(f, Hc, H_fit)
        if concentrated:
            notes.append(concentrated)
    if std is not None:
        # a mode the selection left out (a heavily damped one is not stable over orders:
        # zeta 10 % at 150 Hz between two 1 % modes, local mean 23-30 there)
        missing = _missing_mode_note(f, Hc, H_fit, std, np.concatenate([poles, edges]))
        if missing and refit:
            # the refinement is a fit of the selected modes alone (docs/ema.md: a mode left
            # out moved a refined neighbour 18 sigma)
            missing += ("; the poles were refined as if the selection held every mode of "
                        "the band, so such a mode pulls them: compare without --refine")
        if missing:
            notes.append(missing)
    measured = np.isfinite(Hc)
    around = frfs_around_modes(f, measured, poles)
    shapes, part = shapes_from_residues(residues, around)
    partial = [k for k in range(poles.size)
               if (around[k] != measured.any(axis=0)).any()]
    if partial:
        notes.append("shape entries left out (null) where an FRF has no lines around the "
                     "mode (a run stopped, or a setup measured another band): "
                     + "; ".join(f"{fn_:.4g} Hz: {int((~around[k] & measured.any(axis=0)).sum())} "
                                 "FRF(s)" for k, fn_ in
                                 ((k, pole_frequency_damping(poles[k:k + 1])[0][0])
                                  for k in partial)))
    mpc, mpd = modal_phase_collinearity(shapes)
    fn, zeta = pole_frequency_damping(poles)
    return EmaResult(
        frequency_hz=fn, damping_ratio=zeta, poles=poles, shapes=shapes, participation=part,
        residues=residues, mpc=mpc, mpd_deg=mpd, lower_residual=LR, upper_residual=UR,
        fit_frequency_hz=f, H_fit=H_fit, H_measured=Hc, diagram=diagram,
        selection=selection, notes=notes, significance=significance, residual_poles=edges,
        frequency_std_hz=f_std, damping_ratio_std=z_std,
    )
