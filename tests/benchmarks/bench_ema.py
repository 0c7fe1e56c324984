"""EMA: accuracy and speed of p-LSCF + LSFD against the truth and against sdypy-EMA's LSCF.

Cases (1 % proportional complex noise, seed 1): the pelvis model (appendix E) at the thesis'
ch. 11 layout (13 landmarks x 3 axes = 39 outputs), drive on the left iliac fossa (+ the
sacrum for the 2-input case), 5-300 Hz on a 0.25 Hz grid, the 2.5 Hz stepped-sine grid and a
non-uniform grid; and the real pyuff beam (accelerance -> receptance, 10-1000 Hz).
pelvislab selects poles automatically; sdypy-EMA (optional extra ``bench``) has no automatic
selection, so it is given the TRUE natural frequencies (``select_closest_poles``): an
advantage for it. sdypy's LSCF is FFT-based and single-input, so it runs only on uniform
grids with one input. Errors are max |relative error| over the in-band modes found (a mode
not found is counted, not scored); MAC is the minimum. The rows "with --refine" are the same
data with the p-LSCF poles refined by the pole/residue fit (``refine=True``, opt-in), and
"in its reported std" divides each damping error by the uncertainty the refinement reports.
Run: ``python -m pelvislab.tests.benchmarks ema``.
"""

from __future__ import annotations

import contextlib
import io
import time
import warnings
from pathlib import Path

import numpy as np

from pelvislab.tests.benchmarks.harness import Result

BEAM = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "real" / "pyuff_beam"


def _pelvis():
    from pelvislab.model.assembly import point_rows
    from pelvislab.model.frf import Points
    from pelvislab.model.landmarks import load_landmarks
    from pelvislab.model.modal import model_modes
    from pelvislab.model.pelvis import load_model
    from pelvislab.tests.test_ema_rigid_body import triaxial_geometry

    model = load_model()
    modes = model_modes(model)
    bones, pos, dirs = triaxial_geometry()
    cat = load_landmarks()
    drive = cat["iliac_fossa_drive_L"]
    inputs = Points((drive.bone, "sacrum"), [drive.position_m, cat["sacrum_x"].position_m],
                    [-drive.direction, [1.0, 0.0, 0.0]])
    outputs = Points(tuple(bones), pos, dirs)
    shapes = point_rows(model, bones, pos, dirs) @ modes.shapes
    fn = modes.natural_frequencies_hz
    inband = np.flatnonzero((fn >= 5) & (fn <= 300))
    return model, outputs, inputs, fn[inband], modes.damping_ratios[inband], shapes[:, inband]


