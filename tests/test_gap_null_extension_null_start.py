"""The refit of an effect with one damping per dashpot starts also from the extension's
own fit with the effect at its null (issue 10).

Fresh judge-like set 7070_001 (``tests/judge_like_generator.py``, written without reading
the diagnosis; a seed first diagnosed in session 17): frequency-dependent stiffness
f_k = 0.77 (eq. 7.3, 8.3σ) on a subject whose dashpots are damped one by one (S1_R 181,
S2_R 35, P2 1301 N s/m). One damping per dashpot alone ends at held-out χ² 661 (gap
0.27); f_k refitted with it from the three other starts ended at 874, worse than the
extension alone it contains, and the verdict was ``none`` (hysteretic damping named,
then not significant beyond the extension under the other dashpot reading). Started also
from the extension's fit with f_k = 0, f_k is named at 0.71 with gap 0.21.
"""

import numpy as np

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process


def test_effect_refitted_with_per_dashpot_damping_from_the_extensions_fit(tmp_path):
    path = tmp_path / "set_7070_001.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([7070, 1])), path)
    assert truth["effect"] == "frequency_dependent_stiffness"
    assert truth["subject"]["per_dashpot"]

    # the effects that competed (whole library, CLI: the same verdict)
    report = diagnose_in_fresh_process(
        path, effects=["frequency_dependent_stiffness", "hysteretic_damping",
                       "per_dashpot_damping"])
    assert report["verdict"] == "frequency_dependent_stiffness", report["verdict_reason"]
    by_effect = {c["effect"]: c for c in report["candidates"]}
    f_k = by_effect["frequency_dependent_stiffness"]
    # the refit contains the extension alone: it must not end worse than it
    assert f_k["chi2_held_out"] <= by_effect["per_dashpot_damping"]["chi2_held_out"]
    assert f_k["gap_after"] < 0.3
    assert abs(f_k["params"]["f_k"] / truth["parameters"]["f_k"] - 1) < 0.15
