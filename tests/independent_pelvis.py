"""Independent, numpy-only implementation of the thesis' linearised pelvis model.

Written from the thesis text alone (Conza, "Dynamics of the human pelvis", ch. 4.2,
5.2-5.4 and appendix E) as a cross-check of ``pelvislab.model``. It deliberately imports
nothing from ``pelvislab``; every number below is transcribed from appendix E.

Model (thesis ch. 4.2 and 5):

* 3 rigid bodies, 6 generalised coordinates each (ch. 5.2: "the number of degrees of
  freedom of the model sums up to 18"): translation of the centre of mass ``u_b`` (m) and
  small rotation angles ``theta_b`` (rad) about the global x, y, z axes (eq. 4.8).
  Coordinate order here: bodies ``innominate_right``, ``innominate_left``, ``sacrum``; per
  body ``(ux, uy, uz, theta_x, theta_y, theta_z)``.
* Displacement of a point of body b (eq. 4.9): ``du = du_b + theta_b x rho``, with ``rho``
  the point's position relative to the body's centre of mass, i.e. ``du = G(rho) q_b``
  with ``G = [I3, -[rho]x]``.
* Mass matrix from the kinetic energy (eq. 4.11, 4.18): ``blockdiag(m_b I3, I_b)``, with
  ``I_b`` the rotational inertia about the centre of mass in global axes (appendix E).
* Stiffness from ``V = sum 1/2 k_l (|u_sx - u_dx| - L_l)^2`` (eq. 4.12-4.13), linearised at
  the rest configuration (eq. 4.20-4.21). Springs are unloaded at rest (ch. 5.3: "a length
  of the springs at rest with no elongation, thus no energy storage"), so no geometric
  stiffness term: ``K += k e e^T`` on the relative displacement of the two attachment
  points, ``e`` the unit vector between them.
* Damping (ch. 5.4, Fig. 5.6): each dashpot "reacts to the projection of the velocity
  difference of the two attachment points onto the normal to the surface", so
  ``D = 1/2 c (n . (v_A - v_B))^2`` and ``C += c n n^T`` on the relative velocity of the
  two attachment points. (Eq. 4.16 taken literally would use the full velocity difference;
  ch. 5.4 restricts it to the joint normal, and that is what is implemented.)
* Receptance (eq. 4.52-4.54, design 4.1, convention x(t) = Re(X e^{+i w t})):
  ``H(w) = (-w^2 M + i w C + K)^{-1}`` in m/N, mapped to points and directions through
  eq. 4.9: ``H_point[out, in] = d_out^T G_out H G_in^T e_in``.
* Gravity is neglected (ch. 4.2, eq. 4.14: "negligible influence of the gravitational
  pull").

Frame (ch. 5.2, design 4.1): origin midway between the two SIAS, +x anterior, +y to the
subject's left, +z superior; right-side points have y < 0. Appendix E gives right-side
values; "for the homologous coordinates on the left side just change the sign of the
y-coordinate".

Transcription notes (typos / ambiguities in appendix E and how they are resolved here):

1. Dashpot line S1: the thesis prints ``u_S1,in,R = (-79, -45, -0.2)`` next to
   ``u_S2,scr,R = (-80, -45, 0)``. The second label is a typo for ``u_S1,scr,R`` (S2,scr,R
   is given on the next line with other values).
2. Joint normal. The three sacral dashpot points S1-S3 (right) are thirds printed to
   three decimals (-93.333 = -280/3, -38.333 = -115/3, -13.333 = -40/3) and lie on the
   plane ``2x - 2y - z = -70 mm``; the right sacroiliac joint normal is therefore exactly
   ``n = (2, -2, -1)/3`` (left: y-mirror ``(2, 2, -1)/3``). Ch. 5.4 / Fig. 5.6: the dashpot
   "remains aligned with the normal vector n", so every sacroiliac dashpot acts along
   that normal ("parallel but non-coplanar"), not along the line between its two points.
   ``dashpot_direction="pair"`` switches to that line, for diagnosis only.
   (A first version took the normal numerically from the rounded printed points; that
   tilts it by ~1e-5 rad and shows up as a 3e-5 relative change of C.)
3. ``u_S1,in,R = (-79, -45, -0.2)`` is inconsistent with S2 and S3: for those the
   innominate point is the sacral point shifted by exactly 0.7 mm along ``n`` (e.g. S3:
   (-80, -38.333, -13.333) -> (-79.533, -38.8, -13.567)); for S1 that would give
   (-79.533, -45.467, -0.233). The printed S1 offset (1, 0, -0.2) mm is not along ``n``.
   The value is kept as printed. It then matters *where* each body's velocity is taken:
   eq. 4.16 and Fig. 5.6 take "the velocities of the attachment points" A and B
   themselves (``dashpot_lever="points"``, the default here). With the printed S1 pair
   that dashpot also reacts (weakly) to a rigid rotation of the whole pelvis, since
   ``n . (omega x (A - B)) != 0``. ``dashpot_lever="midpoint"`` evaluates both bodies at the
   midpoint of A and B (blind to rigid motion). Both agree for every dashpot whose two
   points are offset along its normal, i.e. all appendix-E dashpots except S1.
4. Pubic dashpots P1, P2: only the right-innominate point is printed; the left one is its
   y-mirror. Their direction is the normal of the symphysis plane, which "coincides with
   the sagittal plane x - z" (ch. 5.4), i.e. ``(0, 1, 0)``. (The y coordinates, e.g. the
   odd -35 mm of P1, have no effect: a lever-arm component along n does not change
   ``n . (theta x rho)``.)
5. Pubic springs: PUBH is printed only for the right innominate, ``(0, -5, -95)``; its
   left end is the y-mirror ``(0, 5, -95)`` (a spring "in y direction", ch. 5.3). PUBS is
   printed with both ends, right ``(0, 0, -90)``, left ``(-10, 0, -100)``: direction
   (1, 0, 1)/sqrt(2) as ch. 5.3 / 6.2 state.
6. The stiffness list names the long posterior spring ``pst`` once and ``PSL`` elsewhere;
   read as ``psl``.
7. Damping coefficients ``c_sij`` and ``c_pub`` are per dashpot: "The dash-pots belonging
   to the same articulation were assigned one and the same damping coefficient" (ch. 5.4).
8. Inertia tensors are taken about each body's centre of mass (eq. 4.11 pairs them with
   the centre-of-mass velocity; about the origin they would be several times larger than
   printed). A body's mass factor scales its inertia tensor with it (ch. 5.2: inertia
   divided by mass "to enable the modulation of the rotational inertia matrix with
   different mass values"; design 4.5).
"""

