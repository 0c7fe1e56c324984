"""The FRF set of design 4.2 (``/frf``): an in-memory container and its HDF5 reader/writer.

This is the one place that knows the ``/frf`` layout; session files, FRF-only files, UFF
import and every consumer (identification, EMA, gap diagnosis) go through it.
Receptance in m/N, SI units throughout.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

FRF_SCHEMA = "pelvislab-frf"
FRF_SCHEMA_VERSION = 1
BONES = ("innominate_right", "innominate_left", "sacrum", "")


class FrfFileError(ValueError):
    """A file or group that does not hold a valid /frf set; the message names what is wrong."""


@dataclass
class Channels:
    """Named measurement or excitation points: bone, position (m, model frame), unit direction."""

    name: list[str]
    bone: list[str]
    position_m: np.ndarray  # (n, 3)
    direction: np.ndarray  # (n, 3), unit vectors

    def __post_init__(self) -> None:
        self.name = [str(n) for n in self.name]
        self.bone = [str(b) for b in self.bone]
        self.position_m = np.asarray(self.position_m, dtype=float).reshape(-1, 3)
        self.direction = np.asarray(self.direction, dtype=float).reshape(-1, 3)
        n = len(self.name)
        if not (len(self.bone) == n == self.position_m.shape[0] == self.direction.shape[0]):
            raise FrfFileError(
                f"channel arrays disagree: {n} names, {len(self.bone)} bones, "
                f"{self.position_m.shape[0]} positions, {self.direction.shape[0]} directions"
            )
        if len(set(self.name)) != n:
            raise FrfFileError(f"channel names are not unique: {self.name}")
        unknown = sorted(set(self.bone) - set(BONES))
        if unknown:
            raise FrfFileError(f"unknown bone(s) {unknown}; expected one of {list(BONES)}")
        norms = np.linalg.norm(self.direction, axis=1)
        if n and not np.allclose(norms, 1.0, atol=1e-6):
            raise FrfFileError(f"channel directions must be unit vectors (norms {norms})")

    def __len__(self) -> int:
        return len(self.name)

    def index(self, name: str) -> int:
        """Position of the channel called ``name``."""
        try:
            return self.name.index(name)
        except ValueError:
            raise KeyError(f"no channel named {name!r}; have {self.name}") from None

    def subset(self, indices: list[int] | np.ndarray) -> Channels:
        """The channels at ``indices``, in that order."""
        idx = list(np.asarray(indices, dtype=int))
        return Channels(
            [self.name[i] for i in idx], [self.bone[i] for i in idx],
            self.position_m[idx], self.direction[idx],
        )


@dataclass
class FrfSet:
    """Receptance FRFs ``H[f, out, in]`` (m/N) with optional standard uncertainty and times."""

    frequency_hz: np.ndarray  # (n_f,)
    H: np.ndarray  # (n_f, n_out, n_in) complex; NaN where not measured
    outputs: Channels
    inputs: Channels
    H_std: np.ndarray | None = None  # (n_f, n_out, n_in) float
    acquired_at_s: np.ndarray | None = None  # (n_f,)
    attrs: dict[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.frequency_hz = np.asarray(self.frequency_hz, dtype=float).reshape(-1)
        self.H = np.asarray(self.H, dtype=complex)
        n_f = self.frequency_hz.size
        expected = (n_f, len(self.outputs), len(self.inputs))
        if self.H.shape != expected:
            raise FrfFileError(
                f"H has shape {self.H.shape}, expected (n_f, n_out, n_in) = {expected}"
            )
        if np.any(~np.isfinite(self.frequency_hz)) or np.any(self.frequency_hz < 0):
            raise FrfFileError("frequency_hz must be finite and non-negative")
        if n_f > 1 and np.any(np.diff(self.frequency_hz) <= 0):
            raise FrfFileError("frequency_hz must be strictly increasing")
        if self.H_std is not None:
            self.H_std = np.asarray(self.H_std, dtype=float)
            if self.H_std.shape != expected:
                raise FrfFileError(f"H_std has shape {self.H_std.shape}, expected {expected}")
        if self.acquired_at_s is not None:
            self.acquired_at_s = np.asarray(self.acquired_at_s, dtype=float).reshape(-1)
            if self.acquired_at_s.shape != (n_f,):
                raise FrfFileError(
                    f"acquired_at_s has {self.acquired_at_s.size} values, expected {n_f}"
                )

    @property
    def measured(self) -> np.ndarray:
        """Boolean mask (n_f, n_out, n_in) of the lines that hold a measurement."""
        return np.isfinite(self.H)


def _write_channels(group: h5py.Group, channels: Channels) -> None:
    text = h5py.string_dtype()
    group.create_dataset("name", data=np.array(channels.name, dtype=object), dtype=text)
    group.create_dataset("bone", data=np.array(channels.bone, dtype=object), dtype=text)
    group.create_dataset("position_m", data=channels.position_m)
    group.create_dataset("direction", data=channels.direction)


def write_frf(target: h5py.File | h5py.Group | str | Path, frf: FrfSet, name: str = "frf") -> None:
    """Write ``frf`` as the group ``name`` (default ``/frf``) of an open file/group or a new file.

    An existing group of that name is replaced, so a session's FRF can be rewritten as lines
    are added. When given a path, the file is created (an FRF-only file) and must not exist;
    it appears under that name only once complete.
    """
    if isinstance(target, (str, Path)):
        import os
        import secrets

        from pelvislab.acquisition.session import (
            WriteRefusedError,
            fsync_path,
            publish_new_file,
            refused_write_text,
        )

        path = Path(target)
        if path.exists():
            raise FileExistsError(f"{path} exists; not overwriting")
        # Built in memory, then written as plain bytes: a write the disk refuses (full, a
        # quota, ulimit -f) is an ordinary OSError. Built on disk, HDF5 crashed inside its
        # flush or close after such a write, or dropped it and the file was published with
        # zeros for data (review, session 51). An FRF file is a few MB at most.
        memory = h5py.File(f"{path.name}.in-memory", "w", driver="core", backing_store=False)
        try:
            memory.attrs["schema"] = FRF_SCHEMA
            memory.attrs["schema_version"] = FRF_SCHEMA_VERSION
            write_frf(memory, frf, name)
            memory.flush()
            image = memory.id.get_file_image()
        finally:
            memory.close()
        # written under a hidden name and published complete: an interrupted write leaves
        # no half file under the real name, and a file that appears meanwhile is kept
        tmp = path.parent / f".{path.name}.{os.getpid()}.{secrets.token_hex(4)}.tmp"
        try:
            try:
                fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
                try:
                    view = memoryview(image)
                    while view:
                        view = view[os.write(fd, view):]
                finally:
                    os.close(fd)
                fsync_path(tmp)
            except OSError as exc:
                raise WriteRefusedError(exc.errno, refused_write_text(path, exc)) from None
            publish_new_file(tmp, path)
        finally:
            tmp.unlink(missing_ok=True)
        return
    if name in target:
        del target[name]
    group = target.create_group(name)
    group.attrs["schema"] = FRF_SCHEMA
    group.attrs["schema_version"] = FRF_SCHEMA_VERSION
    group.attrs["units"] = "m/N"
    for key, value in frf.attrs.items():
        if key not in ("schema", "schema_version", "units"):
            group.attrs[key] = value
    group.create_dataset("frequency_hz", data=frf.frequency_hz)
    group.create_dataset("H", data=frf.H.astype(np.complex128))
    if frf.H_std is not None:
        group.create_dataset("H_std", data=frf.H_std)
    if frf.acquired_at_s is not None:
        group.create_dataset("acquired_at_s", data=frf.acquired_at_s)
    _write_channels(group.create_group("outputs"), frf.outputs)
    _write_channels(group.create_group("inputs"), frf.inputs)


def _read_strings(dataset: h5py.Dataset) -> list[str]:
    """Names/bones as str, whatever string layout the writer chose: variable- or
    fixed-length, ASCII or UTF-8, bytes or str (fixed-length padding removed)."""
    values = np.asarray(dataset[()]).reshape(-1)
    return [(v.decode("utf-8", "replace") if isinstance(v, bytes) else str(v)).strip(" \x00")
            for v in values]


def _scalar_attr(value: object) -> object:
    """An attribute as a python scalar: bytes decoded, one-element arrays unwrapped (writers
    differ: str or bytes, numpy or python scalars, fixed- or variable-length strings)."""
    if isinstance(value, np.ndarray):
        if value.size != 1:
            return value
        value = value.reshape(-1)[0]
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace").strip(" \x00")
    if isinstance(value, np.generic):
        return value.item()
    return value


def _dataset(group: h5py.Group, name: str) -> h5py.Dataset:
    try:
        item = group[name]
    except KeyError:
        raise FrfFileError(f"{group.name} lacks the required dataset {name!r}") from None
    if not isinstance(item, h5py.Dataset):
        raise FrfFileError(f"{group.name}/{name} is a group, expected a dataset")
    return item


def _real_array(group: h5py.Group, name: str) -> np.ndarray:
    """The dataset ``name`` of ``group`` as float64; a dataset of another kind (strings, a
    compound) is refused with its name rather than numpy's conversion error."""
    dataset = _dataset(group, name)
    if dataset.dtype.kind not in "biuf":
        raise FrfFileError(f"{group.name}/{name} holds {dataset.dtype} values, expected "
                           "real numbers")
    return np.asarray(dataset[()], dtype=float)


