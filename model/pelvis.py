"""The rigid-body pelvis model: bodies, springs, dashpots, point masses; loading from TOML.

Thesis ch. 4.2 and 5 (three rigid bodies, 12 springs with rest length, 3 + 3 + 2 dashpots
normal to the joint planes) and appendix E (the default parameter values, shipped as
``model/appendix_e.toml``). Frame and units: design 4.1 (SI, +x anterior, +y left,
+z superior, origin between the two anterior superior iliac spines).

The model is an immutable value: every ``with_*`` method returns a new model, so extra
springs, dashpots, grounding springs, point masses or whole bodies can be added
programmatically (sim-to-real gap candidates) without touching the file.

Generalised coordinates (eq. 4.6-4.9): for body ``b`` (index in ``model.bodies``), DOFs
``6 b .. 6 b + 5`` are the centre-of-mass translation ``(ux, uy, uz)`` in m followed by the
small rotation ``(θx, θy, θz)`` in rad. A point ``p`` of the body moves by
``u_b + θ_b × (p − com_b)`` (eq. 4.9).
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

GROUND = "ground"
"""Reserved body name: a spring or dashpot end on ``ground`` is fixed in space."""

DASHPOT_LEVERS = ("midpoint", "points")
"""Readings of where a dashpot takes its bodies' velocities (:attr:`PelvisModel.dashpot_lever`)."""

MODEL_SCHEMA = "pelvislab-model"
MODEL_SCHEMA_VERSION = 1
DEFAULT_MODEL_PATH = Path(__file__).with_name("appendix_e.toml")


class ModelError(ValueError):
    """A model description that is missing or inconsistent; the message names the entry."""


