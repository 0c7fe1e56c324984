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

``converged`` means the result can be trusted, not only that the optimiser stopped: besides
the optimiser's convergence and no parameter on its bound, every measured mode must end
paired with a model mode of its own, at MAC >= :data:`PAIR_MIN_MAC` and with the model's
frequency within the measured one's uncertainty (``ModalData.frequency_tol_hz``; peak
picking: between the lines next to the peak), and the modes must determine every parameter
(no unresolved direction, no std above the value). The message says which fails.

Peak-picked modes (``ModalData.picking``) are weighted by a standard uncertainty per datum
(the frequency's tolerance and picking bias, the shape's picking bias: both read on the
model's own FRFs at the fit, damped at least as the data's peaks show, :func:`_picking_bias`)
and their std are absolute; modes given otherwise are fitted
unweighted with std scaled by the misfit.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from scipy.linalg import eigh
from scipy.optimize import least_squares

from pelvislab.model.identification import (
    FitResult,
    FrfProblem,
    SystemMatrices,
    covariance_report,
    one_blas_thread,
)

#: A measured mode and its model partner count as the same mode at MAC >= 0.9: the usual
#: threshold of consistent correlation; the thesis calls its EMA's modes "well identified"
#: at MAC > 0.95 (ch. 7.2) and read 0.91-0.97 as "no change" (ch. 11.3). With shapes at a few
#: points MAC discriminates little (two random unit vectors at 5 points: 0.2 on average),
#: so a lower threshold would pass wrong partners.
PAIR_MIN_MAC = 0.9

#: Frequency uncertainty of modes given without one (``ModalData.frequency_tol_hz`` None):
#: 1 % either way, above the thesis' EMA frequency errors (at most 0.75 %, ch. 7.2).
DEFAULT_FREQUENCY_TOL = 0.01


#: Most times the picked shapes' standard uncertainty is estimated, each at the latest
#: refit (:func:`identify_modal`), before it is taken as settled.
PICKING_PASSES = 4

#: Standard uncertainty of each entry of a unit-normalised picked shape below which the
#: picking-bias estimate is not trusted (FRF noise, the real direction of a complex column):
#: 0.5 % of the shape's norm, the measurement chain's gain tolerance.
SHAPE_STD_FLOOR = 0.005

#: The model's own picked peak (:func:`_picking_bias`) is sought within x/÷ BIAS_WINDOW of
#: its undamped frequency, on BIAS_GRID_LINES lines (0.2 % of the frequency apart at most).
BIAS_WINDOW = 1.25
BIAS_GRID_LINES = 225

#: Largest factor :func:`_damping_like_the_data` scales the model's damping by, to make its
#: peak as flat as the data's.
DAMPING_SCALE_MAX = 30.0


@dataclass(frozen=True)
class PeakPicking:
    """Where :func:`modes_from_frf` read the modes: the lines it picked on
    (``frequency_hz``, (n_lines,) Hz), the FRF entries it used on each line (``measured``,
    (n_lines, n_out, n_in) bool) and each mode's peak line (``peak_line``, (n_m,) index
    into ``frequency_hz``). :func:`identify_modal` repeats the picking on the model's FRFs
    there to estimate how far picking moves a shape from the undamped mode's."""

    frequency_hz: np.ndarray
    measured: np.ndarray
    peak_line: np.ndarray
    shape_noise_std: np.ndarray | None = None
    """(n_m,) standard uncertainty of each entry of each picked unit shape from the FRFs'
    noise (their H_std at the peak line over the column's norm), or None."""
    mean_log_magnitude: np.ndarray | None = None
    """(n_lines,) the mean log|H| (natural log of m/N) the peaks were picked on, or None."""
    mean_log_entries: np.ndarray | None = None
    """(n_out, n_in) bool: the FRFs that mean is over."""
    min_prominence: float = 0.1
    """The smallest prominence (natural-log units) a peak was picked with."""


