"""`identify` must not claim confidence it does not have (thesis: the untrusted optimiser).

Review of session 36 (a helper ran `pelvislab identify` on cases made to break it): a
misfit left by model error or a local minimum was `converged: true` without H_std, std
were kept at the declared noise when the misfit was 13x it, noise 1.4x the declared level
passed the noise floor, a parameter on its bound kept a std, and a weak direction known to
worse than an e-fold was "resolved". Small chain fixtures keep these tests fast.
"""

from __future__ import annotations

import numpy as np
import pytest

from pelvislab.model.identification import (
    ResidualSpec,
    Strategy,
    covariance_report,
    default_strategy,
    identify_frf,
    noise_floor_rms,
    residual_lag1_correlation,
)
from pelvislab.tests.test_identification_frf import chain_problem, synth


def test_lag1_correlation_tells_independent_noise_from_a_smooth_misfit():
    rng = np.random.default_rng(3)
    mask = np.ones((200, 2, 1), bool)
    mask[50:60, 0, 0] = False  # unmeasured lines: neighbours are the next measured ones
    white = rng.standard_normal(2 * int(mask.sum()))
    r1, pairs = residual_lag1_correlation(white, mask)
    assert pairs == 2 * (189 + 199) and abs(r1) < 4 / np.sqrt(pairs)
    f = np.linspace(0, 1, 200)
    smooth = np.broadcast_to(np.sin(6 * f)[:, None, None], mask.shape)[mask]
    r1, _ = residual_lag1_correlation(np.concatenate([smooth, smooth]), mask)
    assert r1 > 0.9


def test_a_fit_the_model_cannot_match_is_not_converged_without_h_std():
    # data of a 4-mass chain, fitted with one stiffness held 30 % wrong: the best
    # minimum is reproduced by a second start, which alone made it "converged"
    p = chain_problem(4, seed=2)
    f = np.arange(2.0, 80.0, 1.0)
    rng = np.random.default_rng(1)
    H = synth(p, p.nominal, f)
    H = H * (1 + 0.002 * (rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)))
    start = p.nominal.copy()
    start[p.names.index("k1")] *= 1.3
    free = [n for n in p.names if n != "k1"]
    res = identify_frf(p, f, H, free=free, start=start, residual=ResidualSpec("log"),
                       strategy=default_strategy("log"))
    white = res.extra["residual_whiteness"]
    assert white["structured"] and white["lag1_correlation"] > 0.5
    assert not res.converged
    assert "structured along frequency" in res.message
    # the same fit with the model right: white residuals, converged
    ok = identify_frf(p, f, H, residual=ResidualSpec("log"), strategy=default_strategy("log"))
    assert ok.converged, ok.message
    assert not ok.extra["residual_whiteness"]["structured"]


def noisy(p, f, level, seed):
    H0 = synth(p, p.nominal, f)
    sigma = level * np.abs(H0)
    rng = np.random.default_rng(seed)
    return H0 + sigma / np.sqrt(2) * (rng.standard_normal(H0.shape)
                                      + 1j * rng.standard_normal(H0.shape)), sigma


def test_noise_above_the_declared_level_misses_the_floor_and_widens_the_std():
    p = chain_problem(3, seed=6, damping=20.0)
    f = np.arange(2.0, 60.0, 0.25)
    H, sigma = noisy(p, f, 0.02, seed=0)
    right = identify_frf(p, f, H, sigma, residual=ResidualSpec("std"),
                         strategy=default_strategy("std"))
    assert right.converged, right.message
    under = identify_frf(p, f, H, sigma / 1.4, residual=ResidualSpec("std"),
                         strategy=default_strategy("std"))
    assert under.extra["rms_residual"] == pytest.approx(1.4, rel=0.05)
    assert not under.converged  # the fixed floor of 1.5 passed it
    assert "above the target" in under.message
    # std scaled by sqrt(chi2/dof): as wide as with the right H_std, not 1.4x narrower
    np.testing.assert_allclose(under.std, right.std, rtol=0.05)
    far_under = identify_frf(p, f, H, sigma / 5, residual=ResidualSpec("std"),
                             strategy=default_strategy("std"))
    np.testing.assert_allclose(far_under.std, right.std, rtol=0.05)


