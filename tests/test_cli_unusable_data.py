"""FRF files that hold no usable response are refused with the reason, not analysed
(helper review, session 34: all-zero FRFs gave a gap diagnosis `unexplained` at gap 29.7
with exit 0, an EMA "no mode found", and identify "no measured FRF lines" for lines that
were measured; one frequency line was "identified" into 18 parameters; an H_std of -1
made identify say there were no measured lines)."""

from __future__ import annotations

import json

import h5py
import numpy as np
import pytest

from pelvislab.app.cli import main


def _model_file(tmp_path, name="m.h5", step_hz="5"):
    path = tmp_path / name
    assert main(["model", "frf", "--points", "sacrum_x,SIAS_R_x", "--start-hz", "5",
                 "--stop-hz", "300", "--step-hz", step_hz, "--out", str(path)]) == 0
    return path


def _edit(path, **datasets):
    with h5py.File(path, "r+") as f:
        for key, value in datasets.items():
            if key in f["frf"]:
                del f["frf"][key]
            f["frf"].create_dataset(key, data=value)


@pytest.mark.parametrize("argv", [
    ["identify", "{f}", "--json", "{o}.json"],
    ["ema", "{f}", "--json", "{o}.json"],
    ["gap", "diagnose", "{f}", "--json", "{o}.json", "--no-plots"],
])
def test_all_zero_frfs_are_refused_with_the_reason(tmp_path, capsys, argv):
    path = _model_file(tmp_path)
    with h5py.File(path, "r") as f:
        shape = f["frf/H"].shape
    _edit(path, H=np.zeros(shape, complex))
    capsys.readouterr()
    code = main([a.format(f=path, o=tmp_path / "out") for a in argv])
    err = capsys.readouterr().err
    assert code == 1
    assert "every measured value of /frf/H is exactly 0" in err, err
    assert not (tmp_path / "out.json").exists()


def test_too_few_lines_to_identify_are_refused(tmp_path, capsys):
    path = _model_file(tmp_path, step_hz="300")  # one line: 5 Hz
    capsys.readouterr()
    code = main(["identify", str(path), "--json", str(tmp_path / "i.json")])
    err = capsys.readouterr().err
    assert code == 1
    assert "cannot identify 18 parameters" in err and "needs >= 3 lines" in err, err


def test_an_unusable_h_std_is_ignored_with_a_note_not_taken_for_no_data(tmp_path, capsys):
    path = _model_file(tmp_path)
    with h5py.File(path, "r") as f:
        shape = f["frf/H"].shape
    _edit(path, H_std=-np.ones(shape))
    out = tmp_path / "i.json"
    code = main(["identify", str(path), "--json", str(out), "--params", "k_io_R,c_sij_R"])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "H_std holds no positive finite value on the measured lines: ignored" in err
    doc = json.loads(out.read_text())
    assert doc["notes"] == ["H_std holds no positive finite value on the measured lines: "
                            "ignored"]


@pytest.mark.parametrize("argv, where", [
    (["identify", "{f}", "--json", "{o}.json", "--params", "k_io_R,c_sij_R"], "notes"),
    (["ema", "{f}", "--json", "{o}.json"], "notes"),
    (["export-uff", "{f}", "{o}.uff"], None),
])
def test_infinite_frf_values_are_named_not_dropped_without_a_word(tmp_path, capsys, argv,
                                                                  where):
    # helper review, session 34: export-uff left an infinite value out of the UFF file
    # without a word (every analysis reads a non-finite value as a line not measured)
    path = _model_file(tmp_path)
    with h5py.File(path, "r") as f:
        H = f["frf/H"][()]
    H[7, 0, 0] = complex(np.inf, 0.0)
    H[9, 1, 0] = complex(1e-6, -np.inf)
    _edit(path, H=H)
    capsys.readouterr()
    code = main([a.format(f=path, o=tmp_path / "out") for a in argv])
    err = capsys.readouterr().err
    assert code == 0, err
    message = "2 value(s) of /frf/H are infinite: read as not measured"
    assert message in err, err
    if where:
        doc = json.loads((tmp_path / "out.json").read_text())
        assert any(message in n for n in doc[where]), doc[where]


def test_gap_diagnosis_names_infinite_frf_values(tmp_path, capsys):
    path = _model_file(tmp_path)
    with h5py.File(path, "r") as f:
        H = f["frf/H"][()]
    H[3, 0, 0] = complex(-np.inf, 1.0)
    _edit(path, H=H)
    out = tmp_path / "g.json"
    code = main(["gap", "diagnose", str(path), "--json", str(out), "--no-plots",
                 "--effects", "added_mass", "--jobs", "1"])
    err = capsys.readouterr().err
    assert code == 0, err
    message = ("1 value(s) of /frf/H are infinite: read as not measured (as NaN), so those "
               "values are left out of the analysis")
    assert json.loads(out.read_text())["warnings"] == [message]
    assert message in err
