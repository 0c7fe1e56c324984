"""``pelvislab export-uff`` / ``import-uff`` end to end."""

from __future__ import annotations

import json

import numpy as np
import pyuff

from pelvislab.acquisition.frfset import read_frf, write_frf
from pelvislab.app.cli import main
from pelvislab.tests.test_uff_roundtrip import sample_frfset


def test_export_import_round_trip_exact(tmp_path):
    frf = sample_frfset(5)
    write_frf(tmp_path / "s.h5", frf)
    assert main(["export-uff", str(tmp_path / "s.h5"), str(tmp_path / "s.uff")]) == 0
    assert main(["import-uff", str(tmp_path / "s.uff"), "--out", str(tmp_path / "b.h5")]) == 0
    back = read_frf(tmp_path / "b.h5")
    np.testing.assert_array_equal(back.frequency_hz, frf.frequency_hz)
    np.testing.assert_array_equal(back.H, frf.H)
    np.testing.assert_array_equal(back.outputs.direction, frf.outputs.direction)
    np.testing.assert_array_equal(back.inputs.position_m, frf.inputs.position_m)
    assert back.outputs.bone == frf.outputs.bone


def test_export_with_modes_from_ema_json(tmp_path):
    frf = sample_frfset(6)
    write_frf(tmp_path / "s.h5", frf)
    doc = {"outputs": [{"name": n} for n in reversed(frf.outputs.name)],
           "modes": [{"frequency_hz": 50.0, "damping_ratio": 0.02,
                      "shape": {"re": [0.0, 0.5, 1.0], "im": [0.0, 0.0, 0.1]}}]}
    (tmp_path / "e.json").write_text(json.dumps(doc))
    argv = ["export-uff", str(tmp_path / "s.h5"), str(tmp_path / "m.uff"), "--modes",
            str(tmp_path / "e.json"), "--ascii", "--geometry", "15"]
    assert main(argv) == 0
    types = list(pyuff.UFF(str(tmp_path / "m.uff")).get_set_types())
    assert types.count(55) == 1 and 15 in types


def test_import_with_points_and_errors(tmp_path, capsys):
    frf = sample_frfset(7)
    write_frf(tmp_path / "s.h5", frf)
    assert main(["export-uff", str(tmp_path / "s.h5"), str(tmp_path / "s.uff")]) == 0
    assert main(["export-uff", str(tmp_path / "s.h5"), str(tmp_path / "s.uff")]) == 1
    assert "not overwriting" in capsys.readouterr().err
    (tmp_path / "p.toml").write_text('[[point]]\nnode = 1\nname = "x"\nbone = "sacrum"\n')
    argv = ["import-uff", str(tmp_path / "s.uff"), "--out", str(tmp_path / "b.h5"),
            "--points", str(tmp_path / "p.toml")]
    assert main(argv) == 0
    back = read_frf(tmp_path / "b.h5")
    assert back.outputs.bone[0] == "sacrum"  # node 1 (the first output) re-mapped
    # its name "x" is not applied, and said so (it was silent: review 67)
    assert back.outputs.name[0] == frf.outputs.name[0]
    assert "node 1: the points file's name 'x' is not applied" in capsys.readouterr().err
    assert main(["import-uff", str(tmp_path / "none.uff"), "--out", str(tmp_path / "c.h5")]) == 1
    assert "no such file" in capsys.readouterr().err
    assert main(["export-uff", str(tmp_path / "s.h5"), str(tmp_path / "z.uff"), "--modes",
                 str(tmp_path / "p.toml")]) == 1
    assert "not JSON" in capsys.readouterr().err


def test_import_of_a_file_that_is_no_uff_says_what_it_is(tmp_path, capsys):
    """Helper review, session 34: an HDF5 file and an empty file were both reported as a
    UFF "ends inside a dataset (no closing '-1' line): truncated?"."""
    write_frf(tmp_path / "s.h5", sample_frfset())
    (tmp_path / "empty.uff").write_bytes(b"")
    (tmp_path / "notes.txt").write_text("a lab note\n    -1\n")
    expected = {"s.h5": "is an HDF5 file, not UFF", "empty.uff": "is empty",
                "notes.txt": "does not start with a dataset delimiter line"}
    for name, reason in expected.items():
        assert main(["import-uff", str(tmp_path / name), "--out",
                     str(tmp_path / f"{name}.h5")]) == 1
        err = capsys.readouterr().err
        assert reason in err and "truncated" not in err, err
        assert not (tmp_path / f"{name}.h5").exists()


def test_export_with_unknown_shape_entries_counts_the_modes_written(tmp_path, capsys):
    # `ema` writes null for a shape entry not measured around its mode: --modes refused
    # such a file ("not a `pelvislab ema` result"), and a mode with no entry at all was
    # counted in "(N modes)" though no dataset 55 was written for it
    frf = sample_frfset(6)
    write_frf(tmp_path / "s.h5", frf)
    doc = {"outputs": [{"name": n} for n in frf.outputs.name],
           "modes": [{"frequency_hz": 50.0, "damping_ratio": 0.02,
                      "shape": {"re": [None, 0.5, 1.0], "im": [None, 0.0, 0.1]}},
                     {"frequency_hz": 120.0, "damping_ratio": 0.01,
                      "shape": {"re": [None] * 3, "im": [None] * 3}}]}
    (tmp_path / "e.json").write_text(json.dumps(doc))
    argv = ["export-uff", str(tmp_path / "s.h5"), str(tmp_path / "m.uff"), "--modes",
            str(tmp_path / "e.json")]
    assert main(argv) == 0
    err = capsys.readouterr().err
    assert "(1 modes)" in err and "the mode at 120 Hz is not in the file" in err
    sets = [s for s in pyuff.UFF(str(tmp_path / "m.uff")).read_sets()
            if s["type"] == 55]
    assert len(sets) == 1 and len(sets[0]["node_nums"]) == 2


