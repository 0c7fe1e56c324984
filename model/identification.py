"""FRF-based model updating (thesis ch. 6.2, versions A and B of ch. 7).

The identification works on any linear structural model given as *system matrices with
parameter derivatives* (:class:`SystemMatrices`) plus real observation/excitation matrices
mapping the model DOFs to measurement points: the pelvis model of ``pelvislab.model``
supplies both (see :func:`pelvislab.model.identification_model.pelvis_problem`).

Dynamic stiffness (receptance convention of design 4.1, eq. 7.1-7.3 of the thesis)::

    Z(w) = -w^2 M + (1 + f_k w / (4 w_max)) K + i (w + f_c w_max / 4) C

Version A is ``f_k = f_c = 0``; version B identifies ``f_k`` and ``f_c`` as well.
H(w) = O Z(w)^-1 B and its analytic Jacobian dH/dp = -(O Z^-1) dZ/dp (Z^-1 B) is
evaluated batched over all frequencies (one LU solve per frequency with stacked
right-hand sides).

Residual formulations (``ResidualSpec.kind``):

* ``"eq610"`` -- the thesis' cost eq. 6.10: ``a Re(H - H~)^2 + b Im(H - H~)^2`` (absolute);
* ``"std"``   -- the same difference divided by the measurement standard uncertainty
  ``H_std`` (design 4.2): a chi-square, so the covariance of the estimate is absolute;
* ``"log"``   -- complex log-ratio ``log(H / H~)``: log-magnitude and phase residuals, which
  weight every line by its *relative* misfit (small FRFs away from resonance count as
  much as the peaks).

Parameters are optimised as ``log(p)`` (positive physical parameters, relative scaling)
with bounds; the frequency-dependence factors of version B are optimised linearly
(they may be 0) and bounded to ``[-0.5, 5]`` (0 is then an interior point).
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import glob
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

FREQ_DEP_NAMES = ("f_k", "f_c")

#: Residuals count as structured along frequency when their lag-1 correlation exceeds
#: this many standard deviations of white noise's (1/sqrt(pairs)); measured (session 36,
#: face-up 5-300 Hz at 5 Hz, 1770 pairs): white noise |r1| <= 0.047 in 11 fits, a local
#: minimum 0.27, version-B data fitted as A 0.34, asymmetric data fitted symmetric 0.26,
#: the thesis' sensor errors (2 mm, 10 deg) 0.08-0.19.
WHITENESS_SIGMAS = 4.0
#: Fewer neighbour pairs than this: whiteness not judged.
MIN_WHITENESS_PAIRS = 20
#: Residuals at or below this rms (relative kinds, log and eq610; ``std`` ones relative to
#: the data's rms in the same weighting) are an exact fit (synthetic data): rounding, not
#: judged for structure; also ``default_strategy``'s target for the relative kinds.
EXACT_FIT_RMS = 1e-8
#: p-value of :func:`frequency_dependence_test` below which version B's f_k, f_c count as
#: explaining part of a version-A fit's misfit (one false alarm in a thousand fits of data
#: without frequency dependence, at the declared noise).
FREQUENCY_DEPENDENCE_P = 1e-3


def _openblas_handles() -> list[tuple[Callable, Callable]]:
    """(get, set) thread-count functions of the OpenBLAS copies numpy and scipy bundle."""
    import scipy

    handles = []
    for pkg in (np, scipy):
        libs = os.path.join(os.path.dirname(os.path.dirname(pkg.__file__)),
                            f"{pkg.__name__}.libs", "*openblas*.so*")
        for path in glob.glob(libs):
            try:
                lib = ctypes.CDLL(path)
            except OSError:
                continue
            for get, set_ in (("scipy_openblas_get_num_threads64_",
                               "scipy_openblas_set_num_threads64_"),
                              ("scipy_openblas_get_num_threads",
                               "scipy_openblas_set_num_threads"),
                              ("openblas_get_num_threads", "openblas_set_num_threads")):
                if hasattr(lib, get) and hasattr(lib, set_):
                    handles.append((getattr(lib, get), getattr(lib, set_)))
                    break
    return handles


@contextlib.contextmanager
def single_blas_thread() -> Iterator[None]:
    """Run the block with one OpenBLAS thread (numpy's and scipy's copies), then restore.

    Identification makes thousands of small LAPACK/BLAS calls; a multi-threaded OpenBLAS
    on a loaded 2-core machine was measured ~10x slower (one 18-parameter fit 19.9 s vs
    1.6 s wall; a 3588 x 18 SVD 0.44 s vs ~1 ms). threadpoolctl does this properly; it is
    not a dependency of the project, so this is a best-effort no-op when the library
    layout is unknown.
    """
    saved = []
    try:
        for get, set_ in _openblas_handles():
            saved.append((set_, int(get())))
            set_(1)
    except Exception:  # thread control is an optimisation only
        pass
    try:
        yield
    finally:
        for set_, n in saved:
            with contextlib.suppress(Exception):
                set_(n)



@dataclass(frozen=True)
class SystemMatrices:
    """M, C, K (n_dof, n_dof) and their derivatives (n_p, n_dof, n_dof) w.r.t. each parameter.

    Units: kg, N s/m, N/m for the matrices; per unit of the parameter (SI) for derivatives.
    """

    M: np.ndarray
    C: np.ndarray
    K: np.ndarray
    dM: np.ndarray
    dC: np.ndarray
    dK: np.ndarray


Assemble = Callable[[np.ndarray], SystemMatrices]


@dataclass(frozen=True)
class FrfProblem:
    """A parametric FRF model: named parameters, matrix assembly, observation and excitation.

    ``assemble(values)`` returns the system matrices for the full parameter vector
    ``values`` (SI, same order as ``names``) and their derivatives. ``outputs`` (n_out, n_dof)
    maps DOF displacements to measured displacements (m) along the measurement directions;
    ``inputs`` (n_dof, n_in) maps unit point forces (N) to generalised forces.
    ``omega_max_rad_s`` is w_max of eq. 7.2-7.3 (version B only).
    """

    names: tuple[str, ...]
    nominal: np.ndarray
    assemble: Assemble
    outputs: np.ndarray
    inputs: np.ndarray
    omega_max_rad_s: float = 2 * np.pi * 300.0

    @property
    def n_params(self) -> int:
        """Number of physical parameters."""
        return len(self.names)


@dataclass(frozen=True)
class ResidualSpec:
    """How the FRF misfit is turned into a residual vector (see the module docstring)."""

    kind: str = "log"
    a: float = 1.0
    b: float = 1.0

    def __post_init__(self) -> None:
        if self.kind not in ("eq610", "std", "log", "logmag"):
            raise ValueError(
                f"unknown residual kind {self.kind!r}; use eq610, std, log or logmag")
        if self.a < 0 or self.b < 0 or self.a + self.b == 0:
            raise ValueError("weights a, b must be non-negative and not both zero")


def dynamic_stiffness_terms(
    omega_rad_s: np.ndarray, omega_max_rad_s: float, f_k: float, f_c: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Frequency factors (mass, stiffness, damping) of Z = -w^2 M + kappa K + i gamma C.

    kappa = 1 + f_k w / (4 w_max) (eq. 7.3), gamma = w + f_c w_max / 4 (eq. 7.2); w in rad/s.
    """
    w = np.asarray(omega_rad_s, dtype=float)
    return -(w**2), 1.0 + f_k * w / (4.0 * omega_max_rad_s), w + f_c * omega_max_rad_s / 4.0


