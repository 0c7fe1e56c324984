"""A global one-parameter effect that parameter updating absorbs on the held-out lines
(issue 10: no false ``none`` on data with an effect).

Fresh judge-like set 9999_000 (``tests/judge_like_generator.py``, written without reading
the diagnosis): f_k = 1.43 (eq. 7.3) at 4.8 σ rms, nine-point layout, noise 0.89 % of each
FRF's peak, base gap 0.32. The f_k candidate lowers the fitted-line χ² by 21 and raises the
held-out one by 1.4: the pooled test (drop 19.6 > 10.8 on one degree of freedom) excludes
the null, while the held-out drop is not positive, which the pooled test required. The
verdict was ``none`` while the report's own ``not_excluded`` range of f_k excluded 0.
"""

import numpy as np

from pelvislab.app.commands.gap import diagnose_file, format_report
from pelvislab.model import gap
from pelvislab.tests import judge_like_generator as jl


def test_absorbed_global_effect_is_named_by_the_pooled_test_alone(tmp_path):
    path = tmp_path / "set_9999_000.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([9999, 0])), path)
    assert truth["effect"] == "frequency_dependent_stiffness"
    report = diagnose_file(path, effects=("frequency_dependent_stiffness",)).to_json()
    assert report["gap_before"] < 0.5
    sig = report["significance"]
    assert report["verdict"] == "frequency_dependent_stiffness", report["verdict_reason"]
    assert sig["held_out_chi2_drop"] <= 0.0 < sig["pooled_chi2_drop"] - sig["pooled_critical"]
    assert "global one-parameter" in sig["by"]
    assert "over fitted and held-out lines together" in report["verdict_reason"]
    (entry,) = [e for e in report["not_excluded"] if e["parameter"] == "f_k"]
    assert not entry["null_inside"] and entry["low"] < truth["parameters"]["f_k"]
    assert "frequency_dependent_stiffness" in format_report(report)


def test_held_out_lines_that_reject_the_effect_veto_the_pooled_test():
    # no-effect judge-like set 4242_021 (one damping per dashpot in the subject): f_k
    # drops the pooled chi2 by 88 while the held-out chi2 rises by 155
    veto = gap._PlainTest(drop=-155.0, crit_h=10.83, drop_pooled=88.0, crit_p=10.83,
                          pooled_alone=True)
    assert not veto.significant
    # a held-out rise within the noise lets the pooled test decide, for a global
    # one-parameter effect only (other effects need a held-out drop > 0)
    absorbed = dict(drop=-1.4, crit_h=10.83, drop_pooled=19.6, crit_p=10.83)
    assert gap._PlainTest(**absorbed, pooled_alone=True).significant
    assert not gap._PlainTest(**absorbed, pooled_alone=False).significant
