"""``pelvislab identify``: parameter identification from /frf (thesis ch. 6-7, design 4.5)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from pelvislab.app.commands._common import (
    check_new_output,
    comma_list,
    incomplete_session_warning,
    infinite_as_unmeasured,
    print_json,
    require_response,
    write_json,
)

#: a/b of eq. 6.10 when not given: the thesis' choice after its ch. 6.2 study (smaller
#: ratios identified stiffness and damping better), used for ch. 7's updating.
EQ610_A_OVER_B = 0.1

IDENTIFY_SCHEMA = "pelvislab-identify"
IDENTIFY_SCHEMA_VERSION = 2  # 1: design 4.5 as written (std always a float)


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``identify`` to the CLI."""
    p = subparsers.add_parser(
        "identify", help="identify stiffness, damping and mass from a session's FRFs",
        description="Update the pelvis model to the measured FRFs (/frf of a session or an "
        "FRF-only file). Writes the result JSON (design 4.5) to OUT, or prints it on stdout "
        "with --json - (nothing else goes to stdout); notes and progress go to stderr.",
    )
    p.add_argument("session", metavar="S.h5", help="session or FRF-only file")
    p.add_argument("--method", choices=("frf", "modal"), default="frf",
                   help="frf: FRF updating (ch. 6.2); modal: modal updating (ch. 6.1, app. C) "
                   "on peak-picked modes")
    p.add_argument("--params", metavar="NAMES",
                   help="comma-separated parameters to identify (design 4.5 names); default: "
                   "all (frf) or the stiffnesses (modal: frequencies and shapes cannot tell "
                   "a common scale of masses and stiffnesses)")
    p.add_argument("--model", metavar="M.toml", help="starting model; default: thesis appendix E")
    p.add_argument("--symmetric", action="store_true",
                   help="impose left/right symmetry (k_io, c_sij, m_innominate, ...)")
    p.add_argument("--version-b", action="store_true",
                   help="also identify the eq. 7.2-7.3 factors f_k and f_c (ch. 7 version B; "
                   "--method frf). Without it a fit with the std misfit is tested against "
                   "version B and is not converged when version B fits significantly better")
    p.add_argument("--residual", choices=("auto", "log", "std", "eq610"), default=None,
                   help="misfit (default auto): auto = std, weighted by the file's H_std "
                   "or, without it, by the noise estimated from the data (third differences along "
                   "frequency; JSON 'noise' says which); log = relative misfit")
    p.add_argument("--a-b", type=float, default=None, metavar="RATIO",
                   help="ratio a/b of real to imaginary weights (eq. 6.10: default 0.1, the "
                   "thesis' choice in ch. 6-7; log residual: log-magnitude to phase, "
                   "default 1)")
    p.add_argument("--starts", type=int, default=None, metavar="N",
                   help="maximum number of starts of the global strategy (the JSON's "
                   "'starts' counts every fit made, the rescues and refits after them "
                   "included)")
    p.add_argument("--seed", type=int, default=None,
                   help="random seed of the multi-start (default 0)")
    p.add_argument("--gain-std", type=float, default=None, metavar="FRACTION",
                   help="standard uncertainty of each FRF's gain (a chain error common to its "
                   "lines), in the weights and the std; default 0.003 (the chain's ±0.5 %% "
                   "tolerance) for --method frf; 0: the std are the noise's share only")
    p.add_argument("--calibration-std", type=float, default=None, metavar="FRACTION",
                   help="standard uncertainty of the drive chain's calibration (N/V), one "
                   "gain common to every FRF (e.g. 0.02), added to the std; default: the "
                   "one the session's bench file stated, else 0")
    p.add_argument("--profile", metavar="NAMES",
                   help="profile likelihood of these masses, springs or dampings "
                   "(comma-separated design 4.5 names, or 'weak': those whose std is at "
                   "least 10 %% of their value or undetermined): the chi2 with each held "
                   "over a walk of values, the others refitted; its 95 %% interval without "
                   "the linearisation, and any second or lower minimum (the fit is made "
                   "again from a lower one; JSON 'profile'; std misfit, --method frf)")
    p.add_argument("--json", required=True, metavar="OUT",
                   help="write the result JSON here ('-' for stdout)")
    p.set_defaults(handler=_identify)


def _progress(enabled: bool):  # noqa: ANN202 - Callable[[str], None] | None
    if not enabled:
        return None

    def report(text: str) -> None:
        print(f"identify: {text}", file=sys.stderr, flush=True)

    return report


@dataclass
class IdentificationReport:
    """One identification of a file: the design 4.5 JSON, the measured FRFs and the model's
    FRFs at the identified parameters (for measured-vs-model plots)."""

    document: dict[str, Any]
    frf: Any  # pelvislab.acquisition.frfset.FrfSet
    model_H: Any  # (n_f, n_out, n_in) complex, m/N
    converged: bool
    message: str

    def to_json(self) -> dict[str, Any]:
        """The JSON document written by ``pelvislab identify --json``."""
        return self.document


