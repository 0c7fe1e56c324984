"""The dashpot reading revisited after the effects (issue 10).

Fresh judge-like set 3141_004 (``tests/judge_like_generator.py``, written without reading
the diagnosis): frequency-dependent stiffness f_k = 1.40 on a heavily damped subject of
appendix E's "points" reading of dashpot S1, σ estimated from the data (no H_std). The
reading is chosen on the base fit, before any effect: fitted-line χ² 9555 (midpoint)
against 9456 (points), short of the 25 % rule, so midpoint is kept, and f_k fitted under
it leaves gap 1.04: ``unexplained``. Refitted under "points" it leaves 0.89 and is named.
Since session 47's noise estimate (the band's low edge followed) f_k under midpoint
already leaves 0.51 (named, shrink 75 %); the refit still takes the subject's reading,
"points", where f_k leaves 0.27.
"""

import numpy as np

from pelvislab.acquisition.frfset import read_frf
from pelvislab.model.gap import GapOptions, diagnose, prepare_data
from pelvislab.model.pelvis import default_model
from pelvislab.tests import judge_like_generator as jl


def _report(path, n_leading):
    s = read_frf(path)
    data = prepare_data(s.frequency_hz, s.H, s.H_std, s.outputs, s.inputs)
    # f_k alone: the full library reaches the same verdicts (diagnose CLI, 32 s) in 3 s
    opt = GapOptions(effects=("frequency_dependent_stiffness",),
                     other_reading_candidates=n_leading)
    return diagnose(data, default_model(), opt).report


def test_effect_under_the_reading_not_chosen_is_named_instead_of_unexplained(tmp_path):
    path = tmp_path / "set_3141_004.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([3141, 4])), path)
    assert truth["effect"] == "frequency_dependent_stiffness"
    assert truth["subject"]["dashpot_lever"] == "points"

    # without the refit the reading chosen before the effects, not the subject's, stays:
    # this is what it fixes (the effect under it explained nothing before session 47's
    # noise estimate, and leaves about twice the gap since)
    before = _report(path, 0)
    assert before["base_fit"]["dashpot_lever"] == "midpoint"

    report = _report(path, 3)
    assert report["verdict"] == "frequency_dependent_stiffness", report["verdict_reason"]
    assert report["base_fit"]["dashpot_lever"] == "points"
    assert "chosen after the effects" in report["base_fit"]["dashpot_lever_choice"]
    best = report["candidates"][0]
    assert best["gap_after"] < 1.0 < report["gap_before"]
    assert best["gap_after"] < 0.7 * before["candidates"][0]["gap_after"]
    assert abs(best["params"]["f_k"] - truth["parameters"]["f_k"]) < 0.1
    assert "other_reading_s" in report["timing_s"]