def _vec3(value: object, what: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ModelError(f"{what}: expected 3 numbers, got {value!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ModelError(f"{what}: expected 3 finite numbers, got {value!r}")
    return arr


def _unit(value: object, what: str) -> np.ndarray:
    arr = _vec3(value, what)
    norm = float(np.linalg.norm(arr))
    if norm == 0.0:
        raise ModelError(f"{what}: direction must not be the zero vector")
    return arr / norm


def _nonneg(value: object, what: str) -> float:
    try:
        x = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ModelError(f"{what}: expected a number, got {value!r}") from None
    if not math.isfinite(x) or x < 0:
        raise ModelError(f"{what}: must be finite and >= 0, got {value!r}")
    return x


@dataclass(frozen=True, eq=False)
class Body:
    """A rigid body: mass (kg), centre of mass (m), inertia tensor about the CM (kg m²).

    ``group`` names the mass parameter when left/right symmetry is imposed
    (``m_<group>``, design 4.5); without symmetry the parameter is ``m_<name>``.
    """

    name: str
    mass_kg: float
    com_m: np.ndarray
    inertia_kg_m2: np.ndarray
    group: str = ""

    def __post_init__(self) -> None:
        what = f"body {self.name!r}"
        if not self.name or self.name == GROUND:
            raise ModelError(f"{what}: invalid body name")
        mass = _nonneg(self.mass_kg, f"{what}: mass_kg")
        if mass == 0.0:
            raise ModelError(f"{what}: mass_kg must be > 0")
        object.__setattr__(self, "mass_kg", mass)
        object.__setattr__(self, "com_m", _vec3(self.com_m, f"{what}: centre of mass"))
        inertia = np.asarray(self.inertia_kg_m2, dtype=float)
        if inertia.shape != (3, 3) or not np.all(np.isfinite(inertia)):
            raise ModelError(f"{what}: inertia must be a 3x3 matrix of finite numbers")
        if not np.allclose(inertia, inertia.T, rtol=1e-9, atol=1e-15):
            raise ModelError(f"{what}: inertia tensor is not symmetric")
        if np.linalg.eigvalsh(inertia).min() <= 0:
            raise ModelError(f"{what}: inertia tensor is not positive definite")
        object.__setattr__(self, "inertia_kg_m2", inertia)
        if not self.group:
            object.__setattr__(self, "group", self.name)


@dataclass(frozen=True, eq=False)
class Spring:
    """A linear spring between a point on ``body_a`` and a point on ``body_b`` (eq. 4.12-4.13).

    The points are given in the reference configuration (m); their distance is the rest
    length (no preload), so the linearised spring reacts to the elongation along the unit
    ``axis`` (default: from point a to point b). ``body_b = "ground"`` grounds the spring.
    Parameter name: ``k_<group>_<side>`` (or ``k_<group>`` without a side); with symmetry
    ``k_<group>``.
    """

    name: str
    body_a: str
    point_a_m: np.ndarray
    body_b: str
    point_b_m: np.ndarray
    stiffness_n_per_m: float
    group: str = ""
    side: str = ""
    axis: np.ndarray | None = None

    def __post_init__(self) -> None:
        _init_connector(self, "spring", "stiffness_n_per_m")

    @property
    def rest_length_m(self) -> float:
        """Distance between the two attachment points at rest, L in eq. 4.13."""
        return float(np.linalg.norm(self.point_b_m - self.point_a_m))


@dataclass(frozen=True, eq=False)
class Dashpot:
    """A viscous dashpot reacting to the relative velocity of its two points along ``axis``.

    Thesis ch. 5.4 / fig. 5.6: the axis is the normal of the joint plane (unit vector); the
    force is ``c · n·(v_a − v_b)``. Without an explicit axis the line between the points is
    used. Parameter name: ``c_<group>_<side>`` (or ``c_<group>``); with symmetry ``c_<group>``.
    """

    name: str
    body_a: str
    point_a_m: np.ndarray
    body_b: str
    point_b_m: np.ndarray
    coefficient_n_s_per_m: float
    group: str = ""
    side: str = ""
    axis: np.ndarray | None = None

    def __post_init__(self) -> None:
        _init_connector(self, "dashpot", "coefficient_n_s_per_m")


def _init_connector(obj: Spring | Dashpot, kind: str, coef: str) -> None:
    what = f"{kind} {obj.name!r}"
    if not obj.name:
        raise ModelError(f"{kind} without a name")
    object.__setattr__(obj, coef, _nonneg(getattr(obj, coef), f"{what}: {coef}"))
    a = _vec3(obj.point_a_m, f"{what}: point a")
    b = _vec3(obj.point_b_m, f"{what}: point b")
    object.__setattr__(obj, "point_a_m", a)
    object.__setattr__(obj, "point_b_m", b)
    if obj.body_a == obj.body_b:
        raise ModelError(f"{what}: both ends on body {obj.body_a!r}")
    if obj.body_a == GROUND:
        raise ModelError(f"{what}: put the grounded end as body_b, not body_a")
    if obj.axis is not None:
        axis = _unit(obj.axis, f"{what}: axis")
        d = b - a
        length = float(np.linalg.norm(d))
        # A spring's elongation is along the line of its points (eq. 4.13): an explicit axis
        # is only for coincident points (e.g. grounding) or must agree with that line.
        if kind == "spring" and length > 1e-9 and np.linalg.norm(np.cross(axis, d / length)) > 1e-6:
            raise ModelError(f"{what}: axis is not along the line between the two points")
        object.__setattr__(obj, "axis", axis)
    else:
        d = b - a
        if np.linalg.norm(d) < 1e-9:
            raise ModelError(
                f"{what}: the two points coincide, so the axis is undefined; give 'axis'"
            )
        object.__setattr__(obj, "axis", d / np.linalg.norm(d))
    if not obj.group:
        object.__setattr__(obj, "group", obj.name)
    if obj.side not in ("", "R", "L"):
        raise ModelError(f"{what}: side must be 'R', 'L' or '' (got {obj.side!r})")


@dataclass(frozen=True, eq=False)
class PointMass:
    """A lumped mass (kg) rigidly attached to ``body`` at ``position_m`` (e.g. a sensor)."""

    name: str
    body: str
    position_m: np.ndarray
    mass_kg: float

    def __post_init__(self) -> None:
        what = f"point mass {self.name!r}"
        object.__setattr__(self, "mass_kg", _nonneg(self.mass_kg, f"{what}: mass_kg"))
        object.__setattr__(self, "position_m", _vec3(self.position_m, f"{what}: position"))


@dataclass(frozen=True, eq=False)
class FrequencyDependence:
    """Frequency-dependent stiffness and hysteretic damping of thesis eq. 7.1-7.3.

    ``K' = f_k K / (4 ω_max)`` and ``D = f_c C ω_max / 4`` with ``ω_max = 2π f_max_hz``.
    ``f_k = f_c = 0`` is the constant-matrix model.
    """

    f_k: float = 0.0
    f_c: float = 0.0
    f_max_hz: float = 300.0

    def __post_init__(self) -> None:
        for key in ("f_k", "f_c"):
            value = float(getattr(self, key))
            if not math.isfinite(value):
                raise ModelError(f"frequency_dependence: {key} must be finite")
            object.__setattr__(self, key, value)
        if not (math.isfinite(self.f_max_hz) and self.f_max_hz > 0):
            raise ModelError("frequency_dependence: f_max_hz must be > 0")

    @property
    def active(self) -> bool:
        """True when K' or D is non-zero."""
        return self.f_k != 0.0 or self.f_c != 0.0


@dataclass(frozen=True, eq=False)
class PelvisModel:
    """Bodies, springs, dashpots and point masses of a rigid-body model (validated)."""

    bodies: tuple[Body, ...]
    springs: tuple[Spring, ...] = ()
    dashpots: tuple[Dashpot, ...] = ()
    point_masses: tuple[PointMass, ...] = ()
    frequency_dependence: FrequencyDependence = field(default_factory=FrequencyDependence)
    name: str = "model"
    dashpot_lever: str = "midpoint"
    """Where a dashpot reads its bodies' velocities (thesis ch. 5.4, fig. 5.6):
    ``"midpoint"``, both bodies at the midpoint of the two attachment points (blind to
    rigid motion of the whole model); ``"points"``, each body at its own attachment point
    (eq. 4.16's attachment points, projected on the normal as in fig. 5.6; eq. 4.16 alone
    would take the whole velocity difference). The two agree when the points are offset
    along the axis; appendix E's printed S1 pair is 0.71 mm off the joint normal (see
    :attr:`dashpot_lever_matters`)."""

    def __post_init__(self) -> None:
        if self.dashpot_lever not in DASHPOT_LEVERS:
            raise ModelError(f"model {self.name!r}: dashpot_lever must be one of "
                             f"{DASHPOT_LEVERS}, got {self.dashpot_lever!r}")
        object.__setattr__(self, "bodies", tuple(self.bodies))
        object.__setattr__(self, "springs", tuple(self.springs))
        object.__setattr__(self, "dashpots", tuple(self.dashpots))
        object.__setattr__(self, "point_masses", tuple(self.point_masses))
        if not self.bodies:
            raise ModelError(f"model {self.name!r}: no bodies")
        for kind, items in (
            ("body", self.bodies), ("spring", self.springs),
            ("dashpot", self.dashpots), ("point mass", self.point_masses),
        ):
            seen: set[str] = set()
            for item in items:
                if item.name in seen:
                    raise ModelError(f"model {self.name!r}: duplicate {kind} name {item.name!r}")
                seen.add(item.name)
        names = {b.name for b in self.bodies}
        for kind, items in (("spring", self.springs), ("dashpot", self.dashpots)):
            for c in items:
                for end in (c.body_a, c.body_b):
                    if end != GROUND and end not in names:
                        raise ModelError(
                            f"{kind} {c.name!r}: body {end!r} is not in the model "
                            f"(bodies: {sorted(names)}, or {GROUND!r})"
                        )
        for pm in self.point_masses:
            if pm.body not in names:
                raise ModelError(
                    f"point mass {pm.name!r}: body {pm.body!r} is not in the model "
                    f"(bodies: {sorted(names)})"
                )

    # -- queries -----------------------------------------------------------------------
    @property
    def n_dof(self) -> int:
        """Number of generalised coordinates, 6 per body (18 for the pelvis)."""
        return 6 * len(self.bodies)

    @property
    def body_names(self) -> tuple[str, ...]:
        """Body names in DOF order."""
        return tuple(b.name for b in self.bodies)

    def body_index(self, name: str) -> int:
        """Index of body ``name`` (its DOFs are ``6*i .. 6*i+5``)."""
        for i, b in enumerate(self.bodies):
            if b.name == name:
                return i
        raise KeyError(f"no body named {name!r}; bodies: {list(self.body_names)}")

    def body(self, name: str) -> Body:
        """The body called ``name``."""
        return self.bodies[self.body_index(name)]

    def spring(self, name: str) -> Spring:
        """The spring called ``name``."""
        for s in self.springs:
            if s.name == name:
                return s
        raise KeyError(f"no spring named {name!r}")

    def dashpot(self, name: str) -> Dashpot:
        """The dashpot called ``name``."""
        for d in self.dashpots:
            if d.name == name:
                return d
        raise KeyError(f"no dashpot named {name!r}")

    @property
    def dashpot_lever_matters(self) -> bool:
        """Whether the two dashpot readings (:attr:`dashpot_lever`) give different damping:
        some dashpot between two bodies has its points offset off its axis (> 1 µm)."""
        for d in self.dashpots:
            if d.body_b == GROUND or d.body_a == GROUND:
                continue
            if np.linalg.norm(np.cross(d.point_b_m - d.point_a_m, d.axis)) > 1e-6:
                return True
        return False

    # -- programmatic extension (each returns a new model) --------------------------------
    def with_dashpot_lever(self, lever: str) -> PelvisModel:
        """A copy reading the dashpots with ``lever`` (``"midpoint"`` or ``"points"``)."""
        return replace(self, dashpot_lever=lever)

    def with_body(self, body: Body) -> PelvisModel:
        """A copy with one more rigid body (6 more DOFs, appended at the end)."""
        return replace(self, bodies=(*self.bodies, body))

    def with_spring(self, spring: Spring) -> PelvisModel:
        """A copy with one more spring (``body_b="ground"`` for a grounding spring)."""
        return replace(self, springs=(*self.springs, spring))

    def with_dashpot(self, dashpot: Dashpot) -> PelvisModel:
        """A copy with one more dashpot (``body_b="ground"`` for a grounding dashpot)."""
        return replace(self, dashpots=(*self.dashpots, dashpot))

    def with_point_mass(self, point_mass: PointMass) -> PelvisModel:
        """A copy with a lumped mass rigidly attached to one of the bodies."""
        return replace(self, point_masses=(*self.point_masses, point_mass))

    def with_grounding(
        self, body: str, stiffness_n_per_m: float, point_m: Iterable[float] | None = None,
        axes: Iterable[Iterable[float]] = ((1, 0, 0), (0, 1, 0), (0, 0, 1)),
        coefficient_n_s_per_m: float = 0.0, prefix: str = "ground",
    ) -> PelvisModel:
        """A copy with springs (and dashpots if ``coefficient_n_s_per_m > 0``) from a point
        of ``body`` (default: its centre of mass) to ground, one per axis."""
        b = self.body(body)
        p = b.com_m if point_m is None else _vec3(point_m, f"grounding of {body!r}")
        model = self
        for j, ax in enumerate(axes):
            name = f"{prefix}_{body}_{j}"
            model = model.with_spring(Spring(name, body, p, GROUND, p, stiffness_n_per_m,
                                             group=name, axis=np.asarray(ax, float)))
            if coefficient_n_s_per_m > 0:
                model = model.with_dashpot(Dashpot(name, body, p, GROUND, p,
                                                   coefficient_n_s_per_m, group=name,
                                                   axis=np.asarray(ax, float)))
        return model

    def with_frequency_dependence(
        self, f_k: float = 0.0, f_c: float = 0.0, f_max_hz: float | None = None
    ) -> PelvisModel:
        """A copy with the eq. 7.1-7.3 factors set (``f_max_hz`` kept unless given)."""
        fmax = self.frequency_dependence.f_max_hz if f_max_hz is None else f_max_hz
        return replace(self, frequency_dependence=FrequencyDependence(f_k, f_c, fmax))

    def replace_spring(self, name: str, **changes: Any) -> PelvisModel:
        """A copy with spring ``name`` changed (e.g. ``stiffness_n_per_m=2e6``).

        Moving an attachment point of a spring whose points are distinct re-derives its axis
        from the new points (eq. 4.13) unless ``axis`` is given.
        """
        old = self.spring(name)
        if ({"point_a_m", "point_b_m"} & set(changes) and "axis" not in changes
                and old.rest_length_m > 1e-9):
            changes = {**changes, "axis": None}
        springs = tuple(replace(s, **changes) if s.name == name else s for s in self.springs)
        return replace(self, springs=springs)

    def replace_dashpot(self, name: str, **changes: Any) -> PelvisModel:
        """A copy with dashpot ``name`` changed."""
        self.dashpot(name)
        dashpots = tuple(replace(d, **changes) if d.name == name else d for d in self.dashpots)
        return replace(self, dashpots=dashpots)

    def replace_body(self, name: str, **changes: Any) -> PelvisModel:
        """A copy with body ``name`` changed (mass, inertia, centre of mass)."""
        self.body(name)
        bodies = tuple(replace(b, **changes) if b.name == name else b for b in self.bodies)
        return replace(self, bodies=bodies)

    def with_mass(self, body: str, mass_kg: float) -> PelvisModel:
        """A copy with ``body``'s mass set and its inertia scaled with it (ch. 5.2)."""
        b = self.body(body)
        return self.replace_body(
            body, mass_kg=mass_kg, inertia_kg_m2=b.inertia_kg_m2 * (mass_kg / b.mass_kg)
        )

    def mirrored(self) -> PelvisModel:
        """The model reflected in the sagittal plane (y → −y, right ↔ left names and sides).

        Used to check the left/right symmetry of a model: a symmetric model's mirror
        assembles to the same matrices after the body permutation.
        """
        flip = np.diag([1.0, -1.0, 1.0])

        def swap(text: str) -> str:
            return text.replace("right", "\0").replace("left", "right").replace("\0", "left")

        def swap_name(text: str) -> str:
            if text.endswith("_R"):
                return text[:-2] + "_L"
            if text.endswith("_L"):
                return text[:-2] + "_R"
            return swap(text)

        side = {"R": "L", "L": "R", "": ""}
        bodies = tuple(
            Body(swap(b.name), b.mass_kg, flip @ b.com_m, flip @ b.inertia_kg_m2 @ flip,
                 b.group)
            for b in self.bodies
        )

        def end(body: str) -> str:
            return body if body == GROUND else swap(body)

        springs = tuple(
            Spring(swap_name(s.name), end(s.body_a), flip @ s.point_a_m, end(s.body_b),
                   flip @ s.point_b_m, s.stiffness_n_per_m, s.group, side[s.side],
                   flip @ s.axis)
            for s in self.springs
        )
        dashpots = tuple(
            Dashpot(swap_name(d.name), end(d.body_a), flip @ d.point_a_m, end(d.body_b),
                    flip @ d.point_b_m, d.coefficient_n_s_per_m, d.group, side[d.side],
                    flip @ d.axis)
            for d in self.dashpots
        )
        pms = tuple(PointMass(swap_name(p.name), swap(p.body), flip @ p.position_m, p.mass_kg)
                    for p in self.point_masses)
        return PelvisModel(bodies, springs, dashpots, pms, self.frequency_dependence,
                           self.name + " (mirrored)", self.dashpot_lever)


# ---------------------------------------------------------------------------------------
# TOML loading
# ---------------------------------------------------------------------------------------

_UNITS = {"m": 1.0, "mm": 1e-3}


def _length(entry: Mapping[str, Any], key: str, what: str, required: bool = True) -> Any:
    """Read ``<key>_m`` or ``<key>_mm`` (exactly one), returned in metres."""
    found = [(u, entry[f"{key}_{u}"]) for u in _UNITS if f"{key}_{u}" in entry]
    if len(found) > 1:
        raise ModelError(f"{what}: give either {key}_m or {key}_mm, not both")
    if not found:
        if required:
            raise ModelError(f"{what}: missing {key}_m (or {key}_mm)")
        return None
    unit, value = found[0]
    return _vec3(value, f"{what}: {key}_{unit}") * _UNITS[unit]


def _check_keys(entry: Mapping[str, Any], allowed: set[str], what: str) -> None:
    unknown = sorted(set(entry) - allowed)
    if unknown:
        raise ModelError(f"{what}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


def _require(entry: Mapping[str, Any], key: str, what: str) -> Any:
    if key not in entry:
        raise ModelError(f"{what}: missing {key!r}")
    return entry[key]


def _len_keys(*names: str) -> set[str]:
    return {f"{n}_{u}" for n in names for u in _UNITS}


def parse_model(data: Mapping[str, Any], source: str = "<model>") -> PelvisModel:
    """Build a validated :class:`PelvisModel` from a parsed TOML mapping.

    Layout (see ``model/appendix_e.toml``): ``[[body]]`` (name, group, mass_kg, com_m|com_mm,
    inertia_kg_m2), ``[[spring]]`` (name, group, side, body_a, point_a_m|_mm, body_b,
    point_b_m|_mm, stiffness_n_per_m, optional axis), ``[[dashpot]]`` (same with
    coefficient_n_s_per_m), ``[[point_mass]]`` (name, body, position_m|_mm, mass_kg),
    optional ``[frequency_dependence]`` (f_k, f_c, f_max_hz), optional top-level
    ``dashpot_lever`` ("midpoint", the default, or "points"). Errors name the entry.
    """
    where = f"model file {source}"
    _check_keys(data, {"schema", "schema_version", "name", "description", "body", "spring",
                       "dashpot", "point_mass", "frequency_dependence", "dashpot_lever"},
                where)
    if data.get("schema", MODEL_SCHEMA) != MODEL_SCHEMA:
        raise ModelError(f"{where}: schema is {data.get('schema')!r}, expected {MODEL_SCHEMA!r}")
    version = data.get("schema_version", MODEL_SCHEMA_VERSION)
    if version != MODEL_SCHEMA_VERSION:
        raise ModelError(f"{where}: unsupported schema_version {version!r}")
    bodies = []
    for i, e in enumerate(data.get("body", [])):
        what = f"{where}: body #{i + 1} {e.get('name', '?')!r}"
        _check_keys(e, {"name", "group", "mass_kg", "inertia_kg_m2"} | _len_keys("com"), what)
        try:
            bodies.append(Body(str(_require(e, "name", what)), _require(e, "mass_kg", what),
                               _length(e, "com", what),
                               _require(e, "inertia_kg_m2", what), str(e.get("group", ""))))
        except ModelError as exc:
            raise ModelError(f"{where}: {exc}") from None
    connector_keys = {"name", "group", "side", "body_a", "body_b", "axis"} | _len_keys(
        "point_a", "point_b")
    def connectors(table: str, cls: type, coefficient_key: str) -> list:
        """Springs or dashpots: the same keys but for the coefficient's name."""
        found = []
        for i, e in enumerate(data.get(table, [])):
            what = f"{where}: {table} #{i + 1} {e.get('name', '?')!r}"
            _check_keys(e, connector_keys | {coefficient_key}, what)
            try:
                found.append(cls(
                    str(_require(e, "name", what)), str(_require(e, "body_a", what)),
                    _length(e, "point_a", what), str(_require(e, "body_b", what)),
                    _length(e, "point_b", what), _require(e, coefficient_key, what),
                    str(e.get("group", "")), str(e.get("side", "")), e.get("axis")))
            except ModelError as exc:
                raise ModelError(f"{where}: {exc}") from None
        return found

    springs = connectors("spring", Spring, "stiffness_n_per_m")
    dashpots = connectors("dashpot", Dashpot, "coefficient_n_s_per_m")
    pms = []
    for i, e in enumerate(data.get("point_mass", [])):
        what = f"{where}: point_mass #{i + 1} {e.get('name', '?')!r}"
        _check_keys(e, {"name", "body", "mass_kg"} | _len_keys("position"), what)
        try:
            pms.append(PointMass(str(_require(e, "name", what)), str(_require(e, "body", what)),
                                 _length(e, "position", what), _require(e, "mass_kg", what)))
        except ModelError as exc:
            raise ModelError(f"{where}: {exc}") from None
    fd = data.get("frequency_dependence", {})
    _check_keys(fd, {"f_k", "f_c", "f_max_hz"}, f"{where}: [frequency_dependence]")
    try:
        freq = FrequencyDependence(float(fd.get("f_k", 0.0)), float(fd.get("f_c", 0.0)),
                                   float(fd.get("f_max_hz", 300.0)))
        return PelvisModel(tuple(bodies), tuple(springs), tuple(dashpots), tuple(pms), freq,
                           str(data.get("name", Path(source).stem)),
                           str(data.get("dashpot_lever", "midpoint")))
    except ModelError as exc:
        raise ModelError(f"{where}: {exc}") from None


def load_model(path: str | Path | None = None) -> PelvisModel:
    """Load a model TOML file; ``None`` loads the thesis appendix E default model."""
    p = DEFAULT_MODEL_PATH if path is None else Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"model file not found: {p}")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ModelError(f"model file {p}: not valid TOML ({exc})") from None
    except UnicodeDecodeError:
        raise ModelError(f"model file {p}: not a UTF-8 text file (a model is TOML; "
                         "an HDF5 or other binary file given by mistake?)") from None
    return parse_model(data, str(p))


def default_model() -> PelvisModel:
    """The thesis appendix E model (3 bodies, 12 springs, 8 dashpots)."""
    return load_model(None)