def identify_file(path: str | Path, method: str = "frf", params: list[str] | None = None,
                  model_path: str | Path | None = None,
                  progress: Callable[[str], None] | None = None, *, symmetric: bool = False,
                  version_b: bool = False, residual: str | None = None,
                  a_b: float | None = None,
                  starts: int | None = None, seed: int | None = None,
                  gain_std: float | None = None,
                  calibration_std: float | None = None,
                  profile: list[str] | None = None) -> IdentificationReport:
    """Identify the pelvis model's parameters from the /frf of ``path`` (session or FRF-only).

    The one entry point of the CLI and the GUI's replay view; the numerics are
    :func:`pelvislab.model.identification.identify_frf` / ``identify_modal``.
    ``gain_std``: each FRF's gain uncertainty (``identify_frf(gain_std=)``); None: the
    measurement chain's :data:`DEFAULT_GAIN_STD` for the FRF fit, 0 for modal updating.
    ``residual``, ``a_b``, ``starts``, ``seed`` shape the FRF fit only: given with modal
    updating they are refused (they were ignored without a word). None: ``residual``
    auto, ``seed`` 0.
    ``calibration_std``: relative standard uncertainty of the drive chain's calibration,
    one gain common to every FRF (``identify_frf(chain_gain_std=)``); None: the session's
    recorded one (:func:`recorded_calibration_std`), else 0.
    ``profile``: masses, springs or dampings (``"weak"`` among them: those of
    :func:`pelvislab.model.identification.weak_parameters`) whose profile likelihood is
    added (:func:`_profiled`); FRF fit with the std misfit only.
    """
    import numpy as np

    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.identification import (
        ResidualSpec,
        Strategy,
        default_strategy,
        frf_with_jacobian,
        identify_frf,
    )
    from pelvislab.model.identification_modal import (
        identify_modal,
        modes_from_frf,
        picking_frfs,
        picking_lines,
    )
    from pelvislab.model.identification_pelvis import pelvis_problem
    from pelvislab.model.pelvis import load_model

    frf = read_frf(path)
    infinite_note = infinite_as_unmeasured(frf)
    frf, left_out_note = modelled_channels(frf, path)
    model = load_model(model_path)
    problem, _ = pelvis_problem(model, frf.outputs, frf.inputs, symmetric=symmetric)
    free = list(params) if params else None
    if free is not None:
        repeated = sorted({n for n in free if free.count(n) > 1})
        if repeated:
            # fitted as two parameters, the pair unresolved (each std n/a) and "converged"
            raise ValueError(f"parameter(s) {repeated} named more than once")
        unknown = [n for n in free if n not in problem.names]
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown}; choose from "
                             f"{', '.join(problem.names)}")
    if profile:
        _check_profile_names(profile, free if free is not None else list(problem.names),
                             method, residual)
    try:
        require_response(frf.H)
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from None
    H_std, std_note = frf.H_std, None
    if H_std is not None and not np.any(
            np.isfinite(frf.H) & np.isfinite(H_std) & (H_std > 0)):
        # zeros or NaN written for "unknown" (design 4.2 makes H_std optional): read as absent
        H_std, std_note = None, ("H_std holds no positive finite value on the measured "
                                 "lines: ignored")
    f_k, f_c = model.frequency_dependence.f_k, model.frequency_dependence.f_c
    calibration_note = restart_note = profile_note = None
    if calibration_std is None:
        calibration_std, calibration_source, calibration_note = recorded_calibration_std(
            path, frf.frequency_hz[np.isfinite(frf.H).any(axis=(1, 2))])
    else:
        calibration_source = "option"
    if method == "modal":
        if gain_std:
            raise ValueError("--gain-std applies to --method frf (the FRF fit)")
        if version_b:
            # it was dropped without a word (exit 0, no f_k, f_c in the JSON): audit
            raise ValueError("--version-b applies to --method frf (the FRF fit; modal "
                             "updating holds the model file's f_k, f_c)")
        # options of the FRF fit's misfit and multi-start: modal updating has neither, and
        # they were dropped without a word (exit 0; session 41's note)
        fit_only = [flag for flag, given in (
            ("--residual", residual is not None), ("--a-b", a_b is not None),
            ("--starts", starts is not None), ("--seed", seed is not None)) if given]
        if fit_only:
            raise ValueError(f"{', '.join(fit_only)} appl{'ies' if len(fit_only) == 1 else 'y'}"
                             " to --method frf (the FRF fit's misfit and starts; modal "
                             "updating fits picked modes from one start)")
        gain_std = 0.0
        if calibration_source == "option" and calibration_std:
            raise ValueError("--calibration-std applies to --method frf (the FRF fit)")
        calibration_note = None
        # the FRFs' noise enters the picked shapes' uncertainty: the file's H_std, else
        # the noise the data show (as the FRF fit's)
        noise_source = "H_std"
        if H_std is None:
            from pelvislab.model.gap import estimate_noise

            H_std, noise_source = estimate_noise(frf.H, frf.frequency_hz), "estimated"
        try:
            data = modes_from_frf(frf.frequency_hz, frf.H, H_std=H_std)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None
        noise_note = _dropped_lines_note(frf, picking_lines(frf.H), picking_frfs(frf.H))
        result = identify_modal(problem, data, free=free, progress=progress, f_k=f_k, f_c=f_c)
        extra: dict[str, Any] = {"method": "modal", "noise": noise_source,
                                 "modes_hz": [float(f) for f in data.frequency_hz]}
    elif method == "frf":
        kind = residual or "auto"
        noise_source = "H_std" if H_std is not None else None
        noise_note = None
        if kind == "auto":
            kind = "std"
            if H_std is None:
                # weighted by the noise the data show (third differences along frequency,
                # absolute or proportional to |H|: the gap diagnosis' estimate), not by a
                # relative misfit, which weighs a noisy anti-resonance like a resonance
                # peak. Measured on three simulated-chain sessions without their H_std:
                # median parameter error 0.36-1.62 % (log: 1.32-3.58 %), largest 11-90 %
                # (log: 73-145 %); docs/identification.md
                from pelvislab.model.gap import estimate_noise

                H_std, noise_source = estimate_noise(frf.H, frf.frequency_hz), "estimated"
                noise_note = _unestimated_noise_note(frf)
        if kind == "std" and H_std is None:
            raise ValueError(f"{path}: --residual std needs H_std in /frf"
                             + (f" ({std_note})" if std_note else ""))
        n_free = len(free) if free is not None else len(problem.names)
        lines = np.isfinite(frf.H).any(axis=(1, 2))
        n_residuals = 2 * int(np.isfinite(frf.H).sum())  # real and imaginary parts
        # mass, damping and stiffness act alike at one frequency (-w^2 M + i w C + K)
        if int(lines.sum()) < 3 or n_residuals < n_free:
            raise ValueError(
                f"{path}: {int(lines.sum())} measured frequency line(s), "
                f"{n_residuals // 2} FRF value(s), cannot identify {n_free} parameters "
                "(needs >= 3 lines and at least as many real and imaginary parts as "
                "parameters); measure more lines or free fewer parameters (--params)")
        if a_b is not None and kind == "std":
            # it was dropped without a word (exit 0, the default fit): review 66
            raise ValueError("--a-b applies to --residual eq610 or log (the std misfit "
                             "weighs real and imaginary parts by H_std alone)")
        if a_b is None:
            # eq. 6.10 with the thesis' weights a/b = 0.1 (ch. 6.2, used in ch. 7); the
            # default was 1 for every residual (thesis fidelity review, session 36)
            a_b = EQ610_A_OVER_B if kind == "eq610" else 1.0
        if not (np.isfinite(a_b) and a_b > 0):
            raise ValueError(f"--a-b {a_b}: must be a finite ratio > 0")
        spec = ResidualSpec(kind, a=a_b / (1 + a_b), b=1 / (1 + a_b))
        if gain_std is None:
            gain_std = DEFAULT_GAIN_STD
        strategy = default_strategy(kind, starts=starts, seed=0 if seed is None else seed)

        def fit_from(start: Any) -> Any:
            return identify_frf(
                problem, frf.frequency_hz, frf.H, H_std, free=free, residual=spec,
                strategy=strategy, version_b=version_b, start_freq_dep=(f_k, f_c),
                progress=progress, gain_std=gain_std, chain_gain_std=calibration_std,
                start=start)

        t_fit = time.perf_counter()
        result = fit_from(None)
        if kind == "std" and free is None:
            result, restart_note = _from_the_global_base_fit(
                problem, frf, H_std, model, result, fit_from, progress, gain_std=gain_std,
                held_freq_dep=(f_k, f_c))
        extra = {"method": "frf", "noise": noise_source if kind == "std" else None,
                 "gain_std": float(gain_std),
                 "calibration_std": float(calibration_std),
                 "calibration_std_source": calibration_source}
        if kind == "std" and not version_b:
            untested = result
            result, extra["frequency_dependence"] = _tested_for_frequency_dependence(
                problem, frf, H_std, untested, (f_k, f_c), gain_std, progress)
            if (free is None and restart_note is None
                    and (extra["frequency_dependence"] or {}).get("significant")):
                # version B fitting significantly better may only say that version A
                # stopped in a local minimum: a foreign file without any frequency
                # dependence fitted at rms 1.014 (at the noise floor) with k_pubh 6x its
                # true value, 160 in chi2 above the truth; version B lowered it by 62 and
                # the fit was told to use version B (review 66). Version A again from the
                # gap diagnosis' global base fit, kept when it fits better, then tested
                again, restart_note = _from_the_global_base_fit(
                    problem, frf, H_std, model, untested, fit_from, progress,
                    gain_std=gain_std, held_freq_dep=(f_k, f_c), at_floor_too=True)
                if restart_note is not None:
                    result, extra["frequency_dependence"] = _tested_for_frequency_dependence(
                        problem, frf, H_std, again, (f_k, f_c), gain_std, progress)
                else:  # the tested fit stays; the effort spent on the other counts
                    result = replace(result, evaluations=again.evaluations,
                                     starts=again.starts)
        if profile:
            if kind != "std":
                raise ValueError("--profile needs the std misfit (chi2 in units of the "
                                 f"noise), not --residual {kind}")

            def polish_from(start: Any, freq_dep: tuple[float, float]) -> Any:
                # one start at the profile's point, no continuation: the minimum the
                # profile walked into is the question, not a global search; judged as
                # identify's own fit, at the noise floor (without the target any fit that
                # stopped was converged: review 61), with its damping rescue below it
                return identify_frf(
                    problem, frf.frequency_hz, frf.H, H_std, free=free, residual=spec,
                    strategy=Strategy(max_starts=1, hold_freq_dep_first=False,
                                      stop_at_noise_floor=True),
                    version_b=version_b, start_freq_dep=freq_dep, progress=progress,
                    gain_std=gain_std, chain_gain_std=calibration_std, start=start)

            def retested(fit: Any) -> Any:
                if version_b:
                    return fit
                fit, extra["frequency_dependence"] = _tested_for_frequency_dependence(
                    problem, frf, H_std, fit, (f_k, f_c), gain_std, progress)
                return fit

            result, extra["profile"], refits = _profiled_and_refitted(
                problem, frf, H_std, result, profile, (f_k, f_c), gain_std, progress,
                polish_from, retested)
            if refits:
                extra["profile_refits"] = refits
                profile_note = _profile_refits_note(refits)
        # the whole identification's time, the fallback's and the test's fits included
        result = replace(result, wall_time_s=time.perf_counter() - t_fit)
        if kind in ("eq610", "log"):  # the weights of the std residual are its H_std
            extra["a_over_b"] = float(a_b)
    else:
        raise ValueError(f"unknown method {method!r}; use frf or modal")
    doc = result.as_dict()
    doc.update(extra)
    doc["units"] = {"m_": "kg", "k_": "N/m", "c_": "N s/m", "f_": "1"}
    doc["source"] = str(path)
    # design 4.5 fixes {"value": v, "std": s}; std (and interval_95) may be null where the
    # data do not determine a parameter: version 2 of the document (docs/identification.md,
    # "Migration")
    doc["schema"], doc["schema_version"] = IDENTIFY_SCHEMA, IDENTIFY_SCHEMA_VERSION
    notes = [n for n in (left_out_note, infinite_note, std_note, noise_note,
                         calibration_note, restart_note, profile_note) if n]
    if notes:
        doc["notes"] = notes
    doc["model"] = model.name
    # The model's FRFs at the identified values, for measured-vs-model views.
    identified = dict(zip(result.names, np.asarray(result.values, dtype=float), strict=True))
    values = np.array([identified.get(n, v) for n, v in zip(problem.names, problem.nominal,
                                                             strict=True)])
    model_H, _ = frf_with_jacobian(
        problem.assemble(values), problem.outputs, problem.inputs, frf.frequency_hz,
        f_k=identified.get("f_k", f_k), f_c=identified.get("f_c", f_c),
        omega_max_rad_s=problem.omega_max_rad_s, jacobian=False)
    return IdentificationReport(doc, frf, model_H, bool(result.converged), str(result.message))