def test_the_noise_floor_follows_the_number_of_residuals():
    assert noise_floor_rms(3540, 18) == pytest.approx(1.044, abs=1e-3)
    # the limit is on chi2/dof (within 4 sigma of 1), the floor on sqrt(chi2 / residuals):
    # at 20 lines and 18 parameters chi2/dof may reach 1 + 4 sqrt(2/22) = 2.21, not 4.0
    # (review of session 36's diff)
    for m, p in ((40, 18), (3540, 18), (400, 4)):
        dof = m - p
        chi2_per_dof = noise_floor_rms(m, p) ** 2 * m / dof
        assert chi2_per_dof == pytest.approx(1 + 4 * np.sqrt(2 / dof))


def test_an_exact_fit_is_converged_also_without_a_stop_target():
    # Strategy() (no stop_rms) judged the rounding residual of an exact fit as structured
    p = chain_problem(4, seed=2)
    f = np.arange(2.0, 80.0, 1.0)
    for kind in ("log", "eq610"):
        res = identify_frf(p, f, synth(p, p.nominal, f), start=p.nominal * 1.2,
                           residual=ResidualSpec(kind), strategy=Strategy(max_starts=1))
        assert res.extra["rms_residual"] < 1e-10
        assert res.converged, res.message


def test_a_parameter_on_its_bound_is_named_and_has_no_std():
    p = chain_problem(3, seed=4)
    f = np.arange(2.0, 80.0, 1.0)
    true = p.nominal.copy()
    # beyond start x 10 (a damping this far is now fitted in its wider range: below)
    true[p.names.index("k2")] *= 30.0
    res = identify_frf(p, f, synth(p, true, f), residual=ResidualSpec("log"),
                       strategy=Strategy(max_starts=1, stop_rms=1e-8))
    assert res.extra["on_bound"] == ["k2"]
    assert np.isnan(res.std[p.names.index("k2")])
    assert "k2 (std null; the others' std hold it there)" in res.message
    assert not res.converged
    assert res.as_dict()["parameters"]["k2"]["std"] is None
    assert res.as_dict()["parameters"]["k2"]["interval_95"] is None
    # the others' std are those of a fit with k2 held where it ended (its column left out)
    held = identify_frf(p, f, synth(p, true, f), free=[n for n in p.names if n != "k2"],
                        start=res.values, residual=ResidualSpec("log"),
                        strategy=Strategy(max_starts=1, stop_rms=1e-8))
    others = [p.names.index(n) for n in held.names]
    np.testing.assert_allclose(res.std[others], held.std, rtol=0.02)
    assert np.isnan(res.correlation[p.names.index("k2")]).all()


@pytest.mark.parametrize("factor", [30.0, 1e3, 1e-3])
def test_a_damping_decades_from_the_start_is_fitted_in_its_wider_range(factor):
    """Subjects' damping may lie decades from appendix E's (judge-like sets: 10-3000 for
    0.8 N s/m): within start x/÷ 10 it ended on its bound, not converged (0 of 19 such
    sets, session 43). When no start reaches the target the dampings are scanned over
    decades and fitted within x/÷ 1e4-3e4 of the start."""
    p = chain_problem(3, seed=4)
    f = np.arange(2.0, 80.0, 1.0)
    true = p.nominal.copy()
    true[p.names.index("c")] *= factor
    res = identify_frf(p, f, synth(p, true, f), residual=ResidualSpec("log"),
                       strategy=Strategy(max_starts=1, stop_rms=1e-8))
    assert res.converged, res.message
    assert res.extra["on_bound"] == []
    np.testing.assert_allclose(res.values, true, rtol=1e-4)


