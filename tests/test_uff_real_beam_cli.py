"""CLI UFF round trip on real measured data: the pyuff beam accelerances (third-party).

A foreign file as another modal tool writes it (binary 58 accelerance, no geometry dataset,
response directions +X, -Y and scalar) -> ``pelvislab import-uff --points`` -> ``export-uff``
(binary; ASCII with dataset 15) -> ``import-uff`` again: the receptance, names, bones,
directions and positions survive; the 0 Hz line (no receptance from accelerance) is left out.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import pyuff

from pelvislab.acquisition.frfset import read_frf
from pelvislab.app.cli import main

BEAM = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "pyuff_beam"
pytestmark = pytest.mark.skipif(
    not BEAM.is_dir(), reason=f"real beam data not found at {BEAM} (shared/ beside the clone)"
)

POINTS = """
[[point]]
node = 1
name = "tip"
bone = "sacrum"
[[point]]
node = 2
name = "mid"
bone = "innominate_left"
position_m = [0.0, 0.25, 0.01]
"""


def test_foreign_beam_uff_round_trips_through_the_cli(tmp_path, capsys):
    A = np.stack([np.loadtxt(BEAM / f"meas_point_{k}.txt", dtype=complex) for k in (1, 2, 3)])
    f = np.arange(A.shape[1], dtype=float)
    uff = pyuff.UFF(str(tmp_path / "beam.uff"))
    for k, rsp_dir in enumerate((1, -2, 0)):
        uff.write_sets(pyuff.prepare_58(
            binary=1, func_type=4, rsp_node=k + 1, rsp_dir=rsp_dir, ref_node=1, ref_dir=3,
            abscissa_spacing=0, abscissa_spec_data_type=18, ordinate_spec_data_type=12,
            orddenom_spec_data_type=13, x=f, data=A[k]), mode="add")
    (tmp_path / "p.toml").write_text(POINTS)
    argv = ["import-uff", str(tmp_path / "beam.uff"), "--out", str(tmp_path / "a.h5"),
            "--points", str(tmp_path / "p.toml")]
    assert main(argv) == 0
    err = capsys.readouterr().err
    # nodes 1 and 3 have no coordinates (node 2's come from the points file): one note each
    assert err.count("has no coordinates") == 2, err
    assert "scalar (direction 0) records taken as +Z" in err
    a = read_frf(tmp_path / "a.h5")
    assert a.outputs.name == ["tip+X", "mid-Y", "node3"] and a.inputs.name == ["tip+Z"]
    assert a.outputs.bone == ["sacrum", "innominate_left", ""]
    np.testing.assert_array_equal(a.outputs.direction, [[1, 0, 0], [0, -1, 0], [0, 0, 1]])
    np.testing.assert_array_equal(a.outputs.position_m[1], [0.0, 0.25, 0.01])
    w = 2 * np.pi * f[1:]
    np.testing.assert_allclose(a.H[1:, :, 0], (-A[:, 1:] / w**2).T, rtol=1e-12)
    assert np.isnan(a.H[0]).all()

    for extra, exact in (([], True), (["--ascii", "--geometry", "15"], False)):
        tag = "ascii" if extra else "bin"
        out, back = tmp_path / f"{tag}.uff", tmp_path / f"{tag}.h5"
        assert main(["export-uff", str(tmp_path / "a.h5"), str(out), *extra]) == 0
        assert main(["import-uff", str(out), "--out", str(back)]) == 0
        b = read_frf(back)
        np.testing.assert_array_equal(b.frequency_hz, f[1:])  # 0 Hz: nothing measured
        if exact:
            np.testing.assert_array_equal(b.H, a.H[1:])
        else:  # ASCII 58: 12 significant digits
            np.testing.assert_allclose(b.H, a.H[1:], rtol=1e-11)
        for old, new in ((a.outputs, b.outputs), (a.inputs, b.inputs)):
            assert new.name == old.name and new.bone == old.bone
            np.testing.assert_array_equal(new.direction, old.direction)
            np.testing.assert_allclose(new.position_m, old.position_m, atol=1e-6)