def _from_the_global_base_fit(problem: Any, frf: Any, H_std: Any, model: Any, result: Any,
                              fit_from: Callable[[Any], Any],
                              progress: Callable[[str], None] | None, *,
                              gain_std: float = 0.0,
                              held_freq_dep: tuple[float, float] = (0.0, 0.0),
                              at_floor_too: bool = False
                              ) -> tuple[Any, str | None]:
    """``result`` (an FRF fit with the std residual, every parameter free), or, when it
    missed the noise floor, the same fit started from the gap diagnosis' global base fit
    (:func:`pelvislab.model.gap.global_base_fit`) if that fits better; and a note saying
    so (None otherwise). identify's starts lie within +-30 % of the model file's values
    and its damping rescue scans only the dampings; the diagnosis' base fit also scans
    stiffness and mass scales and each damping group, and restarts around the best (a
    judge-like set without effect: identify rms 5.95 in a local minimum, k_pss_L 10x low;
    from that fit it reached the floor, session 45). ``at_floor_too``: also when it reached
    the floor (a fit at the floor may still be a local minimum: see identify_file)."""
    import numpy as np

    from pelvislab.model.gap import global_base_fit, prepare_data
    from pelvislab.model.gap_effects import base_structure
    from pelvislab.model.identification import noise_floor_rms, weighted_chi2

    known = np.isfinite(frf.H) & np.isfinite(H_std) & (H_std > 0)
    rms = float(result.extra["rms_residual"])
    if not at_floor_too and rms <= noise_floor_rms(2 * int(known.sum()), len(result.names)):
        return result, None
    if any(name not in base_structure(model).names for name in problem.names):
        # a parametrisation of its own (--symmetric): the base fit (design 4.5's names)
        # cannot start it, and was run for nothing (identify --symmetric 2.99 s, now 2.08 s,
        # on a simulated demo session without its H_std: review 45)
        return result, None
    try:
        data = prepare_data(frf.frequency_hz, frf.H, H_std, frf.outputs, frf.inputs)
        base = global_base_fit(data, model)
    except ValueError:
        return result, None  # the diagnosis cannot read these data: nothing to start from

    def spent(fit: Any, *others: Any) -> Any:
        # the whole identification's effort, a second fit's not kept included (its time:
        # identify_file's wall_time_s covers the whole identification)
        return replace(fit, evaluations=fit.evaluations + sum(o.evaluations for o in others),
                       starts=fit.starts + sum(o.starts for o in others))

    fitted = dict(zip(base.names, base.values, strict=True))
    start = np.array([fitted[name] for name in problem.names])
    ours = dict(zip(result.names, result.values, strict=True))
    held = (ours.get("f_k", held_freq_dep[0]), ours.get("f_c", held_freq_dep[1]))
    def chi2_at(values: Any) -> float:
        return weighted_chi2(problem, frf.frequency_hz, frf.H, H_std, values,
                             gain_std=gain_std, freq_dep=held)

    if not chi2_at(start) < chi2_at(np.array([ours[name] for name in problem.names])):
        return result, None  # no better a start: a second fit is not worth its time
    if progress:
        progress(f"rms residual {rms:.3g} above the noise floor: fitted again from the gap "
                 f"diagnosis' global base fit (fitted-line gap {base.gap_fit:.3g})")
    again = fit_from(start)
    rms_again = float(again.extra["rms_residual"])
    if not rms_again < rms * (1 - 1e-4):
        return spent(result, again), None
    return spent(again, result), (
        f"fitted from the gap diagnosis' global base fit (its grid over damping decades and "
        f"stiffness and mass scales; bounds x/÷ 10 around it): rms residual {rms:.3g} from "
        f"identify's own starts, {rms_again:.3g} from it")


