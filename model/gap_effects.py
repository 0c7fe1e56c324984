"""Parametric FRF model for gap diagnosis: base parameters plus one candidate extension.

The base model is the rigid-body pelvis of thesis ch. 4.2/5 (appendix E by default),
written as a sum of rank-1 "atoms" so that every named parameter (design 4.5) enters the
dynamic stiffness linearly::

    Z(ω) = a_m(ω) Σ θ_p M_p + a_k(ω) Σ θ_p K_p + a_c(ω) Σ θ_p C_p + ΔZ_effect(ω)
    H(ω) = G_out(ω) ⊙ [O_effect Z(ω)⁻¹ Iᵀ] ⊙ G_in(ω)              (m/N, design 4.1)

with a_m = −ω², a_k = 1, a_c = iω for the plain viscous model (eq. 4.54). A candidate
*effect* (sim-to-real gap hypothesis) may change the frequency factors (eq. 7.1-7.3:
frequency-dependent stiffness, hysteretic damping), add a low-rank ΔZ (added mass, missing
ligament, support, soft-tissue loading) — or a ΔZ_j present only in the columns of input j,
i.e. only while the shaker drives there (tissue under the shaker: ``H[:, :, j] =
O (Z + ΔZ_j)⁻¹ i_j``) —, change an output row (sensor misorientation) or multiply
outputs/inputs by a measurement-chain gain (soft tissue, fixture resonance).

All functions here are pure numerics on arrays (no I/O). Frequencies in Hz, ω in rad/s,
SI units throughout. This module deliberately shares no code with the simulator's effect
generator (``sim_instruments``): the withheld-effect benchmark must stay blind.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.optimize import least_squares

from pelvislab.model.assembly import connector_vector, point_rows
from pelvislab.model.pelvis import PelvisModel

KIND_M, KIND_K, KIND_C = 0, 1, 2

# Joint centres (m) for the missing-ligament candidate: mean of the appendix-E dashpot and
# spring attachment points of each joint (thesis appendix E, right side; left = y-mirror).
JOINT_CENTRES_M: dict[str, tuple[str, str, np.ndarray]] = {
    "sij_right": ("innominate_right", "sacrum", np.array([-0.0880, -0.0400, 0.0000])),
    "sij_left": ("innominate_left", "sacrum", np.array([-0.0880, 0.0400, 0.0000])),
    "pubic": ("innominate_right", "innominate_left", np.array([-0.0050, 0.0000, -0.0950])),
}


# ---------------------------------------------------------------------------------------
# Base structure: named parameters as rank-1 atoms
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class BaseStructure:
    """Named parameters of a :class:`PelvisModel` as rank-1 atoms of M, K, C.

    ``∂M/∂θ_p = Σ_{a: param[a]=p, kind[a]=M} w_a v_a v_aᵀ`` (likewise K, C); the matrices are
    linear in the parameters: a body mass scales its inertia with it (ch. 5.2), a spring
    adds ``k g gᵀ`` (eq. 4.12-4.13), a dashpot group ``c Σ g gᵀ`` (ch. 5.4).
    """

    model: PelvisModel
    names: tuple[str, ...]
    nominal: np.ndarray
    vectors: np.ndarray  # (n_a, n_dof)
    weights: np.ndarray  # (n_a,)
    kinds: np.ndarray  # (n_a,)
    params: np.ndarray  # (n_a,)
    constant_M: np.ndarray  # (n_dof, n_dof) unparametrised mass (point masses of the file)
    outers: np.ndarray = field(init=False)  # (n_a, n_dof, n_dof) w v vᵀ
    # per kind (M, K, C): the atoms' parameter indices and their outers, for ``matrices``
    by_kind: tuple[tuple[np.ndarray, np.ndarray], ...] = field(init=False)
    # ``fixed_gram`` of the places asked for so far
    _grams: dict[tuple[str, bytes, bytes], np.ndarray] = field(
        init=False, default_factory=dict, repr=False)
    # ``line_spring_rows`` of the latest points (a bounded memo, oldest dropped first)
    _line_rows: dict[tuple[str, str, bytes], np.ndarray] = field(
        init=False, default_factory=dict, repr=False)
    # the atoms sorted by parameter, and where each parameter's atoms start
    grouped_vectors: np.ndarray = field(init=False)
    grouped_weights: np.ndarray = field(init=False)
    grouped_kinds: np.ndarray = field(init=False)
    grouped_params: np.ndarray = field(init=False)
    param_starts: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        outers = self.weights[:, None, None] * self.vectors[:, :, None] * self.vectors[:, None, :]
        object.__setattr__(self, "outers", outers)
        # the selections ``matrices`` makes on every call (the same arrays, made once)
        object.__setattr__(self, "by_kind", tuple(
            (self.params[self.kinds == kind], outers[self.kinds == kind])
            for kind in (KIND_M, KIND_K, KIND_C)))
        # the atoms grouped by parameter (stable order), for the Jacobian's sum per parameter
        order = np.argsort(self.params, kind="stable")
        object.__setattr__(self, "grouped_vectors", np.ascontiguousarray(self.vectors[order]))
        object.__setattr__(self, "grouped_weights", self.weights[order])
        object.__setattr__(self, "grouped_kinds", self.kinds[order])
        object.__setattr__(self, "grouped_params", self.params[order])
        starts = np.flatnonzero(np.r_[True, np.diff(self.params[order]) != 0])
        if starts.size != len(self.names):
            raise ValueError("every named parameter needs at least one atom")
        object.__setattr__(self, "param_starts", starts)

    @property
    def n_dof(self) -> int:
        """Number of generalised coordinates."""
        return int(self.vectors.shape[1])

    @property
    def n_params(self) -> int:
        """Number of named parameters."""
        return len(self.names)

    def matrices(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(M, K, C) at parameter values ``theta`` (SI)."""
        theta = np.asarray(theta, float)
        out = [np.tensordot(theta[params], outers, axes=1) for params, outers in self.by_kind]
        out[0] = out[0] + self.constant_M
        return out[0], out[1], out[2]

    def rows(self, bones: Sequence[str], position_m: np.ndarray,
             direction: np.ndarray) -> np.ndarray:
        """(n, n_dof) rows: displacement of points along directions (eq. 4.9)."""
        return point_rows(self.model, list(bones), position_m, direction)

    def fixed_gram(self, bone: str, point_m: np.ndarray, directions: np.ndarray
                   ) -> np.ndarray:
        """``GᵀG`` (n_dof, n_dof) of the rows ``G`` of a point of ``bone`` along each of
        ``directions`` (k, 3): an effect at a fixed place builds it at every evaluation.
        Kept per place (the same rows and product, computed once; read-only)."""
        point_m = np.asarray(point_m, float)
        directions = np.asarray(directions, float)
        key = (bone, point_m.tobytes(), directions.tobytes() + bytes(directions.shape))
        gram = self._grams.get(key)
        if gram is None:
            G = self.rows([bone] * len(directions), np.tile(point_m, (len(directions), 1)),
                          directions)
            gram = G.T @ G
            gram.flags.writeable = False
            self._grams[key] = gram
        return gram

    def reference_point(self, bone: str) -> np.ndarray:
        """Centre of mass of ``bone`` (m), the default attachment point of effects."""
        return np.asarray(self.model.body(bone).com_m, float)

    @property
    def bones(self) -> tuple[str, ...]:
        """Body names in DOF order."""
        return self.model.body_names


def base_structure(model: PelvisModel) -> BaseStructure:
    """Named-parameter atoms of ``model`` with design 4.5 names.

    Masses ``m_<body>``, springs ``k_<group>_<side>`` (``k_<group>`` without side), dashpot
    groups ``c_<group>_<side>``; values from the model file are the nominal values.
    """
    names: list[str] = []
    nominal: list[float] = []
    vecs: list[np.ndarray] = []
    weights: list[float] = []
    kinds: list[int] = []
    params: list[int] = []
    n = model.n_dof
    index: dict[str, int] = {}

    def param(name: str, value: float) -> int:
        if name not in index:
            index[name] = len(names)
            names.append(name)
            nominal.append(value)
        return index[name]

    for b, body in enumerate(model.bodies):
        p = param(f"m_{body.name}", body.mass_kg)
        for axis in range(3):
            v = np.zeros(n)
            v[6 * b + axis] = 1.0
            vecs.append(v)
            weights.append(1.0)
            kinds.append(KIND_M)
            params.append(p)
        lam, vec = np.linalg.eigh(np.asarray(body.inertia_kg_m2, float) / body.mass_kg)
        for lk, vk in zip(lam, vec.T, strict=True):
            v = np.zeros(n)
            v[6 * b + 3:6 * b + 6] = vk
            vecs.append(v)
            weights.append(float(lk))
            kinds.append(KIND_M)
            params.append(p)
    for kind, items, attr, prefix in (
        (KIND_K, model.springs, "stiffness_n_per_m", "k"),
        (KIND_C, model.dashpots, "coefficient_n_s_per_m", "c"),
    ):
        for item in items:
            name = f"{prefix}_{item.group}_{item.side}" if item.side else f"{prefix}_{item.group}"
            p = param(name, float(getattr(item, attr)))
            vecs.append(connector_vector(model, item))
            weights.append(1.0)
            kinds.append(kind)
            params.append(p)
    const_m = np.zeros((n, n))
    for pm in model.point_masses:
        rows = point_rows(model, [pm.body] * 3, np.tile(pm.position_m, (3, 1)), np.eye(3))
        const_m += pm.mass_kg * rows.T @ rows
    return BaseStructure(
        model=model, names=tuple(names), nominal=np.asarray(nominal, float),
        vectors=np.asarray(vecs, float), weights=np.asarray(weights, float),
        kinds=np.asarray(kinds, int), params=np.asarray(params, int), constant_M=const_m,
    )


