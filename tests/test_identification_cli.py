"""``pelvislab identify``: JSON of design 4.5 from an FRF-only file, clear errors."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from pelvislab.acquisition.frfset import FrfSet, write_frf
from pelvislab.app.cli import main
from pelvislab.app.commands.identify import _digits_to_show
from pelvislab.model.identification import FitResult, frf_with_jacobian
from pelvislab.model.identification_pelvis import FACE_UP, layout_channels, pelvis_problem
from pelvislab.model.pelvis import default_model


def _frf_file(path: Path, scale: dict[str, float], with_std: bool = False) -> FrfSet:
    outs, ins, mask = layout_channels(FACE_UP)
    problem, space = pelvis_problem(default_model(), outs, ins)
    values = space.values().copy()
    for name, factor in scale.items():
        values[space.index(name)] *= factor
    f = np.arange(5.0, 300.0, 5.0)
    H, _ = frf_with_jacobian(problem.assemble(values), problem.outputs, problem.inputs, f,
                             jacobian=False)
    H = np.where(mask[None], H, np.nan)
    std = np.where(mask[None], 1e-3 * np.abs(H), np.nan) if with_std else None
    frf = FrfSet(f, H, outs, ins, H_std=std)
    write_frf(path, frf)
    return frf


def test_identify_writes_design_json(tmp_path: Path) -> None:
    src = tmp_path / "frf.h5"
    _frf_file(src, {"k_pubh": 1.3, "k_pubs": 0.8})
    out = tmp_path / "out.json"
    code = main(["identify", str(src), "--params", "k_pubh,k_pubs", "--json", str(out)])
    assert code == 0
    doc = json.loads(out.read_text())
    assert set(doc["parameters"]) == {"k_pubh", "k_pubs"}
    assert doc["parameters"]["k_pubh"]["value"] == pytest.approx(1.3e5, rel=1e-6)
    assert doc["parameters"]["k_pubs"]["value"] == pytest.approx(0.8 * 5e3, rel=1e-6)
    assert doc["converged"] is True
    for key in ("cost", "evaluations", "wall_time_s", "identifiability", "correlation"):
        assert key in doc
    assert isinstance(doc["evaluations"], int) and doc["wall_time_s"] > 0


def test_a_misfit_hidden_by_an_overstated_noise_is_still_judged(tmp_path: Path) -> None:
    """Exactness is judged relative to the data, not in noise units: with H_std 1e8 times
    |H| and k_pubs held 25 % off, the misfit's rms is 3.6e-9 sigma (below the 1e-8 of an
    exact fit) and its residual is structured along frequency: not converged (review 65)."""
    frf = _frf_file(tmp_path / "exact.h5", {"k_pubh": 1.3, "k_pubs": 0.8})
    src = tmp_path / "overstated.h5"
    write_frf(src, FrfSet(frf.frequency_hz, frf.H, frf.outputs, frf.inputs,
                          H_std=1e8 * np.abs(frf.H)))
    out = tmp_path / "out.json"
    main(["identify", str(src), "--params", "k_pubh", "--json", str(out)])
    doc = json.loads(out.read_text())
    assert doc["residual"] == "std" and doc["rms_residual"] < 1e-8
    assert doc["residual_whiteness"]["structured"] and doc["converged"] is False


def test_an_exact_fit_of_std_residuals_is_not_judged_for_structure(tmp_path: Path,
                                                                   monkeypatch) -> None:
    """Rounding is all that is left of an exact fit: its lag-1 correlation depends on the
    machine's floating-point kernels (0.37 on one, white on another, for the data of
    test_identify_writes_design_json: 'not converged' at rms 1.5e-11 sigma). Made
    correlated here on any machine; a std residual that small against the data is not
    judged."""
    from pelvislab.model import identification

    real = identification.residual_lag1_correlation
    monkeypatch.setattr(identification, "residual_lag1_correlation",
                        lambda r, mask: (0.37, real(r, mask)[1]))
    src = tmp_path / "frf.h5"
    _frf_file(src, {"k_pubh": 1.3, "k_pubs": 0.8})
    out = tmp_path / "out.json"
    assert main(["identify", str(src), "--params", "k_pubh,k_pubs", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["residual"] == "std" and doc["rms_residual"] < 1e-8
    assert doc["residual_whiteness"]["lag1_correlation"] == 0.37
    assert not doc["residual_whiteness"]["structured"]
    assert doc["converged"] is True, doc["message"]


def test_identify_with_h_std_uses_chi_square(tmp_path: Path, capsys) -> None:
    src = tmp_path / "frf.h5"
    _frf_file(src, {"m_sacrum": 1.1}, with_std=True)
    out = tmp_path / "out.json"
    assert main(["identify", str(src), "--params", "m_sacrum,k_io_R", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["residual"] == "std"
    assert doc["parameters"]["m_sacrum"]["value"] == pytest.approx(0.396, rel=1e-6)
    assert doc["parameters"]["m_sacrum"]["std"] > 0
    # the terminal gets the result too (nothing was printed when it converged)
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith("identify (frf): converged, rms residual ")

    def line(name: str, unit: str) -> str:
        # the digits that show the std (a std of 2.4e-6 kg on 0.396 kg: 7)
        p = doc["parameters"][name]
        d = _digits_to_show(p["value"], p["std"])
        low, high = p["interval_95"]
        return (f"  {name:<8}  {p['value']:.{d}g} {unit}  (std {p['std']:.2g}, 95 % "
                f"{low:.{d}g} to {high:.{d}g})")

    assert printed[1:] == [line("m_sacrum", "kg"), line("k_io_R", "N/m"), f"JSON: {out}"]
    assert _digits_to_show(doc["parameters"]["m_sacrum"]["value"],
                           doc["parameters"]["m_sacrum"]["std"]) == 7


@pytest.mark.parametrize("f_k", [0.0, 0.002, 0.008])
def test_a_fit_that_version_b_beats_is_not_converged(tmp_path: Path, f_k: float) -> None:
    """Noise 1 % of |H| on face-up lines: stiffness 0.05 % higher at 300 Hz (eq. 7.3, f_k
    0.002) leaves a version-A fit at the noise floor (chi2/dof 0.99), but version B's f_k
    fits it significantly better: not converged, saying so; without f_k converged. With
    f_k 0.008 version A misses the floor (chi2/dof 2.3) and version B reaches it: the
    message says to fit version B."""
    outs, ins, mask = layout_channels(FACE_UP)
    problem, space = pelvis_problem(default_model(), outs, ins)
    f = np.arange(5.0, 300.0, 5.0)
    H, _ = frf_with_jacobian(problem.assemble(space.values()), problem.outputs,
                             problem.inputs, f, f_k=f_k,
                             omega_max_rad_s=problem.omega_max_rad_s, jacobian=False)
    std = 0.01 * np.abs(H)
    rng = np.random.default_rng(0)
    H = H + std / np.sqrt(2) * (rng.standard_normal(H.shape)
                                + 1j * rng.standard_normal(H.shape))
    src = tmp_path / "frf.h5"
    write_frf(src, FrfSet(f, np.where(mask[None], H, np.nan), outs, ins,
                          H_std=np.where(mask[None], std, np.nan)))
    out = tmp_path / "out.json"
    main(["identify", str(src), "--params", "k_pubh,k_io_R,k_io_L,k_asd_R,k_asd_L",
          "--json", str(out)])
    doc = json.loads(out.read_text())
    assert (doc["chi2_per_dof"] < 1.05) is (f_k < 0.005)  # at the noise floor or not
    test = doc["frequency_dependence"]
    assert test["significant"] is (f_k > 0)
    assert doc["converged"] is (f_k == 0)
    assert test["at_noise_floor"] and test["chi2_per_dof"] < 1.05
    if f_k:
        assert test["f_k"] == pytest.approx(f_k, abs=5e-4) and test["p_value"] < 1e-6
        assert "version B" in doc["message"] and "--version-b" in doc["message"]
        assert ("carry a model error" in doc["message"]) is (f_k < 0.005)
        assert ("to the noise" in doc["message"]) is (f_k > 0.005)
    else:
        assert "version B" not in doc["message"]
    # version B itself and the relative residuals are not tested
    for flags in (["--version-b"], ["--residual", "log"]):
        other = tmp_path / f"{flags[-1]}.json"
        main(["identify", str(src), "--params", "k_pubh", *flags, "--starts", "1",
              "--json", str(other)])
        assert "frequency_dependence" not in json.loads(other.read_text())


def test_a_fit_with_a_parameter_on_its_bound_is_not_tested_for_frequency_dependence():
    """Version B would stand in for the bound too (a set without frequency dependence,
    two springs on their x10 bound: f_k 4.8 at p 0.0005)."""
    from pelvislab.app.commands.identify import _tested_for_frequency_dependence

    fit = FitResult(["k_io_R"], np.array([1e7]), np.array([np.nan]), np.eye(1), 1.0, False,
                    10, 0.1, "std", np.ones(1), [], extra={"on_bound": ["k_io_R"]})
    assert _tested_for_frequency_dependence(None, None, None, fit, (0.0, 0.0), 0.003,
                                            None) == (fit, None)


def test_a_fit_that_misses_the_noise_floor_is_fitted_again_from_the_global_base_fit(
        tmp_path: Path) -> None:
    """identify's own starts lie within +-30 % of the model file's values; the gap
    diagnosis' base fit scans damping decades and stiffness and mass scales. A fit that
    misses the floor is fitted again from that base fit, kept when better, with a note;
    one at the floor is not (judge-like set s_202_019: rms 5.95, k_pss_L 10x low, then
    0.994, every |z| <= 1.6; session 45)."""
    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.app.commands.identify import _from_the_global_base_fit

    scale = {"k_pss_L": 0.8, "k_io_R": 1.2, "c_sij_R": 150.0, "c_sij_L": 40.0, "c_pub": 400.0}
    src = tmp_path / "frf.h5"
    _frf_file(src, scale, with_std=True)
    frf = read_frf(src)
    model = default_model()
    problem, space = pelvis_problem(model, frf.outputs, frf.inputs)
    truth = space.values().copy()
    for name, factor in scale.items():
        truth[space.index(name)] *= factor
    starts = []

    # a fit stuck at the model file's values (dampings 40-400x below the subject's)
    stuck = FitResult(list(problem.names), problem.nominal.copy(), problem.nominal, np.eye(18),
                      1.0, False, 7, 1.0, "std", np.ones(18), [], starts=4,
                      extra={"rms_residual": 6.0})

    def fit_from(start):
        starts.append(start)
        return replace(stuck, evaluations=5, starts=1, wall_time_s=0.5,
                       extra={"rms_residual": 0.9})

    result, note = _from_the_global_base_fit(problem, frf, frf.H_std, model, stuck, fit_from,
                                             None)
    [start] = starts
    # the diagnosis' base fit found the subject, dampings 40-400x appendix E's included
    np.testing.assert_allclose(start, truth, rtol=0.02)
    assert result.extra["rms_residual"] == 0.9 and (result.evaluations, result.starts) == (12, 5)
    assert "global base fit" in note and "6 from identify's own starts, 0.9 from it" in note
    # not better: the first fit stays, without a note, but the second fit's effort counts
    # (its time too: identify_file's wall_time_s is the whole identification's; review 45)
    worse = replace(stuck, evaluations=5, starts=1, extra={"rms_residual": 7.0})
    kept, note = _from_the_global_base_fit(problem, frf, frf.H_std, model, stuck,
                                           lambda _s: worse, None)
    assert note is None and kept.extra == stuck.extra and kept.values is stuck.values
    assert (kept.evaluations, kept.starts) == (12, 5)
    # at the noise floor, or where the base fit is no better a start: no second fit
    at_floor = replace(stuck, extra={"rms_residual": 1.0})
    assert _from_the_global_base_fit(problem, frf, frf.H_std, model, at_floor,
                                     lambda _s: pytest.fail("fitted again"), None) == (
        at_floor, None)
    near = replace(stuck, values=truth)  # the noise-free data's own values
    kept, note = _from_the_global_base_fit(problem, frf, frf.H_std, model, near,
                                           lambda _s: pytest.fail("fitted again"), None)
    assert note is None and kept.values is truth


def test_bad_file_gives_one_line_error(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not hdf5 at all")
    code = main(["identify", str(bad), "--json", str(tmp_path / "o.json")])
    err = capsys.readouterr().err.strip()
    assert code == 1
    assert len(err.splitlines()) == 1 and "bad.h5" in err
    assert main(["identify", str(tmp_path / "missing.h5"), "--json", "o.json"]) == 1
    assert "no such file" in capsys.readouterr().err


def test_unknown_parameter_is_named(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    src = tmp_path / "frf.h5"
    _frf_file(src, {})
    code = main(["identify", str(src), "--params", "k_nope", "--json", str(tmp_path / "o.json")])
    assert code == 1
    assert "k_nope" in capsys.readouterr().err


def test_eq610_weights_default_to_the_thesis_ratio(tmp_path: Path) -> None:
    # thesis ch. 6.2/7 (L1358, L1470): a/b = 0.1; --a-b defaulted to 1 for every residual
    # (thesis fidelity review, session 36)
    src = tmp_path / "frf.h5"
    _frf_file(src, {"k_pubh": 1.2})
    ratios = {}
    for residual, extra in (("eq610", []), ("log", []), ("eq610", ["--a-b", "3"])):
        out = tmp_path / f"{residual}{len(extra)}.json"
        assert main(["identify", str(src), "--params", "k_pubh", "--residual", residual,
                     *extra, "--json", str(out)]) == 0
        doc = json.loads(out.read_text())
        ratios[(residual, len(extra))] = doc["a_over_b"]
        assert doc["parameters"]["k_pubh"]["value"] == pytest.approx(1.2e5, rel=1e-6)
    assert ratios == {("eq610", 0): 0.1, ("log", 0): 1.0, ("eq610", 2): 3.0}
    _frf_file(tmp_path / "std.h5", {"k_pubh": 1.2}, with_std=True)
    out = tmp_path / "std.json"
    assert main(["identify", str(tmp_path / "std.h5"), "--params", "k_pubh", "--json",
                 str(out)]) == 0
    assert "a_over_b" not in json.loads(out.read_text())  # std: weighted by H_std alone


def test_layout_channels_have_a_sessions_signs() -> None:
    # the layouts' inputs pushed along the landmark direction (outward), a session's force
    # goes into the surface (protocol default): synthetic FRFs of a layout had the opposite
    # sign of the simulated face-down demo's /frf for the same names (audit)
    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.identification_pelvis import FACE_DOWN

    session = read_frf(Path(__file__).parent / "data" / "demo_sim_seed1.h5")
    outs, ins, mask = layout_channels(FACE_DOWN)
    assert list(ins.name) == list(session.inputs.name)
    np.testing.assert_allclose(ins.direction, session.inputs.direction, atol=1e-12)
    problem, space = pelvis_problem(default_model(), outs, ins)
    f = session.frequency_hz
    H, _ = frf_with_jacobian(problem.assemble(space.values()), problem.outputs,
                             problem.inputs, f, jacobian=False)
    rows = [list(session.outputs.name).index(n) for n in outs.name]
    measured = session.H[:, rows, :]
    ok = mask[None] & np.isfinite(measured)
    ratio = measured[ok] / H[ok]
    assert ok.sum() > 100
    assert np.median(ratio.real) == pytest.approx(1.0, abs=0.1)


def test_identify_json_dash_prints_the_json_alone_on_stdout(tmp_path: Path, capsys) -> None:
    # design 4.5: "pelvislab identify --json prints ..."; '-' was refused ("'-' (standard
    # output) is not supported here") although ema takes it (audit)
    frf = _frf_file(tmp_path / "frf.h5", {"k_pubh": 1.3})
    frf.H_std = np.zeros(frf.H.shape)  # read as absent, with a note: on stderr only
    write_frf(tmp_path / "zero_std.h5", frf)
    assert main(["identify", str(tmp_path / "zero_std.h5"), "--params", "k_pubh",
                 "--json", "-"]) == 0
    captured = capsys.readouterr()
    doc = json.loads(captured.out)  # the whole of stdout is the JSON
    assert doc["parameters"]["k_pubh"]["value"] == pytest.approx(1.3e5, rel=1e-6)
    assert doc["notes"] and "note: H_std holds no positive finite value" in captured.err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frf.h5", "zero_std.h5"]


def test_modal_updating_refuses_version_b(tmp_path: Path, capsys) -> None:
    """--version-b with --method modal was dropped without a word (exit 0, no f_k, f_c in
    the JSON; audit); refused in one line like --gain-std, before anything is written."""
    data = Path(__file__).parent / "data" / "demo_sim_seed1.h5"
    out = tmp_path / "m.json"
    assert main(["identify", str(data), "--method", "modal", "--version-b",
                 "--json", str(out)]) == 1
    err = capsys.readouterr().err
    assert err.startswith("pelvislab identify: error: --version-b applies to --method frf")
    assert err.count("\n") == 1, err
    assert not out.exists()


@pytest.mark.parametrize("options", [["--residual", "log"], ["--residual", "auto"],
                                     ["--a-b", "0.5"], ["--starts", "3", "--seed", "0"]])
def test_modal_updating_refuses_the_frf_fit_options(tmp_path: Path, capsys, options) -> None:
    """--residual, --a-b, --starts and --seed shape the FRF fit only; with --method modal
    they were ignored without a word (exit 0; session 41's note). An explicit --seed 0 or
    --residual auto is refused too: an option the user gave, not the default."""
    data = Path(__file__).parent / "data" / "demo_sim_seed1.h5"
    out = tmp_path / "m.json"
    assert main(["identify", str(data), "--method", "modal", *options,
                 "--json", str(out)]) == 1
    err = capsys.readouterr().err
    named = [o for o in options if o.startswith("--")]
    assert err.startswith(f"pelvislab identify: error: {', '.join(named)} appl"), err
    assert "--method frf" in err and err.count("\n") == 1, err
    assert not out.exists()


def test_modal_updating_picks_peaks_on_the_lines_it_has(tmp_path: Path, capsys) -> None:
    """One failed line (every FRF NaN at 10 Hz, as the nine-point protocol's first step)
    made every FRF "incomplete" and refused the file ("no complete FRF line to pick peaks
    from", audit); a line one FRF lacks is left out too. Both are named in a note."""
    src = tmp_path / "frf.h5"
    frf = _frf_file(tmp_path / "full.h5", {})
    H = frf.H.copy()
    H[1] = np.nan  # 10 Hz, every FRF
    measured = np.argwhere(np.isfinite(H[2]))[0]
    H[20, measured[0], measured[1]] = np.nan  # 105 Hz, one FRF
    write_frf(src, FrfSet(frf.frequency_hz, H, frf.outputs, frf.inputs))
    out = tmp_path / "m.json"
    assert main(["identify", str(src), "--method", "modal", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    note = "peak picking left out 2 of 59 lines on which a kept FRF has no value: 10, 105 Hz"
    assert doc["notes"] == [note]
    assert f"note: {note}" in capsys.readouterr().err
    # the same peaks as from the whole file, where no left-out line is next to one
    full = tmp_path / "m_full.json"
    assert main(["identify", str(tmp_path / "full.h5"), "--method", "modal", "--json",
                 str(full)]) == 0
    whole = json.loads(full.read_text())["modes_hz"]
    assert [f for f in whole if min(abs(f - 10), abs(f - 105)) > 5] == [
        f for f in doc["modes_hz"] if min(abs(f - 10), abs(f - 105)) > 5]
    assert "notes" not in json.loads(full.read_text())


def test_modal_updating_gets_the_model_files_frequency_dependence(tmp_path: Path,
                                                                  monkeypatch) -> None:
    """identify --method modal fitted the modes of M and K only: a model file's f_k, f_c
    were dropped."""
    import pelvislab.model.identification_modal as modal

    text = (Path(modal.__file__).parent / "appendix_e.toml").read_text()
    model = tmp_path / "fk.toml"
    model.write_text(text.replace("f_k = 0.0", "f_k = 0.5").replace("f_c = 0.0", "f_c = 0.2"))
    seen = {}
    fit = modal.identify_modal

    def recording(*args, **kwargs):
        seen.update(kwargs)
        return fit(*args, **kwargs)

    monkeypatch.setattr(modal, "identify_modal", recording)
    data = Path(__file__).parent / "data" / "demo_sim_seed1.h5"
    main(["identify", str(data), "--method", "modal", "--model", str(model),
          "--json", str(tmp_path / "m.json")])
    assert (seen["f_k"], seen["f_c"]) == (0.5, 0.2)


def test_the_summary_calls_an_undetermined_parameter_so() -> None:
    """Modal updating of the demo session left parameters with std 200 e-folds: printed
    "95 % 4.774e-125 to 1.801e+136" N/m (review)."""
    from pelvislab.app.commands.identify import summary_text

    doc = {"method": "modal", "converged": False, "units": {"k_": "N/m"},
           "parameters": {"k_a": {"value": 1e5, "std": 2e7, "interval_95": [1e-165, 1e175]},
                          "k_b": {"value": 1e5, "std": 1e3, "interval_95": [9.8e4, 1.02e5]}}}
    text = summary_text(doc)
    assert "k_a  1e+05 N/m  (std 2e+07, undetermined: std above the value)" in text
    assert "k_b  1e+05 N/m  (std 1e+03, 95 % 9.8e+04 to 1.02e+05)" in text


def test_the_summary_shows_a_tight_interval_with_its_digits() -> None:
    """k_pubh fitted to 2.1 N/m on 1e5 N/m printed "95 % 1e+05 to 1e+05" (review 66):
    value and interval now carry the digits that show the std's first two."""
    from pelvislab.app.commands.identify import summary_text

    doc = {"method": "frf", "converged": True, "units": {"k_": "N/m", "m_": "kg"},
           "parameters": {"k_pubh": {"value": 100000.31, "std": 2.1,
                                     "interval_95": [99996.2, 100004.4]},
                          "m_sacrum": {"value": 0.29331, "std": 0.001,
                                       "interval_95": [0.2913, 0.2953]}}}
    text = summary_text(doc)
    assert "k_pubh    100000.3 N/m  (std 2.1, 95 % 99996.2 to 100004.4)" in text
    assert "m_sacrum  0.2933 kg  (std 0.001, 95 % 0.2913 to 0.2953)" in text


@pytest.mark.parametrize("held", [(0.0, 0.0), (0.3, 0.2)])
def test_the_frequency_dependence_message_says_from_what_f_k_f_c_were_released(
        monkeypatch: pytest.MonkeyPatch, held: tuple[float, float]) -> None:
    """With the model file's f_k 0.3, f_c 0.2 held, a simulated face-down session without
    frequency dependence fitted version B at f_k 0.007, f_c -0.0003, p 0: the message said
    "frequency-dependent stiffness and damping fit significantly better" (review 45)."""
    import pelvislab.model.identification as identification
    from pelvislab.app.commands.identify import _tested_for_frequency_dependence

    test = {"delta_chi2": 2.6e4, "p_value": 0.0, "p_limit": 1e-3, "significant": True,
            "f_k": 0.00668, "f_c": -0.0003, "chi2_per_dof": 0.85, "at_noise_floor": True}
    monkeypatch.setattr(identification, "frequency_dependence_test",
                        lambda *_a, **_k: test)
    fit = FitResult(["k_io_R"], np.array([1e6]), np.array([1e4]), np.eye(1), 1.0, False,
                    10, 0.1, "std", np.ones(1), [], message="best rms residual 3.8",
                    extra={"on_bound": []})
    frf = SimpleNamespace(frequency_hz=np.array([5.0]), H=np.ones((1, 1, 1), complex))
    result, said = _tested_for_frequency_dependence(None, frf, None, fit, held, 0.003, None)
    assert said is test and "fit with --version-b" in result.message
    if any(held):
        assert "released from the model file's 0.3, 0.2" in result.message
        assert "frequency-dependent stiffness and damping" not in result.message
    else:
        assert "frequency-dependent stiffness and damping (version B" in result.message


def test_a_symmetric_fit_does_not_run_the_global_base_fit(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """--symmetric has names of its own (k_io, c_sij, ...) that the gap diagnosis' base
    fit (design 4.5's) cannot start: it ran for nothing, ~0.9 s of 3 on a simulated demo
    session without its H_std, before being dropped (review 45)."""
    import pelvislab.model.gap as gap
    from pelvislab.app.commands.identify import _from_the_global_base_fit

    monkeypatch.setattr(gap, "prepare_data", lambda *_a, **_k: None)
    monkeypatch.setattr(gap, "global_base_fit",
                        lambda *_a, **_k: pytest.fail("base fit run for a symmetric fit"))
    outs, ins, _mask = layout_channels(FACE_UP)
    problem, _ = pelvis_problem(default_model(), outs, ins, symmetric=True)
    n = len(problem.names)
    missed = FitResult(list(problem.names), problem.nominal.copy(), problem.nominal, np.eye(n),
                       1.0, False, 7, 1.0, "std", np.ones(n), [], starts=4,
                       extra={"rms_residual": 6.0})
    frf = SimpleNamespace(frequency_hz=np.arange(5.0, 20.0), H=np.ones((15, 1, 1), complex))
    assert _from_the_global_base_fit(
        problem, frf, np.ones((15, 1, 1)), default_model(), missed,
        lambda _s: pytest.fail("fitted again"), None) == (missed, None)


def test_a_parameter_named_twice_is_refused(tmp_path: Path) -> None:
    """The API refuses what the CLI's option parsing does: a name given twice was fitted
    as two parameters, their sum resolved and each std n/a, "converged" (review 66)."""
    from pelvislab.app.commands.identify import identify_file

    src = tmp_path / "frf.h5"
    _frf_file(src, {"k_pubh": 1.3})
    with pytest.raises(ValueError, match=r"\['k_pubh'\] named more than once"):
        identify_file(src, params=["k_pubh", "k_pubs", "k_pubh"])


@pytest.mark.parametrize(("options", "message"), [
    (["--a-b", "0.5"], "--a-b applies to --residual eq610 or log"),
    (["--residual", "std", "--a-b", "2"], "--a-b applies to --residual eq610 or log"),
    (["--residual", "log", "--a-b", "inf"], "--a-b inf: must be a finite ratio > 0"),
    (["--residual", "eq610", "--a-b", "0"], "--a-b 0.0: must be a finite ratio > 0"),
])
def test_a_b_where_it_means_nothing_is_refused(options: list[str], message: str,
                                               tmp_path: Path, capsys) -> None:
    """The std misfit has no a/b (its weights are H_std): --a-b with it ran the default
    fit and exited 0; an infinite ratio reached scipy ("Residuals are not finite in the
    initial point"). Both are option errors, before any fit (review 66)."""
    src = tmp_path / "frf.h5"
    _frf_file(src, {"k_pubh": 1.3}, with_std=True)
    out = tmp_path / "out.json"
    assert main(["identify", str(src), "--params", "k_pubh", "--json", str(out),
                 *options]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err
    assert not out.exists()


def test_a_start_that_is_not_positive_is_named() -> None:
    """A model file with its dampings at 0 failed with "start values of identified
    parameters must be positive", naming none (review 66)."""
    from pelvislab.model.identification import identify_frf

    outs, ins, mask = layout_channels(FACE_UP)
    problem, _ = pelvis_problem(default_model(), outs, ins)
    start = np.asarray(problem.nominal, float).copy()
    start[list(problem.names).index("c_pub")] = 0.0
    f = np.arange(5.0, 100.0, 5.0)
    H = np.ones((f.size, len(outs.name), len(ins.name)), complex)
    with pytest.raises(ValueError, match=r"\['c_pub'\] are not .*--params"):
        identify_frf(problem, f, H, start=start)
