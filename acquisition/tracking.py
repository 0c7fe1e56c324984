"""Echo time-of-flight tracking: raw segmented echo records to bone displacement (thesis ch. 8.3).

Each transducer fires N pulses; the digitizer stores one segment per pulse. The bone echo's
arrival time changes as the bone moves; the change relative to the first pulse, times half the
speed of sound, is the displacement (thesis 8.2: ``d = c * dt / 2``).

Conventions (docs/tracking.md has the full derivation):

* **Timing.** Sample ``n`` of segment ``k`` holds the signal at ``delay_s +
  trigger_offset_s[k] + n / sample_rate_hz`` after that segment's trigger (the pulser fires at
  the trigger). ``trigger_offset_s`` is the digitizer's per-segment ``horPos``: the time from
  the trigger to the first sample (Acqiris reports it in ``[-1/fs, 0]``). An echo found ``m``
  samples into segment ``k`` therefore arrived at ``m / fs + trigger_offset_s[k] + delay_s``.
* **Sign.** ``displacement_m[k] = -c/2 * (t_k - t_0)``: an echo that arrives earlier than the
  first pulse's echo means the bone moved TOWARD the transducer, which is positive (design 4.1).

Method (all echoes at once, no Python loop per echo):

1. gate on the strongest echo envelope (the bone; override with ``TrackingOptions.gate``);
2. reference = mean of the first echoes, then the mean of all echoes aligned on a first
   (coarse) pass — far less noisy than the single first echo the thesis correlated with;
3. band-pass prefilter (Butterworth, ``scipy.signal``) applied zero-phase to the reference
   only: correlating raw echoes with the ``|H|^2``-filtered reference equals correlating
   filtered echoes with the filtered reference, at no per-echo cost;
4. cross-correlation over a bounded lag range as a matrix product of the echo windows with a
   Toeplitz matrix of shifted references (measured faster than FFT correlation, bench);
5. sub-sample peak: cosine fit through the three correlation samples around the peak
   (default; chosen by measurement over parabolic, cubic-spline and analytic-phase estimators:
   lowest jitter, bias < 0.001 sample down to 20 samples per carrier period, docs/tracking.md);
6. quality per echo; echoes leaving the lag range make the gate follow the echo (per-echo
   offsets from a sparse whole-record search); a change of echo shape along the record
   triggers block-wise re-referencing; echoes that cannot be tracked are NaN and ``lost``.
"""

from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from scipy import fft as sp_fft
from scipy import interpolate, signal

ESTIMATORS = ("cosine", "parabolic", "spline", "phase")
#: A segment's trigger offset further than this from the record's median (in samples) is a
#: misread timing: its echo is marked lost (the Acqiris reports sub-sample offsets; the
#: tests use up to 3 samples of spread).
MAX_OFFSET_SPREAD_SAMPLES = 8.0


@dataclass(frozen=True)
class TrackingOptions:
    """Settings of :func:`track_echoes`; defaults sized for the thesis set-up (ch. 8.3: 5 MHz
    transducers, 500 MS/s), the method itself is ours (the thesis correlated each echo with
    the first one and interpolated the peak).

    gate: (start, stop) sample indices of the bone echo window; None = automatic (strongest
        envelope, extended down to ``gate_threshold`` of its peak plus ``gate_margin_samples``).
    max_lag_samples: half-width of the correlation lag range (samples). At 500 MS/s and
        1540 m/s one sample is 1.54 um of displacement.
    band_hz: prefilter pass band (Hz); None = 0.4 to 1.6 times the echo's centre frequency.
    estimator: sub-sample peak estimator, one of ``ESTIMATORS``.
    reference_iterations: number of aligned-average reference rebuilds (0 = mean of the first
        ``initial_reference_echoes`` echoes only).
    min_correlation: echoes whose correlation coefficient is below this are ``lost``.
    rereference: follow drift beyond the lag range, and rebuild the reference block-wise when
        the echo changes shape (else echoes outside the lag range are lost).
    block_size: echoes per block when re-referencing (and per end in the shape check).
    hop_threshold_periods: a delay jump from its neighbours' median larger than this fraction
        of the carrier period is a peak hop.
    min_in_record: an echo that moved so far that less than this fraction of its energy (the
        reference's, at its delay) is inside the record has left the recorded window: lost.
    """

    gate: tuple[int, int] | None = None
    min_in_record: float = 0.7
    gate_threshold: float = 0.1
    gate_margin_samples: int = 5
    max_lag_samples: int = 12
    band_hz: tuple[float, float] | None = None
    filter_order: int = 4
    estimator: str = "cosine"
    reference_iterations: int = 1
    initial_reference_echoes: int = 8
    min_correlation: float = 0.5
    rereference: bool = True
    block_size: int = 32
    hop_threshold_periods: float = 0.25
    coarse_lag_step: int = 4

    def __post_init__(self) -> None:
        # a value outside these ranges loses every echo or means nothing; say so at once
        # rather than after reprocessing a whole session into NaN
        ranges = {"min_in_record": (0.0, 1.0), "gate_threshold": (0.0, 1.0),
                  "min_correlation": (0.0, 1.0), "hop_threshold_periods": (0.0, 10.0)}
        for name, (low, high) in ranges.items():
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value)
                    and low < value <= high) and not (name == "min_correlation"
                                                      and value == 0.0):
                raise ValueError(f"tracking option {name} = {value!r}: must be within "
                                 f"({low:g}, {high:g}]")
        minima = {"gate_margin_samples": 0, "max_lag_samples": 1, "filter_order": 1,
                  "reference_iterations": 0, "initial_reference_echoes": 1,
                  "block_size": 4, "coarse_lag_step": 1}
        for name, low in minima.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ValueError(f"tracking option {name} = {value!r}: must be an integer "
                                 f">= {low}")
        if self.estimator not in ESTIMATORS:
            raise ValueError(f"tracking option estimator = {self.estimator!r}: one of "
                             f"{list(ESTIMATORS)}")
        if self.gate is not None and not (
                len(self.gate) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) for v in self.gate)
                and 0 <= self.gate[0] < self.gate[1]):
            raise ValueError(f"tracking option gate = {self.gate!r}: must be (start, stop) "
                             "sample indices with 0 <= start < stop")
        if self.band_hz is not None and not (
                len(self.band_hz) == 2
                and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                        and math.isfinite(v) for v in self.band_hz)
                and 0 < self.band_hz[0] < self.band_hz[1]):
            raise ValueError(f"tracking option band_hz = {self.band_hz!r}: must be "
                             "(low, high) in Hz with 0 < low < high")


@dataclass
class TrackingResult:
    """Displacement and per-echo quality of one channel's record.

    displacement_m: (n,) bone displacement relative to pulse 0, m, positive toward the
        transducer; NaN where ``lost``.
    delay_s: (n,) echo arrival time minus pulse 0's (trigger offsets applied), s.
    gate: (start, stop) samples of the initial bone-echo window.
    correlation: (n,) correlation coefficient of each echo with the reference (0..1).
    snr_db: (n,) 20 log10(echo peak amplitude / residual noise SD), per echo.
    peak_hops: (n,) True where the correlation peak jumped to another carrier lobe (the
        value was re-picked on the lobe nearest the neighbours; the flag stays).
    lost: (n,) True where the echo could not be tracked (left the record or the gate, or
        correlation below ``min_correlation``).
    gate_shift_samples: (n,) how far the gate followed the echo (re-referencing), samples.
    n_rereferences: how many times the reference was rebuilt to follow drift.
    center_frequency_hz: the echo's mean frequency after the prefilter.
    echo_amplitude_v: peak envelope of the (filtered) reference echo, volts.
    clipped: (n,) True where the echo peak reached the digitizer's code limits (integer
        codes only; clipping distorts the echo: lower the receiver gain).
    warnings: what went wrong or was corrected, in words (empty when all is well).
    echo_time_s: mean arrival time of the bone echo after the record's first sample, s (the
        gate's centre plus the mean tracked delay, trigger offsets included); with the
        record delay it gives the round trip, half of which is when each pulse samples the
        bone (:func:`pelvislab.acquisition.frf_lines.bone_sampling_delay_s`).
    """

    displacement_m: np.ndarray
    delay_s: np.ndarray
    gate: tuple[int, int]
    correlation: np.ndarray
    snr_db: np.ndarray
    peak_hops: np.ndarray
    lost: np.ndarray
    gate_shift_samples: np.ndarray
    n_rereferences: int
    center_frequency_hz: float
    sample_rate_hz: float
    speed_of_sound_m_s: float
    estimator: str
    echo_amplitude_v: float = float("nan")
    clipped: np.ndarray | None = None
    warnings: list[str] = field(default_factory=list)
    echo_time_s: float = float("nan")


# --------------------------------------------------------------------------------------------
# Reference waveform


@dataclass
class _Reference:
    """A filtered reference echo (gate length) and what the correlation needs from it.

    ``q_hilbert`` and ``raw_env_peak`` are computed when first used (the first-pass reference
    of a normal record never needs them): from the rfft spectra of the reference.
    """

    q: np.ndarray  # (G,) float32, band-passed, zero-phase
    omega: float  # mean angular frequency of the cross-spectrum, rad/sample
    norm: float  # ||q||
    unit_raw: np.ndarray  # (G,) float32, unfiltered reference / its norm (quality figures)
    offset: float  # its position relative to the first reference, samples
    raw: np.ndarray  # (G,) float64, mean-free unfiltered reference
    raw_norm: float  # ||raw||
    spectrum: np.ndarray  # rfft of raw on nfft points
    filtered_spectrum: np.ndarray  # the same times |H|^2 (the spectrum of q)
    nfft: int

    @functools.cached_property
    def q_hilbert(self) -> np.ndarray:
        """(G,) float32, Hilbert transform of q."""
        return _hilbert(self.filtered_spectrum, self.nfft, self.q.size).astype(np.float32)

    @functools.cached_property
    def raw_env_peak(self) -> float:
        """Peak envelope of unit_raw (turns a projection into an amplitude)."""
        env = np.abs(self.raw + 1j * _hilbert(self.spectrum, self.nfft, self.raw.size))
        return float(env.max() / self.raw_norm)


def _hilbert(spectrum: np.ndarray, nfft: int, G: int) -> np.ndarray:
    """First ``G`` samples of the Hilbert transform of the ``nfft``-point signal whose rfft is
    ``spectrum``."""
    sh = -1j * spectrum
    sh[0] = 0.0
    return np.fft.irfft(sh, nfft)[:G]


@functools.lru_cache(maxsize=32)
def _band_sos(band_hz: tuple[float, float], order: int, fs: float) -> np.ndarray:
    lo, hi = band_hz
    hi = min(hi, 0.45 * fs)
    if not 0.0 < lo < hi:
        raise ValueError(f"prefilter band {band_hz} Hz is not a valid pass band at fs={fs} Hz")
    return signal.butter(order, (lo, hi), btype="bandpass", fs=fs, output="sos")