# ---------------------------------------------------------------------------------------
# Evaluation context and effect terms
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class Context:
    """Everything an effect needs: frequencies, the base structure, the channel geometry."""

    base: BaseStructure
    frequency_hz: np.ndarray
    out_rows: np.ndarray  # (n_out, n_dof)
    in_rows: np.ndarray  # (n_in, n_dof)
    out_bones: tuple[str, ...]
    out_position_m: np.ndarray
    out_direction: np.ndarray
    out_names: tuple[str, ...]
    in_names: tuple[str, ...]
    in_bones: tuple[str, ...] = ()
    in_position_m: np.ndarray | None = None
    # the band's highest measured frequency (Hz); None: that of ``frequency_hz``
    band_max_hz: float | None = None
    # :func:`solve`'s latest base dynamic stiffnesses and their solves (see there)
    _base_Z: dict[bytes, tuple] = field(init=False, default_factory=dict, repr=False)
    _base_solves: dict[tuple[bytes, tuple[int, ...]], np.ndarray] = field(
        init=False, default_factory=dict, repr=False)

    @property
    def omega(self) -> np.ndarray:
        """Angular frequency (rad/s)."""
        return 2 * np.pi * self.frequency_hz

    @property
    def omega_max(self) -> float:
        """ω_max of eq. 7.2-7.3: the highest measured frequency of the whole band (rad/s),
        also on a subset of its lines."""
        f_max = self.band_max_hz if self.band_max_hz is not None else np.max(self.frequency_hz)
        return float(2 * np.pi * f_max)

    def subset(self, lines: np.ndarray) -> Context:
        """The same context on a subset of frequency lines. ω_max stays the band's: an
        effect scaled by it (eq. 7.2-7.3) must be the same on fitted and held-out lines
        (the held-out lines' own maximum is up to 3 lines lower)."""
        return Context(self.base, self.frequency_hz[lines], self.out_rows, self.in_rows,
                       self.out_bones, self.out_position_m, self.out_direction,
                       self.out_names, self.in_names, self.in_bones, self.in_position_m,
                       self.omega_max / (2 * np.pi))


@dataclass
class EffectTerms:
    """How one effect changes the FRF model (see the module docstring). ``None`` = unchanged."""

    a_m: np.ndarray | None = None
    a_k: np.ndarray | None = None
    a_c: np.ndarray | None = None
    dZ: np.ndarray | None = None  # (n_f, n, n) complex
    # per input: extra (n_f, n, n) dynamic stiffness present only while that input is
    # driven (something the shaker brings with it in that input's setups), None = none
    dZ_input: tuple[np.ndarray | None, ...] | None = None
    out_gain: np.ndarray | None = None  # (n_f, n_out) complex
    in_gain: np.ndarray | None = None  # (n_f, n_in) complex
    out_rows: np.ndarray | None = None  # (n_out, n)


