"""The prior range of the parameter updating (issue 10): "updating alone explains the data"
must mean updating to plausible values. With wide bounds (springs x30, damping x1e6) a base
fit absorbs an effect with implausible parameters and the verdict is a false ``none``."""

from __future__ import annotations

import json

import numpy as np
import pytest

from pelvislab.acquisition.frfset import FrfSet, write_frf
from pelvislab.app.cli import main
from pelvislab.model.frf import frf
from pelvislab.model.gap import GapOptions, _base_bounds, at_bound, diagnose, prepare_data
from pelvislab.model.pelvis import default_model
from pelvislab.tests.benchmarks.bench_gap import make_generator
from pelvislab.tests.test_gap_diagnosis import F_HZ, IN, OUT, noisy, true_model


def write_frf_file(path):
    Hn, sigma = noisy(frf(true_model(), F_HZ, OUT, IN), np.random.default_rng(2))
    write_frf(path, FrfSet(F_HZ, Hn, OUT, IN, H_std=sigma))
    return path


def test_bounds_follow_the_updating_range_and_reject_factors_below_one():
    names = ("m_sacrum", "k_io_R", "c_sij_R")
    start = np.array([0.36, 1e6, 0.8])
    b = _base_bounds(names, start, 1.6, 3e4)
    np.testing.assert_allclose(np.exp(b.lo[:2]), start[:2] / 1.6)
    np.testing.assert_allclose(np.exp(b.hi[:2]), start[:2] * 1.6)
    np.testing.assert_allclose(np.exp([b.lo[2], b.hi[2]]), [0.8e-4, 0.8 * 3e4])
    for bad in ((0.9, 3e4), (float("nan"), 3e4), (1.6, float("inf"))):
        with pytest.raises(ValueError, match="finite factors > 1"):
            _base_bounds(names, start, *bad)
    theta = np.array([0.36, 1.6e6, 100.0])
    assert at_bound(names, theta, start, b) == {"k_io_R": 1.6}


def test_effect_absorbed_by_implausible_updating_is_named():
    """Seed 2026, frequency-dependent stiffness #1 of the benchmark (f_k 3.12): x30 bounds
    let the base fit absorb it (every spring x1.5-2.4, base gap 0; verdict none before
    the pooled test, which still finds it: chi2 drop 30 on fitted + held-out lines, 4.9
    held out); within the default range the springs end at their bound and the effect is
    named on the held-out lines alone."""
    gen, _ = make_generator("auto", 2026)
    case = gen("frequency_dependent_stiffness", 1)
    data = prepare_data(case.frequency_hz, case.H, case.H_std, case.outputs, case.inputs)
    effects = ("frequency_dependent_stiffness", "hysteretic_damping")
    wide = diagnose(data, default_model(), GapOptions(effects=effects, updating_range=30.0,
                                                      damping_max=1e6)).report
    assert wide["gap_before"] == 0.0
    assert wide["verdict"] == "frequency_dependent_stiffness"
    assert wide["significance"]["by"].startswith("fitted + held-out")
    rep = diagnose(data, default_model(), GapOptions(effects=effects)).report
    assert rep["verdict"] == "frequency_dependent_stiffness"
    assert rep["significance"]["by"] == "held-out lines"
    assert rep["base_fit"]["at_bound"]
    assert max(rep["base_fit"]["at_bound"].values()) == pytest.approx(1.6, rel=0.02)


def test_cli_refuses_an_updating_range_below_one(tmp_path, capsys):
    path = write_frf_file(tmp_path / "s.h5")
    code = main(["gap", "diagnose", str(path), "--json", str(tmp_path / "o.json"),
                 "--updating-range", "0.8"])
    assert code == 1
    err = capsys.readouterr().err
    assert "--updating-range must be a finite factor > 1" in err
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "o.json").exists()


