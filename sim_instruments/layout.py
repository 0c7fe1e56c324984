"""Where the simulated shaker pushes and where the simulated transducers look.

Landmarks come from the product's catalogue (``protocols/landmarks.toml`` through
``pelvislab.acquisition.protocol.load_landmarks``) when it has the name; otherwise from the
fallback table below: the measurement points of thesis fig. 6.8 in the frame of design 4.1
(origin between the anterior superior iliac spines, +x anterior, +y left, +z superior),
placed by reading appendix E's attachment points (the posterior sacroiliac ligaments end
near the posterior superior iliac spines, the long ones on the sacrum near S3-S4).

Default bench layout: the face-down scenario of table 6.4, first excitation: the shaker
under the bed pushes the right SIAS posteriorly (force along -x); transducer 1 looks at the
median sacral crest at S4, transducer 2 at the right SIPS, both from behind (direction -x,
from the bone toward the transducer).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "DEFAULT_CHANNELS",
    "DEFAULT_EXCITATION",
    "FALLBACK_LANDMARKS",
    "Landmark",
    "resolve",
]


@dataclass(frozen=True)
class Landmark:
    """A named point on a bone with its direction (unit; design 4.1 conventions)."""

    name: str
    bone: str
    position_m: tuple[float, float, float]
    direction: tuple[float, float, float]

    def __post_init__(self) -> None:
        d = np.asarray(self.direction, dtype=float)
        n = float(np.linalg.norm(d))
        if d.shape != (3,) or not n > 0:
            raise ValueError(f"landmark {self.name!r}: direction must be a non-zero 3-vector")
        object.__setattr__(self, "direction", tuple(float(x) for x in d / n))
        p = np.asarray(self.position_m, dtype=float)
        if p.shape != (3,) or not np.all(np.isfinite(p)):
            raise ValueError(f"landmark {self.name!r}: position must be 3 finite numbers")
        object.__setattr__(self, "position_m", tuple(float(x) for x in p))


def _mm(name: str, bone: str, x: float, y: float, z: float,
        d: tuple[float, float, float]) -> Landmark:
    return Landmark(name, bone, (x * 1e-3, y * 1e-3, z * 1e-3), d)


FALLBACK_LANDMARKS: dict[str, Landmark] = {
    lm.name: lm
    for lm in (
        # fig. 6.8 point 1: median sacral crest at S4, measured/excited along x
        _mm("sacrum_x", "sacrum", -150.0, 0.0, -55.0, (-1.0, 0.0, 0.0)),
        # points 2-3: anterior superior iliac spines, along x (the frame's origin is between them)
        _mm("SIAS_R_x", "innominate_right", 0.0, -115.0, 0.0, (1.0, 0.0, 0.0)),
        _mm("SIAS_L_x", "innominate_left", 0.0, 115.0, 0.0, (1.0, 0.0, 0.0)),
        # points 4-5: externally below the SIAS, along y (outward)
        _mm("SIAS_R_y", "innominate_right", -10.0, -115.0, -25.0, (0.0, -1.0, 0.0)),
        _mm("SIAS_L_y", "innominate_left", -10.0, 115.0, -25.0, (0.0, 1.0, 0.0)),
        # points 6-7: posterior superior iliac spines, along x
        _mm("SIPS_R_x", "innominate_right", -135.0, -40.0, 5.0, (-1.0, 0.0, 0.0)),
        _mm("SIPS_L_x", "innominate_left", -135.0, 40.0, 5.0, (-1.0, 0.0, 0.0)),
    )
}

DEFAULT_EXCITATION = "SIAS_R_x"
"""Face-down scenario (table 6.4): the shaker pushes the right SIAS from below."""
DEFAULT_EXCITATION_DIRECTION = (-1.0, 0.0, 0.0)
"""Force direction of the default excitation: posterior (the subject lies face down), i.e.
minus the landmark's outward direction, the default for any excitation."""
DEFAULT_CHANNELS: dict[int, str] = {1: "sacrum_x", 2: "SIPS_R_x"}
"""Digitizer channel -> landmark of the default layout (both seen from behind)."""


def _catalogue() -> Mapping[str, Any]:
    try:
        from pelvislab.acquisition.protocol import load_landmarks
    except ImportError:  # pragma: no cover - the runner's module is part of the product
        return {}
    try:
        return load_landmarks()
    except Exception:  # a broken catalogue must not stop the simulated bench
        return {}


def resolve(point: str | Landmark | Any, catalogue: Mapping[str, Any] | None = None) -> Landmark:
    """A :class:`Landmark` from a name (catalogue first, then the fallback table) or any
    object with ``bone``, ``position_m``, ``direction`` (and optionally ``name``)."""
    if isinstance(point, Landmark):
        return point
    if isinstance(point, str):
        cat = _catalogue() if catalogue is None else catalogue
        found = cat.get(point)
        if found is None:
            found = FALLBACK_LANDMARKS.get(point)
        if found is None:
            known = sorted(set(cat) | set(FALLBACK_LANDMARKS))
            raise KeyError(f"unknown landmark {point!r} (known: {known})")
        if isinstance(found, Landmark):
            return found
        return Landmark(point, str(found.bone), tuple(found.position_m), tuple(found.direction))
    name = str(getattr(point, "name", "point"))
    return Landmark(name, str(point.bone), tuple(point.position_m), tuple(point.direction))
