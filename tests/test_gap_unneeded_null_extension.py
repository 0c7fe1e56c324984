"""One damping coefficient per dashpot is part of the null only where the data ask for it
(issue 10: no false ``none`` on data with an effect).

Fresh judge-like set 7777_021 (``tests/judge_like_generator.py``, written without reading
the diagnosis; first diagnosed in session 21): frequency-dependent stiffness, f_k = 1.0,
4.5 sigma rms, on a subject with grouped damping. The base fit is at the noise (gap 0);
f_k lowers the held-out chi2 by 12.1, where 10.8 is needed. One damping coefficient per
dashpot alone reaches the noise too, and f_k's drop beyond it is 5.1, so the verdict was
``none``. But that extension is no better than the base fit (held-out drop 7.0 with 8
coefficients, pooled 12.7, where 26.1 is needed): the data do not ask for it, and the
null is the base fit, which f_k beats.
"""

import numpy as np

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process


def test_effect_is_not_tested_against_an_extension_the_data_do_not_ask_for(tmp_path):
    path = tmp_path / "set_7777_021.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([7777, 21])), path)
    assert truth["effect"] == "frequency_dependent_stiffness"
    assert truth["subject"]["per_dashpot"] is False

    report = diagnose_in_fresh_process(
        path, effects=["frequency_dependent_stiffness", "per_dashpot_damping"])
    by_effect = {c["effect"]: c for c in report["candidates"]}
    f_k, null_ext = by_effect["frequency_dependent_stiffness"], by_effect["per_dashpot_damping"]
    chi2_base = report["held_out"]["chi2_before"]
    # the situation: both at the noise, f_k significant against the base fit, the
    # extension not (8 coefficients, p = 1e-3: 26.1)
    assert report["gap_before"] < 0.5 and null_ext["gap_after"] < 1.0
    assert report["significance"]["held_out_chi2_drop"] > report["significance"][
        "held_out_critical"]
    assert chi2_base - null_ext["chi2_held_out"] < 26.1
    assert f_k["chi2_held_out"] < null_ext["chi2_held_out"]
    assert report["verdict"] == "frequency_dependent_stiffness", report["verdict_reason"]
    assert "is not significant against the base fit" in report["verdict_reason"]
    assert "not part of the null" in report["verdict_reason"]