def frf_with_jacobian(
    mats: SystemMatrices,
    outputs: np.ndarray,
    inputs: np.ndarray,
    frequency_hz: np.ndarray,
    *,
    f_k: float = 0.0,
    f_c: float = 0.0,
    omega_max_rad_s: float = 2 * np.pi * 300.0,
    jacobian: bool = True,
    freq_dep_jacobian: bool = False,
    loss_factor: float = 0.0,
) -> tuple[np.ndarray, np.ndarray | None]:
    """Receptance H (n_f, n_out, n_in) in m/N and dH/dp (n_f, n_p[+2], n_out, n_in).

    Eq. 7.1 with eq. 7.2-7.3 (f_k = f_c = 0: the plain viscous model of ch. 4.4).
    dH/dp_j = -(O Z^-1) dZ_j (Z^-1 B) batched over frequency; with ``freq_dep_jacobian``
    two trailing columns hold dH/df_k and dH/df_c. ``loss_factor`` eta adds structural
    damping i eta K (zeta ~ eta / 2 on every mode): used only as a continuation device that
    widens the model's resonance peaks during the first stages of a fit.
    """
    w = 2 * np.pi * np.asarray(frequency_hz, dtype=float)
    am, ak, ac = dynamic_stiffness_terms(w, omega_max_rad_s, f_k, f_c)
    if loss_factor:
        ak = ak + 1j * loss_factor
    Z = (am[:, None, None] * mats.M + ak[:, None, None] * mats.K
         + 1j * ac[:, None, None] * mats.C)
    n_in = inputs.shape[1]
    # Z is complex symmetric, so (O Z^-1)^T = Z^-1 O^T: one solve for both sides.
    rhs = np.concatenate([inputs, outputs.T], axis=1).astype(complex)
    sol = np.linalg.solve(Z, np.broadcast_to(rhs, (w.size, *rhs.shape)))
    X = sol[:, :, :n_in]  # Z^-1 B (n_f, n, n_in)
    Lt = sol[:, :, n_in:]  # (O Z^-1)^T (n_f, n, n_out)
    H = np.einsum("on,fni->foi", outputs, X)
    if not jacobian:
        return H, None
    L = np.swapaxes(Lt, 1, 2)  # (n_f, n_out, n)
    n_f, n, _ = X.shape
    n_p = mats.dM.shape[0]
    # dZ_j X for every j and f: one GEMM per matrix family, (n_p n, n) @ (n, n_f n_in),
    # combined with the frequency factors, then one batched (n_out, n) @ (n, n_p n_in).
    Xr = np.transpose(X, (1, 0, 2)).reshape(n, n_f * n_in)

    Xre, Xim = np.ascontiguousarray(Xr.real), np.ascontiguousarray(Xr.imag)
    dZX = np.zeros((n_p, n, n_f, n_in), complex)
    for d, factor in ((mats.dM, am), (mats.dK, ak), (mats.dC, 1j * ac)):
        nz = np.flatnonzero(np.any(d != 0, axis=(1, 2)))  # most parameters touch one matrix
        if nz.size == 0:
            continue
        dd = d[nz].reshape(nz.size * n, n)
        # real @ real twice: numpy has no BLAS path for real @ complex
        prod = (dd @ Xre + 1j * (dd @ Xim)).reshape(nz.size, n, n_f, n_in)
        dZX[nz] += factor[None, None, :, None] * prod
    dZX = np.transpose(dZX, (2, 1, 0, 3)).reshape(n_f, n, n_p * n_in)
    dH = -(L @ dZX).reshape(n_f, L.shape[1], n_p, n_in).transpose(0, 2, 1, 3)
    if freq_dep_jacobian:
        LKX = L @ mats.K @ X
        LCX = L @ mats.C @ X
        d_fk = -(w / (4.0 * omega_max_rad_s))[:, None, None] * LKX
        d_fc = -(1j * omega_max_rad_s / 4.0) * LCX
        dH = np.concatenate([dH, d_fk[:, None], d_fc[:, None]], axis=1)
    return H, dH


# --------------------------------------------------------------------------------------
# Residuals


@dataclass
class _Target:
    """Measured data flattened to the measured lines only."""

    frequency_hz: np.ndarray
    mask: np.ndarray  # (n_f, n_out, n_in) bool
    H: np.ndarray  # (n_lines,) complex
    weight: np.ndarray  # (n_lines,) real, multiplies H - H~ for eq610/std
    spec: ResidualSpec

    @classmethod
    def build(cls, frequency_hz: np.ndarray, H: np.ndarray, H_std: np.ndarray | None,
              spec: ResidualSpec) -> _Target:
        mask = np.isfinite(H)
        if H_std is not None:
            mask &= np.isfinite(H_std) & (H_std > 0)
        if spec.kind in ("log", "logmag"):
            mask &= np.abs(np.where(mask, H, 0)) > 0
        if not mask.any():
            raise ValueError("no measured FRF lines to fit")
        h = H[mask]
        if spec.kind == "std":
            if H_std is None:
                raise ValueError("residual 'std' needs H_std in the FRF file")
            # H_std is the rms of the complex error: each of Re/Im has sigma/sqrt(2).
            weight = np.sqrt(2.0) / H_std[mask]
        elif spec.kind == "eq610":
            # One global scale so the cost is O(1) and tolerances make sense; the
            # minimiser of eq. 6.10 is unchanged.
            weight = np.full(h.shape, 1.0 / np.sqrt(np.mean(np.abs(h) ** 2)))
        else:
            weight = np.ones(h.shape)
        return cls(np.asarray(frequency_hz, float), mask, h, weight, spec)

    def residual(self, H_model: np.ndarray) -> np.ndarray:
        h = H_model[self.mask]
        s = self.spec
        if s.kind == "logmag":
            return np.log(np.abs(h / self.H))
        if s.kind == "log":
            ratio = h / self.H
            return np.concatenate([np.sqrt(s.a) * np.log(np.abs(ratio)),
                                   np.sqrt(s.b) * np.angle(ratio)])
        d = self.weight * (h - self.H)
        wa, wb = (np.sqrt(s.a), np.sqrt(s.b)) if s.kind == "eq610" else (1.0, 1.0)
        return np.concatenate([wa * d.real, wb * d.imag])

    def jacobian(self, H_model: np.ndarray, dH: np.ndarray) -> np.ndarray:
        # dH (n_f, n_p, n_out, n_in) -> (n_lines, n_p)
        d = np.moveaxis(dH, 1, -1)[self.mask]
        s = self.spec
        if s.kind == "logmag":
            return (d / H_model[self.mask][:, None]).real
        if s.kind == "log":
            g = d / H_model[self.mask][:, None]  # d log H
            return np.concatenate([np.sqrt(s.a) * g.real, np.sqrt(s.b) * g.imag])
        g = self.weight[:, None] * d
        wa, wb = (np.sqrt(s.a), np.sqrt(s.b)) if s.kind == "eq610" else (1.0, 1.0)
        return np.concatenate([wa * g.real, wb * g.imag])


# --------------------------------------------------------------------------------------
# Parameter mapping (log-parameters for physical ones, linear for f_k/f_c)


@dataclass(frozen=True)
class _Mapping:
    free: np.ndarray  # indices into the physical parameter vector
    base: np.ndarray  # full physical vector (fixed values used for non-free parameters)
    freq_dep: bool  # version B: two extra linear parameters f_k, f_c
    fixed_fk: float
    fixed_fc: float

    def unpack(self, x: np.ndarray) -> tuple[np.ndarray, float, float]:
        n = self.free.size
        values = self.base.copy()
        values[self.free] = np.exp(x[:n])
        if self.freq_dep:
            return values, float(x[n]), float(x[n + 1])
        return values, self.fixed_fk, self.fixed_fc

    def pack(self, values: np.ndarray, f_k: float, f_c: float) -> np.ndarray:
        x = np.log(values[self.free])
        return np.concatenate([x, [f_k, f_c]]) if self.freq_dep else x


@dataclass
class FitResult:
    """Outcome of one identification (physical SI values, not log-parameters)."""

    names: list[str]
    values: np.ndarray
    std: np.ndarray  # standard errors (SI); NaN where the layout cannot determine them
    correlation: np.ndarray
    cost: float  # 0.5 * sum(residual^2) of the chosen residual kind
    converged: bool
    evaluations: int
    wall_time_s: float
    residual_kind: str
    singular_values: np.ndarray  # of the relative (log-parameter) Jacobian, descending
    weak_directions: list[dict[str, float]]  # parameter combinations the data barely sees
    starts: int = 1
    message: str = ""
    extra: dict[str, object] = field(default_factory=dict)

    def as_dict(self) -> dict[str, object]:
        """JSON-ready dict (design 4.5)."""
        return {
            "parameters": {n: {"value": float(v), "std": _nan_to_none(s),
                               "interval_95": interval_95(n, float(v), float(s))}
                           for n, v, s in zip(self.names, self.values, self.std, strict=True)},
            "converged": bool(self.converged),
            "cost": float(self.cost),
            "evaluations": int(self.evaluations),
            "wall_time_s": float(self.wall_time_s),
            "residual": self.residual_kind,
            "starts": int(self.starts),
            "message": self.message,
            "correlation": {"names": list(self.names),
                            "matrix": [[_nan_to_none(c) for c in row]
                                       for row in self.correlation]},
            "identifiability": {
                "singular_values": [float(s) for s in self.singular_values],
                "weak_directions": self.weak_directions,
            },
            **self.extra,
        }


#: Two-sided 95 % quantile of the standard normal.
Z_95 = 1.959963984540054


def interval_95(name: str, value: float, std: float, log: bool | None = None
                ) -> list[float] | None:
    """The 95 % interval [low, high] of a fitted parameter, in its SI unit, in the space the
    fit ran in: ``value x/÷ exp(1.96 std / value)`` for the log-fitted masses, stiffnesses
    and dampings (their ``std`` is the linearised ``value x std(log p)``), ``value +- 1.96
    std`` for the linear f_k, f_c (eq. 7.1-7.3). A weak parameter's linear ``value +- 2 std``
    reached below zero, a value no mass or spring can take, and hid that the fit's
    uncertainty is a factor (calibration audit, session 43). ``log``: whether the fit ran
    in log p (None: by the name, as above; MAC updating fits coordinates linearly). None
    without a finite std."""
    if not (np.isfinite(std) and np.isfinite(value)) or std < 0:
        return None
    linear = name in ("f_k", "f_c") if log is None else not log
    if linear or value <= 0:
        return [value - Z_95 * std, value + Z_95 * std]
    # capped below float's range (value x e^300 stays finite for any SI value here): a std
    # of many e-folds says "undetermined" as well
    factor = float(np.exp(min(Z_95 * std / value, 300.0)))
    return [value / factor, value * factor]


