"""Correlation of measured and model modes and FRFs (thesis ch. 14; MAC eq. 4.49).

MAC and the one-to-one mode pairing are the model core's (:mod:`pelvislab.model.modal`); this
module adds what correlation needs on top:

- :func:`comac` — coordinate MAC (Lieven & Ewins, IMAC VI 1988): per channel, how well the
  paired modes agree there (finds the sensor or point that spoils the correlation);
- :func:`frac` — frequency response assurance criterion per FRF (shape agreement of two
  FRFs over frequency, Heylen et al., "Modal analysis theory and testing", 1998);
- :func:`complexity` / :func:`complexity_plot` — modal complexity (MPC, MPD) and the complex
  plane view of the thesis' fig. 14.2;
- :func:`correlation_shapes` — the filtering of fig. 14.1: global rigid motion removed with the
  measured geometry, then each bone's rigid motion kept (``x_corr``), applied identically to
  measured and model shapes before MAC;
- :func:`correlate` — pairing table (MAC, frequency and damping differences, COMAC);
- :func:`mac_cost` — the updating cost of eq. 14.1, ``J = N_modes - sum MAC``.

Pure numerics on arrays; no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pelvislab.model.ema import modal_phase_collinearity
from pelvislab.model.modal import mac, pair_modes
from pelvislab.model.rigid_body import filter_bones, filter_global


def comac(shapes_a: np.ndarray, shapes_b: np.ndarray) -> np.ndarray:
    """COMAC per channel for paired columns of ``shapes_a`` and ``shapes_b`` (n_dof, n_pairs).

    ``COMAC_j = (sum_r |a_jr conj(b_jr)|)^2 / (sum_r |a_jr|^2 sum_r |b_jr|^2)``, in [0, 1].
    Each mode is first scaled onto its partner (modal scale factor), so arbitrary complex
    normalisation of either set does not matter.
    """
    a = np.asarray(shapes_a, dtype=complex)
    b = np.asarray(shapes_b, dtype=complex)
    a = a[:, None] if a.ndim == 1 else a
    b = b[:, None] if b.ndim == 1 else b
    if a.shape != b.shape:
        raise ValueError(f"paired shape sets differ: {a.shape} vs {b.shape}")
    # modal scale factor: b scaled to best match a
    msf = np.sum(a * b.conj(), axis=0) / np.maximum(np.sum(np.abs(b) ** 2, axis=0), 1e-300)
    b = b * msf[None, :]
    num = np.sum(np.abs(a * b.conj()), axis=1) ** 2
    den = np.sum(np.abs(a) ** 2, axis=1) * np.sum(np.abs(b) ** 2, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


def frac(H_a: np.ndarray, H_b: np.ndarray) -> np.ndarray:
    """FRAC per FRF: ``|sum_f H_a conj(H_b)|^2 / (sum_f |H_a|^2 sum_f |H_b|^2)``.

    ``H_a``, ``H_b`` (n_f, ...) on the same lines; lines where either is NaN are ignored.
    Returns the trailing shape (e.g. (n_out, n_in)); 1 = same FRF shape up to a factor.
    """
    a = np.asarray(H_a, dtype=complex)
    b = np.asarray(H_b, dtype=complex)
    if a.shape != b.shape:
        raise ValueError(f"FRF sets differ: {a.shape} vs {b.shape}")
    ok = np.isfinite(a) & np.isfinite(b)
    a = np.where(ok, a, 0.0)
    b = np.where(ok, b, 0.0)
    num = np.abs(np.sum(a * b.conj(), axis=0)) ** 2
    den = np.sum(np.abs(a) ** 2, axis=0) * np.sum(np.abs(b) ** 2, axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(den > 0, num / den, np.nan)


def complexity(shapes: np.ndarray) -> dict[str, np.ndarray]:
    """Modal complexity of shapes (n_dof, n_modes): MPC, MPD (deg) and ``1 - MPC``."""
    mpc, mpd = modal_phase_collinearity(shapes)
    return {"mpc": mpc, "mpd_deg": mpd, "complexity": 1.0 - mpc}


def complexity_plot(shape: np.ndarray, reference: int = 0) -> np.ndarray:
    """A shape scaled so entry ``reference`` is 1 (thesis fig. 14.2): plot real vs imaginary.

    A normal mode lies on a straight line through the origin; spread means complexity.
    """
    v = np.asarray(shape, dtype=complex).reshape(-1)
    if v[reference] == 0:
        raise ValueError(f"entry {reference} of the shape is zero; choose another reference")
    return v / v[reference]


def correlation_shapes(shapes: np.ndarray, bones: list[str], position_m: np.ndarray,
                       direction: np.ndarray) -> np.ndarray:
    """Shapes as correlated in the thesis (fig. 14.1): global rigid motion filtered out with
    the measured geometry (eq. 11.1-11.3), then each bone's rigid part kept (``x_corr``,
    eq. 11.5-11.6). Apply to measured and model shapes alike. Channels on no bone are NaN."""
    g = filter_global(shapes, position_m, direction)
    return filter_bones(g.x_el, bones, position_m, direction).x_corr


@dataclass
class Correlation:
    """Paired measured (a) and model (b) modes."""

    pairs: list[tuple[int, int]]  # (index in a, index in b)
    mac: np.ndarray  # (n_pairs,)
    frequency_error: np.ndarray  # (n_pairs,) f_a / f_b - 1
    damping_difference: np.ndarray  # (n_pairs,) zeta_a - zeta_b
    mac_matrix: np.ndarray  # (n_a, n_b)
    comac: np.ndarray  # (n_dof,) over the pairs

    def as_rows(self) -> list[dict[str, float | int]]:
        """Rows for JSON/tables."""
        return [{"measured": a, "model": b, "mac": float(m), "frequency_error": float(fe),
                 "damping_difference": float(dd)}
                for (a, b), m, fe, dd in zip(self.pairs, self.mac, self.frequency_error,
                                             self.damping_difference, strict=True)]


def correlate(frequency_a_hz: np.ndarray, shapes_a: np.ndarray, frequency_b_hz: np.ndarray,
              shapes_b: np.ndarray, damping_a: np.ndarray | None = None,
              damping_b: np.ndarray | None = None, min_mac: float = 0.0) -> Correlation:
    """Pair modes of two sets by maximum total MAC (the model core's Hungarian pairing).

    Shapes (n_dof, n_modes) at the same channels; NaN channels (e.g. on no bone) are ignored.
    """
    a = np.asarray(shapes_a, dtype=complex)
    b = np.asarray(shapes_b, dtype=complex)
    keep = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    a, b = a[keep], b[keep]
    pairs = pair_modes(a, b, min_mac=min_mac)
    fa = np.asarray(frequency_a_hz, dtype=float)
    fb = np.asarray(frequency_b_hz, dtype=float)
    za = np.zeros(fa.size) if damping_a is None else np.asarray(damping_a, dtype=float)
    zb = np.zeros(fb.size) if damping_b is None else np.asarray(damping_b, dtype=float)
    ia = np.array([p.a for p in pairs], dtype=int)
    ib = np.array([p.b for p in pairs], dtype=int)
    full_comac = np.full(keep.size, np.nan)
    if pairs:
        full_comac[keep] = comac(a[:, ia], b[:, ib])
    return Correlation(
        pairs=[(int(x), int(y)) for x, y in zip(ia, ib, strict=True)],
        mac=np.array([p.mac for p in pairs]),
        frequency_error=fa[ia] / fb[ib] - 1 if pairs else np.zeros(0),
        damping_difference=za[ia] - zb[ib] if pairs else np.zeros(0),
        mac_matrix=mac(a, b), comac=full_comac,
    )


def mac_cost(measured: np.ndarray, model: np.ndarray, pairs: list[tuple[int, int]]) -> float:
    """Thesis eq. 14.1: ``J = N_modes - sum_pairs MAC(x_corr, x_model,corr)``; 0 is perfect.

    ``measured``/``model`` (n_dof, n) are correlation shapes (:func:`correlation_shapes`);
    ``pairs`` lists (measured index, model index). NaN channels are ignored.
    """
    a = np.asarray(measured, dtype=complex)
    b = np.asarray(model, dtype=complex)
    keep = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    total = 0.0
    for i, j in pairs:
        total += float(mac(a[keep, i], b[keep, j])[0, 0])
    return float(len(pairs) - total)
