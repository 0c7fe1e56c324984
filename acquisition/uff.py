"""Universal File Format (UFF) interchange of FRF sets with other modal tools, through pyuff.

Export (:func:`write_uff`): dataset 164 (SI units), the measurement points as nodes in dataset
2411 (double precision; or 15; channels at one point along the global axes share its node,
a direction off the axes gets a node of its own), one dataset 58 per measured FRF (function
type 4, receptance: ordinate displacement over force), and optionally identified modes as
dataset 55 (complex modes, one per mode, node vectors in the global frame).

Import (:func:`read_uff`): every dataset 58 of FRF type (function type 4 or 0 "general",
with complex data: a record of real values, a magnitude, is skipped with a note), whatever
its response quantity: displacement (receptance), velocity (mobility) or acceleration
(accelerance) over force; mobility and accelerance are converted to receptance
(``X = V / (i w) = -A / w^2``; the 0 Hz line becomes NaN). Records on different abscissae
are merged on the union grid, NaN where a record has no line. Node coordinates from
2411 or 15 (converted to metres with dataset 164's length factor); nodes are named and mapped to
bones by an optional points file (:func:`read_points_file`), else ``node<N>`` with bone ``""``.

Exact round trip. pelvislab writes binary 58 ("58b", IEEE doubles, uneven abscissa) and 2411
(``%25.16e``), so frequencies, FRF values and positions come back bit for bit. UFF can only
name a measurement direction as +/-X, Y, Z: an axis direction is written that way, any other
as 0 (scalar), and the exact unit vector, channel name and bone ride in the ID lines of each 58
record (``id2``/``id3`` "out|in <bone> <name>", ``id4``/``id5`` "do|di <dx> <dy> <dz>"), which
pelvislab reads back. Not carried: ``H_std``, ``acquired_at_s``, and frequency lines where no
FRF was measured (UFF readers turn NaN into 0, so unmeasured lines are left out of each record).
"""

from __future__ import annotations

import os
import re
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pelvislab.acquisition.frfset import BONES, Channels, FrfSet

MARKER = "pelvislab FRF receptance m/N"
# dataset 151 (header) description of our exports: how many records the file holds, so that
# a file cut between two datasets, which UFF itself cannot tell from a shorter one, is refused
HEADER_PREFIX = "pelvislab export:"
HEADER_PATTERN = re.compile(r"pelvislab export: (\d+) FRF records?, (\d+) modes?")
FUNC_GENERAL = 0
FUNC_FRF = 4
# dataset 58 "specific data type" codes (UFF 58 record 8-11)
SPEC_FREQUENCY = 18
SPEC_DISPLACEMENT = 8
SPEC_VELOCITY = 11
SPEC_ACCELERATION = 12
SPEC_FORCE = 13
# what the other codes of UFF 58 record 8 (specific data type) are, for the notes
SPEC_NAMES = {0: "unknown", 1: "general", 2: "stress", 3: "strain", 5: "temperature",
              6: "heat flux", 8: "displacement", 9: "reaction force", 11: "velocity",
              12: "acceleration", 13: "excitation force", 15: "pressure", 16: "mass",
              17: "time", 18: "frequency", 19: "rpm", 20: "order"}
# abscissae read as frequencies in Hz: frequency, or a type the file leaves open
FREQUENCY_ABSCISSAE = (0, 1, SPEC_FREQUENCY)
# ordinates that are responses (0 "unknown" is taken as displacement, as before)
RESPONSE_ORDINATES = (0, SPEC_DISPLACEMENT, SPEC_VELOCITY, SPEC_ACCELERATION)
# denominators read as force: excitation or reaction force, or a type the file leaves open
# (unknown: silently, as before; general and reaction force with a note)
FORCE_DENOMINATORS = (0, 1, 9, SPEC_FORCE)
STANDARD_GRAVITY_M_S2 = 9.80665  # m/s^2 per g (3rd CGPM, 1901; ISO 80000-3)
AXES = np.eye(3)


@dataclass
class UffModes:
    """Modes to export as dataset 55: per mode a frequency, damping and complex channel shape."""

    frequency_hz: np.ndarray  # (n_modes,) undamped natural frequency
    damping_ratio: np.ndarray  # (n_modes,)
    shapes: np.ndarray  # (n_out, n_modes) complex, at the FRF set's outputs


@dataclass
class PointInfo:
    """What a points file says about one UFF node."""

    name: str
    bone: str = ""
    position_m: np.ndarray | None = None