@functools.lru_cache(maxsize=32)
def _power_response(band_hz: tuple[float, float], order: int, fs: float,
                    nfft: int) -> np.ndarray:
    """|H(f)|^2 of the Butterworth band-pass on the rfft grid of ``nfft`` points.

    Multiplying a spectrum by it is the zero-phase forward-backward filter (filtfilt) without
    its edge transients.
    """
    sos = _band_sos(band_hz, order, fs)
    _, h = signal.sosfreqz(sos, worN=np.fft.rfftfreq(nfft, 1.0 / fs), fs=fs)
    return np.abs(h) ** 2


def _centre_frequency_hz(x: np.ndarray, fs: float) -> float:
    """Peak of the (zero-padded) magnitude spectrum of a mean echo."""
    nfft = max(2048, 1 << int(np.ceil(np.log2(x.size))))
    spec = np.abs(np.fft.rfft(x - x.mean(), nfft))
    spec[0] = 0.0
    return float(np.argmax(spec) * fs / nfft)


@dataclass(frozen=True)
class _Band:
    hz: tuple[float, float]
    order: int
    fs: float


@functools.lru_cache(maxsize=8)
def _ramp(n: int) -> np.ndarray:
    """``linspace(0, pi, n)``: angular frequency (rad/sample) of each rfft bin (read-only)."""
    out = np.linspace(0.0, np.pi, n)
    out.flags.writeable = False
    return out


def _make_reference(raw: np.ndarray, band: _Band, offset: float = 0.0) -> _Reference:
    raw = np.asarray(raw, dtype=float)
    raw = raw - raw.mean()
    G = raw.size
    nfft = int(sp_fft.next_fast_len(4 * G, real=True))
    R = np.fft.rfft(raw, nfft)
    # |H|^2: correlating raw echoes with q = correlating filtered echoes with filtered ref.
    Q = R * _power_response(band.hz, band.order, band.fs, nfft)
    q = np.fft.irfft(Q, nfft)[:G]
    norm = float(np.linalg.norm(q))
    if norm == 0.0:
        raise ValueError("reference echo is empty (all samples equal): nothing to track")
    # Mean frequency of the cross-spectrum raw x conj(q) = |H|^2 |S|^2: the phase slope of
    # the analytic correlation at zero lag.
    w = np.real(R * np.conj(Q))
    omega = float(np.sum(w * _ramp(w.size)) / np.sum(w))
    raw_norm = float(np.linalg.norm(raw))
    return _Reference(q.astype(np.float32), omega, norm, (raw / raw_norm).astype(np.float32),
                      offset, raw, raw_norm, R, Q, nfft)


def _toeplitz(q: np.ndarray, lags: np.ndarray, base: int, n_cols: int = 0) -> np.ndarray:
    """Matrix T with ``window @ T[:, j] = sum_n window[base + lags[j] + n] * q[n]``.

    ``n_cols``: at least this many columns (zero columns after the lags' ones).
    """
    G = q.size
    width = base + int(lags.max()) + G
    T = np.zeros((width, max(lags.size, n_cols)), dtype=np.float32)
    for j, lag in enumerate(lags):
        T[base + lag: base + lag + G, j] = q
    return T