@dataclass(frozen=True)
class ModalData:
    """Measured modes: frequency_hz (n_m,), shapes (n_points, n_m) real, any scaling.

    ``frequency_tol_hz``: how far each true frequency may lie from ``frequency_hz``, (n_m,)
    either way or (n_m, 2) below and above (peak picking: up to the neighbouring lines);
    None: :data:`DEFAULT_FREQUENCY_TOL` of the frequency. ``picking``: where peak picking
    read them (:class:`PeakPicking`), None for modes given otherwise.
    """

    frequency_hz: np.ndarray
    shapes: np.ndarray
    frequency_tol_hz: np.ndarray | None = None
    picking: PeakPicking | None = None

    def __post_init__(self) -> None:
        f = np.asarray(self.frequency_hz, float).reshape(-1)
        s = np.asarray(self.shapes, float)
        if s.ndim != 2 or s.shape[1] != f.size:
            raise ValueError(f"shapes must be (n_points, {f.size}); got {s.shape}")
        object.__setattr__(self, "frequency_hz", f)
        object.__setattr__(self, "shapes", s)
        if self.frequency_tol_hz is not None:
            tol = np.asarray(self.frequency_tol_hz, float)
            tol = np.stack([tol, tol], axis=1) if tol.ndim == 1 else tol
            if tol.shape != (f.size, 2) or not np.all(tol >= 0):
                raise ValueError(f"frequency_tol_hz must be (n_m,) or (n_m, 2) and >= 0 for "
                                 f"{f.size} modes; got {tol.shape}")
            object.__setattr__(self, "frequency_tol_hz", tol)
        if self.picking is not None and np.size(self.picking.peak_line) != f.size:
            raise ValueError(f"picking names {np.size(self.picking.peak_line)} peak line(s) "
                             f"for {f.size} modes: select modes with their peak lines")

    def frequency_range_hz(self) -> np.ndarray:
        """(n_m, 2): the interval each measured mode's true frequency lies in."""
        tol = (DEFAULT_FREQUENCY_TOL * np.stack([self.frequency_hz] * 2, axis=1)
               if self.frequency_tol_hz is None else self.frequency_tol_hz)
        return np.stack([self.frequency_hz - tol[:, 0], self.frequency_hz + tol[:, 1]], axis=1)


