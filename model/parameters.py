"""Named parameter vector of the pelvis model, its bounds, log scaling and derivatives.

Names follow design 4.5 / appendix E: masses ``m_innominate_right``, ``m_innominate_left``,
``m_sacrum``; springs ``k_<group>_R`` / ``k_<group>_L`` (``io, asa, asd, pss, psl``) and
``k_pubh``, ``k_pubs``; dashpot groups ``c_sij_R``, ``c_sij_L``, ``c_pub``. With left/right
symmetry imposed the side suffix is dropped (``k_io``, ``c_sij``, ``m_innominate``): 7 to 12
stiffness parameters (ch. 5.3). Optionally the eq. 7.1-7.3 factors ``f_k`` and ``f_c``
(updating version B, ch. 7).

A mass parameter scales its body's inertia tensor with it (ch. 5.2: geometry fixed, mass
free). Every physical parameter enters M, K or C linearly, so ∂M/∂p, ∂K/∂p, ∂C/∂p are exact
constants: ``M(p) = M₀ + Σ p_j ∂M/∂p_j`` (same for K, C).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from pelvislab.model.assembly import (
    SystemMatrices,
    assemble,
    connector_vector,
    connector_vector_derivative,
)
from pelvislab.model.frf import (
    KIND_C,
    KIND_D,
    KIND_K,
    KIND_KPRIME,
    KIND_M,
    DerivativeAtoms,
    PointsLike,
    receptance_and_jacobian,
    rows_for,
)
from pelvislab.model.pelvis import PelvisModel

KINDS = ("mass", "stiffness", "damping", "f_k", "f_c", "coordinate")
LINEAR_KINDS = ("mass", "stiffness", "damping")
_END_KEY = {"a": "point_a_m", "b": "point_b_m"}


@dataclass(frozen=True)
class Parameter:
    """One identifiable parameter: ``kind`` in KINDS, ``members`` the bodies / springs /
    dashpots it sets (all to the same value), SI ``unit``, default bounds, log scaling."""

    name: str
    kind: str
    members: tuple[str, ...]
    unit: str
    lower: float
    upper: float
    log: bool = True
    # kind "coordinate": spring end ("a"/"b"), model axis (0, 1, 2) and, per member, the
    # sign relating the member's coordinate to the value (−1 for y on a mirrored left side)
    end: str = ""
    axis: int = -1
    signs: tuple[float, ...] = ()


def _param_name(prefix: str, group: str, side: str, symmetric: bool) -> str:
    return f"{prefix}_{group}" if symmetric or not side else f"{prefix}_{group}_{side}"


class ParameterSpace:
    """An ordered set of named parameters on a base model.

    Build it with :func:`parameter_space`. ``values()`` reads the base model,
    ``apply(values)`` returns the model with those values, ``matrices(values)`` returns the
    same M, K, C as ``assemble(apply(values))`` but by a tensor product (fast).
    """

    def __init__(self, model: PelvisModel, parameters: Sequence[Parameter]) -> None:
        self.parameters: tuple[Parameter, ...] = tuple(parameters)
        names = [p.name for p in self.parameters]
        if len(set(names)) != len(names):
            raise ValueError(f"duplicate parameter names: {names}")
        self.names: tuple[str, ...] = tuple(names)
        self._index = {n: j for j, n in enumerate(names)}
        # Equalise group members so that the base model is a point of the space.
        self.model = self.apply_to(model, self._read(model))
        self.n_dof = self.model.n_dof
        self._has_coordinates = any(p.kind == "coordinate" for p in self.parameters)
        self._dM, self._dK, self._dC = self._dense_derivatives(self.model)
        s = assemble(self.model)
        p0 = self.values()
        lin = self._linear_values(p0)
        self._M0 = s.M - np.tensordot(lin, self._dM, axes=1)
        self._K0 = s.K - np.tensordot(lin, self._dK, axes=1)
        self._C0 = s.C - np.tensordot(lin, self._dC, axes=1)
        self._atoms_static = self._static_atoms(self.model)

    # -- basic API ---------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.parameters)

    def index(self, name: str) -> int:
        """Position of parameter ``name``."""
        try:
            return self._index[name]
        except KeyError:
            raise KeyError(f"no parameter {name!r}; have {list(self.names)}") from None

    def _read(self, model: PelvisModel) -> np.ndarray:
        out = np.empty(len(self.parameters))
        fd = model.frequency_dependence
        for j, p in enumerate(self.parameters):
            if p.kind == "mass":
                vals = [model.body(m).mass_kg for m in p.members]
            elif p.kind == "stiffness":
                vals = [model.spring(m).stiffness_n_per_m for m in p.members]
            elif p.kind == "damping":
                vals = [model.dashpot(m).coefficient_n_s_per_m for m in p.members]
            elif p.kind == "coordinate":
                vals = [sg * getattr(model.spring(m), _END_KEY[p.end])[p.axis]
                        for m, sg in zip(p.members, p.signs, strict=True)]
            else:
                vals = [fd.f_k if p.kind == "f_k" else fd.f_c]
            out[j] = float(np.mean(vals))
        return out

    def _linear_values(self, values: np.ndarray) -> np.ndarray:
        """Values with non-linear (coordinate) entries zeroed, for the linear decomposition."""
        v = np.asarray(values, dtype=float)
        return np.where([p.kind in LINEAR_KINDS for p in self.parameters], v, 0.0)

    def values(self) -> np.ndarray:
        """Parameter values of the base model (group members equalised to their mean)."""
        return self._read(self.model)

    def as_dict(self, values: np.ndarray | None = None) -> dict[str, float]:
        """``{name: value}`` for ``values`` (default: the base model's)."""
        v = self.values() if values is None else np.asarray(values, dtype=float)
        return {n: float(x) for n, x in zip(self.names, v, strict=True)}

    def from_dict(self, mapping: dict[str, float]) -> np.ndarray:
        """A value vector from a (possibly partial) ``{name: value}``; others from the base."""
        v = self.values()
        for name, x in mapping.items():
            v[self.index(name)] = float(x)
        return v

    def apply_to(self, model: PelvisModel, values: Iterable[float]) -> PelvisModel:
        """``model`` with every parameter's members set to its value (masses scale inertia)."""
        vals = np.asarray(list(values), dtype=float)
        if vals.shape != (len(self.parameters),):
            raise ValueError(f"expected {len(self.parameters)} values, got {vals.shape}")
        fd = model.frequency_dependence
        f_k, f_c = fd.f_k, fd.f_c
        for p, x in zip(self.parameters, vals, strict=True):
            if p.kind == "mass":
                for m in p.members:
                    model = model.with_mass(m, x)
            elif p.kind == "stiffness":
                for m in p.members:
                    model = model.replace_spring(m, stiffness_n_per_m=x)
            elif p.kind == "damping":
                for m in p.members:
                    model = model.replace_dashpot(m, coefficient_n_s_per_m=x)
            elif p.kind == "coordinate":
                key = _END_KEY[p.end]
                for m, sg in zip(p.members, p.signs, strict=True):
                    point = getattr(model.spring(m), key).copy()
                    point[p.axis] = sg * x
                    model = model.replace_spring(m, **{key: point})
            elif p.kind == "f_k":
                f_k = x
            else:
                f_c = x
        if (f_k, f_c) != (fd.f_k, fd.f_c):
            model = model.with_frequency_dependence(f_k, f_c)
        return model

    def apply(self, values: Iterable[float]) -> PelvisModel:
        """The base model with ``values`` applied."""
        return self.apply_to(self.model, values)

    # -- bounds and scaling -------------------------------------------------------------
    @property
    def lower(self) -> np.ndarray:
        """Default lower bounds (SI)."""
        return np.array([p.lower for p in self.parameters])

    @property
    def upper(self) -> np.ndarray:
        """Default upper bounds (SI)."""
        return np.array([p.upper for p in self.parameters])

    @property
    def log_mask(self) -> np.ndarray:
        """True where the parameter is log-scaled (all physical ones; not f_k, f_c)."""
        return np.array([p.log for p in self.parameters], dtype=bool)

    def to_scaled(self, values: np.ndarray) -> np.ndarray:
        """x = ln(p) for log-scaled parameters, x = p otherwise."""
        v = np.asarray(values, dtype=float)
        if np.any(v[self.log_mask] <= 0):
            raise ValueError("log-scaled parameters must be > 0")
        return np.where(self.log_mask, np.log(np.where(self.log_mask, v, 1.0)), v)

    def from_scaled(self, x: np.ndarray) -> np.ndarray:
        """Inverse of :meth:`to_scaled`."""
        x = np.asarray(x, dtype=float)
        return np.where(self.log_mask, np.exp(np.where(self.log_mask, x, 0.0)), x)

    def scaled_chain(self, values: np.ndarray) -> np.ndarray:
        """dp/dx per parameter: p for log-scaled, 1 otherwise (multiply ∂/∂p by it)."""
        v = np.asarray(values, dtype=float)
        return np.where(self.log_mask, v, 1.0)

    # -- matrices and derivatives -------------------------------------------------------
    def _dense_derivatives(self, model: PelvisModel
                           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        n, n_p = self.n_dof, len(self.parameters)
        dM, dK, dC = (np.zeros((n_p, n, n)) for _ in range(3))
        for j, p in enumerate(self.parameters):
            if p.kind == "coordinate":
                for m, sg in zip(p.members, p.signs, strict=True):
                    sp = model.spring(m)
                    g = connector_vector(model, sp)
                    dg = sg * connector_vector_derivative(model, sp, p.end, p.axis)
                    dK[j] += sp.stiffness_n_per_m * (np.outer(dg, g) + np.outer(g, dg))
                continue
            for m in p.members:
                if p.kind == "mass":
                    b = model.body_index(m)
                    body = model.bodies[b]
                    blk = np.zeros((6, 6))
                    blk[:3, :3] = np.eye(3)
                    blk[3:, 3:] = body.inertia_kg_m2 / body.mass_kg
                    dM[j, 6 * b:6 * b + 6, 6 * b:6 * b + 6] += blk
                elif p.kind == "stiffness":
                    g = connector_vector(model, model.spring(m))
                    dK[j] += np.outer(g, g)
                elif p.kind == "damping":
                    g = connector_vector(model, model.dashpot(m))
                    dC[j] += np.outer(g, g)
        return dM, dK, dC

    def derivatives(self, values: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """∂M/∂p, ∂K/∂p, ∂C/∂p, each (n_p, n_dof, n_dof), exact.

        Constant for masses, stiffness and damping coefficients; attachment coordinates
        enter K non-linearly, so with coordinate parameters the derivatives are taken at
        ``values`` (default: the base model). Zero for ``f_k`` / ``f_c`` (they act through
        Z(ω), see :meth:`atoms`).
        """
        if values is None or not self._has_coordinates:
            return self._dM.copy(), self._dK.copy(), self._dC.copy()
        return self._dense_derivatives(self.apply(values))

    def matrices(self, values: np.ndarray) -> SystemMatrices:
        """M, K, C (and f_k, f_c) at ``values`` = ``assemble(self.apply(values))``, fast."""
        v = np.asarray(values, dtype=float)
        if self._has_coordinates:  # K is not linear in attachment coordinates
            return assemble(self.apply(v))
        fd = self.model.frequency_dependence
        f_k, f_c = fd.f_k, fd.f_c
        for j, p in enumerate(self.parameters):
            if p.kind == "f_k":
                f_k = v[j]
            elif p.kind == "f_c":
                f_c = v[j]
        return SystemMatrices(self._M0 + np.tensordot(v, self._dM, axes=1),
                              self._K0 + np.tensordot(v, self._dK, axes=1),
                              self._C0 + np.tensordot(v, self._dC, axes=1),
                              float(f_k), float(f_c), fd.f_max_hz)

    def _static_atoms(self, model: PelvisModel) -> tuple[list, list, list, list]:
        vecs, weights, kinds, params = [], [], [], []
        for j, p in enumerate(self.parameters):
            if p.kind == "coordinate":
                # ∂K/∂r = k (dg gᵀ + g dgᵀ) = k/2 [(g+dg)(g+dg)ᵀ − (g−dg)(g−dg)ᵀ]
                for m, sg in zip(p.members, p.signs, strict=True):
                    sp = model.spring(m)
                    g = connector_vector(model, sp)
                    dg = sg * connector_vector_derivative(model, sp, p.end, p.axis)
                    for vec, w in ((g + dg, 0.5), (g - dg, -0.5)):
                        vecs.append(vec)
                        weights.append(w * sp.stiffness_n_per_m)
                        kinds.append(KIND_K)
                        params.append(j)
                continue
            for m in p.members:
                if p.kind == "mass":
                    b = model.body_index(m)
                    body = model.bodies[b]
                    lam, v = np.linalg.eigh(body.inertia_kg_m2 / body.mass_kg)
                    for k in range(3):
                        e = np.zeros(self.n_dof)
                        e[6 * b + k] = 1.0
                        vecs.append(e)
                        weights.append(1.0)
                        kinds.append(KIND_M)
                        params.append(j)
                    for k in range(3):
                        e = np.zeros(self.n_dof)
                        e[6 * b + 3:6 * b + 6] = v[:, k]
                        vecs.append(e)
                        weights.append(lam[k])
                        kinds.append(KIND_M)
                        params.append(j)
                elif p.kind in ("stiffness", "damping"):
                    el = model.spring(m) if p.kind == "stiffness" else model.dashpot(m)
                    vecs.append(connector_vector(model, el))
                    weights.append(1.0)
                    kinds.append(KIND_K if p.kind == "stiffness" else KIND_C)
                    params.append(j)
        return vecs, weights, kinds, params

    def atoms(self, values: np.ndarray) -> DerivativeAtoms:
        """Rank-1 atoms of ∂Z/∂p at ``values`` (f_k / f_c atoms depend on K, C values)."""
        v = np.asarray(values, dtype=float)
        if self._has_coordinates:
            model = self.apply(v)
            vecs, weights, kinds, params = self._static_atoms(model)
        else:
            model = None
            vecs, weights, kinds, params = (list(x) for x in self._atoms_static)
        fk_j = [j for j, p in enumerate(self.parameters) if p.kind in ("f_k", "f_c")]
        if fk_j:
            model = self.apply(v) if model is None else model
            for j in fk_j:
                kind = self.parameters[j].kind
                elements = model.springs if kind == "f_k" else model.dashpots
                for el in elements:
                    coef = el.stiffness_n_per_m if kind == "f_k" else el.coefficient_n_s_per_m
                    vecs.append(connector_vector(model, el))
                    weights.append(coef)
                    kinds.append(KIND_KPRIME if kind == "f_k" else KIND_D)
                    params.append(j)
        return DerivativeAtoms(np.array(vecs).reshape(-1, self.n_dof),
                               np.array(weights, dtype=float), np.array(kinds, dtype=int),
                               np.array(params, dtype=int), len(self.parameters))

    def frf_and_jacobian(self, values: np.ndarray, frequency_hz: np.ndarray,
                         outputs: PointsLike | np.ndarray, inputs: PointsLike | np.ndarray,
                         scaled: bool = False) -> tuple[np.ndarray, np.ndarray]:
        """H (n_f, n_out, n_in) and ∂H/∂p (n_f, n_out, n_in, n_p) at ``values``.

        ``outputs`` / ``inputs`` are points (bone, position_m, direction) or precomputed
        rows from :func:`pelvislab.model.frf.rows_for` (faster in a loop). With
        ``scaled=True`` the derivative is with respect to :meth:`to_scaled` coordinates
        (∂H/∂ln p for log-scaled parameters).
        """
        v = np.asarray(values, dtype=float)
        o = outputs if isinstance(outputs, np.ndarray) else rows_for(self.model, outputs)
        i = inputs if isinstance(inputs, np.ndarray) else rows_for(self.model, inputs)
        s = self.matrices(v)
        H, dH = receptance_and_jacobian(s.M, s.K, s.C, frequency_hz, o, i, self.atoms(v),
                                        s.f_k, s.f_c, s.f_max_hz)
        if scaled:
            dH = dH * self.scaled_chain(v)
        return H, dH


def parameter_space(model: PelvisModel, symmetric: bool = True, masses: bool = True,
                    stiffness: bool = True, damping: bool = True,
                    frequency_dependence: bool = False, only: Iterable[str] | None = None,
                    bound_factor: float = 100.0, coordinates: Iterable[str] = (),
                    coordinate_range_m: float = 0.01) -> ParameterSpace:
    """The named parameters of ``model`` (design 4.5).

    ``symmetric=True`` ties left and right (``k_io``, ``c_sij``, ``m_innominate``); False
    gives independent sides (``k_io_R``, ``k_io_L``, ...). ``frequency_dependence`` adds
    ``f_k`` and ``f_c`` (eq. 7.1-7.3, bounds [0, 1], linear scaling). ``only`` keeps the
    named parameters only (in the listed order). Default bounds: value / ``bound_factor`` to
    value × ``bound_factor`` (a zero value gets [0, 1] in SI and linear scaling).

    ``coordinates``: spring names or groups whose attachment points become parameters
    (ch. 14 updated all spring positions except the pubic ones): ``r_<group>[_<side>]_<a|b>_
    <x|y|z>`` in m (symmetric: ``r_<group>_<a|b>_<x|y|z>``, the left point mirroring the
    right one in y), linear scaling, bounds nominal ± ``coordinate_range_m``.
    """
    groups: dict[str, tuple[str, str, list[str], str]] = {}

    def add(name: str, kind: str, member: str, unit: str) -> None:
        if name in groups:
            if groups[name][1] != kind:
                raise ValueError(f"parameter {name!r} would mix a {groups[name][1]} and a {kind}")
            groups[name][2].append(member)
        else:
            groups[name] = (name, kind, [member], unit)

    if masses:
        for b in model.bodies:
            add(f"m_{b.group}" if symmetric else f"m_{b.name}", "mass", b.name, "kg")
    if stiffness:
        for s in model.springs:
            add(_param_name("k", s.group, s.side, symmetric), "stiffness", s.name, "N/m")
    if damping:
        for d in model.dashpots:
            add(_param_name("c", d.group, d.side, symmetric), "damping", d.name, "N s/m")
    params = []
    for name, kind, members, unit in groups.values():
        if kind == "mass":
            value = float(np.mean([model.body(m).mass_kg for m in members]))
        elif kind == "stiffness":
            value = float(np.mean([model.spring(m).stiffness_n_per_m for m in members]))
        else:
            value = float(np.mean([model.dashpot(m).coefficient_n_s_per_m for m in members]))
        if value > 0:
            params.append(Parameter(name, kind, tuple(members), unit,
                                    value / bound_factor, value * bound_factor, True))
        else:
            params.append(Parameter(name, kind, tuple(members), unit, 0.0, 1.0, False))
    wanted_coords = list(coordinates)
    if wanted_coords:
        known = {sp.name for sp in model.springs} | {sp.group for sp in model.springs}
        unknown = [c for c in wanted_coords if c not in known]
        if unknown:
            raise KeyError(f"coordinates: unknown spring(s) or group(s) {unknown}")
        coord_groups: dict[str, list[str]] = {}
        for sp in model.springs:
            if sp.name in wanted_coords or sp.group in wanted_coords:
                base = _param_name("r", sp.group, sp.side, symmetric)
                coord_groups.setdefault(base, []).append(sp.name)
        for base, members in coord_groups.items():
            for end in ("a", "b"):
                for axis, label in enumerate("xyz"):
                    signs = tuple(-1.0 if (axis == 1 and model.spring(m).side == "L"
                                           and symmetric and len(members) > 1) else 1.0
                                  for m in members)
                    value = float(np.mean([sg * getattr(model.spring(m), _END_KEY[end])[axis]
                                           for m, sg in zip(members, signs, strict=True)]))
                    params.append(Parameter(f"{base}_{end}_{label}", "coordinate",
                                            tuple(members), "m", value - coordinate_range_m,
                                            value + coordinate_range_m, False, end, axis,
                                            signs))
    if frequency_dependence:
        params.append(Parameter("f_k", "f_k", (), "1", 0.0, 1.0, False))
        params.append(Parameter("f_c", "f_c", (), "1", 0.0, 1.0, False))
    if only is not None:
        by_name = {p.name: p for p in params}
        wanted = list(only)
        missing = [n for n in wanted if n not in by_name]
        if missing:
            raise KeyError(f"unknown parameter(s) {missing}; have {list(by_name)}")
        params = [by_name[n] for n in wanted]
    return ParameterSpace(model, params)
