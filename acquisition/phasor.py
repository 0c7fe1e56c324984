"""Phasor of a measured harmonic motion at the drive frequency (thesis ch. 8.3).

Convention (design 4.1): ``x(t) = Re(X e^{+i w t})``, ``X`` the PEAK amplitude, ``t = 0`` the
origin of ``time_s`` (pass times since the step's first pulse: the phasor then refers to the
first pulse, design 4.2).

* Coherent DFT when the record holds an integer number of drive periods and is uniformly
  sampled without gaps (the thesis' "clean FFT", ch. 8.3): ``X_h = 2/N sum x_k e^{-i h w t_k}``.
* Otherwise (or with gaps from lost echoes, or ``detrend``) the least-squares sine fit of
  IEEE Std 1057 with known frequency (the "3-parameter" fit: offset, cosine and sine
  amplitudes), extended with the 2nd and 3rd harmonics and optionally a linear trend, solved
  by the normal equations (``scipy.linalg.pinvh``).

Standard uncertainties come from the residual (white-noise model): covariance
``s^2 (A^T A)^-1`` with ``s^2 = |r|^2 / (N - p)``. ``std`` is the standard uncertainty of the
complex value, ``sqrt(E|X_hat - X|^2)``; amplitude and phase uncertainties are first-order
propagations of the same covariance.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import linalg


@dataclass(frozen=True)
class Phasor:
    """Complex amplitude of one frequency component with its uncertainty and distortion.

    value: X (peak, signal units) with x(t) = Re(X e^{i 2 pi f t}).
    std: sqrt(E|X_hat - X|^2), same units. amplitude_std, phase_std_rad: of |X| and arg X.
    harmonics: X_2, X_3 (NaN when at or above Nyquist or not fitted).
    distortion: |X_2|/|X_1|, |X_3|/|X_1| (2nd, 3rd harmonic distortion; nonlinearity
    indicator). thd: sqrt(|X_2|^2 + |X_3|^2)/|X_1|.
    offset: mean level; residual_rms: RMS of what the model leaves; n_used: samples used;
    method: "dft" or "lsq".
    """

    frequency_hz: float
    value: complex
    std: float
    amplitude_std: float
    phase_std_rad: float
    harmonics: np.ndarray
    harmonics_std: np.ndarray
    distortion: np.ndarray
    thd: float
    offset: float
    residual_rms: float
    n_used: int
    method: str

    @property
    def amplitude(self) -> float:
        """|X|, peak amplitude."""
        return float(abs(self.value))

    @property
    def phase_rad(self) -> float:
        """arg X in (-pi, pi]."""
        return float(np.angle(self.value))


def _is_integer_periods(t: np.ndarray, frequency_hz: float) -> bool:
    n = t.size
    if n < 8:
        return False
    dt = np.diff(t)
    step = (t[-1] - t[0]) / (n - 1)
    if step <= 0 or not np.allclose(dt, step, rtol=1e-6, atol=0.0):
        return False
    periods = n * step * frequency_hz
    return bool(abs(periods - np.rint(periods)) < 1e-6 * max(1.0, periods) and periods >= 1)


def estimate_phasor(signal: np.ndarray, time_s: np.ndarray, frequency_hz: float, *,
                    n_harmonics: int = 3, detrend: bool = False,
                    method: str = "auto") -> Phasor:
    """Phasor of ``signal`` at ``frequency_hz`` (and its harmonics), referred to ``t = 0``.

    signal: (N,) samples (NaN = missing; they are dropped). time_s: (N,) sample times (s).
    n_harmonics: highest harmonic estimated (1 = pure 3-parameter fit; default 3).
    detrend: also fit a linear trend (slow drift would otherwise leak into the line).
    method: "auto" (DFT when coherent and complete, else least squares), "dft" or "lsq".
    """
    x = np.asarray(signal, dtype=float).reshape(-1)
    t = np.asarray(time_s, dtype=float).reshape(-1)
    if x.size != t.size:
        raise ValueError(f"signal has {x.size} samples but time_s has {t.size}")
    if not frequency_hz > 0:
        raise ValueError(f"frequency_hz must be positive, got {frequency_hz}")
    if method not in ("auto", "dft", "lsq"):
        raise ValueError(f"method must be 'auto', 'dft' or 'lsq', got {method!r}")
    ok = np.isfinite(x) & np.isfinite(t)
    complete = bool(ok.all())
    x, t = x[ok], t[ok]
    n = x.size
    n_harmonics = max(1, int(n_harmonics))
    if n < 2 * n_harmonics + 2 + int(detrend):
        raise ValueError(f"only {n} valid samples: too few for a phasor fit")
    span = t.max() - t.min()
    # Nyquist of the (mean) sampling rate: harmonics at or above it are not estimable.
    nyquist = 0.5 * (n - 1) / span if span > 0 else 0.0
    orders = [h for h in range(1, n_harmonics + 1) if h * frequency_hz < nyquist * (1 - 1e-9)]
    if 1 not in orders:
        raise ValueError(f"{frequency_hz} Hz is at or above the Nyquist frequency "
                         f"{nyquist:.6g} Hz of the samples")
    coherent = complete and _is_integer_periods(t, frequency_hz)
    if method == "dft" and not coherent:
        raise ValueError("DFT needs complete, uniform samples spanning an integer number of "
                         "periods; use method='lsq'")
    use_dft = coherent and not detrend and method != "lsq"

    w = 2.0 * np.pi * frequency_hz
    cols = [np.ones(n)]
    if detrend:
        cols.append((t - t.mean()) / max(span, 1e-30))
    first = len(cols)
    for h in orders:
        cols += [np.cos(h * w * t), np.sin(h * w * t)]
    A = np.column_stack(cols)
    p = A.shape[1]
    if use_dft:
        # Orthogonal columns over whole periods: the LS solution is the coherent DFT.
        coef = np.empty(p)
        coef[0] = x.mean()
        coef[first:] = (2.0 / n) * (A[:, first:].T @ x)
        gram_inv = np.diag(np.r_[1.0 / n, np.full(p - 1, 2.0 / n)])
    else:
        # Normal equations: the columns are near-orthogonal (cond(A) ~ 1 over a period or
        # more), and this small solve avoids LAPACK's threaded least-squares drivers, which
        # were measured 100x slower than single-threaded on a loaded 2-core machine.
        gram_inv = linalg.pinvh(A.T @ A)
        coef = gram_inv @ (A.T @ x)
    resid = x - A @ coef
    dof = max(n - p, 1)
    s2 = float(resid @ resid) / dof
    cov = s2 * gram_inv

    values, stds, amp_std, ph_std = [], [], 0.0, 0.0
    for i, _h in enumerate(orders):
        j = first + 2 * i
        a, b = coef[j], coef[j + 1]
        c = cov[j: j + 2, j: j + 2]
        X = complex(a, -b)  # Re((a - i b) e^{iwt}) = a cos + b sin
        values.append(X)
        stds.append(float(np.sqrt(max(c[0, 0] + c[1, 1], 0.0))))
        if i == 0:
            mag = abs(X)
            if mag > 0:
                g_amp = np.array([a, b]) / mag
                g_ph = np.array([b, -a]) / mag**2  # d/da, d/db of atan2(-b, a)
                amp_std = float(np.sqrt(max(g_amp @ c @ g_amp, 0.0)))
                ph_std = float(np.sqrt(max(g_ph @ c @ g_ph, 0.0)))
            else:
                amp_std, ph_std = stds[0] / np.sqrt(2.0), np.pi
    harm = np.full(2, np.nan + 0j)
    harm_std = np.full(2, np.nan)
    for i, h in enumerate(orders[1:], start=1):
        if h <= 3:
            harm[h - 2], harm_std[h - 2] = values[i], stds[i]
    X1 = values[0]
    with np.errstate(divide="ignore", invalid="ignore"):
        dist = np.abs(harm) / abs(X1) if abs(X1) > 0 else np.full(2, np.nan)
    # NaN, not 0, when no harmonic is estimable (all at or above Nyquist): 0 read as "no
    # distortion" whatever the motion held (review, session 36)
    thd = (float(np.sqrt(np.nansum(np.abs(harm) ** 2)) / abs(X1))
           if abs(X1) > 0 and np.isfinite(harm).any() else np.nan)
    return Phasor(
        frequency_hz=float(frequency_hz), value=X1, std=stds[0], amplitude_std=amp_std,
        phase_std_rad=ph_std, harmonics=harm, harmonics_std=harm_std, distortion=dist,
        thd=thd, offset=float(coef[0]), residual_rms=float(np.sqrt(np.mean(resid**2))),
        n_used=n, method="dft" if use_dft else "lsq")


def phase_difference_deg(reference: Phasor, other: Phasor) -> tuple[float, float]:
    """Phase of ``other`` relative to ``reference`` in degrees, (-180, 180], and its std.

    As in thesis table 8.1 (phase shift between the two transducers' displacements): negative
    means ``other`` lags ``reference``. The std combines both phasors' phase uncertainties
    (independent channels).
    """
    if reference.frequency_hz != other.frequency_hz:
        raise ValueError(f"phasors at different frequencies: {reference.frequency_hz} Hz "
                         f"and {other.frequency_hz} Hz")
    diff = float(np.degrees(np.angle(other.value * np.conj(reference.value))))
    if diff == -180.0:
        diff = 180.0
    std = float(np.degrees(np.hypot(reference.phase_std_rad, other.phase_std_rad)))
    return diff, std
