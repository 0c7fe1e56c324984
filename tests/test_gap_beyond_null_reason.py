"""A verdict's reason says which test a candidate failed (issue 10: a readable report).

Fresh judge-like no-effect set 8383_028 (``tests/judge_like_generator.py`` with
``kind="none"``; first diagnosed in session 22), a subject with one damping coefficient
per dashpot. The best candidate is f_k fitted together with that extension: against the
base fit it lowers the held-out chi2 by 536 (27.9 needed), but beyond the extension alone
by 3.1 (10.8 needed), so the verdict is rightly ``none``. The reason used to say "is not
significant (chi2 drop 536; needs > 27.9)", which reads as a contradiction.
"""

import numpy as np

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process


def test_reason_names_the_extension_the_candidate_did_not_beat(tmp_path):
    path = tmp_path / "set_8383_028.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([8383, 28]), kind="none"), path)
    assert truth["subject"]["per_dashpot"] is True

    # the joint fits as they ran: since session 33 one damping per dashpot is also fitted
    # from its own starts and reaches gap 0.08 alone (the verdict `none` by that route)
    report = diagnose_in_fresh_process(
        path, effects=["frequency_dependent_stiffness", "per_dashpot_damping"],
        global_own_starts=False)
    sig = report["significance"]
    assert report["verdict"] == "none"
    # passed against the base fit, failed beyond the extension
    assert sig["held_out_chi2_drop"] > sig["held_out_critical"]
    assert sig["significant"] is False
    failed = sig["beyond_null_failed"]
    assert failed is not None
    assert failed["held_out_chi2_drop"] < failed["critical"]
    assert failed["pooled_chi2_drop"] < failed["critical"]
    reason = report["verdict_reason"]
    assert "is not significant beyond one damping coefficient per dashpot alone" in reason
    assert f"{sig['held_out_chi2_drop']:.3g}" not in reason
