"""Round trip and validation of the /frf container (design 4.2)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest

from pelvislab.acquisition.frfset import Channels, FrfFileError, FrfSet, read_frf, write_frf


def _channels(n: int, prefix: str) -> Channels:
    rng = np.random.default_rng(n)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return Channels([f"{prefix}{i}" for i in range(n)], ["sacrum"] * n, rng.normal(size=(n, 3)), d)


def _frfset() -> FrfSet:
    rng = np.random.default_rng(1)
    f = np.linspace(5, 300, 7)
    H = rng.normal(size=(7, 3, 2)) + 1j * rng.normal(size=(7, 3, 2))
    H[2, 1, 0] = np.nan
    return FrfSet(f, H, _channels(3, "o"), _channels(2, "i"), H_std=np.abs(H.real) * 0.1,
                  acquired_at_s=np.arange(7.0))


def test_round_trip_is_exact(tmp_path):
    frf = _frfset()
    write_frf(tmp_path / "f.h5", frf)
    back = read_frf(tmp_path / "f.h5")
    np.testing.assert_array_equal(back.H, frf.H)
    np.testing.assert_array_equal(back.H_std, frf.H_std)
    np.testing.assert_array_equal(back.frequency_hz, frf.frequency_hz)
    assert back.outputs.name == frf.outputs.name
    np.testing.assert_array_equal(back.inputs.direction, frf.inputs.direction)
    assert back.measured.sum() == frf.H.size - 1


def test_refuses_to_overwrite(tmp_path):
    write_frf(tmp_path / "f.h5", _frfset())
    with pytest.raises(FileExistsError):
        write_frf(tmp_path / "f.h5", _frfset())


def test_wrong_schema_version_is_named(tmp_path):
    write_frf(tmp_path / "f.h5", _frfset())
    with h5py.File(tmp_path / "f.h5", "a") as h:
        h["frf"].attrs["schema_version"] = 99
    with pytest.raises(FrfFileError, match="schema_version 99"):
        read_frf(tmp_path / "f.h5")


def test_truncated_file_gives_clear_error(tmp_path):
    write_frf(tmp_path / "f.h5", _frfset())
    data = (tmp_path / "f.h5").read_bytes()
    (tmp_path / "t.h5").write_bytes(data[: len(data) // 3])
    with pytest.raises((FrfFileError, OSError)):
        read_frf(tmp_path / "t.h5")


def test_shape_mismatch_rejected():
    frf = _frfset()
    with pytest.raises(FrfFileError, match="H has shape"):
        FrfSet(frf.frequency_hz[:-1], frf.H, frf.outputs, frf.inputs)


def test_non_unit_direction_rejected():
    with pytest.raises(FrfFileError, match="unit vectors"):
        Channels(["a"], ["sacrum"], [[0, 0, 0]], [[0, 0, 2.0]])


@pytest.mark.parametrize("name", ["frequency_hz", "H_std", "acquired_at_s"])
def test_a_dataset_of_text_is_named_not_a_conversion_error(tmp_path, name):
    # helper review, session 34: "could not convert string to float: np.bytes_(b'a')"
    write_frf(tmp_path / "f.h5", _frfset())
    with h5py.File(tmp_path / "f.h5", "a") as h:
        shape = h["frf"][name].shape
        del h["frf"][name]
        h["frf"].create_dataset(name, data=np.full(shape, b"a"))
    with pytest.raises(FrfFileError, match=f"/frf/{name} holds .* values, expected real"):
        read_frf(tmp_path / "f.h5")