def _tested_for_frequency_dependence(problem: Any, frf: Any, H_std: Any, result: Any,
                                     held_freq_dep: tuple[float, float], gain_std: float,
                                     progress: Callable[[str], None] | None
                                     ) -> tuple[Any, dict[str, Any] | None]:
    """``result`` (a version-A FRF fit with the std residual) and the JSON of its
    frequency-dependence test (:func:`pelvislab.model.identification.
    frequency_dependence_test`; None, not run, when a parameter is on its bound: version B
    then also stands in for the bound, e.g. f_k 4.8 for two springs at start x 10 on a set
    without frequency dependence, p 0.0005). A fit that converged otherwise is not
    converged when the test is significant, saying why: its parameters carry a model error
    that version B's two parameters explain (judge-like f_k sets had passed as converged
    at the noise floor with k_pubh 30 std off). A fit that did not converge is told to fit
    version B only when version B reaches the noise floor (from a local minimum, chi2/dof
    35, version B lowered the chi2 by 4e4 and stayed far from it)."""
    from pelvislab.model.identification import frequency_dependence_test

    if result.extra.get("on_bound"):
        return result, None
    test = frequency_dependence_test(problem, frf.frequency_hz, frf.H, H_std, result,
                                     start_freq_dep=held_freq_dep, gain_std=gain_std)
    # with the model file's own f_k, f_c held, version B may fit better by *removing*
    # frequency dependence (f_k 0.3, f_c 0.2 held on a simulated session without any: f_k
    # 0.007, f_c -0.0003 fitted, p 0): say from what they were released
    what = ("frequency-dependent stiffness and damping" if not any(held_freq_dep) else
            f"f_k, f_c released from the model file's {held_freq_dep[0]:.3g}, "
            f"{held_freq_dep[1]:.3g}")
    said = (f"{what} (version B, eq. 7.1-7.3) fit "
            f"{'significantly ' if test['significant'] else 'no '}better: chi2 "
            f"{test['delta_chi2']:.3g} lower with f_k {test['f_k']:.3g}, f_c {test['f_c']:.3g} "
            f"(F test p {test['p_value']:.2g}, limit {test['p_limit']:g})")
    if progress:
        progress(said)
    if not test["significant"]:
        return result, test
    if result.converged:
        return replace(result, converged=False, message=(
            f"{result.message}; {said}: the parameters carry a model error that two "
            "parameters explain; fit with --version-b, or run 'pelvislab gap diagnose' to "
            "tell it from other unmodelled effects").lstrip("; ")), test
    if test["at_noise_floor"]:
        return replace(result, message=(
            f"{result.message}; {said}, to the noise (chi2/dof {test['chi2_per_dof']:.3g}): "
            "fit with --version-b").lstrip("; ")), test
    return result, test


