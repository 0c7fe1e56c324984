"""A named effect fitted without the null extension must also beat that extension alone
(issue 10).

Fresh judge-like set 7272_019 (``tests/judge_like_generator.py``, written without reading
the diagnosis; a seed first diagnosed in session 17): no effect, nine-point layout,
noise 1.9 % of each FRF's peak. A 1.2e5 N/m spring at the pubic joint lowered the held-out
χ² from the base's (gap 0.38) to 307.4 (gap 0.16), significant against the base, and
was named; one damping coefficient per dashpot alone, which is parameter updating
(``NULL_EXTENSIONS``), reaches 308.2 (gap 0.17). Tested against that extension, as
against the other dashpot reading's null, the spring is not significant: ``none``.
"""

import numpy as np

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process


def test_effect_that_one_damping_per_dashpot_explains_as_well_is_not_named(tmp_path):
    path = tmp_path / "set_7272_019.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([7272, 19])), path)
    assert truth["effect"] == "none"

    # the candidates that competed at c3d3cda (with the whole library the CLI then said
    # `none` too; since e3a4299 it names soft_tissue: the armature jobs give the stuck base
    # fit one more way out of its local minimum - docs/gap-diagnosis.md "Session 18")
    report = diagnose_in_fresh_process(
        path, effects=["missing_ligament", "per_dashpot_damping"])
    by_effect = {c["effect"]: c for c in report["candidates"]}
    spring, null_ext = by_effect["missing_ligament"], by_effect["per_dashpot_damping"]
    # the situation: the spring leads on held-out lines and is significant against the
    # base, the extension alone nearly as good and near the noise
    assert spring["score"] < null_ext["score"]
    assert spring["chi2_held_out"] < null_ext["chi2_held_out"] < spring["chi2_held_out"] + 5
    assert null_ext["gap_after"] < 1.0
    assert report["verdict"] == "none", report["verdict_reason"]
    assert "one damping coefficient per dashpot" in report["verdict_reason"]
