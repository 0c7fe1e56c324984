"""import-uff: dataset 58 records that are no response over force in Hz (review of the EMA
path): an rpm abscissa was read as Hz, a force ordinate failed the whole import, and an
ordinate in g (accelerance in g/N) was read as m/s^2."""

from __future__ import annotations

import numpy as np
import pytest
import pyuff

from pelvislab.acquisition.uff import read_uff

F_HZ = np.arange(1.0, 21.0)
A = np.exp(1j * F_HZ / 5) * (1 + F_HZ / 10)  # an accelerance


def _write(path, records):
    """One ASCII dataset 58 per dict of overrides (node 1..n +Z over node 9 +Z)."""
    uff = pyuff.UFF(str(path))
    for k, extra in enumerate(records):
        fields = dict(func_type=4, rsp_node=k + 1, rsp_dir=3, ref_node=9, ref_dir=3,
                      abscissa_spacing=0, abscissa_spec_data_type=18,
                      ordinate_spec_data_type=12, orddenom_spec_data_type=13, x=F_HZ,
                      data=A, id1="other tool")
        fields.update(extra)
        uff.write_sets(pyuff.prepare_58(**fields), mode="overwrite" if k == 0 else "add")
    return path


def test_an_rpm_abscissa_is_skipped_with_a_note_not_read_as_hz(tmp_path):
    path = _write(tmp_path / "r.uff", [{}, {"abscissa_spec_data_type": 19,
                                           "abscissa_axis_units_lab": "rpm"}])
    frf, notes = read_uff(path)
    assert frf.outputs.name == ["node1+Z"]  # node 2's record is not imported
    assert any("node 2 / 9" in n and "rpm (specific data type 19)" in n
               and "not a frequency" in n for n in notes), notes


def test_a_file_of_order_records_only_is_refused_with_the_reason(tmp_path):
    path = _write(tmp_path / "o.uff", [{"abscissa_spec_data_type": 20}])
    with pytest.raises(ValueError, match=r"order \(specific data type 20\)"):
        read_uff(path)


@pytest.mark.parametrize("ordinate", [13, 9])
def test_a_force_ordinate_is_skipped_with_a_note_and_the_rest_imported(tmp_path, ordinate):
    path = _write(tmp_path / "f.uff", [{}, {"ordinate_spec_data_type": ordinate}, {}])
    frf, notes = read_uff(path)
    assert frf.outputs.name == ["node1+Z", "node3+Z"]
    assert any("node 2 / 9" in n and "force (specific data type" in n
               and "not a response" in n for n in notes), notes


@pytest.mark.parametrize("denominator", [12, 11, 8])
def test_a_transmissibility_is_skipped_with_a_note_not_read_as_receptance(tmp_path,
                                                                          denominator):
    """An acceleration over an acceleration was divided by -w^2 and imported as m/N, with
    only "taken as force" said (review 67)."""
    path = _write(tmp_path / "t.uff", [{}, {"orddenom_spec_data_type": denominator}])
    frf, notes = read_uff(path)
    assert frf.outputs.name == ["node1+Z"]
    assert any("node 2 / 9" in n and f"(specific data type {denominator}), not a force" in n
               for n in notes), notes


@pytest.mark.parametrize("denominator", [1, 9])
def test_a_denominator_left_open_or_a_reaction_force_is_taken_as_force(tmp_path,
                                                                       denominator):
    path = _write(tmp_path / "o.uff", [{"orddenom_spec_data_type": denominator}])
    frf, notes = read_uff(path)
    assert frf.outputs.name == ["node1+Z"]
    assert any(f"denominator type {denominator}, taken as force" in n for n in notes), notes


def test_accelerance_in_g_is_converted_with_standard_gravity(tmp_path):
    si = _write(tmp_path / "si.uff", [{"ordinate_axis_units_lab": "m/s^2"}])
    in_g = _write(tmp_path / "g.uff", [{"ordinate_axis_units_lab": "g"},
                                       {"ordinate_axis_units_lab": "G/N"}])
    H_si, _ = read_uff(si)
    H_g, notes = read_uff(in_g)
    np.testing.assert_allclose(H_g.H[:, 0, 0], H_si.H[:, 0, 0] * 9.80665,
                               rtol=1e-12)
    np.testing.assert_allclose(H_g.H[:, 1, 0], H_g.H[:, 0, 0], rtol=1e-12)
    assert any("2 record(s) in g" in n and "9.80665 m/s^2 per g" in n for n in notes), notes


@pytest.mark.parametrize("label, ordinate", [("g/lbf", 12), ("g", 8), ("g^2/Hz", 12)])
def test_a_g_label_that_cannot_be_read_reliably_is_skipped(tmp_path, label, ordinate):
    path = _write(tmp_path / "u.uff", [{}, {"ordinate_axis_units_lab": label,
                                           "ordinate_spec_data_type": ordinate}])
    frf, notes = read_uff(path)
    assert frf.outputs.name == ["node1+Z"]
    assert any("node 2 / 9" in n and repr(label) in n and "cannot be read reliably" in n
               for n in notes), notes


def test_two_nodes_given_one_name_are_kept_apart_and_said_so(tmp_path):
    """A points file naming nodes 1 and 2 alike renamed every output (node3+Z#3 too) and
    said nothing; only the shared name is numbered now, with a note (review 67)."""
    from pelvislab.acquisition.uff import read_points_file

    path = _write(tmp_path / "n.uff", [{}, {}, {}])
    (tmp_path / "p.toml").write_text('[[point]]\nnode = 1\nname = "a"\n'
                                     '[[point]]\nnode = 2\nname = "a"\n')
    frf, notes = read_uff(path, read_points_file(tmp_path / "p.toml"))
    assert frf.outputs.name == ["a+Z#1", "a+Z#2", "node3+Z"]
    assert any("output channel name(s) ['a+Z'] given to more than one node" in n
               for n in notes), notes
