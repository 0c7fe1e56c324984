"""Below the noise (base gap <= near_noise_gap) a significant effect is named whatever part
of the gap it removes (issue 10: no false ``none`` on data with an effect).

Until session 48 such an effect also had to remove 20 % of the held-out gap
(``small_shrink``). Of the 105 no-effect sets with base gap <= 1 in the stored runs (89
judge-like, 16 of the benchmark), diagnosed again with the rule, it was the reason for
``none`` in two; diagnosed without it, both are ``none`` by the later nulls
(`docs/gap-runs/gap-judge-like-session48-below-noise.txt`,
`docs/gap-runs/gap-judge-like-session48-rule-off.txt`). Sets from
``tests/judge_like_generator.py`` (written without reading the diagnosis).
"""

import numpy as np

from pelvislab.app.commands.gap import diagnose_file
from pelvislab.tests import judge_like_generator as jl


def _diagnosed_right(tmp_path, seed, index, effect, max_gap):
    """The report on judge-like set ``seed``_``index`` (whose truth is ``effect``), checked
    for base gap in (0, ``max_gap``], the right verdict, and no below-noise shrink rule."""
    path = tmp_path / f"set_{seed}_{index:03d}.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([seed, index])), path)
    assert truth["effect"] == effect
    report = diagnose_file(path).to_json()
    assert 0.0 < report["gap_before"] <= max_gap
    assert report["verdict"] == effect, report["verdict_reason"]
    assert "removes only" not in report["verdict_reason"]
    return report


def test_a_significant_effect_below_the_noise_is_named_however_little_it_removes(tmp_path):
    # judge-like 1414_000: f_k = 0.56 (eq. 7.3) at 3.7 sigma rms that updating absorbs to a
    # base gap of 0.23; f_k removes 2 % of it held out, and passes the pooled test with a
    # held-out drop > 0 (pooled drop 14.0 > 10.8): it was a false none
    report = _diagnosed_right(tmp_path, 1414, 0, "frequency_dependent_stiffness", 0.5)
    sig = report["significance"]
    assert sig["significant"] and sig["held_out_chi2_drop"] > 0.0
    assert sig["shrink_judged"] is None  # judged by the held-out test, not the pooled shrink
    (fk,) = [c for c in report["candidates"] if c["effect"] == report["verdict"]]
    assert 0.0 < fk["shrink"] < 0.2  # what the old rule needed: 20 %


def test_a_no_effect_set_the_rule_alone_made_none_is_none_by_a_later_null(tmp_path):
    # judge-like 1313_010, no effect, one damping per dashpot in the subject: a spring
    # passes the pooled test (29.5 > 25.1) and removes 12 % of the base gap 0.36, which
    # the 20 % rule alone called none; one damping per dashpot explains the data as well
    report = _diagnosed_right(tmp_path, 1313, 10, "none", 1.0)
    assert "one damping coefficient per dashpot" in report["verdict_reason"]
