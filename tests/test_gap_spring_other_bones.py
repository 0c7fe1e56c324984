"""A spring to ground's line is also fitted at the other bones it reaches (issue 10).

Fresh judge-like set 8989_004 (``tests/judge_like_generator.py``, written without reading
the diagnosis): a 2.3e5 N/m iliolumbar spring from a fixed L5 to the right innominate,
6.0σ, nine-point layout. The search found its line of action to within 5 mm but on the
sacrum (2.8e6 N/m; named with one damping per dashpot, gap 1.76 -> 0.50): near the
sacroiliac joint a grounded spring acts almost alike on either bone. The same line on the
right innominate, started at a third of the sacrum's stiffness, finishes at 2.6e5 N/m and
gap 0.04 (probe); the spring is now named on the right innominate.
"""

import numpy as np

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process


def test_ground_spring_moved_to_the_true_bone(tmp_path):
    path = tmp_path / "set_8989_004.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([8989, 4])), path)
    assert truth["effect"] == "missing_ligament"
    assert truth["place"]["bones"] == ["innominate_right"]

    # the effects that led (whole library, CLI: the same verdict and place)
    report = diagnose_in_fresh_process(
        path, effects=["missing_ligament", "support_resonance", "per_dashpot_damping"])
    assert report["verdict"] == "missing_ligament", report["verdict_reason"]
    spring = next(c for c in report["candidates"] if c["effect"] == "missing_ligament")
    assert spring["place"] == "innominate_right to ground"
    assert jl.place_hit(truth, spring)
    assert spring["gap_after"] < 0.2 * report["gap_before"]
    k = spring["params"]["stiffness_n_per_m"]
    assert abs(k / truth["parameters"]["k_n_m"] - 1) < 0.3