from __future__ import annotations

import numpy as np

BONES = ("innominate_right", "innominate_left", "sacrum")
NDOF = 6 * len(BONES)
MM = 1e-3

_MIRROR = np.array([1.0, -1.0, 1.0])

# --- appendix E, "Masses of the bones in kg" -----------------------------------------
MASS = {
    "innominate_right": 0.64,  # m_in (appendix E); also ch. 5.2 "0.64 kg each"
    "innominate_left": 0.64,  # m_in, same for both sides
    "sacrum": 0.36,  # m_sacrum (appendix E); ch. 5.2 "sacrum: 0.36 kg"
}

# --- appendix E, "Centers of mass of the bodies in m" --------------------------------
_CM_IN_R = np.array([-63.8e-3, -72.8e-3, -27e-3])  # u_CM,in,R
CENTRE_OF_MASS = {
    "innominate_right": _CM_IN_R,
    "innominate_left": _CM_IN_R * _MIRROR,  # left: y sign changed (appendix E preamble)
    "sacrum": np.array([-93.2e-3, 0.0, 2.8e-3]),  # u_CM,scr
}

# --- appendix E, rotational inertia matrices in kg m^2 (about the centre of mass) ----
INERTIA = {
    # "Rotational inertia of the right innominate bone"
    "innominate_right": np.array([
        [1.4656e-3, 1.1120e-4, 1.3628e-4],
        [1.1120e-4, 1.5634e-3, 2.6670e-4],
        [1.3628e-4, 2.6670e-4, 7.4577e-4],
    ]),
    # "Rotational inertia matrix of the left innominate bone" (xy, yz terms change sign,
    # consistent with the y mirror)
    "innominate_left": np.array([
        [1.4656e-3, -1.1120e-4, 1.3628e-4],
        [-1.1120e-4, 1.5634e-3, -2.6670e-4],
        [1.3628e-4, -2.6670e-4, 7.4577e-4],
    ]),
    # "Rotational inertia of the sacrum"
    "sacrum": np.array([
        [3.3083e-4, 0.0, -7.8333e-5],
        [0.0, 2.2500e-4, 0.0],
        [-7.8333e-5, 0.0, 3.1083e-4],
    ]),
}

