"""A spring between bones that a wrong effect explains well enough to be named is still
searched for (issue 10).

Judge-like set 7575_007 (``tests/judge_like_generator.py``, written without reading the
diagnosis): a sacrotuberous ligament, 1.4e5 N/m from the sacrum to the right innominate,
face-down layout, effect 1194 sigma. No local start reaches it. A bed contact under the
sacrum (with one damping per dashpot) takes the held-out gap from 235 to 79: shrink 66 %,
above ``min_shrink``. Until session 21 that named ``support_resonance``, because the global
search of the springs between bones ran only before a verdict ``unexplained``. It now runs
whenever no candidate has come near the noise, and finds the spring at sij_right, gap 0.
Its end-to-end test (59 s in the suite) was removed in session 29 to keep ``make test``
under 10 minutes: the case below runs the same search behind the finer gate, and fails as
well when the search runs only before ``unexplained`` (checked in session 29: the search
did not run); ``pelvislab gap diagnose`` on set 7575_007 still shows the case.

Judge-like set 7777_029: a sacrospinous ligament, 5.1e4 N/m from the sacrum to the right
innominate, 24.7 sigma. The base fit absorbs it with twelve parameters at their bounds. A
point mass on the left innominate then takes the gap from 1.89 to 0.49, not near the noise
in statistical terms (328 held-out values: chi2/n 1.24, 4.3 standard deviations above the
noise's 1), but below ``near_noise_gap``. The search now runs while the best candidate is
more than ``pair_search_sigma`` standard deviations above the noise, and finds the spring
at sij_right, gap 0.04. Since session 25 (the mass's job from the model file's values) the
leading mass is on the sacrum at 1.31 and f_k leads at 0.77 (whole library, CLI); the test
uses f_k as the wrong effect below ``near_noise_gap``.
"""

import numpy as np
import pytest

from pelvislab.model.gap import GapOptions
from pelvislab.tests import judge_like_generator as jl
from pelvislab.tests.fresh_process import diagnose_in_fresh_process

# the effect that leads on 7777_029 below near_noise_gap with the whole library (a point
# mass on the left innominate until session 25; since the mass's job from the model file's
# values its leading place is the sacrum, gap 1.31, and f_k leads at 0.77), with one
# damping per dashpot
EFFECTS_7777 = ["frequency_dependent_stiffness", "missing_ligament", "per_dashpot_damping"]


def _ligament_set(tmp_path_factory, seed: int, index: int, variant: str):
    """Judge-like set ``seed``_``index`` written to a temporary file; its truth must be a
    missing ligament of ``variant``."""
    path = tmp_path_factory.mktemp("pair") / f"set_{seed}_{index:03d}.h5"
    truth = jl.write_set(jl.make_set(np.random.default_rng([seed, index])), path)
    assert truth["effect"] == "missing_ligament" and truth["variant"] == variant
    return path


@pytest.fixture(scope="module")
def set_7777_029(tmp_path_factory):
    return _ligament_set(tmp_path_factory, 7777, 29, "sacrospinous")


def test_spring_between_bones_is_searched_while_the_best_gap_is_above_the_noise(
        set_7777_029):
    report = diagnose_in_fresh_process(set_7777_029, effects=EFFECTS_7777)
    by_effect = {c["effect"]: c for c in report["candidates"]}
    leader = by_effect["frequency_dependent_stiffness"]
    # the situation: the leading wrong effect is below near_noise_gap (the session 20
    # gate) but measurably above the noise
    n_held = report["held_out"]["lines_held_out"]
    assert np.sqrt(GapOptions().pair_search_sigma / np.sqrt(n_held)) < leader["gap_after"]
    # below near_noise_gap on the machines of sessions 21-25 (0.77), where only the new
    # gate runs the search; 4.19 on session 26's (AMD EPYC, same packages: local minima
    # that depend on the BLAS kernels), where the session 20 gate would run it too, so
    # there the test shows only that the search finds the spring
    assert "pair_search_s" in report["timing_s"]
    assert report["verdict"] == "missing_ligament", report["verdict_reason"]
    best = report["candidates"][0]
    assert best["variant"] == "extra spring" and best["place"] == "sij_right"
    assert best["gap_after"] < 0.2