def undamped_modes(M: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eigenvalues w^2 (rad^2/s^2, ascending) and mass-normalised modes (z^T M z = 1)."""
    lam, Z = eigh(K, M)
    return lam, Z


def frequency_dependent_omega2(lam: np.ndarray, f_k: float, omega_max_rad_s: float
                               ) -> tuple[np.ndarray, np.ndarray]:
    """Undamped ω² (rad²/s²) of modes whose eigenvalues of (K, M) are ``lam`` when the
    stiffness is K(ω) = K (1 + f_k ω / (4 ω_max)) (eq. 7.1-7.3, app. D), and dω²/dλ.

    K(ω) scales K, so the shapes are those of (K, M) and each mode's ω solves
    ω² = λ (1 + a ω), a = f_k / (4 ω_max): ω = (aλ + √((aλ)² + 4λ)) / 2 (the fixed point
    app. D iterates to, without damping); dω²/dλ = 2ω (1 + aω) / (2ω − aλ). ``f_k`` 0: λ
    and 1."""
    lam = np.clip(np.asarray(lam, float), 0.0, None)
    if f_k == 0.0:
        return lam, np.ones_like(lam)
    a = f_k / (4.0 * omega_max_rad_s)
    w = 0.5 * (a * lam + np.sqrt((a * lam) ** 2 + 4.0 * lam))
    with np.errstate(invalid="ignore", divide="ignore"):
        slope = np.where(w > 0, 2 * w * (1 + a * w) / (2 * w - a * lam), 1.0)
    return w**2, slope


def _frf(problem: FrfProblem, mats: SystemMatrices, frequency_hz: np.ndarray,
         freq_dep: tuple[float, float]) -> np.ndarray:
    """The model's FRFs (n_f, n_out, n_in) at ``frequency_hz`` with the eq. 7.1-7.3
    factors ``freq_dep`` = (f_k, f_c)."""
    from pelvislab.model.identification import frf_with_jacobian

    H, _ = frf_with_jacobian(mats, problem.outputs, problem.inputs, frequency_hz,
                             f_k=freq_dep[0], f_c=freq_dep[1],
                             omega_max_rad_s=problem.omega_max_rad_s, jacobian=False)
    return H


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
    f_k: float = 0.0,
    f_c: float = 0.0,
) -> FitResult:
    """Gauss-Newton modal updating of the ``free`` parameters (default: the stiffnesses).

    Measured shapes live at the rows of ``problem.outputs``. Model modes below 1e-6 x the
    largest eigenvalue (rigid-body modes) are never paired. Mode pairing by maximum MAC
    is redone at every residual evaluation (modes may swap order while updating).
    ``frequency_weight``, ``shape_weight``: the residual weights of modes given without
    ``data.picking``; peak-picked modes are weighted by their standard uncertainty, and
    these weigh only the first fit, from which that uncertainty is first estimated.
    ``f_k``, ``f_c``: the model's eq. 7.1-7.3 factors, held: the model's frequencies are
    those of K(ω) (:func:`frequency_dependent_omega2`; they were left out, so a model file
    with f_k was fitted as if it had none), its FRFs for the picking's biases include both.
    """
    t0 = time.perf_counter()
    freq_dep = (float(f_k), float(f_c))

    def omega2(lam: np.ndarray) -> np.ndarray:
        return frequency_dependent_omega2(lam, freq_dep[0], problem.omega_max_rad_s)[0]

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
    # residual weights, 1 / standard uncertainty: set from the picking once it is known
    weight_f = np.full(n_modes, float(frequency_weight))
    weight_s = np.full(n_modes, float(shape_weight))

    def paired(x: np.ndarray) -> tuple[np.ndarray, object, np.ndarray, np.ndarray, np.ndarray]:
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
        fratio = np.abs(np.log(omega2(lam[elastic])[:, None] / w2_meas[None, :]))
        score = m - 0.01 * fratio
        pairs = elastic[np.argmax(score, axis=0)]
        return values, mats, lam, Z, pairs

    def model(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        values, mats, lam, Z, pairs = paired(x)
        dlam, dz = eigen_sensitivities(mats.M, mats.K, mats.dM[idx], mats.dK[idx], lam, Z,
                                       list(pairs))
        evals[0] += 1
        w2, slope = frequency_dependent_omega2(lam[pairs], freq_dep[0],
                                               problem.omega_max_rad_s)
        r_f = weight_f * (w2 / w2_meas - 1.0)
        J_f = weight_f[:, None] * slope[:, None] * dlam / w2_meas[:, None]
        r_s, J_s = [], []
        for i, s in enumerate(pairs):
            u = O @ Z[:, s]
            nu = np.linalg.norm(u)
            n_hat = u / nu
            sign = np.sign(n_hat @ phi_meas[:, i]) or 1.0
            r_s.append(weight_s[i] * (sign * n_hat - phi_meas[:, i]))
            du = dz[i] @ O.T  # (n_p, n_points)
            dn = (du - np.outer(du @ n_hat, n_hat)) / nu
            J_s.append(weight_s[i] * sign * dn.T)
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

    def fit(start_x: np.ndarray):  # noqa: ANN202 - scipy's OptimizeResult
        cache.clear()
        return least_squares(lambda x: get(x)[0], start_x, jac=lambda x: get(x)[1],
                             bounds=(lo, hi), method="trf", ftol=1e-14, xtol=1e-14,
                             gtol=1e-14, max_nfev=max_nfev)

    sol = fit(x0)
    absolute = False
    shape_std = None
    if data.picking is not None:
        # Peak-picked modes are biased where modes are damped or close: a shape read off a
        # peak carries its neighbours' response, and the fit matched such shapes exactly
        # with std scaled by a near-zero misfit (a damped chain: converged 20-30 % off at
        # |z| up to 100; session 42). Each datum gets a standard uncertainty instead, the
        # fit is redone with those weights and its std are absolute, scaled up by the
        # misfit when it exceeds them.
        # The frequency's tolerance is a 2-sigma interval, as `matched` holds the model's
        # frequency within it (tolerance/sqrt(3), a uniform's std, let the weighted fit
        # drift to its edge and out of the pair: review).
        # The shape's is the difference picking makes on the model's own FRFs at the fit
        # (its damping) between the read shape and the undamped mode's, with the FRFs'
        # noise, at least SHAPE_STD_FLOOR. The fit absorbs part of the bias it should
        # measure (a first fit's 0.041 for 0.19 at the truth: review): estimated again at
        # each refit, at most PICKING_PASSES times, until it settles within 10 %.
        # The frequency's picking bias is estimated the same way (the peak the model's own
        # FRFs show against its undamped frequency) and combined with the tolerance: a
        # damped chain's picked peak 2 Hz below the undamped 31 Hz was held to +-0.5 Hz,
        # k2 17 % off at z -5 (session 43).
        grid_std_hz = np.diff(data.frequency_range_hz(), axis=1)[:, 0] / 4
        frequency_std_hz = grid_std_hz
        for _ in range(PICKING_PASSES):
            estimate, bias_hz = _picking_bias(problem, paired(sol.x), data.picking, O,
                                              freq_dep)
            estimate_f = np.hypot(grid_std_hz, bias_hz)
            if shape_std is not None:
                # never below an earlier estimate: a fit that absorbed the bias shows less
                estimate = np.maximum(estimate, shape_std)
                estimate_f = np.maximum(estimate_f, frequency_std_hz)
                if (np.all(estimate <= 1.1 * shape_std)
                        and np.all(estimate_f <= 1.1 * frequency_std_hz)):
                    break  # settled: the weights of the last fit stand
            shape_std, frequency_std_hz = estimate, estimate_f
            weight_s[:] = 1.0 / shape_std
            # sigma of the w^2 ratio: twice sigma_f / f
            weight_f[:] = data.frequency_hz / (2 * frequency_std_hz)
            sol = fit(sol.x)
        absolute = True
    r, J = get(sol.x)
    values = base.copy()
    values[idx] = np.exp(sol.x)
    # independent equations, not residual entries: a unit shape at n outputs has n - 1
    dof = max(n_equations - len(free), 1)
    misfit_scale = max(1.0, float(r @ r) / dof) if absolute else 1.0
    std, corr, sv, weak = covariance_report(J / np.sqrt(misfit_scale), r, list(free),
                                            values[idx], absolute_sigma=absolute)
    rms = float(np.sqrt(np.mean(r**2)))
    on_bound = np.isclose(sol.x, lo, atol=1e-6) | np.isclose(sol.x, hi, atol=1e-6)
    bound_names = [n for n, b in zip(free, on_bound, strict=True) if b]
    # Trust (an audit: from appendix E itself, the truth of a simulated demo session, the
    # fit went to k ~ 0.5e6 for 1e6 and reported converged, its measured modes paired with
    # model modes 2-3x their frequency or at MAC 0.47, std 4-40x the values):
    # each measured mode needs a model mode of its own, of the same shape and within the
    # frequency's uncertainty, and the modes must determine the parameters.
    picked = shape_std is not None
    ranges = data.frequency_range_hz()
    if picked:
        # the 2-sigma interval of the weights the fit used: the grid's interval widened by
        # twice the picking bias (in quadrature, on each side)
        sides = np.abs(ranges - data.frequency_hz[:, None])
        widen = 2 * np.sqrt(np.maximum(frequency_std_hz**2 - grid_std_hz**2, 0.0))
        sides = np.hypot(sides, widen[:, None])
        ranges = np.stack([data.frequency_hz - sides[:, 0], data.frequency_hz + sides[:, 1]],
                          axis=1)
    pairs_report = _mode_pairs(paired(sol.x), O, data, ranges, omega2)
    for i, pair in enumerate(pairs_report):
        # the uncertainties a picked mode was weighed with (null: given without picking)
        pair["shape_std"] = float(shape_std[i]) if picked else None
        pair["frequency_std_hz"] = float(frequency_std_hz[i]) if picked else None
    unmatched = [p for p in pairs_report if not p["matched"]]
    # the model's peaks at the fit that no measured mode stands for: a mode the picking or
    # the selection left out, or model error; said, not judged (a subject damped more than
    # the model may smear a peak the model shows)
    extra_peaks = (_model_peaks_without_data(problem, paired(sol.x)[1], data.picking, ranges,
                                             freq_dep) if picked else [])
    with np.errstate(invalid="ignore"):
        undetermined = [n for n, v, s in zip(free, values[idx], std, strict=True)
                        if not np.isfinite(s) or s > abs(v)]
    unresolved = sum(1 for w in weak if not w["resolved"])
    converged = (bool(sol.status > 0) and not bound_names and not unmatched
                 and not undetermined and not unresolved)
    message = str(sol.message)
    if bound_names:
        message += (f"; on the bound of its range (start x/÷ {bounds_factor:g}): "
                    + ", ".join(bound_names))
    if unmatched:
        message += (f"; {len(unmatched)} of {len(pairs_report)} measured mode(s) without a "
                    f"model mode of their own at MAC >= {PAIR_MIN_MAC:g} within their "
                    "frequency's uncertainty: " + ", ".join(_unmatched_text(p)
                                                            for p in unmatched)
                    + " (peaks that are not model modes, shapes read off resonance, or "
                    "model error)")
    if extra_peaks:
        message += ("; the model at the fit shows peak(s) at "
                    + ", ".join(f"{f:.4g}" for f in extra_peaks)
                    + " Hz that no measured mode stands for (a mode the picking or the "
                    "selection left out, or model error)")
    if undetermined or unresolved:
        message += ("; the modes do not determine the parameters: "
                    + ("std above the value or null for "
                       + ("every parameter" if len(undetermined) == len(free)
                          else ", ".join(undetermined)) if undetermined else "")
                    + ("; " if undetermined and unresolved else "")
                    + (f"{unresolved} parameter combination(s) unresolved (std along "
                       "them beyond an e-fold)" if unresolved else ""))
    if progress:
        progress(f"modal updating: rms residual {rms:.3g} after {evals[0]} evaluations")
    return FitResult(
        names=list(free), values=values[idx], std=std, correlation=corr,
        cost=0.5 * float(r @ r), converged=converged,
        evaluations=evals[0], wall_time_s=time.perf_counter() - t0, residual_kind="modal",
        singular_values=sv, weak_directions=weak, message=message,
        extra={"rms_residual": rms, "on_bound": bound_names, "mode_pairs": pairs_report,
               "model_peaks_without_data_hz": extra_peaks,
               "pair_min_mac": PAIR_MIN_MAC, "undetermined": undetermined},
    )


def _mode_pairs(state: tuple, O: np.ndarray, data: ModalData, ranges: np.ndarray,
                omega2: Callable[[np.ndarray], np.ndarray] = lambda lam: lam,
                ) -> list[dict[str, object]]:
    """Each measured mode's model partner at the fit: frequencies, MAC, the interval the
    measured frequency allows (``ranges``, (n_m, 2) Hz), and whether the pair holds
    (MAC >= PAIR_MIN_MAC, the model's frequency in the interval, no other measured mode
    paired with the same model mode)."""
    _, _, lam, Z, pairs = state
    f_model = np.sqrt(np.clip(omega2(lam[pairs]), 0.0, None)) / (2 * np.pi)
    macs = np.array([mac(O @ Z[:, [s]], data.shapes[:, [i]])[0, 0]
                     for i, s in enumerate(pairs)])
    shared = np.array([np.count_nonzero(pairs == s) > 1 for s in pairs])
    report = []
    for i in range(pairs.size):
        within = bool(ranges[i, 0] <= f_model[i] <= ranges[i, 1])
        report.append({
            "measured_hz": float(data.frequency_hz[i]), "model_hz": float(f_model[i]),
            "mac": float(macs[i]),
            "frequency_range_hz": [float(ranges[i, 0]), float(ranges[i, 1])],
            "shared": bool(shared[i]),
            "matched": bool(macs[i] >= PAIR_MIN_MAC and within and not shared[i])})
    return report


def _unmatched_text(p: dict) -> str:
    lo, hi = p["frequency_range_hz"]
    f, fm = p["measured_hz"], p["model_hz"]
    # to the grid's precision: one decimal more than the uncertainty's leading digit
    step = min(f - lo, hi - f)
    nd = max(0, 1 - int(np.floor(np.log10(step)))) if step > 0 else 3
    why = []
    if fm < lo:
        why.append(f"more than {f - lo:.{nd}f} Hz below")
    elif fm > hi:
        why.append(f"more than {hi - f:.{nd}f} Hz above")
    if p["mac"] < PAIR_MIN_MAC:
        why.append(f"MAC {p['mac']:.2f}")
    if p["shared"]:
        why.append("shared with another measured mode")
    return f"{f:.{nd}f} Hz (model {fm:.{nd}f} Hz, {', '.join(why)})"


def _column_at_peak(Hk: np.ndarray, measured: np.ndarray, iterations: int = 50
                    ) -> np.ndarray:
    """The mode's column at a peak line, (n_out,) complex, from the FRF matrix there
    ``Hk`` (n_out, n_in) and which of its entries were ``measured``.

    Near a resonance H ≈ φ ψᵀ (one mode's residue: shape at the outputs times shape at the
    inputs). The input with the largest response supplies φ when it measured every output
    that any input measured; otherwise φ is the rank-one least-squares fit of the measured
    entries (alternating least squares from that column), so an output one input missed
    takes its value from the others. Reading the missed entries as 0 spoiled the shapes of
    layouts where each input misses an output (demo, face_down: the 232 Hz mode at MAC
    0.775 against the model's own shape, 0.9999 over the measured points; review, session
    41). Outputs measured by no input stay 0."""
    col = int(np.argmax(np.sum(np.abs(Hk), axis=0)))
    phi = Hk[:, col].copy()
    seen = measured.any(axis=1)
    if np.all(measured[seen, col]):
        return phi
    w = measured.astype(float)
    for _ in range(iterations):
        psi = (np.conj(phi)[:, None] * Hk * w).sum(axis=0) / np.maximum(
            (np.abs(phi)[:, None] ** 2 * w).sum(axis=0), np.finfo(float).tiny)
        phi = (Hk * np.conj(psi)[None, :] * w).sum(axis=1) / np.maximum(
            (np.abs(psi)[None, :] ** 2 * w).sum(axis=1), np.finfo(float).tiny)
    return np.where(seen, phi, 0.0)


PICKING_MIN_LINE_SHARE = 0.9
"""An FRF holding fewer than this share of the lines the fullest FRF holds is left out of
peak picking (:func:`picking_frfs`) rather than taking its missing lines from every FRF."""


def picking_frfs(H: np.ndarray) -> np.ndarray:
    """(n_out, n_in) bool: the FRFs :func:`modes_from_frf` picks peaks from: measured (a
    finite, non-zero value somewhere) on at least :data:`PICKING_MIN_LINE_SHARE` of the
    lines the fullest FRF holds. One FRF measured on part of the band, or on alternate
    lines, took the other lines from every FRF: a chain's three modes became one (review,
    session 41)."""
    held = (np.abs(np.where(np.isfinite(H), H, 0.0)) > 0).sum(axis=0)
    return (held > 0) & (held >= PICKING_MIN_LINE_SHARE * held.max())


def picking_lines(H: np.ndarray) -> np.ndarray:
    """(n_f,) bool: the lines :func:`modes_from_frf` picks peaks on, those on which every
    FRF of :func:`picking_frfs` has a value and every measured output has one from some
    FRF: a shape has no value to take at an output nothing measured on that line (an FRF
    left out of the picking may be the only one that measures its output: its missing
    lines then read 0 in the shapes, MAC 0.63-0.78 for three demo-layout modes; review,
    session 41)."""
    held = np.abs(np.where(np.isfinite(H), H, 0.0)) > 0
    kept = picking_frfs(H)
    outputs = held.any(axis=(0, 2))
    every_output = np.all(held.any(axis=2)[:, outputs], axis=1)
    return np.all(held[:, kept], axis=1) & every_output & kept.any()


def modes_from_frf(
    frequency_hz: np.ndarray, H: np.ndarray, *, max_modes: int = 12, min_prominence: float = 0.1,
    H_std: np.ndarray | None = None,
) -> ModalData:
    """Peak picking (ch. 4.5): peaks of the mean log|H|, shapes = the FRF column there.

    A simple single-degree-of-freedom estimator for lightly damped, well separated modes:
    the column (input) with the largest response at each peak supplies the shape. Unmeasured
    FRFs (NaN throughout) and FRFs holding under 90 % of the lines are left out of the
    picking (:func:`picking_frfs`), and lines on which a kept FRF has no value are left out
    (:func:`picking_lines`; one failed line refused the whole file before);
    ``min_prominence`` is in natural-log units. Good enough to seed modal
    updating; the EMA module does better. Each frequency is known to the grid only: the
    peak line is higher than both its neighbours, so a single resonance lies between them
    (``frequency_tol_hz``: the spacing to each neighbour, a left-out line widening it, and
    at least :data:`DEFAULT_FREQUENCY_TOL` of the frequency). ``H_std`` (as ``H``, m/N):
    the FRFs' noise, which gives each picked shape's noise (``PeakPicking.shape_noise_std``:
    rms H_std of the line's measured entries over the norm of the mode's column there).
    """
    from scipy.signal import find_peaks

    use = picking_lines(H)
    if use.sum() < 3:
        raise ValueError(f"{int(use.sum())} frequency line(s) on which every measured FRF "
                         "has a value: too few to pick peaks from")
    f = np.asarray(frequency_hz, float)[use]
    Hm = np.where(np.isfinite(H), H, 0.0)[use]
    mag = np.abs(Hm).reshape(Hm.shape[0], -1)
    entries = np.all(mag > 0, axis=0)
    mag = mag[:, entries]
    # mean log-magnitude over the FRFs: every FRF counts, peaks of small ones too
    total = np.mean(np.log(mag), axis=1)
    peaks, props = find_peaks(total, prominence=min_prominence)
    if peaks.size == 0:
        raise ValueError("no resonance peaks found in the FRFs")
    order = np.argsort(-props["prominences"])[:max_modes]
    peaks = np.sort(peaks[order])
    measured = np.isfinite(H[use]) & (np.abs(Hm) > 0)
    shapes = [_picked_shape(Hm[k], measured[k]) for k in peaks]
    noise = None
    if H_std is not None:
        S = np.asarray(H_std, float)[use]
        noise = np.empty(peaks.size)
        for i, k in enumerate(peaks):
            ok = measured[k] & np.isfinite(S[k]) & (S[k] > 0)
            sigma = float(np.sqrt(np.mean(S[k][ok] ** 2))) if ok.any() else 0.0
            noise[i] = sigma / max(float(np.linalg.norm(_column_at_peak(Hm[k], measured[k]))),
                                   np.finfo(float).tiny)
    # find_peaks never returns the first or last line: both neighbours exist. At least
    # DEFAULT_FREQUENCY_TOL of the frequency: the peak of the mean log|H| is not the
    # undamped frequency the model is held against (damping, neighbouring modes), and a
    # tolerance of the line spacing alone made finer lines refuse better fits (a damped
    # chain: 0.35 % off refused on 0.1 Hz lines, 0.45 % accepted on 0.5 Hz; review,
    # session 41)
    spacing = np.stack([f[peaks] - f[peaks - 1], f[peaks + 1] - f[peaks]], axis=1)
    tol = np.maximum(spacing, DEFAULT_FREQUENCY_TOL * f[peaks][:, None])
    return ModalData(f[peaks], np.array(shapes).T, frequency_tol_hz=tol,
                     picking=PeakPicking(f, measured, peaks, noise, total,
                                         entries.reshape(Hm.shape[1:]),
                                         float(min_prominence)))


def _picked_shape(Hk: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """The real shape peak picking reads at one line: the mode's column there
    (:func:`_column_at_peak`) and its dominant real direction, Im H on the peak, Re H when
    the grid misses a lightly damped peak (the nearest mode dominates either way); unit
    norm, (n_out,)."""
    h = _column_at_peak(Hk, measured)
    u, _, _ = np.linalg.svd(np.stack([h.real, h.imag], axis=1), full_matrices=False)
    return u[:, 0]


def _picking_bias(problem: FrfProblem, state: tuple, picking: PeakPicking, O: np.ndarray,
                  freq_dep: tuple[float, float] = (0.0, 0.0)
                  ) -> tuple[np.ndarray, np.ndarray]:
    """What peak picking makes of the model's own FRFs at ``state`` (the fit's values, the
    model's damping), against the paired undamped modes:

    - (n_m,) standard uncertainty of each entry of each picked unit shape: the difference
      between the shape read at the data's peak line (same lines and entries as the data)
      and the undamped mode's, rms over the outputs, combined with the FRFs' noise
      (``picking.shape_noise_std``) and at least :data:`SHAPE_STD_FLOOR`;
    - (n_m,) frequency bias, Hz: where the model's mean log|H| over the same entries peaks
      (the local maximum nearest the undamped frequency, on a grid of
      :data:`BIAS_GRID_LINES` lines within x/÷ :data:`BIAS_WINDOW` of it and short of
      halfway to the neighbouring modes, refined by a parabola) minus the undamped
      frequency; 0 when the model shows no peak there in the band.

    A model estimate of the picking's bias (a damped mode's peak lies below its undamped
    frequency, neighbouring modes move it either way): right to the extent the model's
    damping and neighbouring modes are the subject's."""

    _, mats0, lam, Z, pairs = state
    lines = picking.frequency_hz[picking.peak_line]
    w2 = frequency_dependent_omega2(lam, freq_dep[0], problem.omega_max_rad_s)[0]
    f_undamped = np.sqrt(w2[pairs]) / (2 * np.pi)
    f_all = np.sqrt(w2[lam > 1e-6 * lam.max()]) / (2 * np.pi)
    band = picking.frequency_hz[[0, -1]]
    std = np.empty(pairs.size)
    bias_hz = np.empty(pairs.size)
    for i, (s, k) in enumerate(zip(pairs, picking.peak_line, strict=True)):
        # the model's damping, or more where the data's peak is flatter: a model damped
        # less than the subject showed no bias to estimate (chains damped 30x the model:
        # converged fits beyond |z| 3, 39 % -> 0 %; session 43)
        mats = _damping_like_the_data(problem, mats0, picking, k, freq_dep)
        H = _frf(problem, mats, lines[i:i + 1], freq_dep)
        # the entries the data lack read 0 there when the column is chosen: here too
        read = _picked_shape(np.where(picking.measured[k], H[0], 0.0), picking.measured[k])
        mode = O @ Z[:, s]
        mode = mode / np.linalg.norm(mode)
        read = read * (np.sign(read @ mode) or 1.0)
        std[i] = np.sqrt(np.mean((read - mode) ** 2))
        # the mode's own stretch: up to halfway (geometrically) to its neighbours, whose
        # peaks are not its bias (the pelvis' 313 Hz mode took a 267 Hz peak for its own)
        others = f_all[np.abs(f_all - f_undamped[i]) > 1e-9 * f_undamped[i]]
        below, above = others[others < f_undamped[i]], others[others > f_undamped[i]]
        lo = max(band[0], f_undamped[i] / BIAS_WINDOW,
                 np.sqrt(below.max() * f_undamped[i]) if below.size else 0.0)
        hi = min(band[1], f_undamped[i] * BIAS_WINDOW,
                 np.sqrt(above.min() * f_undamped[i]) if above.size else np.inf)
        fine = np.linspace(lo, hi, BIAS_GRID_LINES)
        peak = _model_peak_hz(problem, mats, fine, picking.measured[k], f_undamped[i],
                              freq_dep) if fine[-1] > fine[0] else None
        # no peak of the model's there (heavily damped, or beyond the band): no estimate,
        # the grid's tolerance stands (the data's own miss made a mismatched datum weightless)
        bias_hz[i] = 0.0 if peak is None else peak - f_undamped[i]
    if picking.shape_noise_std is not None:
        std = np.hypot(std, picking.shape_noise_std)
    return np.maximum(std, SHAPE_STD_FLOOR), bias_hz