# --- appendix E, "Attachment position of springs in mm" (right side) ----------------
# name: (innominate point u_<NAME>,in,R, sacrum point u_<NAME>,scr,R)
_SIJ_SPRINGS_R = {
    "io": ((-105.0, -30.0, 10.0), (-75.0, -25.0, 10.0)),  # u_IO,in,R / u_IO,scr,R
    "asa": ((-85.0, -70.0, 10.0), (-75.0, -50.0, 0.0)),  # u_ASA,in,R / u_ASA,scr,R
    "asd": ((-55.0, -75.0, -30.0), (-65.0, -55.0, -20.0)),  # u_ASD,in,R / u_ASD,scr,R
    "pss": ((-115.0, -35.0, 25.0), (-110.0, -5.0, 15.0)),  # u_PSS,in,R / u_PSS,scr,R
    "psl": ((-130.0, -35.0, -5.0), (-145.0, -5.0, -50.0)),  # u_PSL,in,R / u_PSL,scr,R
}
_PUBH_IN_R = (0.0, -5.0, -95.0)  # u_PUBH,in,R; left end = y-mirror (note 5)
_PUBS_IN_R = (0.0, 0.0, -90.0)  # u_PUBS,in,R
_PUBS_IN_L = (-10.0, 0.0, -100.0)  # u_PUBS,in,L

# --- appendix E, "Stiffness coefficients in N/m" -------------------------------------
STIFFNESS_E = {
    "io": 1e6,  # k_io
    "asa": 1e6,  # k_asa
    "asd": 1e6,  # k_asd
    "pss": 1e6,  # k_pss
    "psl": 1e6,  # k_pst (typo for psl, note 6)
    "pubh": 1e5,  # k_pubh
    "pubs": 5e3,  # k_pubs
}

# --- appendix E, "Attachment position of the dashpots in mm" (right side) -----------
# sacroiliac dashpots: (innominate point u_Sj,in,R, sacrum point u_Sj,scr,R)
_SIJ_DASHPOTS_R = {
    "S1": ((-79.0, -45.0, -0.2), (-80.0, -45.0, 0.0)),  # scr label printed "S2" (note 1)
    "S2": ((-92.867, -58.8, -0.233), (-93.333, -58.333, 0.0)),
    "S3": ((-79.533, -38.8, -13.567), (-80.0, -38.333, -13.333)),
}
# right sacroiliac joint plane through the three sacral points: 2x - 2y - z = -70 mm (note 2)
SIJ_NORMAL_R = np.array([2.0, -2.0, -1.0]) / 3.0
SIJ_PLANE_OFFSET_MM = -70.0
# pubic dashpots: right-innominate point u_Pj,in,R; left point = y-mirror (note 4)
_PUB_DASHPOTS_R = {
    "P1": (0.0, -35.0, -95.0),
    "P2": (-10.0, -1.0, -100.0),
}