def _split_factor(a: np.ndarray | None, default_real: np.ndarray | None,
                  default_imag: np.ndarray | None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(real, imaginary) parts of a frequency factor; None for a part that is zero."""
    if a is None:
        return default_real, default_imag
    if np.iscomplexobj(a):
        return a.real, a.imag
    return a, None


def _dynamic_stiffness(factors: Sequence[tuple[np.ndarray | None, np.ndarray | None]],
                       matrices: Sequence[np.ndarray], n_f: int) -> np.ndarray:
    """Z (n_f, n, n) = Σ a_j(ω) X_j for real matrices X_j and complex factors a_j, built
    on the real and imaginary parts separately: the same sums as the complex products
    (a zero part adds nothing; H is bit-identical), without complex temporaries."""
    n = matrices[0].shape[0]
    Z = np.empty((n_f, n, n), complex)
    term = None
    for part, out in ((0, Z.real), (1, Z.imag)):
        first = True
        for pair, X in zip(factors, matrices, strict=True):
            a = pair[part]
            if a is None:
                continue
            # the first term straight into Z, the others added to it: the same products
            # and sums, in the same order, as ``a₀X₀ + a₁X₁ + ...``, without temporaries
            if first:
                np.multiply(a[:, None, None], X, out=out)
                first = False
            else:
                if term is None:
                    term = np.empty((n_f, n, n))
                np.multiply(a[:, None, None], X, out=term)
                np.add(out, term, out=out)
        if first:
            out[...] = 0.0
    return Z


@dataclass(frozen=True, eq=False)
class Solved:
    """The solves of one model evaluation: H and what its Jacobian needs (see
    :func:`solve`). ``groups`` holds, per set of input columns solved together, the
    columns and ``X = Z_g⁻¹ [Oᵀ I_gᵀ]`` (n_f, n, n_out + n_cols)."""

    theta: np.ndarray
    terms: EffectTerms
    factors: tuple[tuple[np.ndarray | None, np.ndarray | None], ...]
    groups: tuple[tuple[list[int], np.ndarray], ...]
    H: np.ndarray  # (n_f, n_out, n_in), measurement-chain gains applied
    gain: np.ndarray | None  # (n_f, n_out, n_in) gains, None = none
    matrices: tuple[np.ndarray, np.ndarray, np.ndarray]  # M, K, C at theta
    H_raw: np.ndarray  # (n_f, n_out, n_in) before the gains


def solve(ctx: Context, theta: np.ndarray, terms: EffectTerms | None = None) -> Solved:
    """H (n_f, n_out, n_in) of the base model with parameters ``theta`` (SI) plus ``terms``.

    One batched solve ``Z⁻¹ [Oᵀ Iᵀ]`` per call (one more per input that carries its own
    ``dZ_input``: column j is then ``O (Z + ΔZ_j)⁻¹ i_j``), kept for :func:`model_jacobian`.
    """
    base = ctx.base
    terms = terms or EffectTerms()
    w = ctx.omega
    n_f = w.size
    o = ctx.out_rows if terms.out_rows is None else terms.out_rows
    i = ctx.in_rows
    n_out, n_in = o.shape[0], i.shape[0]
    plain = (list(range(n_in)) if terms.dZ_input is None
             else [j for j in range(n_in) if terms.dZ_input[j] is None])
    # A fit with the base frozen builds the same base Z(θ) at every evaluation, and an
    # effect that leaves Z and the output rows alone (gains, a ΔZ per input) also solves
    # it for the plain inputs every time: both are kept per context (the last few θ) and
    # reused, the same arrays (read-only). Z(θ) + ΔZ is then a new array, the same sums.
    base_factors = terms.a_m is None and terms.a_k is None and terms.a_c is None
    theta_key = np.asarray(theta, float).tobytes() if base_factors else None
    kept = None if theta_key is None else ctx._base_Z.get(theta_key)
    if kept is not None:
        (M, K, C), factors, Z = kept
    else:
        M, K, C = base.matrices(theta)
        # the plain viscous factors (eq. 4.54): a_m = −ω², a_k = 1, a_c = iω
        factors = _plain_factors(terms, w)
        Z = _dynamic_stiffness(factors, (M, K, C), n_f)
        if theta_key is not None:
            _keep(ctx._base_Z, theta_key, ((M, K, C), factors, _read_only(M, K, C, Z)[-1]))
    if terms.dZ is not None:
        if theta_key is None:
            Z += terms.dZ  # Z is this call's own array
        else:
            Z = Z + terms.dZ
    solve_key = (None if theta_key is None or terms.dZ is not None
                 or terms.out_rows is not None else (theta_key, tuple(plain)))
    X_plain = None if solve_key is None else ctx._base_solves.get(solve_key)
    # (dynamic stiffness, input columns) solved together
    to_solve: list[tuple[np.ndarray, list[int]]] = []
    if plain:
        to_solve.append((Z, plain))
    if terms.dZ_input is not None:
        to_solve.extend((Z + d, [j]) for j, d in enumerate(terms.dZ_input) if d is not None)
    H = np.empty((n_f, n_out, n_in), complex)
    groups = []
    for Zg, cols in to_solve:
        if Zg is Z and X_plain is not None:
            X = X_plain
        else:
            rhs = np.concatenate([o, i[cols]]).T.astype(complex)
            X = np.linalg.solve(Zg, np.broadcast_to(rhs, (n_f, *rhs.shape)))
            if Zg is Z and solve_key is not None:
                _keep(ctx._base_solves, solve_key, _read_only(X)[0])
        H[:, :, cols] = o @ X[..., n_out:]
        groups.append((cols, X))
    gain = _gain(terms, H.shape)
    return Solved(np.asarray(theta, float), terms, factors, tuple(groups),
                  H if gain is None else H * gain, gain, (M, K, C), H)


_BASE_SOLVES_KEPT = 4  # base Z(θ) and solves kept per context (see solve)


def _keep(memo: dict, key: object, value: object) -> None:
    """``memo[key] = value``, the oldest entry dropped beyond ``_BASE_SOLVES_KEPT``."""
    if len(memo) >= _BASE_SOLVES_KEPT:
        del memo[next(iter(memo))]
    memo[key] = value


def _read_only(*arrays: np.ndarray) -> tuple[np.ndarray, ...]:
    """``arrays``, marked read-only (kept arrays that callers share)."""
    for a in arrays:
        a.flags.writeable = False
    return arrays


def _gain(terms: EffectTerms, shape: tuple[int, ...]) -> np.ndarray | None:
    """The measurement-chain gain (n_f, n_out, n_in) of ``terms``; None when it has none."""
    if terms.out_gain is None and terms.in_gain is None:
        return None
    gain = np.ones(shape, complex)
    if terms.out_gain is not None:
        gain = gain * terms.out_gain[:, :, None]
    if terms.in_gain is not None:
        gain = gain * terms.in_gain[:, None, :]
    return gain


def _plain_factors(terms: EffectTerms, omega: np.ndarray
                   ) -> tuple[tuple[np.ndarray | None, np.ndarray | None], ...]:
    """(real, imaginary) parts of a_m, a_k, a_c of ``terms`` (eq. 4.54 where it leaves one
    unchanged: a_m = −ω², a_k = 1, a_c = iω)."""
    return (_split_factor(terms.a_m, -(omega**2), None),
            _split_factor(terms.a_k, np.ones_like(omega), None),
            _split_factor(terms.a_c, None, omega))


def _difference(new: np.ndarray | None, old: np.ndarray | None) -> np.ndarray | None:
    """``new − old`` of two optional arrays (None = zero); None when both are None."""
    if new is None and old is None:
        return None
    if old is None:
        return np.asarray(new)
    return -np.asarray(old) if new is None else np.asarray(new) - old


def effect_jacobian(ctx: Context, solved: Solved, changed: Sequence[EffectTerms],
                    steps: Sequence[float]) -> np.ndarray:
    """∂H along changes of the effect's terms, (n_f, n_out, n_in, k): column k is the
    first-order change of H from ``solved.terms`` to ``changed[k]`` divided by
    ``steps[k]`` (a forward difference of the terms, not of H), carried through the solve
    already made: with ``A = Z⁻¹Oᵀ``, ``B = Z⁻¹Iᵀ`` of each solved group (Z complex
    symmetric), ``δH = G ⊙ (δO B − Aᵀ δZ B) + δG ⊙ (O B)`` for changes δZ of the
    dynamic stiffness (frequency factors, common and per-input ΔZ), δO of the output rows
    and δG of the gains. No solve per column: for effects that change more than the
    common ΔZ (frequency factors, gains, output rows, a ΔZ per input) this replaces one
    solve per parameter. Every ``changed`` must keep the solve's groups (the same inputs
    with a ΔZ of their own)."""
    n_f, n_out, n_in = solved.H.shape
    old = solved.terms
    o = ctx.out_rows if old.out_rows is None else old.out_rows
    dH = np.empty((n_f, n_out, n_in, len(changed)), complex)
    for k, (new, h) in enumerate(zip(changed, steps, strict=True)):
        # δZ common to every column: the changed frequency factors times M, K, C, and ΔZ
        dZ = _difference(new.dZ, old.dZ)
        for X, f_new, f_old in zip(solved.matrices, _plain_factors(new, ctx.omega),
                                   solved.factors, strict=True):
            for a_new, a_old, unit in ((f_new[0], f_old[0], 1.0), (f_new[1], f_old[1], 1j)):
                da = _difference(a_new, a_old)
                if da is None or not np.any(da):
                    continue
                term = (unit * da)[:, None, None] * X
                dZ = term if dZ is None else dZ + term
        d_rows = (None if new.out_rows is None and old.out_rows is None
                  else (ctx.out_rows if new.out_rows is None else new.out_rows) - o)
        own = [None] * n_in if old.dZ_input is None else list(old.dZ_input)
        own_new = [None] * n_in if new.dZ_input is None else list(new.dZ_input)
        if [d is None for d in own] != [d is None for d in own_new]:
            raise ValueError("changed terms must keep the inputs that carry their own ΔZ")
        d_raw = np.zeros((n_f, n_out, n_in), complex)
        for cols, X in solved.groups:
            A, B = X[..., :n_out], X[..., n_out:]
            dZ_g = dZ
            if len(cols) == 1 and own[cols[0]] is not None:
                d_own = own_new[cols[0]] - own[cols[0]]
                dZ_g = d_own if dZ_g is None else dZ_g + d_own
            if dZ_g is not None:
                d_raw[:, :, cols] -= A.transpose(0, 2, 1) @ (dZ_g @ B)
            if d_rows is not None:
                d_raw[:, :, cols] += d_rows @ B
        gain_new = _gain(new, solved.H.shape)
        d_gain = None  # a missing gain is 1
        if gain_new is not None or solved.gain is not None:
            d_gain = ((1.0 if gain_new is None else gain_new)
                      - (1.0 if solved.gain is None else solved.gain))
        col = d_raw if solved.gain is None else solved.gain * d_raw
        if d_gain is not None:
            col = col + d_gain * solved.H_raw
        dH[..., k] = col / h
    return dH


def model_jacobian(ctx: Context, solved: Solved, dZ_directions: np.ndarray | None = None,
                   rows: np.ndarray | None = None, base_columns: bool = True) -> np.ndarray:
    """∂H/∂log θ (n_f, n_out, n_in, n_p) at a :func:`solve` of ``ctx``, from its solves.

    The atoms give ``∂H/∂θ_p = −(Z⁻¹Oᵀ)ᵀ ∂Z/∂θ_p (Z⁻¹Iᵀ)`` (Z complex symmetric). With
    ``dZ_directions``, k more columns ``−(Z⁻¹Oᵀ)ᵀ D_k (Z⁻¹Iᵀ)`` follow: the
    derivative of H along changes D_k of the common ΔZ (effect parameters that enter only
    through ``dZ``), without a solve per direction. ``dZ_directions`` is (n_f, k, n, n):
    each line's k directions together.

    With ``rows`` (flat indices into (n_f, n_out, n_in)), only those rows of
    ``dH.reshape(-1, n_p [+ k])`` are computed and returned, (rows.size, n_p [+ k]): the
    same products and sums of the same values, without the unmeasured pairs (a fit's
    Jacobian needs only the measured FRFs' lines). ``base_columns=False`` (with ``rows``)
    leaves out the n_p columns of θ: a fit with the base frozen needs only the k others.
    """
    if rows is not None:
        return _model_jacobian_rows(ctx, solved, dZ_directions, np.asarray(rows),
                                    base_columns)
    if not base_columns:
        raise ValueError("base_columns=False needs rows")
    base = ctx.base
    n_f = ctx.frequency_hz.size
    n_out, n_in = solved.H.shape[1:]
    n_extra = 0 if dZ_directions is None else dZ_directions.shape[1]
    dH = np.empty((n_f, n_out, n_in, base.n_params + n_extra), complex)
    a_kind = np.stack([_factor(p, n_f) for p in solved.factors], axis=1)  # (n_f, 3)
    # d/dlog θ of each atom's factor, atoms grouped by parameter: (n_a, n_f)
    c_atoms = (base.grouped_weights[:, None] * a_kind[:, base.grouped_kinds].T
               * solved.theta[base.grouped_params][:, None])
    for cols, X in solved.groups:
        n_c, n = len(cols), X.shape[1]
        # atom projections g_aᵀ X for all lines in one real product: (n_a, n_f, n_out + n_c)
        ab = np.tensordot(base.grouped_vectors, X.view(float), axes=([1], [1])).view(complex)
        # the outer products in blocks of lines that stay in a core's cache (~0.25 MB):
        # every value is computed as in one block (148 lines, 38 atoms: 2.3 -> 1.6 ms)
        block = max(1, 2**18 // (16 * ab.shape[0] * n_out * n_c))
        for f0 in range(0, n_f, block):
            f = slice(f0, f0 + block)
            outer = ((c_atoms[:, f, None] * ab[:, f, :n_out])[:, :, :, None]
                     * ab[:, f, None, n_out:])  # (n_a, lines, n_out, n_c)
            per_param = np.add.reduceat(outer, base.param_starts, axis=0)  # (n_p, ...)
            dH[f, :, cols, :base.n_params] = -np.moveaxis(per_param, 0, -1)
        if n_extra:
            # −Aᵀ (D_k B), the k directions stacked per line (two products per line)
            A, B = X[..., :n_out], X[..., n_out:]
            DB = dZ_directions.reshape(n_f, n_extra * n, n) @ B  # (n_f, k n, n_c)
            DB = DB.reshape(n_f, n_extra, n, n_c).transpose(0, 2, 1, 3)
            ext = A.transpose(0, 2, 1) @ DB.reshape(n_f, n, n_extra * n_c)
            dH[:, :, cols, base.n_params:] = -ext.reshape(n_f, n_out, n_extra, n_c
                                                          ).transpose(0, 1, 3, 2)
    return dH if solved.gain is None else dH * solved.gain[..., None]


def _model_jacobian_rows(ctx: Context, solved: Solved, dZ_directions: np.ndarray | None,
                         rows: np.ndarray, base_columns: bool = True) -> np.ndarray:
    """:func:`model_jacobian` at the flat indices ``rows`` only: each value is the same
    product ``(c_a a_o) b_i`` of the same factors, summed over a parameter's atoms in the
    same order (``reduceat`` along the atoms), as in the full array. Without
    ``base_columns``, only the ΔZ directions' columns."""
    base = ctx.base
    n_f = ctx.frequency_hz.size
    n_out, n_in = solved.H.shape[1:]
    n_p = base.n_params if base_columns else 0
    n_extra = 0 if dZ_directions is None else dZ_directions.shape[1]
    out = np.empty((rows.size, n_p + n_extra), complex)
    line_out, col_in = np.divmod(rows, n_in)  # (line, output) flat, input
    if base_columns:
        a_kind = np.stack([_factor(p, n_f) for p in solved.factors], axis=1)  # (n_f, 3)
        c_atoms = (base.grouped_weights[:, None] * a_kind[:, base.grouped_kinds].T
                   * solved.theta[base.grouped_params][:, None])
    for cols, X in solved.groups:
        n_c, n = len(cols), X.shape[1]
        local = np.full(n_in, -1)
        local[cols] = np.arange(n_c)
        sel = np.flatnonzero(local[col_in] >= 0)
        if not sel.size:
            continue
        lo_sel = line_out[sel]  # line * n_out + output
        c_sel = local[col_in[sel]]
        if n_extra:
            A, B = X[..., :n_out], X[..., n_out:]
            DB = dZ_directions.reshape(n_f, n_extra * n, n) @ B  # (n_f, k n, n_c)
            DB = DB.reshape(n_f, n_extra, n, n_c).transpose(0, 2, 1, 3)
            ext = A.transpose(0, 2, 1) @ DB.reshape(n_f, n, n_extra * n_c)
            ext = ext.reshape(n_f * n_out, n_extra, n_c)
            out[sel, n_p:] = -ext[lo_sel, :, c_sel]
        if not base_columns:
            continue
        ab = np.tensordot(base.grouped_vectors, X.view(float), axes=([1], [1])).view(complex)
        ca = (c_atoms[:, :, None] * ab[:, :, :n_out]).reshape(ab.shape[0], -1)
        b_in = ab[:, :, n_out:].reshape(ab.shape[0], -1)
        b_idx = (lo_sel // n_out) * n_c + c_sel  # line * n_c + input of the group
        # in blocks of rows that stay in a core's cache (each value as in one block)
        block = max(1, 2**18 // (16 * ab.shape[0]))
        every = sel.size == rows.size  # one group: its rows are all, in order
        for e0 in range(0, sel.size, block):
            e = slice(e0, e0 + block)
            outer = ca.take(lo_sel[e], axis=1) * b_in.take(b_idx[e], axis=1)  # (n_a, rows)
            per_param = np.add.reduceat(outer, base.param_starts, axis=0)  # (n_p, rows)
            if every:
                np.negative(per_param.T, out=out[e, :n_p])
            else:
                out[sel[e], :n_p] = -per_param.T
    if solved.gain is not None:
        out *= solved.gain.reshape(-1)[rows][:, None]
    return out


def evaluate(ctx: Context, theta: np.ndarray, terms: EffectTerms | None = None,
             jacobian: bool = False, dZ_directions: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray | None]:
    """H (n_f, n_out, n_in) and, optionally, ∂H/∂log θ (n_f, n_out, n_in, n_p [+ k]):
    :func:`solve` then, with ``jacobian``, :func:`model_jacobian` (``dZ_directions``: see
    there)."""
    solved = solve(ctx, theta, terms)
    if not jacobian:
        return solved.H, None
    return solved.H, model_jacobian(ctx, solved, dZ_directions)


def _factor(pair: tuple[np.ndarray | None, np.ndarray | None], n_f: int) -> np.ndarray:
    """A frequency factor (n_f,) complex from its (real, imaginary) parts."""
    re, im = pair
    out = np.zeros(n_f, complex)
    if re is not None:
        out.real = re
    if im is not None:
        out.imag = im
    return out


# ---------------------------------------------------------------------------------------
# Candidate library
# ---------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class LineSpringPlace:
    """Where a line spring may act: between ``bone_a`` and ``bone_b`` (``""``: ground),
    along a line through ``centre_m + d`` with every component of ``d`` within
    ``reach_m``; its stiffness is ``k0_n_per_m |v|²`` (see :func:`_ligament_candidates`)."""

    bone_a: str
    bone_b: str
    centre_m: np.ndarray
    k0_n_per_m: float
    reach_m: float


@dataclass(frozen=True, eq=False)
class Candidate:
    """One parametric extension at one place.

    ``build(u, ctx)`` maps the internal parameter vector ``u`` (bounded by ``lower``,
    ``upper``; several ``starts``) to :class:`EffectTerms`; ``describe(u)`` gives the
    physical parameters (SI, named with units) for the report.
    """

    effect: str
    variant: str
    place: str
    place_kind: str  # "global", "output", "input", "inputs", "bone", "joint"
    labels: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    starts: tuple[np.ndarray, ...]
    build: Callable[[np.ndarray, Context], EffectTerms]
    describe: Callable[[np.ndarray], dict[str, float]]
    bone: str = ""  # the bone the place belongs to ("" when not on one bone)
    # for a line spring (missing ligament): where it acts, so that the diagnosis can
    # compute a linearised start (:func:`line_spring_basis`, :func:`line_spring_parameters`)
    line_spring: LineSpringPlace | None = None
    # the effect parameters at which the extension vanishes (the base model), when that
    # point lies within the bounds: a joint fit that ends worse than the base is finished
    # again from there
    null: np.ndarray | None = None
    # effect parameters that change the model only through the common ΔZ (``dZ``) even
    # when others do not: their Jacobian columns need no solve (see ``with_extension``)
    dZ_params: tuple[int, ...] = ()
    # effect parameters scored with the base frozen, whose best points start one more
    # joint fit: for extensions whose own starts miss narrow basins (the diagnosis's
    # ``screened_grid_starts``)
    screen_grid: tuple[np.ndarray, ...] = ()
    # a richer form of this candidate at the same place, fitted only from this one's fit
    # (the diagnosis's refinement stage): that candidate, whose parameters are this one's
    # then more, and the start of the extra ones
    refined: tuple[Candidate, np.ndarray] | None = None

    @property
    def n_params(self) -> int:
        """Number of effect parameters (the complexity of the candidate)."""
        return len(self.labels)


def _sdof_transmissibility(omega: np.ndarray, f_hz: float, zeta: float) -> np.ndarray:
    """T = (k + iωc)/(k + iωc − ω²m) of a mass on a spring-damper (base excitation)."""
    wn = 2 * np.pi * f_hz
    num = wn**2 + 2j * zeta * wn * omega
    return num / (num - omega**2)


def _rank1(coef: np.ndarray, g: np.ndarray) -> np.ndarray:
    return coef[:, None, None] * np.outer(g, g)[None]


def _point_block(ctx: Context, bone: str, point_m: np.ndarray) -> np.ndarray:
    """(3, n_dof) rows of the x, y, z displacement of a point on ``bone``."""
    return ctx.base.rows([bone] * 3, np.tile(point_m, (3, 1)), np.eye(3))


def _perp_basis(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    d = d / np.linalg.norm(d)
    helper = np.eye(3)[int(np.argmin(np.abs(d)))]
    e1 = np.cross(d, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(d, e1)


def _f_starts(ctx: Context, n: int = 6) -> np.ndarray:
    """Log-spaced start frequencies (Hz) covering the measured band and a bit beyond."""
    return _band_starts_hz(ctx.frequency_hz, n)


def _band_starts_hz(frequency_hz: np.ndarray, n: int) -> np.ndarray:
    """:func:`_f_starts` for a frequency grid (Hz)."""
    f = np.asarray(frequency_hz, float)
    return np.geomspace(max(f.min(), 1.0) * 1.2, f.max() * 1.1, n)


def _global_candidates() -> list[Candidate]:
    cands = []

    def fdk_build(u: np.ndarray, ctx: Context) -> EffectTerms:
        # eq. 7.1 and 7.3: K(ω) = K (1 + f_k ω / (4 ω_max))
        return EffectTerms(a_k=1.0 + u[0] * ctx.omega / (4 * ctx.omega_max))

    cands.append(Candidate(
        "frequency_dependent_stiffness", "eq7.3", "all springs", "global", ("f_k",),
        np.array([-2.0]), np.array([10.0]), (np.array([0.5]),), fdk_build,
        lambda u: {"f_k": float(u[0])}, null=np.array([0.0])))

    def hyst_c_build(u: np.ndarray, ctx: Context) -> EffectTerms:
        # eq. 7.1-7.2: i(ωC + D), D = f_c C ω_max / 4
        return EffectTerms(a_c=1j * (ctx.omega + u[0] * ctx.omega_max / 4))

    cands.append(Candidate(
        "hysteretic_damping", "eq7.2 (D = f_c C w_max/4)", "all joints", "global", ("f_c",),
        np.array([0.0]), np.array([200.0]), (np.array([0.5]), np.array([5.0])), hyst_c_build,
        lambda u: {"f_c": float(u[0])}, null=np.array([0.0])))

    def hyst_k_build(u: np.ndarray, ctx: Context) -> EffectTerms:
        # structural damping: K (1 + i η), loss factor η
        return EffectTerms(a_k=np.full(ctx.omega.shape, 1.0 + 1j * u[0]))

    cands.append(Candidate(
        "hysteretic_damping", "loss factor (K(1+i eta))", "all springs", "global", ("eta",),
        np.array([0.0]), np.array([2.0]), (np.array([0.02]), np.array([0.2])), hyst_k_build,
        lambda u: {"loss_factor": float(u[0])}, null=np.array([0.0])))
    return cands


def _tissue_candidates(ctx: Context) -> list[Candidate]:
    """Soft tissue between skin and bone (thesis ch. 8: the probe sits on the skin, the
    shaker pushes through it): a tissue mass m on a spring-damper (f_t, ζ_t) to the bone
    point, coupled on every axis. Exact condensation of the extra DOF: the bone point sees
    ``ΔZ = −ω² m T GᵀG`` and the channel the transmissibility ``T`` (force into the tissue
    mass F: ``(Z + ΔZ) u = T Gᵀ d F``, ``T = k*/(k* − ω²m)``, ``k* = k + iωc``).

    Three variants:

    * ``tissue at output``: the probe reads the tissue mass (T on that output row), the
      tissue loads the bone in every FRF;
    * ``tissue at input``: the shaker drives the tissue mass (T on that input column), the
      tissue stays attached to the bone in every FRF (it loads the columns of the other
      inputs too);
    * ``tissue under the shaker``: the tissue is a subsystem only while the shaker pushes
      on it — in the setups that drive that input, so ΔZ and T act on that input's column
      alone (``O (Z + ΔZ_j)⁻¹ i_j T``) and the other inputs' FRFs see the bare bone; the
      measured FRF of a session is assembled setup by setup (one excitation point each,
      thesis table 6.3), and the tissue's own mass at rest is part of the bone mass that
      parameter updating fits. At one input, or at every driven input with one shared
      tissue (the real shaker always pushes through skin).
    """
    cands = []
    lo = np.array([np.log(1.0), np.log(0.02), np.log(1e-4)])
    hi = np.array([np.log(5000.0), np.log(3.0), np.log(2.0)])
    starts = tuple(np.array([np.log(f), np.log(0.3), np.log(0.02)]) for f in _f_starts(ctx))
    labels = ("log_f", "log_zeta", "log_m")

    def describe(u: np.ndarray) -> dict[str, float]:
        return {"frequency_hz": float(np.exp(u[0])), "damping_ratio": float(np.exp(u[1])),
                "mass_kg": float(np.exp(u[2]))}

    def tissue(u: np.ndarray, c: Context, bone: str, pos: np.ndarray
               ) -> tuple[np.ndarray, np.ndarray]:
        """(T (n_f,), ΔZ (n_f, n, n)) of the tissue at a point of ``bone``."""
        T = _sdof_transmissibility(c.omega, np.exp(u[0]), np.exp(u[1]))
        gram = c.base.fixed_gram(bone, pos, np.eye(3))  # GᵀG of _point_block(c, bone, pos)
        dZ = (-(c.omega**2) * np.exp(u[2]) * T)[:, None, None] * gram[None]
        return T, dZ

    for side, names in (("output", ctx.out_names), ("input", ctx.in_names)):
        for j, name in enumerate(names):
            def build(u: np.ndarray, c: Context, j: int = j, side: str = side) -> EffectTerms:
                if side == "output":
                    bone, pos = c.out_bones[j], c.out_position_m[j]
                else:
                    bone, pos = c.in_bones[j], c.in_position_m[j]
                T, dZ = tissue(u, c, bone, pos)
                n_ch = len(c.out_names) if side == "output" else len(c.in_names)
                gain = np.ones((c.omega.size, n_ch), complex)
                gain[:, j] = T
                if side == "output":
                    return EffectTerms(dZ=dZ, out_gain=gain)
                return EffectTerms(dZ=dZ, in_gain=gain)

            bone = ctx.out_bones[j] if side == "output" else ctx.in_bones[j]
            cands.append(Candidate("soft_tissue", f"tissue at {side}", name, side, labels,
                                   lo, hi, starts, build, describe, bone))

    bones = set(ctx.base.bones)
    driven = [j for j, b in enumerate(ctx.in_bones) if b in bones]
    places = [([j], ctx.in_names[j], "input", ctx.in_bones[j]) for j in driven]
    if len(driven) > 1:
        # the whole drive chain, no place to choose: fitted jointly like the global
        # effects (screening with the base fit frozen misranks it: a tissue in every
        # column is what parameter updating distorts the base most to absorb)
        places.append((driven, "all inputs", "global", ""))
    for cols, name, kind, bone in places:
        def sbuild(u: np.ndarray, c: Context, cols: list[int] = cols) -> EffectTerms:
            dZs: list[np.ndarray | None] = [None] * len(c.in_names)
            gain = np.ones((c.omega.size, len(c.in_names)), complex)
            for j in cols:
                T, dZs[j] = tissue(u, c, c.in_bones[j], c.in_position_m[j])
                gain[:, j] = T
            return EffectTerms(dZ_input=tuple(dZs), in_gain=gain)

        # the shared tissue at every drive point is its own variant (one place): ranked
        # against the one-input variant, not hidden behind it as a fourth place
        variant = "tissue under the shaker" + (", every input" if len(cols) > 1 else "")
        cands.append(Candidate("soft_tissue", variant, name, kind, labels, lo, hi, starts,
                               sbuild, describe, bone))
    return cands + _armature_candidates(ctx, suspended=False)


def _orientation_candidates(ctx: Context) -> list[Candidate]:
    """Sensor misorientation at one output (thesis ch. 6.2, fig. 6.9): the probe axis is
    tilted by (a, b) in the plane normal to the nominal direction (point target: the
    projection of the motion on the tilted axis), or, for a flat reflector, the reading is
    the nominal component scaled by 1/cos α (a gain)."""
    cands = []
    for j, name in enumerate(ctx.out_names):
        d = ctx.out_direction[j]
        e1, e2 = _perp_basis(d)

        def build(u: np.ndarray, c: Context, j: int = j, e1: np.ndarray = e1,
                  e2: np.ndarray = e2) -> EffectTerms:
            d = c.out_direction[j] + u[0] * e1 + u[1] * e2
            d = d / np.linalg.norm(d)
            rows = c.out_rows.copy()
            rows[j] = c.base.rows([c.out_bones[j]], c.out_position_m[j:j + 1], d[None])[0]
            return EffectTerms(out_rows=rows)

        def describe(u: np.ndarray) -> dict[str, float]:
            return {"tilt_deg": float(np.degrees(np.arctan(np.hypot(u[0], u[1])))),
                    "tilt_a": float(u[0]), "tilt_b": float(u[1])}

        starts = tuple(np.array(s) for s in ((0.05, 0.0), (0.0, 0.05), (-0.05, 0.0),
                                             (0.0, -0.05)))
        cands.append(Candidate("sensor_misorientation", "tilted axis", name, "output",
                               ("tilt_a", "tilt_b"), np.array([-1.5, -1.5]),
                               np.array([1.5, 1.5]), starts, build, describe,
                               ctx.out_bones[j], null=np.zeros(2)))

        def gbuild(u: np.ndarray, c: Context, j: int = j) -> EffectTerms:
            gain = np.ones((c.omega.size, len(c.out_names)), complex)
            gain[:, j] = np.exp(u[0])
            return EffectTerms(out_gain=gain)

        # a flat reflector read through a tilted beam gives 1/cos α >= 1 (fig. 6.9): a gain
        # below 1 would be a calibration error, not a misorientation
        cands.append(Candidate("sensor_misorientation", "1/cos gain", name, "output",
                               ("log_gain",), np.array([0.0]), np.array([np.log(3.0)]),
                               (np.array([0.1]),), gbuild,
                               lambda u: {"gain": float(np.exp(u[0]))}, ctx.out_bones[j],
                               null=np.zeros(1)))
    return cands


def _mass_candidates(ctx: Context) -> list[Candidate]:
    """A point mass rigidly attached to a bone at an unknown position (ΔM = m TᵀT, the
    same kinematics as eq. 4.9)."""
    cands = []
    for bone in ctx.base.bones:
        ref = ctx.base.reference_point(bone)

        def build(u: np.ndarray, c: Context, bone: str = bone,
                  ref: np.ndarray = ref) -> EffectTerms:
            T = _point_block(c, bone, ref + u[1:4])
            dM = np.exp(u[0]) * T.T @ T
            return EffectTerms(dZ=-(c.omega**2)[:, None, None] * dM[None].astype(complex))

        def describe(u: np.ndarray, ref: np.ndarray = ref) -> dict[str, float]:
            p = ref + u[1:4]
            return {"mass_kg": float(np.exp(u[0])), "x_m": float(p[0]), "y_m": float(p[1]),
                    "z_m": float(p[2])}

        # within 12 cm of the centre of mass on every axis (an innominate reaches ~10 cm
        # from it: a 384 g mass at the ischial spine, 8.5 cm below, was out of reach at
        # 8 cm), started also at every measured point of the bone (a probe holder)
        lim = 0.12
        offsets = [(0, 0, 0), (0.03, 0, 0), (-0.03, 0, 0), (0, 0, 0.03)]
        offsets += [tuple(p - ref) for _name, b, p in _channel_points(ctx)
                    if b == bone and np.all(np.abs(p - ref) < lim)]
        starts = tuple(np.array([np.log(m), *off]) for m in (0.05, 0.2) for off in offsets)
        cands.append(Candidate("added_mass", "point mass", bone, "bone",
                               ("log_m", "dx", "dy", "dz"),
                               np.array([np.log(1e-3), -lim, -lim, -lim]),
                               np.array([np.log(2.0), lim, lim, lim]), starts, build, describe,
                               bone))
    return cands


def _ligament_candidates(ctx: Context) -> list[Candidate]:
    """A missing ligament: one extra spring ``k n nᵀ`` (eq. 4.12-4.13, zero rest elongation)
    between the two bones of a joint — or from a bone to ground (e.g. an iliolumbar
    ligament to an immobile L5) — acting along a line through an unknown point ``p``
    near the joint (only the line of action matters). Written as ``v vᵀ`` with
    ``v = √(k/k₀) n`` so that the direction needs no angles. Thesis ch. 5.3/11: the
    sacrotuberous, sacrospinous and iliolumbar ligaments were left out of the model."""
    cands = []
    k0 = 1e5
    bones = set(ctx.base.bones)
    lim = 0.09
    places: list[tuple[str, str, str, np.ndarray]] = []
    for joint, (ba, bb, centre) in JOINT_CENTRES_M.items():
        if ba in bones and bb in bones:
            places.append((joint, ba, bb, centre))
    for bone in ctx.base.bones:
        places.append((f"{bone} to ground", bone, "", ctx.base.reference_point(bone)))
    for joint, ba, bb, centre in places:
        place = LineSpringPlace(ba, bb, centre, k0, lim)

        def build(u: np.ndarray, c: Context, place: LineSpringPlace = place) -> EffectTerms:
            g = u[:3] @ line_spring_rows(c.base, place, place.centre_m + u[3:6])
            dK = k0 * np.outer(g, g)
            return EffectTerms(dZ=np.broadcast_to(dK.astype(complex),
                                                  (c.omega.size, *dK.shape)))

        def describe(u: np.ndarray, centre: np.ndarray = centre) -> dict[str, float]:
            v = u[:3]
            k = k0 * float(v @ v)
            n = v / np.linalg.norm(v) if k > 0 else v
            p = centre + u[3:6]
            return {"stiffness_n_per_m": k, "axis_x": float(n[0]), "axis_y": float(n[1]),
                    "axis_z": float(n[2]), "x_m": float(p[0]), "y_m": float(p[1]),
                    "z_m": float(p[2])}

        offsets = ((0.0, 0.0, 0.0), (-0.04, 0.0, -0.06))
        starts = tuple(np.array([*(s * ax), *off]) for ax in np.eye(3) for s in (1.0,)
                       for off in offsets)
        cands.append(Candidate("missing_ligament", "extra spring" if bb else "spring to ground",
                               joint, "joint" if bb else "bone",
                               ("vx", "vy", "vz", "dx", "dy", "dz"),
                               np.array([-30, -30, -30, -lim, -lim, -lim], float),
                               np.array([30, 30, 30, lim, lim, lim], float), starts, build,
                               describe, ba, place))
    return cands


def support_on_line(spring: Candidate, u_spring: np.ndarray, frequency_hz: np.ndarray
                    ) -> Candidate:
    """A support (bed, foam pad, frame) touching a bone along the line of action of a fitted
    spring to ground: ``support_resonance``, variant ``bed contact on a fitted line``.

    The contact is a damped spring (k_c + iω c_c, c_c = 2ζ_c √(k_c m): a foam pad is
    lossy) to a support body of mass m on its own suspension (f_s, ζ_s). Condensing the
    body gives the contact's dynamic stiffness
    ``k_eff = k_c* k_s* / (k_c* + k_s*)``, ``k_s* = m(2πf_s)² + 2iζ_s m 2πf_s ω − ω²m``,
    which adds ``k_eff n nᵀ`` along the line exactly as the spring's ``k n nᵀ`` (eq.
    4.12-4.13); a frequency-independent spring is its limit k_s → ∞, ζ_c → 0. The bed
    contacts of :func:`_support_candidates` sit at measured points, their contact damped
    only in their refined form; a bed under an unmeasured point (judge-like set
    4242_026: 2.2 kg at 113 Hz under the right iliac fossa, ζ 0.1) is taken by a spring
    to ground there, whose line this candidate reuses. Parameters: the spring's ``v``
    (direction, k_c = k₀|v|²) and ``d`` (point), then log f_s, log ζ_s, log m, log ζ_c:
    ten in all, the line counted.
    Starts: the fitted line, k_c one and three times the spring's stiffness, f_s over the
    band, m from 0.3 to 3 kg."""
    place = spring.line_spring
    if place is None or place.bone_b:
        raise ValueError(f"{spring.place}: a support acts along a spring to ground")
    k0 = place.k0_n_per_m

    def build(u: np.ndarray, c: Context) -> EffectTerms:
        g = u[:3] @ line_spring_rows(c.base, place, place.centre_m + u[3:6])
        k_c = max(k0 * float(u[:3] @ u[:3]), 1e-9 * k0)
        w_s = 2 * np.pi * np.exp(u[6])
        m = np.exp(u[8])
        k_s = m * w_s**2 + 2j * np.exp(u[7]) * m * w_s * c.omega - c.omega**2 * m
        k_cd = damped_contact(k_c, np.exp(u[9]), m, c.omega)
        # k_eff n nᵀ = (k_eff / k_c) k₀ g gᵀ (g carries √(k_c/k₀))
        ratio = k_cd * k_s / ((k_cd + k_s) * k_c)
        return EffectTerms(dZ=ratio[:, None, None] * (k0 * np.outer(g, g))[None])

    def describe(u: np.ndarray) -> dict[str, float]:
        line = spring.describe(u[:6])
        return {"contact_stiffness_n_per_m": line["stiffness_n_per_m"],
                **{k: v for k, v in line.items() if k != "stiffness_n_per_m"},
                "frequency_hz": float(np.exp(u[6])), "damping_ratio": float(np.exp(u[7])),
                "mass_kg": float(np.exp(u[8])),
                "contact_damping_ratio": float(np.exp(u[9]))}

    u_spring = np.asarray(u_spring, float)
    starts = tuple(np.concatenate([u_spring[:3] * np.sqrt(a), u_spring[3:6],
                                   np.log([f, 0.15, m, 0.1])])
                   for a in (1.0, 3.0)
                   for f in _band_starts_hz(frequency_hz, 6)
                   for m in (0.3, 1.0, 3.0))
    lower = np.concatenate([spring.lower[:6], np.log([0.5, 0.005, 1e-3, 0.005])])
    upper = np.concatenate([spring.upper[:6], np.log([3000.0, 3.0, 50.0, 3.0])])
    return Candidate("support_resonance", "bed contact on a fitted line", spring.place,
                     "bone", ("vx", "vy", "vz", "dx", "dy", "dz", "log_f", "log_zeta",
                              "log_m", "log_zeta_contact"),
                     lower, upper, starts, build, describe, spring.bone)


def line_spring_rows(base: BaseStructure, place: LineSpringPlace, point_m: np.ndarray
                     ) -> np.ndarray:
    """(3, n_dof) rows of the relative x, y, z displacement of ``bone_a`` with respect to
    ``bone_b`` (or ground) at ``point_m``: a spring of stiffness k along the unit vector n
    through that point adds ``k g gᵀ`` with ``g = nᵀ G`` (eq. 4.12-4.13, zero rest
    elongation).

    Read-only, and kept for the latest points: a line spring's Jacobian builds its ΔZ at
    the fitted point once per parameter, the direction's three at the same point (the
    same rows, computed once)."""
    point = np.asarray(point_m, float)
    key = (place.bone_a, place.bone_b, point.tobytes() + bytes(point.shape))
    memo = base._line_rows
    G = memo.get(key)
    if G is None:
        p = np.tile(point, (3, 1))
        G = base.rows([place.bone_a] * 3, p, np.eye(3))
        if place.bone_b:
            G = G - base.rows([place.bone_b] * 3, p, np.eye(3))
        G.flags.writeable = False
        if len(memo) >= _LINE_ROWS_KEPT:
            del memo[next(iter(memo))]
        memo[key] = G
    return G


_LINE_ROWS_KEPT = 64  # points of line_spring_rows kept per base structure


def line_spring_basis(base: BaseStructure, place: LineSpringPlace) -> np.ndarray:
    """(r, n_dof) orthonormal rows spanning every line-spring vector ``g = nᵀ G(p)`` of the
    place (r = 6 for two rigid bones or a bone and ground: the relative rigid motion).

    Any line spring there is ``ΔK = Qᵀ (k w wᵀ) Q`` for some w in this basis, which makes
    the first-order FRF change a quadratic form in w (used for the linearised start)."""
    h = place.reach_m
    pts = [place.centre_m + h * e for e in (np.zeros(3), *np.eye(3))]
    G = np.concatenate([line_spring_rows(base, place, p) for p in pts])
    _, sv, Vt = np.linalg.svd(G, full_matrices=False)
    return Vt[sv > 1e-9 * sv[0]]


def line_spring_parameters(base: BaseStructure, place: LineSpringPlace, g: np.ndarray
                           ) -> tuple[np.ndarray, float]:
    """Candidate parameters ``u = (v, d)`` of the line spring whose ``√k₀ vᵀ G(centre + d)``
    is closest to the generalised vector ``g`` (n_dof; sign free), with |d_i| <= reach.

    A vector g of the relative-motion space is a line (Plücker coordinates) only on a
    5-dimensional subset; the closest line is taken. Returns (u, relative misfit)."""
    g = np.asarray(g, float)
    norm_g = float(np.linalg.norm(g))
    if norm_g == 0.0:
        return np.concatenate([np.eye(3)[0], np.zeros(3)]), 1.0
    sk = np.sqrt(place.k0_n_per_m)

    def solve(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        Gt = sk * line_spring_rows(base, place, place.centre_m + d).T  # (n, 3)
        v, *_ = np.linalg.lstsq(Gt, g, rcond=None)
        return v, (Gt @ v - g) / norm_g

    lim = place.reach_m * (1 - 1e-6)
    best = (np.inf, np.zeros(3), np.zeros(3))
    for d0 in (np.zeros(3), *(s * 0.5 * lim * e for e in np.eye(3) for s in (-1, 1))):
        sol = least_squares(lambda d: solve(d)[1], d0, bounds=(-lim, lim), method="trf",
                            max_nfev=40)
        if sol.cost < best[0]:
            best = (sol.cost, sol.x, solve(sol.x)[0])
    cost, d, v = best
    return np.concatenate([v, d]), float(np.sqrt(2 * cost))


def base_dynamic_stiffness(ctx: Context, theta: np.ndarray) -> np.ndarray:
    """Z(ω) = −ω²M + K + iωC of the base model at ``theta`` on the context's lines,
    (n_f, n_dof, n_dof) complex (eq. 4.52)."""
    w = ctx.omega
    M, K, C = ctx.base.matrices(theta)
    return (-(w**2)[:, None, None] * M + K[None] + 1j * w[:, None, None] * C).astype(complex)


def response_vectors(ctx: Context, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(Z⁻¹Oᵀ, Z⁻¹Iᵀ)`` of the base model at ``theta``: (n_f, n_dof, n_out) and
    (n_f, n_dof, n_in); the first-order change of H for a stiffness change ΔK is
    ``δH = −(Z⁻¹Oᵀ)ᵀ ΔK (Z⁻¹Iᵀ)`` (Z complex symmetric)."""
    w = ctx.omega
    Z = base_dynamic_stiffness(ctx, theta)
    n_out = ctx.out_rows.shape[0]
    rhs = np.concatenate([ctx.out_rows, ctx.in_rows]).T.astype(complex)
    X = np.linalg.solve(Z, np.broadcast_to(rhs, (w.size, *rhs.shape)))
    return X[..., :n_out], X[..., n_out:]


def _channel_points(ctx: Context) -> list[tuple[str, str, np.ndarray]]:
    """(name, bone, position in m) of every measured point, outputs then inputs."""
    points = [(n, b, np.asarray(p, float)) for n, b, p in zip(
        ctx.out_names, ctx.out_bones, ctx.out_position_m, strict=True)]
    if ctx.in_position_m is not None:
        points += [(n, b, np.asarray(p, float)) for n, b, p in zip(
            ctx.in_names, ctx.in_bones, ctx.in_position_m, strict=True)]
    return points


def _contact_points(ctx: Context) -> list[tuple[str, str, np.ndarray]]:
    """Where a support may touch each bone: (bone, label, point in m). The bone's centre of
    mass (label "") and every measured point on it (label " at NAME"): a subject lies on
    the landmarks the probes and the shaker reach (face-up: sacrum and PSIS on the bed)."""
    places = []
    for bone in ctx.base.bones:
        places.append((bone, "", ctx.base.reference_point(bone)))
        seen: list[np.ndarray] = []
        for name, b, pos in _channel_points(ctx):
            if b != bone or any(np.linalg.norm(pos - q) < 0.01 for q in seen):
                continue  # one contact per spot (x and y probes of one landmark share it)
            seen.append(pos)
            places.append((bone, f" at {name}", np.asarray(pos, float)))
    return places


def damped_contact(k_c_n_per_m: float | np.ndarray, zeta_c: float, mass_kg: float,
                   omega: np.ndarray) -> np.ndarray:
    """A lossy contact's dynamic stiffness (N/m) at ``omega`` (rad/s): its stiffness with
    a dashpot of damping ratio ζ_c against the body it carries, ``k_c + iω 2ζ_c √(k_c m)``
    (a foam pad, or the skin over a landmark)."""
    return k_c_n_per_m + 2j * zeta_c * np.sqrt(k_c_n_per_m * mass_kg) * omega


DAMPED_BED_VARIANT = "bed contact, damped"
"""The bed contact's refined form: its contact damped (:func:`_support_candidates`)."""
DAMPED_BED_START = 0.01
"""The contact damping ratio ζ_c its fit starts from (the undamped fit's other values)."""


def _support_candidates(ctx: Context) -> list[Candidate]:
    """Support / fixture resonances (thesis ch. 10-11: foam and frame resonances drove the
    measured response).

    * ``bed``: the pelvis touches a support body (exam bed, foam, frame) at a bone (at its
      centre of mass or at one of its measured points, :func:`_contact_points`): a mass
      m on its own suspension (f_s, ζ_s, i.e. k_s = m(2πf_s)², c_s = 2ζ_s m 2πf_s) in
      contact through a stiffness k_c, along one axis or all three. Condensing the support
      DOF gives the dynamic stiffness seen by the bone point
      ``k_eff = k_c (k_s* − ω²m) / (k_c + k_s* − ω²m)``, ``k_s* = k_s + iωc_s``; the two
      limits are a grounded spring-mass (k_c → ∞) and a resonant frame mass (k_s → 0).
      Its refined form (``refined``, :data:`DAMPED_BED_VARIANT`) damps the contact,
      ``k_c* = k_c + iω 2ζ_c √(k_c m)`` in place of k_c (a foam pad or the skin over the
      landmark is lossy): five parameters, fitted from the undamped contact's fit only.
      Judge-like set 2121_008 (1.43 kg at 104 Hz, ζ 0.094 in contact and suspension):
      undamped, the bed was fitted only with one damping per dashpot added, held-out gap
      1198 -> 63.7. As a fifth parameter of every bed contact's own fits, ζ_c sent the
      fits of a benchmark bed (seed 9001 support #0, 3.6 kg at 30 Hz, undamped contact)
      to another basin (gap 0.155 -> 1.65).
    * ``excitation fixture``: a resonance in the force path of one input (shaker on a
      flexible fixture), H[:, :, j] × (1 + μ ω² /(ω_r² − ω² + 2iζω_rω)) — or all inputs.
    """
    cands = []
    f_st = _f_starts(ctx, 6)
    axes = {"xyz": np.eye(3), "x": np.eye(3)[:1], "y": np.eye(3)[1:2], "z": np.eye(3)[2:]}
    lo = np.array([np.log(0.5), np.log(0.005), np.log(1e-3), np.log(1e2)])
    hi = np.array([np.log(3000.0), np.log(3.0), np.log(50.0), np.log(1e9)])
    starts = tuple(np.array([np.log(f), np.log(0.15), np.log(m), np.log(kc)])
                   for f in f_st for m, kc in ((1.0, 3e5),))

    def describe(u: np.ndarray) -> dict[str, float]:
        d = {"frequency_hz": float(np.exp(u[0])), "damping_ratio": float(np.exp(u[1])),
             "mass_kg": float(np.exp(u[2])), "contact_stiffness_n_per_m": float(np.exp(u[3]))}
        if u.size > 4:
            d["contact_damping_ratio"] = float(np.exp(u[4]))
        return d

    labels = ("log_f", "log_zeta", "log_m", "log_kc")
    lo_damped, hi_damped = np.append(lo, np.log(1e-3)), np.append(hi, np.log(3.0))
    for bone, point, ref in _contact_points(ctx):
        for axname, dirs in axes.items():
            def build(u: np.ndarray, c: Context, bone: str = bone, ref: np.ndarray = ref,
                      dirs: np.ndarray = dirs) -> EffectTerms:
                gram = c.base.fixed_gram(bone, ref, dirs)
                ws = 2 * np.pi * np.exp(u[0])
                m = np.exp(u[2])
                ks = m * ws**2 + 2j * np.exp(u[1]) * m * ws * c.omega - c.omega**2 * m
                kc = np.exp(u[3])
                if u.size > 4:  # the refined form: the contact damped
                    kc = damped_contact(kc, np.exp(u[4]), m, c.omega)
                keff = kc * ks / (kc + ks)
                return EffectTerms(dZ=keff[:, None, None] * gram[None])

            place = f"{bone}{point} {axname}"
            damped = Candidate("support_resonance", DAMPED_BED_VARIANT, place, "bone",
                               (*labels, "log_zeta_c"), lo_damped, hi_damped, (), build,
                               describe, bone)
            cands.append(Candidate(
                "support_resonance", "bed contact", place, "bone", labels, lo, hi, starts,
                build, describe, bone, refined=(damped, np.log([DAMPED_BED_START]))))
    places = [(j, name) for j, name in enumerate(ctx.in_names)]
    if len(ctx.in_names) > 1:
        places.append((-1, "all inputs"))
    for j, name in places:
        def ebuild(u: np.ndarray, c: Context, j: int = j) -> EffectTerms:
            wr = 2 * np.pi * np.exp(u[0])
            zeta = np.exp(u[1])
            R = 1 + np.exp(u[2]) * c.omega**2 / (wr**2 - c.omega**2 + 2j * zeta * wr * c.omega)
            gain = np.ones((c.omega.size, len(c.in_names)), complex)
            if j < 0:
                gain[:] = R[:, None]
            else:
                gain[:, j] = R
            return EffectTerms(in_gain=gain)

        estarts = tuple(np.array([np.log(f), np.log(0.1), np.log(0.3)]) for f in f_st)
        cands.append(Candidate(
            "support_resonance", "excitation fixture", name, "input" if j >= 0 else "inputs",
            ("log_f", "log_zeta", "log_mu"),
            np.array([np.log(0.5), np.log(0.005), np.log(1e-4)]),
            np.array([np.log(5000.0), np.log(3.0), np.log(20.0)]), estarts, ebuild,
            lambda u: {"frequency_hz": float(np.exp(u[0])), "damping_ratio": float(np.exp(u[1])),
                       "mass_ratio": float(np.exp(u[2]))}))
    cands += _armature_candidates(ctx, suspended=True)
    return cands


ARMATURE_VARIANT = "shaker armature on its suspension"
TISSUE_ALONG_AXIS_VARIANT = "tissue under the shaker, along its axis"
"""The two variants of :func:`_armature_candidates`: the tissue is the armature with no
suspension (its first three parameters; the armature's f_s → 0)."""


def _armature_candidates(ctx: Context, suspended: bool) -> list[Candidate]:
    """A mass between the force and the bone, along the drive axis, only in the setups that
    drive that input: the shaker's moving mass m on its suspension (k_s, 5 % damping) when
    the force is the coil force of the calibrated drive chain (design 2), pushing the bone
    through a contact/stinger (k_t, c_t) — ``support_resonance`` (``suspended``); or a lump
    of tissue under the shaker with no suspension — ``soft_tissue``. Condensing the mass's
    DOF (z_t = k_t + iωc_t, z_s = k_s + iωc_s, D = z_t + z_s − ω²m): the bone point sees
    ``ΔZ_j = z_t (z_s − ω²m)/D · i_j i_jᵀ`` and receives ``T = z_t/D`` of the force, so
    ``H[:, :, j] = O (Z + ΔZ_j)⁻¹ i_j T``. Parameters: f_t = √(k_t/m)/2π, ζ_t, m
    (and f_s = √(k_s/m)/2π)."""
    cands = []
    bones = set(ctx.base.bones)
    n_u = 4 if suspended else 3
    lo = np.log([2.0, 0.003, 1e-3, 0.3][:n_u])
    hi = np.log([5000.0, 2.0, 5.0, 200.0][:n_u])
    starts = tuple(np.log([f, z, 0.1, 10.0][:n_u]) for f in _f_starts(ctx, 6)
                   for z in ((0.05,) if suspended else (0.3,)))
    # the suspension resonance lies in the band and is sharp (5 % damping): the own starts
    # can miss its basin (judge-like set 8787_003: 0.42 kg on 11.8 Hz, contact 101 Hz; of
    # the twelve own starts' fits, at f_s = 10 Hz and m = 0.1 kg, eight ended with f_s at
    # its lower bound, three with m at its lower bound, one at f_s = 52 Hz: held-out gap
    # 1.52-5.27 after a base gap of 1.64; from the best point of this grid, 0.23).
    # Contact frequency over the band, mass 50 g - 0.8 kg, suspension 3-40 Hz (a lab
    # shaker's 5-20 Hz with a margin): 180 points, ~0.2 s with the base frozen
    grid = tuple(np.log([f, 0.05, m, f_s]) for f in _f_starts(ctx, 6)
                 for m in (0.05, 0.2, 0.8) for f_s in np.geomspace(3.0, 40.0, 10)
                 ) if suspended else ()
    labels = ("log_f_contact", "log_zeta_contact", "log_m", "log_f_suspension")[:n_u]

    def describe(u: np.ndarray) -> dict[str, float]:
        d = {"contact_frequency_hz": float(np.exp(u[0])),
             "contact_damping_ratio": float(np.exp(u[1])), "mass_kg": float(np.exp(u[2]))}
        if u.size > 3:
            d["suspension_frequency_hz"] = float(np.exp(u[3]))
        return d

    for j, name in enumerate(ctx.in_names):
        if ctx.in_bones[j] not in bones:
            continue

        def build(u: np.ndarray, c: Context, j: int = j) -> EffectTerms:
            w = c.omega
            m = np.exp(u[2])
            wt = 2 * np.pi * np.exp(u[0])
            zt = m * wt**2 + 2j * np.exp(u[1]) * m * wt * w
            zs = 0.0
            if u.size > 3:
                ws = 2 * np.pi * np.exp(u[3])
                zs = m * ws**2 + 2j * 0.05 * m * ws * w
            D = zt + zs - w**2 * m
            dZs: list[np.ndarray | None] = [None] * len(c.in_names)
            dZs[j] = (zt * (zs - w**2 * m) / D)[:, None, None] * np.outer(
                c.in_rows[j], c.in_rows[j])[None]
            gain = np.ones((w.size, len(c.in_names)), complex)
            gain[:, j] = zt / D
            return EffectTerms(dZ_input=tuple(dZs), in_gain=gain)

        if suspended:
            cands.append(Candidate("support_resonance", ARMATURE_VARIANT,
                                   name, "input", labels, lo, hi, starts, build, describe,
                                   ctx.in_bones[j], screen_grid=grid))
        else:
            cands.append(Candidate("soft_tissue", TISSUE_ALONG_AXIS_VARIANT,
                                   name, "input", labels, lo, hi, starts, build, describe,
                                   ctx.in_bones[j]))
    return cands


def _dashpot_damping_candidates(ctx: Context) -> list[Candidate]:
    """One damping coefficient per dashpot instead of one per joint (design 4.5's groups):
    appendix E has 8 dashpots, a subject need not damp its three sacroiliac dashpots alike.
    Extra non-negative damping Δc_d on each dashpot's own atom, ``ΔC = Σ Δc_d g_d g_dᵀ``
    (with the group coefficient free to go down, any pattern ≥ 0 is reachable). This is
    parameter updating, not an unmodelled effect: when it explains the data the verdict is
    ``none`` (``NULL_EXTENSIONS``). Only for models with a group of several dashpots."""
    base = ctx.base
    is_c = base.kinds == KIND_C
    groups = base.params[is_c]
    if is_c.sum() < 2 or np.unique(groups).size == groups.size:
        return []
    g = base.vectors[is_c] * np.sqrt(base.weights[is_c])[:, None]  # (n_d, n_dof)
    outer = g[:, :, None] * g[:, None, :]
    n_d = g.shape[0]
    names = [base.names[p] for p in groups]
    labels = tuple(f"log_dc_{i}_{names[i]}" for i in range(n_d))

    def build(u: np.ndarray, c: Context) -> EffectTerms:
        dC = np.tensordot(np.exp(u), outer, axes=1)
        return EffectTerms(dZ=(1j * c.omega)[:, None, None] * dC[None])

    def describe(u: np.ndarray) -> dict[str, float]:
        return {f"extra_c_{i}_{names[i]}_n_s_per_m": float(np.exp(x)) for i, x in enumerate(u)}

    starts = tuple(np.full(n_d, np.log(v)) for v in (1.0, 30.0, 300.0))
    return [Candidate(PER_DASHPOT_DAMPING, "one coefficient per dashpot", "all dashpots",
                      "global", labels, np.full(n_d, np.log(1e-3)), np.full(n_d, np.log(1e5)),
                      starts, build, describe)]


def with_extension(cand: Candidate, extension: Candidate) -> Candidate:
    """``cand`` together with a ΔZ-only null extension (one damping per dashpot): the
    effect's parameters, then the extension's; the extension's ΔZ adds to the effect's."""
    n1 = cand.n_params
    # the last build of each part: the Jacobian's forward differences change one
    # parameter at a time, so one part is built again from the same values (a pure
    # function of them; the context is kept with its result, so that a new context at a
    # reused address is never taken for it)
    last: dict[str, tuple[Context, bytes, object]] = {}

    def part(key: str, fn: Callable[[np.ndarray, Context], object], u: np.ndarray,
             c: Context) -> object:
        ub = np.asarray(u, float).tobytes()
        hit = last.get(key)
        if hit is not None and hit[0] is c and hit[1] == ub:
            return hit[2]
        value = fn(u, c)
        last[key] = (c, ub, value)
        return value

    def build(u: np.ndarray, c: Context) -> EffectTerms:
        terms = part("effect", cand.build, u[:n1], c)
        extra = part("extension", lambda v, c_: extension.build(v, c_).dZ, u[n1:], c)
        return replace(terms, dZ=extra if terms.dZ is None else terms.dZ + extra)

    def describe(u: np.ndarray) -> dict[str, float]:
        return {**cand.describe(u[:n1]), **extension.describe(u[n1:])}

    return replace(cand, variant=f"{cand.variant} + {extension.variant}",
                   labels=cand.labels + extension.labels,
                   lower=np.concatenate([cand.lower, extension.lower]),
                   upper=np.concatenate([cand.upper, extension.upper]),
                   starts=tuple(np.concatenate([s, extension.starts[0]]) for s in cand.starts),
                   build=build, describe=describe, null=None,
                   dZ_params=cand.dZ_params + tuple(range(n1, n1 + extension.n_params)))


EFFECT_NAMES = (
    "support_resonance", "frequency_dependent_stiffness", "hysteretic_damping", "soft_tissue",
    "sensor_misorientation", "added_mass", "missing_ligament",
)

PER_DASHPOT_DAMPING = "per_dashpot_damping"
NULL_EXTENSIONS = (PER_DASHPOT_DAMPING,)
"""Candidates that are parameter updating beyond design 4.5's parametrisation, not effects:
fitted and ranked like the effects, but a verdict for one of them is ``none``."""


def calibration_gains(ctx: Context, tol: float) -> Candidate:
    """The measurement chain's calibration as an extension of the model: one real gain per
    output channel within ``1 ± tol`` (displacement calibration: speed of sound in the
    overlying tissue, d = c Δt / 2 of ch. 8; tracking bias from the tissue's speckle mixed
    into the bone echo, docs/simulated-bench.md). Not an effect: the verdict's null
    hypothesis, fitted jointly with the base parameters (a gain common to all outputs is a
    scale the base parameters absorb).
    ``tol`` > 0 (relative)."""
    if not tol > 0:
        raise ValueError(f"calibration tolerance must be > 0, got {tol}")
    names = ctx.out_names

    def build(u: np.ndarray, c: Context) -> EffectTerms:
        return EffectTerms(out_gain=np.broadcast_to(np.exp(u).astype(complex),
                                                    (c.omega.size, len(u))))

    def describe(u: np.ndarray) -> dict[str, float]:
        return {f"gain_{name}": float(np.exp(v)) for name, v in zip(names, u, strict=True)}

    n = len(names)
    return Candidate("calibration", "gain per output", "all outputs", "global",
                     tuple(f"log_gain_{name}" for name in names),
                     np.full(n, np.log1p(-tol)), np.full(n, np.log1p(tol)), (np.zeros(n),),
                     build, describe, null=np.zeros(n))


def candidate_library(ctx: Context, effects: Sequence[str] | None = None) -> list[Candidate]:
    """All candidate extensions at all places for the channels of ``ctx``."""
    cands = (_global_candidates() + _support_candidates(ctx) + _tissue_candidates(ctx)
             + _orientation_candidates(ctx) + _mass_candidates(ctx) + _ligament_candidates(ctx)
             + _dashpot_damping_candidates(ctx))
    if effects is not None:
        unknown = sorted(set(effects) - set(EFFECT_NAMES) - set(NULL_EXTENSIONS))
        if unknown:
            raise ValueError(f"unknown effect(s) {unknown}; known: {list(EFFECT_NAMES)}")
        cands = [c for c in cands if c.effect in effects]
    return cands
