"""MAC-based model updating (thesis ch. 14.2, eq. 14.1) with attachment coordinates and damping.

The thesis minimised ``J(p) = N_modes - sum MAC(x_corr, x_model,corr(p))`` (eq. 14.1) with
``fminsearch`` over the spring attachment coordinates (± 1 cm) and, later, the joint damping.
Here the same cost is minimised as a least-squares problem (``scipy.optimize.least_squares``,
trust region, bounds) with:

* shape residual ``a - e^{iφ} b`` between unit-normalised, phase-aligned correlation shapes
  (fig. 14.1 filtering, :func:`~pelvislab.model.correlation.correlation_shapes`, applied as the
  same linear map to measured and model shapes). Its squared norm is ``2(1 - sqrt MAC)``,
  i.e. ``1 - MAC`` to first order near a match, so the sum over modes is eq. 14.1; the exact
  eq. 14.1 value is reported (``mac_cost``);
* optional relative natural-frequency errors ``f_model/f_meas - 1`` (the thesis paired mode 1
  "on the shape and not on the frequency": give it weight 0) and damping-ratio errors
  ``(ζ_model - ζ_meas)/ζ_meas`` (complex MAC alone hardly sees the appendix-E damping: the
  thesis found damping changes "with no influence" on eq. 14.1);
* mode pairing by MAC (Hungarian, :func:`~pelvislab.model.modal.pair_modes`) at every
  evaluation; measured modes with no model partner above ``min_mac`` at the start are left out
  of the cost and reported;
* derivatives: exact complex-eigenvalue and eigenvector sensitivities of the quadratic problem
  ``(λ²M + λC + K) z = 0`` (Nelson's method, one 18x18 solve per mode) chained through the
  parameter space's exact ``dM, dK, dC`` (attachment coordinates included); or finite
  differences of the modal solution (``jacobian="fd"``);
* positive parameters in log scale, coordinates linear (the parameter space's scaling),
  multi-start from perturbed starts, standard errors from the Jacobian
  (:func:`~pelvislab.model.identification.covariance_report`).

Pure numerics, no I/O.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from pelvislab.model.correlation import correlation_shapes, mac_cost
from pelvislab.model.frf import Points, rows_for
from pelvislab.model.identification import covariance_report, interval_95, one_blas_thread
from pelvislab.model.modal import complex_modes, mac, pair_modes
from pelvislab.model.parameters import ParameterSpace, parameter_space
from pelvislab.model.pelvis import PelvisModel
from pelvislab.model.rigid_body import filter_global


@dataclass(frozen=True)
class MeasuredModes:
    """Experimental modes at output channels.

    ``frequency_hz`` (n_m,) natural frequencies; ``shapes`` (n_ch, n_m) complex, any scaling;
    ``bones`` (n_ch,) bone of each channel (``""``: on no bone, ignored); ``position_m``
    (n_ch, 3) and ``direction`` (n_ch, 3) in the model frame (design 4.1);
    ``damping_ratio`` (n_m,) optional (enables the damping residual).
    """

    frequency_hz: np.ndarray
    shapes: np.ndarray
    bones: tuple[str, ...]
    position_m: np.ndarray
    direction: np.ndarray
    damping_ratio: np.ndarray | None = None

    def __post_init__(self) -> None:
        f = np.asarray(self.frequency_hz, float).reshape(-1)
        s = np.asarray(self.shapes, complex)
        s = s[:, None] if s.ndim == 1 else s
        p = np.asarray(self.position_m, float).reshape(-1, 3)
        d = np.asarray(self.direction, float).reshape(-1, 3)
        bones = tuple(str(b) for b in self.bones)
        if s.shape[1] != f.size:
            raise ValueError(f"shapes must be (n_channels, {f.size}); got {s.shape}")
        if not (len(bones) == p.shape[0] == d.shape[0] == s.shape[0]):
            raise ValueError("bones, position_m, direction and shapes disagree in channel count")
        if np.any(f <= 0):
            raise ValueError("measured frequencies must be positive (Hz)")
        object.__setattr__(self, "frequency_hz", f)
        object.__setattr__(self, "shapes", s)
        object.__setattr__(self, "bones", bones)
        object.__setattr__(self, "position_m", p)
        object.__setattr__(self, "direction", d / np.linalg.norm(d, axis=1, keepdims=True))
        if self.damping_ratio is not None:
            z = np.asarray(self.damping_ratio, float).reshape(-1)
            if z.size != f.size:
                raise ValueError(f"damping_ratio must have {f.size} entries")
            object.__setattr__(self, "damping_ratio", z)

    @property
    def points(self) -> Points:
        """The channels as model points."""
        return Points(self.bones, self.position_m, self.direction)


@dataclass
class MacUpdateResult:
    """Outcome of :func:`update_by_mac`. Units: parameters in SI (coordinates in m)."""

    names: list[str]
    values: np.ndarray
    std: np.ndarray  # NaN for parameters on an unresolved direction
    correlation: np.ndarray
    converged: bool
    message: str
    cost_eq14_1: float  # J = N_modes - sum MAC over the paired modes (thesis eq. 14.1)
    pairs: list[tuple[int, int]]  # (measured mode, model elastic mode), final pairing
    mac: np.ndarray  # (n_measured,) MAC with the partner, NaN when unpaired
    frequency_error: np.ndarray  # (n_measured,) f_model/f_meas - 1, NaN when unpaired
    damping_error: np.ndarray  # (n_measured,) zeta_model - zeta_meas, NaN when unpaired
    unpaired: list[int]  # measured modes left out (no model mode above min_mac, or
    # unknown shape entries on the channels correlated)
    model_frequency_hz: np.ndarray  # elastic natural frequencies of the updated model
    starts: int
    start_costs: list[float]
    evaluations: int
    wall_time_s: float
    weak_directions: list[dict[str, object]] = field(default_factory=list)
    model: PelvisModel | None = None
    log_mask: np.ndarray | None = None  # (n_p,) fitted in log p (else linearly: coordinates)

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary (NaN as None)."""
        def num(x: float) -> float | None:
            return None if not np.isfinite(x) else float(x)

        log = (np.ones(len(self.names), bool) if self.log_mask is None
               else np.asarray(self.log_mask, bool))
        return {
            "parameters": {n: {"value": float(v), "std": num(s),
                               "interval_95": interval_95(n, float(v), float(s), bool(g))}
                           for n, v, s, g in zip(self.names, self.values, self.std, log,
                                                 strict=True)},
            "converged": self.converged, "message": self.message,
            "cost_eq14_1": self.cost_eq14_1,
            "pairs": [{"measured": a, "model": b, "mac": num(self.mac[a]),
                       "frequency_error": num(self.frequency_error[a]),
                       "damping_error": num(self.damping_error[a])} for a, b in self.pairs],
            "unpaired": list(self.unpaired), "starts": self.starts,
            "start_costs": self.start_costs, "evaluations": self.evaluations,
            "wall_time_s": self.wall_time_s, "weak_directions": self.weak_directions,
        }