# --- appendix E, "Damping coefficients in Ns/m" --------------------------------------
DAMPING_E = {"sij": 0.8, "pub": 0.8}  # c_sij, c_pub (per dashpot, note 7)


def _element(name, bone_a, point_a_mm, bone_b, point_b_mm):
    return {
        "name": name,
        "bone_a": bone_a,
        "point_a": np.asarray(point_a_mm, dtype=float) * MM,
        "bone_b": bone_b,
        "point_b": np.asarray(point_b_mm, dtype=float) * MM,
    }


def springs():
    """The 12 springs of ch. 5.3 as dicts (name, bone_a, point_a, bone_b, point_b; m).

    Names: ``<io|asa|asd|pss|psl>_<R|L>``, ``pubh``, ``pubs``. Positions in metres in the
    model frame, from appendix E (left side by y mirror).
    """
    out = []
    for side, bone, mirror in (("R", "innominate_right", np.ones(3)),
                               ("L", "innominate_left", _MIRROR)):
        for name, (p_in, p_scr) in _SIJ_SPRINGS_R.items():
            out.append(_element(f"{name}_{side}", bone, np.array(p_in) * mirror,
                                "sacrum", np.array(p_scr) * mirror))
    out.append(_element("pubh", "innominate_right", _PUBH_IN_R,
                        "innominate_left", np.array(_PUBH_IN_R) * _MIRROR))
    out.append(_element("pubs", "innominate_right", _PUBS_IN_R,
                        "innominate_left", _PUBS_IN_L))
    return out


def sij_plane_residual_mm():
    """Largest distance (mm) of the printed right sacral dashpot points from the plane
    ``n . x = -70/3 mm`` (note 2); nonzero only by the three-decimal printing."""
    pts = np.array([p_scr for _, p_scr in _SIJ_DASHPOTS_R.values()])
    return float(np.abs(pts @ SIJ_NORMAL_R - SIJ_PLANE_OFFSET_MM / 3.0).max())


def dashpots(direction="plane"):
    """The 8 dashpots of ch. 5.4 as dicts (name, bone_a, point_a, bone_b, point_b, normal).

    Names: ``S1_R .. S3_R``, ``S1_L .. S3_L`` (sacroiliac, innominate -> sacrum) and
    ``P1``, ``P2`` (pubic symphysis, right -> left innominate). Positions in metres,
    normal a unit vector. ``direction="plane"`` (default, note 2) uses the joint-plane
    normal; ``"pair"`` uses the unit vector between the two printed points of each dashpot.
    """
    if direction not in ("plane", "pair"):
        raise ValueError("direction must be 'plane' or 'pair'")
    out = []
    for side, bone, mirror in (("R", "innominate_right", np.ones(3)),
                               ("L", "innominate_left", _MIRROR)):
        n_joint = SIJ_NORMAL_R * mirror
        for name, (p_in, p_scr) in _SIJ_DASHPOTS_R.items():
            el = _element(f"{name}_{side}", bone, np.array(p_in) * mirror,
                          "sacrum", np.array(p_scr) * mirror)
            el["normal"] = n_joint
            out.append(el)
    for name, p_r in _PUB_DASHPOTS_R.items():
        el = _element(name, "innominate_right", p_r,
                      "innominate_left", np.array(p_r) * _MIRROR)
        el["normal"] = np.array([0.0, 1.0, 0.0])  # symphysis plane = x-z plane (ch. 5.4)
        out.append(el)
    if direction == "pair":
        for el in out:
            d = el["point_a"] - el["point_b"]
            el["normal"] = d / np.linalg.norm(d)
    return out


def default_stiffness():
    """Per-spring stiffness (N/m) of appendix E, keyed by spring name."""
    k = {}
    for s in springs():
        base = s["name"].split("_")[0]
        k[s["name"]] = STIFFNESS_E[base]
    return k