def read_points_file(path: str | Path) -> dict[int, PointInfo]:
    """Read a points file mapping UFF node numbers to landmark names and bones.

    TOML, one table per node::

        [[point]]
        node = 12
        name = "SIAS_R"              # landmark / channel base name
        bone = "innominate_right"    # one of the design-4.1 bones, or "" (default)
        position_m = [0.0, -0.12, 0.0]   # optional: overrides the UFF coordinates

    A node without ``position_m`` keeps its UFF coordinates; without those either, a name
    of the landmark catalogue (``SIAS_R_x``, or ``SIAS_R`` when ``SIAS_R_x/_y/_z`` share a
    position) gives the catalogue's position, else the origin (each said in a note).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no such points file: {path}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as exc:
        raise ValueError(f"{path} is not valid TOML: {exc}") from None
    points: dict[int, PointInfo] = {}
    for k, entry in enumerate(data.get("point", [])):
        where = f"{path} point {k + 1}"
        if "node" not in entry or "name" not in entry:
            raise ValueError(f"{where}: needs 'node' and 'name'")
        bone = str(entry.get("bone", ""))
        if bone not in BONES:
            raise ValueError(f"{where}: unknown bone {bone!r}; expected one of {list(BONES)}")
        pos = entry.get("position_m")
        if pos is not None:
            pos = np.asarray(pos, dtype=float)
            if pos.shape != (3,):
                raise ValueError(f"{where}: position_m must have 3 numbers")
        node = int(entry["node"])
        if node in points:
            raise ValueError(f"{where}: node {node} listed twice")
        points[node] = PointInfo(str(entry["name"]), bone, pos)
    if not points:
        raise ValueError(f"{path} lists no [[point]] tables")
    return points


def _catalogue_position(name: str, catalogue: dict) -> np.ndarray | None:
    """Position (m, model frame) of landmark ``name`` in ``catalogue`` (the shipped one,
    :func:`load_landmarks`), or of the landmarks ``name_x``, ``name_y``, ``name_z`` when
    they share one; None otherwise."""
    if name in catalogue:
        return np.asarray(catalogue[name].position_m, dtype=float)
    same = [np.asarray(catalogue[f"{name}_{a}"].position_m, dtype=float)
            for a in "xyz" if f"{name}_{a}" in catalogue]
    if same and all(np.allclose(p, same[0]) for p in same):
        return same[0]
    return None


def direction_code(direction: np.ndarray) -> int:
    """UFF direction code of a unit vector: +/-1, 2, 3 for the global axes, 0 otherwise."""
    for axis in range(3):
        if np.array_equal(direction, AXES[axis]):
            return axis + 1
        if np.array_equal(direction, -AXES[axis]):
            return -(axis + 1)
    return 0


def _line(text: str, what: str) -> str:
    if len(text) > 80:
        raise ValueError(f"{what} does not fit a UFF ID line (80 characters): {text!r}")
    return text


def _channel_lines(prefix: str, dprefix: str, channels: Channels, k: int) -> tuple[str, str]:
    name = channels.name[k]
    if not name or name != name.strip() or not name.isprintable() or not name.isascii():
        raise ValueError(f"channel name {name!r} cannot be written to a UFF ID line "
                         "(printable ASCII without leading/trailing blanks)")
    bone = channels.bone[k] or "-"
    d = channels.direction[k]
    return (
        _line(f"{prefix} {bone} {channels.name[k]}", f"channel name {channels.name[k]!r}"),
        _line(f"{dprefix} {float(d[0])!r} {float(d[1])!r} {float(d[2])!r}", "direction"),
    )


_MONTHS = ("Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec")


def _header_dates() -> dict[str, str]:
    """Dataset 151's dates and times from ``SOURCE_DATE_EPOCH`` (seconds since 1970, UTC;
    the reproducible-builds convention), so that two exports of one file are identical;
    empty when it is not set (pyuff then writes the local time of writing). A malformed
    value is an error, as that convention asks."""
    raw = os.environ.get("SOURCE_DATE_EPOCH")
    if raw is None:
        return {}
    try:
        stamp = time.gmtime(int(raw))
    except (ValueError, OverflowError, OSError):
        raise ValueError(f"SOURCE_DATE_EPOCH must be whole seconds since 1970, got {raw!r}"
                         ) from None
    date = f"{stamp.tm_mday:02d}-{_MONTHS[stamp.tm_mon - 1]}-{stamp.tm_year % 100:02d}"
    clock = time.strftime("%H:%M:%S", stamp)
    return {f"{kind}_{what}": value for what in ("db_created", "db_saved", "file_written")
            for kind, value in (("date", date), ("time", clock))}


def uff_datasets(frf: FrfSet, modes: UffModes | None = None, binary: bool = True,
                 geometry: int = 2411) -> list[dict]:
    """The pyuff dataset dictionaries (164, geometry, 58 per FRF, 55 per mode) of ``frf``."""
    import pyuff

    if geometry not in (15, 2411):
        raise ValueError(f"geometry dataset must be 15 or 2411, got {geometry}")
    nodes: dict[tuple, int] = {}
    coords: list[np.ndarray] = []
    taken: dict[tuple[int, int], str] = {}  # (node, direction code) -> channel name

    def node_of(channels: Channels, k: int) -> int:
        # Channels at one point along global axes share a node (+X, +Y, ... of one point;
        # a drive point is the same node as its response), as other modal tools expect.
        # A direction off the axes (code 0) cannot be told apart in dataset 58: own node.
        name, code = channels.name[k], direction_code(channels.direction[k])
        point = (channels.bone[k], tuple(float(x) for x in channels.position_m[k]))
        key: tuple = point if code != 0 else (name, *point)
        if key in nodes and taken.get((nodes[key], code), name) != name:
            key = (name, *point)  # another channel already has this node and direction
        if key not in nodes:
            nodes[key] = len(nodes) + 1
            coords.append(channels.position_m[k])
        taken[(nodes[key], code)] = name
        return nodes[key]

    out_nodes = [node_of(frf.outputs, o) for o in range(len(frf.outputs))]
    in_nodes = [node_of(frf.inputs, i) for i in range(len(frf.inputs))]
    xyz = np.array(coords, dtype=float).reshape(-1, 3)
    n = xyz.shape[0]
    n_records = int(np.isfinite(frf.H).any(axis=0).sum())
    n_modes = 0 if modes is None else len(modes.frequency_hz)
    sets: list[dict] = [{**pyuff.prepare_151(
        model_name="pelvislab", db_app="pelvislab", program="pelvislab",
        description=f"{HEADER_PREFIX} {n_records} FRF records, {n_modes} modes"),
        **_header_dates()}]
    sets.append(pyuff.prepare_164(
        units_code=1, units_description="SI: meter (newton)", temp_mode=1,
        length=1.0, force=1.0, temp=1.0, temp_offset=273.15))
    prepare_geometry = pyuff.prepare_2411 if geometry == 2411 else pyuff.prepare_15
    sets.append(prepare_geometry(
        node_nums=np.arange(1, n + 1), def_cs=np.zeros(n, dtype=int),
        disp_cs=np.zeros(n, dtype=int), color=np.ones(n, dtype=int),
        x=xyz[:, 0].copy(), y=xyz[:, 1].copy(), z=xyz[:, 2].copy()))
    for o in range(len(frf.outputs)):
        for i in range(len(frf.inputs)):
            ok = np.isfinite(frf.H[:, o, i])
            if not ok.any():
                continue
            id2, id4 = _channel_lines("out", "do", frf.outputs, o)
            id3, id5 = _channel_lines("in", "di", frf.inputs, i)
            x, values = frf.frequency_hz[ok], frf.H[ok, o, i].astype(complex)
            if x.size == 1:  # pyuff cannot write a one-point record: repeat the point
                x, values = np.repeat(x, 2), np.repeat(values, 2)
            sets.append(pyuff.prepare_58(
                binary=1 if binary else 0, id1=MARKER, id2=id2, id3=id3, id4=id4, id5=id5,
                func_type=FUNC_FRF, rsp_ent_name="pelvislab", rsp_node=out_nodes[o],
                rsp_dir=direction_code(frf.outputs.direction[o]), ref_ent_name="pelvislab",
                ref_node=in_nodes[i], ref_dir=direction_code(frf.inputs.direction[i]),
                abscissa_spacing=0, abscissa_spec_data_type=SPEC_FREQUENCY,
                abscissa_axis_units_lab="Hz", ordinate_spec_data_type=SPEC_DISPLACEMENT,
                ordinate_len_unit_exp=1, ordinate_axis_units_lab="m",
                orddenom_spec_data_type=SPEC_FORCE, orddenom_force_unit_exp=1,
                orddenom_axis_units_lab="N",
                x=x.copy(), data=values.copy()))
    if modes is not None:
        sets.extend(_mode_datasets(frf, modes, out_nodes))
    return sets


def _mode_datasets(frf: FrfSet, modes: UffModes, out_nodes: list[int]) -> list[dict]:
    """Dataset 55 per mode: the node displacement vector that best explains the channels.

    A node measured along several directions gets the least-squares vector ``u`` with
    ``d_c . u = psi_c`` (exact for orthogonal directions); a node measured along one
    direction gets ``psi d``. Channels whose shape entry is NaN are left out, and so is a
    node with none (a mode with no known entry gets no dataset).
    """
    import pyuff

    shapes = np.asarray(modes.shapes, dtype=complex)
    if shapes.shape[0] != len(frf.outputs):
        raise ValueError(
            f"mode shapes have {shapes.shape[0]} entries, the FRF set {len(frf.outputs)} outputs"
        )
    sets = []
    for r in range(shapes.shape[1]):
        # a channel without a shape entry (NaN: not measured around this mode) is left
        # out; a node with none is left out of this mode's dataset (UFF has no "unknown")
        known = np.isfinite(shapes[:, r])
        node_ids = sorted({n for o, n in enumerate(out_nodes) if known[o]})
        if not node_ids:
            continue
        vec = np.zeros((len(node_ids), 3), dtype=complex)
        for k, node in enumerate(node_ids):
            rows = [o for o, n in enumerate(out_nodes) if n == node and known[o]]
            D = frf.outputs.direction[rows]
            vec[k] = np.linalg.lstsq(D, shapes[rows, r], rcond=None)[0]
        fn = float(modes.frequency_hz[r])
        zeta = float(modes.damping_ratio[r])
        wn = 2 * np.pi * fn
        eig = complex(-zeta * wn, wn * np.sqrt(max(1 - zeta**2, 0.0)))
        sets.append(pyuff.prepare_55(
            id1="pelvislab EMA mode", id2=f"mode {r + 1} {fn:.6g} Hz zeta {zeta:.4g}",
            id3="NONE", id4="NONE", id5="NONE", model_type=1, analysis_type=3, data_ch=2,
            spec_data_type=8, data_type=5, n_data_per_node=3, load_case=1, mode_n=r + 1,
            eig=eig, modal_a=0j, modal_b=0j, node_nums=np.array(node_ids),
            r1=vec[:, 0].copy(), r2=vec[:, 1].copy(), r3=vec[:, 2].copy()))
    return sets


#: Significant digits of an abscissa in ASCII dataset 58 (E13.5, records 7 and 12 of the
#: format; the ordinates keep 12: E20.12)
ASCII_ABSCISSA_DIGITS = 6


def ascii_frequency_note(frequency_hz: np.ndarray) -> str | None:
    """What ASCII dataset 58 does to these frequency lines (Hz): ``None`` when each keeps
    its value to 1e-12, a note with the largest shift when rounding to
    :data:`ASCII_ABSCISSA_DIGITS` significant digits moves some, ``ValueError`` when it
    makes two lines one (a 0.5 mHz grid at 231.9 Hz lost 10 of its 21 lines on import,
    read as an FRF given twice; review 67)."""
    f = np.asarray(frequency_hz, float)
    f = f[np.isfinite(f)]
    rounded = np.array([float(f"{x:.{ASCII_ABSCISSA_DIGITS - 1}e}") for x in f])
    if np.unique(rounded).size < np.unique(f).size:
        raise ValueError(
            f"ASCII dataset 58 keeps {ASCII_ABSCISSA_DIGITS} significant digits of frequency "
            "(E13.5), and rounded so some of these lines become one "
            f"({np.unique(f).size} lines, {np.unique(rounded).size} after rounding): write "
            "the binary format (without --ascii), which keeps every digit")
    shift = np.abs(rounded - f)
    moved = int(np.sum(shift > 1e-12 * np.maximum(np.abs(f), 1.0)))
    if not moved:
        return None
    return (f"ASCII dataset 58 keeps {ASCII_ABSCISSA_DIGITS} significant digits of frequency "
            f"(E13.5): {moved} line(s) moved by up to {shift.max():.3g} Hz (the binary "
            "format keeps every digit)")


def write_uff(path: str | Path, frf: FrfSet, modes: UffModes | None = None,
              binary: bool = True, geometry: int = 2411) -> int:
    """Write ``frf`` (and ``modes``) as a new UFF file; returns the number of datasets.

    ``binary=False`` writes ASCII 58: values with 12 significant digits, frequencies with
    6 (the format's E13.5; refused where that makes two lines one,
    :func:`ascii_frequency_note`): not an exact round trip.
    Refuses to overwrite an existing file.
    """
    import pyuff

    path = Path(path)
    if path.exists():
        raise FileExistsError(f"{path} exists; not overwriting")
    if not binary:
        ascii_frequency_note(frf.frequency_hz)
    sets = uff_datasets(frf, modes, binary, geometry)
    from pelvislab.acquisition.session import (
        WriteRefusedError,
        publish_new_file,
        refused_write_text,
    )

    # a hidden name of this process: published complete, never over a file that appeared
    # meanwhile (a replace would overwrite it)
    tmp = path.parent / f".{path.name}.{os.getpid()}.{time.monotonic_ns()}.part"
    try:
        uff = pyuff.UFF(str(tmp))
        # one dataset per call, always appending to the fresh file: pyuff's binary-58 writer
        # reopens the file ("wb" in overwrite mode truncates what it just wrote)
        for dset in sets:
            try:
                uff.write_sets(dset, mode="add")
            except Exception as exc:
                # pyuff says "Error writing data-set #58" over the system's reason
                refused = _os_error_behind(exc)
                if refused is None:
                    raise
                raise WriteRefusedError(refused.errno,
                                        refused_write_text(path, refused)) from None
        publish_new_file(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
    return len(sets)


def _os_error_behind(exc: BaseException) -> OSError | None:
    """The first ``OSError`` with an errno in ``exc`` or the exceptions it was raised
    from or during, else None."""
    seen = 0
    while exc is not None and seen < 10:
        if isinstance(exc, OSError) and exc.errno:
            return exc
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


def _direction_from_code(code: int, where: str) -> np.ndarray:
    code = int(code)
    if code == 0:
        return np.array([0.0, 0.0, 1.0])
    if abs(code) > 3:
        raise ValueError(f"{where}: rotational direction code {code} is not supported")
    return float(np.sign(code)) * AXES[abs(code) - 1]


def _parse_channel(id_name: str, id_dir: str, prefix: str, dprefix: str
                   ) -> tuple[str, str, np.ndarray] | None:
    parts = id_name.strip().split(" ", 2)
    dparts = id_dir.strip().split()
    if len(parts) != 3 or parts[0] != prefix or len(dparts) != 4 or dparts[0] != dprefix:
        return None
    try:
        d = np.array([float(v) for v in dparts[1:]])
    except ValueError:
        return None
    bone = "" if parts[1] == "-" else parts[1]
    return parts[2], bone, d


def to_receptance(frequency_hz: np.ndarray, values: np.ndarray, quantity: int) -> np.ndarray:
    """Receptance from an FRF whose response is displacement, velocity or acceleration.

    ``quantity`` is the UFF specific data type of the ordinate (8, 11, 12; 0 "unknown" is taken
    as displacement). Mobility ``V = i w X``, accelerance ``A = -w^2 X``; 0 Hz gives NaN.
    """
    w = 2 * np.pi * np.asarray(frequency_hz, dtype=float)
    values = np.asarray(values, dtype=complex)
    if quantity in (0, SPEC_DISPLACEMENT):
        return values.copy()
    with np.errstate(divide="ignore", invalid="ignore"):
        if quantity == SPEC_VELOCITY:
            out = values / (1j * w)
        elif quantity == SPEC_ACCELERATION:
            out = -values / w**2
        else:
            raise ValueError(f"ordinate type {quantity} is not displacement, velocity or "
                             "acceleration")
    return np.where(w > 0, out, np.nan + 0j)


def _spec_name(code: int) -> str:
    return f"{SPEC_NAMES.get(code, 'unlisted')} (specific data type {code})"


def record_problem(dset: dict) -> str:
    """Why a dataset 58 FRF record cannot be read as a response over force ("" if it can).

    Its abscissa must be a frequency (UFF 58 record 8, specific data type 18, or 0/1
    "unknown"/"general"): an rpm (19) or order (20) axis is not one, and was read as Hz.
    Its ordinate (record 9) must be a response: displacement, velocity, acceleration (or 0,
    taken as displacement); a force over force (a force-transmissibility or a reference
    channel) made the whole import fail. Its denominator (record 9's ordinate denominator)
    must be a force (or unknown/general, taken as force): a response over a response (an
    acceleration transmissibility) was divided by -w^2 and read as a receptance in m/N.
    An ordinate units label in g must be that of an acceleration
    (:func:`ordinate_g_factor`)."""
    abscissa = int(dset.get("abscissa_spec_data_type", 0))
    if abscissa not in FREQUENCY_ABSCISSAE:
        return (f"its abscissa is {_spec_name(abscissa)}, not frequency in Hz (an rpm or "
                "order axis is not a frequency)")
    ordinate = int(dset.get("ordinate_spec_data_type", 0))
    if ordinate not in RESPONSE_ORDINATES:
        return (f"its ordinate is {_spec_name(ordinate)}, not a response (displacement, "
                "velocity or acceleration) over force")
    denominator = int(dset.get("orddenom_spec_data_type", SPEC_FORCE))
    if denominator not in FORCE_DENOMINATORS:
        return (f"its denominator is {_spec_name(denominator)}, not a force (a "
                "transmissibility is no FRF over force)")
    return ordinate_g_factor(dset)[1]


def ordinate_g_factor(dset: dict) -> tuple[float, str]:
    """(m/s^2 per ordinate unit, problem) from the ordinate units label (record 9 field 6).

    A label ``g`` or ``g/N`` (any case) on an acceleration ordinate means accelerance in g
    per force unit: ``STANDARD_GRAVITY_M_S2`` (9.80665 m/s^2 per g). The label takes
    precedence over the units of dataset 164 for the numerator (UFF 58: "if fields 5 and 6
    are supplied, they take precedence over program generated labels and units"), so the
    length factor of 164 does not apply to it. Other labels naming g as a unit (``g/lbf``,
    ``g^2/Hz``, g on a displacement or velocity ordinate) cannot be read reliably: a
    problem is returned (the record is skipped). Otherwise (1.0, "")."""
    label = str(dset.get("ordinate_axis_units_lab", "") or "").strip()
    if not re.search(r"(?<![A-Za-z])[gG](?![A-Za-z])", label):
        return 1.0, ""
    ordinate = int(dset.get("ordinate_spec_data_type", 0))
    if label.lower() in ("g", "g/n") and ordinate == SPEC_ACCELERATION:
        return STANDARD_GRAVITY_M_S2, ""
    return 1.0, (f"its ordinate units label {label!r} on an ordinate of "
                 f"{_spec_name(ordinate)} cannot be read reliably (read: 'g' or 'g/N' on "
                 "acceleration, 9.80665 m/s^2 per g)")


def _delimiter_count(path: Path) -> int:
    """Number of dataset delimiter lines ``    -1`` in the file, found as pyuff finds them.

    Every dataset opens and closes with one, so an odd count is a file cut right after a
    dataset's opening line, which the check of the file's last line lets pass.
    """
    data = path.read_bytes()
    count, at = 0, data.find(b"    -1")
    while at != -1:
        after = at + 6
        if after == len(data) or data[after] in (10, 13) or \
                data[after:at + 80] == b" " * 74:
            count += 1
        at = data.find(b"    -1", at + 1)
    return count


def read_uff(path: str | Path, points: dict[int, PointInfo] | None = None
             ) -> tuple[FrfSet, list[str]]:
    """Read the FRFs of a UFF file as a receptance :class:`FrfSet`; also returns notes.

    Notes name what was skipped or assumed (non-FRF records, scalar directions, unit factors).
    """
    import pyuff

    path = Path(path)
    if path.is_dir():
        raise IsADirectoryError(f"{path} is a folder, not a UFF file")
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {path}")
    with open(path, "rb") as handle:  # every dataset ends with a line "    -1"
        head = handle.read(4096)  # the first line, past any blank lines before it
        handle.seek(max(0, path.stat().st_size - 64))
        tail = handle.read().rstrip(b" \t\r\n\x00")
    # what the file is when it is no UFF at all, before guessing at a truncation
    if not head.strip():
        raise ValueError(f"{path} is empty (or blank): not a UFF file")
    if head.startswith(b"\x89HDF"):
        raise ValueError(f"{path} is an HDF5 file, not UFF (sessions and FRF files are "
                         "read directly by every command)")
    if head.lstrip(b" \t\r\n").split(b"\n", 1)[0].strip() != b"-1":
        raise ValueError(f"{path} is not a UFF file: it does not start with a dataset "
                         "delimiter line ('    -1')")
    if not (tail.endswith(b"-1") and (len(tail) == 2 or tail[-3:-2] in b" \t\r\n")):
        # pyuff silently drops a dataset cut short: the import would lose FRFs unseen
        raise ValueError(f"{path} ends inside a dataset (no closing '-1' line): truncated? "
                         "Not importing part of it")
    if _delimiter_count(path) % 2:
        raise ValueError(f"{path} has an odd number of dataset delimiter lines ('    -1'): "
                         "truncated right after a dataset's opening line, or a delimiter "
                         "inside binary data that UFF readers would split wrongly. Not "
                         "importing part of it")
    try:
        uff = pyuff.UFF(str(path))
        types = list(uff.get_set_types())
        sets = uff.read_sets() if types else []
    except Exception as exc:  # pyuff raises bare Exceptions on malformed files
        raise ValueError(f"{path} is not a readable UFF file ({exc})") from None
    if isinstance(sets, dict):
        sets = [sets]
    notes: list[str] = []
    length_factor = force_factor = 1.0
    coords: dict[int, np.ndarray] = {}
    records = []
    header: tuple[int, int] | None = None
    n_mode_sets = 0
    real_frf = 0  # FRF records with real values, skipped
    unusable = 0  # FRF records that are no response over force in Hz (record_problem)
    for dset in sets:
        kind = int(dset.get("type", -1))
        if kind == 151:
            found = HEADER_PATTERN.fullmatch(str(dset.get("description", "")).strip())
            if found:
                header = (int(found.group(1)), int(found.group(2)))
        elif kind == 55:
            n_mode_sets += 1
        elif kind == 164:
            length_factor = float(dset.get("length", 1.0)) or 1.0
            force_factor = float(dset.get("force", 1.0)) or 1.0
            if (length_factor, force_factor) != (1.0, 1.0):
                notes.append(f"units: length factor {length_factor:g}, force factor "
                             f"{force_factor:g} (converted to SI)")
        elif kind in (15, 2411):
            for n, x, y, z in zip(dset["node_nums"], dset["x"], dset["y"], dset["z"],
                                  strict=True):
                coords[int(n)] = np.array([x, y, z], dtype=float)
        elif kind == 58:
            func = int(dset.get("func_type", -1))
            data = np.asarray(dset.get("data", []))
            if func in (FUNC_FRF, FUNC_GENERAL) and np.iscomplexobj(data):
                problem = record_problem(dset)
                if problem:
                    unusable += 1
                    notes.append(f"skipped a dataset 58 record (node {dset.get('rsp_node')} "
                                 f"/ {dset.get('ref_node')}): {problem}")
                else:
                    records.append(dset)
            elif func == FUNC_FRF:
                # real ordinates (data type 2 or 4): a magnitude, or one part of the FRF;
                # read as complex they were an FRF of zero phase, silently (review of the
                # EMA path)
                real_frf += 1
                notes.append(f"skipped a dataset 58 FRF with real values (node "
                             f"{dset.get('rsp_node')} / {dset.get('ref_node')}): an FRF "
                             "is complex; a magnitude or one part of it cannot be used")
            else:
                notes.append(f"skipped a dataset 58 of function type {func} (not an FRF)")
    n_frf = len(records) + unusable + real_frf  # what the header of our export counts
    if header is not None and (n_frf < header[0] or n_mode_sets < header[1]):
        raise ValueError(
            f"{path} holds {n_frf} FRF records and {n_mode_sets} modes, but its "
            f"pelvislab header says {header[0]} and {header[1]}: truncated? Not importing "
            "part of it")
    if n_mode_sets:  # they were dropped without a word (review 67)
        notes.append(f"{n_mode_sets} mode shape dataset(s) (55) not imported: the file "
                     "written holds the FRFs (/frf); run `pelvislab ema` on it for modes")
    if header is not None and (n_frf, n_mode_sets) != header:
        notes.append(f"{n_frf} FRF records and {n_mode_sets} modes, more than the "
                     f"pelvislab header's {header[0]} and {header[1]}: datasets were added "
                     "after the export (all imported)")
    if not records:
        # the function types say why: a file of time responses read "set types: [58]"
        # (first-day review, session 39)
        skipped = sorted({int(d.get("func_type", -1)) for d in sets
                          if int(d.get("type", -1)) == 58} - {FUNC_FRF})
        raise ValueError(f"{path} holds no dataset 58 FRF (set types: "
                         f"{sorted({int(t) for t in types})}"
                         + (f"; its datasets 58 are of function type "
                            f"{', '.join(map(str, skipped))}, not 4 (FRF)" if skipped else "")
                         + (f"; {real_frf} FRF record(s) hold real values, not complex ones "
                            "(a magnitude?)" if real_frf else "")
                         + (f"; {unusable} record(s) skipped as the notes say: "
                            + "; ".join(n.split(": ", 1)[1] for n in notes
                                        if n.startswith("skipped a dataset 58 record"))
                            if unusable else "")
                         + ")")
    for n in coords:
        coords[n] = coords[n] / length_factor
    points = points or {}

    outputs: dict[object, tuple[str, str, np.ndarray, np.ndarray]] = {}
    inputs: dict[object, tuple[str, str, np.ndarray, np.ndarray]] = {}
    entries = []
    scalar_warned = False
    unplaced: set[int] = set()  # nodes already named in a "no coordinates" note
    renamed_not: set[int] = set()  # nodes whose points-file name was noted as not applied
    used_nodes: set[int] = set()  # nodes of the FRF records imported
    catalogue: dict = {}  # the landmark catalogue, for nodes named after a landmark

    def channel(dset: dict, role: str) -> tuple[object, tuple[str, str, np.ndarray, np.ndarray]]:
        nonlocal scalar_warned
        node = int(dset["rsp_node" if role == "out" else "ref_node"])
        used_nodes.add(node)
        code = int(dset["rsp_dir" if role == "out" else "ref_dir"])
        where = f"{path} node {node}"
        ours = str(dset.get("id1", "")).strip() == MARKER
        parsed = None
        if ours:
            if role == "out":
                parsed = _parse_channel(dset["id2"], dset["id4"], "out", "do")
            else:
                parsed = _parse_channel(dset["id3"], dset["id5"], "in", "di")
        position = coords.get(node)
        info = points.get(node)
        if info is not None and info.position_m is not None:
            position = info.position_m
        if position is None and info is not None:
            # a node mapped to a landmark of the catalogue sits where the catalogue says
            # (it was put at the origin, where identify would model it: review, session 39)
            if not catalogue:  # read once, when a node needs it
                from pelvislab.acquisition.protocol import load_landmarks

                catalogue.update(load_landmarks())
            found = _catalogue_position(info.name, catalogue)
            if found is not None:
                position = found
                if node not in unplaced:
                    unplaced.add(node)
                    notes.append(f"node {node} ({info.name}) has no coordinates; placed at "
                                 "the landmark catalogue's position for that name")
        if position is None:
            position = np.zeros(3)
            if node not in unplaced:
                unplaced.add(node)
                notes.append(f"node {node} has no coordinates; placed at the origin")
        if parsed is not None:
            name, bone, direction = parsed
            key: object = name
            if info is not None and node not in renamed_not:
                # the file's own records name each channel (a node carries several): the
                # points file's node name is not applied, its bone and position are
                # (it was silent: review 67)
                renamed_not.add(node)
                notes.append(f"node {node}: the points file's name {info.name!r} is not "
                             f"applied (this file's records name their channels, e.g. "
                             f"{name!r}); its bone and position are")
        else:
            direction = _direction_from_code(code, where)
            if code == 0 and not scalar_warned:
                notes.append("scalar (direction 0) records taken as +Z")
                scalar_warned = True
            label = {0: "", 1: "+X", -1: "-X", 2: "+Y", -2: "-Y", 3: "+Z", -3: "-Z"}[code]
            name = f"{info.name if info is not None else f'node{node}'}{label}"
            bone = ""
            key = (node, code)
        if info is not None:
            bone = info.bone
        return key, (name, bone, np.asarray(position, dtype=float), direction)

    converted: dict[int, int] = {}  # records per ordinate quantity converted
    in_g = 0  # accelerance records in g per force unit
    for dset in records:
        ko, out = channel(dset, "out")
        ki, inp = channel(dset, "in")
        outputs.setdefault(ko, out)
        inputs.setdefault(ki, inp)
        x = np.asarray(dset["x"], dtype=float)
        values = np.asarray(dset["data"]).astype(complex)
        if x.size != values.size:
            raise ValueError(f"{path}: a dataset 58 has {x.size} abscissae, {values.size} values")
        quantity = int(dset.get("ordinate_spec_data_type", 0))
        denom = int(dset.get("orddenom_spec_data_type", SPEC_FORCE))
        if denom not in (0, SPEC_FORCE):  # record_problem refused what is not a force
            notes.append(f"record {out[0]}/{inp[0]} has denominator type {denom}, taken as force")
        g_m_s2, _ = ordinate_g_factor(dset)  # record_problem refused what it cannot read
        if g_m_s2 != 1.0:
            # the label sets the numerator's unit: m/s^2 from g, not 164's length factor
            values = to_receptance(x, values, quantity) * (g_m_s2 * force_factor)
            in_g += 1
        else:
            values = to_receptance(x, values, quantity) * (force_factor / length_factor)
        entries.append((ko, ki, x, values))
        converted[quantity] = converted.get(quantity, 0) + 1

    for quantity, what, by in ((SPEC_VELOCITY, "mobility", "(i w)"),
                               (SPEC_ACCELERATION, "accelerance", "-w^2")):
        if converted.get(quantity):
            # said: the division multiplies the noise of the lowest lines (by up to 1/w^2),
            # which then dominate a fit without H_std (first-day review, session 39)
            notes.append(f"{converted[quantity]} {what} record(s) converted to receptance "
                         f"(divided by {by}): the lowest lines' noise grows with it; "
                         "`pelvislab ema` says when they dominate")

    if in_g:
        notes.append(f"{in_g} record(s) in g per force unit (ordinate units label 'g'): "
                     f"converted with {STANDARD_GRAVITY_M_S2} m/s^2 per g")
    out_keys = list(outputs)
    in_keys = list(inputs)
    # (a repeated abscissa, as pelvislab writes one-line records, lands on the same line)
    grid = np.unique(np.concatenate([e[2] for e in entries]))
    H = np.full((grid.size, len(out_keys), len(in_keys)), np.nan + 0j)
    replaced: dict[tuple[str, str], int] = {}  # pair -> lines given another value again
    for ko, ki, x, values in entries:
        idx = np.searchsorted(grid, x)
        o, i = out_keys.index(ko), in_keys.index(ki)
        values = np.asarray(values)
        # two records of one FRF (a repeat, or bands that overlap): the later one's values
        # replaced the earlier's without a word (review of the EMA path). Whole records at
        # once (a line loop took ~3 s for 300 records of 6400 lines); a record that gives
        # one line twice is taken line by line, as it always was
        if np.all(np.diff(idx) > 0) or np.unique(idx).size == idx.size:
            old = H[idx, o, i]
            n = int(np.count_nonzero(np.isfinite(old) & (old != values)))
            H[idx, o, i] = values
        else:
            n = 0
            for k, v in zip(idx, values, strict=True):
                n += int(np.isfinite(H[k, o, i]) and H[k, o, i] != v)
                H[k, o, i] = v
        if n:
            pair = (outputs[ko][0], inputs[ki][0])
            replaced[pair] = replaced.get(pair, 0) + n
    for (out_name, in_name), n in replaced.items():
        notes.append(f"FRF {out_name}/{in_name} is given more than once with different "
                     f"values at {n} line(s): the values of the record read last are kept")

    unused = sorted(set(points) - used_nodes)
    if unused:  # a typo in a node number was silent (review 67)
        notes.append(f"points file node(s) {unused} are in no FRF record imported: not used")

    def channels(table: dict, role: str) -> Channels:
        rows = list(table.values())
        names = [r[0] for r in rows]
        shared = sorted({n for n in names if names.count(n) > 1})
        if shared:
            # two nodes mapped to one name: those channels kept apart as NAME#1, NAME#2
            # (every channel was renamed, the others too, and silently: review 67)
            seen: dict[str, int] = {}
            for k, n in enumerate(names):
                if n in shared:
                    seen[n] = seen.get(n, 0) + 1
                    names[k] = f"{n}#{seen[n]}"
            notes.append(f"{role} channel name(s) {shared} given to more than one node (the "
                         "points file?): kept apart as NAME#1, NAME#2, ...; a drive point "
                         "among them no longer pairs with its input by name")
        return Channels(names, [r[1] for r in rows], np.array([r[2] for r in rows]),
                        np.array([r[3] for r in rows]))

    frf = FrfSet(grid, H, channels(outputs, "output"), channels(inputs, "input"),
                 attrs={"source": f"UFF import of {path.name}"})
    return frf, notes