def _read_complex(dataset: h5py.Dataset) -> np.ndarray:
    """``H`` (design 4.2: complex128). HDF5 has no complex type: writers store a compound of
    two floats, h5py as ("r", "i"), other tools as ("real", "imag"), ("re", "im") ...; a
    two-float compound is read as real, imaginary in field order. Real data is refused (a
    receptance is complex; a dropped imaginary part would be read as phase 0)."""
    data = dataset[()]
    dtype = data.dtype
    if dtype.names is not None:
        fields = [dtype.fields[n][0] for n in dtype.names]
        if len(fields) == 2 and all(f.kind == "f" and f.shape == () for f in fields):
            return data[dtype.names[0]] + 1j * data[dtype.names[1]].astype(np.float64)
        raise FrfFileError(f"{dataset.name} is a compound {dtype}; expected complex128 "
                           "(a compound of two floats: real, imaginary)")
    if dtype.kind != "c":
        raise FrfFileError(f"{dataset.name} has type {dtype} {data.shape}; design 4.2 stores "
                           "H as complex128 (n_f, n_out, n_in)")
    return data.astype(np.complex128)


def _read_channels(group: h5py.Group, where: str) -> Channels:
    if not isinstance(group, h5py.Group):
        raise FrfFileError(f"{where} is a dataset, expected a group")
    names = _read_strings(_dataset(group, "name"))
    n = len(names)
    arrays = {}
    for key in ("position_m", "direction"):
        a = np.asarray(_dataset(group, key)[()], dtype=float)
        if a.shape != (n, 3):  # a transposed (3, n) array must not be silently reshaped
            raise FrfFileError(f"{where}/{key} has shape {a.shape}, expected (n, 3) = ({n}, 3)")
        arrays[key] = a
    direction = arrays["direction"]
    # rounded on writing (e.g. 0.866): renormalise rows within 1e-3 of unit length that
    # Channels (1e-6) would refuse; exact unit vectors are kept bit for bit
    off = np.abs(np.linalg.norm(direction, axis=1) - 1.0)
    rounded = (off > 1e-6) & (off < 1e-3)
    if rounded.any():
        direction = direction.copy()
        direction[rounded] /= np.linalg.norm(direction[rounded], axis=1)[:, None]
    return Channels(names, _read_strings(_dataset(group, "bone")), arrays["position_m"], direction)