def _model_peaks_without_data(problem: FrfProblem, mats: SystemMatrices,
                              picking: PeakPicking, ranges: np.ndarray,
                              freq_dep: tuple[float, float] = (0.0, 0.0)) -> list[float]:
    """Frequencies (Hz) of the peaks the model's own FRFs (``mats``: the fit, its damping)
    show where the data's were picked (same lines, same FRFs, the same prominence) that lie
    outside every measured mode's interval (``ranges``, (n_m, 2) Hz) by more than a line:
    resonances the model predicts in the band and the measured modes do not include."""
    from scipy.signal import find_peaks

    if picking.mean_log_entries is None:
        return []
    f = picking.frequency_hz
    H = _frf(problem, mats, f, freq_dep)
    mag = np.abs(H[:, picking.mean_log_entries])
    mag = mag[:, np.all(mag > 0, axis=0)]
    if mag.shape[1] == 0:
        return []
    peaks, _ = find_peaks(np.mean(np.log(mag), axis=1), prominence=picking.min_prominence)
    out = []
    for k in peaks:
        line = max(f[k] - f[k - 1], f[k + 1] - f[k])
        if not np.any((ranges[:, 0] - line <= f[k]) & (f[k] <= ranges[:, 1] + line)):
            out.append(float(f[k]))
    return out