def _nan_to_none(x: float) -> float | None:
    return None if not np.isfinite(x) else float(x)


class _Evaluator:
    """Caches the last FRF/Jacobian evaluation, counts model evaluations."""

    def __init__(self, problem: FrfProblem, target: _Target, mapping: _Mapping,
                 frequency_hz: np.ndarray, loss_factor: float = 0.0) -> None:
        self.loss_factor = loss_factor
        self.problem = problem
        self.target = target
        self.mapping = mapping
        self.frequency_hz = frequency_hz
        self.evaluations = 0
        self._key: bytes | None = None
        self._cache: tuple[np.ndarray, np.ndarray] | None = None

    def _eval(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = np.asarray(x, float).tobytes()
        if key == self._key and self._cache is not None:
            return self._cache
        values, f_k, f_c = self.mapping.unpack(x)
        mats = self.problem.assemble(values)
        H, dH = frf_with_jacobian(
            mats, self.problem.outputs, self.problem.inputs, self.frequency_hz,
            f_k=f_k, f_c=f_c, omega_max_rad_s=self.problem.omega_max_rad_s,
            freq_dep_jacobian=self.mapping.freq_dep, loss_factor=self.loss_factor,
        )
        assert dH is not None
        n_phys = self.problem.n_params
        cols = list(self.mapping.free) + (
            [n_phys, n_phys + 1] if self.mapping.freq_dep else [])
        dH = dH[:, cols]
        # chain rule for log-parameters: dH/dlog p = p dH/dp
        scale = np.ones(len(cols))
        scale[: self.mapping.free.size] = values[self.mapping.free]
        dH = dH * scale[None, :, None, None]
        self.evaluations += 1
        self._key, self._cache = key, (H, dH)
        return H, dH

    def residual(self, x: np.ndarray) -> np.ndarray:
        return self.target.residual(self._eval(x)[0])

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        H, dH = self._eval(x)
        return self.target.jacobian(H, dH)


def _gain_columns(final: _Evaluator, x: np.ndarray, gain_std: float, chain_gain_std: float
                  ) -> tuple[np.ndarray, list[float], list[str]]:
    """d residual / d gain (m, k) for one relative gain per FRF (when ``gain_std`` > 0) and
    one common to every FRF (when ``chain_gain_std`` > 0): the model FRF on the lines a
    gain scales, in the residual's units; their prior std and names."""
    H_model = final._eval(x)[0]
    mask = final.target.mask
    columns: list[np.ndarray] = []  # (n_f, n_out, n_in) bool: the FRF entries a gain scales
    priors: list[float] = []
    labels: list[str] = []
    if gain_std > 0:
        for o in range(mask.shape[1]):
            for i in range(mask.shape[2]):
                if mask[:, o, i].any():
                    scaled = np.zeros(mask.shape, dtype=bool)
                    scaled[:, o, i] = True
                    columns.append(scaled)
                    priors.append(gain_std)
                    labels.append(f"gain_{o}_{i}")
    if chain_gain_std > 0:
        columns.append(np.ones(mask.shape, dtype=bool))
        priors.append(chain_gain_std)
        labels.append("chain_gain")
    dH = np.zeros((mask.shape[0], len(columns), *mask.shape[1:]), dtype=complex)
    for k, scaled in enumerate(columns):
        dH[:, k][scaled] = H_model[scaled]
    return final.target.jacobian(H_model, dH), priors, labels


def _sandwich_with_gains(final: _Evaluator, x: np.ndarray, jac_log: np.ndarray,
                         residual: np.ndarray, values: np.ndarray, absolute: bool,
                         gain_std: float, chain_gain_std: float, rho: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray]:
    """std and correlation of a fit weighted with the gain floor, sqrt(H_std^2 + (g|H|)^2),
    under the noise it has: independent H_std per line (``rho``: H_std over the floored σ,
    per residual row) plus the relative gains (per FRF, common) as correlated errors. The
    sandwich (JᵀJ)⁺ Jᵀ Σ J (JᵀJ)⁺ with Σ = diag(rho²) s² + G diag(prior²) Gᵀ in the
    residual's units; s² = 1 when absolute, else the residual variance. Directions J does
    not resolve (singular values below 1e-6 of the largest) are left out of (JᵀJ)⁺ as in
    :func:`covariance_report`, whose NaNs the caller keeps."""
    G, priors, _ = _gain_columns(final, x, gain_std, chain_gain_std)
    m, n = jac_log.shape
    _, s, Vt = np.linalg.svd(jac_log, full_matrices=False)
    keep = s > 1e-6 * s[0] if s.size and s[0] > 0 else np.zeros(n, bool)
    a_pinv = (Vt.T * np.where(keep, 1.0 / np.where(keep, s, 1.0) ** 2, 0.0)) @ Vt
    s2 = 1.0 if absolute else float(residual @ residual) / max(m - n, 1)
    jg = jac_log.T @ G  # (n, k)
    middle = s2 * (jac_log.T * rho ** 2) @ jac_log + (jg * np.square(priors)) @ jg.T
    cov_log = a_pinv @ middle @ a_pinv
    std_log = np.sqrt(np.clip(np.diag(cov_log), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_log / np.outer(std_log, std_log)
    return np.abs(values) * std_log, corr


def _with_gain_uncertainty(final: _Evaluator, x: np.ndarray, jac_log: np.ndarray,
                           residual: np.ndarray, names: Sequence[str], values: np.ndarray,
                           absolute: bool, gain_std: float,
                           chain_gain_std: float) -> tuple[np.ndarray, np.ndarray]:
    """std and correlation of the parameters with relative gains marginalised: one per FRF
    (prior ``gain_std``, when > 0) and one shared by every FRF (prior ``chain_gain_std``,
    when > 0: the drive chain's calibration). The Jacobian gains a
    column per gain (d residual / d gain: the model FRF on the lines it scales) and a prior
    row per gain (1 / its std); the parameters' block of the covariance of that augmented
    problem (GUM: type-B uncertainties of the calibration)."""
    G, priors, labels = _gain_columns(final, x, gain_std, chain_gain_std)
    (m, n), k = jac_log.shape, len(priors)
    # the data rows in units of their noise first (s from the data residual alone, as the
    # fit's own covariance: 1 when absolute), the priors in theirs: scaling the augmented
    # problem as a whole by s^2 multiplied a stated 3 % by the residual's rms (6 % at
    # chi2/dof 4, 0.2 % with the log residual: review of session 40)
    noise = 1.0 if absolute else float(np.sqrt(residual @ residual / max(m - n, 1)))
    if not noise > 0:
        noise = 1.0  # an exact fit (rounding only): its std are nil but for the priors'
    augmented = np.block([[jac_log / noise, G / noise],
                          [np.zeros((k, n)), np.diag(1.0 / np.asarray(priors))]])
    std, corr, _, _ = covariance_report(
        augmented, np.zeros(m + k), list(names) + labels,
        np.concatenate([values, np.ones(k)]), absolute_sigma=True)
    return std[:n], corr[:n, :n]


def residual_lag1_correlation(residual: np.ndarray, mask: np.ndarray) -> tuple[float, int]:
    """Lag-1 autocorrelation of fit residuals along frequency, pooled over FRFs and parts.

    ``residual`` is the stacked residual of :class:`_Target` (one or two parts, each over
    the measured lines ``mask`` (n_f, n_out, n_in) in C order); neighbours are the next
    measured line of the same FRF. Returns (r1, number of neighbour pairs): r1 =
    sum r_i r_i+1 / sum r_i^2 (uncentred, so a common offset counts as structure). The
    lines of a stepped sine are measured one by one, so independent measurement noise
    gives r1 ~ N(0, 1/pairs); model error or a local minimum leaves a smooth misfit,
    r1 near 1 (the Durbin-Watson idea, d ~ 2 (1 - r1), for regression residuals).
    """
    n = int(mask.sum())
    if n == 0 or residual.size % n:
        return float("nan"), 0
    num = den = 0.0
    pairs = 0
    for part in residual.reshape(-1, n):
        grid = np.full(mask.shape, np.nan)
        grid[mask] = part
        for column in grid.reshape(mask.shape[0], -1).T:
            values = column[np.isfinite(column)]
            if values.size >= 2:
                num += float(values[:-1] @ values[1:])
                den += float(values @ values)
                pairs += values.size - 1
    return (num / den if den > 0 else float("nan")), pairs


# --------------------------------------------------------------------------------------
# Uncertainty and identifiability


def covariance_report(
    jac_log: np.ndarray, residual: np.ndarray, names: Sequence[str], values: np.ndarray,
    *, absolute_sigma: bool, n_weak: int = 3, rel_threshold: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, object]]]:
    """Standard errors, correlations and identifiability from the Jacobian at the optimum.

    ``jac_log`` is d residual / d log p (linear columns for f_k, f_c: ``values`` must
    then hold 1.0 for them so that std = value * std(log p) stays right). Covariance
    = s^2 (J^T J)^+ with s^2 = 1 (``absolute_sigma``: residuals already divided by the
    measurement std) or the residual variance 2 cost / (m - n). Singular directions of
    J below ``rel_threshold`` x the largest are reported and their parameters' std is NaN;
    a weak direction is ``resolved`` when above that threshold and known to better than an
    e-fold (``std_along`` <= 1).
    Returns (std, correlation, singular_values, weak_directions).
    """
    m, n = jac_log.shape
    U, s, Vt = np.linalg.svd(jac_log, full_matrices=False)
    dof = max(m - n, 1)
    s2 = 1.0 if absolute_sigma else float(residual @ residual) / dof
    keep = s > rel_threshold * s[0] if s.size and s[0] > 0 else np.zeros(n, bool)
    inv = np.where(keep, 1.0 / np.where(keep, s, 1.0) ** 2, 0.0)
    cov_log = (Vt.T * inv) @ Vt * s2
    std_log = np.sqrt(np.clip(np.diag(cov_log), 0, None))
    # Parameters that load on an unresolved direction are not determined.
    unresolved = np.zeros(n, bool)
    for k in np.flatnonzero(~keep):
        unresolved |= np.abs(Vt[k]) > 0.1
    std_log[unresolved] = np.nan
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_log / np.outer(std_log, std_log)
    corr[unresolved, :] = np.nan
    corr[:, unresolved] = np.nan
    std = np.abs(values) * std_log
    weak: list[dict[str, object]] = []
    for k in np.argsort(s)[:n_weak]:
        v = Vt[k]
        order = np.argsort(-np.abs(v))
        combo = {names[i]: round(float(v[i]), 4) for i in order if abs(v[i]) > 0.1}
        # 1-sigma change along this direction (relative for log-parameters)
        std_along = float(np.sqrt(s2) / s[k]) if s[k] > 0 else float("inf")
        weak.append({"singular_value_relative": float(s[k] / s[0]) if s[0] else 0.0,
                     # numerically resolved is not enough: one standard deviation beyond
                     # an e-fold change (std_along > 1) leaves the combination undetermined
                     # (one FRF for 18 parameters had std_along 1.15 "resolved": review,
                     # session 36)
                     "resolved": bool(keep[k]) and std_along <= 1.0,
                     "std_along": std_along,
                     "combination": combo})
    return std, corr, s, weak


# --------------------------------------------------------------------------------------
# The identification driver


@dataclass(frozen=True)
class Stage:
    """One step of a fit: residual kind (None = the final one), model loss factor (a
    continuation device, 0 = the real model), frequency stride, and the parameter-name
    prefixes that are free in this step (None = all free parameters)."""

    kind: str | None = None
    loss_factor: float = 0.0
    stride: int = 1
    groups: tuple[str, ...] | None = None
    max_nfev: int = 40
    tol: float = 1e-6


@dataclass(frozen=True)
class Strategy:
    """Global strategy of :func:`identify_frf`.

    Each start runs ``stages`` in order, then a final stage on the full grid with the
    chosen residual and the real model. The first start uses the given start values, the
    next ones random log-uniform perturbations of up to +-``spread``. ``stop_rms``: stop as
    soon as a start reaches this rms residual (~0 for noise-free data); without it all
    ``max_starts`` run and the best is kept. ``stop_at_noise_floor`` (``std`` residuals
    only, in place of ``stop_rms``): stop at :func:`noise_floor_rms`.
    ``alternate``: every second start skips the stages (the continuation helps lightly
    damped data and can mislead on heavily damped data, e.g. ch. 7 f_c = 1).
    ``hold_freq_dep_first`` (version B): the stages fit with f_k, f_c held at their start
    values plus one held stage on the real model, then all are released (measured: ch. 7
    case 1 otherwise lands in a local minimum at f_k = 0.05 from every start).
    """

    max_starts: int = 8
    spread: float = 0.5
    stages: tuple[Stage, ...] = ()
    stop_rms: float | None = None
    stop_at_noise_floor: bool = False
    stop_when_reproduced: bool = False
    alternate: bool = True
    hold_freq_dep_first: bool = True
    seed: int = 0
    max_nfev: int = 200
    tol: float = 1e-12


#: Loss-factor continuation measured best (docs/identification.md): the model's peaks are
#: first widened with structural damping eta = 0.1 (zeta ~ 5 %), then 0.02, then the real
#: model. Noise-free face-up data, 18 free parameters, +-40 % perturbation: 40/40 recovered
#: from a single start, against 0/10 for the plain log residual and 1/10 at +-10 % for
#: eq. 6.10.
CONTINUATION = (Stage("log", 0.1), Stage("log", 0.02))


def default_strategy(residual: str = "log", starts: int | None = None, seed: int = 0,
                     stop_rms: float | None = None) -> Strategy:
    """The strategy ``pelvislab identify`` uses: loss-factor continuation, then multi-start.

    Stops as soon as the target is reached (for ``std`` residuals the noise floor,
    :func:`noise_floor_rms`; otherwise ``stop_rms``, default 1e-8: an exact fit) or when
    a second start reproduces the best minimum (two independent starts landing on the
    same cost within 1e-4 relative).
    """
    at_floor = stop_rms is None and residual == "std"
    if stop_rms is None and not at_floor:
        # relative residuals: an exact fit (synthetic data) -- real data never reach it
        # and rely on the reproduced-minimum rule
        stop_rms = EXACT_FIT_RMS
    return Strategy(max_starts=4 if starts is None else max(1, int(starts)), spread=0.3,
                    stages=CONTINUATION, stop_rms=stop_rms, stop_at_noise_floor=at_floor,
                    stop_when_reproduced=True, seed=seed)


def noise_floor_rms(n_residuals: int, n_parameters: int, sigmas: float = 4.0) -> float:
    """Largest rms (sqrt(chi2 / n_residuals)) of ``std`` residuals (each divided by its
    standard uncertainty) that independent noise at the declared level explains: chi2/dof
    within ``sigmas`` standard deviations of 1 (chi2/dof has std sqrt(2/dof)), dof =
    n_residuals - n_parameters. 1770 lines (3540 residuals), 18 parameters: 1.044; 20
    lines, 18 parameters: 1.102. (The earlier fixed 1.5 passed noise 1.4x the declared
    level as "converged": review, session 36; compared with the rms directly, the chi2/dof
    limit was 4.0 instead of 2.2 at 20 lines: review of that change.)"""
    n = max(int(n_residuals), 1)
    dof = max(n - n_parameters, 1)
    return float(np.sqrt(dof / n * (1.0 + sigmas * np.sqrt(2.0 / dof))))


#: How far below and above its start a damping may go when the fit from the usual bounds
#: did not reach the noise (:func:`identify_frf`): the gap diagnosis' range (1e-4 and
#: ``GapOptions.damping_max``; appendix E's 0.8 N s/m up to 24 000 N s/m).
DAMPING_DOWN = 1e4
DAMPING_UP = 3e4

#: The decades of the damping scan, log10 of the factor on the start's dampings.
DAMPING_SCAN_DECADES = tuple(np.arange(-2.0, 4.51, 0.5))


def _damping_columns(problem: FrfProblem, values: np.ndarray, free_idx: np.ndarray
                     ) -> np.ndarray:
    """(n_free,) bool: the free parameters that enter the damping matrix only (their
    derivative of C is non-zero, of M and K zero), whatever their names."""
    mats = problem.assemble(values)
    out = np.zeros(free_idx.size, bool)
    for k, j in enumerate(free_idx):
        out[k] = (np.any(mats.dC[j] != 0) and not np.any(mats.dK[j] != 0)
                  and not np.any(mats.dM[j] != 0))
    return out


def _damping_decade_scan(ev: _Evaluator, x0: np.ndarray, damping: np.ndarray,
                         lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """``x0`` with its damping columns moved to the decade (common to all, then each on
    its own, once over) of :data:`DAMPING_SCAN_DECADES` with the least residual, within
    ``lo``..``hi``: dampings may lie decades from the start, and groups decades apart."""
    cols = np.flatnonzero(damping)

    def cost(x: np.ndarray) -> float:
        r = ev.residual(x)
        return float(r @ r) if np.all(np.isfinite(r)) else np.inf

    def moved(x: np.ndarray, which: np.ndarray, decade: float) -> np.ndarray:
        y = x.copy()
        y[which] = np.clip(x0[which] + decade * np.log(10), lo[which], hi[which])
        return y

    best_x, best_c = x0, cost(x0)
    for decade in DAMPING_SCAN_DECADES:
        y = moved(x0, cols, decade)
        c = cost(y)
        if c < best_c:
            best_x, best_c = y, c
    if cols.size > 1:
        for j in cols:
            for decade in DAMPING_SCAN_DECADES:
                y = moved(best_x, np.array([j]), decade)
                c = cost(y)
                if c < best_c:
                    best_x, best_c = y, c
    return best_x


def _solve_stage(ev: _Evaluator, x: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                 active: np.ndarray, strategy: Strategy | Stage) -> tuple[np.ndarray, object]:
    """least_squares over the ``active`` columns of x, the others held."""
    def full(z: np.ndarray) -> np.ndarray:
        y = x.copy()
        y[active] = z
        return y

    sol = least_squares(lambda z: ev.residual(full(z)),
                        np.clip(x[active], lo[active], hi[active]),
                        jac=lambda z: ev.jacobian(full(z))[:, active],
                        bounds=(lo[active], hi[active]), method="trf",
                        ftol=strategy.tol, xtol=strategy.tol, gtol=strategy.tol,
                        max_nfev=strategy.max_nfev)
    return full(sol.x), sol


def gain_floored_std(H: np.ndarray, H_std: np.ndarray, gain_std: float) -> np.ndarray:
    """The FRF fit's standard uncertainty per value (m/N): sqrt(H_std^2 + (gain_std |H|)^2)
    where ``H_std`` is known (finite, > 0); elsewhere ``H_std`` as it is (unknown: such
    values are left out of the fit). ``gain_std`` relative (:func:`identify_frf`)."""
    known = np.isfinite(H_std) & (H_std > 0)
    return np.where(known, np.sqrt(np.square(np.where(known, H_std, 0.0))
                                   + np.square(gain_std * np.abs(H))), H_std)


def weighted_chi2(problem: FrfProblem, frequency_hz: np.ndarray, H: np.ndarray,
                  H_std: np.ndarray, values: np.ndarray, *, gain_std: float = 0.0,
                  freq_dep: tuple[float, float] = (0.0, 0.0)) -> float:
    """sum |H_model - H|^2 / sigma^2 over the measured values with a known ``H_std``, sigma
    the FRF fit's weights (:func:`gain_floored_std`), at ``values`` (``problem``'s order)
    and ``freq_dep`` (f_k, f_c): the std misfit of :func:`identify_frf` at a given point,
    without fitting (identify compares candidate starts with it)."""
    H_model, _ = frf_with_jacobian(problem.assemble(values), problem.outputs, problem.inputs,
                                   frequency_hz, f_k=freq_dep[0], f_c=freq_dep[1],
                                   omega_max_rad_s=problem.omega_max_rad_s, jacobian=False)
    ok = np.isfinite(H) & np.isfinite(H_std) & (H_std > 0)
    sigma = gain_floored_std(H, H_std, gain_std)
    return float(np.sum(np.abs(H_model[ok] - H[ok]) ** 2 / np.square(sigma[ok])))


def one_blas_thread(fn: Callable) -> Callable:
    """Decorator: run ``fn`` inside :func:`single_blas_thread`."""
    @functools.wraps(fn)
    def wrapper(*args: object, **kwargs: object) -> object:
        with single_blas_thread():
            return fn(*args, **kwargs)

    return wrapper


@one_blas_thread
def identify_frf(
    problem: FrfProblem,
    frequency_hz: np.ndarray,
    H: np.ndarray,
    H_std: np.ndarray | None = None,
    *,
    free: Sequence[str] | None = None,
    start: np.ndarray | None = None,
    version_b: bool = False,
    start_freq_dep: tuple[float, float] = (0.0, 0.0),
    residual: ResidualSpec | None = None,
    strategy: Strategy | None = None,
    bounds_factor: float = 10.0,
    progress: Callable[[str], None] | None = None,
    gain_std: float = 0.0,
    chain_gain_std: float = 0.0,
) -> FitResult:
    """Identify the ``free`` parameters (default: all) of ``problem`` from measured FRFs.

    ``H`` (n_f, n_out, n_in) complex m/N with NaN where not measured; ``H_std`` optional.
    Physical parameters are bounded to [start / bounds_factor, start * bounds_factor].
    ``gain_std`` (relative, e.g. 0.003): standard uncertainty of each FRF's gain, an error
    of the measurement chain common to all lines of that FRF that ``H_std`` does not hold.
    When > 0 the std include it: one gain per FRF is a nuisance parameter with that prior,
    marginalised in the covariance; with the ``std`` residual it also enters the weights as
    a relative floor, sqrt(H_std^2 + (gain_std |H|)^2), so that lines measured far more
    precisely than the chain's gain is known do not rule the fit (only where H_std is
    known). Measured on simulated sessions (docs/identification.md): six demo sessions'
    std ~1.9x too small without it; face_up sessions not converged (chi2/dof 2.3-3.4) and
    their std 10-13x too small. With the floor the std are the sandwich covariance of
    that weighted fit under independent H_std plus the correlated gains
    (:func:`_sandwich_with_gains`): sum z^2 4-9 for 18 on the simulated chain, whose gains
    are below 0.003.
    ``chain_gain_std`` (relative): standard uncertainty of one gain common to every FRF, the
    drive chain's calibration (N/V: one shaker, amplifier and calibration drive every
    input); when > 0 marginalised in the std the same way. It is a common scale of the
    masses, stiffnesses and dampings, which the data cannot tell apart from the gain.
    Returns a :class:`FitResult` with values, standard errors and identifiability.
    """
    if not (np.isfinite(gain_std) and gain_std >= 0):
        raise ValueError(f"gain_std must be a finite relative uncertainty >= 0, got {gain_std}")
    if not (np.isfinite(chain_gain_std) and chain_gain_std >= 0):
        raise ValueError("chain_gain_std must be a finite relative uncertainty >= 0, got "
                         f"{chain_gain_std}")
    t0 = time.perf_counter()
    residual = residual or (ResidualSpec("std") if H_std is not None else ResidualSpec("log"))
    noise_std = None  # H_std before the gain floor: the covariance's independent noise
    if gain_std > 0 and H_std is not None and residual.kind == "std":
        noise_std = H_std
        # the gain error in the weights too, as a relative floor: with H_std alone the
        # simulated face_up sessions' 5-12.5 Hz lines (0.1-0.2 % gain errors, H_std
        # 0.002-0.02 %: 5-60 sigma) ruled the fit (chi2/dof 2.3-3.4, not converged,
        # sum z^2 1500-3100 for 18); with 0.003 chi2/dof 0.83-0.85, converged, z^2 10-13
        # only where H_std is known: a zero or NaN there means "unknown" and leaves the
        # line out (_Target); floored, such lines came back at the gain's weight alone
        # (half the lines zero: chi2/dof 979, k_io_R 4 % off: review of session 40)
        H_std = gain_floored_std(H, H_std, gain_std)
    strategy = strategy or Strategy()
    names = list(problem.names)
    free_names = list(free) if free is not None else names
    unknown = [n for n in free_names if n not in names]
    if unknown:
        raise ValueError(f"unknown parameter(s) {unknown}; the model has {names}")
    free_idx = np.array([names.index(n) for n in free_names], dtype=int)
    base = np.asarray(problem.nominal if start is None else start, dtype=float).copy()
    if np.any(base[free_idx] <= 0):
        # named: a model file with its dampings at 0 gave no clue which (review 66)
        bad = [names[i] for i in free_idx if base[i] <= 0]
        raise ValueError(f"start values of identified parameters must be positive: {bad} "
                         "are not (give them positive values in the model file, or leave "
                         "them out of the fit with --params)")
    mapping = _Mapping(free_idx, base, version_b, *start_freq_dep)
    x0 = mapping.pack(base, *start_freq_dep)
    nf = free_idx.size
    lo, hi = x0.copy(), x0.copy()
    lo[:nf] -= np.log(bounds_factor)
    hi[:nf] += np.log(bounds_factor)
    if version_b:
        # f_k = f_c = 0 (no frequency dependence) must be an interior point: a true value
        # on the bound stalled the trust region in measurements (ch. 7 cases 1-2)
        lo[nf:], hi[nf:] = -0.5, 5.0
        x0[nf:] = np.clip(x0[nf:], -0.5, 5.0)
    out_names = free_names + (list(FREQ_DEP_NAMES) if version_b else [])
    frequency_hz = np.asarray(frequency_hz, float)
    final_target = _Target.build(frequency_hz, H, H_std, residual)
    final = _Evaluator(problem, final_target, mapping, frequency_hz)
    evaluators: list[_Evaluator] = [final]
    stage_evs = []
    stages = list(strategy.stages)
    if version_b and strategy.hold_freq_dep_first:
        stages.append(Stage(None, 0.0))
    for st in stages:
        spec = ResidualSpec(st.kind, residual.a, residual.b) if st.kind else residual
        sl = slice(None, None, max(1, st.stride))
        tgt = _Target.build(frequency_hz[sl], H[sl], None if H_std is None else H_std[sl],
                            spec)
        ev = _Evaluator(problem, tgt, mapping, frequency_hz[sl], st.loss_factor)
        if st.groups is None:
            active = np.ones(x0.size, bool)
        else:
            active = np.array([any(n.startswith(g) for g in st.groups) for n in out_names])
        if version_b and strategy.hold_freq_dep_first:
            active[nf:] = False
        stage_evs.append((ev, active))
        evaluators.append(ev)
    all_active = np.ones(x0.size, bool)

    rng = np.random.default_rng(strategy.seed)
    best: tuple[float, np.ndarray, object] | None = None
    reproduced = False
    starts = 0
    stop = strategy.stop_rms
    if strategy.stop_at_noise_floor and residual.kind == "std":
        stop = noise_floor_rms(2 * int(final_target.mask.sum()), x0.size)
    for k in range(strategy.max_starts):
        starts += 1
        x = x0.copy()
        if k > 0:
            x[:nf] += rng.uniform(-1, 1, nf) * np.log1p(strategy.spread)
            if version_b:
                x[nf:] = rng.uniform(0.0, 1.0, 2)
            x = np.clip(x, lo, hi)
        skip_stages = strategy.alternate and k % 2 == 1
        for (ev, active), st in zip(stage_evs, stages, strict=True):
            if active.any() and not skip_stages:
                x, _ = _solve_stage(ev, x, lo, hi, active, st)
        x, sol = _solve_stage(final, x, lo, hi, all_active, strategy)
        r = final.residual(x)
        rms = float(np.sqrt(np.mean(r**2)))
        if progress:
            progress(f"start {k + 1}/{strategy.max_starts}: rms residual {rms:.3g}")
        if best is not None and abs(rms - best[0]) <= 1e-4 * best[0]:
            reproduced = True
        elif best is None or rms < best[0]:
            best, reproduced = (rms, x, sol), False
        if stop is not None and rms <= stop:
            break
        if strategy.stop_when_reproduced and reproduced:
            break
    assert best is not None
    start_rms = float(np.sqrt(np.mean(final.residual(x0) ** 2)))
    if (stop is not None and best[0] > stop) or start_rms < best[0]:
        # the continuation can lead away from a start already in the right basin: a
        # simulated demo session (sim seed 1) started at its own truth ended at rms 12.5
        # from every start, where the start fitted directly reaches the noise floor
        # (session 39). The given start is therefore also fitted without the
        # continuation when no start reached the target, and kept when it fits better;
        # and so it is when the start itself fits better than every start's fit, even one
        # at the target: a foreign file started at its truth (rms 0.984) ended at rms
        # 1.014, within the noise floor but 160 in chi2 worse, with k_pubh 6x the truth
        # (review 66)
        starts += 1
        x, sol = _solve_stage(final, x0.copy(), lo, hi, all_active, strategy)
        rms = float(np.sqrt(np.mean(final.residual(x) ** 2)))
        if progress:
            progress(f"the start fitted directly: rms residual {rms:.3g}")
        if rms < best[0] * (1 - 1e-4):
            best, reproduced = (rms, x, sol), False
    damping = _damping_columns(problem, base, free_idx)
    widened = False
    # a damping on the bound of its range is not fitted either, even where the misfit
    # reached the target: the range was too narrow (a set of judge-like subjects, damping
    # 11-26 N s/m from appendix E's 0.8, reached the noise floor with all three dampings on
    # their x10 bound and ended not converged without trying the wider range; a chain with
    # its damping x15-40 from the start likewise: 27 of 27 fits; session 44)
    stuck = np.isclose(best[1][:nf], lo[:nf], atol=1e-6) | np.isclose(best[1][:nf],
                                                                      hi[:nf], atol=1e-6)
    if damping.any() and ((stop is not None and best[0] > stop)
                          or bool(np.any(stuck & damping))):
        # Damping far from the start: the bounds (start x/÷ bounds_factor) hold appendix E's
        # 0.8 N s/m within 0.08-8, and a subject's 10-3000 N s/m was never reached (an
        # audit of judge-like sets: 0 of 19 converged, 700 % off, several dampings on the
        # bound; from a start within x2 of their damping 95 % converged, session 43).
        # Dampings then range from DAMPING_DOWN below to DAMPING_UP above the start, and
        # the fit starts again from the best of a scan over their decades (as the gap
        # diagnosis' base fit does), kept when it fits better.
        wide_lo, wide_hi = lo.copy(), hi.copy()
        wide_lo[:nf][damping] = x0[:nf][damping] - np.log(DAMPING_DOWN)
        wide_hi[:nf][damping] = x0[:nf][damping] + np.log(DAMPING_UP)
        x_scan = _damping_decade_scan(final, x0, damping, wide_lo, wide_hi)
        starts += 1
        x = x_scan.copy()
        for (ev, active), st in zip(stage_evs, stages, strict=True):
            if active.any():
                x, _ = _solve_stage(ev, x, wide_lo, wide_hi, active, st)
        x, sol = _solve_stage(final, x, wide_lo, wide_hi, all_active, strategy)
        rms = float(np.sqrt(np.mean(final.residual(x) ** 2)))
        if progress:
            progress(f"dampings scanned over decades and fitted within x/÷ "
                     f"{DAMPING_DOWN:g}-{DAMPING_UP:g}: rms residual {rms:.3g}")
        if rms < best[0] * (1 - 1e-4):
            best, reproduced = (rms, x, sol), False
            lo, hi, widened = wide_lo, wide_hi, True
    rms, x, sol = best
    r = final.residual(x)
    J = final.jacobian(x)
    values, f_k, f_c = mapping.unpack(x)
    out_values = np.concatenate([values[free_idx], [f_k, f_c] if version_b else []])
    # For linear parameters, std(log) must be read as absolute: pass 1.0 as "value".
    scale_vals = np.concatenate([values[free_idx], [1.0, 1.0] if version_b else []])
    dof = max(r.size - x.size, 1)
    chi2_per_dof = float(r @ r) / dof
    # With H_std the covariance is absolute, unless the misfit exceeds the noise: then the
    # std are scaled by sqrt(chi2/dof) (the Birge ratio) rather than kept at the declared
    # noise (they stayed at it whatever the misfit: review, session 36). Where the misfit
    # is model error this still does not make them right: the fit is then not converged,
    # and the message says why.
    absolute = residual.kind == "std" and chi2_per_dof <= 1.0
    cost = 0.5 * float(r @ r)
    on_bound = np.isclose(x, lo, atol=1e-6) | np.isclose(x, hi, atol=1e-6)
    bound_names = [n for n, b in zip(out_names, on_bound, strict=True) if b]
    # a parameter on its bound is not a minimum in it: no std of its own, and the others'
    # are those with it held there (its column left out of the Jacobian)
    inner = ~on_bound
    std = np.full(x.size, np.nan)
    corr = np.full((x.size, x.size), np.nan)
    if inner.any():
        std_in, corr_in, sv, weak = covariance_report(
            J[:, inner], r, [n for n, b in zip(out_names, inner, strict=True) if b],
            scale_vals[inner], absolute_sigma=absolute)
        std[inner] = std_in
        corr[np.ix_(inner, inner)] = corr_in
        if noise_std is not None:
            # the gain is in the weights (floor): the covariance of that estimator under
            # the noise it has, independent H_std per line plus correlated gains (the
            # augmented problem below counted the gain twice: std up to ~2x)
            sigma = np.where(final_target.mask, H_std, np.nan)[final_target.mask]
            rho = np.tile(noise_std[final_target.mask] / sigma, 2)
            std_g, corr_g = _sandwich_with_gains(
                final, x, J[:, inner], r, scale_vals[inner], absolute, gain_std,
                chain_gain_std, rho)
        elif gain_std > 0 or chain_gain_std > 0:
            std_g, corr_g = _with_gain_uncertainty(
                final, x, J[:, inner], r, [n for n, b in zip(out_names, inner, strict=True)
                                           if b], scale_vals[inner], absolute, gain_std,
                chain_gain_std)
        if gain_std > 0 or chain_gain_std > 0:
            # a direction unresolved without the gains stays so (NaN kept)
            std[inner] = np.where(np.isnan(std_in), np.nan, std_g)
            corr[np.ix_(inner, inner)] = np.where(np.isnan(corr_in), np.nan, corr_g)
    else:
        sv, weak = np.zeros(0), []
    reached = stop is None or rms <= stop
    r_white = r
    if gain_std > 0 and residual.kind == "std":
        # the chain's gain per FRF (within gain_std) is a constant offset along each FRF,
        # which the lag-1 test reads as structure: simulated face_up sessions fitted right
        # (|z| <= 1.8) were refused at lag-1 0.10-0.12 against 0.067, and 0.01-0.03 with
        # each FRF's gain removed (identify audit, session 43). The test runs on the
        # residual of the fit with those gains as parameters too, under their prior (the
        # residual is in units of its standard uncertainty): linearised at the fit, the
        # parameters re-adjusting with the gains (the gains' offsets alone, projected
        # out, left the part the parameters had bent to: lag-1 0.63 on a chain)
        G, _priors, _ = _gain_columns(final, x, gain_std, 0.0)
        if G.size:
            A = np.hstack([J, G])
            prior = np.hstack([np.zeros((G.shape[1], J.shape[1])),
                               np.eye(G.shape[1]) / gain_std])
            step = np.linalg.lstsq(np.vstack([A, prior]),
                                   np.concatenate([r, np.zeros(G.shape[1])]),
                                   rcond=None)[0]
            r_white = r - A @ step
    r1, pairs = residual_lag1_correlation(r_white, final_target.mask)
    # an exact fit's residual (relative rms 1e-8 and below) is rounding: not judged (with no
    # stop target it was: review of session 36's diff). For std residuals too, relative to
    # the data in the same weighting: exact data with an estimated noise fitted to 1.5e-11
    # sigma were "not converged" on one machine at rounding's lag-1 correlation 0.37, and
    # converged on another (session 48); in noise units alone an H_std overstated ~1e7x
    # would have hidden a real misfit (review 65)
    exact_rms = EXACT_FIT_RMS
    if residual.kind == "std":
        exact_rms *= float(np.sqrt(np.mean(np.abs(final_target.weight * final_target.H) ** 2)
                                   / 2.0))
    structured = (pairs >= MIN_WHITENESS_PAIRS and r1 > WHITENESS_SIGMAS / np.sqrt(pairs)
                  and rms > exact_rms)
    # Converged: the optimiser converged, no parameter on a bound, residuals without
    # structure along frequency, and the misfit reached the target or (without a noise
    # level) a second start reproduced the best minimum. With H_std (std residual) only
    # reaching the noise floor counts.
    confirmed = reached or (reproduced and residual.kind != "std")
    converged = (bool(getattr(sol, "status", 0) > 0) and not bound_names and confirmed
                 and not structured)
    msg = str(getattr(sol, "message", ""))
    if bound_names:
        ranges = (f"start x/÷ {bounds_factor:g}" + (
            f"; dampings /{DAMPING_DOWN:g} to x{DAMPING_UP:g}" if widened else ""))
        msg += f"; on the bound of its range ({ranges}): " + \
            ", ".join(bound_names) + " (std null; the others' std hold it there)"
    if not reached:
        msg += (f"; best rms residual {rms:.3g} above the target {stop:.3g} "
                + ("(reproduced by a second start: model error or noise)" if reproduced
                   else "(local minimum?)"))
    if structured:
        msg += (f"; residuals structured along frequency (lag-1 correlation {r1:.2f} over "
                f"{pairs} neighbour pairs; independent noise stays below "
                f"{WHITENESS_SIGMAS / np.sqrt(pairs):.2f}): model error or a local minimum, "
                "and the std, which assume independent residuals, are too small")
    return FitResult(
        names=out_names, values=out_values, std=std, correlation=corr, cost=cost,
        converged=converged, evaluations=sum(e.evaluations for e in evaluators),
        wall_time_s=time.perf_counter() - t0, residual_kind=residual.kind,
        singular_values=sv, weak_directions=weak, starts=starts, message=msg,
        extra={"rms_residual": rms, "best_reproduced": reproduced,
               "chi2_per_dof": chi2_per_dof if residual.kind == "std" else None,
               "residual_whiteness": {"lag1_correlation": _nan_to_none(r1),
                                      "pairs": int(pairs),
                                      "structured": bool(structured)},
               "on_bound": bound_names},
    )


def frequency_dependence_test(
    problem: FrfProblem,
    frequency_hz: np.ndarray,
    H: np.ndarray,
    H_std: np.ndarray,
    fit: FitResult,
    *,
    start_freq_dep: tuple[float, float] = (0.0, 0.0),
    gain_std: float = 0.0,
    p_limit: float = FREQUENCY_DEPENDENCE_P,
) -> dict[str, object]:
    """Whether frequency-dependent stiffness and damping (version B, thesis eq. 7.1-7.3:
    K + w K', K' = f_k K / (4 w_max), and i D, D = f_c C w_max / 4) explain part of the
    misfit of ``fit``, a version-A fit (f_k, f_c held at ``start_freq_dep``) of the same
    data with the ``std`` residual (each value divided by its standard uncertainty).

    Version B is fitted once, from ``fit``'s values with f_k, f_c released (its minimum
    can only lie at or below version A's, which it contains), and the drop in chi2 is
    judged by an F test on 2 and dof_B degrees of freedom: F = (delta chi2 / 2) /
    s2, s2 = max(chi2_B / dof_B, 1), i.e. the declared noise, or the misfit where that
    is larger (the lack of fit then counts as noise and the test is conservative).
    Why: a version-A fit of frequency-dependent data can reach the noise floor with
    white residuals, converged, while its parameters carry the model error (judge-like
    sets with f_k 0.7-1.1: chi2/dof 1.05-1.10 under the floor, k_pubh at 30 std; session
    44). The fit from version A's minimum takes 0.1-0.2 s on a 15-FRF pelvis file.

    Returns ``{"delta_chi2", "f_statistic", "dof", "p_value", "significant", "p_limit",
    "f_k", "f_c", "chi2_per_dof", "at_noise_floor"}`` (f_k, f_c, chi2_per_dof: version B's
    fit; ``significant``: ``p_value < p_limit``; ``at_noise_floor``: version B's misfit
    within :func:`noise_floor_rms`).
    """
    from scipy.stats import f as f_dist

    if fit.residual_kind != "std":
        raise ValueError("the frequency-dependence test needs a fit with the std residual "
                         f"(the misfit in units of the noise), not {fit.residual_kind!r}")
    if any(n in FREQ_DEP_NAMES for n in fit.names):
        raise ValueError("the frequency-dependence test takes a version-A fit; this one "
                         "fitted f_k, f_c already")
    names = list(problem.names)
    start = np.asarray(problem.nominal, dtype=float).copy()
    for name, value in zip(fit.names, fit.values, strict=True):
        start[names.index(name)] = value
    extended = identify_frf(
        problem, frequency_hz, H, H_std, free=list(fit.names), start=start, version_b=True,
        start_freq_dep=start_freq_dep, residual=ResidualSpec("std"),
        # one start from version A's minimum, without the continuation: version B's
        # minimum near it is the question, not a global search
        strategy=Strategy(max_starts=1, hold_freq_dep_first=False), gain_std=gain_std)
    chi2_a, chi2_b = 2.0 * fit.cost, 2.0 * extended.cost
    delta = max(chi2_a - chi2_b, 0.0)
    # the std residual's values: real and imaginary part of each line with a known H_std
    measured = np.isfinite(H) & np.isfinite(H_std) & (H_std > 0)
    dof = max(2 * int(measured.sum()) - len(extended.names), 1)
    s2 = max(chi2_b / dof, 1.0)
    f_statistic = delta / 2.0 / s2
    p_value = float(f_dist.sf(f_statistic, 2, dof))
    floor = noise_floor_rms(dof + len(extended.names), len(extended.names))
    return {"delta_chi2": float(delta), "f_statistic": float(f_statistic), "dof": int(dof),
            "p_value": p_value, "p_limit": float(p_limit),
            "significant": bool(p_value < p_limit),
            "f_k": float(extended.values[-2]), "f_c": float(extended.values[-1]),
            "chi2_per_dof": float(chi2_b / dof),
            "at_noise_floor": bool(float(extended.extra["rms_residual"]) <= floor)}


#: Δχ² at the ends of a one-parameter 95 % profile interval (the χ²₁ 0.95 quantile).
PROFILE_DELTA_CHI2_95 = 3.841458820694124

#: A parameter counts as weak, and ``pelvislab identify --profile weak`` profiles it, when its
#: linearised std is at least this fraction of its value (or undetermined): there the
#: linearisation behind ``std`` and ``interval_95`` is least trusted (calibration audit,
#: session 43: std/value 0.2-0.3 had skewed z).
PROFILE_WEAK_REL = 0.1


def weak_parameters(fit: FitResult, rel: float = PROFILE_WEAK_REL) -> list[str]:
    """The masses, springs and dampings of ``fit`` whose std is at least ``rel`` of their
    value or undetermined (null), those on a bound of their range excepted (no minimum in
    them to profile)."""
    on_bound = set(fit.extra.get("on_bound", ()))
    return [n for n, v, s in zip(fit.names, fit.values, fit.std, strict=True)
            if n not in FREQ_DEP_NAMES and n not in on_bound
            and not (np.isfinite(s) and s < rel * abs(v))]


def profile_parameter(
    problem: FrfProblem,
    frequency_hz: np.ndarray,
    H: np.ndarray,
    H_std: np.ndarray,
    fit: FitResult,
    name: str,
    *,
    start_freq_dep: tuple[float, float] = (0.0, 0.0),
    gain_std: float = 0.0,
    max_steps: int = 8,
    stop_delta_chi2: float = 25.0,
    progress: Callable[[str], None] | None = None,
) -> dict[str, object]:
    """Profile likelihood of one mass, spring or damping ``name`` of ``fit`` (an FRF fit of
    the same data with the ``std`` residual): the χ² with ``name`` held at values walked
    out from the fitted one in equal steps of log p, every other free parameter of the fit
    (f_k, f_c too in version B) refitted from its neighbour's point, one start each.

    Why: ``std`` and ``interval_95`` are the linearisation at the minimum, and the thesis'
    optimiser was not to be trusted (ch. 6-7). A fit may stop in one of two minima the
    data hold alike (calibration audit, session 43: c_pub 102 N s/m for a true 457, at the
    noise floor, the truth's minimum 14 higher in χ², not covered by the std); the profile
    shows such a second minimum and a minimum *below* the fit's (the fit is then not the
    best one), and gives the interval where Δχ² stays within
    :data:`PROFILE_DELTA_CHI2_95` (Venzon & Moolgavkar 1988's profile interval) without the
    linearisation. Δχ² is scaled by max(χ²/dof, 1) of ``fit`` (the misfit counts as noise
    where it exceeds the declared one, as the std's Birge ratio does). The profile is
    conditional on the chain's gains: ``gain_std`` enters the weights as in the fit, but
    the per-FRF gains and a calibration common to all FRFs are not marginalised as the
    std's are (``identify_frf(gain_std=, chain_gain_std=)``), so with a sizeable
    calibration uncertainty it is narrower than the std's interval for that reason alone.
    The refits' bounds are ×/÷ 10 around each start (their neighbour's point): the walk
    may take the others beyond the fit's own range; a fit with a parameter on its bound
    is not profiled by ``pelvislab identify`` (its first refit would release it).

    The step is the linearised std(log p), within 1e-4-0.5 (0.25 where the std is
    undetermined); the walk goes ``max_steps`` steps each way and stops earlier where Δχ²
    passes ``stop_delta_chi2`` (25: five standard deviations; far enough to pass a barrier
    to a second minimum such as the audit's, 14 above) or the parameter leaves
    1e-6..1e6 × its fitted value. Returns ``{"values", "delta_chi2"}`` (ascending in the
    value, the fit's own point included at 0), ``"interval_95"`` ([low, high], an end null
    where the walk did not reach the limit), ``"linearised_interval_95"``,
    ``"lower_minimum"`` (the lowest point when Δχ² < -:data:`PROFILE_LOWER_TOL` there,
    with every parameter's value there, ``"parameters"``; ``interval_95`` is then [None,
    None]; else None), ``"second_minimum"`` (the lowest local minimum of the profile
    apart from the fit's own, at least :data:`PROFILE_BARRIER` below the highest point on
    each side of it, with its Δχ²; one within the limit lies inside ``interval_95``; None
    when there is none or a lower minimum) and ``"fits"``. A refit the model cannot be
    evaluated at ends the walk (that side's end is then null, as where the walk ended
    within the limit: the data say nothing beyond it).
    """
    if fit.residual_kind != "std":
        raise ValueError("the profile needs a fit with the std residual (chi2 in units of "
                         f"the noise), not {fit.residual_kind!r}")
    if name in FREQ_DEP_NAMES or name not in fit.names:
        choices = ", ".join(n for n in fit.names if n not in FREQ_DEP_NAMES)
        raise ValueError(f"cannot profile {name!r}: choose one of the fit's masses, springs "
                         f"and dampings ({choices})")
    names = list(problem.names)
    fitted = dict(zip(fit.names, fit.values, strict=True))
    version_b = "f_k" in fitted
    free = [n for n in fit.names if n not in FREQ_DEP_NAMES and n != name]
    start = np.asarray(problem.nominal, dtype=float).copy()
    for n in fit.names:
        if n not in FREQ_DEP_NAMES:
            start[names.index(n)] = fitted[n]
    freq_dep = (fitted["f_k"], fitted["f_c"]) if version_b else start_freq_dep
    value = fitted[name]
    std = float(fit.std[fit.names.index(name)])
    step = float(np.clip(std / value, 1e-4, 0.5)) if np.isfinite(std) else 0.25
    chi2_best = 2.0 * fit.cost
    measured = np.isfinite(H) & np.isfinite(H_std) & (H_std > 0)
    dof = max(2 * int(measured.sum()) - len(fit.names), 1)
    scale = max(chi2_best / dof, 1.0)
    points: list[tuple[float, float, dict[str, float]]] = [(value, 0.0, dict(fitted))]
    fits = 0
    for direction in (-1.0, 1.0):
        here, dep = start.copy(), freq_dep
        for k in range(1, max_steps + 1):
            held = value * float(np.exp(direction * k * step))
            if not 1e-6 < held / value < 1e6:
                break
            here[names.index(name)] = held
            refit = identify_frf(
                problem, frequency_hz, H, H_std, free=free, start=here, version_b=version_b,
                start_freq_dep=dep, residual=ResidualSpec("std"),
                # from the neighbour's point, no continuation: the profile near the fit is
                # the question, not a global search
                strategy=Strategy(max_starts=1, hold_freq_dep_first=False), gain_std=gain_std)
            fits += 1
            delta = (2.0 * refit.cost - chi2_best) / scale
            if not np.isfinite(delta):
                break  # the model could not be evaluated there: the walk ends
            refitted = dict(zip(refit.names, refit.values, strict=True))
            points.append((held, float(delta), {**refitted, name: held}))
            if progress:
                progress(f"profile of {name}: {held:.4g} -> delta chi2 {delta:.3g}")
            for n in free:
                here[names.index(n)] = refitted[n]
            if version_b:
                dep = (refitted["f_k"], refitted["f_c"])
            if delta > stop_delta_chi2:
                break
    points.sort(key=lambda p: p[0])
    summary = profile_summary(np.array([p[0] for p in points]),
                              np.array([p[1] for p in points]), value)
    if summary["lower_minimum"] is not None:
        # every parameter there, so that the fit can be started from that point
        lowest = next(p for p in points if p[0] == summary["lower_minimum"]["value"])
        summary["lower_minimum"]["parameters"] = {n: float(v) for n, v in lowest[2].items()}
    return {**summary, "linearised_interval_95": interval_95(name, value, std),
            "fits": fits}


def profile_summary(values: np.ndarray, delta_chi2: np.ndarray, fitted: float
                    ) -> dict[str, object]:
    """What a profile likelihood says (:func:`profile_parameter`): ``values`` ascending (SI,
    > 0), ``delta_chi2`` the χ² rise at each over the fit's, ``fitted`` the fit's own value
    (the point of ``values`` nearest to it in log value, at Δχ² 0). Returns ``{"values",
    "delta_chi2", "interval_95", "lower_minimum", "second_minimum"}`` as
    :func:`profile_parameter` describes them."""
    values, deltas = np.asarray(values, float), np.asarray(delta_chi2, float)
    keep = np.isfinite(deltas)  # a point the model could not be evaluated at says nothing
    values, deltas = values[keep], deltas[keep]
    # the fit's own point (the nearest in log value: not only its bit-exact value)
    i0 = int(np.argmin(np.abs(np.log(values) - np.log(fitted))))
    lowest = int(np.argmin(deltas))
    lower = ({"value": float(values[lowest]), "delta_chi2": float(deltas[lowest])}
             if deltas[lowest] < -PROFILE_LOWER_TOL else None)
    second = None
    # a second minimum is one above the fit's: below it, it is the lower minimum (review 60)
    for i in range(1, values.size - 1) if lower is None else ():
        if abs(i - i0) <= 1 or not (deltas[i] < deltas[i - 1] and deltas[i] < deltas[i + 1]):
            continue
        # a local minimum apart from the fit's, behind a barrier of at least
        # PROFILE_BARRIER on both sides (a flat profile's ripples of a few 0.01 are the
        # refits' tolerance, not minima: review 59)
        between = deltas[min(i, i0):max(i, i0) + 1]
        beyond = deltas[i + 1:] if i > i0 else deltas[:i]
        if (between.max() - deltas[i] >= PROFILE_BARRIER
                and beyond.max() - deltas[i] >= PROFILE_BARRIER
                and (second is None or deltas[i] < second["delta_chi2"])):
            second = {"value": float(values[i]), "delta_chi2": float(deltas[i])}
    # an interval about a minimum the profile went below is no 95 % interval: none given
    interval = ([None, None] if lower is not None else
                [_profile_end(values, deltas, i0, -1), _profile_end(values, deltas, i0, 1)])
    return {"values": [float(v) for v in values], "delta_chi2": [float(d) for d in deltas],
            "interval_95": interval, "lower_minimum": lower, "second_minimum": second}


#: Δχ² below which a profile point counts as a lower minimum than the fit's (a rounding
#: margin: the refits stop at a relative tolerance).
PROFILE_LOWER_TOL = 0.05

#: Δχ² a second minimum of a profile must lie below the highest point on each side of it.
PROFILE_BARRIER = 1.0


def _profile_end(values: np.ndarray, deltas: np.ndarray, i0: int, direction: int
                 ) -> float | None:
    """The end of the 95 % profile interval on one side (``direction`` -1: below the fit's
    point at index ``i0``, +1: above): where the profile rises through
    :data:`PROFILE_DELTA_CHI2_95` beyond the outermost point still within it (a second
    minimum within the limit is inside), interpolated between the two points linearly in
    sqrt(Δχ²) against log value (exact where the profile is the parabola the linearised
    std assume: linear in Δχ² it put the end of a well-determined mass, 120 above the
    limit one step out, 5.6x too close: review 59); None when the walk ended within the
    limit (the end lies further out)."""
    side = range(i0, values.size) if direction > 0 else range(i0, -1, -1)
    inside = [i for i in side if deltas[i] <= PROFILE_DELTA_CHI2_95]
    i = inside[-1]
    j = i + direction
    if not 0 <= j < values.size:
        return None
    r0, r1 = np.sqrt(max(deltas[i], 0.0)), np.sqrt(deltas[j])
    t = (np.sqrt(PROFILE_DELTA_CHI2_95) - r0) / (r1 - r0) if r1 > r0 else 1.0
    return float(np.exp(np.log(values[i]) + t * (np.log(values[j]) - np.log(values[i]))))
