"""Modes (undamped, complex, app. D), modal superposition, MAC, pairing, landmarks, CLI."""

import json

import numpy as np
import pytest

from pelvislab.app.cli import main
from pelvislab.model.assembly import assemble
from pelvislab.model.frf import Points, receptance, rows_for
from pelvislab.model.landmarks import landmark_points, load_landmarks
from pelvislab.model.modal import (
    complex_modes,
    mac,
    modal_mass,
    modal_receptance,
    model_modes,
    pair_modes,
    undamped_modes,
)
from pelvislab.model.pelvis import GROUND, Body, Dashpot, PelvisModel, Spring, default_model


@pytest.fixture(scope="module")
def model():
    return default_model()


@pytest.fixture(scope="module")
def mats(model):
    return assemble(model)


@pytest.fixture(scope="module")
def pts():
    return landmark_points(["SIAS_R_x", "SIAS_L_y", "sacrum_x", "SIPS_L_x", "iliac_crest_R_z"])


def test_undamped_modes(mats):
    u = undamped_modes(mats.M, mats.K)
    assert u.n_rigid_body == 6
    assert np.all(u.frequencies_hz[:6] == 0) and np.all(u.frequencies_hz[6:] > 1.0)
    assert np.all(np.diff(u.frequencies_hz[6:]) > 0)
    assert np.allclose(modal_mass(mats.M, u.shapes), 1.0)
    assert np.allclose(u.shapes.T @ mats.K @ u.shapes, np.diag(u.omega2), atol=1e-6)


def test_complex_modes_free_free(mats):
    cm = complex_modes(mats.M, mats.K, mats.C)
    assert cm.n_rigid_body == 6 and cm.poles.size == 12 and cm.overdamped_poles.size == 0
    assert np.all(cm.poles.real < 0) and np.all(np.diff(cm.poles.imag) > 0)
    # each pole solves the quadratic eigenproblem (4.45): (λ²M + λC + K) z = 0
    for lam, z in zip(cm.poles, cm.shapes.T, strict=True):
        r = (lam**2 * mats.M + lam * mats.C + mats.K) @ z
        assert np.linalg.norm(r) < 1e-8 * np.linalg.norm(mats.K @ z)
    zeta = cm.damping_ratios
    assert np.allclose(zeta, -cm.poles.real / np.abs(cm.poles))  # eq. 7.5
    assert np.allclose(cm.natural_frequencies_hz ** 2,
                       cm.damped_frequencies_hz ** 2 + (cm.poles.real / 2 / np.pi) ** 2)
    # light damping: damped ≈ undamped frequencies
    u = undamped_modes(mats.M, mats.K)
    assert np.allclose(cm.natural_frequencies_hz, u.frequencies_hz[6:], rtol=1e-3)


def test_single_dof_pole_closed_form():
    m, k, c = 2.0, 8e3, 6.0
    body = Body("b", m, [0, 0, 0], np.eye(3))
    model = PelvisModel((body,))
    big = 1e12
    model = model.with_spring(Spring("kx", "b", [0, 0, 0], GROUND, [0, 0, 0], k, axis=[1, 0, 0]))
    model = model.with_dashpot(Dashpot("cx", "b", [0, 0, 0], GROUND, [0, 0, 0], c,
                                       axis=[1, 0, 0]))
    for name, p, ax in (("y", [0, 0, 0], [0, 1, 0]), ("z", [0, 0, 0], [0, 0, 1]),
                        ("ry", [1.0, 0, 0], [0, 0, 1]), ("rz", [0, 1.0, 0], [0, 0, 1]),
                        ("rx", [1.0, 0, 0], [0, 1, 0])):
        model = model.with_spring(Spring(name, "b", p, GROUND, p, big, axis=ax))
    cm = model_modes(model)
    wn = np.sqrt(k / m)
    zeta = c / (2 * np.sqrt(k * m))
    assert cm.n_rigid_body == 0
    assert cm.natural_frequencies_hz[0] == pytest.approx(wn / 2 / np.pi, rel=1e-9)
    assert cm.damping_ratios[0] == pytest.approx(zeta, rel=1e-7)


@pytest.mark.parametrize("grounded", [False, True])
def test_frf_equals_modal_superposition(model, pts, grounded):
    """Eq. 4.55 (+ rigid-body term when free-free) equals the direct solve to 1e-9."""
    m = model.with_grounding("sacrum", 2e4, coefficient_n_s_per_m=3.0) if grounded else model
    s = assemble(m)
    o = rows_for(m, pts)
    f = np.linspace(1.0, 1200.0, 700)
    direct = receptance(s.M, s.K, s.C, f, o, o)
    modal = modal_receptance(complex_modes(s.M, s.K, s.C), f, o, o)
    assert np.abs(direct - modal).max() / np.abs(direct).max() < 1e-9


