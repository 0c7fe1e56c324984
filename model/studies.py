"""Simulation studies of thesis ch. 6.2 and ch. 7, reproduced on the appendix E model.

The thesis' ch. 6-7 spring layouts have no published geometry, so every study here uses the
appendix E model (``model/appendix_e.toml``) and the landmark estimates of
``protocols/landmarks.toml``; numbers are comparable in kind, not digit by digit.

* ch. 6.2: perturbation bins (each parameter p_i = p0_i (1 + dp u_i), u_i ~ U(-1, 1), 10 sets
  per bin), frequency grid 5-300 Hz at df, layouts of tables 6.3/6.4, the two noise types
  (sensor position +-2 mm across the beam, orientation 0-10 deg giving the 1/cos gain of
  fig. 6.9), the eq. 6.10 cost with a/b ratios against our strategy;
* ch. 7: the 7 (f_k, f_c) cases of table 7.2, fig. 7.1 layout, 10 Hz grid to 550 Hz
  (w_max = 2 pi 550), additive noise of eq. 7.4 optional; version A (constant matrices)
  and B (f_k, f_c identified), errors in parameters, frequencies, damping ratios and MAC.

Each run is a pure function of a :class:`Run` (seeded), so runs are independent and go
through any ``concurrent.futures`` executor (:func:`run_all`): a local process pool
(:func:`make_executor`) or a dask.distributed cluster (:func:`dask_executor`).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Executor, ProcessPoolExecutor
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from pelvislab.acquisition.frfset import Channels
from pelvislab.model.identification import (
    CONTINUATION,
    ResidualSpec,
    Strategy,
    frf_with_jacobian,
    identify_frf,
    one_blas_thread,
)
from pelvislab.model.identification_pelvis import LAYOUTS, layout_channels, pelvis_problem
from pelvislab.model.pelvis import load_model

THESIS_CH6 = {
    "mass_error_pct": {"10": 2.5, "20": 5.0, "30": 7.0},
    "stiffness_damping_error_pct": "30-60",
    "dp40": "impairs the identification (discarded)",
    "a_over_b_chosen": 0.1,
    "df_hz": "1.25 ~ 2.5; 5 much worse",
}
THESIS_CH7_B = ("cases 1-4, 6 perfect (< 0.5 % parameter error); "
                "cases 5 and 7 fail after 2000 starts")
CH7_CASES = ((0, 0), (0, 0.5), (0, 1), (0.5, 0), (1, 0), (0.5, 0.5), (1, 1))


@dataclass(frozen=True)
class Run:
    """One simulated identification (all inputs; the result depends on nothing else)."""

    study: str
    label: str
    seed: int
    dp: float = 0.2  # perturbation bin of the true parameters (ch. 6.2)
    layout: str = "face_up"
    f_start_hz: float = 5.0
    f_stop_hz: float = 300.0
    df_hz: float = 2.5
    position_mm: float = 0.0  # noise a): sensor position error, uniform +-, across the beam
    orientation_deg: float = 0.0  # noise b): tilt uniform in [0, deg], gain 1/cos
    gaussian_g: float = 0.0  # eq. 7.4: g as a fraction of max |H|
    f_k: float = 0.0
    f_c: float = 0.0
    f_max_hz: float = 300.0
    version_b: bool = False
    start_dp: float = 0.0  # start = nominal (0) or random +-start_dp around it (ch. 7)
    residual: str = "log"
    a_over_b: float = 1.0
    strategy: str = "continuation"  # or "plain" (one least-squares run, as the thesis)
    max_starts: int = 8


@dataclass
class Outcome:
    """Result of one :class:`Run`: relative parameter errors and figures of merit."""

    run: Run
    names: list[str]
    true: list[float]
    identified: list[float]
    rel_error: list[float]
    converged: bool
    rms_residual: float
    wall_time_s: float
    cpu_time_s: float
    evaluations: int
    starts: int
    extra: dict[str, object] = field(default_factory=dict)

    @property
    def max_error(self) -> float:
        """Largest relative parameter error (including f_k, f_c as absolute error)."""
        return float(np.max(np.abs(self.rel_error)))

    def as_dict(self) -> dict[str, object]:
        """JSON-ready dict."""
        d = asdict(self)
        d["max_error"] = self.max_error
        return d


def _noisy_channels(ch: Channels, rng: np.random.Generator, position_mm: float,
                    orientation_deg: float) -> tuple[Channels, np.ndarray]:
    """Sensor channels displaced across the beam and the 1/cos gains of fig. 6.9."""
    pos = ch.position_m.copy()
    for i, d in enumerate(ch.direction):
        # two unit vectors perpendicular to the beam
        a = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
        a /= np.linalg.norm(a)
        b = np.cross(d, a)
        pos[i] += 1e-3 * position_mm * (rng.uniform(-1, 1) * a + rng.uniform(-1, 1) * b)
    gain = 1.0 / np.cos(np.deg2rad(rng.uniform(0.0, orientation_deg, len(ch))))
    return Channels(ch.name, ch.bone, pos, ch.direction), gain


@one_blas_thread
def execute(run: Run) -> Outcome:
    """Simulate the measurement of ``run`` and identify it; pure, seeded."""
    t0, c0 = time.perf_counter(), time.process_time()
    rng = np.random.default_rng(run.seed)
    model = load_model(None)
    outs, ins, mask = layout_channels(LAYOUTS[run.layout])
    problem, space = pelvis_problem(model, outs, ins, f_max_hz=run.f_max_hz)
    nominal = space.values()
    true = nominal * (1 + run.dp * rng.uniform(-1, 1, nominal.size))
    f = np.arange(run.f_start_hz, run.f_stop_hz + 1e-9, run.df_hz)
    # measurement: possibly from displaced / tilted sensors (the model does not know)
    meas_outs, gain = _noisy_channels(outs, rng, run.position_mm, run.orientation_deg)
    meas_problem, _ = pelvis_problem(model, meas_outs, ins, f_max_hz=run.f_max_hz)
    H, _ = frf_with_jacobian(meas_problem.assemble(true), meas_problem.outputs,
                             meas_problem.inputs, f, f_k=run.f_k, f_c=run.f_c,
                             omega_max_rad_s=problem.omega_max_rad_s, jacobian=False)
    H = H * gain[None, :, None]
    if run.gaussian_g:
        g = run.gaussian_g * np.nanmax(np.abs(H[:, mask]))
        H = H + g * rng.standard_normal(H.shape) * np.exp(2j * np.pi * rng.uniform(size=H.shape))
    H = np.where(mask[None], H, np.nan)
    start = nominal * (1 + run.start_dp * rng.uniform(-1, 1, nominal.size))
    ratio = run.a_over_b
    spec = ResidualSpec(run.residual, a=ratio / (1 + ratio), b=1 / (1 + ratio))
    if run.strategy == "plain":
        strategy = Strategy(max_starts=1, max_nfev=300)
    else:
        noise_free = not (run.position_mm or run.orientation_deg or run.gaussian_g)
        # noise-free: the global minimum has zero misfit, so keep starting until found;
        # noisy: stop when a second start lands on the best minimum again
        strategy = Strategy(max_starts=run.max_starts, spread=0.3, stages=CONTINUATION,
                            stop_rms=1e-6 if noise_free else None,
                            stop_when_reproduced=not noise_free, seed=run.seed)
    res = identify_frf(problem, f, H, start=start, residual=spec, strategy=strategy,
                       version_b=run.version_b)
    true_all = list(true) + ([run.f_k, run.f_c] if run.version_b else [])
    err = [(v - t) / t for v, t in zip(res.values[:nominal.size], true, strict=True)]
    if run.version_b:
        err += [res.values[-2] - run.f_k, res.values[-1] - run.f_c]
    extra: dict[str, object] = {}
    if run.study == "ch7":
        extra = _modal_errors(space, true, res.values, run)
    return Outcome(run, list(res.names), [float(x) for x in true_all],
                   [float(x) for x in res.values], [float(e) for e in err],
                   bool(res.converged), float(res.extra["rms_residual"]),
                   time.perf_counter() - t0, time.process_time() - c0,
                   int(res.evaluations), int(res.starts), extra)


def _modal_errors(space: object, true: np.ndarray, identified: np.ndarray, run: Run
                  ) -> dict[str, object]:
    """Ch. 7 figures: frequency, damping-ratio error (%) and MAC of the identified model's
    modes against the true (frequency-dependent) system's, paired by MAC, for the true
    modes inside the measured band."""
    from pelvislab.model.modal import complex_modes, mac, pair_modes

    n = len(true)
    mt = space.matrices(true)  # type: ignore[attr-defined]
    mi = space.matrices(np.asarray(identified[:n]))  # type: ignore[attr-defined]
    fk_i, fc_i = (identified[n], identified[n + 1]) if run.version_b else (0.0, 0.0)
    a = complex_modes(mt.M, mt.K, mt.C, f_k=run.f_k, f_c=run.f_c, f_max_hz=run.f_max_hz)
    b = complex_modes(mi.M, mi.K, mi.C, f_k=fk_i, f_c=fc_i, f_max_hz=run.f_max_hz)
    pairs = pair_modes(a.shapes, b.shapes)
    m = mac(a.shapes, b.shapes)
    df, dz, macs = [], [], []
    band = []
    for p in pairs:
        fa, fb = a.damped_frequencies_hz[p.a], b.damped_frequencies_hz[p.b]
        if not run.f_start_hz <= fa <= run.f_stop_hz:
            continue  # modes outside the measured band are not constrained by the data
        band.append(float(fa))
        za, zb = a.damping_ratios[p.a], b.damping_ratios[p.b]
        df.append(float(100 * (fb - fa) / fa))
        dz.append(float(100 * (zb - za) / za) if za > 0 else float("nan"))
        macs.append(float(m[p.a, p.b]))
    return {"frequency_error_pct": df, "damping_ratio_error_pct": dz, "mac": macs,
            "true_frequencies_hz": band}


def one_thread_env() -> None:
    """Worker processes inherit this: one BLAS thread each (many small LAPACK calls)."""
    for var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")


def make_executor(workers: int | None = None) -> Executor:
    """A process pool of ``workers`` (default: CPU count) single-BLAS-thread workers."""
    import multiprocessing

    one_thread_env()
    return ProcessPoolExecutor(max_workers=workers or os.cpu_count() or 1,
                               mp_context=multiprocessing.get_context("spawn"))


@contextmanager
def dask_executor(address: str, connect_timeout_s: float = 5.0) -> Iterator[Executor]:
    """A ``concurrent.futures`` executor on the dask.distributed scheduler at ``address``
    (``distributed.Client(address).get_executor()``), closed on exit. Workers run
    :func:`execute` (each run seeded, so results equal the local pool's).

    Raises ``RuntimeError`` if ``distributed`` is not installed and ``ConnectionError`` if
    the scheduler does not answer within ``connect_timeout_s``.
    """
    try:
        from distributed import Client
    except ImportError as exc:
        raise RuntimeError("--dask needs dask.distributed: pip install 'pelvislab[cluster]' "
                           f"({exc})") from None
    try:
        client = Client(address, timeout=connect_timeout_s)
    except (OSError, TimeoutError, ValueError) as exc:
        raise ConnectionError(f"cannot reach the dask scheduler at {address!r} within "
                              f"{connect_timeout_s:g} s: {exc}") from None
    try:
        yield client.get_executor()
    finally:
        client.close()


def run_all(runs: Iterable[Run], executor: Executor | None = None,
            progress: Callable[[str], None] | None = None) -> list[Outcome]:
    """Execute independent runs (in order of ``runs``) through ``executor`` (or inline)."""
    runs = list(runs)
    if executor is None:
        out = []
        for i, r in enumerate(runs):
            out.append(execute(r))
            if progress:
                progress(f"{i + 1}/{len(runs)} {r.label}")
        return out
    futures = [executor.submit(execute, r) for r in runs]
    out = []
    for i, fut in enumerate(futures):
        out.append(fut.result())
        if progress:
            progress(f"{i + 1}/{len(runs)} {runs[i].label}")
    return out


# --------------------------------------------------------------------------------------
# Study definitions


def bins_runs(dps: Iterable[float] = (0.1, 0.2, 0.3, 0.4), n_sets: int = 10, **kw: object
              ) -> list[Run]:
    """Ch. 6.2 perturbation bins: ``n_sets`` seeded parameter sets per bin."""
    return [Run("bins", f"dp={dp:g} set {k}", seed=1000 * int(round(100 * dp)) + k, dp=dp,
                **kw)  # type: ignore[arg-type]
            for dp in dps for k in range(n_sets)]


def ch6_runs(n_sets: int = 10) -> list[Run]:
    """The ch. 6.2 study: bins x (our strategy vs eq. 6.10 at a/b ratios) x df x noise x
    layout. Noise (both types together) as the thesis' step 1."""
    noise = {"position_mm": 2.0, "orientation_deg": 10.0}
    runs: list[Run] = []
    for r in bins_runs(n_sets=n_sets):
        runs.append(replace(r, study="ch6_ours_noisefree"))
        runs.append(replace(r, study="ch6_ours_noise", **noise))
    for ab in (0.01, 0.1, 1.0, 10.0, 100.0):
        for r in bins_runs((0.1, 0.2, 0.3), n_sets=min(n_sets, 2)):
            runs.append(replace(r, study=f"ch6_eq610_ab{ab:g}", residual="eq610",
                                a_over_b=ab, strategy="plain", **noise))
    for df in (1.25, 5.0):
        for r in bins_runs((0.1, 0.2, 0.3), n_sets=n_sets):
            runs.append(replace(r, study=f"ch6_ours_noise_df{df:g}", df_hz=df, **noise))
    for which, extra in (("position", {"position_mm": 2.0}),
                         ("orientation", {"orientation_deg": 10.0})):
        for r in bins_runs((0.1, 0.2, 0.3), n_sets=n_sets):
            runs.append(replace(r, study=f"ch6_ours_{which}_only", **extra))
    for layout in ("face_down", "full"):
        for r in bins_runs((0.1, 0.2, 0.3), n_sets=n_sets):
            runs.append(replace(r, study=f"ch6_ours_noise_{layout}", layout=layout, **noise))
    return runs


def ch7_runs(seed: int = 7) -> list[Run]:
    """Table 7.2 cases, versions A and B, from random +-10 % starts (as the thesis)."""
    runs = []
    for case, (fk, fc) in enumerate(CH7_CASES, start=1):
        for version_b in (False, True):
            runs.append(Run("ch7", f"case {case} version {'B' if version_b else 'A'}",
                            seed=seed + case, dp=0.0, layout="ch7", f_start_hz=10.0,
                            f_stop_hz=550.0, df_hz=10.0, f_k=fk, f_c=fc, f_max_hz=550.0,
                            version_b=version_b, start_dp=0.1))
    return runs


# --------------------------------------------------------------------------------------
# Summaries (pure: tables as lists of dicts and markdown text; the writer lives in
# docs/studies/run_studies.py)


def _pct(values: Iterable[float], q: float) -> float:
    v = np.asarray(list(values), float)
    return float(np.percentile(v, q)) if v.size else float("nan")


def summarise_ch6(outcomes: list[Outcome]) -> list[dict[str, object]]:
    """One row per (study, bin): success rate and error percentiles per parameter family."""
    rows = []
    keys = sorted({(o.run.study, o.run.dp) for o in outcomes})
    for study, dp in keys:
        sel = [o for o in outcomes if o.run.study == study and o.run.dp == dp]
        err = np.abs(np.array([o.rel_error for o in sel])) * 100
        rows.append({
            "study": study, "dp_pct": round(100 * dp), "n": len(sel),
            "success_pct": 100.0 * float(np.mean([o.max_error < 1e-3 for o in sel])),
            "mass_err_median_pct": _pct(err[:, 0:3].ravel(), 50),
            "mass_err_max_pct": float(err[:, 0:3].max()),
            "stiffness_err_median_pct": _pct(err[:, 3:15].ravel(), 50),
            "stiffness_err_p90_pct": _pct(err[:, 3:15].ravel(), 90),
            "damping_err_median_pct": _pct(err[:, 15:18].ravel(), 50),
            "median_wall_time_s": _pct([o.wall_time_s for o in sel], 50),
        })
    return rows


def summarise_ch7(outcomes: list[Outcome]) -> list[dict[str, object]]:
    """One row per case and version: parameter, frequency, damping-ratio errors, MAC."""
    rows = []
    for o in outcomes:
        e = o.extra
        freq = np.abs(e.get("frequency_error_pct", [np.nan]))
        zeta = np.abs(np.asarray(e.get("damping_ratio_error_pct", [np.nan]), float))
        macs = np.asarray(e.get("mac", [np.nan]), float)
        err = np.abs(np.array(o.rel_error[:18])) * 100
        rows.append({
            "case": o.run.label.split(" version")[0], "f_k": o.run.f_k, "f_c": o.run.f_c,
            "version": "B" if o.run.version_b else "A",
            "recovered": bool(o.max_error < 1e-3),
            "param_err_max_pct": float(err.max()),
            "c_sij_err_max_pct": float(err[15:17].max()),
            "freq_err_max_pct": float(np.nanmax(freq)),
            "zeta_err_max_pct": float(np.nanmax(zeta)) if np.isfinite(zeta).any() else None,
            "mac_min": float(np.nanmin(macs)),
            "f_k_identified": o.identified[18] if o.run.version_b else None,
            "f_c_identified": o.identified[19] if o.run.version_b else None,
            "starts": o.starts, "wall_time_s": o.wall_time_s,
        })
    return rows


def markdown_table(rows: list[dict[str, object]]) -> str:
    """A GitHub markdown table of ``rows`` (floats with 3 significant digits)."""
    if not rows:
        return "(no rows)\n"
    cols = list(rows[0])

    def fmt(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.3g}"
        return "" if v is None else str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r[c]) for c in cols) + " |" for r in rows]
    return "\n".join(lines) + "\n"