def read_frf_group(group: h5py.Group) -> FrfSet:
    """Read an open ``/frf`` group, checking its schema and version.

    Accepts what design 4.2 leaves to the writer: string and scalar attribute types,
    fixed/variable-length strings, float32 arrays, complex stored under other field names,
    extra attributes/datasets/groups (ignored), and frequency lines in any order (a
    downward sweep written in acquisition order; sorted here, with every per-line array).
    """
    if not isinstance(group, h5py.Group):
        raise FrfFileError(f"{group.name} is a dataset, expected the FRF group of design 4.2")
    schema = _scalar_attr(group.attrs.get("schema"))
    if not isinstance(schema, str) or schema != FRF_SCHEMA:
        raise FrfFileError(f"{group.name} has schema {schema!r}, expected {FRF_SCHEMA!r}")
    raw_version = _scalar_attr(group.attrs.get("schema_version", -1))
    try:
        version = int(raw_version)  # type: ignore[call-overload]
    except (TypeError, ValueError):
        version = -1
    if version != FRF_SCHEMA_VERSION:
        raise FrfFileError(f"{group.name} has schema_version {raw_version}; this pelvislab "
                           f"reads {FRF_SCHEMA_VERSION}")
    units = _scalar_attr(group.attrs.get("units", "m/N"))
    if not isinstance(units, str) or units.replace(" ", "") not in ("m/N", "m.N^-1", "mN^-1"):
        # every consumer takes H as receptance (design 4.1); a mobility or accelerance
        # would be identified, fitted and diagnosed as a wrong receptance without a word
        raise FrfFileError(f"{group.name} has units {units!r}; pelvislab reads receptance "
                           "in m/N (design 4.2): convert the FRFs first")
    frequency = _real_array(group, "frequency_hz").reshape(-1)
    H = _read_complex(_dataset(group, "H"))
    attrs = {k: group.attrs[k] for k in group.attrs if k not in ("schema", "schema_version")}
    for name in ("outputs", "inputs"):
        if name not in group:
            raise FrfFileError(f"{group.name} lacks the group {name!r}")
    H_std = _real_array(group, "H_std") if "H_std" in group else None
    acquired = (_real_array(group, "acquired_at_s").reshape(-1)
                if "acquired_at_s" in group else None)
    if frequency.size > 1 and frequency.size == H.shape[0] and np.all(np.isfinite(frequency)):
        order = np.argsort(frequency, kind="stable")
        if np.any(np.diff(frequency[order]) == 0):
            raise FrfFileError(f"{group.name}/frequency_hz holds a frequency twice")
        if np.any(order != np.arange(frequency.size)):
            frequency, H = frequency[order], H[order]
            if H_std is not None and H_std.shape[:1] == order.shape:
                H_std = H_std[order]
            if acquired is not None and acquired.shape == order.shape:
                acquired = acquired[order]
    return FrfSet(
        frequency_hz=frequency,
        H=H,
        outputs=_read_channels(group["outputs"], f"{group.name}/outputs"),
        inputs=_read_channels(group["inputs"], f"{group.name}/inputs"),
        H_std=H_std,
        acquired_at_s=acquired,
        attrs=attrs,
    )