def test_overdamped_modes_in_superposition():
    """Two bodies with a very strong dashpot: real poles appear and are kept in eq. 4.55."""
    b1 = Body("one", 1.0, [0, 0, 0], np.eye(3) * 0.01)
    b2 = Body("two", 2.0, [0.1, 0, 0], np.eye(3) * 0.02)
    m = PelvisModel((b1, b2))
    m = m.with_spring(Spring("k", "one", [0, 0, 0], "two", [0.1, 0, 0], 1e3))
    m = m.with_dashpot(Dashpot("c", "one", [0, 0, 0], "two", [0.1, 0, 0], 500.0))
    m = m.with_grounding("one", 1e4, coefficient_n_s_per_m=1.0)
    m = m.with_grounding("two", 1e4, point_m=[0.2, 0.05, 0.03], prefix="g2")
    m = m.with_grounding("two", 1e4, point_m=[0.1, 0.1, -0.1], prefix="g3")
    s = assemble(m)
    cm = complex_modes(s.M, s.K, s.C)
    assert cm.overdamped_poles.size > 0
    p = Points(("one", "two"), [[0, 0, 0], [0.1, 0, 0]], [[1, 0, 0], [1, 0.2, 0]])
    o = rows_for(m, p)
    f = np.linspace(0.5, 200, 300)
    direct = receptance(s.M, s.K, s.C, f, o, o)
    assert np.abs(direct - modal_receptance(cm, f, o, o)).max() / np.abs(direct).max() < 1e-9


def test_appendix_d_fixed_point(mats):
    """Converged poles satisfy eq. D-4 with the matrices evaluated at their own ω_s."""
    fk, fc, fmax = 1.0, 1.0, 300.0
    cm = complex_modes(mats.M, mats.K, mats.C, fk, fc, fmax)
    wmax = 2 * np.pi * fmax
    assert cm.iterations is not None and np.all(cm.iterations >= 2)
    for lam, z in zip(cm.poles, cm.shapes.T, strict=True):
        w = lam.imag
        K = mats.K * (1 + fk * w / (4 * wmax))
        C = mats.C * (1 + fc * wmax / (4 * w))
        r = (lam**2 * mats.M + lam * C + K) @ z
        assert np.linalg.norm(r) < 1e-5 * np.linalg.norm(K @ z)
    base = complex_modes(mats.M, mats.K, mats.C)
    # the modes stay distinct (the iteration follows each mode by its shape)
    assert np.all(np.diff(cm.damped_frequencies_hz) > 0)
    assert np.allclose(np.diag(mac(cm.shapes, base.shapes)), 1.0, atol=1e-3)
    # stiffening alone raises every frequency; hysteretic damping alone raises damping (ch. 7)
    stiff = complex_modes(mats.M, mats.K, mats.C, 1.0, 0.0, fmax)
    assert np.all(stiff.damped_frequencies_hz > base.damped_frequencies_hz)
    hyst = complex_modes(mats.M, mats.K, mats.C, 0.0, 1.0, fmax)
    assert np.all(hyst.damping_ratios > base.damping_ratios)
    assert np.allclose(hyst.natural_frequencies_hz, base.natural_frequencies_hz, rtol=1e-3)


def test_mac_and_pairing():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(9, 4)) + 1j * rng.normal(size=(9, 4))
    m = mac(a, a * (2 - 3j))
    assert np.allclose(np.diag(m), 1.0) and np.all((m >= 0) & (m <= 1 + 1e-12))
    assert np.allclose(m, m.T)
    perm = [2, 0, 3, 1]
    pairs = pair_modes(a, a[:, perm] * 1.7)
    assert [(p.a, p.b) for p in pairs] == [(0, 1), (1, 3), (2, 0), (3, 2)]
    assert all(p.mac == pytest.approx(1.0) for p in pairs)
    assert mac(np.array([1.0, 0]), np.array([0.0, 1]))[0, 0] == 0.0


def test_landmarks(model):
    cat = load_landmarks()
    assert {"sacrum_x", "SIAS_R_x", "SIAS_L_x", "SIAS_R_y", "SIAS_L_y", "SIPS_R_x",
            "SIPS_L_x"} <= set(cat)
    for lm in cat.values():
        assert lm.bone in model.body_names
        assert np.linalg.norm(lm.direction) == pytest.approx(1.0)
        # points lie within 12 cm of their bone's centre of mass
        assert np.linalg.norm(lm.position_m - model.body(lm.bone).com_m) < 0.12
        if lm.bone == "innominate_right":
            assert lm.position_m[1] < 0
    # right/left pairs are mirror images
    for name, lm in cat.items():
        if "_R" in name:
            other = cat[name.replace("_R", "_L").replace("ch11_2_", "ch11_10_")
                        .replace("ch11_4_", "ch11_12_")]
            assert np.allclose(other.position_m, lm.position_m * [1, -1, 1])
            assert np.allclose(other.direction, lm.direction * [1, -1, 1])
    with pytest.raises(ValueError, match="nope"):
        landmark_points(["nope"])


