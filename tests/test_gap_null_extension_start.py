"""The refit of an effect with one damping per dashpot starts also from the effect's own
fit (issue 10).

Fresh judge-like set 5050_022 (``tests/judge_like_generator.py``, written without reading
the diagnosis): a 4.8e5 N/m iliolumbar spring from the right innominate to ground on a
subject whose dashpots are damped one by one (S1_R 496, S2_R 792, S3_R 59 N s/m), 91σ.
The spring alone ends at held-out χ² 9333 (the dashpots' spread left); refitted with the
null extension from the extension's own fit it ended at 1.6e4, and a support on the
spring's line was named (gap 4.8). Started also from the spring's fit with the extension
at its least, the spring is named with gap 0.13.
"""

import numpy as np

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process


def test_spring_refitted_with_per_dashpot_damping_from_its_own_fit(tmp_path):
    path = tmp_path / "set_5050_022.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([5050, 22])), path)
    assert truth["effect"] == "missing_ligament" and truth["subject"]["per_dashpot"]

    # the effects that competed (whole library, CLI: the same verdict)
    report = diagnose_in_fresh_process(
        path, effects=["missing_ligament", "support_resonance", "per_dashpot_damping"])
    assert report["verdict"] == "missing_ligament", report["verdict_reason"]
    spring = next(c for c in report["candidates"] if c["effect"] == "missing_ligament")
    assert jl.place_hit(truth, spring)
    assert spring["variant"].startswith("spring to ground")
    assert spring["gap_after"] < 0.5
    assert abs(spring["params"]["stiffness_n_per_m"] / truth["parameters"]["k_n_m"] - 1) < 0.1
