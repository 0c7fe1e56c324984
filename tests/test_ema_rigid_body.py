"""Rigid-body filtering (eq. 11.1-11.7) and the per-channel sensor check, on the pelvis model."""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.assembly import point_rows
from pelvislab.model.frf import Points, frf
from pelvislab.model.landmarks import load_landmarks
from pelvislab.model.modal import model_modes
from pelvislab.model.pelvis import load_model
from pelvislab.model.rigid_body import (
    check_channels,
    filter_bones,
    filter_global,
    rigid_body_matrix,
)

LANDMARKS = ["SIAS_R_x", "SIPS_R_x", "iliac_crest_R_z", "iliac_fossa_R", "ch11_4_ischial_spine_R",
             "SIAS_L_x", "SIPS_L_x", "iliac_crest_L_z", "iliac_fossa_L", "ch11_12_ischial_spine_L",
             "sacrum_x", "sacrum_S1_x", "sacrum_S3_x"]


def triaxial_geometry() -> tuple[list[str], np.ndarray, np.ndarray]:
    """The thesis' ch. 11 layout: 13 points measured in x, y and z (39 channels)."""
    cat = load_landmarks()
    bones, pos, dirs = [], [], []
    for name in LANDMARKS:
        for axis in np.eye(3):
            bones.append(cat[name].bone)
            pos.append(cat[name].position_m)
            dirs.append(axis)
    return bones, np.array(pos), np.array(dirs)


@pytest.fixture(scope="module")
def pelvis():
    model = load_model()
    modes = model_modes(model)
    bones, pos, dirs = triaxial_geometry()
    shapes = point_rows(model, bones, pos, dirs) @ modes.shapes
    return model, modes, bones, pos, dirs, shapes


def test_matrix_rows_reproduce_rigid_motion():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(5, 3))
    d = rng.normal(size=(5, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t, theta = rng.normal(size=3), rng.normal(size=3) * 0.1
    o = p.mean(axis=0)
    u = t + np.cross(theta, p - o)
    np.testing.assert_allclose(rigid_body_matrix(p, d) @ np.r_[t, theta], np.sum(u * d, axis=1))


def test_model_modes_are_bone_rigid_and_rigid_modes_globally_rigid(pelvis):
    model, modes, bones, pos, dirs, shapes = pelvis
    g = filter_global(shapes, pos, dirs)
    assert g.rank == 6
    # a 3-rigid-body model: every bone moves rigidly in every mode (eq. 11.7 ratio = 1)
    b = filter_bones(g.x_el, bones, pos, dirs)
    assert b.bones == ["innominate_right", "innominate_left", "sacrum"]
    assert all(r == 6 for r in b.rank.values())
    np.testing.assert_allclose(b.rigidity_table(), 1.0, atol=1e-9)
    # the six rigid-body modes are purely global rigid motion (eq. 11.4 content = 1)
    rigid = filter_global(point_rows(model, bones, pos, dirs) @ modes.rigid_shapes, pos, dirs)
    np.testing.assert_allclose(rigid.rigid_content, 1.0, atol=1e-9)
    # elastic modes are not (the first ones carry some global content: free-free model)
    assert np.all(g.rigid_content < 0.999)


def test_noise_lowers_rigidity_and_filtering_cleans_it(pelvis):
    _, _, bones, pos, dirs, shapes = pelvis
    rng = np.random.default_rng(1)
    scale = np.abs(shapes).max(axis=0)
    noise = 0.03 * scale * (rng.normal(size=shapes.shape) + 1j * rng.normal(size=shapes.shape))
    g = filter_global(shapes + noise, pos, dirs)
    b = filter_bones(g.x_el, bones, pos, dirs)
    table = b.rigidity_table()
    assert np.all(table < 0.9999) and np.median(table) > 0.5
    clean = filter_bones(filter_global(shapes, pos, dirs).x_el, bones, pos, dirs).x_corr
    # the bone-rigid projection removes the part of the noise that is not rigid motion
    err_before = np.linalg.norm(g.x_el - clean)
    err_after = np.linalg.norm(b.x_corr - clean)
    assert err_after < 0.8 * err_before


def _ods(model, bones, pos, dirs, seed):
    """Operating deflection shapes: FRF lines to two drive points, 1 % noise."""
    f = np.arange(20.0, 300.0, 10.0)
    drive = Points(("innominate_left", "sacrum"), pos[[15, 30]], [[0.0, 1.0, 0.0], [1.0, 0, 0]])
    out = Points(tuple(bones), pos, dirs)
    H = frf(model, f, out, drive)
    H = np.concatenate([H[:, :, 0], H[:, :, 1]]).T  # (n_channels, 2 n_lines)
    if seed is None:
        return H
    rng = np.random.default_rng(seed)
    return H * (1 + 0.01 * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape)))


def test_clean_sensors_are_not_flagged(pelvis):
    model, _, bones, pos, dirs, _ = pelvis
    check = check_channels(_ods(model, bones, pos, dirs, 2), bones, pos, dirs)
    assert not check.flagged.any(), check.relative_residual
    assert np.nanmax(check.relative_residual) < 0.1


def test_misoriented_sensor_is_flagged_with_its_direction(pelvis):
    model, _, bones, pos, dirs, _ = pelvis
    true_dirs = dirs.copy()
    bad = 4  # SIPS_R, y channel: the sensor really measures 25 degrees off its nominal axis
    a = np.radians(25.0)
    true_dirs[bad] = [np.sin(a), np.cos(a), 0.0]
    x = _ods(model, bones, pos, true_dirs, 3)
    check = check_channels(x, bones, pos, dirs)  # analysed with the nominal directions
    assert list(np.flatnonzero(check.flagged)) == [bad]
    # 1 % noise biases the estimate (the x motion of SIPS_R is small); noise-free it is exact
    assert check.direction_error_deg[bad] == pytest.approx(25.0, abs=8.0)
    exact = check_channels(_ods(model, bones, pos, true_dirs, None), bones, pos, dirs)
    assert exact.direction_error_deg[bad] == pytest.approx(25.0, abs=1e-6)
    np.testing.assert_allclose(exact.best_direction[bad], true_dirs[bad], atol=1e-8)


def test_misplaced_sensor_is_flagged(pelvis):
    model, _, bones, pos, dirs, _ = pelvis
    true_pos = pos.copy()
    bad = 22  # iliac_crest_L y channel, 3 cm anterior of where the analysis believes it is
    true_pos[bad] = pos[bad] + [0.03, 0.0, 0.0]
    x = _ods(model, bones, true_pos, dirs, 4)
    check = check_channels(x, bones, pos, dirs)
    assert list(np.flatnonzero(check.flagged)) == [bad]
    np.testing.assert_allclose(check.position_shift_m[bad], [0.03, 0.0, 0.0], atol=0.005)


def test_too_few_channels_are_not_checkable():
    p = np.random.default_rng(0).normal(size=(6, 3))
    d = np.tile([1.0, 0.0, 0.0], (6, 1))
    check = check_channels(np.ones((6, 2)), ["sacrum"] * 6, p, d)
    assert np.isnan(check.relative_residual).all() and not check.flagged.any()
