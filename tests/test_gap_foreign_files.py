"""`gap diagnose` on /frf files written by someone who only read design.md 4.2.

The files come from :mod:`pelvislab.tests.foreign_frf_writer`, which writes the layout with
h5py directly (not with ``write_frf``) in the ways the contract leaves open: string and
scalar types, complex field names, float32 arrays, grid order and spacing, extra content,
a full session file. These tests check the *reading* (fast); the full diagnosis of every
variant is run by ``python -m pelvislab.tests.foreign_frf_writer OUT --run`` (~30 s each).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pelvislab.acquisition.frfset import FrfFileError, read_frf
from pelvislab.app.cli import main
from pelvislab.app.commands.gap import usable_std
from pelvislab.tests.foreign_frf_writer import VARIANTS, synthesise, write_variant

GOOD = [v for v in VARIANTS if not v.bad]
BAD = [v for v in VARIANTS if v.bad]


@pytest.mark.parametrize("variant", GOOD, ids=[v.name for v in GOOD])
def test_foreign_layout_reads_back_the_written_values(tmp_path, variant):
    d = synthesise(variant)
    frf = read_frf(write_variant(tmp_path / "f.h5", variant, d))
    order = np.argsort(d["f"])  # a downward sweep comes back sorted, every array with it
    rtol = 1e-6 if variant.real_dtype == "float64" else 1e-6 * 2**29  # float32: ~1e-7
    np.testing.assert_allclose(frf.frequency_hz, d["f"][order], rtol=rtol)
    assert np.all(np.diff(frf.frequency_hz) > 0)
    measured = np.isfinite(d["H"][order])
    assert np.array_equal(frf.measured, measured)
    np.testing.assert_array_equal(frf.H[measured], d["H"][order][measured])
    assert frf.H.dtype == np.complex128
    assert frf.outputs.name == list(d["outs"].name) and frf.inputs.name == list(d["ins"].name)
    assert frf.outputs.bone == list(d["outs"].bone) and frf.inputs.bone == list(d["ins"].bone)
    np.testing.assert_allclose(frf.outputs.position_m, d["outs"].position_m, atol=1e-7)
    np.testing.assert_allclose(np.linalg.norm(frf.outputs.direction, axis=1), 1.0, atol=1e-9)
    np.testing.assert_allclose(frf.outputs.direction, d["outs"].direction, atol=1e-3)
    if variant.with_std:
        np.testing.assert_array_equal(frf.H_std[measured], d["std"][order][measured])
    else:
        assert frf.H_std is None
    if variant.acquired:
        np.testing.assert_allclose(frf.acquired_at_s, d["acquired"][order], rtol=1e-6)


def test_descending_grid_keeps_lines_with_their_frequency(tmp_path):
    v = next(v for v in GOOD if v.order == "down")
    d = synthesise(v)
    frf = read_frf(write_variant(tmp_path / "f.h5", v, d))
    k = int(np.flatnonzero(d["f"] == 5.0)[0])  # the last line written is the 5 Hz one
    assert k == d["f"].size - 1 and frf.frequency_hz[0] == 5.0
    np.testing.assert_array_equal(frf.H[0, 0, 0], d["H"][k, 0, 0])
    assert frf.acquired_at_s[0] == d["acquired"][k]


def test_zero_std_is_read_as_no_std_with_a_warning(tmp_path):
    v = next(v for v in GOOD if v.std_zero)
    frf = read_frf(write_variant(tmp_path / "f.h5", v))
    std, warnings = usable_std(frf)
    assert std is None and "estimated" in warnings[0]
    plain = read_frf(write_variant(tmp_path / "g.h5", GOOD[0]))
    std, warnings = usable_std(plain)
    assert std is plain.H_std and warnings == []


@pytest.mark.parametrize("variant", BAD, ids=[v.name for v in BAD])
def test_bad_file_exits_1_with_one_line_reason(tmp_path, capsys, variant):
    path = write_variant(tmp_path / "f.h5", variant)
    code = main(["gap", "diagnose", str(path), "--json", str(tmp_path / "o.json"),
                 "--no-plots"])
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert err.startswith("pelvislab gap diagnose: error:")
    assert not (tmp_path / "o.json").exists()


def test_transposed_positions_are_refused_not_reshaped(tmp_path):
    v = next(v for v in BAD if v.bad == "pos_transposed")
    with pytest.raises(FrfFileError, match=r"position_m has shape \(3, 7\)"):
        read_frf(write_variant(tmp_path / "f.h5", v))


def test_rounded_direction_renormalised_but_wrong_length_refused(tmp_path):
    v = next(v for v in GOOD if v.tilted_rounded)
    d = synthesise(v)
    frf = read_frf(write_variant(tmp_path / "f.h5", v, d))
    assert np.all(np.abs(np.linalg.norm(d["outs"].direction, axis=1) - 1) < 1e-3)
    np.testing.assert_allclose(np.linalg.norm(frf.outputs.direction, axis=1), 1.0)
    d["outs"].direction = 2 * d["outs"].direction
    with pytest.raises(FrfFileError, match="unit vectors"):
        read_frf(write_variant(tmp_path / "g.h5", dataclasses.replace(v), d))


def test_residual_map_columns_sit_at_their_frequency():
    from pelvislab.app.commands.gap import uniform_columns

    cols, f0, df = uniform_columns(np.arange(5.0, 200.5, 1.0))
    assert np.array_equal(cols, np.arange(196)) and (f0, df) == (5.0, 1.0)
    f = np.geomspace(5.0, 250.0, 180)  # log grid: line 90 is at ~36 Hz, not at ~127 Hz
    cols, f0, df = uniform_columns(f)
    centre = f0 + df * np.arange(cols.size)
    assert np.all(np.abs(f[cols] - centre) <= np.diff(f).max() / 2 + 1e-9)
    assert abs(centre[np.flatnonzero(cols == 90)].mean() - f[90]) < 0.5


def test_odd_schema_attribute_gives_a_clear_error(tmp_path):
    import h5py

    path = write_variant(tmp_path / "f.h5", GOOD[0])
    with h5py.File(path, "r+") as handle:
        handle["frf"].attrs["schema"] = ["pelvislab-frf", "pelvislab-session"]
    with pytest.raises(FrfFileError, match="has schema"):
        read_frf(path)
