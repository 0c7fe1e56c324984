"""import-uff: dataset 58 records that are no response over force in Hz (review of the EMA
path): an rpm abscissa was read as Hz, and a force ordinate failed the whole import."""

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
