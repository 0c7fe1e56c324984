"""The landmark catalogue (``protocols/landmarks.toml``) as model points.

Each landmark: bone, position (m, design 4.1 frame), default unit direction (bone surface
toward the sensor). An excitation at a landmark pushes into the surface, along minus that
direction (:func:`excitation_points`), as a protocol's default ``excitation_direction``
(``pelvislab.acquisition.protocol``). See the file header for which coordinates the
thesis fixes (none beyond the frame definition) and which are derived estimates.
"""

from __future__ import annotations

import tomllib
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from pelvislab.model.frf import Points

LANDMARKS_SCHEMA = "pelvislab-landmarks"
_KEYS = {"bone", "position_m", "position_mm", "direction", "description", "figures",
         "coordinates", "basis"}


@dataclass(frozen=True, eq=False)
class Landmark:
    """One catalogue point: ``position_m`` (3,), unit ``direction`` (3,)."""

    name: str
    bone: str
    position_m: np.ndarray
    direction: np.ndarray
    description: str = ""
    coordinates: str = "derived"


def _read_text(path: str | Path | None) -> tuple[str, str]:
    if path is None:
        res = resources.files("pelvislab.protocols") / "landmarks.toml"
        return res.read_text(encoding="utf-8"), "protocols/landmarks.toml"
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"landmark catalogue not found: {p}")
    return p.read_text(encoding="utf-8"), str(p)


def load_landmarks(path: str | Path | None = None) -> dict[str, Landmark]:
    """Read the catalogue (default: the shipped one); errors name the landmark."""
    text, where = _read_text(path)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{where}: not valid TOML ({exc})") from None
    table = data.get("landmarks")
    if not isinstance(table, dict):
        raise ValueError(f"{where}: no [landmarks.NAME] tables")
    out: dict[str, Landmark] = {}
    for name, e in table.items():
        what = f"{where}: landmark {name!r}"
        unknown = sorted(set(e) - _KEYS)
        if unknown:
            raise ValueError(f"{what}: unknown key(s) {unknown}")
        if ("position_m" in e) == ("position_mm" in e):
            raise ValueError(f"{what}: give exactly one of position_m, position_mm")
        pos = np.asarray(e.get("position_m", e.get("position_mm")), dtype=float)
        if "position_mm" in e:
            pos = pos * 1e-3
        d = np.asarray(e.get("direction", []), dtype=float)
        if pos.shape != (3,) or d.shape != (3,) or not np.isfinite(pos).all():
            raise ValueError(f"{what}: position and direction must be 3 numbers each")
        norm = float(np.linalg.norm(d))
        if norm == 0 or abs(norm - 1) > 1e-6:
            raise ValueError(f"{what}: direction must be a unit vector (norm {norm:g})")
        if "bone" not in e:
            raise ValueError(f"{what}: missing 'bone'")
        out[name] = Landmark(name, str(e["bone"]), pos, d / norm, str(e.get("description", "")),
                             str(e.get("coordinates", "derived")))
    return out


def landmark_points(names: list[str] | tuple[str, ...],
                    catalogue: dict[str, Landmark] | None = None) -> Points:
    """:class:`~pelvislab.model.frf.Points` for catalogue ``names`` (in that order)."""
    cat = load_landmarks() if catalogue is None else catalogue
    missing = [n for n in names if n not in cat]
    if missing:
        raise ValueError(f"unknown landmark(s) {missing}; catalogue: {sorted(cat)}")
    lm = [cat[n] for n in names]
    return Points(tuple(x.bone for x in lm), np.array([x.position_m for x in lm]).reshape(-1, 3),
                  np.array([x.direction for x in lm]).reshape(-1, 3), tuple(names))


def excitation_points(names: list[str] | tuple[str, ...],
                      catalogue: dict[str, Landmark] | None = None) -> Points:
    """:class:`~pelvislab.model.frf.Points` of unit forces at catalogue ``names``: into the
    surface, along minus each landmark's direction, the default force direction of a
    protocol's setup (design 4.1), so that model FRFs and a session's /frf agree in sign
    for the same (output, input) names."""
    pts = landmark_points(names, catalogue)
    return Points(pts.bone, pts.position_m, 0.0 - pts.direction, pts.name)  # no -0.0