def default_damping():
    """Per-dashpot damping coefficient (N s/m) of appendix E, keyed by dashpot name."""
    return {d["name"]: DAMPING_E["pub"] if d["name"].startswith("P") else DAMPING_E["sij"]
            for d in dashpots()}


def expand_parameters(params):
    """Map design-4.5 parameter names to per-element values.

    Accepts ``m_<bone>`` / ``m_innominate`` (kg), ``k_<name>_R|L`` / ``k_<name>``,
    ``k_pubh``, ``k_pubs`` (N/m), ``c_sij_R|L`` / ``c_sij``, ``c_pub`` (N s/m). Returns
    ``(mass_scale, stiffness, damping)`` suitable for :func:`matrices`; mass entries
    are returned as factors relative to appendix E.
    """
    mass_scale, k, c = {}, {}, {}
    for key, value in params.items():
        value = float(value)
        if key == "m_innominate":
            for b in ("innominate_right", "innominate_left"):
                mass_scale[b] = value / MASS[b]
        elif key.startswith("m_"):
            mass_scale[key[2:]] = value / MASS[key[2:]]
        elif key.startswith("k_"):
            name = key[2:]
            if name in ("pubh", "pubs") or name.endswith(("_R", "_L")):
                k[name] = value
            else:
                k[f"{name}_R"] = value
                k[f"{name}_L"] = value
        elif key == "c_pub":
            c["P1"] = c["P2"] = value
        elif key.startswith("c_sij"):
            sides = ("R", "L") if key == "c_sij" else (key[-1],)
            for side in sides:
                for j in (1, 2, 3):
                    c[f"S{j}_{side}"] = value
        else:
            raise KeyError(key)
    return mass_scale, k, c