def _check_profile_names(profile: list[str], free: list[str], method: str,
                         residual: str | None) -> None:
    """Refuses a ``--profile`` that cannot run, before any fit: modal updating, a misfit
    other than std, names not among the fitted masses, springs and dampings."""
    if method != "frf":
        raise ValueError("--profile applies to --method frf (the FRF fit's chi2)")
    if residual not in (None, "auto", "std"):
        raise ValueError(f"--profile needs the std misfit (chi2 in units of the noise), not "
                         f"--residual {residual}")
    wrong = [n for n in profile if n != "weak" and (n not in free or n in ("f_k", "f_c"))]
    if wrong:
        raise ValueError(f"--profile {','.join(wrong)}: not a fitted mass, spring or damping; "
                         f"choose from {', '.join(free)} or 'weak'")


def _profiled(problem: Any, frf: Any, H_std: Any, result: Any, profile: list[str],
              held_freq_dep: tuple[float, float], gain_std: float,
              progress: Callable[[str], None] | None, refits: int = 0
              ) -> tuple[Any, dict[str, Any]]:
    """``result`` and the profile likelihood of each name in ``profile`` (``"weak"`` among
    them: the fit's weak parameters) as :func:`pelvislab.model.identification.profile_parameter`
    gives it, by name; ``result`` as :func:`_profile_verdict` judges it (not profiled, each
    profile ``None``, when a parameter is on its bound, saying so)."""
    from pelvislab.model.identification import profile_parameter, weak_parameters

    names = list(dict.fromkeys(  # in the order given, 'weak' expanded in its place
        m for n in profile for m in (weak_parameters(result) if n == "weak" else [n])))
    on_bound = list(result.extra.get("on_bound", ()))
    if on_bound:
        # the refits' ranges are centred on each start: the first would release the
        # parameter on its bound and credit the profiled one with the drop (review 59: a
        # chain with k0 on its bound had every point of m1's profile below the fit)
        return replace(result, message="; ".join([
            result.message, f"not profiled: {', '.join(on_bound)} on the bound of its "
            "range"]).lstrip("; ")), {name: None for name in (names or on_bound)}
    if progress and not names:
        progress("profile: no weak parameter (std under 10 % of the value) to profile")
    profiles = {name: profile_parameter(problem, frf.frequency_hz, frf.H, H_std, result, name,
                                        start_freq_dep=held_freq_dep, gain_std=gain_std,
                                        progress=progress)
                for name in names}
    return _profile_verdict(result, profiles, refits), profiles


def _profile_verdict(result: Any, profiles: dict[str, Any], refits: int = 0) -> Any:
    """``result`` as its ``profiles`` judge it: a profile that went below the fit's minimum
    makes it not converged, saying where (the multi-start did not reach the best minimum)
    and, after ``refits`` fits from such points (:func:`_profiled_and_refitted`), that
    they were made; a second minimum is said in the message."""
    said = []
    for name, prof in profiles.items():
        if prof is None:
            continue
        if prof["lower_minimum"] is not None:
            low = prof["lower_minimum"]
            advice = ("fit again from there" if not refits else
                      f"identify fitted again from such a point {refits} time(s) "
                      "(profile_refits) and stopped")
            said.append(f"the profile of {name} went below the fit's minimum (chi2 "
                        f"{-low['delta_chi2']:.3g} lower at {name} {low['value']:.4g}): the "
                        f"fit is not the best one; {advice} (every parameter's value there "
                        f"in the JSON's profile.{name}.lower_minimum.parameters)")
        elif prof["second_minimum"] is not None:
            second = prof["second_minimum"]
            said.append(f"the profile of {name} has a second minimum at {second['value']:.4g}"
                        f" (chi2 {second['delta_chi2']:.3g} above the fit's)")
    if not said:
        return result
    lower = any(p is not None and p["lower_minimum"] is not None for p in profiles.values())
    message = "; ".join([result.message, *said]).lstrip("; ")
    return replace(result, converged=result.converged and not lower, message=message)


#: Fits from a profile's lower minimum that ``identify --profile`` makes before it leaves
#: the fit not converged (each is profiled again).
PROFILE_REFITS = 2