def test_export_note_on_h_std_says_what_ema_does_without_it(tmp_path, capsys):
    # review of the EMA path: the note said "an analysis of the imported file estimates the
    # noise instead"; `ema` does not (it weights each FRF by 1/RMS of its values)
    frf = sample_frfset(5)
    frf.H_std = 0.01 * np.abs(frf.H)
    write_frf(tmp_path / "s.h5", frf)
    assert main(["export-uff", str(tmp_path / "s.h5"), str(tmp_path / "s.uff")]) == 0
    note = next(line for line in capsys.readouterr().err.splitlines() if "H_std" in line)
    assert "`ema` weights each FRF by 1/RMS of its values" in note
    assert "`gap diagnose` estimate the noise" in note


def _grid_file(tmp_path, frequency_hz):
    from pelvislab.acquisition.frfset import FrfSet

    frf = sample_frfset(8)
    n = frequency_hz.size
    H = np.resize(frf.H, (n, *frf.H.shape[1:]))
    path = tmp_path / "g.h5"
    write_frf(path, FrfSet(frequency_hz, H, frf.outputs, frf.inputs))
    return path


def test_ascii_export_refuses_a_grid_its_six_digits_merge(tmp_path, capsys):
    """ASCII dataset 58 writes frequencies as E13.5: a 0.5 mHz zoom at 231.9 Hz became 11
    lines of 21 on import, read as FRFs given twice, and the export said nothing (review
    67). Refused before writing; the binary format keeps them."""
    path = _grid_file(tmp_path, 231.9 + 0.0005 * np.arange(21))
    out = tmp_path / "a.uff"
    assert main(["export-uff", str(path), str(out), "--ascii"]) == 1
    err = capsys.readouterr().err
    assert "6 significant digits of frequency" in err and "21 lines, 11 after" in err
    assert not out.exists()
    assert main(["export-uff", str(path), str(tmp_path / "b.uff")]) == 0
    assert main(["import-uff", str(tmp_path / "b.uff"), "--out", str(tmp_path / "b.h5")]) == 0
    assert read_frf(tmp_path / "b.h5").frequency_hz.size == 21


def test_ascii_export_says_how_far_its_lines_moved(tmp_path, capsys):
    f = 5.0 + 0.1234567 * np.arange(30)
    path = _grid_file(tmp_path, f)
    assert main(["export-uff", str(path), str(tmp_path / "a.uff"), "--ascii"]) == 0
    err = capsys.readouterr().err
    assert "line(s) moved by up to" in err
    assert main(["import-uff", str(tmp_path / "a.uff"), "--out", str(tmp_path / "a.h5")]) == 0
    back = read_frf(tmp_path / "a.h5").frequency_hz
    shift = float(err.split("moved by up to ")[1].split(" Hz")[0])
    assert np.isclose(np.max(np.abs(back - f)), shift, rtol=1e-2)  # what the note says


def test_export_with_ema_says_what_ema_says(tmp_path, capsys):
    """``export-uff --ema`` wrote 3 of the real beam's 6 modes without a word where ``ema``
    notes the dropped poles and the lowest lines' weight (review 67)."""
    frf = sample_frfset(9)
    write_frf(tmp_path / "s.h5", frf)
    assert main(["ema", str(tmp_path / "s.h5"), "--json", str(tmp_path / "e.json")]) == 0
    notes = json.loads((tmp_path / "e.json").read_text())["notes"]
    assert notes
    capsys.readouterr()
    assert main(["export-uff", str(tmp_path / "s.h5"), str(tmp_path / "m.uff"), "--ema"]) == 0
    err = capsys.readouterr().err
    for note in notes:
        assert f"note (ema): {note}" in err


def test_import_says_what_it_leaves_out(tmp_path, capsys):
    """Mode datasets (55) and points-file nodes in no record were dropped without a word;
    a folder given as the file read "no such file" (review 67)."""
    frf = sample_frfset(6)
    write_frf(tmp_path / "s.h5", frf)
    doc = {"outputs": [{"name": n} for n in frf.outputs.name],
           "modes": [{"frequency_hz": 50.0, "damping_ratio": 0.02,
                      "shape": {"re": [0.0, 0.5, 1.0], "im": [0.0, 0.0, 0.1]}}]}
    (tmp_path / "e.json").write_text(json.dumps(doc))
    assert main(["export-uff", str(tmp_path / "s.h5"), str(tmp_path / "m.uff"), "--modes",
                 str(tmp_path / "e.json")]) == 0
    (tmp_path / "p.toml").write_text('[[point]]\nnode = 77\nname = "x"\nbone = "sacrum"\n')
    capsys.readouterr()
    assert main(["import-uff", str(tmp_path / "m.uff"), "--out", str(tmp_path / "b.h5"),
                 "--points", str(tmp_path / "p.toml")]) == 0
    err = capsys.readouterr().err
    assert "1 mode shape dataset(s) (55) not imported" in err
    assert "points file node(s) [77] are in no FRF record imported" in err
    assert main(["import-uff", str(tmp_path), "--out", str(tmp_path / "c.h5")]) == 1
    assert "is a folder, not a UFF file" in capsys.readouterr().err
