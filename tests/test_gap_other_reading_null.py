"""The null under the dashpot reading not chosen (issue 10).

Fresh judge-like set 9753_019 (``tests/judge_like_generator.py``, written without reading
the diagnosis): no effect; a face_up subject of appendix E's "points" reading of dashpot
S1 with one damping per dashpot (S1_L 1875, S2_L 74 N s/m), noise 1.3 % of each FRF's
peak. The base fits of the two readings differ by little (fitted-line χ² 4072 midpoint,
4068 points), so midpoint is kept; a 2.2 g point mass with one damping per dashpot then
took up the readings' difference (held-out χ² 743.9, gap 0.90 → 0.11) and was named.
One damping per dashpot alone reaches the same 743.9 under "points": the mass is not
significant against that null, and the verdict must be ``none``. With the tied starts of
each joint fit finished (``GapOptions.finish_ties``) one damping per dashpot reaches the
noise under midpoint itself; the stage is checked with one start finished, as it ran.
"""

import numpy as np

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process

# the effect that was named and the null extension that absorbs the readings' difference:
# the same verdicts as with the whole library (CLI: 40 s), in a fraction of the time
EFFECTS = ("added_mass", "per_dashpot_damping")


def _report(path, **options):
    # in a fresh interpreter: on this set the verdict's path turns on rounding (in the
    # test process, after other tests, the stage below was not reached with
    # finish_ties=0)
    return diagnose_in_fresh_process(path, effects=list(EFFECTS), **options)


def test_effect_not_beyond_the_other_readings_null_is_not_named(tmp_path):
    path = tmp_path / "set_9753_019.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([9753, 19])), path)
    assert truth["effect"] == "none" and truth["subject"]["dashpot_lever"] == "points"

    # since the tied starts of a joint fit are finished too, one damping per dashpot
    # under midpoint reaches gap 0.10 by itself (0.19 before) and the verdict is `none`
    # without the other reading's null. That default run was asserted here until session
    # 29 and dropped to keep `make test` under 10 minutes (~25 s); the no-effect sets of
    # the judge-like re-runs (docs/gap-diagnosis-history.md) check such verdicts at scale

    # the stage under test, as it ran before: one start finished per joint fit, the
    # global ones not from their own starts (since session 33 one damping per dashpot
    # from its own starts explains the set under midpoint: `none` without this stage)
    report = _report(path, finish_ties=0, global_own_starts=False)
    assert report["base_fit"]["dashpot_lever"] == "midpoint"
    assert report["verdict"] == "none", report["verdict_reason"]
    assert report["verdict_reason"].startswith("under the other dashpot reading (points)")
    assert "other_reading_null_s" in report["timing_s"]

    # what it was before this test: the mass, named
    assert "; before it: added_mass brings the held-out gap" in report["verdict_reason"]