def _profiled_and_refitted(problem: Any, frf: Any, H_std: Any, result: Any,
                           profile: list[str], held_freq_dep: tuple[float, float],
                           gain_std: float, progress: Callable[[str], None] | None,
                           polish_from: Callable[[Any, tuple[float, float]], Any],
                           retested: Callable[[Any], Any]
                           ) -> tuple[Any, dict[str, Any], list[dict[str, Any]]]:
    """:func:`_profiled`, and where a profile went below the fit's minimum, the fit again
    from the lowest such point (``polish_from(start, (f_k, f_c))``: one start, every
    parameter of ``result`` free, judged at the noise floor as identify's own fit) and that
    fit tested (``retested``: version B's test) and profiled again, up to
    :data:`PROFILE_REFITS` times. The thesis' optimiser stopped in minima it could not
    tell from the best one (ch. 6-7); a profile that walks into a lower one has shown the
    way out of it, so the product takes it rather than only saying so. Returns the final
    fit (not converged, as :func:`_profile_verdict` says, when a profile of it still goes
    lower), its profiles and one entry per fit from a lower minimum
    (``profile``: whose profile, ``value``: that parameter's value there,
    ``chi2_before`` / ``chi2_after``: the fit's chi2 before and after it, ``kept``: whether
    the fit after it replaced the one before)."""
    import numpy as np

    refits: list[dict[str, Any]] = []
    while True:
        profiled, profiles = _profiled(problem, frf, H_std, result, profile, held_freq_dep,
                                       gain_std, progress, refits=len(refits))
        lows = [(prof["lower_minimum"]["delta_chi2"], name, prof["lower_minimum"])
                for name, prof in profiles.items()
                if prof is not None and prof["lower_minimum"] is not None]
        if not lows or len(refits) == PROFILE_REFITS:
            return profiled, profiles, refits
        _, name, low = min(lows, key=lambda item: item[0])
        at = low["parameters"]
        start = np.array([at.get(n, v) for n, v in zip(problem.names, problem.nominal,
                                                        strict=True)], dtype=float)
        freq_dep = (at["f_k"], at["f_c"]) if "f_k" in at else held_freq_dep
        if progress:
            progress(f"the profile of {name} went below the fit's minimum: fitting again "
                     f"from {name} {low['value']:.4g}")
        again = polish_from(start, freq_dep)
        chi2_before, chi2_after = 2.0 * float(result.cost), 2.0 * float(again.cost)
        kept = chi2_after < chi2_before
        refits.append({"profile": name, "value": float(low["value"]),
                       "chi2_before": chi2_before, "chi2_after": chi2_after, "kept": kept})
        if not kept:
            # the local fit did not stay below the fit it would replace (it can only
            # when its bounds or free set differ from the profile's): keep the fit, which
            # the profile calls not converged; the refit's effort counts, as that of
            # _from_the_global_base_fit's second fit does
            kept_fit = replace(result, evaluations=result.evaluations + again.evaluations,
                               starts=result.starts + again.starts)
            return _profile_verdict(kept_fit, profiles, len(refits)), profiles, refits
        result = retested(replace(again, evaluations=again.evaluations + result.evaluations,
                                  starts=again.starts + result.starts))


def _profile_refits_note(refits: list[dict[str, Any]]) -> str:
    """What ``identify --profile``'s fits from a profile's lower minimum did, for the
    JSON's notes."""
    steps = "; then ".join(
        f"the profile of {r['profile']} went below the fit's minimum at {r['value']:.4g}: "
        f"fitted again from there, chi2 {r['chi2_before']:.6g} -> {r['chi2_after']:.6g}"
        + ("" if r["kept"] else " (not lower: not kept)") for r in refits)
    if any(r["kept"] for r in refits):
        steps += " (the parameters, std and profiles are those of the last fit kept)"
    return steps


def modelled_channels(frf: Any, path: str | Path) -> tuple[Any, str | None]:
    """``frf`` without its outputs and inputs on no modelled bone (design 4.1: bone ``""``,
    e.g. a pick-up on the bed frame), and a note naming them (``None`` when there are none).

    The model predicts nothing at such a point, so its FRFs cannot enter the fit; the rest
    of the file can. Refuses a file with nothing usable left: every output or every input
    on no modelled bone, or no measured value between the remaining ones."""
    import numpy as np

    from pelvislab.acquisition.frfset import FrfSet

    keep_out = [k for k, b in enumerate(frf.outputs.bone) if b != ""]
    keep_in = [k for k, b in enumerate(frf.inputs.bone) if b != ""]
    off = ([f"output {frf.outputs.name[k]}" for k, b in enumerate(frf.outputs.bone) if b == ""]
           + [f"input {frf.inputs.name[k]}" for k, b in enumerate(frf.inputs.bone) if b == ""])
    if not off:
        return frf, None
    named = ", ".join(off)
    if not keep_out or not keep_in or not np.isfinite(
            frf.H[:, keep_out][:, :, keep_in]).any():
        side = ("output" if not keep_out else "input" if not keep_in else "")
        why = (f"every {side} is on no modelled bone" if side else
               "no measured value is left between the channels on modelled bones")
        raise ValueError(f"{path}: nothing left to identify from: {why} (design 4.1: bone "
                         f"\"\"; {named})")
    subset = FrfSet(
        frf.frequency_hz, frf.H[:, keep_out][:, :, keep_in], frf.outputs.subset(keep_out),
        frf.inputs.subset(keep_in),
        H_std=None if frf.H_std is None else frf.H_std[:, keep_out][:, :, keep_in],
        acquired_at_s=frf.acquired_at_s, attrs=frf.attrs)
    return subset, (f"left out of the fit, on no modelled bone (design 4.1: bone \"\"; the "
                    f"model predicts nothing there): {named}")