def correlation_operator(measured: MeasuredModes, filter_rigid: bool = True) -> np.ndarray:
    """The fig. 14.1 filtering as a real matrix P (n_ch, n_ch): ``x_corr = P x``.

    :func:`correlation_shapes` is linear in the shapes (least-squares projections with the
    measured geometry), so applying it to the identity gives P; the same P then filters
    measured and model shapes alike and passes derivatives through. Rows of channels on no
    bone are NaN. ``filter_rigid=False``: identity (plain MAC at the channels).
    """
    n = len(measured.bones)
    if not filter_rigid:
        P = np.eye(n)
        P[[k for k, b in enumerate(measured.bones) if not b]] = np.nan
        return P
    P = correlation_shapes(np.eye(n), list(measured.bones), measured.position_m,
                           measured.direction)
    return np.real(P)


def mode_sensitivities(M: np.ndarray, K: np.ndarray, C: np.ndarray, lam: complex,
                       z: np.ndarray, dM: np.ndarray, dK: np.ndarray, dC: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """dλ/dp (n_p,) and dz/dp (n_dof, n_p) of one complex mode of ``(λ²M + λC + K) z = 0``.

    Symmetric M, K, C (left eigenvector = right one): ``dλ = −zᵀ(λ²dM + λdC + dK)z /
    zᵀ(2λM + C)z`` (the quadratic analogue of app. C eq. C-4). Eigenvector by Nelson's method
    (AIAA J. 14, 1976): the component of largest |z| is held fixed, the remaining square
    system is regular for a simple eigenvalue. Any complex rescaling of z is invisible to MAC,
    so this normalisation is as good as any.
    """
    A = lam**2 * M + lam * C + K
    B = 2 * lam * M + C
    dA = lam**2 * dM + lam * dC + dK  # (n_p, n, n)
    dAz = dA @ z  # (n_p, n)
    dlam = -(dAz @ z) / (z @ B @ z)
    rhs = -(dAz + dlam[:, None] * (B @ z)[None, :])  # (n_p, n)
    k = int(np.argmax(np.abs(z)))
    keep = np.arange(z.size) != k
    dz = np.zeros((z.size, dM.shape[0]), complex)
    dz[keep] = np.linalg.solve(A[np.ix_(keep, keep)], rhs[:, keep].T)
    return dlam, dz


def _aligned(y: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, float, complex]:
    """Unit-normalised y rotated onto unit a: ``y e^{iθ}/|y|`` with θ = arg(yᴴa)."""
    n = float(np.linalg.norm(y))
    c = np.vdot(y, a)
    e = c / abs(c) if abs(c) > 0 else 1.0
    return y * e / n, n, c


def _aligned_derivative(y: np.ndarray, dy: np.ndarray, a: np.ndarray) -> np.ndarray:
    """d(aligned y) for directions dy (n, n_p); exact differentiation of :func:`_aligned`."""
    yt, n, c = _aligned(y, a)
    e = c / abs(c) if abs(c) > 0 else 1.0
    dn = np.real(np.conj(y) @ dy) / n  # (n_p,)
    dc = np.conj(dy).T @ a  # (n_p,)
    dtheta = np.imag(dc / c) if abs(c) > 0 else np.zeros(dy.shape[1])
    return e / n * (dy + 1j * np.outer(y, dtheta)) - np.outer(yt, dn / n)


def _coordinate_groups(model: PelvisModel, names: Sequence[str]) -> list[str]:
    groups = []
    for g in dict.fromkeys(s.group or s.name for s in model.springs):
        if any(n.startswith(f"r_{g}_") for n in names):
            groups.append(g)
    return groups


def updating_space(model: PelvisModel, params: Sequence[str], *, symmetric: bool = True,
                   bound_factor: float = 10.0, coordinate_range_m: float = 0.01
                   ) -> ParameterSpace:
    """The parameter space :func:`update_by_mac` updates: ``params`` of
    :func:`~pelvislab.model.parameters.parameter_space` (``symmetric`` names), with the
    attachment coordinates of every spring group named as ``r_<group>_...`` (bounds nominal
    ± ``coordinate_range_m``, m). Raises KeyError for a name the model does not have."""
    return parameter_space(model, symmetric=symmetric, only=list(params),
                           bound_factor=bound_factor,
                           coordinates=_coordinate_groups(model, params),
                           coordinate_range_m=coordinate_range_m)


@one_blas_thread
def update_by_mac(
    model: PelvisModel,
    measured: MeasuredModes,
    params: Sequence[str],
    *,
    symmetric: bool = True,
    frequency_weight: float | Sequence[float] = 1.0,
    mac_weight: float | Sequence[float] = 1.0,
    damping_weight: float | Sequence[float] = 1.0,
    shape_std: float | Sequence[float] | None = None,
    frequency_std_hz: float | Sequence[float] | None = None,
    damping_std: float | Sequence[float] | None = None,
    filter_rigid: bool = True,
    min_mac: float = 0.5,
    max_pair_frequency_error: float = 0.2,
    coordinate_range_m: float = 0.01,
    bound_factor: float = 10.0,
    n_starts: int = 4,
    perturbation: float = 0.3,
    seed: int = 0,
    jacobian: str = "analytic",
    max_nfev: int = 60,
    cost_tol: float = 1e-10,
    space: ParameterSpace | None = None,
) -> MacUpdateResult:
    """Update ``params`` of ``model`` so its modes match ``measured`` (thesis eq. 14.1).

    ``params``: names from :func:`~pelvislab.model.parameters.parameter_space` with
    ``symmetric`` (e.g. ``k_io``, ``c_sij``, ``r_io_a_x``; attachment coordinates
    ``r_<group>[_<side>]_<a|b>_<x|y|z>`` in m, bounds nominal ± ``coordinate_range_m``; positive
    parameters in log scale, bounds start ×/÷ ``bound_factor``). Weights are per measured
    mode or scalar: ``mac_weight`` multiplies the eq. 14.1 shape term, ``frequency_weight`` the
    relative frequency error (0: pair on the shape only, as the thesis did for mode 1),
    ``damping_weight`` the relative damping-ratio error (only with measured damping).
    Measurement standard deviations replace the weights and calibrate the standard errors:
    ``shape_std`` (std of the real and of the imaginary part of each shape entry, in the units
    of ``measured.shapes``), ``frequency_std_hz``, ``damping_std`` (of the damping ratio). When
    every residual term in use has its std, the covariance is absolute (chi-square); otherwise
    it is scaled by the pooled residual variance, which mixes shape, frequency and damping
    residuals and can underestimate the errors several-fold (measured: see docs/ema.md).
    ``filter_rigid``: correlate the shapes filtered as in fig. 14.1 (default; the filter
    removes the 6 global rigid motions, so a layout that does not determine all six, or
    that leaves fewer independent directions than measured modes, is refused with a
    ValueError) or the plain shapes at the channels (``False``).
    ``max_pair_frequency_error``: a pair that ends further apart in relative frequency is
    named in ``message`` and the result is not ``converged`` (MAC alone pairs the modes).
    ``n_starts``: the nominal start, then random starts (log-uniform ±``perturbation`` for
    positive parameters, ±``perturbation`` × range for coordinates); stops early when the
    eq. 14.1 cost is below ``cost_tol``. ``jacobian``: ``"analytic"`` (eigen-sensitivities)
    or ``"fd"`` (finite differences of the modal solution).
    """
    t0 = time.perf_counter()
    params = list(params)
    if not params:
        raise ValueError("no parameters to update")
    if jacobian not in ("analytic", "fd"):
        raise ValueError(f"jacobian must be 'analytic' or 'fd', not {jacobian!r}")
    if space is None:
        space = updating_space(model, params, symmetric=symmetric, bound_factor=bound_factor,
                               coordinate_range_m=coordinate_range_m)
    names = list(space.names)
    n_m = measured.frequency_hz.size

    def per_mode(w: float | Sequence[float], what: str, positive: bool = False) -> np.ndarray:
        arr = np.broadcast_to(np.asarray(w, float), (n_m,)).copy() if np.ndim(w) == 0 \
            else np.asarray(w, float)
        if arr.shape != (n_m,) or np.any(arr < 0) or (positive and np.any(arr <= 0)):
            kind = "positive" if positive else "non-negative"
            raise ValueError(f"{what} must be a {kind} scalar or {n_m} values")
        return arr

    w_mac = per_mode(mac_weight, "mac_weight")
    w_f = per_mode(frequency_weight, "frequency_weight")
    w_z = per_mode(damping_weight, "damping_weight") if measured.damping_ratio is not None \
        else np.zeros(n_m)

    # fig. 14.1 filtering as one linear map; channels on no bone dropped
    P = correlation_operator(measured, filter_rigid)
    ok = np.all(np.isfinite(P), axis=1)
    if ok.sum() < 2:
        raise ValueError("fewer than two measured channels lie on a bone")
    if filter_rigid:
        # the filter takes out the 6 global rigid motions and correlates what is left: a
        # layout that cannot see all six leaves a remnant that is not the elastic motion
        # (make demo's 5 x-probes see 3 and leave 2 directions, in which the pairing by MAC
        # took the 231.9 Hz mode for the 303.6 Hz one, 31 % off, and "converged")
        n_ch = len(measured.bones)
        seen = filter_global(np.eye(n_ch), measured.position_m, measured.direction).rank
        left = int(np.linalg.matrix_rank(P[ok], tol=1e-8))
        if seen < 6 or left < max(2, n_m):
            raise ValueError(
                f"the rigid-body filter of thesis fig. 14.1 needs the 6 global rigid motions "
                f"determined and more independent directions left than modes: the "
                f"{n_ch} channels determine {seen} of 6 and leave {left} for {n_m} measured "
                "mode(s) (the thesis' ch. 11 layout: 39 channels); measure more directions, "
                "or pass filter_rigid=False for plain MAC at the channels")
    rows = rows_for(space.model, measured.points)
    G = P[ok] @ np.nan_to_num(rows)  # (n_ok, n_dof): model DOFs -> correlation shapes
    a_corr = (P[ok] @ measured.shapes).astype(complex)
    # a mode whose shape lacks entries the correlation uses (null in `ema`'s JSON: no FRF
    # measured around it, e.g. a run stopped below it) cannot be correlated; it was left
    # out as having "no model partner with MAC >= 0.5" (review of the EMA path)
    unknown = [int(i) for i in np.flatnonzero(~np.all(np.isfinite(a_corr), axis=0))]
    a_corr[:, unknown] = 0.0
    if len(unknown) == n_m:
        raise ValueError(f"measured mode(s) {unknown} have unknown shape entries (not "
                         "measured around them) on channels the correlation uses: no mode "
                         "to update on")
    a_norm = np.linalg.norm(a_corr, axis=0)
    a_norm[unknown] = 1.0
    if np.any(a_norm == 0):
        raise ValueError(f"measured mode(s) {list(np.flatnonzero(a_norm == 0))} vanish after "
                         "the rigid-body filtering")
    a_hat = a_corr / a_norm
    if shape_std is not None:
        w_mac = a_norm / per_mode(shape_std, "shape_std", True)
    if frequency_std_hz is not None:
        w_f = measured.frequency_hz / per_mode(frequency_std_hz, "frequency_std_hz", True)
    if damping_std is not None and measured.damping_ratio is not None:
        w_z = measured.damping_ratio / per_mode(damping_std, "damping_std", True)
    absolute_sigma = (shape_std is not None
                      and (frequency_std_hz is not None or not np.any(w_f))
                      and (damping_std is not None or not np.any(w_z)))
    zeta_meas = measured.damping_ratio

    def modes_at(values: np.ndarray) -> tuple[object, object]:
        mats = space.matrices(values)
        return mats, complex_modes(mats.M, mats.K, mats.C, mats.f_k, mats.f_c, mats.f_max_hz)

    # which measured modes can be paired at all (nominal start); the rest are reported
    _, modes0 = modes_at(space.values())
    m0 = mac(a_hat, G @ modes0.shapes)
    unpaired = [i for i in range(n_m) if i not in unknown
                and (m0.shape[1] == 0 or m0[i].max() < min_mac)]
    active = np.array([i for i in range(n_m) if i not in unpaired and i not in unknown],
                      dtype=int)
    state = {"active": active}
    if active.size == 0:
        raise ValueError(f"no measured mode pairs with a model mode at MAC >= {min_mac}")
    n_eval = [0]

    def evaluate(x: np.ndarray, need_jac: bool) -> tuple[np.ndarray, np.ndarray | None, dict]:
        n_eval[0] += 1
        values = space.from_scaled(x)
        mats, modes = modes_at(values)
        y_all = G @ modes.shapes
        active = state["active"]
        pairs = pair_modes(a_hat[:, active], y_all)
        partner = {int(active[p.a]): p.b for p in pairs}
        lam = modes.poles
        res, jac = [], []
        if need_jac:
            dM, dK, dC = space.derivatives(values)
            chain = space.scaled_chain(values)
        for i in active:
            j = partner.get(int(i))
            if j is None:  # more measured than model modes: no partner this time
                res.append(np.zeros(2 * G.shape[0] + 2))
                if need_jac:
                    jac.append(np.zeros((2 * G.shape[0] + 2, len(names))))
                continue
            yt, _, _ = _aligned(y_all[:, j], a_hat[:, i])
            f_model = abs(lam[j]) / (2 * np.pi)
            zeta = -lam[j].real / abs(lam[j])
            d = w_mac[i] * (a_hat[:, i] - yt)
            rz = (w_z[i] * (zeta / zeta_meas[i] - 1.0)) if w_z[i] > 0 else 0.0
            res.append(np.concatenate([d.real, d.imag,
                                       [w_f[i] * (f_model / measured.frequency_hz[i] - 1.0), rz]]))
            if need_jac:
                dlam, dz = mode_sensitivities(mats.M, mats.K, mats.C, lam[j], modes.shapes[:, j],
                                              dM, dK, dC)
                dd = -w_mac[i] * _aligned_derivative(y_all[:, j], G @ dz, a_hat[:, i])
                s = abs(lam[j])
                ds = np.real(np.conj(lam[j]) * dlam) / s
                df = w_f[i] * ds / (2 * np.pi) / measured.frequency_hz[i]
                dzeta = -np.real(dlam) / s + lam[j].real * ds / s**2
                dzr = w_z[i] * dzeta / zeta_meas[i] if w_z[i] > 0 else np.zeros(len(names))
                jac.append(np.vstack([dd.real, dd.imag, df[None], dzr[None]]) * chain[None, :])
        info = {"modes": modes, "y": y_all, "partner": partner}
        return np.concatenate(res), (np.vstack(jac) if need_jac else None), info

    cache: dict[bytes, tuple] = {}

    def get(x: np.ndarray, need_jac: bool) -> tuple:
        key = x.tobytes()
        hit = cache.get(key)
        if hit is None or (need_jac and hit[1] is None):
            cache.clear()
            cache[key] = hit = evaluate(x, need_jac)
        return hit

    lo = space.to_scaled(space.lower)
    hi = space.to_scaled(space.upper)
    x0 = np.clip(space.to_scaled(space.values()), lo, hi)
    rng = np.random.default_rng(seed)
    log = space.log_mask
    start_costs: list[float] = []
    starts = 0
    x_centre = x0
    # Modes left out at the start are re-checked against the updated model and, once they
    # pair above min_mac, included and the fit repeated from there (at most 3 rounds).
    for _round in range(3):
        best = None
        for k in range(max(1, n_starts)):
            if k == 0:
                xs = x_centre.copy()
            else:
                u = rng.uniform(-1.0, 1.0, x0.size)
                step = np.where(log, np.log1p(perturbation) * u,
                                perturbation * u * (hi - lo) / 2)
                xs = np.clip(x_centre + step, lo + 1e-9 * (hi - lo), hi - 1e-9 * (hi - lo))
            starts += 1
            jac_arg = (lambda x: get(x, True)[1]) if jacobian == "analytic" else "2-point"
            sol = least_squares(lambda x: get(x, jacobian == "analytic")[0], xs, jac=jac_arg,
                                bounds=(lo, hi), method="trf", x_scale="jac", ftol=1e-12,
                                xtol=1e-12, gtol=1e-12, max_nfev=max_nfev)
            start_costs.append(float(sol.cost))
            if best is None or sol.cost < best.cost:
                best = sol
            if best.cost < cost_tol:
                break
        assert best is not None
        if not unpaired:
            break
        info_now = get(best.x, False)[2]
        m_now = mac(a_hat[:, unpaired], info_now["y"])
        back = [i for i, row in zip(unpaired, m_now, strict=True) if row.max() >= min_mac]
        if not back:
            break
        unpaired = [i for i in unpaired if i not in back]
        state["active"] = np.array(sorted([*state["active"], *back]), dtype=int)
        cache.clear()
        x_centre = best.x
    assert best is not None
    r, J, info = get(best.x, True) if jacobian == "analytic" else get(best.x, False)
    if J is None:  # fd mode: the Jacobian least_squares ended with
        J = best.jac
    values = space.from_scaled(best.x)
    # std in the scaled variables: log p for positive parameters, p for coordinates
    std_vals = np.where(log, values, 1.0)
    std, corr, _, weak = covariance_report(J, r, names, std_vals,
                                             absolute_sigma=absolute_sigma)

    modes = info["modes"]
    y_all = info["y"]
    m_full = mac(a_hat, y_all)
    final_pairs = sorted(info["partner"].items())
    macs = np.full(n_m, np.nan)
    ferr = np.full(n_m, np.nan)
    zerr = np.full(n_m, np.nan)
    f_model = modes.natural_frequencies_hz
    for i, j in final_pairs:
        macs[i] = m_full[i, j]
        ferr[i] = f_model[j] / measured.frequency_hz[i] - 1.0
        if zeta_meas is not None:
            zerr[i] = modes.damping_ratios[j] - zeta_meas[i]
    no_partner = sorted({*unpaired, *(int(i) for i in state["active"]
                                      if int(i) not in info["partner"])})
    unpaired = sorted({*no_partner, *unknown})
    cost = mac_cost(a_hat, y_all, final_pairs)
    low = [i for i, _ in final_pairs if macs[i] < min_mac]
    at_bound = np.flatnonzero(np.isclose(best.x, lo, atol=1e-6 * (hi - lo))
                              | np.isclose(best.x, hi, atol=1e-6 * (hi - lo)))
    msgs = [str(best.message)]
    if at_bound.size:
        msgs.append("on bound: " + ", ".join(names[k] for k in at_bound))
    if no_partner:
        msgs.append(f"measured mode(s) {no_partner} have no model partner with MAC >= "
                    f"{min_mac} and were left out")
    if unknown:
        msgs.append(f"measured mode(s) {unknown} have unknown shape entries (not measured "
                    "around them) on channels the correlation uses and were left out")
    if low:
        msgs.append(f"measured mode(s) {low} ended paired below MAC {min_mac}")
    # pairing is by MAC alone; a pair this far apart in frequency after the fit is more
    # likely a wrong partner than an updated model (make demo's layout with the filter:
    # 231.9 Hz paired with the model's 303.6 Hz mode, 31 % off, "converged")
    far = [i for i, _ in final_pairs if abs(ferr[i]) > max_pair_frequency_error]
    if far:
        msgs.append(f"measured mode(s) {far} ended paired with model modes more than "
                    f"{100 * max_pair_frequency_error:g} % away in frequency: check the "
                    "pairing (MAC alone decides it; too few channels?)")
    converged = bool(best.status > 0) and at_bound.size == 0 and not low and not far
    return MacUpdateResult(
        names=names, values=values, std=std, correlation=corr, converged=converged,
        message="; ".join(msgs), cost_eq14_1=float(cost), pairs=[(int(i), int(j))
                                                                  for i, j in final_pairs],
        mac=macs, frequency_error=ferr, damping_error=zerr, unpaired=unpaired,
        model_frequency_hz=f_model, starts=starts, start_costs=start_costs,
        evaluations=n_eval[0], wall_time_s=time.perf_counter() - t0, weak_directions=weak,
        model=space.apply(values), log_mask=np.asarray(log, bool),
    )