def test_cli_modes_json(capsys):
    assert main(["model", "modes", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["n_rigid_body"] == 6 and len(out["frequencies_hz"]) == 12
    assert out["frequencies_hz"] == sorted(out["frequencies_hz"])
    assert all(0 < z < 1 for z in out["damping_ratios"])
    assert main(["model", "modes", "--json", "--points", "SIAS_R_x,SIAS_L_x"]) == 0
    shapes = json.loads(capsys.readouterr().out)["shapes"]
    assert shapes["points"] == ["SIAS_R_x", "SIAS_L_x"]
    assert np.array(shapes["real"]).shape == (2, 12)


def test_cli_frf_json_and_errors(capsys, tmp_path):
    assert main(["model", "frf", "--points", "SIAS_R_x,sacrum_x", "--inputs", "SIPS_L_x",
                 "--start-hz", "10", "--stop-hz", "20", "--step-hz", "5", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frequency_hz"] == [10.0, 15.0, 20.0]
    assert np.array(out["H_real"]).shape == (3, 2, 1)
    assert main(["model", "frf", "--points", "nope"]) == 1
    assert "unknown landmark" in capsys.readouterr().err
    bad = tmp_path / "bad.toml"
    bad.write_text("[[body]]\nname = 'x'\n")
    assert main(["model", "modes", "--model", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "body #1 'x'" in err and "Traceback" not in err


def test_docs_examples_run():
    """The usage and extension examples of docs/model-api.md execute as written."""
    import re
    from pathlib import Path

    doc = Path(__file__).resolve().parents[1] / "docs" / "model-api.md"
    blocks = re.findall(r"```python\n(.*?)```", doc.read_text(encoding="utf-8"), re.S)
    runnable = [b for b in blocks if "import" in b]
    assert len(runnable) >= 2
    namespace: dict = {}
    for block in runnable:
        exec(compile(block, str(doc), "exec"), namespace)
    assert namespace["dH"].shape[-1] == len(namespace["space"])
    assert namespace["m5"].n_dof == 24


def _sign_protocol() -> str:
    """The contract tests' two-channel protocol at 50 and 150 Hz."""
    from pelvislab.tests.test_contracts import TINY_PROTOCOL

    sweep = "start_hz = 100.0\nstop_hz = 120.0\nstep_hz = 10.0\n"
    assert sweep in TINY_PROTOCOL
    return TINY_PROTOCOL.replace(sweep, "frequencies_hz = [50.0, 150.0]\n")


def test_cli_frf_agrees_in_sign_with_a_simulated_session(tmp_path, capsys):
    # `model frf` pushed along the landmark direction (outward) while a session's force
    # goes into the surface (protocol default): same names, opposite signs (audit). Now the
    # model file, its --json and a measured /frf agree for the same (output, input) names.
    from pelvislab.acquisition.frfset import read_frf

    (tmp_path / "p.toml").write_text(_sign_protocol())
    assert main(["run", str(tmp_path / "p.toml"), "--out", str(tmp_path / "s.h5"),
                 "--quiet"]) == 0
    args = ["model", "frf", "--points", "sacrum_x,SIAS_R_x", "--inputs", "SIAS_R_x",
            "--start-hz", "50", "--stop-hz", "150", "--step-hz", "100"]
    assert main([*args, "--out", str(tmp_path / "m.h5")]) == 0
    assert main([*args, "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    session, model = read_frf(tmp_path / "s.h5"), read_frf(tmp_path / "m.h5")
    assert list(model.inputs.name) == list(session.inputs.name) == ["SIAS_R_x"]
    np.testing.assert_allclose(model.inputs.direction, session.inputs.direction, atol=1e-12)
    np.testing.assert_allclose(js["input_directions"], session.inputs.direction, atol=1e-12)
    assert list(session.frequency_hz) == list(model.frequency_hz) == [50.0, 150.0]
    H_json = np.array(js["H_real"]) + 1j * np.array(js["H_imag"])
    np.testing.assert_allclose(H_json, model.H)
    for o, name in enumerate(model.outputs.name):
        measured = session.H[:, list(session.outputs.name).index(name), 0]
        ratio = measured / model.H[:, o, 0]
        # the simulated chain (tissue, echoes, tracking) is the model to a few per cent
        assert np.all(np.abs(ratio - 1) < 0.2), (name, ratio)