def test_a_damping_on_its_bound_is_fitted_in_the_wider_range_also_at_the_noise_floor():
    """A damping x15 from the start with 5 % noise: the fit reached the noise floor with
    it on its x10 bound, ended not converged and never tried the wider range (27 of 27
    such chains; judge-like sets likewise: helper audit, session 44)."""
    p = chain_problem(3, seed=4)
    f = np.arange(2.0, 80.0, 1.0)
    true = p.nominal.copy()
    true[p.names.index("c")] *= 15.0
    H0 = synth(p, true, f)
    std = 0.05 * np.abs(H0)
    rng = np.random.default_rng(0)
    H = H0 + std * (rng.normal(size=H0.shape) + 1j * rng.normal(size=H0.shape)) / np.sqrt(2)
    res = identify_frf(p, f, H, std, residual=ResidualSpec("std"))
    assert res.converged, res.message
    assert res.extra["on_bound"] == []
    c = res.names.index("c")
    assert abs(res.values[c] / true[p.names.index("c")] - 1) < 3 * res.std[c] / res.values[c]


def test_a_weak_direction_known_to_worse_than_an_e_fold_is_not_resolved():
    J = np.array([[1.0, 0.0], [0.0, 0.5], [0.0, 0.0]])
    _, _, _, weak = covariance_report(J, np.zeros(3), ["a", "b"], np.ones(2),
                                      absolute_sigma=True)
    assert weak[0]["std_along"] == pytest.approx(2.0)
    assert not weak[0]["resolved"]  # numerically resolved, but std_along 2 > 1
    assert weak[1]["resolved"] and weak[1]["std_along"] == pytest.approx(1.0)


def test_a_session_whose_continuation_leaves_the_right_basin_is_fitted_from_its_start():
    """A simulated demo session (`pelvislab run protocols/demo.toml`, simulated bench seed 1;
    its /frf in tests/data; the subject is appendix E): from appendix E itself the
    loss-factor continuation led every one of the 4 starts into a local minimum (rms 12.5,
    k_pss x1.5, not converged; session 39). The start fitted directly, tried when no start
    reached the noise floor, reaches it."""
    from pathlib import Path

    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.identification import default_strategy, identify_frf
    from pelvislab.model.identification_pelvis import pelvis_problem
    from pelvislab.model.pelvis import default_model

    frf = read_frf(Path(__file__).parent / "data" / "demo_sim_seed1.h5")
    problem, _ = pelvis_problem(default_model(), frf.outputs, frf.inputs)
    res = identify_frf(problem, frf.frequency_hz, frf.H, frf.H_std,
                       strategy=default_strategy("std"))
    d = res.as_dict()
    assert d["converged"], d["message"]
    assert d["rms_residual"] < 1.05
    truth = dict(zip(problem.names, problem.nominal, strict=True))
    found = dict(zip(res.names, res.values, strict=True))
    assert all(abs(v / truth[n] - 1) < 0.1 for n, v in found.items()
               if not n.startswith("c_")), found


def test_a_gain_uncertainty_per_frf_calibrates_the_std_of_chain_data():
    """The same session: converged at chi2/dof ~1, yet sum z^2 = 47 over 18 parameters
    (expected ~18): its FRFs carry gains of a few tenths of a per cent that H_std does not
    hold (docs/identification.md). gain_std = 0.3 % marginalises one gain per FRF and
    floors the weights: every std grows, and z^2 is 8.8 (sandwich covariance; session 39,
    std term only: 19.0, and over six such sessions the mean went from 63 to 21)."""
    from pathlib import Path

    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.identification import default_strategy, identify_frf
    from pelvislab.model.identification_pelvis import pelvis_problem
    from pelvislab.model.pelvis import default_model

    frf = read_frf(Path(__file__).parent / "data" / "demo_sim_seed1.h5")
    problem, _ = pelvis_problem(default_model(), frf.outputs, frf.inputs)
    truth = np.array(problem.nominal)
    fits = [identify_frf(problem, frf.frequency_hz, frf.H, frf.H_std,
                         strategy=default_strategy("std"), gain_std=g) for g in (0.0, 0.003)]
    # in the weights too (a relative floor): the values move, within their new std (at
    # most 0.73 of it), and every std grows (1.15-4x)
    assert np.all(np.abs(fits[1].values - fits[0].values) < fits[1].std)
    assert np.all(fits[1].std > fits[0].std)
    z2 = [float(np.sum(((f.values - truth) / f.std) ** 2)) for f in fits]
    # 46.9 and 8.8 (19.0 with the std term only; 11.2 with the gain counted twice)
    assert z2[0] > 35 and z2[1] < 10, z2
    with pytest.raises(ValueError, match="gain_std"):
        identify_frf(problem, frf.frequency_hz, frf.H, frf.H_std, gain_std=-0.1)


