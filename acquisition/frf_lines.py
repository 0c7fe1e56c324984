"""FRF lines from displacement and force phasors, and their assembly into the /frf set.

One stepped-sine step gives, per ultrasound channel, the displacement phasor ``X`` (m, peak,
referred to the first pulse; :mod:`pelvislab.acquisition.phasor`) and one force phasor ``F``
(N, same time origin). The receptance line is ``H = X / F`` (m/N, design 4.1/4.2) with the
first-order standard uncertainty of the complex ratio for independent ``X`` and ``F``::

    H_std^2 = E|H_hat - H|^2 = std_X^2 / |F|^2 + |H|^2 std_F^2 / |F|^2

Lines are assembled into :class:`pelvislab.acquisition.frfset.FrfSet` (the one FRF container).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pelvislab.acquisition.frfset import Channels, FrfSet
from pelvislab.acquisition.phasor import Phasor, estimate_phasor
from pelvislab.acquisition.tracking import TrackingResult


@dataclass(frozen=True)
class FrfLine:
    """One measured receptance value H (m/N) at one frequency for one (output, input) pair."""

    frequency_hz: float
    output: str
    input: str
    H: complex
    H_std: float
    acquired_at_s: float = float("nan")


def frf_ratio(x: complex, x_std: float, f: complex, f_std: float) -> tuple[complex, float]:
    """``H = x / f`` and its standard uncertainty sqrt(E|H_hat - H|^2) (first order)."""
    if f == 0:
        raise ValueError("force phasor is zero: no FRF line")
    H = complex(x) / complex(f)
    std = float(np.sqrt(x_std**2 + abs(H) ** 2 * f_std**2) / abs(f))
    return H, std


def frf_line(displacement: Phasor, force: Phasor, output: str, input: str,
             acquired_at_s: float = float("nan")) -> FrfLine:
    """Receptance line ``X / F`` from a displacement phasor (m) and a force phasor (N)."""
    if not np.isclose(displacement.frequency_hz, force.frequency_hz, rtol=1e-9, atol=0.0):
        raise ValueError(f"displacement at {displacement.frequency_hz} Hz but force at "
                         f"{force.frequency_hz} Hz")
    H, std = frf_ratio(displacement.value, displacement.std, force.value, force.std)
    return FrfLine(float(displacement.frequency_hz), str(output), str(input), H, std,
                   float(acquired_at_s))


def drive_force_phasor(frequency_hz: float, drive_amplitude_vpp: float,
                       newton_per_volt: complex, drive_phase_rad: float = 0.0,
                       newton_per_volt_std: float = 0.0) -> Phasor:
    """Force phasor (N) from the calibrated drive chain (design 2: volts -> amperes -> newtons).

    drive_amplitude_vpp: generator output, volts peak-to-peak; drive_phase_rad: phase of the
    drive sine at the first pulse (the SYNC-triggered burst fixes it); newton_per_volt: complex
    calibration (N per volt peak) at this frequency, with its standard uncertainty.
    """
    if not drive_amplitude_vpp > 0:
        raise ValueError(f"drive amplitude must be positive, got {drive_amplitude_vpp} Vpp")
    volts = 0.5 * drive_amplitude_vpp * np.exp(1j * drive_phase_rad)
    F = complex(newton_per_volt) * volts
    std = float(abs(volts) * newton_per_volt_std)
    nan2 = np.full(2, np.nan)
    return Phasor(frequency_hz=float(frequency_hz), value=F, std=std,
                  amplitude_std=std / np.sqrt(2.0),
                  phase_std_rad=std / np.sqrt(2.0) / abs(F) if F != 0 else np.pi,
                  harmonics=nan2 + 0j, harmonics_std=nan2, distortion=nan2, thd=float("nan"),
                  offset=0.0, residual_rms=0.0, n_used=0, method="calibration")


def drive_calibration_at(frequency_hz: float | np.ndarray,
                         table_frequency_hz: Sequence[float] | np.ndarray,
                         table_newton_per_volt: Sequence[complex] | np.ndarray) -> np.ndarray:
    """Drive-chain calibration (N per V peak, complex) at ``frequency_hz`` from a table
    measured at ``table_frequency_hz`` (Hz, strictly increasing, at least two rows).

    Between rows, log|N/V| and the unwrapped phase are interpolated linearly in frequency
    (a transfer function's magnitude and phase vary smoothly; interpolating real and
    imaginary parts would dip the magnitude where the phase turns). No extrapolation: a
    frequency outside the table (beyond a relative 1e-9) raises ValueError, since an
    amplifier/shaker chain's roll-off beyond what was measured is not known.
    """
    f_tab = np.asarray(table_frequency_hz, dtype=float)
    g_tab = np.asarray(table_newton_per_volt, dtype=complex)
    if f_tab.ndim != 1 or f_tab.shape != g_tab.shape or len(f_tab) < 2:
        raise ValueError("a drive calibration table needs at least two rows of "
                         "(frequency_hz, N/V) of equal length")
    if not (np.all(np.isfinite(f_tab)) and np.all(np.diff(f_tab) > 0)):
        raise ValueError("the drive calibration's frequencies must be finite and increase "
                         "strictly")
    if not (np.all(np.isfinite(g_tab)) and np.all(g_tab != 0)):
        raise ValueError("the drive calibration's values must be finite and non-zero")
    f = np.asarray(frequency_hz, dtype=float)
    lo, hi = f_tab[0], f_tab[-1]
    tol = 1e-9 * hi
    outside = ~((f >= lo - tol) & (f <= hi + tol))
    if np.any(outside):
        bad = np.atleast_1d(f)[np.atleast_1d(outside)]
        raise ValueError(f"{bad[0]:g} Hz is outside the drive calibration's range "
                         f"{lo:g}-{hi:g} Hz (not extrapolated)")
    fc = np.clip(f, lo, hi)
    log_mag = np.interp(fc, f_tab, np.log(np.abs(g_tab)))
    phase = np.interp(fc, f_tab, np.unwrap(np.angle(g_tab)))
    return np.exp(log_mag + 1j * phase)


def calibrated_newton_per_volt(frequency_hz: float, newton_per_volt: complex,
                               table_frequency_hz: Sequence[float] = (),
                               table_newton_per_volt: Sequence[complex] = ()) -> complex:
    """The drive chain's N/V at ``frequency_hz``: the table's value
    (:func:`drive_calibration_at`) when a table is given, else the one constant
    ``newton_per_volt`` (a bench file's ``drive_newton_per_volt``)."""
    if len(table_frequency_hz):
        return complex(drive_calibration_at(frequency_hz, table_frequency_hz,
                                            table_newton_per_volt))
    return complex(newton_per_volt)


def bone_sampling_delay_s(record_delay_s: float, tracking: TrackingResult) -> float:
    """When a pulse samples the bone, s after the pulse leaves (the trigger): half the echo's
    round trip, ``(record_delay_s + tracking.echo_time_s) / 2``.

    The echo reports where the bone was when the pulse reached it, one way (depth / c)
    after the pulse: 5.3 us under 8.2 mm of tissue, 26 us under 40 mm. Taking it as the
    pulse's own time turns the phasor by +omega * delay: 0.05 rad (5 % of |H|, in
    quadrature) at 300 Hz under 40 mm, beyond the noise of a good line.
    record_delay_s: the record's start after the trigger (``echoes`` attribute ``delay_s``,
    design 4.2). NaN (no echo tracked) gives 0.
    """
    delay = 0.5 * (float(record_delay_s) + float(getattr(tracking, "echo_time_s", np.nan)))
    return delay if np.isfinite(delay) else 0.0


def displacement_phasor(tracking: TrackingResult, prf_hz: float, frequency_hz: float,
                        sampling_delay_s: float = 0.0, **options: object) -> Phasor:
    """Displacement phasor (m) of a tracked record at the drive frequency, referred to the
    first pulse (design 4.2).

    Pulse ``k`` leaves at ``k / prf_hz`` after the first pulse (the ns trigger offsets are
    negligible on this time scale) and samples the bone ``sampling_delay_s`` later
    (:func:`bone_sampling_delay_s`; 0 for a motion that was sampled at the pulses);
    lost echoes (NaN) are dropped, which selects the least-squares fit. ``options`` go to
    :func:`estimate_phasor`.
    """
    n = tracking.displacement_m.size
    return estimate_phasor(tracking.displacement_m,
                           np.arange(n) / float(prf_hz) + float(sampling_delay_s),
                           frequency_hz, **options)  # type: ignore[arg-type]


def _combine(values: list[complex], stds: list[float]) -> tuple[complex, float]:
    """Inverse-variance mean of repeated lines (plain mean when any std is unknown)."""
    v = np.asarray(values, dtype=complex)
    s = np.asarray(stds, dtype=float)
    if v.size == 1:
        return complex(v[0]), float(s[0])
    if np.all(np.isfinite(s) & (s > 0)):
        w = 1.0 / s**2
        return complex(np.sum(w * v) / w.sum()), float(1.0 / np.sqrt(w.sum()))
    return complex(v.mean()), float("nan")


def assemble_frf(lines: Sequence[FrfLine], outputs: Channels, inputs: Channels,
                 attrs: dict[str, object] | None = None) -> FrfSet:
    """FrfSet (design 4.2) holding ``lines``; NaN where a pair was not measured.

    Frequencies are the sorted distinct line frequencies (equal within 1e-9 relative).
    Repeated (frequency, output, input) lines are merged by inverse-variance weighting;
    ``acquired_at_s`` per frequency is the earliest of its lines.
    """
    if not lines:
        raise ValueError("no FRF lines to assemble")
    freqs = np.array(sorted({float(line.frequency_hz) for line in lines}))
    # Merge frequencies that differ by rounding only.
    keep = np.r_[True, np.diff(freqs) > 1e-9 * np.maximum(freqs[1:], 1.0)]
    freqs = freqs[keep]
    n_f = freqs.size
    groups: dict[tuple[int, int, int], tuple[list[complex], list[float]]] = {}
    times = np.full(n_f, np.nan)
    for line in lines:
        i = int(np.argmin(np.abs(freqs - line.frequency_hz)))
        o, j = outputs.index(line.output), inputs.index(line.input)
        vals, stds = groups.setdefault((i, o, j), ([], []))
        vals.append(line.H)
        stds.append(line.H_std)
        if np.isfinite(line.acquired_at_s):
            times[i] = np.fmin(times[i], line.acquired_at_s)
    H = np.full((n_f, len(outputs), len(inputs)), np.nan + 0j)
    H_std = np.full(H.shape, np.nan)
    for (i, o, j), (vals, stds) in groups.items():
        H[i, o, j], H_std[i, o, j] = _combine(vals, stds)
    return FrfSet(frequency_hz=freqs, H=H, outputs=outputs, inputs=inputs, H_std=H_std,
                  acquired_at_s=times if np.any(np.isfinite(times)) else None,
                  attrs=dict(attrs or {}))
