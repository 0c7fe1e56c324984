"""A missing spring on a subject whose dashpots differ within a joint: its line is searched
again together with one damping per dashpot (issue 10, "which").

Fresh judge-like set 1717_020 (session 49; ``tests/judge_like_generator.py``, written
without reading the diagnosis): a 4.1e5 N/m sacrospinous spring between the sacrum and
the left innominate, subject damped per dashpot, the dashpots' midpoint lever, base gap
2.52. Without the extension the spring's best line was at the pubic joint (it also mimics
the dashpots' misfit); refitted from that line with one damping per dashpot it ended at
held-out gap 0.64, and a point mass (0.52) was named. The left sacroiliac place, fitted
with the extension from its own linearised starts, reaches 0.15.
"""

import numpy as np

from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process


def test_a_spring_on_a_subject_damped_per_dashpot_is_found_on_its_own_joint(tmp_path):
    path = tmp_path / "set_1717_020.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([1717, 20])), path)
    assert truth["effect"] == "missing_ligament"
    assert truth["place"]["bones"] == ["innominate_left", "sacrum"]
    assert truth["subject"]["per_dashpot"]
    # as the command line runs it (tests/fresh_process.py)
    report = diagnose_in_fresh_process(path)
    assert report["gap_before"] > 2.0
    assert report["verdict"] == "missing_ligament", report["verdict_reason"]
    (spring,) = [c for c in report["candidates"] if c["effect"] == "missing_ligament"]
    assert spring["place"] == "sij_left" and spring["bone"] == "innominate_left"
    assert spring["variant"] == "extra spring + one coefficient per dashpot"
    assert spring["gap_after"] < 0.3 and spring["shrink"] > 0.85
    assert 1e5 < spring["params"]["stiffness_n_per_m"] < 2e6