def test_cli_gain_std_is_checked_and_recorded(tmp_path, capsys):
    import json
    from pathlib import Path

    from pelvislab.app.cli import main

    data = Path(__file__).parent / "data" / "demo_sim_seed1.h5"
    assert main(["identify", str(data), "--gain-std", "-0.1", "--json",
                 str(tmp_path / "bad.json")]) == 1
    assert "--gain-std -0.1: must be a fraction" in capsys.readouterr().err
    assert main(["identify", str(data), "--method", "modal", "--gain-std", "0.003",
                 "--json", str(tmp_path / "m.json")]) == 1
    out = tmp_path / "id.json"
    assert main(["identify", str(data), "--gain-std", "0.002", "--json", str(out)]) == 0
    assert json.loads(out.read_text())["gain_std"] == 0.002
    # the chain's tolerance by default (session 40); modal updating has none by default
    default = tmp_path / "default.json"
    assert main(["identify", str(data), "--starts", "1", "--json", str(default)]) == 0
    assert json.loads(default.read_text())["gain_std"] == 0.003
    modal = tmp_path / "modal.json"
    capsys.readouterr()
    assert main(["identify", str(data), "--method", "modal", "--json", str(modal)]) in (0, 1)
    assert "--gain-std" not in capsys.readouterr().err


def test_the_gain_floor_leaves_lines_of_unknown_h_std_out():
    """H_std 0 (or NaN) means unknown and leaves the line out; the floor sqrt(H_std^2 +
    (g|H|)^2) had brought them back at the gain's weight alone: half the lines at 0 gave
    chi2/dof 979 and k_io_R 4 % off by default (review of session 40)."""
    from pathlib import Path

    from pelvislab.acquisition.frfset import read_frf
    from pelvislab.model.identification import default_strategy, identify_frf
    from pelvislab.model.identification_pelvis import pelvis_problem
    from pelvislab.model.pelvis import default_model

    frf = read_frf(Path(__file__).parent / "data" / "demo_sim_seed1.h5")
    problem, _ = pelvis_problem(default_model(), frf.outputs, frf.inputs)
    H_std = frf.H_std.copy()
    H_std[::2] = 0.0
    fit = identify_frf(problem, frf.frequency_hz, frf.H, H_std,
                       strategy=default_strategy("std", starts=1), gain_std=0.003)
    assert fit.extra["chi2_per_dof"] < 2.0, fit.extra["chi2_per_dof"]


@pytest.mark.parametrize("seed", [1, 3])
def test_per_frf_gains_within_their_prior_are_not_read_as_structure(seed):
    """Each FRF off by its chain's gain (within gain_std 0.003) leaves an offset along that
    FRF which the lag-1 test read as model error: right fits (|z| <= 1.8) refused at lag-1
    0.63-0.87 here, and 4 of 14 simulated face_up sessions so (identify audit, session 43).
    The test runs on the residual with those gains fitted too, under their prior."""
    p = chain_problem(3, seed=4, damping=20.0)
    f = np.arange(2.0, 80.0, 0.5)
    rng = np.random.default_rng(seed)
    H = synth(p, p.nominal, f)
    gains = 1 + rng.normal(0, 0.003, H.shape[1:])
    H_std = 2e-4 * np.abs(H)
    noise = rng.standard_normal(H.shape) + 1j * rng.standard_normal(H.shape)
    res = identify_frf(p, f, H * gains + H_std * noise / np.sqrt(2), H_std, gain_std=0.003)
    assert res.converged, res.message
    assert abs(res.extra["residual_whiteness"]["lag1_correlation"]) < 0.1
    assert np.all(np.abs((res.values - p.nominal) / res.std) < 3)