def _blas_width(n_cols: int) -> int:
    """``n_cols`` rounded up to a multiple of 8: OpenBLAS' float32 kernels work on 8-column
    panels, and a product with 8 columns was measured faster than one with 7 or 9 (each
    column's values unchanged)."""
    return -(-n_cols // 8) * 8


def _every_other_float32(W: np.ndarray, par: int) -> np.ndarray:
    """``W[:, par::2]`` (every other sample from column ``par``) as C-contiguous float32.

    numpy's strided int8 -> float32 cast was measured 2x slower than reading the same rows
    as little-endian int16 sample pairs, whose high byte (arithmetic ``>> 8``) is the odd and
    whose low byte (cast to int8) is the even sample: that is done for int8 codes.
    """
    if W.dtype != np.int8 or W.strides[1] != 1 or not np.little_endian:
        return W[:, par::2].astype(np.float32)
    n, width = W.shape
    k = (width - par + 1) // 2
    out = np.empty((n, k), dtype=np.float32)
    if par:
        np.right_shift(W[:, : 2 * k].view(np.int16), 8, out=out, casting="unsafe")
    else:
        pairs = width // 2
        out[:, :pairs] = W[:, : 2 * pairs].view(np.int16).astype(np.int8)
        if pairs < k:  # odd width: the last sample has no partner
            out[:, pairs] = W[:, -1]
    return out


# --------------------------------------------------------------------------------------------
# Sub-sample peak estimators on fine correlation arrays


def _spline_basis(n_points: int, grid: np.ndarray) -> np.ndarray:
    """Values at ``grid`` of the cubic-spline cardinal functions on ``n_points`` unit knots."""
    knots = np.arange(n_points) - (n_points - 1) / 2.0
    spline = interpolate.CubicSpline(knots, np.eye(n_points), axis=0, bc_type="not-a-knot")
    return spline(grid)  # (n_grid, n_points)


_SPLINE_GRID = np.linspace(-1.5, 1.5, 601)
_SPLINE_BASIS = _spline_basis(7, _SPLINE_GRID).astype(np.float64)


def _subsample(C: np.ndarray, Ch: np.ndarray, half: int, omega: float,
               estimator: str) -> np.ndarray:
    """Peak position (relative to the centre column) of each row of ``C[:, :2*half+1]``.

    C: (n, >= 2*half+1), the correlation at lags -half..half in its first columns (more
    columns may follow: a C-contiguous array is indexed flat, measured 2x faster).
    ``Ch`` is the correlation with the Hilbert-transformed reference (for ``phase``).
    """
    n = C.shape[0]
    rows = np.arange(n)
    Cl = C[:, : 2 * half + 1]
    m = np.minimum(np.maximum(np.argmax(Cl, axis=1), 1), 2 * half - 1)
    if C.flags.c_contiguous:
        flat, at = C.ravel(), rows * C.shape[1] + m
        y0, y1, y2 = (flat[at - 1].astype(float), flat[at].astype(float),
                      flat[at + 1].astype(float))
    else:
        y0, y1, y2 = (C[rows, m - 1].astype(float), C[rows, m].astype(float),
                      C[rows, m + 1].astype(float))
    if estimator == "parabolic":
        den = y0 - 2.0 * y1 + y2
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(den < 0, 0.5 * (y0 - y2) / den, 0.0)
    elif estimator == "cosine":
        with np.errstate(divide="ignore", invalid="ignore"):
            w = np.arccos(np.minimum(np.maximum((y0 + y2) / (2.0 * y1), -1.0), 1.0))
            theta = np.arctan2(y0 - y2, 2.0 * y1 * np.sin(w))
            frac = np.where(w > 0, -theta / w, 0.0)
    elif estimator == "phase":
        # Analytic correlation c_a[l] = C[l] - i Ch[l] has phase omega * (l - tau).
        phi = np.arctan2(-Ch[rows, m].astype(float), y1)
        frac = -phi / omega
    elif estimator == "spline":
        vals = Cl.astype(float) @ _SPLINE_BASIS.T  # (n, grid), spline through all 7 points
        k = np.clip(np.argmax(vals, axis=1), 1, _SPLINE_GRID.size - 2)
        a, b, c = vals[rows, k - 1], vals[rows, k], vals[rows, k + 1]
        den = a - 2.0 * b + c
        step = _SPLINE_GRID[1] - _SPLINE_GRID[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            ref = np.where(den < 0, 0.5 * (a - c) / den, 0.0)
        return _SPLINE_GRID[k] + ref * step
    else:
        raise ValueError(f"unknown estimator {estimator!r}; choose one of {ESTIMATORS}")
    # np.clip / nan_to_num are slow on small arrays; plain ufuncs do the same.
    frac = np.minimum(np.maximum(np.where(np.isfinite(frac), frac, 0.0), -1.0), 1.0)
    return (m - half) + frac


# --------------------------------------------------------------------------------------------
# One block of echoes against one reference


@dataclass
class _BlockResult:
    delay: np.ndarray  # (n,) samples, relative to the window's zero lag
    lag: np.ndarray  # (n,) int, integer peak lag
    corr: np.ndarray  # (n,)
    snr_db: np.ndarray  # (n,)
    edge: np.ndarray  # (n,) bool: peak at the border of the lag range


_FINE_HALF = 3  # fine pass: 7 lags around the coarse peak (the spline uses all 7)


def _coarse(W: np.ndarray, ref: _Reference, L: int,
            step: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Peak lag per echo from a lag grid of ``step`` samples, parabola refined (cheap pass).

    W: (n, G + 2L) raw windows (any dtype). With an even ``step`` the windows are decimated
    by 2 (the 5 MHz echo keeps 50 samples per period): half the memory traffic, and the
    integer lag only needs to be right within +-2 samples for the fine pass.
    Returns the delay estimate (samples), its integer lag, and ``edge`` (peak at the border
    of the lag range), each (n,).
    """
    if step % 2 == 0:
        par = L % 2
        lags = np.arange(-(L - par), L + 1, step)
        T = _toeplitz(ref.q[::2], lags // 2, (L - par) // 2, _blas_width(lags.size))
        # (odd L with an even gate length: the last decimated sample is beyond every lag)
        C = _every_other_float32(W, par)[:, : T.shape[0]] @ T
    else:
        lags = np.arange(-L, L + 1, step)
        if lags[-1] != L:
            lags = np.append(lags, L)
        C = W.astype(np.float32, copy=False) @ _toeplitz(ref.q, lags, L,
                                                         _blas_width(lags.size))
    nl = lags.size
    j = np.argmax(C[:, :nl], axis=1)
    jj = np.minimum(np.maximum(j, 1), nl - 2)
    at = np.arange(0, C.size, C.shape[1]) + jj  # C[k, jj[k]] in the flat (C-order) array
    flat = C.ravel()
    y0, y1, y2 = flat[at - 1], flat[at], flat[at + 1]
    den = y0 - 2.0 * y1 + y2
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(den < 0, 0.5 * (y0 - y2) / den, 0.0)
    frac = np.minimum(np.maximum(np.where(np.isfinite(frac), frac, 0.0), -1.0), 1.0)
    est = lags[jj] + frac * step
    return est, np.rint(est).astype(int), (j == 0) | (j == nl - 1)


@dataclass
class _Groups:
    """Each echo's samples around its integer lag, rows sorted by lag (one group per lag).

    Row ``i`` of ``A`` is ``W[order[i], L + lag[i] - h: L + lag[i] + G + h]`` (``h =
    _FINE_HALF``, ``W`` the (n, G + 2L) window, samples): exactly what the fine pass correlates
    at lags ``lag[i] - h .. lag[i] + h``, so one matrix product serves every echo. Sorting by
    lag keeps each lag's rows contiguous (the aligned reference sums them group by group).
    """

    order: np.ndarray  # sorted position -> original row
    A: np.ndarray  # (n, G + 2h) float32, C-contiguous, sorted rows
    lag: np.ndarray  # sorted integer lags (clipped to the fine range), samples
    runs: list[tuple[int, int, int]]  # (lag, first row, end row)
    valid: tuple[np.ndarray, np.ndarray] | None = None  # sorted in-record columns of W per row
    # A holds int8 codes: every float32 sum of them (over < 2^17 rows) or of their squares
    # (over < 1024 columns) is an integer below 2^24, exact in any summation order.
    exact_sums: bool = False

    @classmethod
    def build(cls, W: np.ndarray, lag: np.ndarray, G: int,
              valid: tuple[np.ndarray, np.ndarray] | None = None) -> _Groups:
        """``W``: (n, G + 2L) windows (any dtype); ``lag``: (n,) integer lags in
        ``[-(L - h), L - h]``; ``valid``: per row, the columns of ``W`` inside the record."""
        h = _FINE_HALF
        L = (W.shape[1] - G) // 2
        order = np.argsort(lag, kind="stable")
        lag_s = lag[order]
        runs: list[tuple[int, int, int]] = []
        if lag_s.size:
            first = int(lag_s[0])
            counts = np.bincount(lag_s - first).tolist()
            end = 0
            for i, c in enumerate(counts):
                if c:
                    runs.append((first + i, end, end + c))
                    end += c
        # One lag's rows at a time: gathered and converted (e.g. from int8) in one copy.
        A = np.empty((lag.size, G + 2 * h), dtype=np.float32)
        for p, r0, r1 in runs:
            A[r0:r1] = W[order[r0:r1], L - h + p: L + h + p + G]
        if valid is not None:
            valid = (valid[0][order], valid[1][order])
        exact = W.dtype == np.int8 and A.shape[0] < 2**17 and A.shape[1] < 1024
        return cls(order, A, lag_s, runs, valid, exact)

    def unsort(self, x: np.ndarray) -> np.ndarray:
        """``x`` given per sorted row, in the original row order."""
        out = np.empty_like(x)
        out[self.order] = x
        return out

    def inverse(self) -> np.ndarray:
        """Original row -> sorted position."""
        inv = np.empty_like(self.order)
        inv[self.order] = np.arange(self.order.size)
        return inv


def _fine(g: _Groups, ref: _Reference, L: int, estimator: str) -> _BlockResult:
    """Sub-sample delay of each echo around its integer lag: one matrix product for all echoes.

    Columns: 7 lags of the filtered reference, (for ``phase`` only) 7 of its Hilbert
    transform, the unfiltered unit reference and a window of ones at the integer lag
    (correlation coefficient and SNR); padded to a multiple of 8 columns (the BLAS kernels'
    width: measured faster, each column's values unchanged). Results in the original row order.
    """
    n, G, h = g.A.shape[0], ref.q.size, _FINE_HALF
    lags_local = np.arange(-h, h + 1)
    n_q = (2 if estimator == "phase" else 1) * (2 * h + 1)
    TT = np.zeros((G + 2 * h, _blas_width(n_q + 2)), dtype=np.float32)
    TT[:, : 2 * h + 1] = _toeplitz(ref.q, lags_local, h)
    if estimator == "phase":
        TT[:, 2 * h + 1: n_q] = _toeplitz(ref.q_hilbert, lags_local, h)
    TT[h: h + G, n_q] = ref.unit_raw
    TT[h: h + G, n_q + 1] = 1.0  # window sum, for the window mean
    CC = g.A @ TT
    lone = [r0 for _, r0, r1 in g.runs if r1 - r0 == 1]
    if lone:
        # A lag's lone echo: the vector-matrix product, rounded as when each lag group was
        # correlated on its own (keeps the benchmark figures identical to the digit).
        T_used = np.ascontiguousarray(TT[:, : n_q + 2])
        for r0 in lone:
            CC[r0: r0 + 1, : n_q + 2] = g.A[r0: r0 + 1] @ T_used
    seg = g.A[:, h: h + G]
    # (n,) float32: window energy at the integer lag. np.vecdot (numpy >= 2) is faster than
    # einsum but sums in another order: used where every order gives the same (exact) sums.
    if g.exact_sums and hasattr(np, "vecdot"):
        energy = np.vecdot(seg, seg)
    else:
        energy = np.einsum("ij,ij->i", seg, seg)
    centre = g.lag
    Ch = CC[:, 2 * h + 1: n_q] if estimator == "phase" else CC
    delay = centre + _subsample(CC, Ch, h, ref.omega, estimator)
    truncated = None if g.valid is None else _truncated_correlation(g, ref, L)
    if truncated is not None:
        cut, Ct = truncated
        est = "cosine" if estimator == "phase" else estimator  # no Hilbert column here
        calibration = _cut_calibration(g, ref, L, delay, cut, est)
        delay[cut] = centre[cut] + _subsample(Ct, Ct, h, ref.omega, est) + calibration
    proj = CC[:, n_q].astype(float)  # unit_raw has zero mean: the window mean drops out
    energy = energy - CC[:, n_q + 1].astype(float) ** 2 / G
    proj_pos = np.maximum(proj, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = np.where(energy > 0, proj / np.sqrt(energy), 0.0)
        noise_var = np.maximum(energy - proj_pos ** 2, 1e-12) / (G - 1)
        amp = proj_pos * ref.raw_env_peak
        snr = 20.0 * np.log10(np.maximum(amp, 1e-12) / np.sqrt(noise_var))
    corr = np.minimum(np.maximum(corr, 0.0), 1.0)
    return _BlockResult(g.unsort(delay), g.unsort(g.lag), g.unsort(corr), g.unsort(snr),
                        np.zeros(n, dtype=bool))


def _truncated_correlation(g: _Groups, ref: _Reference, L: int,
                           ) -> tuple[np.ndarray, np.ndarray] | None:
    """Fine correlations of the echoes cut by the record's edge, made unbiased.

    An echo partly outside the record (zeros there) correlates with the reference only over
    the samples it has; the plain correlation peak is then pulled away from the truth (its
    slope at the true delay is s^2(edge)/2, not 0). For those echoes (sorted rows returned
    first) the correlation with the UNFILTERED reference over the in-record samples, divided
    by the square root of the reference energy on those samples at each lag, is the
    least-squares (matched-filter) delay on the samples available (see
    :func:`_in_record_correlation`; :func:`_cut_calibration` puts it on the scale of the
    other echoes' delays).
    (The band-passed reference is not: measured 0.04-0.2 sample of bias at 5-30 % of the
    echo energy cut, against < 0.01 for this.)
    """
    lo, hi = g.valid
    G = ref.q.size
    width = G + 2 * L
    cut = np.nonzero((lo > 0) | (hi < width))[0]
    if cut.size == 0:
        return None
    return cut, _in_record_correlation(g.A[cut], g.lag[cut], lo[cut], hi[cut], ref, L)


def _in_record_correlation(A: np.ndarray, lag: np.ndarray, lo: np.ndarray, hi: np.ndarray,
                           ref: _Reference, L: int) -> np.ndarray:
    """(n, 2h+1) energy-normalised correlations of rows ``A`` (fine blocks, ``_Groups.A``
    rows at integer lags ``lag``) with the unfiltered reference over the window columns
    [``lo``, ``hi``) inside the record: least squares on the samples available."""
    h = _FINE_HALF
    r = ref.unit_raw.astype(float)
    G = r.size
    first = L + lag - h  # window column of the fine block's first sample
    cols = first[:, None] + np.arange(G + 2 * h)[None, :]
    Wc = A.astype(float)  # = the window's columns ``cols``
    # The padded record has its DC removed (``_pad_record``); a per-window mean would bias
    # a cut echo (its in-record part does not average to zero).
    inside = (cols >= lo[:, None]) & (cols < hi[:, None])
    Wc = np.where(inside, Wc, 0.0)
    C = Wc @ _toeplitz(r, np.arange(-h, h + 1), h).astype(float)
    cum = np.concatenate([[0.0], np.cumsum(r**2)])
    q0 = (L + lag)[:, None] + np.arange(-h, h + 1)[None, :]  # column of r[0] per lag
    n_lo = np.clip(lo[:, None] - q0, 0, G)
    n_hi = np.clip(hi[:, None] - q0, 0, G)
    energy = cum[n_hi] - cum[n_lo]
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(energy > 1e-6 * cum[-1], C / np.sqrt(energy), 0.0)


_CUT_CALIBRATION_ECHOES = 256
"""Echoes wholly inside the record used to calibrate the cut echoes' delays (at most)."""
_CUT_CALIBRATION_MIN_ECHOES = 8
_CUT_CALIBRATION_STEP = 4
"""Cut amounts are calibrated on a grid of this many samples."""


def _cut_calibration(g: _Groups, ref: _Reference, L: int, delay: np.ndarray,
                     cut: np.ndarray, estimator: str) -> np.ndarray:
    """Per cut echo (sorted rows ``cut``): the delay offset between the normal fine pass and
    the in-record least-squares path, for that echo's cut (samples; 0 when not measurable).

    The two paths do not share a zero: the normal pass correlates with the band-passed
    reference, and the reference is the echo cut at the gate (10 % envelope), so the echo
    samples just outside the gate pull both peaks by different constant amounts (the
    correlation slope at the true delay gets ``e(edge)^2 / 2`` from each gate edge the
    window holds; a record edge inside the reference removes that edge's term). Echoes
    moving across the record's edge were therefore tracked with a step of ~0.01-0.02 sample
    between their cut and uncut stretches: a gain error of the phasor (measured on the
    simulated bench, face_up at 10-20 Hz, 20-40 um: -0.02 to -0.045 %, many sigma of these
    lines' noise). The offset is measured on the data: echoes wholly inside the record
    (``delay``: their normal-pass delays) are given the same cut (leading and trailing
    samples of the fine block, on a ``_CUT_CALIBRATION_STEP`` grid) and passed through the
    in-record path; the median difference is added to the cut echoes' delays.
    """
    lo, hi = g.valid
    h = _FINE_HALF
    G = ref.q.size
    n_block = G + 2 * h
    correction = np.zeros(cut.size)
    whole = np.ones(lo.size, dtype=bool)
    whole[cut] = False
    full = np.nonzero(whole)[0]
    if full.size < _CUT_CALIBRATION_MIN_ECHOES:
        return correction
    full = full[np.linspace(0, full.size - 1, min(full.size, _CUT_CALIBRATION_ECHOES)
                            ).astype(int)]
    first = L + g.lag[cut] - h
    step = _CUT_CALIBRATION_STEP
    lead = np.rint(np.clip(lo[cut] - first, 0, n_block) / step).astype(int) * step
    trail = np.rint(np.clip(first + n_block - hi[cut], 0, n_block) / step).astype(int) * step
    keys, which = np.unique(np.stack([lead, trail], axis=1), axis=0, return_inverse=True)
    which = np.asarray(which).reshape(-1)
    A, lag = g.A[full], g.lag[full]
    first_full = L + lag - h
    for k, (a, b) in enumerate(keys):
        if a + b >= G // 2:
            continue  # under half the reference left: such echoes are lost anyway
        C = _in_record_correlation(A, lag, first_full + a, first_full + n_block - b, ref, L)
        d_cut = lag + _subsample(C, C, h, ref.omega, estimator)
        correction[which == k] = float(np.median(delay[full] - d_cut))
    return correction


def _aligned_reference(g: _Groups, delay: np.ndarray, good: np.ndarray, G: int,
                       band: _Band, offset: float) -> _Reference | None:
    """Mean of the good echoes, each shifted by its integer lag (sub-sample blur is symmetric).

    ``delay`` and ``good`` are in original row order. The new reference's position relative
    to the one that produced ``delay`` is the mean residual (delay - lag) of the echoes
    averaged, added to ``offset``.
    """
    good_s = good[g.order]
    count = int(np.count_nonzero(good_s))
    if count == 0:
        return None
    weights = good_s.astype(np.float32)
    acc = np.zeros(G)
    h = _FINE_HALF
    if g.exact_sums:  # int8 codes: one product, exact
        acc += weights @ g.A[:, h: h + G]
    else:  # group by group, in lag order (float32 rounding as in earlier versions)
        for _, r0, r1 in g.runs:
            acc += weights[r0:r1] @ g.A[r0:r1, h: h + G]
    resid = float(np.mean(delay[g.order][good_s] - g.lag[good_s]))
    return _make_reference(acc / count, band, offset + resid)


def _track_block(W: np.ndarray, ref: _Reference, L: int, opts: TrackingOptions,
                 band: _Band, rebuilds: int,
                 valid: tuple[np.ndarray, np.ndarray] | None = None,
                 calibration_windows: np.ndarray | None = None,
                 ) -> tuple[_BlockResult, _Reference, _Groups]:
    """Coarse pass, ``rebuilds`` aligned-average reference rebuilds, fine pass.

    W: (n, G + 2L) echo windows; zero lag = the gate. ``edge`` marks echoes whose peak is at
    the border of the lag range (they left the gate). ``valid``: per row, the window columns
    [lo, hi) that lie inside the record (windows cut from a zero-padded record); echoes cut by
    the record's edge get the energy-normalised correlation and are kept out of references.
    calibration_windows: (k, G + 2L) windows of echoes wholly inside the record, taken
        elsewhere in it, each at its own gate; used only when ``W`` holds fewer than
        ``_CUT_CALIBRATION_MIN_ECHOES`` whole echoes and at least one cut echo (with
        ``valid``): they are then tracked along with ``W`` so that :func:`_cut_calibration`
        measures the cut echoes' offset on them. They stay out of reference rebuilds and of
        the returned result (n rows); the returned groups hold them too.
    """
    n_own = W.shape[0]
    if valid is not None and calibration_windows is not None and calibration_windows.size:
        whole_own = (valid[0] <= 0) & (valid[1] >= W.shape[1])
        if (not whole_own.all()
                and np.count_nonzero(whole_own) < _CUT_CALIBRATION_MIN_ECHOES):
            k = calibration_windows.shape[0]
            W = np.concatenate([W, calibration_windows.astype(W.dtype, copy=False)])
            valid = (np.concatenate([valid[0], np.zeros(k, dtype=valid[0].dtype)]),
                     np.concatenate([valid[1], np.full(k, W.shape[1], dtype=valid[1].dtype)]))
    G = ref.q.size
    delay, lag, edge = _coarse(W, ref, L, max(1, min(opts.coarse_lag_step, L)))
    edge |= np.abs(lag) > L - _FINE_HALF
    g = _Groups.build(W, np.clip(lag, -(L - _FINE_HALF), L - _FINE_HALF), G, valid)
    whole = None if valid is None else (valid[0] <= 0) & (valid[1] >= W.shape[1])
    res = None
    for i in range(rebuilds):
        good = ~edge if res is None else ~edge & (res.corr >= opts.min_correlation)
        if whole is not None:
            good = good & whole
        good[n_own:] = False  # calibration echoes: another part of the record
        new = _aligned_reference(g, delay, good, G, band, ref.offset)
        if new is None:
            break
        ref = new
        if i < rebuilds - 1:
            res = _fine(g, ref, L, opts.estimator)
            delay = res.delay
    res = _fine(g, ref, L, opts.estimator)
    res.edge = edge
    if W.shape[0] > n_own:
        res = _BlockResult(res.delay[:n_own], res.lag[:n_own], res.corr[:n_own],
                           res.snr_db[:n_own], res.edge[:n_own])
    return res, ref, g


# --------------------------------------------------------------------------------------------
# Gate


_DFT_MAX_BINS = 64


@functools.lru_cache(maxsize=16)
def _band_dft(m: int, nfft: int, bins: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """The ``nfft``-point DFT of ``m`` samples restricted to ``bins``: forward (m, n_bins) and
    inverse (n_bins, m) matrices, ``x @ fwd`` = ``fft(x, nfft)[bins]`` and ``X @ inv`` =
    ``ifft(spectrum with only those bins)[:m]``."""
    phase = (2.0 * np.pi / nfft) * (np.outer(np.arange(m), np.asarray(bins, dtype=int)) % nfft)
    return np.exp(-1j * phase), np.exp(1j * phase.T) / nfft


_GATE_ECHOES = 8
"""Echoes whose mean envelope places the automatic gate."""
MIN_GATE_SAMPLES = 16
"""Shortest gate (samples) an echo is tracked in, the operator's, the protocol's or the
automatic one; a record must hold it and the lag range on both sides."""


def _first_echoes_envelope(codes: np.ndarray, sample_rate_hz: float, n_echoes: int,
                           band_hz: tuple[float, float] | None) -> np.ndarray:
    """Mean Hilbert envelope (counts, per sample) of the first ``n_echoes`` echoes,
    band-passed over ``band_hz`` (None = 0.4-1.6 x their centre frequency)."""
    x = np.asarray(codes[:n_echoes], dtype=float)
    x = x - x.mean(axis=1, keepdims=True)
    m = x.shape[1]
    if not np.any(x):
        raise ValueError("the first echoes are flat: no echo to gate on (receiver gain? "
                         "record delay?)")
    fc = _centre_frequency_hz(x.mean(axis=0), sample_rate_hz)
    band = band_hz or (0.4 * fc, 1.6 * fc)
    nfft = int(sp_fft.next_fast_len(2 * m))
    f = np.fft.fftfreq(nfft, 1.0 / sample_rate_hz)
    # Analytic band-passed signal: keep the positive pass band only, doubled.
    keep = (f >= band[0]) & (f <= band[1])
    bins = np.nonzero(keep)[0]
    if bins.size <= _DFT_MAX_BINS:
        # A few dozen bins (2-8 MHz of a 1000-point, 500 MS/s transform: 13): the DFT over
        # them as two small matrix products, far cheaper than the two full FFTs.
        fwd, inv = _band_dft(m, nfft, tuple(bins.tolist()))
        return np.abs((2.0 * (x @ fwd)) @ inv).mean(axis=0)
    spec = np.fft.fft(x, nfft, axis=1) * np.where(keep, 2.0, 0.0)
    return np.abs(np.fft.ifft(spec, axis=1)[:, :m]).mean(axis=0)


def _strongest_echo_extent(envelope: np.ndarray, threshold: float) -> tuple[int, int]:
    """(first, last + 1) samples around the envelope's peak where it stays at or above
    ``threshold`` of the peak."""
    k = int(np.argmax(envelope))
    below = envelope < threshold * envelope[k]
    left = np.nonzero(below[:k])[0]
    right = np.nonzero(below[k:])[0]
    return (int(left[-1] + 1) if left.size else 0,
            int(k + right[0]) if right.size else envelope.size)


def auto_gate(codes: np.ndarray, sample_rate_hz: float, *, threshold: float = 0.1,
              margin_samples: int = 5, n_echoes: int = _GATE_ECHOES,
              band_hz: tuple[float, float] | None = None) -> tuple[int, int]:
    """Window (start, stop) samples around the strongest echo envelope (the bone echo).

    The envelope is the mean Hilbert envelope of the first ``n_echoes`` band-passed echoes
    (band: ``band_hz`` or 0.4-1.6 x the centre frequency); the window extends from the peak
    until the envelope drops below ``threshold`` of it, plus ``margin_samples`` each side.
    """
    env = _first_echoes_envelope(codes, sample_rate_hz, n_echoes, band_hz)
    first, end = _strongest_echo_extent(env, threshold)
    return max(0, first - margin_samples), min(env.size, end + margin_samples)


RIVAL_ECHO_DB = 10.0
"""An echo whose envelope peak is within this many dB of the gated one is named in the
tracker's notes: the automatic gate takes the strongest echo for the bone, and with a rival
that close the other may be the bone (session 36 review: a stationary reflection 1.5 x the
bone's echo, 0.3 us before it, was gated and tracked instead, the step ``ok``); one that
overlaps the gated echo biases its delay unless it moves with it. On the simulated bench
the strongest other envelope peak is -19.5 dB (the demo's 616 records, session 38)."""

RIVAL_MIN_DIP = 0.2
"""A rival is a separate echo when the envelope dips by at least this fraction of its peak
(1.9 dB) between it and any higher peak (scipy's peak prominence): the ripple of one echo's
envelope is not a rival."""

RIVAL_MIN_NOISE_RATIO = 3.0
"""... and when its envelope peak is at least this many times the record's noise SD (so that
the noise of a weak record is not called an echo)."""

RIVAL_MIN_ECHOES = 4
"""The noise SD is the echoes' spread across pulses: with fewer than this many (a live
echo of 1-3 pulses) it is not known, and no rival is named (band-limited noise at 10-15 dB
gave false notes on 3 of 60 records with 3 pulses, 41-53 of 60 with 1: helper review,
session 38)."""


def rival_echo(envelope: np.ndarray, noise_sd: float = 0.0,
               within_db: float = RIVAL_ECHO_DB) -> tuple[int, float] | None:
    """The strongest echo other than the envelope's highest, when within ``within_db`` of it.

    envelope: per-sample echo envelope (counts; the record's edges count as zero beyond it,
        so an echo cut by an edge is seen). noise_sd: noise SD in the same unit; a peak below
        ``RIVAL_MIN_NOISE_RATIO`` x it is not an echo.
    Returns (sample of its peak, its level in dB relative to the highest peak) or None. A
    peak is an echo of its own when its prominence is at least ``RIVAL_MIN_DIP`` of its
    height (``scipy.signal.find_peaks``).
    """
    padded = np.concatenate(([0.0], np.asarray(envelope, dtype=float), [0.0]))
    peaks, props = signal.find_peaks(padded, prominence=0.0)
    if peaks.size < 2:
        return None
    heights = padded[peaks]
    highest = int(np.argmax(heights))
    separate = ((props["prominences"] >= RIVAL_MIN_DIP * heights)
                & (heights >= RIVAL_MIN_NOISE_RATIO * noise_sd))
    separate[highest] = False
    if not np.any(separate):
        return None
    best = int(np.argmax(np.where(separate, heights, -np.inf)))
    level_db = 20.0 * math.log10(heights[best] / heights[highest])
    return (int(peaks[best]) - 1, level_db) if level_db >= -within_db else None


def _rival_in(envelope: np.ndarray, first_echoes: np.ndarray) -> tuple[int, float] | None:
    """:func:`rival_echo` in the envelope of ``first_echoes`` (raw codes), their noise SD
    estimated only when there is a candidate."""
    if rival_echo(envelope) is None:  # the usual case, without the noise estimate's cost
        return None
    if len(first_echoes) < RIVAL_MIN_ECHOES:
        return None
    # the raw record's noise SD: the first echoes' spread across pulses, per sample (their
    # motion over 8 pulses can only raise it: fewer notes, never false ones)
    noise_sd = float(np.median(np.std(np.asarray(first_echoes, dtype=float), axis=0)))
    return rival_echo(envelope, noise_sd)


def _rival_note(envelope: np.ndarray, rival: tuple[int, float], gate: tuple[int, int],
                fs: float) -> str:
    """The tracker's note on ``rival`` (:func:`rival_echo`'s answer)."""
    sample, level_db = rival
    lag_s = (sample - int(np.argmax(envelope))) / fs
    where = (f"another echo at sample {sample} ({abs(lag_s) * 1e6:.2f} us "
             f"{'later' if lag_s > 0 else 'earlier'}) is {-level_db:.1f} dB below the gated one")
    if gate[0] <= sample < gate[1]:
        # one that moves with the bone (a second interface, a two-lobed pulse) does no harm
        return (f"{where}, inside the gate: if it does not move with the bone (a fixed "
                "reflector), it biases the tracked delay; look at the A-scan and set the gate "
                "on the bone echo")
    return (f"{where}: the strongest echo was taken for the bone; if the bone is the other, "
            "set the gate on it")


GATE_CUT_LEVEL = 0.5
"""A gate set by hand (the operator's, the protocol's, ``--gate``) whose edge leaves the
echo it holds where that echo's envelope is still at least this fraction of its peak is
named in the tracker's notes. The tracked delay then rests on what is left of the echo and
its edge: on synthetic 30 dB records (``tests/echo_synth.py``, 250 Hz, 0.2 um) the
displacement noise was 1.0-1.1x that of the whole echo with the gate ending at 10-60 % of
the peak, 1.2-1.5x at 70-90 % and 4.9x at the peak; the simulated bench's demo session
re-tracked with ch1's gate ending at its echo's peak had H_std 5.0x larger (median; its /frf
within that std of the automatic gate's). A note, not a failure: cutting off another echo
that overlaps the bone's can be the better choice."""


GATE_CUT_NOTE = re.compile(r"gate \(\d+, \d+\): the gate (cuts the echo|holds only a "
                           r"flank) .*? a neighbouring echo")
"""Matches :func:`_cut_echo_note`'s note (among others joined by "; ")."""


def _cut_echo_note(envelope: np.ndarray, gate: tuple[int, int]) -> str:
    """The tracker's note on a gate that cuts the echo it holds, else "".

    envelope: mean envelope of the first echoes (per sample, any unit). gate: (start,
    stop) samples. The echo is the envelope's highest within the gate, followed uphill out
    of the gate when the gate holds only its flank; the gate cuts it when the envelope at an
    edge on that echo's flank (no dip of :data:`RIVAL_MIN_DIP` between) is at least
    :data:`GATE_CUT_LEVEL` of the echo's peak, or the echo peaks outside the gate. A gate
    whose envelope stays 20 dB or more below the record's strongest echo is not judged."""
    start, stop = gate
    m = envelope.size
    if float(envelope[start:stop].max()) < 0.1 * float(envelope.max()):
        # nothing within 20 dB of the record's strongest echo in the gate: the walk uphill
        # below would reach the main echo from a gate on noise (review of session 40)
        return ""
    peak = start + int(np.argmax(envelope[start:stop]))
    # the gate's highest sample at its edge: the flank of an echo that peaks outside it
    if peak == stop - 1:
        while peak + 1 < m and envelope[peak + 1] > envelope[peak]:
            peak += 1
    if peak == start:
        while peak - 1 >= 0 and envelope[peak - 1] > envelope[peak]:
            peak -= 1
    top = float(envelope[peak])
    if top <= 0.0:
        return ""

    def same_echo(sample: int) -> bool:
        # the edge is on the flank of that echo, not on another one beside it (no dip)
        between = envelope[min(sample, peak):max(sample, peak) + 1]
        return float(between.min()) >= (1.0 - RIVAL_MIN_DIP) * float(envelope[sample])

    edges = [(name, sample, float(envelope[sample]) / top)
             for name, sample, outside in (("start", start, start > 0),
                                           ("stop", stop - 1, stop < m))
             if outside and same_echo(sample)]
    flank = not start <= peak < stop
    toward_peak = "stop" if peak >= stop else "start"
    cut = [(name, sample, level) for name, sample, level in edges
           if (name == toward_peak if flank else level >= GATE_CUT_LEVEL)]
    if not cut:
        return ""
    where = (f"the gate holds only a flank of the echo whose envelope peaks at sample {peak}"
             if flank else f"the gate cuts the echo whose envelope peaks at sample {peak}")
    levels = " and ".join(f"{100 * level:.0f} % of that peak at the gate's {name} (sample "
                          f"{sample if name == 'start' else stop})"
                          for name, sample, level in cut)
    return (f"gate ({start}, {stop}): {where}; the envelope is still {levels}: the part "
            "left out is not tracked and the displacement is noisier (about 5x with the "
            "gate ending at the peak); set the gate around the whole echo (down to ~10 % of "
            "its peak) unless it is there to leave out a neighbouring echo")


def _choose_gate(codes: np.ndarray, fs: float, opts: TrackingOptions,
                 warnings: list[str]) -> tuple[int, int, int | None]:
    """The gate (start, stop samples) :func:`track_echoes` tracks in: ``opts.gate``
    (checked against the record and the lag range) or the automatic one, clipped to the
    lag range; what is worth saying about it is appended to ``warnings``. Third: the
    sample of a rival echo's peak (automatic gate only), else None."""
    m = codes.shape[1]
    L = int(opts.max_lag_samples)
    rival = None
    # found on the first echoes that hold a signal (empty first segments made it fail)
    head = np.flatnonzero(np.ptp(codes[:64], axis=1) != 0)
    first_echoes = codes[head[:_GATE_ECHOES]] if head.size else codes[:_GATE_ECHOES]
    if opts.gate is None:
        env = _first_echoes_envelope(first_echoes, fs, _GATE_ECHOES, opts.band_hz)
        extent = _strongest_echo_extent(env, opts.gate_threshold)
        gate = (max(0, extent[0] - opts.gate_margin_samples),
                min(m, extent[1] + opts.gate_margin_samples))
        start, stop = max(gate[0], L), min(gate[1], m - L)
        # said only when the clip reaches into the echo's own window (beyond the margin
        # added around it): a clip of the margin alone loses nothing of the echo, and it was
        # 58 of the 108 notes on a simulated face_up run (most 1 sample off the end)
        margin = opts.gate_margin_samples
        if start - gate[0] > margin or gate[1] - stop > margin:
            warnings.append(f"gate {gate} clipped to {(start, stop)} to fit the lag range")
        rival = _rival_in(env, first_echoes)
        if rival is not None:
            warnings.append(_rival_note(env, rival, (start, stop), fs))
    else:
        start, stop = (int(v) for v in opts.gate)
        if not 0 <= start - L < stop + L <= m:
            raise ValueError(f"gate {opts.gate} +- max_lag_samples={L} does not fit in "
                             f"{m} samples")
    if stop - start < MIN_GATE_SAMPLES:
        raise ValueError(f"gate ({start}, {stop}) is too short to track an echo")
    if opts.gate is not None and head.size:
        # a gate set by hand through the echo gave `ok` and 5x the noise, unsaid; a note
        # only: records it cannot judge are tracked as before (first segments constant at
        # a non-zero code had failed the channel: review of session 40)
        try:
            note = _cut_echo_note(
                _first_echoes_envelope(first_echoes, fs, _GATE_ECHOES, opts.band_hz),
                (start, stop))
        except ValueError:
            note = ""
        if note:
            warnings.append(note)
    return start, stop, None if rival is None else rival[0]


def gate_problem(gate: tuple[int, int], lag_samples: int, samples: int) -> str:
    """Why ``gate`` (start, stop: sample indices) cannot be tracked in a ``samples``-long
    record with a lag range of +-``lag_samples``; empty when it can (the rule
    :func:`track_echoes` applies to a given gate: 16 samples or more, lag range inside)."""
    start, stop = gate
    if (start - lag_samples >= 0 and stop + lag_samples <= samples
            and stop - start >= MIN_GATE_SAMPLES):
        return ""
    return (f"it must hold {MIN_GATE_SAMPLES} samples or more and leave the lag range "
            f"({lag_samples} samples) inside the {samples}-sample record: start "
            f"{lag_samples} to stop {samples - lag_samples}")


def _zero_segments_not_finite(codes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``codes`` with every segment that holds a sample that is not a number (float codes
    only) zeroed, and which segments those were (a NaN among the first echoes had spread
    the automatic gate over the record; :func:`track_echoes` loses them)."""
    if codes.dtype.kind != "f":
        return codes, np.zeros(codes.shape[0], dtype=bool)
    not_finite = ~np.isfinite(codes).all(axis=1)
    if np.any(not_finite):
        codes = np.where(not_finite[:, None], 0.0, codes)
    return codes, not_finite


class GatePreview(NamedTuple):
    """What :func:`gate_preview` finds on a record."""

    gate: tuple[int, int]
    """(start, stop) sample indices the tracking would use."""
    notes: list[str]
    """The tracker's notes on it (a clipped gate, a rival echo)."""
    rival_sample: int | None
    """Sample of a rival echo's envelope peak (see :func:`rival_echo`), else None."""


def gate_preview(codes: np.ndarray, sample_rate_hz: float,
                 options: TrackingOptions | None = None) -> GatePreview:
    """The gate :func:`track_echoes` would track in on this record, and its notes on it.

    codes: (n_pulses, n_samples) raw digitizer codes (a few pulses suffice: the automatic
        gate looks at the first 8). sample_rate_hz: digitizer sample rate (Hz).
    Returns a :class:`GatePreview` (gate, notes, rival echo's sample). For the live A-scan
    while the operator places the transducers; raises ValueError like :func:`track_echoes`
    (flat echoes, a gate that does not fit).
    """
    opts = options or TrackingOptions()
    codes = np.asarray(codes)
    if codes.ndim != 2 or codes.shape[0] < 1 or codes.shape[1] < 32:
        raise ValueError(f"codes must be (n_pulses, n_samples >= 32), got shape {codes.shape}")
    codes, _ = _zero_segments_not_finite(codes)
    notes: list[str] = []
    start, stop, rival = _choose_gate(codes, float(sample_rate_hz), opts, notes)
    return GatePreview((start, stop), notes, rival)


# --------------------------------------------------------------------------------------------
# Public entry point


def track_echoes(codes: np.ndarray, trigger_offset_s: np.ndarray | None, sample_rate_hz: float,
                 speed_of_sound_m_s: float, volts_per_count: float = 1.0,
                 options: TrackingOptions | None = None) -> TrackingResult:
    """Bone displacement per pulse from one channel's segmented echo record (thesis ch. 8.3).

    codes: (n_pulses, n_samples) raw digitizer codes (int8/int16 or float).
    trigger_offset_s: (n_pulses,) per-segment horPos (s): time from the trigger to the first
        sample; None = all zero.
    sample_rate_hz: digitizer sample rate (Hz). speed_of_sound_m_s: c in the tissue (m/s).
    volts_per_count: scale of the codes; only ``echo_amplitude_v`` depends on it (delays,
        correlation and SNR are scale-free).
    Returns a :class:`TrackingResult`; ``displacement_m = -c/2 * (t_k - t_0)`` (positive toward
    the transducer, relative to the first pulse; thesis 8.2).
    """
    opts = options or TrackingOptions()
    if opts.estimator not in ESTIMATORS:
        raise ValueError(f"unknown estimator {opts.estimator!r}; choose one of {ESTIMATORS}")
    codes = np.asarray(codes)
    if codes.ndim != 2 or codes.shape[0] < 1 or codes.shape[1] < 32:
        raise ValueError(f"codes must be (n_pulses, n_samples >= 32), got shape {codes.shape}")
    n, m = codes.shape
    if trigger_offset_s is None:
        trigger_offset_s = np.zeros(n)
    trigger_offset_s = np.asarray(trigger_offset_s, dtype=float).reshape(-1)
    if trigger_offset_s.size != n:
        raise ValueError(f"{trigger_offset_s.size} trigger offsets for {n} segments")
    if not (sample_rate_hz > 0 and speed_of_sound_m_s > 0):
        raise ValueError("sample_rate_hz and speed_of_sound_m_s must be positive")
    fs = float(sample_rate_hz)
    L = int(opts.max_lag_samples)
    if L < _FINE_HALF + 2:
        raise ValueError(f"max_lag_samples must be >= {_FINE_HALF + 2}")
    warnings: list[str] = []
    codes, not_finite = _zero_segments_not_finite(codes)

    start, stop, _ = _choose_gate(codes, fs, opts, warnings)
    G = stop - start
    # Segments without signal (a digitizer that returned empty segments) or with samples
    # that are not numbers: lost, and said so (they were "left the recorded window: lower
    # the drive level", and one NaN sample lost every echo: tracking review, session 36).
    # A live segment is never constant over the gate, which holds the echo: 16 samples
    # across it suffice (18 us per 2000-segment record; every 4th sample took 150 us).
    probe = np.linspace(start, stop - 1, 16).astype(int)
    empty = not_finite | (np.ptp(codes[:, probe], axis=1) == 0)

    # the first echoes that hold a signal (empty segments left out of the reference)
    initial = np.flatnonzero(~empty)[: max(1, opts.initial_reference_echoes)]
    if initial.size == 0:
        initial = np.arange(min(n, max(1, opts.initial_reference_echoes)))
    first = np.asarray(codes[initial, start:stop], dtype=float)
    first_mean = first.mean(axis=0)
    if np.ptp(first_mean) == 0:
        raise ValueError(f"the gate ({start}, {stop}) of the first echoes is flat: no echo to "
                         "track (check the gate, the receiver gain and the record delay)")
    fc0 = _centre_frequency_hz(first_mean, fs)
    band_hz = opts.band_hz or (0.4 * fc0, 1.6 * fc0)
    band = _Band((float(band_hz[0]), float(band_hz[1])), int(opts.filter_order), fs)
    _band_sos(band.hz, band.order, fs)  # validates the band
    ref0 = _make_reference(first_mean, band)

    W = codes[:, start - L: stop + L]  # a view; converted to float32 once, sorted by lag
    clipped = _clipped(codes, start - L, ref0, L)
    if np.any(clipped):
        warnings.append(f"{int(clipped.sum())} echo(es) clipped at the digitizer's full scale: "
                        "lower the receiver gain")
    res, ref, groups = _track_block(W, ref0, L, opts, band, opts.reference_iterations)
    delay = res.delay + ref.offset
    corr, snr, lost_edge = res.corr, res.snr_db, res.edge.copy()
    shift = np.zeros(n, dtype=int)
    whole = np.ones(n, dtype=bool)
    n_reref = 0
    padded = None
    pad = G + 2 * L
    if np.any(lost_edge & ~empty) and opts.rereference:
        # Drift beyond the lag range: let the gate follow the echo (predicted per echo), in
        # a zero-padded record so that an echo partly past the record's edge stays tracked.
        padded = _pad_record(codes, pad)
        delay, corr, snr, lost_edge, shift, ref, groups, whole = _track_predicted(
            padded, pad, m, start, G, L, ref0, opts, band)
        warnings.append(f"echo drifted beyond +-{L} samples: gate followed it over "
                        f"{int(np.ptp(shift))} samples")
    elif np.any(lost_edge & ~empty):
        warnings.append(f"{int((lost_edge & ~empty).sum())} echo(es) left the +-{L}-sample "
                        "lag range")
    failed = lost_edge & (shift != 0)
    if np.any(failed):
        # Edges of echoes that have left the record do not mean the prediction failed.
        with np.errstate(invalid="ignore"):
            at = start + np.rint(np.where(np.isfinite(delay), delay, 0.0)).astype(int)
        failed &= _in_record_fraction(ref.q, at, m) >= opts.min_in_record
    if opts.rereference and (np.any(failed) or _shape_changed(
            groups, ~lost_edge & whole & (corr >= opts.min_correlation), opts.block_size, G,
            band)):
        # The echo changed shape along the record (or the drift prediction failed):
        # block-wise, rebuilding the reference whenever the correlation drops.
        if padded is None:
            padded = _pad_record(codes, pad)
        delay, corr, snr, lost_edge, shift, n_reref = _track_drifting(
            padded, pad, m, start, G, L, ref, opts, band)
        warnings.append(f"echo shape changed along the record: tracked block-wise with "
                        f"{n_reref} reference rebuild(s)")
    outside = np.zeros(n, dtype=bool)
    if padded is not None:
        # How much of each echo (the reference's energy at its delay) is inside the record:
        # below min_in_record the echo has left the recorded window and is lost.
        with np.errstate(invalid="ignore"):
            first = start + np.rint(np.where(np.isfinite(delay), delay, 0.0)).astype(int)
        inside = _in_record_fraction(ref.q, first, m)
        outside = np.isfinite(delay) & (inside < opts.min_in_record)
        # An echo that has left the record can be "found" at a wrong place where its last
        # lobes overlap the reference's tail: its least-squares amplitude on the in-record
        # samples is then far below that of the echoes wholly inside. Never silently wrong.
        cols = np.clip(pad + first, 0, padded.shape[1] - G)
        r = ref.unit_raw
        proj = np.einsum("ij,j->i", np.lib.stride_tricks.sliding_window_view(
            padded, G, axis=1)[np.arange(n), cols], r)
        e_in = _in_record_fraction(r, first, m)
        with np.errstate(divide="ignore", invalid="ignore"):
            amp = np.where(e_in > 0, proj / e_in, 0.0)
        full = np.isfinite(delay) & (e_in > 0.999)
        if np.count_nonzero(full) >= 8:
            weak = np.isfinite(delay) & ~outside & (amp < 0.5 * np.median(amp[full]))
            outside |= weak & (inside < 0.999)
            # A peak on a neighbouring correlation lobe (a carrier period off, possible when
            # the echo moved far and its shape changed) correlates far worse than the
            # echo's own: ~0.6 against > 0.95 measured on the simulated bench, whereas an
            # echo with 70 % of its energy in the record keeps ~0.84 of the typical value.
            typical = float(np.median(corr[full]))
            off_lobe = np.isfinite(delay) & ~outside & (corr < 0.75 * typical)
            if np.any(off_lobe):
                warnings.append(
                    f"{int(off_lobe.sum())} echo(es) correlate below 75 % of the typical "
                    f"{typical:.2f} after large motion (possibly a carrier period off): "
                    "marked lost")
            lost_edge = lost_edge | off_lobe
        outside &= ~empty  # said below, for what it is
        if np.any(outside):
            late = outside & (first > start)
            side = ("after the record's end (echo arrives later than the record lasts)"
                    if np.all(late[outside]) else
                    "before the record's start (echo arrives earlier than the record "
                    "begins)" if not np.any(late[outside]) else
                    "on both sides of the record")
            warnings.append(
                f"{int(outside.sum())} echo(es) ({100.0 * outside.mean():.1f} %) left the "
                f"recorded window ({m} samples = {m / fs * 1e6:.2f} us, "
                f"{0.5e3 * speed_of_sound_m_s * m / fs:.2f} mm of depth) {side}: "
                f"less than {100 * opts.min_in_record:.0f} % of the echo inside; marked "
                "lost. The motion is larger than the record: lower the drive level, or "
                "lengthen the record / move the record delay to centre the echo")
        lost_edge = lost_edge | outside

    if np.any(empty):
        warnings.append(
            f"{int(empty.sum())} segment(s) hold no signal (every sample the same"
            + (f"; {int(not_finite.sum())} with samples that are not numbers"
               if np.any(not_finite) else "")
            + "): empty digitizer segments? marked lost")
        lost_edge = lost_edge | empty

    period = 2.0 * np.pi / ref.omega
    hops = _peak_hops(delay, opts.hop_threshold_periods * period)
    if np.any(hops):
        # The echo cannot move a carrier period between pulses: put it back on the lobe
        # nearest its neighbours (whole periods), and keep the flag.
        local = _local_median(delay)
        delay = np.where(hops, delay - np.rint((delay - local) / period) * period, delay)
        warnings.append(f"{int(hops.sum())} peak hop(s) corrected by whole carrier periods")

    bad_offset = ~np.isfinite(trigger_offset_s)
    if np.any(bad_offset):
        warnings.append(f"{int(bad_offset.sum())} segment(s) without a finite trigger offset: "
                        "marked lost")
    # the offsets are the sub-sample trigger timing (interfaces.SegmentedRecord): a
    # segment's far from the others' is a misread, not a motion (one at 1e-6 s moved the
    # phase 44 deg, offsets in samples read as seconds gave metres, all unflagged:
    # tracking review, session 36)
    finite_offsets = trigger_offset_s[~bad_offset]
    if finite_offsets.size:
        typical_offset = float(np.median(finite_offsets))
        with np.errstate(invalid="ignore"):
            glitch = ~bad_offset & (np.abs(trigger_offset_s - typical_offset)
                                    > MAX_OFFSET_SPREAD_SAMPLES / fs)
        if np.any(glitch):
            warnings.append(
                f"{int(glitch.sum())} segment(s) with a trigger offset more than "
                f"{MAX_OFFSET_SPREAD_SAMPLES:g} samples from the record's typical "
                f"{typical_offset:.3g} s (largest {np.max(np.abs(trigger_offset_s[glitch])):.3g}"
                " s; a misread digitizer timing?): marked lost")
            bad_offset = bad_offset | glitch
    lost = lost_edge | (corr < opts.min_correlation) | ~np.isfinite(delay) | bad_offset
    low_correlation = lost & ~lost_edge & ~bad_offset
    if np.any(low_correlation):
        warnings.append(f"{int(np.sum(low_correlation))} echo(es) with correlation below "
                        f"{opts.min_correlation}")
    if padded is not None:
        short = _short_stretches(lost)
        if np.any(short):
            lost = lost | short
            warnings.append(
                f"{int(short.sum())} echo(es) in stretches of fewer than 16 tracked echoes "
                "between losses (cannot be checked against their neighbours): marked lost")
        off_lobe = _inconsistent_runs(delay, lost, period)
        if np.any(off_lobe):
            lost = lost | off_lobe
            warnings.append(
                f"{int(off_lobe.sum())} echo(es) in stretches that do not join their "
                "neighbours across a gap (carrier lobe ambiguous after the echo was lost): "
                "marked lost")
    t = delay / fs + trigger_offset_s
    t = np.where(lost, np.nan, t)
    valid = np.nonzero(~lost)[0]
    if valid.size == 0:
        warnings.append("no echo could be tracked")
        t0 = np.nan
    else:
        t0 = t[valid[0]]
        if valid[0] != 0:
            warnings.append(f"pulse 0 lost: displacement relative to pulse {valid[0]}")
    rel = t - t0
    # where the echo sits in the record: the gate's centre (the reference echo's position,
    # symmetric about its envelope peak) plus the mean tracked delay (drift moves it)
    echo_time_s = (0.5 * (start + stop) / fs
                   + (float(np.nanmean(t)) if valid.size else float("nan")))
    return TrackingResult(
        displacement_m=-0.5 * speed_of_sound_m_s * rel, delay_s=rel, gate=(start, stop),
        correlation=corr, snr_db=snr, peak_hops=hops, lost=lost, gate_shift_samples=shift,
        n_rereferences=n_reref, center_frequency_hz=ref.omega * fs / (2.0 * np.pi),
        sample_rate_hz=fs, speed_of_sound_m_s=float(speed_of_sound_m_s),
        estimator=opts.estimator,
        echo_amplitude_v=float(np.max(np.abs(ref.q + 1j * ref.q_hilbert)) * volts_per_count),
        clipped=clipped, warnings=warnings, echo_time_s=echo_time_s)


def _clipped(codes: np.ndarray, w0: int, ref: _Reference, L: int) -> np.ndarray:
    """Echoes whose samples near the echo peak reach the integer code limits."""
    if codes.dtype.kind not in "iu":
        return np.zeros(codes.shape[0], dtype=bool)
    info = np.iinfo(codes.dtype)
    if codes.flags.c_contiguous and codes.max() < info.max and codes.min() > info.min:
        # Nothing clipped anywhere: the usual case, and a contiguous pass over the whole
        # record was measured 3x faster than one over the strided rows near the peak.
        return np.zeros(codes.shape[0], dtype=bool)
    k = w0 + L + int(np.argmax(np.abs(ref.unit_raw)))
    # The peak moves at most L samples: look at +-(L + 2 carrier periods) around it.
    half = L + int(4 * np.pi / ref.omega)
    lo = max(0, k - half)
    seg = codes[:, lo: lo + 2 * half]
    if seg.max() < info.max and seg.min() > info.min:  # the usual case: one pass, no rows
        return np.zeros(codes.shape[0], dtype=bool)
    return (seg.max(axis=1) >= info.max) | (seg.min(axis=1) <= info.min)


def _short_stretches(lost: np.ndarray, min_len: int = 16, max_gap: int = 3) -> np.ndarray:
    """Tracked echoes in stretches shorter than ``min_len`` (stretches joined across gaps of
    up to ``max_gap`` lost echoes): fragments of an echo that is mostly outside the record or
    not found, whose lobe cannot be checked (``_inconsistent_runs``)."""
    ok = np.nonzero(~lost)[0]
    out = np.zeros(lost.size, dtype=bool)
    if ok.size == 0:
        return out
    cuts = np.nonzero(np.diff(ok) > max_gap + 1)[0] + 1
    for run in np.split(ok, cuts):
        if run.size < min_len:
            out[run] = True
    return out


def _inconsistent_runs(delay: np.ndarray, lost: np.ndarray, period: float) -> np.ndarray:
    """Tracked stretches that are not on the same correlation lobe as most of the record.

    An echo leaves the record through one of its ends and can only come back through the
    same end (to reach the other it would have to cross the record, tracked), so the delay
    after a gap continues the one before it; between consecutive tracked echoes the bone
    moves far less than a quarter carrier period. A jump larger than that means one side is
    on a neighbouring lobe (whole periods off) or lost its way. Stretches are labelled by
    their lobe relative to the first (whole periods, a new label when the jump is not close
    to whole periods) and those outside the label with most echoes are returned (to be
    marked lost: which side is right cannot be told from the echoes alone).
    """
    ok = np.nonzero(~lost & np.isfinite(delay))[0]
    out = np.zeros(delay.size, dtype=bool)
    if ok.size < 2:
        return out
    jump = np.diff(delay[ok])
    breaks = np.nonzero(np.abs(jump) > 0.25 * period)[0]
    if breaks.size == 0:
        return out
    whole = np.rint(jump[breaks] / period)
    near = np.abs(jump[breaks] - whole * period) <= 0.25 * period
    labels = np.zeros(breaks.size + 1, dtype=float)
    fresh = 1e6  # labels for stretches whose jump is not near whole periods
    for i, (w, good) in enumerate(zip(whole.tolist(), near.tolist(), strict=True)):
        if good:
            labels[i + 1] = labels[i] + w
        else:
            labels[i + 1] = fresh
            fresh += 1e6
    edges = np.concatenate([[0], breaks + 1, [ok.size]])
    sizes = np.diff(edges)
    values, inverse = np.unique(labels, return_inverse=True)
    best = int(np.argmax(np.bincount(inverse, weights=sizes)))
    for i in np.nonzero(inverse != best)[0]:
        out[ok[edges[i]: edges[i + 1]]] = True
    return out


def _local_median(x: np.ndarray, half: int = 2) -> np.ndarray:
    """Median of each value's ``2*half`` neighbours (itself excluded); gaps interpolated."""
    n = x.size
    ok = np.isfinite(x)
    if n < 3 or not np.any(ok):
        return x.copy()
    idx = np.arange(n)
    filled = np.where(ok, x, np.interp(idx, idx[ok], x[ok]))
    pad = np.concatenate([np.full(half, filled[0]), filled, np.full(half, filled[-1])])
    win = np.lib.stride_tricks.sliding_window_view(pad, 2 * half + 1)
    neigh = np.concatenate([win[:, :half], win[:, half + 1:]], axis=1)
    return np.median(neigh, axis=1)


def _peak_hops(delay: np.ndarray, threshold: float) -> np.ndarray:
    if delay.size < 3:
        return np.zeros(delay.size, dtype=bool)
    # A hop shows as a jump between neighbours; skip the median filter when there is none.
    with np.errstate(invalid="ignore"):
        if not np.any(np.abs(np.diff(delay)) > threshold):
            return np.zeros(delay.size, dtype=bool)
    dev = np.abs(delay - _local_median(delay))
    return np.nan_to_num(dev, nan=0.0) > threshold


def _rebuild_level(rho_ref: float) -> float:
    """Correlation below which the echo is taken to have changed shape."""
    return rho_ref - max(0.01, 1.0 - rho_ref)


def _shape_changed(g: _Groups, good: np.ndarray, B: int, G: int, band: _Band) -> bool:
    """True when the aligned mean echo of the first ``B`` good echoes and that of the last
    ``B`` differ in shape: their band-passed correlation is below 0.99 (two means of 32
    echoes of one shape correlate above 0.998 down to ~6 dB)."""
    rows = np.nonzero(good)[0]  # acquisition order
    if rows.size < 4 * B:
        return False
    inv = g.inverse()
    h = _FINE_HALF
    means = [g.A[inv[r], h: h + G].mean(axis=0) for r in (rows[:B], rows[-B:])]
    nfft = int(sp_fft.next_fast_len(2 * G, real=True))
    spec = np.fft.rfft(np.array(means) - np.mean(means, axis=1, keepdims=True), nfft, axis=1)
    spec *= _power_response(band.hz, band.order, band.fs, nfft)
    a, b = spec
    num = np.real(np.vdot(a, b))
    den = np.sqrt(np.real(np.vdot(a, a)) * np.real(np.vdot(b, b)))
    return bool(den > 0 and num / den < 0.99)


def _pad_record(codes: np.ndarray, pad: int) -> np.ndarray:
    """The record minus its mean (DC offset), with ``pad`` zero samples on both sides
    (float32).

    Windows cut from it never leave the array: an echo partly outside the record keeps the
    samples it has, and ``_truncated_correlation`` makes its delay estimate unbiased.
    """
    n, m = codes.shape
    out = np.zeros((n, m + 2 * pad), dtype=np.float32)
    out[:, pad: pad + m] = codes
    out[:, pad: pad + m] -= np.float32(out[:, pad: pad + m].mean(dtype=np.float64))
    return out


def _in_record_fraction(q: np.ndarray, first: np.ndarray, m: int) -> np.ndarray:
    """Fraction of the reference's energy inside the record [0, m) when its first sample is
    at record column ``first`` (any shape, integer)."""
    cum = np.concatenate([[0.0], np.cumsum(q.astype(float) ** 2)])
    G = q.size
    lo = np.clip(-first, 0, G)
    hi = np.clip(m - first, 0, G)
    return (cum[hi] - cum[lo]) / cum[-1]


# Coarse search: positions where less of the reference's energy than this lies in the record
# are not considered (an echo mostly outside the record is not found, rather than found wrong).
_COARSE_MIN_FRACTION = 0.15


def _follow_lobes(coarse: np.ndarray, strong: np.ndarray, period: float,
                  gap: int = 16) -> np.ndarray:
    """Put each echo's coarse position on the correlation lobe that continues the motion.

    Between pulses the bone moves far less than a quarter carrier period (at 5 kHz PRF,
    0.25 period = 38 um per pulse = 0.19 m/s), but a single echo's correlation peak can sit
    on a neighbouring lobe, a whole period off, and when the echo is partly cut by the
    record's edge whole stretches of echoes can: a neighbour median cannot fix those. So the
    positions are unwrapped sequentially modulo the period against a prediction (the median
    of the last 5 accepted positions), starting from the first 8 echoes' median. An echo
    further than a quarter period from the prediction after unwrapping is not accepted (it
    does not move the prediction) but still gets its nearest lobe. After ``gap`` echoes
    without an accepted one the prediction restarts from the absolute position. Echoes that
    are not ``strong`` (correlation peak below half the record's 90th percentile: no clear
    echo) keep their absolute position and do not move the prediction.
    """
    out = coarse.copy()
    pred = float(np.median(coarse[:8]))
    recent = [pred] * 5
    quarter = 0.25 * period
    last = 0
    for k, x in enumerate(coarse.tolist()):
        if not strong[k]:
            continue  # no clear echo (out of the record, noise): absolute position, no update
        if k - last > gap:
            # Lost for a while (echo out of the record): the motion since is unknown, the
            # absolute position is the best guess; restart from it.
            pred = x
            recent = [x] * 5
        y = x - period * round((x - pred) / period)
        out[k] = y
        if abs(y - pred) <= quarter:
            recent[k % 5] = y
            pred = sorted(recent)[2]
            last = k
    return out


def _track_predicted(padded: np.ndarray, pad: int, m: int, start: int, G: int, L: int,
                     ref: _Reference, opts: TrackingOptions, band: _Band) -> tuple:
    """Track echoes that drift beyond the lag range, all at once.

    ``padded``: the record with ``pad`` zeros each side (``_pad_record``), ``m`` samples long
    in between; ``start``: the gate start in record columns.

    1. every echo: correlation over every position where at least half of the reference's
       energy falls inside the record (every 4th lag, on 2x-decimated samples), divided by
       the square root of that in-record energy so that an echo partly cut off by the
       record's edge is still found where it is; whole-period hops removed against the
       neighbours' median;
    2. per-echo gate offset = that trajectory rounded;
    3. each echo's window is cut at its own offset (zeros outside the record) and the fine
       pass runs on them with the first pass's reference; echoes cut by the record's edge get
       the energy-normalised fine correlation.
    Returns delay, corr, snr, edge, shift, ref, groups and ``whole`` (window inside record).
    """
    n, M = padded.shape
    sp = start + pad  # gate start in padded columns
    par = sp % 2
    lags = np.arange(-(sp - par), M - sp - G + 1, 4)
    frac = _in_record_fraction(ref.q, start + lags, m)
    keep = frac >= _COARSE_MIN_FRACTION
    lags, frac = lags[keep], frac[keep]
    # Rows of the decimated record that the kept lags touch only (smaller product).
    r0 = (sp - par + int(lags[0])) // 2
    T = _toeplitz(ref.q[::2], (lags - lags[0]) // 2, 0)
    C = padded[:, par + 2 * r0: par + 2 * (r0 + T.shape[0]): 2] @ T
    C /= np.sqrt(frac).astype(np.float32)
    coarse = lags[np.argmax(C, axis=1)].astype(float)
    period = 2.0 * np.pi / ref.omega
    peak = C.max(axis=1)
    coarse = _follow_lobes(coarse, peak >= 0.5 * np.percentile(peak, 90), period)
    offset = np.rint(coarse).astype(int)
    width = G + 2 * L
    col0 = np.clip(sp + offset - L, 0, M - width)
    windows = np.lib.stride_tricks.sliding_window_view(padded, width, axis=1)
    W = windows[np.arange(n), col0]
    valid = (pad - col0, pad + m - col0)
    whole = (valid[0] <= 0) & (valid[1] >= width)
    # ``ref`` is the mean of the first echoes (not the first pass's aligned mean: with large
    # motion some of its echoes sit a carrier period off inside the lag range, and a rebuild
    # from the often one-sided set of echoes wholly inside the record was measured to bias
    # the cut echoes' least-squares delays by 0.24-2.2 samples, noise-free, echo walking
    # 200-235 samples to one end of the record; <= 0.04 with this reference). Its noise
    # (1/8 of an echo's variance) adds ~6 % to the per-echo jitter on this path only.
    res, ref, groups = _track_block(W, ref, L, opts, band, 0, valid)
    shift = col0 + L - sp
    delay = shift + res.delay + ref.offset
    return delay, res.corr, res.snr_db, res.edge, shift, ref, groups, whole


def _track_drifting(padded: np.ndarray, pad: int, m: int, start: int, G: int, L: int,
                    ref: _Reference, opts: TrackingOptions,
                    band: _Band) -> tuple[np.ndarray, ...]:
    """Block-wise tracking whose gate follows the echo; the reference is rebuilt at each move.

    ``padded``: the record with ``pad`` zeros each side; ``start``: gate start in record
    columns. Delays stay on one scale: each new reference's position relative to the first is
    carried in ``_Reference.offset`` (mean sub-sample residual of the echoes it was averaged
    from), the gate's move in ``offset_gate``. References are built from echoes wholly inside
    the record only.

    A block shares one gate, so when its window reaches past the record's edge every echo in
    it is cut and none is left to calibrate the cut-echo path on (:func:`_cut_calibration`):
    such a block is calibrated on the good echoes of the latest block that lay wholly inside
    the record (re-tracked with the current reference).
    """
    codes = padded
    n, M = padded.shape
    start = start + pad
    B = max(8, int(opts.block_size))
    delay = np.full(n, np.nan)
    corr = np.zeros(n)
    snr = np.full(n, -np.inf)
    lost = np.ones(n, dtype=bool)
    shift = np.zeros(n, dtype=int)
    offset_gate = 0
    n_reref = 0
    rho_ref: float | None = None
    # Windows of the latest whole block's good echoes. Without them a block cut by the
    # record's edge had no zero for its in-record delays: blocks came out ~1.5 samples off
    # (reference echo itself cut by the record's start; docs/tracking.md).
    calibration: np.ndarray | None = None
    step = max(1, min(opts.coarse_lag_step, L))
    for b0 in range(0, n, B):
        rows = slice(b0, min(n, b0 + B))
        res = None
        for attempt in range(3):
            lo = start + offset_gate - L
            if lo < 0 or lo + G + 2 * L > M:
                res = None
                break  # the echo left the record: these stay lost
            W = codes[rows, lo: lo + G + 2 * L]
            nb = W.shape[0]
            valid = (np.full(nb, pad - lo), np.full(nb, pad + m - lo))
            whole = bool(valid[0][0] <= 0 and valid[1][0] >= W.shape[1])
            res, _, _ = _track_block(W, ref, L, opts, band, 0, valid, calibration)
            if attempt == 2 or not np.any(res.edge):
                break
            if np.mean(res.edge) > 0.5:
                # Moved further than the lag range within a block: wide coarse search.
                wide = min(4 * L, int(0.45 * 2 * np.pi / ref.omega))
                lo_w = max(0, start + offset_gate - wide)
                hi_w = min(M, start + offset_gate + G + wide)
                left = start + offset_gate - lo_w
                lags = np.arange(-left, hi_w - lo_w - G - left + 1, step)
                if lags.size < 2:
                    break
                T = _toeplitz(ref.q, lags, left)
                C = codes[rows, lo_w: lo_w + T.shape[0]].astype(np.float32) @ T
                offset_gate += int(np.median(lags[np.argmax(C, axis=1)]))
            else:
                # Part of the block ran off the range: centre the gate on the block's spread.
                lags_ok = res.lag[~res.edge]
                offset_gate += int(np.rint(0.5 * (lags_ok.min() + lags_ok.max())))
        if res is None:
            continue
        ok = ~res.edge
        delay[rows] = np.where(ok, offset_gate + res.delay + ref.offset, np.nan)
        corr[rows], snr[rows], lost[rows] = res.corr, res.snr_db, ~ok
        shift[rows] = offset_gate
        good = ok & (res.corr >= opts.min_correlation)
        if rho_ref is None and whole and np.count_nonzero(good) >= 4:
            # Start from this block's own echo shape, not a whole-record average.
            new = _aligned_reference(_Groups.build(W, res.lag, G), res.delay, good, G, band,
                                     ref.offset)
            if new is not None:
                ref = new
                res, _, _ = _track_block(W, ref, L, opts, band, 0, valid)
                ok = ~res.edge
                delay[rows] = np.where(ok, offset_gate + res.delay + ref.offset, np.nan)
                corr[rows], snr[rows], lost[rows] = res.corr, res.snr_db, ~ok
                good = ok & (res.corr >= opts.min_correlation)
        if whole and np.count_nonzero(good) >= _CUT_CALIBRATION_MIN_ECHOES:
            calibration = W[good]  # the nearest in time: the echo shape the next blocks have
        if np.count_nonzero(good) >= 4:
            rho = float(np.median(res.corr[good]))
            if rho_ref is None:
                rho_ref = rho
            elif whole and rho < _rebuild_level(rho_ref):
                # The echo no longer looks like the reference: rebuild it from the newer half
                # of this block (closest to what follows), then re-track the block with it
                # and keep, per echo, the better-correlated estimate.
                recent = good & (np.arange(good.size) >= good.size // 2)
                if np.count_nonzero(recent) < 4:
                    recent = good
                new = _aligned_reference(_Groups.build(W, res.lag, G), res.delay, recent, G,
                                         band, ref.offset)
                if new is not None:
                    # Its position relative to the old one (mean residual) is in its offset;
                    # gate moves are carried by offset_gate, so delays stay on one scale.
                    ref, rho_ref = new, None
                    n_reref += 1
                    res2, _, _ = _track_block(W, ref, L, opts, band, 0, valid)
                    better = ~res2.edge & (res2.corr > corr[rows])
                    d2 = offset_gate + res2.delay + ref.offset
                    delay[rows] = np.where(better, d2, delay[rows])
                    snr[rows] = np.where(better, res2.snr_db, snr[rows])
                    lost[rows] = np.where(better, False, lost[rows])
                    corr[rows] = np.where(better, res2.corr, corr[rows])
            # Follow the echo to where the block ENDS (a steady drift keeps going). An
            # integer gate move leaves the reference valid: no rebuild, no error added.
            tail = np.nonzero(good)[0][-max(4, B // 8):]
            move = int(np.rint(np.median(res.lag[tail])))
            if abs(move) >= 2:
                offset_gate += move
    return delay, corr, snr, lost, shift, n_reref