def _model_peak_hz(problem: FrfProblem, mats: SystemMatrices, frequency_hz: np.ndarray,
                   entries: np.ndarray, near_hz: float,
                   freq_dep: tuple[float, float] = (0.0, 0.0)) -> float | None:
    """The local maximum of the model's mean log|H| over ``entries`` ((n_out, n_in) bool)
    on the lines ``frequency_hz`` nearest ``near_hz``, refined by a parabola through it and
    its neighbours; None when the lines' interior has no local maximum."""
    H = _frf(problem, mats, frequency_hz, freq_dep)
    mag = np.abs(H[:, entries])
    mag = mag[:, np.all(mag > 0, axis=0)]
    if mag.shape[1] == 0:
        return None
    total = np.mean(np.log(mag), axis=1)
    inner = np.flatnonzero((total[1:-1] > total[:-2]) & (total[1:-1] >= total[2:])) + 1
    if inner.size == 0:
        return None
    j = inner[np.argmin(np.abs(frequency_hz[inner] - near_hz))]
    y0, y1, y2 = total[j - 1:j + 2]
    curvature = y0 - 2 * y1 + y2
    offset = 0.5 * (y0 - y2) / curvature if curvature < 0 else 0.0
    return float(frequency_hz[j] + offset * (frequency_hz[j + 1] - frequency_hz[j]))


