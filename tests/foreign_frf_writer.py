"""An independent writer of design-4.2 ``/frf`` files: what someone who only read the contract
might write, to check that ``pelvislab gap diagnose`` reads it.

The files are written here directly with h5py from the text of design.md section 4.2, NOT
with :func:`pelvislab.acquisition.frfset.write_frf`. Only the FRF *values* come from the
product's model (``pelvislab.model.frf.frf`` on a perturbed appendix-E model: masses and
springs within +-30 %, dashpots 10-3000 N s/m); the face-up geometry is read from
``protocols/landmarks.toml`` with tomllib (force direction = -landmark direction: the
landmark direction points from the bone toward the sensor, design 4.1).

Every variant is something the contract allows (or leaves open): with/without ``H_std``,
NaN for unmeasured pairs (NaN+NaN j or NaN+0j), fixed-length or variable-length strings,
bytes or str attributes, numpy or python scalars, float32 for the arrays whose type 4.2
does not fix, complex128 as h5py's ("r", "i") compound or another field naming, uniform,
non-uniform or descending (sweep "down") grids, extra groups/attributes, a full session
file with ``/protocol``, ``/bench`` and ``/steps``, a point on no bone, and one with an
added point mass (an effect to be named). ``bad_*`` variants must be refused with exit 1.

    .venv/bin/python -m pelvislab.tests.foreign_frf_writer OUTDIR [--run] [--only a,b]

writes every variant to OUTDIR and, with ``--run``, runs ``pelvislab gap diagnose`` on
each (nice -n 10, one BLAS thread) and prints verdict, gap and wall time per file.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
OUT_NAMES = ["sacrum_x", "SIPS_R_x", "SIPS_L_x", "SIAS_R_x", "SIAS_L_x", "SIAS_R_y", "SIAS_L_y"]
IN_NAMES = ["sacrum_x", "SIPS_R_x", "SIPS_L_x"]


@dataclass
class Points:
    """Names, bones, positions (m) and unit directions of measurement/excitation points."""

    name: list[str]
    bone: list[str]
    position_m: np.ndarray
    direction: np.ndarray


def face_up_points(names: list[str], force: bool = False) -> Points:
    """Points of the landmark catalogue (mm -> m); ``force``: direction into the bone."""
    with open(ROOT / "protocols" / "landmarks.toml", "rb") as handle:
        cat = tomllib.load(handle)["landmarks"]
    sign = -1.0 if force else 1.0
    return Points(list(names), [cat[n]["bone"] for n in names],
                  np.array([cat[n]["position_mm"] for n in names], float) / 1000.0,
                  sign * np.array([cat[n]["direction"] for n in names], float))


def face_up_measured(outs: list[str], ins: list[str]) -> np.ndarray:
    """Table 6.3: a drive-point pick-up is measured only for its own excitation."""
    m = np.ones((len(outs), len(ins)), bool)
    for j, name in enumerate(ins):
        for o, oname in enumerate(outs):
            if oname in ins and oname != name:
                m[o, j] = False
    return m


def perturbed_model(rng: np.random.Generator, per_dashpot: bool = False,
                    inertia_fixed: bool = False) -> object:
    """Appendix E with masses and springs within +-30 %, dashpots log-uniform 10-3000 N s/m
    (one value per dashpot group, or per dashpot when ``per_dashpot``); inertia scaled with
    the mass (design 4.5) or, ``inertia_fixed``, left at appendix E."""
    from pelvislab.model.pelvis import default_model

    m = default_model()
    for b in m.bodies:
        mass = b.mass_kg * (1 + rng.uniform(-0.3, 0.3))
        m = m.replace_body(b.name, mass_kg=mass) if inertia_fixed else m.with_mass(b.name, mass)
    for s in m.springs:
        m = m.replace_spring(s.name,
                             stiffness_n_per_m=s.stiffness_n_per_m * (1 + rng.uniform(-0.3, 0.3)))
    groups = {(d.group, d.side): 10 ** rng.uniform(1.0, np.log10(3000.0)) for d in m.dashpots}
    for d in m.dashpots:
        c = 10 ** rng.uniform(1.0, np.log10(3000.0)) if per_dashpot else groups[(d.group, d.side)]
        m = m.replace_dashpot(d.name, coefficient_n_s_per_m=c)
    return m


@dataclass
class Variant:
    """How one independent writer lays out the file (all within design 4.2)."""

    name: str
    note: str
    grid: str = "1hz"  # 1hz: 5-200 Hz in 1 Hz | log: 180 log-spaced 5-250 Hz | 2.5hz | dc
    # (0-200 Hz in 1 Hz) | dense (5-200 Hz in 0.25 Hz, 781 lines)
    order: str = "up"  # "down": lines in acquisition order of a downward sweep
    with_std: bool = True
    std_unmeasured: str = "nan"  # nan | zero (H_std at unmeasured pairs)
    nan: str = "nan_nan"  # nan_nan | nan_zero for unmeasured H
    strings: str = "vlen"  # vlen | fixed_bytes | fixed_utf8 | vlen_bytes
    attrs: str = "str"  # str | bytes | np_bytes
    version: str = "int"  # int | np_int32 | np_uint8 | np_int64_array1
    real_dtype: str = "float64"  # dtype of frequency_hz, position_m, direction, acquired_at_s
    complex_fields: tuple[str, str] = ("r", "i")
    root: str = "none"  # none | frf | session
    extras: bool = False
    acquired: bool = False
    compress: bool = False
    all_pairs: bool = False  # every output x input measured (no NaN)
    off_bone_output: bool = False  # an extra pick-up on the bed frame (bone "")
    renamed: bool = False  # point names P1..P7 / E1..E3 instead of landmark names
    per_dashpot: bool = False
    inertia_fixed: bool = False  # masses perturbed, inertia tensors left at appendix E
    point_mass_kg: float = 0.0  # > 0: an added point mass on the right innominate
    tilted_rounded: bool = False  # SIAS y pick-ups tilted 30 deg up, directions to 3 decimals
    std_zero: bool = False  # H_std written as zeros (noise-free claim)
    std_scale: float = 1.0  # H_std written as std_scale x the true complex-error std
    noise: str = "peak"  # peak: sigma = noise_rel x the FRF's peak | relative: x |H| per
    # line | drive_profile: peak-based x 0.5 V / face_up drive level (25x at 5 Hz, 1x >= 40 Hz)
    bad: str = ""  # a defect the reader must refuse
    seed: int = 7
    noise_rel: float = 0.005
    expect: str = "none"
    extra: dict = field(default_factory=dict)


VARIANTS = [
    Variant("v01_plain", "h5py defaults: vlen str, complex128, H_std, 1 Hz 5-200 Hz"),
    Variant("v02_no_std", "no H_std (noise estimated)", with_std=False, seed=8),
    Variant("v03_fixed_bytes", "fixed-length bytes strings and bytes attrs, np.int32 version",
            strings="fixed_bytes", attrs="np_bytes", version="np_int32", seed=9),
    Variant("v04_fixed_utf8_f32", "fixed-length utf-8 strings, float32 frequency/positions/"
            "directions, uint8 version", strings="fixed_utf8", real_dtype="float32",
            version="np_uint8", seed=10),
    Variant("v05_compound_real_imag", "complex128 as compound (real, imag), NaN+0j unmeasured",
            complex_fields=("real", "imag"), nan="nan_zero", seed=11),
    Variant("v06_log_grid", "180 log-spaced lines 5-250 Hz, H_std 0 at unmeasured pairs",
            grid="log", std_unmeasured="zero", seed=12),
    Variant("v07_sweep_down", "lines in acquisition order of a downward sweep (decreasing "
            "frequency_hz), acquired_at_s", order="down", acquired=True, seed=13),
    Variant("v08_extras", "unknown root/frf attrs, extra datasets and groups, gzip+shuffle, "
            "root attrs of an FRF file, version as 1-element array", extras=True,
            compress=True, root="frf", version="np_int64_array1", seed=14),
    Variant("v09_session", "full session file: root attrs, /protocol, /bench, /steps with "
            "echoes/phasors, then /frf; vlen bytes names", root="session",
            strings="vlen_bytes", attrs="bytes", grid="2.5hz", seed=15),
    Variant("v10_all_pairs_renamed", "all 21 pairs measured, points named P1.. / E1..",
            all_pairs=True, renamed=True, with_std=False, seed=16),
    Variant("v11_off_bone", "an extra pick-up on the bed frame (bone ''), random FRF",
            off_bone_output=True, seed=17),
    Variant("v12_dc_line", "FFT-like grid 0-200 Hz in 1 Hz, the 0 Hz line NaN", grid="dc",
            seed=18),
    Variant("v13_per_dashpot", "every dashpot its own value (10-3000 N s/m)", per_dashpot=True,
            seed=19),
    Variant("v13b_inertia_fixed", "masses +-30 % with inertia left at appendix E",
            inertia_fixed=True, seed=23),
    Variant("v14_point_mass", "added point mass 0.25 kg on the right innominate",
            point_mass_kg=0.25, expect="added_mass", seed=20),
    Variant("v15_tilted_rounded", "SIAS y pick-ups tilted 30 deg toward +z, directions "
            "written to 3 decimals (|d| = 0.99998)", tilted_rounded=True, seed=21),
    Variant("v16_std_zero", "H_std written as zeros", std_zero=True, seed=22),
    Variant("v17_std_per_component", "H_std written as the std of the real (or imaginary) "
            "part, i.e. 1/sqrt(2) of the 4.2 definition (a misreading)", std_scale=0.5**0.5,
            seed=24),
    Variant("v18_relative_noise", "noise 1 % of |H| per line (not of the peak), no H_std",
            noise="relative", noise_rel=0.01, with_std=False, seed=25),
    Variant("v19_drive_noise", "noise 0.2 % of peak x 0.5 V / face_up drive level (25x "
            "at 5 Hz), no H_std", noise="drive_profile", noise_rel=0.002, with_std=False,
            seed=26),
    Variant("v19b_drive_noise_std", "as v19 with H_std", noise="drive_profile",
            noise_rel=0.002, seed=26),
    Variant("v20_dense", "781 lines: 5-200 Hz in 0.25 Hz", grid="dense", seed=27),
    Variant("bad_no_frf", "session file without /frf", root="session", bad="no_frf",
            expect="error"),
    Variant("bad_H_transposed", "H stored (n_f, n_in, n_out)", bad="H_transposed",
            expect="error"),
    Variant("bad_all_nan", "every H line NaN", bad="all_nan", expect="error"),
    Variant("bad_positions_transposed", "outputs/position_m stored (3, n_out)",
            bad="pos_transposed", expect="error"),
    Variant("bad_real_H", "H stored as float64 (imaginary part dropped)", bad="real_H",
            expect="error"),
    Variant("bad_H_last_axis_2", "H as float64 (n_f, n_out, n_in, 2) real/imag (4.2 says "
            "complex128)", bad="H_pairs", expect="error"),
    Variant("bad_frf_dataset", "/frf is a dataset, not a group", bad="frf_dataset",
            expect="error"),
    Variant("bad_few_lines", "3 frequency lines", bad="few_lines", expect="error"),
    Variant("bad_freq_len", "frequency_hz one value short", bad="freq_len", expect="error"),
    Variant("bad_not_hdf5", "a text file named .h5", bad="not_hdf5", expect="error"),
]


def grid(kind: str) -> np.ndarray:
    """Frequency lines (Hz) of a grid kind."""
    if kind == "1hz":
        return np.arange(5.0, 200.5, 1.0)
    if kind == "2.5hz":
        return np.arange(5.0, 300.1, 2.5)
    if kind == "log":
        return np.geomspace(5.0, 250.0, 180)
    if kind == "dc":
        return np.arange(0.0, 200.5, 1.0)
    if kind == "dense":
        return np.arange(5.0, 200.01, 0.25)
    raise ValueError(kind)


def synthesise(v: Variant) -> dict:
    """Frequency lines, noisy H, H_std and the channels of a variant (before writing)."""
    from pelvislab.model.frf import frf
    from pelvislab.model.pelvis import PointMass

    rng = np.random.default_rng(v.seed)
    f = grid(v.grid)
    outs, ins = face_up_points(OUT_NAMES), face_up_points(IN_NAMES, force=True)
    written_dirs = outs.direction.copy()
    if v.tilted_rounded:
        for o, name in enumerate(outs.name):
            if name.endswith("_y"):
                outs.direction[o] = [0.0, np.sign(outs.direction[o, 1]) * np.cos(np.pi / 6),
                                     np.sin(np.pi / 6)]
        written_dirs = np.round(outs.direction, 3)
    model = perturbed_model(rng, v.per_dashpot, v.inertia_fixed)
    if v.point_mass_kg:
        p = model.body("innominate_right").com_m + np.array([0.02, -0.01, 0.015])
        model = model.with_point_mass(PointMass("foreign", "innominate_right", p,
                                                v.point_mass_kg))
    f_model = np.where(f > 0, f, 1.0)  # the 0 Hz line of a 'dc' grid is written NaN below
    H = frf(model, f_model, outs, ins)
    measured = (np.ones((len(outs.name), len(ins.name)), bool) if v.all_pairs
                else face_up_measured(outs.name, ins.name))
    sigma = v.noise_rel * np.max(np.abs(H), axis=0, keepdims=True) * np.ones(H.shape)
    if v.noise == "relative":
        sigma = v.noise_rel * np.abs(H)
    if v.noise == "drive_profile":  # displacement noise / force: face_up's drive profile
        pts = np.array([[5.0, 0.02], [15.0, 0.05], [20.0, 0.12], [30.0, 0.3], [40.0, 0.5]])
        level = np.exp(np.interp(np.log(f_model), np.log(pts[:, 0]), np.log(pts[:, 1])))
        sigma = sigma * (0.5 / level)[:, None, None]
    H = H + sigma / np.sqrt(2) * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
    outs = Points(outs.name, outs.bone, outs.position_m, written_dirs)
    if v.off_bone_output:
        outs = Points(outs.name + ["bed_frame_z"], outs.bone + [""],
                      np.vstack([outs.position_m, [[-0.2, 0.0, -0.3]]]),
                      np.vstack([outs.direction, [[0.0, 0.0, 1.0]]]))
        extra = 1e-7 * (rng.normal(size=(f.size, 1, len(ins.name)))
                        + 1j * rng.normal(size=(f.size, 1, len(ins.name))))
        H = np.concatenate([H, extra], axis=1)
        sigma = np.concatenate([sigma, np.full((f.size, 1, len(ins.name)), 1e-8)], axis=1)
        measured = np.vstack([measured, np.ones((1, len(ins.name)), bool)])
    if v.renamed:
        outs.name = [f"P{i + 1}" for i in range(len(outs.name))]
        ins.name = [f"E{i + 1}" for i in range(len(ins.name))]
    unmeasured = complex(np.nan, np.nan) if v.nan == "nan_nan" else complex(np.nan, 0.0)
    H = np.where(measured[None], H, unmeasured)
    std = np.where(measured[None], v.std_scale * sigma,
                   np.nan if v.std_unmeasured == "nan" else 0.0)
    if v.std_zero:
        std = np.zeros(std.shape)
    if v.grid == "dc":
        H[0] = unmeasured
        std[0] = np.nan
    acquired = np.cumsum(np.full(f.size, 2.3))
    if v.order == "down":
        f, H, std = f[::-1].copy(), H[::-1].copy(), std[::-1].copy()
    return {"f": f, "H": H, "std": std, "outs": outs, "ins": ins, "acquired": acquired}


def _strings(values: list[str], kind: str) -> tuple[np.ndarray, object]:
    """(data, dtype) of a string dataset in one of the layouts an HDF5 writer may choose."""
    if kind == "vlen":
        return np.array(values, dtype=object), h5py.string_dtype("utf-8")
    if kind == "vlen_bytes":
        return np.array([s.encode() for s in values], dtype=object), h5py.string_dtype("ascii")
    width = max(1, max(len(s.encode()) for s in values))
    if kind == "fixed_bytes":
        return np.array([s.encode() for s in values], dtype=f"S{width}"), None
    if kind == "fixed_utf8":  # written raw, see _write_points (HDF5 will not convert)
        return np.array([s.encode() for s in values], dtype=f"S{width}"), "utf-8"
    raise ValueError(kind)


def _text_attr(value: str, kind: str) -> object:
    return {"str": value, "bytes": value.encode(), "np_bytes": np.bytes_(value.encode())}[kind]


def _version_attr(kind: str) -> object:
    return {"int": 1, "np_int32": np.int32(1), "np_uint8": np.uint8(1),
            "np_int64_array1": np.array([1], np.int64)}[kind]


def _complex_dataset(group: h5py.Group, name: str, H: np.ndarray, fields: tuple[str, str],
                     **kw: object) -> None:
    if fields == ("r", "i"):
        group.create_dataset(name, data=H.astype(np.complex128), **kw)
        return
    dt = np.dtype([(fields[0], np.float64), (fields[1], np.float64)])
    data = np.empty(H.shape, dt)
    data[fields[0]], data[fields[1]] = H.real, H.imag
    group.create_dataset(name, data=data, **kw)


def _write_points(group: h5py.Group, pts: Points, v: Variant, kw: dict) -> None:
    for key, values in (("name", pts.name), ("bone", pts.bone)):
        data, dtype = _strings(values, v.strings)
        if dtype == "utf-8":
            ds = group.create_dataset(key, shape=data.shape,
                                      dtype=h5py.string_dtype("utf-8", data.dtype.itemsize))
            ds.id.write(h5py.h5s.ALL, h5py.h5s.ALL, data, mtype=ds.id.get_type())
        else:
            group.create_dataset(key, data=data, dtype=dtype)
    rd = np.dtype(v.real_dtype)
    pos = pts.position_m.astype(rd)
    if v.bad == "pos_transposed" and group.name.endswith("outputs"):
        pos = pos.T.copy()
    group.create_dataset("position_m", data=pos, **kw)
    group.create_dataset("direction", data=pts.direction.astype(rd), **kw)
    if v.extras:
        group.create_dataset("label", data=np.array([f"label {n}" for n in pts.name],
                                                     dtype=object),
                             dtype=h5py.string_dtype())
        group.attrs["coordinate_frame"] = "design 4.1"


def _write_session_parts(handle: h5py.File, v: Variant, d: dict) -> None:
    """Root attrs, /protocol, /bench and a few /steps of a session file (design 4.2)."""
    handle.attrs["schema"] = _text_attr("pelvislab-session", v.attrs)
    handle.attrs["schema_version"] = _version_attr(v.version)
    handle.attrs["created_utc"] = _text_attr("2026-11-23T10:00:00Z", v.attrs)
    handle.attrs["software_version"] = _text_attr("foreign-writer 0.1", v.attrs)
    handle.create_group("protocol").attrs["toml"] = (ROOT / "protocols" / "face_up.toml"
                                                     ).read_text()
    bench = handle.create_group("bench")
    bench.attrs["simulated"] = True
    bench.attrs["digitizer"] = "synthetic"
    bench.create_group("calibration").attrs["force_n_per_v"] = 10.0
    steps = handle.create_group("steps")
    rng = np.random.default_rng(v.seed + 1000)
    for k in range(4):
        st = steps.create_group(f"{k:06d}")
        st.attrs.update({"setup": "S4-a", "frequency_hz": float(d["f"][k]),
                         "input": d["ins"].name[0], "started_at_s": 2.3 * k, "status": "ok"})
        echoes = st.create_group("echoes")
        ds = echoes.create_dataset("ch1", data=rng.integers(-300, 300, (5, 32)).astype(np.int16))
        ds.attrs.update({"sample_rate_hz": 500e6, "prf_hz": 5000.0, "delay_s": 10e-6,
                         "volts_per_count": 1e-3, "volts_offset": 0.0,
                         "speed_of_sound_m_s": 1540.0, "output": d["outs"].name[0]})
        echoes.create_dataset("ch1_trigger_offset_s", data=np.zeros(5))
        st.create_group("displacement").create_dataset("ch1", data=np.zeros(5))
        st.create_group("phasor").create_dataset("ch1", data=np.complex128(d["H"][k, 0, 0]))
        st.create_dataset("force_phasor_n", data=np.complex128(1.0 + 0j))


def write_variant(path: str | Path, v: Variant, d: dict | None = None) -> Path:
    """Write one variant to ``path`` with h5py only (design 4.2 text), return the path."""
    path = Path(path)
    d = synthesise(v) if d is None else d
    if v.bad == "not_hdf5":
        path.write_text("frequency_hz,H\n5,0\n")
        return path
    f, H, std = d["f"], d["H"], d["std"]
    if v.bad == "all_nan":
        H = np.full(H.shape, complex(np.nan, np.nan))
    if v.bad == "H_transposed":
        H, std = H.transpose(0, 2, 1).copy(), std.transpose(0, 2, 1).copy()
    if v.bad == "few_lines":
        f, H, std = f[:3], H[:3], std[:3]
    if v.bad == "freq_len":
        f = f[:-1]
    kw = {"compression": "gzip", "shuffle": True} if v.compress else {}
    with h5py.File(path, "w") as handle:
        if v.root == "session":
            _write_session_parts(handle, v, d)
        elif v.root == "frf":
            handle.attrs["schema"] = _text_attr("pelvislab-frf", v.attrs)
            handle.attrs["schema_version"] = _version_attr(v.version)
        if v.extras:
            handle.attrs["writer"] = "foreign lab script"
            handle.create_group("notes").attrs["operator"] = "N.N."
            handle.create_dataset("temperature_c", data=np.array([21.5, 21.7]))
        if v.bad == "no_frf":
            return path
        if v.bad == "frf_dataset":
            handle.create_dataset("frf", data=np.abs(np.nan_to_num(H)))
            return path
        g = handle.create_group("frf")
        g.attrs["schema"] = _text_attr("pelvislab-frf", v.attrs)
        g.attrs["schema_version"] = _version_attr(v.version)
        g.attrs["units"] = _text_attr("m/N", v.attrs)
        g.create_dataset("frequency_hz", data=f.astype(v.real_dtype), **kw)
        if v.bad == "real_H":
            g.create_dataset("H", data=H.real.astype(np.float64), **kw)
        elif v.bad == "H_pairs":
            g.create_dataset("H", data=np.stack([H.real, H.imag], axis=-1), **kw)
        else:
            _complex_dataset(g, "H", H, v.complex_fields, **kw)
        if v.with_std:
            g.create_dataset("H_std", data=std.astype(np.float64), **kw)
        if v.acquired:
            g.create_dataset("acquired_at_s", data=d["acquired"].astype(v.real_dtype))
        _write_points(g.create_group("outputs"), d["outs"], v, kw)
        _write_points(g.create_group("inputs"), d["ins"], v, kw)
        if v.extras:
            g.attrs["window"] = "none"
            g.attrs["averages"] = np.int16(10)
            g.attrs["estimator"] = np.bytes_(b"H1")
            g.create_dataset("coherence", data=np.ones(H.shape))
            g.create_group("raw").attrs["note"] = "unknown to pelvislab"
    return path


def run_diagnose(path: Path, out: Path, plots: bool = True) -> dict:
    """``pelvislab gap diagnose`` on ``path`` (nice 10, one BLAS thread): exit code, stderr's
    last line, wall time, verdict, gap_before and the best candidate."""
    exe = ROOT / ".venv" / "bin" / "pelvislab"
    cmd = ["nice", "-n", "10", str(exe), "gap", "diagnose", str(path), "--json", str(out)]
    if not plots:
        cmd.append("--no-plots")
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", QT_QPA_PLATFORM="offscreen")
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    row = {"file": path.name, "exit": proc.returncode, "wall_s": time.perf_counter() - t0,
           "stderr": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else "",
           "stderr_lines": len(proc.stderr.strip().splitlines())}
    if proc.returncode == 0 and out.exists():
        doc = json.loads(out.read_text())
        best = doc["candidates"][0] if doc["candidates"] else {}
        row.update(verdict=doc["verdict"], gap_before=doc["gap_before"],
                   best=best.get("effect"), best_gap_after=best.get("gap_after"),
                   noise=doc.get("noise", {}).get("source"))
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("outdir", type=Path)
    p.add_argument("--run", action="store_true", help="run gap diagnose on every file")
    p.add_argument("--only", help="comma-separated variant names")
    args = p.parse_args(argv)
    args.outdir.mkdir(parents=True, exist_ok=True)
    only = set(args.only.split(",")) if args.only else None
    rows = []
    for v in VARIANTS:
        if only and v.name not in only:
            continue
        path = write_variant(args.outdir / f"{v.name}.h5", v)
        if not args.run:
            print(path)
            continue
        out = args.outdir / f"{v.name}.json"
        out.unlink(missing_ok=True)
        row = run_diagnose(path, out, plots=v.name in ("v01_plain", "v06_log_grid"))
        row.update(expect=v.expect, note=v.note, load=os.getloadavg()[0])
        rows.append(row)
        print(json.dumps(row), flush=True)
    if rows:
        (args.outdir / "summary.json").write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
