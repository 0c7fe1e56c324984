"""A point mass is also fitted from its own starts with the base at the model file's
values (issue 10).

Fresh judge-like set 8888_002 (``tests/judge_like_generator.py``, written without reading
the diagnosis): a 0.31 kg point mass on a 0.33 kg sacrum (575σ), the subject damped per
dashpot (S1_R 378 N s/m, S2_R 12 N s/m), no H_std. The base fit absorbed the mass by
driving eight parameters to the updating bounds and the pubic damping to x100-x500 the
subject's; from there, and from the undistorted and grid bases, the added-mass job's best
start ended at held-out gap 69.1-70.3 (base gap 110) and the verdict was ``unexplained``. From
the model file's values the mass reaches 8.3 alone and 0.0 with one damping per dashpot.
"""

import numpy as np

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process


def test_heavy_mass_found_from_the_model_values(tmp_path):
    path = tmp_path / "set_8888_002.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([8888, 2])), path)
    assert truth["effect"] == "added_mass"
    assert truth["place"]["bone"] == "sacrum"

    # the effects that came next, and the damping per dashpot the subject needs (whole
    # library, CLI: the same verdict)
    report = diagnose_in_fresh_process(
        path, effects=["added_mass", "soft_tissue", "per_dashpot_damping"])
    assert report["verdict"] == "added_mass", report["verdict_reason"]
    mass = next(c for c in report["candidates"] if c["effect"] == "added_mass")
    assert jl.place_hit(truth, mass)
    assert mass["gap_after"] < 0.05 * report["gap_before"]
    assert abs(mass["params"]["mass_kg"] / truth["parameters"]["mass_kg"] - 1) < 0.05
