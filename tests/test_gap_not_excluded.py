"""How large an absorbed effect may be (issue 10): the ranges of the global effects'
parameters that the data cannot exclude.

Judge-like set 1357_020 (``tests/judge_like_generator.py``, written without reading the
diagnosis): f_k = 0.67 (3.1 σ rms), which parameter updating absorbs: base gap 0, the f_k
candidate lowers the held-out χ² by 0.34 where 10.8 is needed, verdict ``none``. The
report must then say that f_k up to beyond the truth is not excluded, and the range must
be what it claims: at its ends the χ² of all lines, the base refitted with f_k held
there, has risen by about the critical value.
"""

import numpy as np

from pelvislab.acquisition.frfset import read_frf
from pelvislab.app.commands.gap import format_report
from pelvislab.model import gap
from pelvislab.model.gap import GapOptions, prepare_data
from pelvislab.model.gap_effects import evaluate
from pelvislab.model.pelvis import default_model
from pelvislab.tests import judge_like_generator as jl


def _profile_chi2(s, cand, theta, f_k):
    """χ² of fitted and held-out lines with f_k held and the base refitted."""
    n = theta.size
    x, _cost, _limit = gap._lsq(
        gap._Model(s.fit, cand, None, n), np.r_[np.log(theta), f_k],
        np.r_[s.bounds.lo, f_k - 1e-9], np.r_[s.bounds.hi, f_k + 1e-9],
        s.opt.max_nfev_joint, s.opt.robust_scale)
    th, terms = np.exp(x[:n]), cand.build(np.array([f_k]), s.fit.ctx)
    return (s.fit.chi2(evaluate(s.fit.ctx, th, terms)[0])
            + s.held.chi2(evaluate(s.held.ctx, th, cand.build(np.array([f_k]), s.held.ctx))[0]))


def test_absorbed_frequency_dependent_stiffness_is_bounded_not_ruled_out(tmp_path,
                                                                        monkeypatch):
    path = tmp_path / "set_1357_020.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([1357, 20])), path)
    assert truth["effect"] == "frequency_dependent_stiffness"
    f_k_true = truth["parameters"]["f_k"]

    stages = {}
    real_not_excluded = gap._not_excluded

    def keep(s, results):
        stages["s"], stages["results"] = s, results
        return real_not_excluded(s, results)

    monkeypatch.setattr(gap, "_not_excluded", keep)
    frf = read_frf(path)
    data = prepare_data(frf.frequency_hz, frf.H, frf.H_std, frf.outputs, frf.inputs)
    report = gap.diagnose(data, default_model(),
                          GapOptions(effects=("frequency_dependent_stiffness",))).report
    assert report["verdict"] == "none", report["verdict_reason"]

    (entry,) = report["not_excluded"]
    assert entry["effect"] == "frequency_dependent_stiffness" and entry["parameter"] == "f_k"
    assert entry["null_inside"] and entry["low"] < 0.0 < entry["high"]
    assert entry["low"] <= entry["fitted"] <= entry["high"]
    assert f_k_true < entry["high"], "the true size must not be excluded"
    assert "not excluded by the data" in format_report(report)

    # the range is the profile's: at each end the pooled χ² has risen by ~ the critical
    # value (linearised: within a factor 1.6 either way)
    s = stages["s"]
    res = min((r for r in stages["results"]
               if r.candidate.effect == "frequency_dependent_stiffness"
               and r.beyond_null is None), key=lambda r: r.score)
    best = _profile_chi2(s, res.candidate, res.theta, float(res.u[0]))
    for end in (entry["low"], entry["high"]):
        rise = _profile_chi2(s, res.candidate, res.theta, end) - best
        assert entry["chi2_critical"] / 1.6 < rise < 1.6 * entry["chi2_critical"], (end, rise)