def test_the_95_interval_is_taken_in_the_space_the_fit_ran_in() -> None:
    """A weak stiffness's linear value +- 2 std reached below zero; the fit ran in log p,
    where the interval is a factor (calibration audit, session 43)."""
    from pelvislab.model.identification import interval_95

    low, high = interval_95("k_io", 1e5, 1.5e5)  # std 150 %: a factor e^2.94 = 19
    assert low > 0 and high / 1e5 == pytest.approx(1e5 / low)
    assert high / 1e5 == pytest.approx(np.exp(1.959964 * 1.5), rel=1e-6)
    # a small std: the linear interval, to first order
    assert interval_95("c_sij", 10.0, 0.1) == pytest.approx([9.804, 10.198], abs=2e-3)
    # f_k, f_c are fitted linearly (they may be 0 or negative)
    assert interval_95("f_k", 0.0, 0.5) == pytest.approx([-0.98, 0.98], abs=1e-3)
    assert interval_95("k_io", 1e5, float("nan")) is None
    assert interval_95("k_io", 1e5, 1e9)[1] < float("inf")  # undetermined, no overflow


def test_a_version_a_fit_of_frequency_dependent_data_at_the_noise_floor_is_found_out():
    """A version-A fit of data with frequency-dependent stiffness (eq. 7.3, f_k 0.1) reaches
    the noise floor, converged, with parameters 10 std off; version B's two parameters
    fit significantly better (judge-like pelvis sets: converged at z 7-30, session 44)."""
    from pelvislab.model.identification import frequency_dependence_test

    p = chain_problem(3, seed=6, damping=20.0)
    f = np.arange(2.0, 60.0, 0.5)
    H0 = synth(p, p.nominal, f, f_k=0.1)
    sigma = 0.01 * np.abs(H0)
    rng = np.random.default_rng(1)
    H = H0 + sigma / np.sqrt(2) * (rng.standard_normal(H0.shape)
                                   + 1j * rng.standard_normal(H0.shape))
    fit = identify_frf(p, f, H, sigma, residual=ResidualSpec("std"),
                       strategy=default_strategy("std"))
    assert fit.converged, fit.message  # what the test is for: the fit alone cannot tell
    assert np.max(np.abs((fit.values - p.nominal) / fit.std)) > 5
    test = frequency_dependence_test(p, f, H, sigma, fit)
    assert test["significant"] and test["p_value"] < 1e-6
    assert test["f_k"] == pytest.approx(0.1, abs=0.02)
    assert test["delta_chi2"] > 30


@pytest.mark.parametrize("seed", [0, 1])
def test_data_without_frequency_dependence_pass_the_version_b_test(seed):
    from pelvislab.model.identification import frequency_dependence_test

    p = chain_problem(3, seed=6, damping=20.0)
    f = np.arange(2.0, 60.0, 0.5)
    H, sigma = noisy(p, f, 0.01, seed)
    fit = identify_frf(p, f, H, sigma, residual=ResidualSpec("std"),
                       strategy=default_strategy("std"))
    test = frequency_dependence_test(p, f, H, sigma, fit)
    assert not test["significant"]
    assert test["p_value"] > 0.01 and abs(test["f_k"]) < 0.03
    # it needs the std residual (a misfit in noise units) and a version-A fit
    log_fit = identify_frf(p, f, H, None, strategy=Strategy(max_starts=1))
    with pytest.raises(ValueError, match="std residual"):
        frequency_dependence_test(p, f, H, sigma, log_fit)
    b_fit = identify_frf(p, f, H, sigma, residual=ResidualSpec("std"), version_b=True,
                         strategy=Strategy(max_starts=1, hold_freq_dep_first=False))
    with pytest.raises(ValueError, match="version-A fit"):
        frequency_dependence_test(p, f, H, sigma, b_fit)
