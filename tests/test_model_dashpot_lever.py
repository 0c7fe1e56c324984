"""The two readings of where a dashpot takes its bodies' velocities (``dashpot_lever``).

Thesis eq. 4.16 / fig. 5.6 take the velocity of each attachment point ("points"); the model
core's default evaluates both bodies at the midpoint of the two points ("midpoint"), which
keeps C blind to rigid motion of the whole pelvis. They differ only for a dashpot whose
points are offset off its axis: appendix E's printed S1 pair (0.71 mm off the normal).
"""

import numpy as np
import pytest

from pelvislab.model.assembly import (
    assemble,
    connector_vector,
    connector_vector_derivative,
    point_transform,
)
from pelvislab.model.pelvis import DEFAULT_MODEL_PATH, ModelError, default_model, load_model

APPENDIX_E = default_model()


def _rigid_rotation(model, theta=(0.3, -0.2, 0.5)):
    """q of a small rotation θ of the whole model about the origin (u_b = θ × com_b)."""
    theta = np.asarray(theta)
    return np.concatenate([np.r_[np.cross(theta, b.com_m), theta] for b in model.bodies])


def _on_axis(model):
    """``model`` with every dashpot's point a moved onto the axis through point b."""
    for d in model.dashpots:
        offset = float((d.point_a_m - d.point_b_m) @ d.axis)
        model = model.replace_dashpot(d.name, point_a_m=d.point_b_m + offset * d.axis)
    return model


def test_appendix_e_readings_differ_and_agree_once_s1_is_on_its_normal():
    assert APPENDIX_E.dashpot_lever == "midpoint"
    assert APPENDIX_E.dashpot_lever_matters
    c_mid = assemble(APPENDIX_E).C
    c_pts = assemble(APPENDIX_E.with_dashpot_lever("points")).C
    assert np.abs(c_pts - c_mid).max() > 1e-6 * np.abs(c_mid).max()
    fixed = _on_axis(APPENDIX_E)
    assert not fixed.dashpot_lever_matters
    np.testing.assert_allclose(assemble(fixed.with_dashpot_lever("points")).C,
                               assemble(fixed).C, rtol=0, atol=1e-12 * np.abs(c_mid).max())


def test_points_reading_is_eq_4_16_at_each_attachment_point():
    model = APPENDIX_E.with_dashpot_lever("points")
    for d in model.dashpots:
        g = np.zeros(model.n_dof)
        for body, point, sign in ((d.body_a, d.point_a_m, 1.0), (d.body_b, d.point_b_m, -1.0)):
            b = model.body_index(body)
            g[6 * b:6 * b + 6] += sign * d.axis @ point_transform(point - model.bodies[b].com_m)
        np.testing.assert_allclose(connector_vector(model, d), g, rtol=0, atol=1e-15)
    # springs are read at their own points in both readings (offset along their axis)
    s = model.spring("io_R")
    np.testing.assert_allclose(connector_vector(model, s), connector_vector(APPENDIX_E, s),
                               atol=1e-15)


def test_only_the_midpoint_reading_is_blind_to_rigid_rotation():
    q = _rigid_rotation(APPENDIX_E)
    c_mid = assemble(APPENDIX_E).C
    c_pts = assemble(APPENDIX_E.with_dashpot_lever("points")).C
    assert np.abs(c_mid @ q).max() < 1e-9 * np.abs(c_mid).max()
    # S1's 0.71 mm lever off the normal: the literal reading damps a rigid rotation
    assert np.abs(c_pts @ q).max() > 1e-5 * np.abs(c_pts).max()
    assert np.linalg.matrix_rank(c_pts) == 8


@pytest.mark.parametrize("lever", ["midpoint", "points"])
@pytest.mark.parametrize("end", ["a", "b"])
def test_derivative_in_attachment_coordinates_matches_fd(lever, end):
    """∂g/∂r of dashpot S1 (axis fixed: the joint normal) against central differences."""
    model = APPENDIX_E.with_dashpot_lever(lever)
    d = model.dashpot("S1_R")
    h = 1e-6
    for axis in range(3):
        step = np.eye(3)[axis] * h
        key = f"point_{end}_m"
        p0 = getattr(d, key)
        gp = connector_vector(model, model.replace_dashpot(d.name, **{key: p0 + step})
                              .dashpot(d.name))
        gm = connector_vector(model, model.replace_dashpot(d.name, **{key: p0 - step})
                              .dashpot(d.name))
        fd = (gp - gm) / (2 * h)
        np.testing.assert_allclose(connector_vector_derivative(model, d, end, axis), fd,
                                   rtol=0, atol=1e-8)


def test_lever_in_the_model_file_and_its_errors(tmp_path):
    text = tmp_path / "m.toml"
    source = DEFAULT_MODEL_PATH.read_text(encoding="utf-8")
    text.write_text('dashpot_lever = "points"\n' + source)
    loaded = load_model(text)
    assert loaded.dashpot_lever == "points"
    np.testing.assert_allclose(assemble(loaded).C,
                               assemble(APPENDIX_E.with_dashpot_lever("points")).C)
    assert loaded.mirrored().dashpot_lever == "points"
    text.write_text('dashpot_lever = "centre"\n' + source)
    with pytest.raises(ModelError, match="dashpot_lever must be one of"):
        load_model(text)
