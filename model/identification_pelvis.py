"""The pelvis model as an identification problem (design 4.5 parameter names).

Thin adapter from the model core (``pelvislab.model.parameters.parameter_space``,
``pelvislab.model.frf.rows_for``; see docs/model-api.md) to
:class:`pelvislab.model.identification.FrfProblem`:

* parameters (design 4.5): ``m_<body>`` (scales mass *and* inertia, ch. 5.2),
  ``k_<group>[_<side>]``, ``c_<group>[_<side>]``; ``symmetric=True`` drops the side suffix;
* M, K, C are linear in these parameters, so the model core's derivative matrices are exact
  constants, fetched once;
* observation / excitation rows come from the model's point kinematics (eq. 4.9 / 6.2);
* the thesis' measurement layouts (tables 6.3 / 6.4, fig. 7.1) by landmark name.
"""

from __future__ import annotations

import numpy as np

from pelvislab.acquisition.frfset import Channels
from pelvislab.model.frf import rows_for
from pelvislab.model.identification import FrfProblem, SystemMatrices
from pelvislab.model.landmarks import excitation_points, landmark_points
from pelvislab.model.parameters import ParameterSpace, parameter_space
from pelvislab.model.pelvis import PelvisModel

#: Table 6.3 (face-up): excitation -> pick-ups (landmark names of protocols/landmarks.toml).
FACE_UP = {
    "sacrum_x": ("sacrum_x", "SIAS_R_x", "SIAS_L_x", "SIAS_R_y", "SIAS_L_y"),
    "SIPS_R_x": ("SIPS_R_x", "SIAS_R_x", "SIAS_L_x", "SIAS_R_y", "SIAS_L_y"),
    "SIPS_L_x": ("SIPS_L_x", "SIAS_R_x", "SIAS_L_x", "SIAS_R_y", "SIAS_L_y"),
}
#: Table 6.4 (face-down).
FACE_DOWN = {
    "SIAS_R_x": ("SIAS_R_x", "sacrum_x", "SIPS_R_x", "SIPS_L_x"),
    "SIAS_L_x": ("SIAS_L_x", "sacrum_x", "SIPS_R_x", "SIPS_L_x"),
}
#: Ch. 6.2 "full complement": the 7 points of fig. 6.8, all 28 non-reciprocal pairs.
_FIG_6_8 = ("sacrum_x", "SIAS_R_x", "SIAS_L_x", "SIAS_R_y", "SIAS_L_y", "SIPS_R_x", "SIPS_L_x")
FULL = {e: _FIG_6_8[i:] for i, e in enumerate(_FIG_6_8)}
#: Fig. 7.1: nine points (three per bone) plus the drive point on the left iliac fossa.
CH7 = {"iliac_fossa_drive_L": (
    "iliac_fossa_drive_L", "SIAS_R_x", "SIPS_R_x", "iliac_crest_R_z", "SIAS_L_x", "SIPS_L_x",
    "iliac_crest_L_z", "sacrum_x", "sacrum_S1_x", "sacrum_S3_x")}
LAYOUTS = {"face_up": FACE_UP, "face_down": FACE_DOWN, "full": FULL, "ch7": CH7}


def layout_channels(layout: dict[str, tuple[str, ...]]) -> tuple[Channels, Channels, np.ndarray]:
    """Output and input channels of a layout and the (n_out, n_in) mask of measured pairs.

    Outputs look along the landmark direction; inputs push into the surface (minus it), as
    a protocol's default excitation, so FRFs of these channels have a session's signs."""
    inputs = list(layout)
    outputs: list[str] = []
    for picks in layout.values():
        outputs += [p for p in picks if p not in outputs]
    mask = np.zeros((len(outputs), len(inputs)), bool)
    for j, e in enumerate(inputs):
        for p in layout[e]:
            mask[outputs.index(p), j] = True

    def channels(names: list[str], points=landmark_points) -> Channels:  # noqa: ANN001
        pts = points(names)
        return Channels(names, list(pts.bone), pts.position_m, pts.direction)

    return channels(outputs), channels(inputs, excitation_points), mask


def pelvis_problem(
    model: PelvisModel, outputs: Channels, inputs: Channels, *, symmetric: bool = False,
    f_max_hz: float | None = None,
) -> tuple[FrfProblem, ParameterSpace]:
    """FrfProblem for ``model`` observed at ``outputs`` and excited at ``inputs``.

    Inputs are unit forces along each input channel's direction. ``f_max_hz`` sets w_max
    of eq. 7.2-7.3 (default: the model's frequency-dependence f_max_hz).
    """
    space = parameter_space(model, symmetric=symmetric)
    dM, dK, dC = space.derivatives()

    def assemble(values: np.ndarray) -> SystemMatrices:
        m = space.matrices(values)
        return SystemMatrices(m.M, m.C, m.K, dM, dC, dK)

    out_rows = rows_for(model, outputs)
    in_rows = rows_for(model, inputs)
    for rows, ch in ((out_rows, outputs), (in_rows, inputs)):
        bad = ~np.all(np.isfinite(rows), axis=1)
        if bad.any():
            names = [ch.name[i] for i in np.flatnonzero(bad)] if hasattr(ch, "name") else []
            raise ValueError(f"channel(s) {names} are on no modelled bone; cannot use them")
    f_max = model.frequency_dependence.f_max_hz if f_max_hz is None else f_max_hz
    problem = FrfProblem(
        names=space.names, nominal=space.values(), assemble=assemble,
        outputs=out_rows, inputs=in_rows.T, omega_max_rad_s=2 * np.pi * float(f_max),
    )
    return problem, space