def _dropped_lines_note(frf: Any, used: Any, kept: Any) -> str | None:
    """A note naming what peak picking left out: measured FRFs holding under 90 % of the
    lines (``picking_frfs``) and lines on which a kept FRF has no value (``picking_lines``:
    e.g. a failed step); None when it used every line of every measured FRF."""
    import numpy as np

    parts = []
    measured = np.isfinite(frf.H).any(axis=0)
    left = [f"{frf.outputs.name[o]}/{frf.inputs.name[i]}"
            for o, i in zip(*np.nonzero(measured & ~np.asarray(kept)), strict=True)]
    if left:
        parts.append(f"{len(left)} FRF(s) holding under 90 % of the lines the fullest holds: "
                     + ", ".join(left[:8]) + (" ..." if len(left) > 8 else ""))
    dropped = [f"{frf.frequency_hz[k]:g}" for k in range(len(used)) if not used[k]]
    if dropped:
        parts.append(f"{len(dropped)} of {len(used)} lines on which a kept FRF has no value: "
                     f"{', '.join(dropped[:8])}{' ...' if len(dropped) > 8 else ''} Hz")
    if not parts:
        return None
    return "peak picking left out " + "; and ".join(parts)


def _unestimated_noise_note(frf: Any) -> str | None:
    """A note naming the FRFs whose noise :func:`pelvislab.model.gap.estimate_noise` could
    not estimate (under 8 measured lines, or all zero): they get 5 % of their peak, which
    weighs them nearly out of the fit (review of session 40: 32x the true noise, unsaid).
    An FRF measured on alternate lines of the file's grid is estimated over its own lines
    (session 41); before, it fell here."""
    import numpy as np

    names = []
    for o, out in enumerate(frf.outputs.name):
        for i, inp in enumerate(frf.inputs.name):
            h = frf.H[:, o, i]
            ok = np.isfinite(h)
            if ok.any() and (ok.sum() < 8 or not np.any(h[ok])):
                names.append(f"{out}/{inp}")
    if not names:
        return None
    return (f"no H_std, and the noise of {len(names)} FRF(s) could not be estimated "
            "(under 8 measured lines, or all zero): taken as 5 % of their peak, which "
            "weighs them nearly out of the fit: "
            + ", ".join(names[:8]) + (" ..." if len(names) > 8 else ""))


DEFAULT_GAIN_STD = 0.003
"""Each FRF's gain uncertainty identify assumes unless told (``--gain-std``): the chain's
per-FRF gains, ±0.5 % as a uniform interval (0.5 %/√3; the gap diagnosis'
``calibration_tol``). Measured on the simulated chain: per-FRF gains −0.47 to +0.37 % on six
demo sessions, 0.1-0.2 % at 5-12.5 Hz on face_up sessions; without it the std were 1.9x
(demo) and 10-13x (face_up) too small and face_up never converged (docs/identification.md).
A real chain's gains (speed of sound, transducer angle) are not smaller: a lower bound."""


def recorded_calibration_std(path: str | Path, frequency_hz: Any
                             ) -> tuple[float, str, str | None]:
    """The drive calibration's relative standard uncertainty a session recorded (its latest
    run's bench, else /bench: ``drive_calibration_u_rel``, docs/bench-file.md): (value,
    source, note). One value as it is; a table's rms over ``frequency_hz`` (interpolated
    linearly as the calibration is), read as one gain common to the band. Source
    ``bench``; ``none`` (0.0) for an FRF-only file, a simulated bench (its chain is exact)
    or a bench file that did not state it, with a note in the last case."""
    import h5py
    import numpy as np

    with h5py.File(path, "r") as handle:
        bench = handle.get("bench")
        if not isinstance(bench, h5py.Group):
            return 0.0, "none", None
        # the latest run's bench: a resumed session keeps its first /bench, and a bench
        # file that stated the uncertainty only later was not read (review, session 40)
        runs = handle.get("runs")
        if isinstance(runs, h5py.Group):
            latest = []
            for name in sorted(runs):
                try:
                    run = runs[name]
                    if isinstance(run, h5py.Group) and isinstance(run.get("bench"),
                                                                  h5py.Group):
                        latest.append(run["bench"])
                except Exception:  # a run record damaged by a kill (session info says so)
                    continue
            bench = latest[-1] if latest else bench
        attrs = dict(bench.attrs)
    u_rel = np.atleast_1d(np.asarray(attrs.get("drive_calibration_u_rel", []), dtype=float))
    if u_rel.size == 0:
        if bool(attrs.get("simulated", False)):
            return 0.0, "none", None
        return 0.0, "none", ("the bench file stated no uncertainty of the drive calibration "
                             "(drive_newton_per_volt_u_rel or a u_rel column, "
                             "docs/bench-file.md): the std hold none; --calibration-std "
                             "FRACTION adds it")
    if u_rel.size == 1:
        return float(u_rel[0]), "bench", None
    table_hz = np.asarray(attrs["drive_calibration_frequency_hz"], dtype=float)
    at_lines = np.interp(np.asarray(frequency_hz, dtype=float), table_hz, u_rel)
    return float(np.sqrt(np.mean(at_lines ** 2))), "bench", None


def parameter_unit(name: str, units: dict[str, str]) -> str:
    """The SI unit of parameter ``name`` from the JSON's ``units`` (by name prefix: m_ kg,
    k_ N/m, c_ N s/m, f_ 1); "" when none applies."""
    return next((u for prefix, u in units.items() if name.startswith(prefix)), "")


def undetermined(entry: dict[str, Any]) -> bool:
    """Whether a JSON parameter entry's std exceeds its value: the data do not determine
    it (modal updating's rule), and its interval spans decades either way."""
    std = entry.get("std")
    return std is not None and std > abs(entry["value"])