def _curvature(frequency_hz: np.ndarray, y: np.ndarray) -> float:
    """Second divided difference of ``y`` over three lines (units of y per Hz^2)."""
    f0, f1, f2 = frequency_hz
    y0, y1, y2 = y
    return float(2 * ((y2 - y1) / (f2 - f1) - (y1 - y0) / (f1 - f0)) / (f2 - f0))


def _damping_like_the_data(problem: FrfProblem, mats: SystemMatrices, picking: PeakPicking,
                           k: int, freq_dep: tuple[float, float] = (0.0, 0.0)
                           ) -> SystemMatrices:
    """``mats`` with the damping matrix C scaled up (at most :data:`DAMPING_SCALE_MAX`)
    until the model's mean log|H| is as flat as the data's across the peak line ``k`` and
    its neighbours (second divided difference over the same FRFs); ``mats`` itself where
    the model's peak is already as flat, or the picking holds no mean log|H|.

    Only ever more damping: the picking's bias grows with damping, and a bias estimated on
    a model damped less than the subject is too small (data damped 10x the model's: 29 % of
    converged 3-mass chains beyond |z| 3), while one estimated on a model damped more only
    widens the std."""
    if picking.mean_log_magnitude is None or picking.mean_log_entries is None:
        return mats
    lines = picking.frequency_hz[k - 1:k + 2]
    data = _curvature(lines, picking.mean_log_magnitude[k - 1:k + 2])

    def flatness(log_scale: float) -> float:
        scaled = replace(mats, C=mats.C * np.exp(log_scale))
        H = _frf(problem, scaled, lines, freq_dep)
        mag = np.abs(H[:, picking.mean_log_entries])
        return _curvature(lines, np.mean(np.log(mag), axis=1))

    top = np.log(DAMPING_SCALE_MAX)
    model = flatness(0.0)
    if not (np.isfinite(data) and data < 0 and np.isfinite(model)) or model >= data:
        return mats
    if flatness(top) < data:
        return replace(mats, C=mats.C * DAMPING_SCALE_MAX)
    lo, hi = 0.0, top
    for _ in range(20):  # bisection on the log of the scale: 2^-20 of log 30
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if flatness(mid) < data else (lo, mid)
    return replace(mats, C=mats.C * np.exp(hi))