def test_cli_reports_the_range_in_the_json(tmp_path):
    path = write_frf_file(tmp_path / "s.h5")
    out = tmp_path / "o.json"
    # the file's subject has io_R at 1.2x appendix E: a range of 1.1 stops it at the bound
    code = main(["gap", "diagnose", str(path), "--json", str(out), "--effects", "added_mass",
                 "--updating-range", "1.1", "--damping-max", "1e5", "--no-plots"])
    assert code == 0
    base = json.loads(out.read_text())["base_fit"]
    assert base["updating_range"] == 1.1 and base["damping_max"] == 1e5
    assert base["at_bound"]["k_io_R"] == pytest.approx(1.1, rel=1e-3)
    assert base["parameters"]["k_io_R"] == pytest.approx(1.1e6, rel=1e-3)


def test_runner_up_effect_is_polished_out_of_its_local_minimum():
    """Seed-9001 support #0 of the benchmark (bed contact under the right innominate,
    30.4 Hz, 3.6 kg): from its screened start the support fit stops at 2.64 and a grounded
    ligament leads with 1.85; polishing the two best effects finds the resonance (measured
    with ``polish_effects=1``: verdict ``missing_ligament``)."""
    gen, _ = make_generator("auto", 9001)
    case = gen("support_resonance", 0)
    data = prepare_data(case.frequency_hz, case.H, case.H_std, case.outputs, case.inputs)
    effects = ("support_resonance", "missing_ligament")
    rep = diagnose(data, default_model(), GapOptions(effects=effects)).report
    assert rep["verdict"] == "support_resonance", rep["verdict_reason"]
    best = rep["candidates"][0]
    assert best["place"] == "innominate_right xyz" and best["gap_after"] < 0.3
    assert abs(best["params"]["frequency_hz"] / case.params["f_hz"] - 1) < 0.02


def test_significant_effect_is_named_when_the_base_gap_is_zero():
    """Seed-31337 misorientation #2 of the benchmark (SIPS_R_x tilted 24 deg): the noise
    drew low, the base model's held-out chi2 is below its expectation (gap 0, so no shrink
    can be measured) and the fitted tilt lowers it by ~41 (needed ~18). Before, the
    below-noise rule (shrink >= 20 %) could never pass at gap 0: a false none."""
    gen, _ = make_generator("auto", 31337)
    case = gen("sensor_misorientation", 2)
    data = prepare_data(case.frequency_hz, case.H, case.H_std, case.outputs, case.inputs)
    rep = diagnose(data, default_model(),
                   GapOptions(effects=("sensor_misorientation", "hysteretic_damping"))).report
    assert rep["gap_before"] == 0.0
    assert rep["verdict"] == "sensor_misorientation", rep["verdict_reason"]
    best = rep["candidates"][0]
    assert best["place"] == case.place
    assert abs(best["params"]["tilt_deg"] - case.params["tilt_deg"]) < 2.0


def test_tilt_absorbed_by_a_distorted_base_fit_is_found_from_the_undistorted_start(tmp_path):
    # judge-like set 8642_007: a probe tilted 9.3 deg at SIPS_L_x (face-down, 5.5 sigma).
    # The base fit absorbs it with 9 parameters at the updating bounds and moves the
    # residual to SIPS_R_x (56 %); fitted from that base, the tilt at SIPS_L_x was never
    # reached (verdict added_mass on the right innominate, 0.88 -> 0.47). From the
    # undistorted start (stiffness and mass at nominal, damping refitted) it reaches gap 0.
    # The tilt and the mass that was named instead suffice (a spring to ground, also
    # fitted before, changes neither: 25 -> 15 s of CPU)
    from pelvislab.tests.test_gap_support_contacts import judge_like_data

    rep = diagnose(judge_like_data(8642, 7, tmp_path), default_model(), GapOptions(
        effects=("sensor_misorientation", "added_mass"))).report
    best = rep["candidates"][0]
    assert rep["verdict"] == "sensor_misorientation", rep["verdict_reason"]
    assert best["place"] == "SIPS_L_x" and best["variant"] == "tilted axis"
    assert 8.3 < best["params"]["tilt_deg"] < 10.3, best["params"]
    assert best["gap_after"] < 0.2
