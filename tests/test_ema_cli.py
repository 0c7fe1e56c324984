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
