"""Rigid-body filtering of measured shapes (thesis ch. 11.3, eq. 11.1-11.7) and sensor checks.

A measured shape (a mode shape, or an operating deflection shape = one FRF line) holds one
complex value per channel: the displacement of a point ``p`` (m, model frame, design 4.1)
along a unit direction ``d``. A rigid motion (translation ``t``, small rotation ``theta``
about a reference point ``o``) moves the point by ``t + theta x (p - o)``, so the channel reads
``d . t + ((p - o) x d) . theta``: one row ``[d, (p - o) x d]`` of the geometric matrix ``R``.

- Global filtering (eq. 11.1-11.4): ``x_raw = R_g alpha_g + x_el``, least squares
  ``alpha_g = (R_g^T R_g)^-1 R_g^T x_raw``, global rigid-body content
  ``(||x_raw|| - ||x_el||) / ||x_raw||``.
- Bone filtering (eq. 11.5-11.7): per bone ``x_el,i = R_i alpha_i + x_res,i`` on that bone's
  channels; ``alpha_i`` (6 per bone, stacked: the 18 model DOFs of the shape), rigidity ratio
  ``(||x_el,i|| - ||x_res,i||) / ||x_el,i||`` and the filtered shape ``x_corr,i = R_i alpha_i``.
- Channel check (the thesis' leave-one-point-out test of ch. 11.3, made per channel): a
  channel is predicted from the rigid motion fitted to the other channels of its bone; a
  channel that rigid motion cannot explain is flagged, with the direction (and the position
  shift) that would explain it.

The reference point ``o`` defaults to the mean of the points involved (keeps ``R`` well
conditioned; rigid content and residuals do not depend on it). Pure numerics, no I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def rigid_body_matrix(position_m: np.ndarray, direction: np.ndarray,
                      reference_m: np.ndarray | None = None) -> np.ndarray:
    """Geometric rigid-body matrix R (n_channels, 6): columns t_x, t_y, t_z, theta_x..z.

    ``position_m`` (n, 3) metres, ``direction`` (n, 3) unit vectors; rotations are about
    ``reference_m`` (default: the mean position). Thesis eq. 11.1 (R_g) and 11.5 (R_i).
    """
    p = np.asarray(position_m, dtype=float).reshape(-1, 3)
    d = np.asarray(direction, dtype=float).reshape(-1, 3)
    o = p.mean(axis=0) if reference_m is None else np.asarray(reference_m, dtype=float)
    return np.hstack([d, np.cross(p - o, d)])


def _norms(x: np.ndarray) -> np.ndarray:
    return np.linalg.norm(x, axis=0)


def _content(x_in: np.ndarray, x_left: np.ndarray) -> np.ndarray:
    n_in = _norms(x_in)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n_in > 0, (n_in - _norms(x_left)) / n_in, np.nan)


@dataclass
class GlobalFilter:
    """Result of eq. 11.1-11.4 for shapes (n_channels, n_shapes)."""

    alpha: np.ndarray  # (6, n_shapes) rigid-body amplitudes (m, rad)
    x_el: np.ndarray  # (n_channels, n_shapes) what rigid motion does not explain
    rigid_content: np.ndarray  # (n_shapes,) eq. 11.4
    rank: int  # rank of R_g (6 when the geometry determines all rigid motions)


def _lstsq(R: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, int]:
    alpha, _, rank, _ = np.linalg.lstsq(R, x.astype(complex), rcond=1e-10)
    return alpha, int(rank)


def filter_global(shapes: np.ndarray, position_m: np.ndarray, direction: np.ndarray
                  ) -> GlobalFilter:
    """Remove the global rigid-body motion from measured shapes (thesis eq. 11.1-11.4)."""
    x = np.asarray(shapes)
    x = x[:, None] if x.ndim == 1 else x
    R = rigid_body_matrix(position_m, direction)
    if R.shape[0] != x.shape[0]:
        raise ValueError(f"shapes have {x.shape[0]} channels, geometry {R.shape[0]}")
    alpha, rank = _lstsq(R, x)
    x_el = x - R @ alpha
    return GlobalFilter(alpha, x_el, _content(x, x_el), rank)


@dataclass
class BoneFilter:
    """Result of eq. 11.5-11.7 for shapes (n_channels, n_shapes), per bone."""

    bones: list[str]  # the bones filtered, in order
    alpha: dict[str, np.ndarray]  # bone -> (6, n_shapes) rigid motion about the bone's points
    reference_m: dict[str, np.ndarray]  # bone -> (3,) rotation centre used for alpha
    rigidity: dict[str, np.ndarray]  # bone -> (n_shapes,) eq. 11.7
    x_corr: np.ndarray  # (n_channels, n_shapes) R_i alpha_i (NaN on channels of no bone)
    x_res: np.ndarray  # (n_channels, n_shapes) remnants
    rank: dict[str, int]

    def rigidity_table(self) -> np.ndarray:
        """(n_shapes, n_bones) rigidity ratios in ``bones`` order (thesis table 11.3)."""
        return np.stack([self.rigidity[b] for b in self.bones], axis=1)


def filter_bones(x_el: np.ndarray, bones: list[str], position_m: np.ndarray,
                 direction: np.ndarray) -> BoneFilter:
    """Rigid motion of each bone separately and its rigidity ratio (thesis eq. 11.5-11.7).

    ``x_el`` (n_channels, n_shapes): usually :func:`filter_global`'s ``x_el``. Channels on
    bone ``""`` are not filtered. A bone whose channels cannot determine all six rigid
    motions (fewer than 6 independent rows) is still filtered in the least-squares sense and
    reports ``rank < 6``.
    """
    x = np.asarray(x_el)
    x = x[:, None] if x.ndim == 1 else x
    p = np.asarray(position_m, dtype=float).reshape(-1, 3)
    d = np.asarray(direction, dtype=float).reshape(-1, 3)
    if not (len(bones) == p.shape[0] == d.shape[0] == x.shape[0]):
        raise ValueError("bones, positions, directions and shapes disagree in channel count")
    names = [b for b in dict.fromkeys(bones) if b]
    alpha: dict[str, np.ndarray] = {}
    ref: dict[str, np.ndarray] = {}
    rigidity: dict[str, np.ndarray] = {}
    rank: dict[str, int] = {}
    x_corr = np.full(x.shape, np.nan + 0j)
    x_res = np.full(x.shape, np.nan + 0j)
    for bone in names:
        idx = np.array([k for k, b in enumerate(bones) if b == bone])
        ref[bone] = p[idx].mean(axis=0)
        R = rigid_body_matrix(p[idx], d[idx], ref[bone])
        a, rank[bone] = _lstsq(R, x[idx])
        alpha[bone] = a
        x_corr[idx] = R @ a
        x_res[idx] = x[idx] - x_corr[idx]
        rigidity[bone] = _content(x[idx], x_res[idx])
    return BoneFilter(names, alpha, ref, rigidity, x_corr, x_res, rank)


@dataclass
class ChannelCheck:
    """Per-channel rigid-motion consistency (leave one channel out, per bone)."""

    relative_residual: np.ndarray  # (n_channels,) misfit / bone RMS amplitude; NaN: unchecked
    flagged: np.ndarray  # (n_channels,) bool
    best_direction: np.ndarray  # (n_channels, 3) unit direction that rigid motion explains best
    direction_error_deg: np.ndarray  # (n_channels,) angle between nominal and best direction
    position_shift_m: np.ndarray  # (n_channels, 3) shift along which the channel is explained
    order: list[int]  # flagged channels in the order they were removed (worst first)


def _predict(R_others: np.ndarray, x_others: np.ndarray, p: np.ndarray, o: np.ndarray
             ) -> np.ndarray:
    """Complex 3-D displacement (3, n_shapes) of point p under the rigid fit to the others."""
    a, _ = _lstsq(R_others, x_others)
    t, theta = a[:3], a[3:]
    r = p - o
    return t + np.cross(theta.T, r).T


def check_channels(shapes: np.ndarray, bones: list[str], position_m: np.ndarray,
                   direction: np.ndarray, max_relative_residual: float = 0.15,
                   min_redundancy: int = 2) -> ChannelCheck:
    """Flag channels whose direction or position is inconsistent with rigid bone motion.

    ``shapes`` (n_channels, n_shapes) complex: mode shapes, or better many operating
    deflection shapes (FRF lines ``H[f, :, i]`` as columns: every line of a rigid bone must
    be a rigid motion below ~300 Hz, thesis ch. 11). Per bone, each channel is predicted from
    the rigid motion fitted to the bone's other channels (which need ``6 + min_redundancy - 1``
    rows, else the channel is not checkable: NaN). The residual ``||psi_c - pred_c||`` is
    relative to the RMS norm of the bone's channels. The channel with the largest relative
    residual above ``max_relative_residual`` is flagged and removed from the fits, and the
    check repeats (so one bad sensor does not smear onto good ones).
    For every checked channel the direction ``d*`` that best explains its readings by the
    predicted 3-D motion ``U`` (least squares ``Re/Im(U^T d*) ~ psi``) and the position shift
    ``dp`` with ``psi - d.U(p) ~ dp . (d x theta)`` are returned as diagnostics.
    Each shape is scaled to unit norm first, so every line or mode counts equally.
    """
    x = np.asarray(shapes)
    x = x[:, None] if x.ndim == 1 else x
    # every shape counts equally (FRF lines near a resonance or at low frequency would
    # otherwise dominate the residuals)
    col = np.linalg.norm(x, axis=0)
    x = x / np.where(col > 0, col, 1.0)[None, :]
    p = np.asarray(position_m, dtype=float).reshape(-1, 3)
    d = np.asarray(direction, dtype=float).reshape(-1, 3)
    n = x.shape[0]
    resid = np.full(n, np.nan)
    best_dir = np.full((n, 3), np.nan)
    angle = np.full(n, np.nan)
    shift = np.full((n, 3), np.nan)
    flagged = np.zeros(n, dtype=bool)
    order: list[int] = []
    for bone in [b for b in dict.fromkeys(bones) if b]:
        members = [k for k, b in enumerate(bones) if b == bone]
        active = list(members)
        while True:
            if len(active) - 1 < 6 + min_redundancy - 1:
                break
            current = {}
            for c in active:
                others = [k for k in active if k != c]
                o = p[others].mean(axis=0)
                R = rigid_body_matrix(p[others], d[others], o)
                if np.linalg.matrix_rank(R) < 6:
                    continue
                U = _predict(R, x[others], p[c], o)
                pred = d[c] @ U
                # misfit in units of the bone's typical channel amplitude: a channel that
                # hardly moves (direction ~ normal to the motion) is not penalised for noise
                den = np.sqrt(np.mean(np.sum(np.abs(x[members]) ** 2, axis=1)))
                current[c] = np.linalg.norm(x[c] - pred) / den if den > 0 else np.nan
                # diagnostics: best direction and position shift (real-stacked least squares)
                A = np.concatenate([U.real.T, U.imag.T])
                b = np.concatenate([x[c].real, x[c].imag])
                dstar = np.linalg.lstsq(A, b, rcond=None)[0]
                if np.linalg.norm(dstar) > 0:
                    dstar = dstar / np.linalg.norm(dstar)
                    best_dir[c] = dstar
                    angle[c] = np.degrees(np.arccos(np.clip(dstar @ d[c], -1.0, 1.0)))
                a, _ = _lstsq(R, x[others])
                G = np.cross(d[c][None, :], a[3:].T)  # (n_shapes, 3): d x theta per shape
                Gs = np.concatenate([G.real, G.imag])
                e = x[c] - pred
                shift[c] = np.linalg.lstsq(Gs, np.concatenate([e.real, e.imag]), rcond=None)[0]
            for c, v in current.items():
                resid[c] = v
            if not current:
                break
            worst = max(current, key=lambda k: current[k])
            if not current[worst] > max_relative_residual:
                break
            flagged[worst] = True
            order.append(worst)
            active.remove(worst)
    return ChannelCheck(resid, flagged, best_dir, angle, shift, order)