def existing_file(path: str | Path) -> Path:
    """``path`` as a Path when it names an existing file; IsADirectoryError for a folder,
    FileNotFoundError otherwise (one line each)."""
    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder, not a session or FRF file")
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    return path


def read_frf(path: str | Path, name: str = "frf") -> FrfSet:
    """Read the FRF set of a session or FRF-only file; clear errors for anything else."""
    path = existing_file(path)
    try:
        handle = h5py.File(path, "r")
    except OSError as exc:
        reason = " ".join(str(exc).split())[:160]
        if "unable to lock file" in reason.lower():  # HDF5's lock: a writer has it open
            # (said "not a readable HDF5 file", as if damaged: replay review, session 36)
            raise FrfFileError(f"{path} is in use by another process (a run in progress?); "
                               f"try again when it has finished: {reason}") from None
        raise FrfFileError(f"{path} is not a readable HDF5 file ({reason})") from None
    with handle:
        if name not in handle:
            raise FrfFileError(f"{path} holds no /{name} group (no FRFs measured yet?)")
        if not isinstance(handle[name], h5py.Group):
            raise FrfFileError(f"{path}: /{name} is a dataset, expected the group of design 4.2")
        try:
            return read_frf_group(handle[name])
        except FrfFileError as exc:  # say which file: the group's own messages cannot
            raise FrfFileError(f"{path}: {exc}") from None