def profile_said(prof: dict[str, Any] | None) -> str:
    """What one profile of the JSON's ``profile`` found, in a few words: its 95 % interval
    (an open end as "below"/"above" the walk's last point), a lower minimum than the fit's
    or a second minimum; "not run" for a parameter's profile left out (``None``)."""
    if prof is None:
        return "not run (a parameter on the bound of its range)"
    if prof["lower_minimum"] is not None:
        return (f"a LOWER minimum than the fit's at {prof['lower_minimum']['value']:.4g} "
                f"(delta chi2 {prof['lower_minimum']['delta_chi2']:.3g}; no interval)")
    low, high = prof["interval_95"]
    # an open end: the walk stayed within the limit up to its last point
    low_txt = f"below {min(prof['values']):.4g}" if low is None else f"{low:.4g}"
    high_txt = f"above {max(prof['values']):.4g}" if high is None else f"{high:.4g}"
    said = f"95 % {low_txt} to {high_txt}"
    if prof["second_minimum"] is not None:
        said += (f"; second minimum at {prof['second_minimum']['value']:.4g} "
                 f"(delta chi2 {prof['second_minimum']['delta_chi2']:.3g})")
    return said


def _digits_to_show(value: float, std: float | None) -> int:
    """Significant digits of a value and its interval in the summary: 4, or as many as
    show the std's first two digits (a std of 2.1 N/m on 1e5 N/m printed "95 % 1e+05 to
    1e+05": review 66); at most 12."""
    import math

    if std is None or not (math.isfinite(std) and std > 0) or not math.isfinite(value) \
            or value == 0:
        return 4
    places = math.floor(math.log10(abs(value))) - math.floor(math.log10(std)) + 2
    return int(min(max(4, places), 12))


def summary_text(document: dict[str, Any]) -> str:
    """The identification's JSON (design 4.5) as a few lines: converged or not, the misfit,
    and each parameter with its unit, standard error and 95 % interval."""
    rms = document.get("rms_residual")
    misfit = "" if rms is None else (
        f", rms residual {rms:.3g}"
        + (" (in noise sigma)" if document.get("residual") == "std" else ""))
    head = ("converged" if document.get("converged")
            else "NOT converged (the reason: on stderr and in the JSON's message)")
    lines = [f"identify ({document.get('method', '?')}): {head}{misfit}"]
    units = document.get("units", {})
    params = document.get("parameters", {})
    width = max((len(n) for n in params), default=0)
    for name, entry in params.items():
        unit = parameter_unit(name, units)
        unit = "" if unit == "1" else f" {unit}"
        std = entry.get("std")
        interval = entry.get("interval_95")
        spread = "std n/a" if std is None else f"std {std:.2g}"
        digits = _digits_to_show(entry["value"], std)
        if undetermined(entry):  # 1e-125 to 1e136 N/m read as numbers (review)
            spread += ", undetermined: std above the value"
        elif interval:
            spread += f", 95 % {interval[0]:.{digits}g} to {interval[1]:.{digits}g}"
        lines.append(f"  {name:<{width}}  {entry['value']:.{digits}g}{unit}  ({spread})")
    profiles = document.get("profile")
    if profiles == {}:
        lines.append("  profile: no weak parameter (std under 10 % of every value)")
    for name, prof in (profiles or {}).items():
        lines.append(f"  profile of {name}: {profile_said(prof)}"
                     + ("" if prof is None else f" ({prof['fits']} fits)"))
    for refit in document.get("profile_refits", []):
        lines.append(f"  fitted again from the lower minimum of {refit['profile']}'s profile: "
                     f"chi2 {refit['chi2_before']:.6g} -> {refit['chi2_after']:.6g}"
                     + ("" if refit["kept"] else " (not lower: not kept)"))
    return "\n".join(lines)


def _identify(args: argparse.Namespace) -> int:
    if args.starts is not None and args.starts < 1:
        raise ValueError(f"--starts {args.starts}: must be >= 1")
    if args.seed is not None and args.seed < 0:
        raise ValueError(f"--seed {args.seed}: must be >= 0")
    if args.gain_std is not None and not (
            math.isfinite(args.gain_std) and 0 <= args.gain_std < 0.5):
        raise ValueError(f"--gain-std {args.gain_std}: must be a fraction in [0, 0.5), "
                         "e.g. 0.003 for 0.3 %")
    if args.calibration_std is not None and not (
            math.isfinite(args.calibration_std) and 0 <= args.calibration_std <= 0.5):
        raise ValueError(f"--calibration-std {args.calibration_std}: must be a fraction in "
                         "[0, 0.5], e.g. 0.02 for 2 %")
    # '-': the JSON on stdout (design 4.5 "identify --json prints"); checked before the fit
    out = None if args.json == "-" else check_new_output(args.json)
    free = comma_list(args.params) if args.params else None
    warning = incomplete_session_warning(args.session)
    if warning:
        print(f"warning: {warning}", file=sys.stderr)
    progress = _progress(sys.stderr.isatty() or args.verbose > 0)
    report = identify_file(
        args.session, args.method, free, args.model, progress, symmetric=args.symmetric,
        version_b=args.version_b, residual=args.residual,
        a_b=None if args.a_b is None else float(args.a_b),
        starts=args.starts, seed=args.seed, gain_std=args.gain_std,
        calibration_std=args.calibration_std,
        profile=comma_list(args.profile) if args.profile else None)
    if out is None:
        print_json(report.to_json())
    else:
        write_json(out, report.to_json())
        # what a user at the terminal wants first (the command printed nothing when it
        # converged: session 44); the JSON holds the rest
        print(summary_text(report.document))
        print(f"JSON: {out}")
    for note in report.document.get("notes", []):
        print(f"note: {note}", file=sys.stderr)
    if not report.converged:
        where = "standard output" if out is None else out
        print(f"identify: not converged ({report.message.strip('; ')}); result written to "
              f"{where}", file=sys.stderr)
    return 0
