"""Linearised mass, stiffness and damping matrices of the rigid-body model (thesis eq. 4.6-4.22).

Kinematics (eq. 4.9): a point ``p`` of body ``b`` moves by ``u_b + θ_b × ρ`` with
``ρ = p − com_b``, i.e. by ``T(ρ) q_b`` with ``T(ρ) = [I₃, −[ρ]×]`` (3x6).

- Mass (eq. 4.11, 4.18): ``blockdiag(m I₃, I_b)`` per body plus ``m Tᵀ T`` per point mass.
- Springs (eq. 4.12-4.13, 4.20): the spring is unloaded at rest, so the elongation to first
  order is ``Δu = e·(δp_a − δp_b)`` with ``e`` the unit axis; ``K += k g gᵀ`` with
  ``g = T_aᵀ e − T_bᵀ e`` (second-order terms of ``Δu`` multiply the zero rest elongation
  and drop out of the linearisation).
- Dashpots (eq. 4.15-4.16 with ch. 5.4): reaction to the relative velocity projected on the
  joint normal ``n``: ``C += c g gᵀ`` with ``g = T_aᵀ n − T_bᵀ n``, both bodies evaluated at
  the midpoint of the two attachment points, or each at its own point when the model's
  ``dashpot_lever`` is ``"points"`` (see :func:`connector_vector`).

All functions are pure; matrices are (n_dof, n_dof) float64, SI units.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pelvislab.model.pelvis import GROUND, Dashpot, PelvisModel, Spring


def skew(v: np.ndarray) -> np.ndarray:
    """Cross-product matrix: ``skew(v) @ w == np.cross(v, w)``."""
    x, y, z = v
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


def point_transform(rho_m: np.ndarray) -> np.ndarray:
    """3x6 map from a body's (u, θ) to the small displacement of a point at ``ρ`` (eq. 4.9).

    ``[I₃, −skew(ρ)]`` written out in one array (the effect fits build it for every trial
    point): the same values, the negated zeros of ``−skew`` included."""
    x, y, z = np.asarray(rho_m, dtype=float)
    return np.array([[1.0, 0.0, 0.0, -0.0, z, -y],
                     [0.0, 1.0, 0.0, -z, -0.0, x],
                     [0.0, 0.0, 1.0, y, -x, -0.0]])


def point_rows(model: PelvisModel, bones: list[str] | tuple[str, ...], position_m: np.ndarray,
               direction: np.ndarray) -> np.ndarray:
    """(n, n_dof) rows mapping generalised coordinates to displacement of points along
    directions (eq. 4.9 projected). By reciprocity the same rows, transposed, map point
    forces (N, along ``direction``) to generalised forces.

    Bone ``"ground"`` gives a zero row; an empty bone (a point on no modelled body) gives a
    NaN row, so FRFs there are NaN ("not predicted").
    """
    pos = np.asarray(position_m, dtype=float).reshape(-1, 3)
    dirs = np.asarray(direction, dtype=float).reshape(-1, 3)
    if not (len(bones) == pos.shape[0] == dirs.shape[0]):
        raise ValueError(f"points disagree: {len(bones)} bones, {pos.shape[0]} positions, "
                         f"{dirs.shape[0]} directions")
    # np.linalg.norm's sum of squares, without its per-call overhead (the same values)
    norms = np.sqrt(np.add.reduce(dirs * dirs, axis=1))
    if np.any(norms == 0) or not np.all(np.isfinite(pos)):
        raise ValueError("point directions must be non-zero and positions finite")
    dirs = dirs / norms[:, None]
    rows = np.zeros((len(bones), model.n_dof))
    # the transform of a point asked for along several directions is built once
    transforms: dict[tuple[int, bytes], np.ndarray] = {}
    for i, bone in enumerate(bones):
        if bone == GROUND:
            continue
        if bone == "":
            rows[i] = np.nan
            continue
        b = model.body_index(bone)
        key = (b, pos[i].tobytes())
        t = transforms.get(key)
        if t is None:
            t = transforms[key] = point_transform(pos[i] - model.bodies[b].com_m)
        rows[i, 6 * b:6 * b + 6] = dirs[i] @ t
    return rows


def connector_vector(model: PelvisModel, element: Spring | Dashpot) -> np.ndarray:
    """``g`` (n_dof,) with ``g·q`` the relative displacement of end a's body with respect to
    end b's body along the element axis; the element adds ``coef · g gᵀ`` to K or C.

    Both bodies' motions are evaluated at one point, the midpoint of the two attachment
    points (the body point when the other end is grounded). When the points lie on the axis
    (all springs, eq. 4.13, and the appendix E dashpots except S1 whose printed points are
    0.7 mm apart but not exactly along the joint normal) this is identical to taking each
    body at its own point; in general it keeps the element blind to rigid-body motion of the
    whole model, so K and C annihilate the six rigid-body modes (ch. 5.3-5.4). A model read
    with ``dashpot_lever = "points"`` evaluates each body of a dashpot at its own point
    instead (eq. 4.16 and fig. 5.6 literally; with appendix E's printed S1 pair its C then
    damps a rigid rotation of the whole pelvis slightly).
    """
    g = np.zeros(model.n_dof)
    for body, sign, x in zip((element.body_a, element.body_b), (1.0, -1.0),
                             _evaluation_points(model, element), strict=True):
        if body == GROUND:
            continue
        b = model.body_index(body)
        rho = x - model.bodies[b].com_m
        g[6 * b:6 * b + 6] += sign * (element.axis @ point_transform(rho))
    return g


def _reads_own_points(model: PelvisModel, element: Spring | Dashpot) -> bool:
    """Whether each body of ``element`` is evaluated at its own attachment point: dashpots
    of a model read with ``dashpot_lever = "points"`` (eq. 4.16's attachment points with
    fig. 5.6's projection on the normal)."""
    return isinstance(element, Dashpot) and model.dashpot_lever == "points"


def _evaluation_points(model: PelvisModel, element: Spring | Dashpot
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Where end a's and end b's bodies are evaluated (m): the midpoint of the two points
    (point a when grounded), or each body at its own point (:func:`_reads_own_points`)."""
    if element.body_b == GROUND:
        return element.point_a_m, element.point_a_m
    if _reads_own_points(model, element):
        return element.point_a_m, element.point_b_m
    x = 0.5 * (element.point_a_m + element.point_b_m)
    return x, x


def connector_vector_derivative(model: PelvisModel, element: Spring | Dashpot, end: str,
                                axis: int) -> np.ndarray:
    """∂g/∂r (n_dof,) for a move of attachment point ``end`` ("a" or "b") along model axis
    ``axis`` (0, 1, 2), with ``g`` from :func:`connector_vector`.

    The evaluation point moves with the points (midpoint, or point a when grounded); the
    element axis turns with them when it is the line of the points (springs, eq. 4.13), and
    is fixed otherwise (dashpot joint normals, explicit axes).
    """
    if end not in ("a", "b") or axis not in (0, 1, 2):
        raise ValueError("end must be 'a' or 'b' and axis 0, 1 or 2")
    a, b = element.point_a_m, element.point_b_m
    e = element.axis
    unit = np.eye(3)[axis]
    grounded = element.body_b == GROUND
    if grounded:
        dx = unit if end == "a" else np.zeros(3)
    else:
        dx = 0.5 * unit
    d = b - a
    length = float(np.linalg.norm(d))
    de = np.zeros(3)
    if isinstance(element, Spring) and length > 1e-9 and np.allclose(np.abs(e @ d), length):
        sign = -1.0 if end == "a" else 1.0
        de = sign * (unit - e * e[axis]) / length * float(np.sign(e @ d))
    own = _reads_own_points(model, element) and not grounded
    dg = np.zeros(model.n_dof)
    for body, sgn, this_end, x in zip((element.body_a, element.body_b), (1.0, -1.0), "ab",
                                      _evaluation_points(model, element), strict=True):
        if body == GROUND:
            continue
        k = model.body_index(body)
        rho = x - model.bodies[k].com_m
        # read at its own point, a body's lever moves only with its own end
        dxk = (unit if this_end == end else np.zeros(3)) if own else dx
        dg[6 * k:6 * k + 3] += sgn * de
        dg[6 * k + 3:6 * k + 6] += sgn * (np.cross(dxk, e) + np.cross(rho, de))
    return dg


def body_mass_block(mass_kg: float, inertia_kg_m2: np.ndarray) -> np.ndarray:
    """6x6 rigid-body mass matrix about the centre of mass (eq. 4.11)."""
    block = np.zeros((6, 6))
    block[:3, :3] = mass_kg * np.eye(3)
    block[3:, 3:] = inertia_kg_m2
    return block


def mass_matrix(model: PelvisModel) -> np.ndarray:
    """M (n_dof, n_dof), kg and kg m² (eq. 4.11, 4.18), including point masses."""
    m = np.zeros((model.n_dof, model.n_dof))
    for b, body in enumerate(model.bodies):
        m[6 * b:6 * b + 6, 6 * b:6 * b + 6] = body_mass_block(body.mass_kg, body.inertia_kg_m2)
    for pm in model.point_masses:
        b = model.body_index(pm.body)
        t = point_transform(pm.position_m - model.bodies[b].com_m)
        m[6 * b:6 * b + 6, 6 * b:6 * b + 6] += pm.mass_kg * t.T @ t
    return m


def stiffness_matrix(model: PelvisModel) -> np.ndarray:
    """K (n_dof, n_dof), N/m, N and N m per rad (eq. 4.12-4.13, 4.20)."""
    k = np.zeros((model.n_dof, model.n_dof))
    for s in model.springs:
        g = connector_vector(model, s)
        k += s.stiffness_n_per_m * np.outer(g, g)
    return k


def damping_matrix(model: PelvisModel) -> np.ndarray:
    """C (n_dof, n_dof), N s/m (eq. 4.15-4.16, 4.20; dashpots along joint normals, ch. 5.4)."""
    c = np.zeros((model.n_dof, model.n_dof))
    for d in model.dashpots:
        g = connector_vector(model, d)
        c += d.coefficient_n_s_per_m * np.outer(g, g)
    return c


@dataclass(frozen=True, eq=False)
class SystemMatrices:
    """M, K, C (n_dof, n_dof) and the eq. 7.1-7.3 factors; Z(ω) = −ω²M + iω C + K in
    the constant case, generally ``(1 + f_k ω/(4ω_max)) K − ω² M + i (ω + f_c ω_max/4) C``."""

    M: np.ndarray
    K: np.ndarray
    C: np.ndarray
    f_k: float = 0.0
    f_c: float = 0.0
    f_max_hz: float = 300.0


def assemble(model: PelvisModel) -> SystemMatrices:
    """M, K, C of ``model`` and its frequency-dependence factors."""
    fd = model.frequency_dependence
    return SystemMatrices(mass_matrix(model), stiffness_matrix(model), damping_matrix(model),
                          fd.f_k, fd.f_c, fd.f_max_hz)