def _skew(v):
    """Cross-product matrix [v]x, so that [v]x w = v x w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def point_map(bone, position):
    """3 x 18 matrix mapping the generalised coordinates to the displacement (m) of a
    point of ``bone`` at ``position`` (m, model frame at rest), eq. 4.9:
    ``du = du_b + theta_b x rho``, ``rho = position - centre of mass``."""
    i = BONES.index(bone)
    rho = np.asarray(position, dtype=float) - CENTRE_OF_MASS[bone]
    g = np.zeros((3, NDOF))
    g[:, 6 * i:6 * i + 3] = np.eye(3)
    g[:, 6 * i + 3:6 * i + 6] = -_skew(rho)
    return g


def _relative_map(el, lever="points"):
    """3 x 18 map from q to the relative displacement of end a with respect to end b (m).

    ``lever="points"``: each body at its own attachment point (eq. 4.13, 4.16);
    ``"midpoint"``: both bodies at the midpoint of the two points (note 3)."""
    if lever == "points":
        xa, xb = el["point_a"], el["point_b"]
    elif lever == "midpoint":
        xa = xb = 0.5 * (el["point_a"] + el["point_b"])
    else:
        raise ValueError("lever must be 'points' or 'midpoint'")
    return point_map(el["bone_a"], xa) - point_map(el["bone_b"], xb)


def matrices(mass_scale=None, stiffness=None, damping=None, dashpot_direction="plane",
             dashpot_lever="points"):
    """Linearised M (kg, kg m^2), C (N s/m ...), K (N/m ...) of the appendix-E model.

    18 x 18, coordinate order as in the module docstring (eq. 4.18, 4.20-4.22).
    ``mass_scale``: {bone: factor} on appendix-E mass and inertia (default 1).
    ``stiffness``: {spring name: k in N/m}, overrides appendix E per spring.
    ``damping``: {dashpot name: c in N s/m}, overrides appendix E per dashpot.
    ``dashpot_direction`` / ``dashpot_lever``: readings of ch. 5.4, notes 2 and 3.
    Springs always use their own attachment points (eq. 4.13; for a spring the two
    choices coincide, its points being offset along its axis).
    """
    mass_scale = dict(mass_scale or {})
    k_val = default_stiffness()
    k_val.update(stiffness or {})
    c_val = default_damping()
    c_val.update(damping or {})
    unknown = (set(mass_scale) - set(BONES)) | (set(k_val) - set(default_stiffness())) \
        | (set(c_val) - set(default_damping()))
    if unknown:
        raise KeyError(f"unknown names: {sorted(unknown)}")

    m = np.zeros((NDOF, NDOF))
    for i, bone in enumerate(BONES):  # eq. 4.11 / 4.18
        f = mass_scale.get(bone, 1.0)
        m[6 * i:6 * i + 3, 6 * i:6 * i + 3] = f * MASS[bone] * np.eye(3)
        m[6 * i + 3:6 * i + 6, 6 * i + 3:6 * i + 6] = f * INERTIA[bone]

    k = np.zeros((NDOF, NDOF))
    for s in springs():  # eq. 4.12-4.13 linearised at rest, no pre-load
        e = s["point_a"] - s["point_b"]
        e = e / np.linalg.norm(e)
        b = e @ _relative_map(s)
        k += k_val[s["name"]] * np.outer(b, b)

    c = np.zeros((NDOF, NDOF))
    for d in dashpots(dashpot_direction):  # ch. 5.4 / Fig. 5.6
        b = d["normal"] @ _relative_map(d, dashpot_lever)
        c += c_val[d["name"]] * np.outer(b, b)
    return m, c, k


def natural_frequencies(mass_scale=None, stiffness=None):
    """Undamped natural frequencies (Hz) from det(-w^2 M + K) = 0 (eq. 4.27), ascending;
    the first six are the free-free rigid-body modes (~0).

    The thesis reports no natural frequencies for the appendix-E model: table 7.3 belongs
    to the ch. 7 model (sacrospinous/sacrotuberous/iliolumbar springs, m_in = 0.61 kg,
    sacrum tied to ground), and tables 10.1-14.1 are measured specimen modes. For
    appendix E this gives 10.38, 38.12, 111.98, 174.88, 231.92, 303.61, 360.16, 515.85,
    687.24, 731.81, 770.22, 867.09 Hz.
    """
    m, _, k = matrices(mass_scale, stiffness)
    lam = np.linalg.eigvals(np.linalg.solve(m, k)).real
    return np.sqrt(np.clip(np.sort(lam), 0.0, None)) / (2 * np.pi)


def _direction_rows(bones, positions, directions):
    rows = []
    for bone, pos, d in zip(bones, positions, directions, strict=True):
        d = np.asarray(d, dtype=float)
        rows.append((d / np.linalg.norm(d)) @ point_map(bone, pos))
    return np.array(rows)


def frf(freqs_hz, outputs, inputs, mass_scale=None, stiffness=None, damping=None,
        dashpot_direction="plane", dashpot_lever="points"):
    """Receptance FRFs H[f, out, in] in m/N (eq. 4.54 mapped by eq. 4.9).

    ``outputs`` / ``inputs``: sequences of (bone, position (3,) in m, direction (3,)).
    An output is the displacement along its (normalised) direction; an input is a unit
    force applied at its position along its (normalised) direction.
    ``freqs_hz``: frequencies in Hz (must avoid 0: the model is free-free).
    Other arguments as in :func:`matrices`.
    """
    m, c, k = matrices(mass_scale, stiffness, damping, dashpot_direction, dashpot_lever)
    d_out = _direction_rows(*zip(*outputs, strict=True))
    d_in = _direction_rows(*zip(*inputs, strict=True))
    freqs = np.atleast_1d(np.asarray(freqs_hz, dtype=float))
    h = np.empty((freqs.size, d_out.shape[0], d_in.shape[0]), dtype=complex)
    for i, f in enumerate(freqs):
        w = 2 * np.pi * f
        z = -w * w * m + 1j * w * c + k
        h[i] = d_out @ np.linalg.solve(z, d_in.T)
    return h
