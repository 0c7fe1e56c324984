"""``pelvislab ema`` end to end on an FRF-only file (analytic system written through /frf)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pelvislab.acquisition.frfset import Channels, FrfSet, write_frf
from pelvislab.app.cli import main
from pelvislab.tests.test_ema_estimator import (
    add_noise,
    analytic_system,
    receptance,
    reference_modes,
)


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("ema_cli")
    M, K, C = analytic_system()
    f = np.arange(5.0, 300.01, 2.5)
    H = add_noise(receptance(M, K, C, f, list(range(6)), [0]), 0.01, seed=11)
    H[10, 2, 0] = np.nan
    rng = np.random.default_rng(0)
    d = np.tile([0.0, 0.0, 1.0], (6, 1))
    outputs = Channels([f"p{k}" for k in range(6)], [""] * 6, rng.normal(size=(6, 3)), d)
    inputs = Channels(["drive"], [""], np.zeros((1, 3)), [[0.0, 0.0, 1.0]])
    write_frf(tmp / "s.h5", FrfSet(f, H, outputs, inputs, H_std=0.01 * np.abs(H)))
    lam, _ = reference_modes(M, K, C)
    return tmp, np.abs(lam) / (2 * np.pi)


def test_json_has_the_contracted_fields(session, capsys):
    tmp, fn = session
    assert main(["ema", str(tmp / "s.h5"), "--json", str(tmp / "out.json")]) == 0
    doc = json.loads((tmp / "out.json").read_text())
    modes = doc["modes"]
    assert len(modes) == 6
    for m in modes:
        assert {"frequency_hz", "damping_ratio", "complexity"} <= set(m)
        assert len(m["shape"]["re"]) == 6
    np.testing.assert_allclose([m["frequency_hz"] for m in modes], fn, rtol=3e-3)
    assert doc["selection"] == "auto" and doc["stabilisation"]
    assert [o["name"] for o in doc["outputs"]] == [f"p{k}" for k in range(6)]
    assert "Hz" in capsys.readouterr().err


def test_band_manual_frequencies_and_stdout(session, capsys):
    tmp, fn = session
    argv = ["ema", str(tmp / "s.h5"), "--band", "80", "200", "--json", "-", "--no-diagram",
            "--frequencies", str(round(fn[2], 1)), str(round(fn[1], 1))]
    assert main(argv) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["selection"] == "manual" and "stabilisation" not in doc
    np.testing.assert_allclose([m["frequency_hz"] for m in doc["modes"]], fn[[1, 2]], rtol=3e-3)
    assert doc["band_hz"][0] >= 80 and doc["band_hz"][1] <= 200


def test_bad_input_gives_one_line_errors(session, tmp_path, capsys):
    tmp, _ = session
    assert main(["ema", str(tmp_path / "none.h5"), "--json", "x.json"]) == 1
    assert "no such file" in capsys.readouterr().err
    assert main(["ema", str(tmp / "s.h5"), "--band", "300", "100", "--json", "-"]) == 1
    assert "band" in capsys.readouterr().err
    # a pick outside the band read "no pole stable near ..." (review 67)
    assert main(["ema", str(tmp / "s.h5"), "--band", "150", "250", "--frequencies", "112",
                 "--json", "-"]) == 1
    assert "[112.0] Hz lie outside the band's lines" in capsys.readouterr().err
    (tmp_path / "junk.h5").write_text("not hdf5")
    assert main(["ema", str(tmp_path / "junk.h5"), "--json", "-"]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err


def test_existing_json_is_never_overwritten(session, tmp_path, capsys):
    tmp, _ = session
    out = tmp_path / "old.json"
    out.write_text("earlier result\n")
    assert main(["ema", str(tmp / "s.h5"), "--json", str(out)]) == 1
    err = capsys.readouterr().err
    assert "exists" in err and err.count("\n") == 1
    assert out.read_text() == "earlier result\n"
    assert main(["ema", str(tmp / "s.h5"), "--json", str(tmp_path / "no" / "o.json")]) == 1
    assert "output folder" in capsys.readouterr().err


def test_pelvis_session_reports_rigid_content_and_flags_a_misoriented_sensor(tmp_path, capsys):
    from pelvislab.model.frf import Points, frf
    from pelvislab.model.pelvis import load_model
    from pelvislab.tests.test_ema_rigid_body import triaxial_geometry

    model = load_model()
    bones, pos, dirs = triaxial_geometry()
    true_dirs = dirs.copy()
    a = np.radians(30.0)
    true_dirs[4] = [np.sin(a), np.cos(a), 0.0]  # SIPS_R y sensor actually 30 deg off
    f = np.arange(5.0, 300.01, 2.5)
    drive = Points(("innominate_left", "sacrum"), pos[[15, 30]], [[0.0, 1.0, 0.0], [1.0, 0, 0]])
    H = add_noise(frf(model, f, Points(tuple(bones), pos, true_dirs), drive), 0.01, seed=3)
    names = [f"c{k}" for k in range(len(bones))]
    outputs = Channels(names, bones, pos, dirs)  # the file states the nominal directions
    inputs = Channels(["drive", "sacrum_drive"], ["innominate_left", "sacrum"], pos[[15, 30]],
                      [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    write_frf(tmp_path / "p.h5", FrfSet(f, H, outputs, inputs))
    assert main(["ema", str(tmp_path / "p.h5"), "--json", str(tmp_path / "p.json")]) == 0
    doc = json.loads((tmp_path / "p.json").read_text())
    assert len(doc["modes"]) == 5
    for m in doc["modes"]:
        rb = m["rigid_body"]
        assert 0 <= rb["global_content"] <= 1
        assert set(rb["bone_rigidity"]) == {"innominate_right", "innominate_left", "sacrum"}
    flagged = [c["name"] for c in doc["channel_check"] if c["flagged"]]
    assert flagged == ["c4"]
    assert "channel c4 is inconsistent" in capsys.readouterr().err


def test_update_matches_the_models_modes_to_the_measured_ones(tmp_path, capsys):
    # thesis ch. 14 from the command line: modes measured on a subject with k_io x1.2 and
    # k_asa x0.9 (ch. 11 triaxial layout, 2.5 Hz grid, 1 % noise); appendix E updated on them
    from pelvislab.model.frf import Points, frf
    from pelvislab.model.parameters import parameter_space
    from pelvislab.model.pelvis import load_model
    from pelvislab.tests.test_ema_rigid_body import triaxial_geometry

    nominal = load_model()
    space = parameter_space(nominal, symmetric=True, only=["k_io", "k_asa"])
    truth = space.as_dict()
    truth = {"k_io": 1.2 * truth["k_io"], "k_asa": 0.9 * truth["k_asa"]}
    subject = space.apply(space.from_dict(truth))
    bones, pos, dirs = triaxial_geometry()
    f = np.arange(5.0, 300.01, 2.5)
    drive = Points(("innominate_left", "sacrum"), pos[[15, 30]], [[0.0, 1.0, 0.0], [1.0, 0, 0]])
    H = add_noise(frf(subject, f, Points(tuple(bones), pos, dirs), drive), 0.01, seed=4)
    outputs = Channels([f"c{k}" for k in range(len(bones))], bones, pos, dirs)
    inputs = Channels(["drive", "sacrum_drive"], ["innominate_left", "sacrum"], pos[[15, 30]],
                      [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    write_frf(tmp_path / "u.h5", FrfSet(f, H, outputs, inputs))
    out = tmp_path / "u.json"
    assert main(["ema", str(tmp_path / "u.h5"), "--json", str(out),
                 "--update", "k_io,k_asa"]) == 0
    upd = json.loads(out.read_text())["model_updating"]
    assert upd["filter_rigid"] is True and "error" not in upd
    for name, value in truth.items():
        assert upd["parameters"][name]["value"] == pytest.approx(value, rel=0.03)
    assert all(abs(p["frequency_error"]) < 0.01 for p in upd["pairs"])
    assert "model updating (eq. 14.1)" in capsys.readouterr().err


def test_update_refused_by_the_layout_still_writes_the_modes(tmp_path, capsys):
    # five probes along x (make demo's layout) cannot determine the six rigid motions the
    # fig. 14.1 filter removes: the EMA result is written with the reason, exit 1; plain
    # MAC (--no-rigid-filter) updates
    from pelvislab.model.frf import Points, frf
    from pelvislab.model.landmarks import load_landmarks
    from pelvislab.model.pelvis import load_model

    cat = load_landmarks()
    names = ["sacrum_x", "SIAS_R_x", "SIAS_L_x", "SIPS_R_x", "SIPS_L_x"]
    outs = Channels(names, [cat[n].bone for n in names], [cat[n].position_m for n in names],
                    [cat[n].direction for n in names])
    ins = Channels(["SIAS_R_x"], [cat["SIAS_R_x"].bone], [cat["SIAS_R_x"].position_m],
                   [-cat["SIAS_R_x"].direction])
    f = np.arange(226.0, 238.01, 0.25)  # a zoom window across the 231.9 Hz mode
    H = add_noise(frf(load_model(), f, Points(tuple(outs.bone), outs.position_m,
                                              outs.direction),
                      Points(tuple(ins.bone), ins.position_m, ins.direction)), 0.01, seed=5)
    write_frf(tmp_path / "d.h5", FrfSet(f, H, outs, ins))
    out = tmp_path / "d.json"
    assert main(["ema", str(tmp_path / "d.h5"), "--json", str(out), "--update", "k_io"]) == 1
    doc = json.loads(out.read_text())
    assert len(doc["modes"]) == 1
    assert "determine 3 of 6" in doc["model_updating"]["error"]
    assert "--no-rigid-filter" in capsys.readouterr().err
    out2 = tmp_path / "d2.json"
    assert main(["ema", str(tmp_path / "d.h5"), "--json", str(out2), "--update", "k_io",
                 "--no-rigid-filter"]) == 0
    upd = json.loads(out2.read_text())["model_updating"]
    assert upd["pairs"][0]["model"] == 4 and abs(upd["pairs"][0]["frequency_error"]) < 1e-3


def test_update_names_checked_before_any_fit(session, tmp_path, capsys):
    tmp, _ = session
    out = tmp_path / "x.json"
    assert main(["ema", str(tmp / "s.h5"), "--json", str(out), "--update", "k_io,k_foo"]) == 1
    assert "unknown parameter(s) ['k_foo']" in capsys.readouterr().err
    assert main(["ema", str(tmp / "s.h5"), "--json", str(out), "--model", "m.toml"]) == 1
    assert "go with --update" in capsys.readouterr().err
    assert not out.exists()


def test_rigid_content_of_a_mode_with_unknown_entries_uses_the_known_channels(tmp_path):
    # a run stopped at 150 Hz for the sacrum's channels: the 174.9 and 231.9 Hz modes have
    # null entries there, and their global content and every bone's rigidity were null too
    # (review of the EMA path); the innominates are still fully measured
    from pelvislab.model.frf import Points, frf
    from pelvislab.model.pelvis import load_model
    from pelvislab.tests.test_ema_rigid_body import triaxial_geometry

    bones, pos, dirs = triaxial_geometry()
    f = np.arange(5.0, 300.01, 2.5)
    drive = Points(("innominate_left",), pos[[15]], [[0.0, 1.0, 0.0]])
    H = add_noise(frf(load_model(), f, Points(tuple(bones), pos, dirs), drive), 0.01, seed=3)
    sacrum = np.array([b == "sacrum" for b in bones])
    H[np.ix_(f > 150, sacrum, [0])] = np.nan
    outputs = Channels([f"c{k}" for k in range(len(bones))], bones, pos, dirs)
    inputs = Channels(["drive"], ["innominate_left"], pos[[15]], [[0.0, 1.0, 0.0]])
    write_frf(tmp_path / "p.h5", FrfSet(f, H, outputs, inputs))
    assert main(["ema", str(tmp_path / "p.h5"), "--json", str(tmp_path / "p.json")]) == 0
    modes = json.loads((tmp_path / "p.json").read_text())["modes"]
    high = [m for m in modes if m["frequency_hz"] > 150]
    assert high and all(None in m["shape"]["re"] for m in high)
    for m in high:
        rb = m["rigid_body"]
        assert 0 <= rb["global_content"] <= 1
        assert set(rb["bone_rigidity"]) == {"innominate_right", "innominate_left"}
        assert all(0.9 < v <= 1 for v in rb["bone_rigidity"].values())