def _noisy(H: np.ndarray, seed: int = 1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return H * (1 + 0.01 * (rng.normal(size=H.shape) + 1j * rng.normal(size=H.shape))
                / np.sqrt(2))


def _score(f_est, z_est, shapes_est, fn, zn, shapes):
    """(modes found within 5 %, max freq error %, max damping error %, min MAC) over found."""
    from pelvislab.model.modal import mac

    fe, ze, macs = [], [], []
    for r in range(fn.size):
        if len(f_est) == 0:
            continue
        j = int(np.argmin(np.abs(np.asarray(f_est) - fn[r])))
        if abs(f_est[j] / fn[r] - 1) >= 0.05:
            continue
        fe.append(abs(f_est[j] / fn[r] - 1))
        ze.append(abs(z_est[j] / zn[r] - 1))
        macs.append(float(mac(shapes[:, r], shapes_est[:, j])[0, 0]))
    if not fe:
        return 0, np.nan, np.nan, np.nan
    return len(fe), 100 * max(fe), 100 * max(ze), min(macs)


def _ours(f, H, refine=None):
    from pelvislab.model.ema import ema

    t = time.process_time()
    r = ema(f, H, refine=refine)
    return r.frequency_hz, r.damping_ratio, r.shapes, time.process_time() - t, r


def _damping_in_std(result, fn, zn) -> float:
    """Largest |damping error| of the in-band modes in units of the reported uncertainty."""
    worst = 0.0
    for r in range(fn.size):
        j = int(np.argmin(np.abs(result.frequency_hz - fn[r])))
        if abs(result.frequency_hz[j] / fn[r] - 1) < 0.05:
            ratio = abs(result.damping_ratio[j] - zn[r]) / result.damping_ratio_std[j]
            if not np.isfinite(ratio):
                return float("nan")  # a mode without an uncertainty: say so, not 0
            worst = max(worst, ratio)
    return worst


def _sdypy(f, H, approx_hz, lower, upper):
    """sdypy-EMA LSCF (order 60) + closest stable poles to approx_hz + its LSFD."""
    import sdypy.EMA as sdypy_ema

    t = time.process_time()
    with warnings.catch_warnings(), contextlib.redirect_stderr(io.StringIO()):
        warnings.simplefilter("ignore")
        m = sdypy_ema.Model(frf=H[:, :, 0].T, freq=f, lower=lower, upper=upper,
                            pol_order_high=60, frf_form="receptance")
        m.get_poles(show_progress=False)
        m.select_closest_poles(list(approx_hz))
        m.get_constants()
    return np.asarray(m.nat_freq), np.asarray(m.nat_xi), np.asarray(m.A), \
        time.process_time() - t


def _have_sdypy() -> bool:
    try:
        import sdypy.EMA  # noqa: F401
    except Exception:
        return False
    return True


def run() -> list[Result]:
    """Accuracy rows (ours, and sdypy where it applies) and CPU-time ratios."""
    from pelvislab.model.frf import frf

    results: list[Result] = []
    sdypy_ok = _have_sdypy()
    model, outputs, inputs, fn, zn, shapes = _pelvis()
    cases = [("pelvis 0.25 Hz 1 input", np.arange(5.0, 300.0 + 1e-9, 0.25), 1, True),
             ("pelvis 2.5 Hz 1 input", np.arange(5.0, 300.0 + 1e-9, 2.5), 1, True),
             ("pelvis 0.25 Hz 2 inputs", np.arange(5.0, 300.0 + 1e-9, 0.25), 2, False),
             ("pelvis non-uniform ~1 Hz 2 inputs",
              np.sort(np.random.default_rng(5).uniform(5.0, 300.0, 300)), 2, False)]
    for name, f, n_in, uniform in cases:
        H = _noisy(frf(model, f, outputs, inputs)[:, :, :n_in])
        fo, zo, so, to, _ = _ours(f, H)
        nf, fe, ze, mm = _score(fo, zo, so, fn, zn, shapes)
        *ref_out, res = _ours(f, H, refine=True)
        *_, ze_refined, _ = _score(*ref_out[:3], fn, zn, shapes)
        results += [Result(f"{name}: pelvislab modes found (of {fn.size})", nf, "",
                           target=f"{fn.size}, none spurious: {fo.size} selected"),
                    Result(f"{name}: pelvislab max freq error", fe, "%", target="<= 0.3"),
                    Result(f"{name}: pelvislab max damping error", ze, "%", target="<= 10"),
                    Result(f"{name}: the same with --refine (pole/residue fit)", ze_refined,
                           "%", target="<= 10"),
                    Result(f"{name}: --refine: largest damping error in its reported std",
                           _damping_in_std(res, fn, zn), "", target="~1-2 (one draw)"),
                    Result(f"{name}: pelvislab min MAC", mm, "", target=">= 0.98")]
        if uniform and sdypy_ok:
            fs, zs, As, ts = _sdypy(f, H, fn, 5.0, 300.0)
            nf, fe, ze, mm = _score(fs, zs, As, fn, zn, shapes)
            results += [Result(f"{name}: sdypy modes found (given the true f)", nf, ""),
                        Result(f"{name}: sdypy max freq error (found modes)", fe, "%"),
                        Result(f"{name}: sdypy max damping error", ze, "%"),
                        Result(f"{name}: sdypy min MAC", mm, ""),
                        Result(f"{name}: pelvislab CPU time", to, "s", baseline=ts,
                               baseline_name="sdypy-EMA")]
        else:
            results.append(Result(f"{name}: pelvislab CPU time", to, "s"))
    if BEAM.is_dir():
        A = np.stack([np.loadtxt(BEAM / f"meas_point_{k}.txt", dtype=complex)
                      for k in (1, 2, 3)], axis=1)
        f = np.arange(A.shape[0], dtype=float)
        sel = (f >= 10) & (f <= 1000)
        H = (-A[sel] / (2 * np.pi * f[sel, None]) ** 2)[:, :, None]
        fo, zo, _, to, _ = _ours(f[sel], H)
        results.append(Result("beam 10-1000 Hz: pelvislab modes found", float(fo.size), "",
                              target="6 (52..959 Hz)"))
        if sdypy_ok:
            fs, zs, _, ts = _sdypy(f[sel], H, fo, 10.0, 1000.0)
            diff = np.max(np.abs(fs / fo - 1)) * 100 if fo.size else np.nan
            results += [Result("beam: max |f_pelvislab / f_sdypy - 1|", float(diff), "%"),
                        Result("beam: max |zeta_pelvislab / zeta_sdypy - 1|",
                               float(np.max(np.abs(zo / zs - 1)) * 100), "%"),
                        Result("beam: pelvislab CPU time", to, "s", baseline=ts,
                               baseline_name="sdypy-EMA")]
    if not sdypy_ok:
        results.append(Result("sdypy-EMA not installed (pip install '.[bench]'): no baseline",
                              0.0, ""))
    return results
