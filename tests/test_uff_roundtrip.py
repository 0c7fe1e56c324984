"""UFF interchange (acquisition/uff.py): exact round trip, foreign files, conversions, modes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import pyuff
from hypothesis import given, settings
from hypothesis import strategies as st

from pelvislab.acquisition.frfset import Channels, FrfSet
from pelvislab.acquisition.uff import (
    UffModes,
    direction_code,
    read_points_file,
    read_uff,
    to_receptance,
    write_uff,
)

BEAM = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "real" / "pyuff_beam"


def sample_frfset(seed: int = 0) -> FrfSet:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(3, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[1] = [0.0, -1.0, 0.0]  # an axis direction: written as UFF code -2
    outputs = Channels(["SIAS_R", "PSIS L 2", "S3"], ["innominate_right", "innominate_left", ""],
                       rng.normal(size=(3, 3)) / 7, d)
    inputs = Channels(["SIAS_R", "shaker"], ["innominate_right", "sacrum"],
                      np.vstack([outputs.position_m[0], rng.normal(size=3)]),
                      np.array([d[0], [0.0, 0.0, 1.0]]))
    f = np.sort(rng.uniform(5, 300, 40))  # non-uniform stepped sine
    H = (rng.normal(size=(40, 3, 2)) + 1j * rng.normal(size=(40, 3, 2))) * 1e-6 / 3
    H[3, 1, 0] = H[7, 2, 1] = np.nan
    H[:, 2, 0] = np.nan  # one FRF never measured
    return FrfSet(f, H, outputs, inputs)


def test_round_trip_through_pyuff_is_exact(tmp_path):
    frf = sample_frfset()
    n_sets = write_uff(tmp_path / "s.uff", frf)
    types = list(pyuff.UFF(str(tmp_path / "s.uff")).get_set_types())
    assert types.count(58) == 5 and 2411 in types and 164 in types and n_sets == len(types)
    back, notes = read_uff(tmp_path / "s.uff")
    assert notes == []
    np.testing.assert_array_equal(back.frequency_hz, frf.frequency_hz)
    np.testing.assert_array_equal(back.H, frf.H)  # NaN in the same places, values bit-exact
    for a, b in ((back.outputs, frf.outputs), (back.inputs, frf.inputs)):
        assert a.name == b.name and a.bone == b.bone
        np.testing.assert_array_equal(a.position_m, b.position_m)
        np.testing.assert_array_equal(a.direction, b.direction)


def test_source_date_epoch_makes_exports_identical(tmp_path, monkeypatch):
    """Two exports of one FRF set differ only in dataset 151's dates; with
    SOURCE_DATE_EPOCH (reproducible-builds convention) they are byte for byte equal and
    carry that date (UTC)."""
    frf = sample_frfset()
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1795651200")  # 2026-11-26 00:00:00 UTC
    write_uff(tmp_path / "a.uff", frf)
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "1795651200")
    write_uff(tmp_path / "b.uff", frf)
    a = (tmp_path / "a.uff").read_bytes()
    assert a == (tmp_path / "b.uff").read_bytes()
    header = pyuff.UFF(str(tmp_path / "a.uff")).read_sets(0)
    assert header["type"] == 151
    assert header["date_db_created"] == "26-Nov-26"
    assert header["time_db_created"] == "00:00:00"
    assert a.count(b"26-Nov-26 00:00:00") == 3  # created, saved, written
    monkeypatch.setenv("SOURCE_DATE_EPOCH", "yesterday")
    with pytest.raises(ValueError, match="SOURCE_DATE_EPOCH"):
        write_uff(tmp_path / "c.uff", frf)


def test_ascii_and_dataset_15_are_close_not_exact(tmp_path):
    frf = sample_frfset(1)
    write_uff(tmp_path / "a.uff", frf, binary=False, geometry=15)
    assert 15 in list(pyuff.UFF(str(tmp_path / "a.uff")).get_set_types())
    back, _ = read_uff(tmp_path / "a.uff")
    np.testing.assert_allclose(back.H, frf.H, rtol=1e-10)
    np.testing.assert_allclose(back.outputs.position_m, frf.outputs.position_m, rtol=1e-4)


def test_refuses_overwrite_and_bad_geometry(tmp_path):
    (tmp_path / "x.uff").write_text("")
    with pytest.raises(FileExistsError):
        write_uff(tmp_path / "x.uff", sample_frfset())
    with pytest.raises(ValueError, match="15 or 2411"):
        write_uff(tmp_path / "y.uff", sample_frfset(), geometry=18)
    assert not (tmp_path / "y.uff").exists()


@pytest.mark.parametrize("binary", [True, False])
def test_truncated_file_is_refused_not_imported_in_part(tmp_path, binary):
    # pyuff drops a dataset cut short without a word: 1 of 8 FRFs was "imported"
    path = tmp_path / "s.uff"
    write_uff(path, sample_frfset(), binary=binary)
    data = path.read_bytes()
    cut = tmp_path / "cut.uff"
    cut.write_bytes(data[: int(len(data) * 0.6)])
    with pytest.raises(ValueError, match="ends inside a dataset"):
        read_uff(cut)
    frf, _notes = read_uff(path)  # the whole file still reads
    assert np.isfinite(frf.H).any()


@pytest.mark.parametrize("binary", [True, False])
def test_file_cut_at_any_dataset_boundary_is_refused(tmp_path, binary):
    """Cuts right after a delimiter line: after a dataset's closing line (UFF cannot tell that
    from a shorter file; our header dataset 151 counts the records) or after the next one's
    opening line (an odd number of delimiters). Both imported part of the file before."""
    from pelvislab.acquisition.uff import UffModes

    frf = sample_frfset()
    modes = UffModes(np.array([50.0, 80.0]), np.array([0.01, 0.02]),
                     np.ones((len(frf.outputs), 2), dtype=complex))
    path = tmp_path / "s.uff"
    write_uff(path, frf, modes, binary=binary)
    data = path.read_bytes()
    ends = [k + 7 for k in range(len(data)) if data.startswith(b"    -1\n", k)]
    assert len(ends) >= 2 * 8 and ends[-1] == len(data)
    for end in ends[:-1]:
        for cut in (end - 1, end):
            (tmp_path / "cut.uff").write_bytes(data[:cut])
            with pytest.raises(ValueError, match="truncated"):
                read_uff(tmp_path / "cut.uff")
    back, _ = read_uff(path)
    assert np.isfinite(back.H).sum() == np.isfinite(frf.H).sum()


def test_datasets_appended_after_our_export_are_imported_with_a_note(tmp_path):
    path = tmp_path / "s.uff"
    write_uff(path, sample_frfset())
    pyuff.UFF(str(path)).write_sets(pyuff.prepare_58(
        binary=0, id1="other tool", func_type=4, rsp_ent_name="other", ref_ent_name="other",
        rsp_node=1, rsp_dir=1, ref_node=1, ref_dir=1, abscissa_spacing=0,
        abscissa_spec_data_type=18, ordinate_spec_data_type=8, orddenom_spec_data_type=13,
        abscissa_axis_units_lab="Hz", ordinate_axis_units_lab="m", orddenom_axis_units_lab="N",
        x=np.array([10.0, 20.0, 30.0]), data=np.array([1 + 1j, 2 + 2j, 3 + 3j]) * 1e-6),
        mode="add")
    frf, notes = read_uff(path)
    assert np.isfinite(frf.H).any(axis=0).sum() == np.isfinite(sample_frfset().H).any(
        axis=0).sum() + 1
    assert any("more than the pelvislab header" in n for n in notes), notes


def test_direction_codes():
    assert direction_code(np.array([0.0, 0.0, -1.0])) == -3
    assert direction_code(np.array([1.0, 0.0, 0.0])) == 1
    assert direction_code(np.array([0.6, 0.8, 0.0])) == 0


def _foreign_uff(path: Path, quantity: int, values: np.ndarray, f: np.ndarray,
                 length_factor: float = 1000.0) -> None:
    """A UFF as another tool writes it: ASCII, even spacing, mm units, axis directions."""
    uff = pyuff.UFF(str(path))
    uff.write_sets(pyuff.prepare_164(units_code=5, units_description="mm (milli newton)",
                                     temp_mode=1, length=length_factor, force=1.0, temp=1.0,
                                     temp_offset=273.15), mode="overwrite")
    uff.write_sets(pyuff.prepare_2411(
        node_nums=np.array([1, 2, 7]), def_cs=np.zeros(3, int), disp_cs=np.zeros(3, int),
        color=np.ones(3, int), x=np.array([10.0, 20.0, 0.0]), y=np.array([0.0, 5.0, 0.0]),
        z=np.zeros(3)), mode="add")
    for k, node in enumerate((1, 2)):
        for direction in (3, -1):
            uff.write_sets(pyuff.prepare_58(
                func_type=4, rsp_node=node, rsp_dir=direction, ref_node=7, ref_dir=3,
                abscissa_spacing=1, abscissa_spec_data_type=18, ordinate_spec_data_type=quantity,
                orddenom_spec_data_type=13, x=f, data=values * (k + 1) * direction,
                id1="other tool"), mode="add")
    uff.write_sets(pyuff.prepare_58(func_type=6, rsp_node=1, rsp_dir=3, ref_node=7, ref_dir=3,
                                    abscissa_spacing=1, x=f, data=np.ones(f.size),
                                    abscissa_spec_data_type=18, ordinate_spec_data_type=0,
                                    orddenom_spec_data_type=0), mode="add")


def test_foreign_accelerance_in_mm_with_points_file(tmp_path):
    f = np.arange(0.0, 50.0, 0.5)
    A = np.exp(1j * f / 7) * (1 + f / 10)  # accelerance in (mm/s^2)/N
    _foreign_uff(tmp_path / "f.uff", 12, A, f)
    (tmp_path / "p.toml").write_text(
        '[[point]]\nnode = 1\nname = "SIAS_R"\nbone = "innominate_right"\n'
        '[[point]]\nnode = 7\nname = "drive"\nbone = "sacrum"\nposition_m = [0.5, 0.0, 0.1]\n'
    )
    frf, notes = read_uff(tmp_path / "f.uff", read_points_file(tmp_path / "p.toml"))
    assert any("function type 6" in n for n in notes)  # the coherence record is skipped
    # the conversion is said (it multiplies the lowest lines' noise: review, session 39)
    assert any("4 accelerance record(s) converted to receptance" in n for n in notes), notes
    assert frf.outputs.name == ["SIAS_R+Z", "SIAS_R-X", "node2+Z", "node2-X"]
    assert frf.outputs.bone == ["innominate_right", "innominate_right", "", ""]
    assert frf.inputs.name == ["drive+Z"] and frf.inputs.bone == ["sacrum"]
    np.testing.assert_allclose(frf.inputs.position_m[0], [0.5, 0.0, 0.1])
    np.testing.assert_allclose(frf.outputs.position_m[2], [0.020, 0.005, 0.0])  # mm -> m
    np.testing.assert_array_equal(frf.outputs.direction[1], [-1.0, 0.0, 0.0])
    w = 2 * np.pi * f[1:]
    expected = -(A[1:] * 2 * -1) / w**2 / 1000.0  # node 2, direction -1, mm -> m
    np.testing.assert_allclose(frf.H[1:, 3, 0], expected, rtol=1e-9)
    assert np.isnan(frf.H[0]).all()  # 0 Hz has no receptance from accelerance


def test_mobility_conversion():
    f = np.array([0.0, 1.0, 2.0])
    X = np.array([1.0, 2.0 + 1j, -1j])
    V = 1j * 2 * np.pi * f * X
    back = to_receptance(f, V, 11)
    assert np.isnan(back[0])
    np.testing.assert_allclose(back[1:], X[1:])
    with pytest.raises(ValueError, match="ordinate type"):
        to_receptance(f, V, 13)


def test_modes_written_as_dataset_55(tmp_path):
    frf = sample_frfset(2)
    shapes = np.array([[1.0, 0.2j], [0.5, 1.0], [-0.3 + 0.1j, 0.4]])
    write_uff(tmp_path / "m.uff", frf, UffModes(np.array([40.0, 120.0]), np.array([0.02, 0.1]),
                                                shapes))
    sets = pyuff.UFF(str(tmp_path / "m.uff")).read_sets()
    modes = [s for s in sets if s["type"] == 55]
    assert len(modes) == 2
    eig = modes[1]["eig"]
    assert abs(eig) == pytest.approx(2 * np.pi * 120.0, rel=1e-4)
    assert -eig.real / abs(eig) == pytest.approx(0.1, rel=1e-3)
    # node 1 (SIAS_R) is measured along one direction: vector = psi * d
    d = frf.outputs.direction[0]
    vec = np.array([modes[0]["r1"][0], modes[0]["r2"][0], modes[0]["r3"][0]])
    np.testing.assert_allclose(vec, shapes[0, 0] * d, atol=1e-4)


def test_a_shape_entry_not_known_leaves_its_node_out_of_dataset_55(tmp_path):
    # ema leaves an entry NaN where the FRF has no lines around the mode (a run stopped):
    # it was written as "nan" into the file (replay review, session 36)
    frf = sample_frfset(2)
    shapes = np.array([[1.0, 0.2j], [np.nan, 1.0], [-0.3 + 0.1j, 0.4]])
    write_uff(tmp_path / "m.uff", frf, UffModes(np.array([40.0, 120.0]), np.array([0.02, 0.1]),
                                                shapes))
    modes = [s for s in pyuff.UFF(str(tmp_path / "m.uff")).read_sets() if s["type"] == 55]
    full = modes[1]["node_nums"].tolist()
    assert len(modes[0]["node_nums"]) == len(full) - 1  # channel 1's node left out
    for m in modes:
        assert np.all(np.isfinite(m["r1"])) and np.all(np.isfinite(m["r2"]))


def test_errors_are_named(tmp_path):
    with pytest.raises(FileNotFoundError):
        read_uff(tmp_path / "none.uff")
    uff = pyuff.UFF(str(tmp_path / "g.uff"))
    uff.write_sets(pyuff.prepare_2411(node_nums=np.array([1]), def_cs=np.zeros(1, int),
                                      disp_cs=np.zeros(1, int), color=np.ones(1, int),
                                      x=np.zeros(1), y=np.zeros(1), z=np.zeros(1)),
                   mode="overwrite")
    with pytest.raises(ValueError, match="no dataset 58"):
        read_uff(tmp_path / "g.uff")
    (tmp_path / "p.toml").write_text('[[point]]\nnode = 1\nname = "a"\nbone = "femur"\n')
    with pytest.raises(ValueError, match="unknown bone"):
        read_points_file(tmp_path / "p.toml")


@pytest.mark.skipif(not BEAM.is_dir(), reason=f"real beam data not found at {BEAM}")
def test_real_beam_accelerance_imports_as_receptance(tmp_path):
    A = np.stack([np.loadtxt(BEAM / f"meas_point_{k}.txt", dtype=complex) for k in (1, 2, 3)])
    f = np.arange(A.shape[1], dtype=float)
    uff = pyuff.UFF(str(tmp_path / "beam.uff"))
    for k in range(3):
        uff.write_sets(pyuff.prepare_58(
            binary=1, func_type=4, rsp_node=k + 1, rsp_dir=3, ref_node=1, ref_dir=3,
            abscissa_spacing=0, abscissa_spec_data_type=18, ordinate_spec_data_type=12,
            orddenom_spec_data_type=13, x=f, data=A[k]), mode="add")  # binary 58: never overwrite
    frf, notes = read_uff(tmp_path / "beam.uff")
    assert frf.H.shape == (1001, 3, 1)
    assert any("no coordinates" in n for n in notes)
    w = 2 * np.pi * f[1:]
    np.testing.assert_allclose(frf.H[1:, :, 0], (-A[:, 1:] / w**2).T, rtol=1e-12)


_names = st.text(alphabet=st.characters(min_codepoint=33, max_codepoint=126), min_size=1,
                 max_size=20)


@settings(max_examples=8, deadline=None)
@given(n_out=st.integers(1, 4), n_in=st.integers(1, 2), n_f=st.integers(2, 12),
       seed=st.integers(0, 10_000), names=st.lists(_names, min_size=6, max_size=6, unique=True))
def test_round_trip_property(tmp_path_factory, n_out, n_in, n_f, seed, names):
    rng = np.random.default_rng(seed)
    bones = ["innominate_right", "innominate_left", "sacrum", ""]

    def channels(names_k):
        d = rng.normal(size=(len(names_k), 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        d[0] = np.eye(3)[seed % 3] * (-1) ** seed  # one axis direction
        return Channels(names_k, [bones[rng.integers(4)] for _ in names_k],
                        rng.normal(size=(len(names_k), 3)), d)

    out = channels(names[:n_out])
    inp = channels(names[4:4 + n_in])
    f = np.sort(rng.choice(np.linspace(0.5, 500.0, 1000), n_f, replace=False))
    H = rng.normal(size=(n_f, n_out, n_in)) + 1j * rng.normal(size=(n_f, n_out, n_in))
    H[rng.random(H.shape) < 0.2] = np.nan
    H[:, 0, 0] = 1e-7 * (1 + 1j)  # every line keeps at least one measured FRF
    # ... and every channel one measured value (a channel without any has no UFF record)
    H[0, :, 0] = np.where(np.isnan(H[0, :, 0]), 2e-7, H[0, :, 0])
    H[0, 0, :] = np.where(np.isnan(H[0, 0, :]), 3e-7, H[0, 0, :])
    frf = FrfSet(f, H, out, inp)
    path = tmp_path_factory.mktemp("prop") / "p.uff"
    write_uff(path, frf)
    back, _ = read_uff(path)
    np.testing.assert_array_equal(back.frequency_hz, f)
    np.testing.assert_array_equal(back.H, H)
    assert back.outputs.name == out.name and back.inputs.bone == inp.bone
    np.testing.assert_array_equal(back.outputs.direction, out.direction)
    np.testing.assert_array_equal(back.inputs.position_m, inp.position_m)


def test_unwritable_names_are_refused(tmp_path):
    frf = sample_frfset()
    frf.outputs.name[0] = " padded"
    with pytest.raises(ValueError, match="cannot be written"):
        write_uff(tmp_path / "n.uff", frf)


def test_channels_of_one_point_share_a_node(tmp_path):
    """+X and +Y of one point are one UFF node, and a drive point is the node of its
    response (what other modal tools need to see a point and a driving-point FRF); a
    direction off the axes keeps a node of its own; the re-import is unchanged."""
    p = np.array([0.1, -0.05, 0.02])
    q = np.array([-0.1, 0.0, 0.03])
    tilted = np.array([0.6, 0.8, 0.0])
    out = Channels(["A_x", "A_y", "A_t", "B_x"], ["sacrum"] * 4, np.array([p, p, p, q]),
                   np.array([[1.0, 0, 0], [0, 1.0, 0], tilted, [-1.0, 0, 0]]))
    inp = Channels(["A_x"], ["sacrum"], np.array([p]), np.array([[1.0, 0, 0]]))
    f = np.array([10.0, 20.0, 30.0])
    H = (np.arange(12).reshape(3, 4, 1) + 1) * (1 + 0.5j) * 1e-6
    path = tmp_path / "shared.uff"
    write_uff(path, FrfSet(f, H, out, inp))
    records = {r["id2"].split()[-1]: r for r in pyuff.UFF(str(path)).read_sets()
               if r["type"] == 58}
    node = {name: int(r["rsp_node"]) for name, r in records.items()}
    assert node["A_x"] == node["A_y"] != node["B_x"]
    assert node["A_t"] not in (node["A_x"], node["B_x"])
    assert {int(r["ref_node"]) for r in records.values()} == {node["A_x"]}  # driving point
    assert int(records["A_y"]["rsp_dir"]) == 2 and int(records["B_x"]["rsp_dir"]) == -1
    back, _ = read_uff(path)
    assert back.outputs.name == out.name and back.inputs.name == inp.name
    np.testing.assert_array_equal(back.H, H)
    np.testing.assert_array_equal(back.outputs.position_m, out.position_m)


def test_a_file_of_time_responses_is_refused_with_their_function_type(tmp_path):
    # "holds no dataset 58 FRF (set types: [58])" did not say why (review, session 39)
    uff = pyuff.UFF(str(tmp_path / "t.uff"))
    t = np.arange(0.0, 1.0, 0.01)
    uff.write_sets(pyuff.prepare_58(func_type=1, rsp_node=1, rsp_dir=3, ref_node=1,
                                    ref_dir=3, abscissa_spacing=1, x=t, data=np.sin(t),
                                    abscissa_spec_data_type=17, ordinate_spec_data_type=8,
                                    orddenom_spec_data_type=0), mode="overwrite")
    with pytest.raises(ValueError, match=r"function type 1, not 4 \(FRF\)"):
        read_uff(tmp_path / "t.uff")


def test_a_node_named_after_a_landmark_without_coordinates_takes_the_catalogues(tmp_path):
    # it was put at the origin, where identify would model it (first-day review, session 39)
    from pelvislab.acquisition.protocol import load_landmarks

    f = np.arange(1.0, 20.0, 1.0)
    uff = pyuff.UFF(str(tmp_path / "n.uff"))
    for node in (1, 2):
        uff.write_sets(pyuff.prepare_58(
            func_type=4, rsp_node=node, rsp_dir=1, ref_node=1, ref_dir=1, abscissa_spacing=1,
            abscissa_spec_data_type=18, ordinate_spec_data_type=8,
            orddenom_spec_data_type=13, x=f, data=np.exp(1j * f) * 1e-6),
            mode="overwrite" if node == 1 else "add")
    (tmp_path / "p.toml").write_text(
        '[[point]]\nnode = 1\nname = "SIPS_R_x"\nbone = "innominate_right"\n'
        '[[point]]\nnode = 2\nname = "somewhere"\n')
    frf, notes = read_uff(tmp_path / "n.uff", read_points_file(tmp_path / "p.toml"))
    catalogue = load_landmarks()
    np.testing.assert_allclose(frf.outputs.position_m[0], catalogue["SIPS_R_x"].position_m)
    np.testing.assert_allclose(frf.outputs.position_m[1], 0.0)
    assert any("node 1 (SIPS_R_x) has no coordinates; placed at the landmark catalogue"
               in n for n in notes), notes
    assert any("node 2 has no coordinates; placed at the origin" in n for n in notes), notes


def test_import_uff_reads_the_landmark_catalogue_once(tmp_path, monkeypatch):
    """The catalogue was parsed on every call, twice per record (output and input node):
    1200 records took 3.3 s instead of 0.18 s (helper review, session 39)."""
    from pelvislab.acquisition import protocol as protocol_module

    f = np.arange(1.0, 20.0)
    uff = pyuff.UFF(str(tmp_path / "n.uff"))
    uff.write_sets([pyuff.prepare_58(
        func_type=4, rsp_node=node, rsp_dir=d, ref_node=100, ref_dir=3, abscissa_spacing=1,
        abscissa_spec_data_type=18, ordinate_spec_data_type=8, orddenom_spec_data_type=13,
        x=f, data=np.exp(1j * f) * 1e-6) for node in (1, 2) for d in (1, 2, 3)],
        mode="overwrite")
    (tmp_path / "p.toml").write_text(
        '[[point]]\nnode = 1\nname = "SIPS_R_x"\n[[point]]\nnode = 2\nname = "sacrum_x"\n'
        '[[point]]\nnode = 100\nname = "drive"\n')
    calls = []
    original = protocol_module.load_landmarks
    monkeypatch.setattr(protocol_module, "load_landmarks",
                        lambda *a, **k: calls.append(1) or original(*a, **k))
    read_uff(tmp_path / "n.uff", read_points_file(tmp_path / "p.toml"))
    assert len(calls) <= 1, f"the catalogue was parsed {len(calls)} times for 6 records"


def test_an_frf_record_of_real_values_is_skipped_not_read_as_zero_phase(tmp_path):
    # a magnitude written as function type 4 was imported as an FRF of zero phase, silently
    # (review of the EMA path): every EMA of it was wrong
    f = np.arange(1.0, 50.0)
    X = 1.0 / (1e4 - (2 * np.pi * f) ** 2 + 10j * 2 * np.pi * f)

    def frf_record(data: np.ndarray, node: int) -> dict:
        return pyuff.prepare_58(binary=1, func_type=4, rsp_node=node, rsp_dir=3, ref_node=1,
                                ref_dir=3, abscissa_spacing=0, abscissa_spec_data_type=18,
                                ordinate_spec_data_type=8, orddenom_spec_data_type=13,
                                x=f, data=data)

    only_real = pyuff.UFF(str(tmp_path / "r.uff"))
    only_real.write_sets(frf_record(np.abs(X), 2), mode="add")
    with pytest.raises(ValueError, match=r"1 FRF record\(s\) hold real values"):
        read_uff(tmp_path / "r.uff")
    mixed = pyuff.UFF(str(tmp_path / "m.uff"))
    mixed.write_sets(frf_record(X, 1), mode="add")
    mixed.write_sets(frf_record(np.abs(X), 2), mode="add")
    frf, notes = read_uff(tmp_path / "m.uff")
    assert frf.outputs.name == ["node1+Z"]
    np.testing.assert_array_equal(frf.H[:, 0, 0], X)
    assert any("FRF with real values (node 2 / 1)" in n for n in notes), notes


def test_two_records_of_one_frf_with_other_values_are_named(tmp_path):
    # a repeated measurement (or overlapping bands) of one FRF: the later record replaced
    # the earlier's values without a word (review of the EMA path)
    f = np.arange(1.0, 50.0)
    X = 1.0 / (1e4 - (2 * np.pi * f) ** 2 + 10j * 2 * np.pi * f)
    uff = pyuff.UFF(str(tmp_path / "d.uff"))
    for data, x in ((X, f), (2 * X[10:], f[10:]), (X[:5], f[:5])):
        uff.write_sets(pyuff.prepare_58(
            binary=1, func_type=4, rsp_node=1, rsp_dir=3, ref_node=1, ref_dir=3,
            abscissa_spacing=0, abscissa_spec_data_type=18, ordinate_spec_data_type=8,
            orddenom_spec_data_type=13, x=x, data=data), mode="add")
    frf, notes = read_uff(tmp_path / "d.uff")
    np.testing.assert_array_equal(frf.H[10:, 0, 0], 2 * X[10:])  # the last record read
    hits = [n for n in notes if "given more than once" in n]
    assert len(hits) == 1 and "node1+Z/node1+Z" in hits[0] and "at 39 line(s)" in hits[0]
